"""The student release: notebooks with their solutions taken out, and the kit they need to run.

``python -m course_lib release OUT_DIR`` writes the student kit:

* ``notebooks/*.ipynb``: every instructor notebook with each solution region (the lines between
  ``# BEGIN SOLUTION`` and ``# END SOLUTION`` of an exercise cell) replaced by a stub
  (``# YOUR CODE HERE`` + ``raise NotImplementedError``; lines of the region that start with
  ``# HINT`` are kept), the signature and docstring untouched. Check cells keep their source and
  their stored reference verdicts (nbval compares the student's run with them), markdown and
  figures stay, the outputs of exercise cells are cleared, execution timestamps are dropped.
* ``course_lib/`` without the reference solutions: left out, or shipped redacted, as
  :mod:`course_lib.instructor.plan` decides.
* ``data/`` (the embedded scenes and the fixtures behind the check cells), an ``environment.txt`` with
  the pins the student kit uses (:func:`student_environment`), ``conftest.py``, a ``pyproject.toml`` whose pytest runs the notebooks, a ``README.md`` for
  students, and ``RELEASE_MANIFEST.json`` (exercises, their check cells, reference verdicts,
  points, and the SHA-256 of every released file).

Releasing twice gives byte-identical files (sorted walks, no timestamps). A notebook whose
solution markers are unbalanced, or whose check cell names an exercise without markers, stops the
release with an error that names the notebook and the cell.

The grader (:mod:`course_lib.instructor.grade`) reads the same :func:`notebook_spec` from the
instructor's notebooks, so the reference verdicts it compares with never come from a file the
student can edit.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import asdict
from pathlib import Path

import nbformat

from course_lib import __version__
from course_lib.checks.core import SCORING_RULE
from course_lib.instructor.notebooks import (
    CHECK_MARK,
    INSTRUCTOR_PACKAGE,
    NOTEBOOKS_DIR,
    SKIP_NAMES,
    NotebookSpec,
    ReleaseError,
    course_lib_modules,
    execute_quick,
    kit_specs,
    marker_regions,
    module_name,
    sha256,
    stream_text,
)
from course_lib.instructor.plan import ReleasePlan, imported_names, redact_module, release_plan
from course_lib.paths import REPO_ROOT

__all__ = ["stub_source", "stub_notebook", "student_readme", "student_environment", "write_release", "release_files",
           "write_files", "verify_release"]

#: Top-level files copied as they are, when present (``environment.txt`` is rewritten: :func:`student_environment`).
COPIED_FILES = ("conftest.py",)
#: The student kit's README.md (``str.format`` fields: the notebooks, exercises, points and the scoring rule),
#: pyproject.toml (its ``version``) and .gitignore.
STUDENT_TEMPLATES = REPO_ROOT / "templates" / "student"

#: Pinned tools the student kit uses without importing them, and the text of the kit that uses them
#: (:func:`student_environment` keeps them; ``release --verify`` checks that the text is there).
STUDENT_TOOLS = {
    "jupyterlab": ("README.md", "jupyter lab"),
    "ipykernel": ("README.md", "jupyter lab"),
    "nbval": ("pyproject.toml", "--nbval-lax"),
    "pytest": ("README.md", "pytest"),
    "nbformat": ("pyproject.toml", "--nbval-lax"),
    "nbclient": ("pyproject.toml", "--nbval-lax"),
}
#: Import names of the pinned distributions whose import name differs from the distribution's.
IMPORT_NAMES = {"opencv-python-headless": "cv2", "opencv-python": "cv2", "scikit-image": "skimage", "pillow": "PIL"}

STUDENT_ENV_HEADER = """\
# Requirements of the student kit: pip install -r environment.txt (README.md, "Set up").
# torch is pinned; from PyPI on Linux even the pinned torch is the CUDA build (gigabytes of NVIDIA packages):
# README.md, "Set up", gives the CPU-only route (PyTorch's CPU wheel index) for a machine without an NVIDIA GPU.
"""


def requirement_name(line: str) -> str | None:
    """The distribution a requirement line pins (``"torch"`` for ``torch==2.13.0``), None for ``-e .`` and comments."""
    line = line.split("#", 1)[0].strip()
    if not line or line.startswith("-"):
        return None
    for sep in ("==", ">=", "<=", "~=", "[", ";", "<", ">", " "):
        line = line.split(sep, 1)[0]
    return line.strip().lower() or None


def student_environment(text: str, imported: set[str]) -> str:
    """The student kit's ``environment.txt``: the kit's pins that the student kit uses, with their comments.

    A pin is kept when the release imports its package (``imported``: top-level import names of its
    code and notebooks) or it is one of :data:`STUDENT_TOOLS`; a pin for the instructor's tests or
    benchmarks (pycolmap, playwright) is dropped with the comment lines just above it. The header is
    :data:`STUDENT_ENV_HEADER`, written for the student kit.
    """
    out, comments, started = [], [], False
    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith("#") or not stripped:
            if started:
                comments.append(line)
            continue
        started = True
        name = requirement_name(line)
        keep = name is None or name in STUDENT_TOOLS or IMPORT_NAMES.get(name, name.replace("-", "_")) in imported
        if keep:
            out += comments + [line]
        comments = []
    return STUDENT_ENV_HEADER + "\n".join(out) + "\n"


def imported_packages(files: dict[str, bytes]) -> set[str]:
    """Top-level names imported by the ``.py`` files and notebook code cells among ``files``."""
    import ast

    sources = []
    for rel, data in files.items():
        if rel.endswith(".py"):
            sources.append(data.decode())
        elif rel.endswith(".ipynb"):
            nb = nbformat.reads(data.decode(), as_version=4)
            sources += ["\n".join(ln for ln in c.source.splitlines() if not ln.lstrip().startswith(("%", "!")))
                        for c in nb.cells if c.cell_type == "code"]
    names: set[str] = set()
    for src in sources:
        try:
            tree = ast.parse(src)
        except SyntaxError:
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                names.add(node.module.split(".")[0])
    return names


# ---------------------------------------------------------------------------------------------
# Stubs
# ---------------------------------------------------------------------------------------------


def stub_source(source: str, where: str = "cell") -> str:
    """The cell source with every solution region replaced by a stub (hints kept)."""
    regions = marker_regions(source, where)
    if not regions:
        return source
    lines = source.splitlines()
    out, k = [], 0
    for a, b in regions:
        out += lines[k:a]
        indent = lines[a][: len(lines[a]) - len(lines[a].lstrip())]
        out += [ln for ln in lines[a + 1:b] if ln.strip().startswith("# HINT")]
        out += [f"{indent}# YOUR CODE HERE", f"{indent}raise NotImplementedError(\"your code here\")"]
        k = b + 1
    out += lines[k:]
    return "\n".join(out) + ("\n" if source.endswith("\n") else "")


def stub_notebook(nb: nbformat.NotebookNode, name: str = "notebook") -> nbformat.NotebookNode:
    """A copy of ``nb`` for students: stubs for solutions, exercise outputs cleared, no timestamps."""
    nb = nbformat.from_dict(json.loads(json.dumps(nb)))
    for i, cell in enumerate(nb.cells):
        cell.metadata.pop("execution", None)
        if cell.cell_type != "code":
            continue
        if marker_regions(cell.source, f"{name}, cell {i}"):
            cell.source = stub_source(cell.source, f"{name}, cell {i}")
            cell.outputs = []
            cell.execution_count = None
    return nb


# ---------------------------------------------------------------------------------------------
# Writing the kit
# ---------------------------------------------------------------------------------------------


def _torch_pin() -> str:
    """The torch version that the kit's ``environment.txt`` pins (for the README's CPU-only route)."""
    env = REPO_ROOT / "environment.txt"
    for line in env.read_text().splitlines() if env.exists() else []:
        if requirement_name(line) == "torch" and "==" in line:
            return line.split("==", 1)[1].split("#", 1)[0].strip()
    return "2.13.0"


def student_readme(specs: list[NotebookSpec], plan: ReleasePlan) -> str:
    """The student release's README.md: what the kit is, how to set it up and work, the exercises and points."""
    rows = []
    for s in specs:
        if not s.exercises:
            continue
        names = ", ".join(f"`{e.name}`" for e in s.exercises)
        pts = sum(e.points for e in s.exercises)
        rows.append(f"| `notebooks/{s.name}` | {names} | {pts:g} |")
    shipped = [s for s in specs if s.name not in plan.left_out_notebooks]
    n_ex = sum(1 for s in shipped if s.exercises)
    optional = [s.name.split("_")[0] for s in shipped if not s.exercises]
    extra = (f" ({n_ex} with exercises; {', '.join(optional)}: optional lessons without exercises)" if optional else "")
    return (STUDENT_TEMPLATES / "README.md").read_text().format(
        n_notebooks=len(shipped), extra=extra, torch=_torch_pin(), rows="\n".join(rows),
        total=sum(e.points for s in specs for e in s.exercises), scoring=SCORING_RULE)


def _walk(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if p.is_file() and not SKIP_NAMES & set(p.relative_to(root).parts)
                  and p.suffix not in (".pyc",))


def write_release(out_dir: Path, notebooks_dir: Path = NOTEBOOKS_DIR, force: bool = False) -> dict:
    """Write the student kit into ``out_dir`` and return its manifest (also written as RELEASE_MANIFEST.json).

    Args:
        out_dir: an empty or missing folder, or an earlier release (it is replaced).
        notebooks_dir: the instructor notebooks (default ``notebooks/`` of this repository).
        force: replace a non-empty ``out_dir`` that is not an earlier release.

    Raises:
        ReleaseError: a notebook cannot be released (the message names it), or ``out_dir`` is not safe to replace.
    """
    out_dir = Path(out_dir).resolve()
    for q in (out_dir, *out_dir.parents):
        if q.exists() and not q.is_dir():
            raise ReleaseError(f"{out_dir}: {q} is a file, not a folder; give a folder path (a new one, or an earlier "
                               "release)")
    if out_dir == REPO_ROOT or REPO_ROOT.is_relative_to(out_dir) or out_dir.is_relative_to(REPO_ROOT / "course_lib"):
        raise ReleaseError(f"refusing to write the release into {out_dir}: choose a folder outside the kit's sources")
    if out_dir.exists() and any(out_dir.iterdir()):
        if not (out_dir / "RELEASE_MANIFEST.json").exists() and not force:
            raise ReleaseError(f"{out_dir} is not empty and not an earlier release; use --force to replace it")
    files = release_files(notebooks_dir)
    if out_dir.exists() and any(out_dir.iterdir()):
        shutil.rmtree(out_dir)
    write_files(files, out_dir)
    return json.loads(files["RELEASE_MANIFEST.json"])


def write_files(files: dict[str, bytes], out_dir: Path) -> Path:
    """Write ``{path inside out_dir: content}`` (:func:`release_files`, or a part of it) into ``out_dir``."""
    for rel, data in sorted(files.items()):
        dst = Path(out_dir) / rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        dst.write_bytes(data)
    return Path(out_dir)


def release_files(notebooks_dir: Path = NOTEBOOKS_DIR) -> dict[str, bytes]:
    """``{path inside the kit: content}`` of the student kit (what :func:`write_release` writes).

    Raises:
        ReleaseError: a notebook cannot be released (the message names it).
    """
    specs = kit_specs(notebooks_dir)
    plan = release_plan(specs)
    files: dict[str, bytes] = {}

    # notebooks
    for p in sorted(Path(notebooks_dir).glob("*.ipynb")):
        if p.name in plan.left_out_notebooks:
            continue
        nb = stub_notebook(nbformat.read(p, as_version=4), p.name)
        files[f"notebooks/{p.name}"] = nbformat.writes(nb).encode() + b"\n"
    # course_lib
    mods = course_lib_modules()
    omit_files = {str(mods[m].relative_to(REPO_ROOT)) for m in plan.omit}
    instructor_dir = REPO_ROOT.joinpath(*INSTRUCTOR_PACKAGE.split("."))
    for p in _walk(REPO_ROOT / "course_lib"):
        rel = str(p.relative_to(REPO_ROOT))
        if p.is_relative_to(instructor_dir) or rel in omit_files or p.suffix != ".py" and p.suffix not in (".json", ".txt", ".md"):
            continue
        mod = module_name(p) if p.suffix == ".py" else None
        files[rel] = (redact_module(p, plan.redact[mod], plan.exercise_notebook, imported_names(mod)).encode()
                      if mod in plan.redact else p.read_bytes())
    # data
    for p in _walk(REPO_ROOT / "data"):
        files[str(p.relative_to(REPO_ROOT))] = p.read_bytes()
    for name in COPIED_FILES:
        if (REPO_ROOT / name).exists():
            files[name] = (REPO_ROOT / name).read_bytes()
    if (REPO_ROOT / "environment.txt").exists():
        files["environment.txt"] = student_environment((REPO_ROOT / "environment.txt").read_text(),
                                                       imported_packages(files)).encode()

    files["pyproject.toml"] = (STUDENT_TEMPLATES / "pyproject.toml").read_text().format(version=__version__).encode()
    files[".gitignore"] = (STUDENT_TEMPLATES / "gitignore").read_bytes()
    files["README.md"] = student_readme(specs, plan).encode()

    manifest = {
        "kit_version": __version__,
        "notebooks": [
            {"name": s.name, "exercises": [asdict(e) for e in s.exercises]} for s in specs
            if s.name not in plan.left_out_notebooks
        ],
        "left_out_notebooks": plan.left_out_notebooks,
        "omitted_modules": plan.omit,
        "redacted": plan.redact,
        "exercise_implementations": plan.implementations,
        "notes": plan.notes,
        "files": {k: sha256(v) for k, v in sorted(files.items())},
    }
    files["RELEASE_MANIFEST.json"] = (json.dumps(manifest, indent=1, sort_keys=True, ensure_ascii=False) + "\n").encode()
    return files


# ---------------------------------------------------------------------------------------------
# Verification: the released notebooks run in the released kit
# ---------------------------------------------------------------------------------------------

ALLOWED_ERRORS = ("NotImplementedError",)
#: Errors allowed after a cell that stopped: names it would have defined, files it would have written.
CONSEQUENCES = ("NameError", "KitInputError", "FileNotFoundError")


def verify_release(out_dir: Path, only: list[str] | None = None, timeout: float = 300.0,
                   solutions: Path | None = None,
                   allowed_errors: tuple[str, ...] = ALLOWED_ERRORS) -> dict[str, list[str]]:
    """Execute the released notebooks inside the released kit and list what is wrong.

    The kernel sees the kit's own ``course_lib`` (``PYTHONPATH=out_dir``), so the left-out reference
    solutions are really absent. The saved solutions (:mod:`course_lib.saved_solutions`) go to
    ``solutions`` (default: an empty scratch folder, so nothing of an earlier run is used and
    nothing is written into the kit). Allowed: cells that stop with ``NotImplementedError`` (an exercise
    not written yet, or a kit function that needs it) and, after such a cell, its consequences
    (``NameError`` for the names it would have defined, a missing file it would have written). Not
    allowed: any other error, an error in an exercise's check cell (checks turn a student's error
    into a verdict), or an exercise's check cell that prints nothing. (The check cells of notebooks
    without exercises, 09 and 10, report on runs that need the student's earlier exercises: their
    errors follow the rule of the other cells.)
    ``allowed_errors=()`` allows no error at all (a release filled with solutions: every cell must run).

    Returns:
        ``{notebook: [problems]}`` (empty lists when the release is sound).
    """
    out_dir = Path(out_dir).resolve()
    problems: dict[str, list[str]] = {}
    manifest = json.loads((out_dir / "RELEASE_MANIFEST.json").read_text())
    exercise_checks = {nb["name"]: {e["check_cell"] for e in nb["exercises"]} for nb in manifest["notebooks"]}
    paths = sorted((out_dir / "notebooks").glob("*.ipynb"))
    if only:
        paths = [p for p in paths if any(p.name.startswith(o) for o in only)]

    with tempfile.TemporaryDirectory(prefix="kit-solutions-") as scratch:
        env = {"PYTHONPATH": os.pathsep.join(filter(None, [str(out_dir), os.environ.get("PYTHONPATH")])),
               "COURSE_LIB_SOLUTIONS": str(solutions) if solutions is not None else scratch}
        for p in paths:
            nb = nbformat.read(p, as_version=4)
            probe = nbformat.v4.new_code_cell("import course_lib\nprint(course_lib.__file__)")
            nb.cells.insert(0, probe)
            execute_quick(nb, p.parent, timeout, **env)
            found, failed_before = [], False
            where = stream_text(nb.cells.pop(0)).strip()
            if not where.startswith(str(out_dir)):
                found.append(f"the kernel imported course_lib from {where or '?'}, not from the kit")
            for i, cell in enumerate(nb.cells):
                if cell.cell_type != "code":
                    continue
                errors = [o for o in cell.outputs if o.output_type == "error"]
                is_check = cell.source.lstrip().startswith(CHECK_MARK) and i in exercise_checks.get(p.name, ())
                if is_check and (errors or not stream_text(cell).strip()):
                    found.append(f"cell {i}: the check cell " + (f"raised {errors[0].ename}" if errors else "printed nothing"))
                for e in errors:
                    if not (e.ename in allowed_errors or (e.ename in CONSEQUENCES and failed_before)):
                        found.append(f"cell {i}: {e.ename}: {e.evalue}")
                    failed_before = True
            problems[p.name] = found
    return problems

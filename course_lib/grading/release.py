"""The student release: notebooks with their solutions taken out, and the kit they need to run.

``python -m course_lib release OUT_DIR`` writes the student kit:

* ``notebooks/*.ipynb``: every instructor notebook with each solution region (the lines between
  ``# BEGIN SOLUTION`` and ``# END SOLUTION`` of an exercise cell) replaced by a stub
  (``# YOUR CODE HERE`` + ``raise NotImplementedError``; lines of the region that start with
  ``# HINT`` are kept), the signature and docstring untouched. Check cells keep their source and
  their stored reference verdicts (nbval compares the student's run with them), markdown and
  figures stay, the outputs of exercise cells are cleared, execution timestamps are dropped.
* ``course_lib/`` without the reference solutions. A module is a *solution module* when a
  solution region imports it (:func:`solution_modules`). Solution modules that no released
  notebook needs are left out, with every module that imports them (:func:`release_plan`); solution
  modules that the kit itself builds on (the NeRF trainer imports :mod:`course_lib.nerf.render`)
  are shipped *redacted*: their exercise functions are replaced by a stand-in that calls the
  student's own function of the same name (:mod:`course_lib.grading.student`).
* ``data/`` (the embedded scenes and the fixtures behind the check cells), ``environment.txt``,
  ``conftest.py``, a ``pyproject.toml`` whose pytest runs the notebooks, a ``README.md`` for
  students, and ``RELEASE_MANIFEST.json`` (exercises, their check cells, reference verdicts,
  points, and the SHA-256 of every released file).

Releasing twice gives byte-identical files (sorted walks, no timestamps). A notebook whose
solution markers are unbalanced, or whose check cell names an exercise without markers, stops the
release with an error that names the notebook and the cell.

The grader (:mod:`course_lib.grading.grade`) reads the same :func:`notebook_spec` from the
instructor's notebooks, so the reference verdicts it compares with never come from a file the
student can edit.
"""

from __future__ import annotations

import ast
import hashlib
import json
import re
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path

import nbformat

from course_lib.paths import REPO_ROOT
from course_lib.validate import KitInputError

__all__ = [
    "BEGIN",
    "END",
    "ReleaseError",
    "ExerciseSpec",
    "NotebookSpec",
    "notebook_spec",
    "kit_specs",
    "stub_notebook",
    "solution_modules",
    "release_plan",
    "write_release",
    "release_files",
]

BEGIN, END = "# BEGIN SOLUTION", "# END SOLUTION"
CHECK_MARK = "# NBVAL_CHECK_OUTPUT"
DEFAULT_POINTS = 10.0
NOTEBOOKS_DIR = REPO_ROOT / "notebooks"

#: Files of course_lib that only the instructor needs (release and grading machinery).
INSTRUCTOR_ONLY = (
    "course_lib/grading/release.py",
    "course_lib/grading/grade.py",
    "course_lib/grading/sandbox.py",
    "course_lib/grading/proxy.py",
    "course_lib/grading/child.py",
    "course_lib/grading/cli_release.py",
    "course_lib/grading/cli_grade.py",
)
#: Top-level files copied as they are, when present.
COPIED_FILES = ("environment.txt", "conftest.py")
SKIP_NAMES = {"__pycache__", ".ipynb_checkpoints", ".pytest_cache", ".DS_Store"}


class ReleaseError(KitInputError):
    """A notebook cannot be released (unbalanced or missing solution markers, unexecuted check cell)."""


# ---------------------------------------------------------------------------------------------
# Reading the instructor notebooks
# ---------------------------------------------------------------------------------------------


@dataclass
class ExerciseSpec:
    """One exercise: a function (or class) of an exercise cell and the check cell after it."""

    notebook: str
    name: str
    cell: int  # index (among all cells) of the exercise cell
    check_cell: int  # index of its check cell
    check_module: str  # e.g. course_lib.grading.fundamental
    check_function: str  # e.g. check_eight_point
    check_source: str
    check_sha256: str
    verdict: str  # the reference run's printed verdict (stdout of the check cell)
    points: float = DEFAULT_POINTS
    reference: str | None = None  # "module:attribute" of the reference solution, if any


@dataclass
class NotebookSpec:
    name: str
    exercises: list[ExerciseSpec] = field(default_factory=list)
    solution_modules: list[str] = field(default_factory=list)
    imports: list[str] = field(default_factory=list)  # course_lib modules imported outside solution regions

    def exercise(self, name: str) -> ExerciseSpec:
        return next(e for e in self.exercises if e.name == name)


def _sha(text: str | bytes) -> str:
    return hashlib.sha256(text.encode() if isinstance(text, str) else text).hexdigest()


def python_source(source: str) -> str:
    """Cell source with IPython magics and shell lines turned into ``pass`` (so ``ast`` can parse it)."""
    out = []
    for line in source.splitlines():
        s = line.lstrip()
        out.append(line[: len(line) - len(s)] + "pass  # " + s if s.startswith(("%", "!")) else line)
    return "\n".join(out)


def marker_regions(source: str, where: str) -> list[tuple[int, int]]:
    """``[(begin_line, end_line)]`` (0-based, inclusive) of the solution regions in a cell.

    Raises:
        ReleaseError: when the markers are unbalanced or nested.
    """
    regions, start = [], None
    for k, line in enumerate(source.splitlines()):
        s = line.strip()
        if s == BEGIN:
            if start is not None:
                raise ReleaseError(f"{where}: '{BEGIN}' at line {k + 1} before the '{END}' of line {start + 1}'s region")
            start = k
        elif s == END:
            if start is None:
                raise ReleaseError(f"{where}: '{END}' at line {k + 1} without a '{BEGIN}' before it")
            regions.append((start, k))
            start = None
    if start is not None:
        raise ReleaseError(f"{where}: '{BEGIN}' at line {start + 1} has no '{END}'")
    return regions


def _stream_text(cell) -> str:
    return "".join(o.get("text", "") for o in cell.get("outputs", []) if o.get("output_type") == "stream"
                   and o.get("name") == "stdout")


def _module_exists(name: str) -> bool:
    parts = name.split(".")
    base = REPO_ROOT.joinpath(*parts)
    return base.with_suffix(".py").exists() or (base / "__init__.py").exists()


def resolve_import(node: ast.AST) -> list[tuple[str, str | None]]:
    """``[(module, imported name or None)]`` for an import statement, modules resolved to files of the kit.

    ``from course_lib.sfm import fundamental`` gives ``("course_lib.sfm.fundamental", None)``;
    ``from course_lib.nerf.rays import get_rays`` gives ``("course_lib.nerf.rays", "get_rays")``.
    """
    out: list[tuple[str, str | None]] = []
    if isinstance(node, ast.Import):
        out += [(a.name, None) for a in node.names]
    elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
        for a in node.names:
            sub = f"{node.module}.{a.name}"
            if sub.startswith("course_lib") and _module_exists(sub):
                out.append((sub, None))
            else:
                out.append((node.module, a.name))
    return out


def _top_defs(tree: ast.Module) -> list[ast.AST]:
    return [n for n in tree.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))]


def notebook_spec(path: Path) -> NotebookSpec:
    """Exercises, check cells and reference verdicts of one instructor notebook.

    Raises:
        ReleaseError: unbalanced markers, a check cell without an exercise with markers, a check
            cell that was not executed, or a notebook without any solution region.
    """
    path = Path(path)
    nb = nbformat.read(path, as_version=4)
    spec = NotebookSpec(path.name)
    defined: dict[str, tuple[int, list[str]]] = {}  # exercise name -> (cell, region texts)
    check_imports: dict[str, str] = {}
    any_region = False
    sol_mods: set[str] = set()
    mods: set[str] = set()
    for i, cell in enumerate(nb.cells):
        if cell.cell_type != "code":
            continue
        where = f"{path.name}, cell {i}"
        regions = marker_regions(cell.source, where)
        lines = cell.source.splitlines()
        try:
            tree = ast.parse(python_source(cell.source))
        except SyntaxError as exc:
            raise ReleaseError(f"{where}: not valid Python ({exc.msg}, line {exc.lineno})") from None
        region_lines = {k for a, b in regions for k in range(a, b + 1)}
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for mod, name in resolve_import(node):
                    if not mod.startswith("course_lib"):
                        continue
                    if node.lineno - 1 in region_lines:
                        sol_mods.add(mod)
                    elif not _in_optional_import(tree, node):
                        mods.add(mod)
                    if mod.startswith("course_lib.grading.") and name and name.startswith("check_"):
                        check_imports[name] = mod
        if regions:
            any_region = True
            for node in _top_defs(tree):
                inside = [(a, b) for a, b in regions if node.lineno - 1 <= a <= node.end_lineno - 1]
                if inside:
                    texts = ["\n".join(lines[a:b + 1]) for a, b in inside]
                    defined[node.name] = (i, texts)
            outside = [r for r in regions if not any(
                n.lineno - 1 <= r[0] <= n.end_lineno - 1 for n in _top_defs(tree))]
            if outside:
                raise ReleaseError(f"{where}: the solution region at line {outside[0][0] + 1} is not inside a function "
                                   "or class definition (an exercise is a def with its signature and docstring)")
        first = cell.source.lstrip().splitlines()[0].strip() if cell.source.strip() else ""
        if first == CHECK_MARK:
            call = next((n for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)
                         and n.func.id.startswith("check_")), None)
            if call is None:
                continue  # nbval compares this cell's output, but it checks no exercise
            if not call.args or not isinstance(call.args[0], ast.Name):
                raise ReleaseError(f"{where}: a check cell must call check_<exercise>(<exercise>)")
            fn, ex = call.func.id, call.args[0].id
            if ex not in defined:
                raise ReleaseError(f"{where}: the check cell calls {fn}({ex}) but no exercise cell before it defines "
                                   f"{ex} with '{BEGIN}' / '{END}' markers (missing solution markers)")
            verdict = _stream_text(cell)
            if not verdict.strip():
                raise ReleaseError(f"{where}: the check cell has no stored verdict; execute the notebook before releasing")
            if fn not in check_imports:
                raise ReleaseError(f"{where}: {fn} is not imported from a course_lib.grading module in this notebook")
            ex_cell, texts = defined[ex]
            points = float(nb.cells[ex_cell].metadata.get("points", DEFAULT_POINTS))
            spec.exercises.append(ExerciseSpec(
                notebook=path.name, name=ex, cell=ex_cell, check_cell=i, check_module=check_imports[fn],
                check_function=fn, check_source=cell.source, check_sha256=_sha(cell.source), verdict=verdict,
                points=points, reference=_reference_of(ex, texts)))
    spec.solution_modules = sorted(sol_mods)
    spec.imports = sorted(mods)
    if not any_region and not spec.exercises:
        return spec  # a notebook without exercises (a demo): released as it is, not graded
    if not spec.exercises:
        raise ReleaseError(f"{path.name}: solution regions but no check cell ('{CHECK_MARK}' on its first line)")
    spec.solution_modules = sorted(sol_mods)
    spec.imports = sorted(mods)
    return spec


def _optional_ids(tree: ast.Module) -> set[int]:
    """ids of the nodes inside ``try:`` blocks whose handlers catch ImportError (optional imports)."""
    out: set[int] = set()
    for t in ast.walk(tree):
        if isinstance(t, ast.Try):
            names = {getattr(h.type, "id", None) for h in t.handlers} | {
                getattr(e, "id", None) for h in t.handlers if isinstance(h.type, ast.Tuple) for e in h.type.elts}
            if names & {"ImportError", "ModuleNotFoundError", "Exception", None}:
                out |= {id(n) for s in t.body for n in ast.walk(s)}
    return out


def _in_optional_import(tree: ast.Module, node: ast.AST, _cache: dict = {}) -> bool:  # noqa: B006 - per-tree cache
    """True if ``node`` sits in a ``try:`` whose handlers catch ImportError (an optional import)."""
    key = id(tree)
    if key not in _cache or _cache[key][0] is not tree:
        _cache.clear()
        _cache[key] = (tree, _optional_ids(tree))
    return id(node) in _cache[key][1]


def _reference_of(name: str, region_texts: list[str]) -> str | None:
    """``"module:attribute"`` of the reference an instructor solution region calls, if any."""
    for text in region_texts:
        try:
            tree = ast.parse("\n".join(line.strip() for line in text.splitlines()))
        except SyntaxError:
            continue
        for node in ast.walk(tree):
            for mod, attr in resolve_import(node) if isinstance(node, (ast.Import, ast.ImportFrom)) else []:
                if not mod.startswith("course_lib"):
                    continue
                return f"{mod}:{attr or name}"
    return None


def kit_specs(notebooks_dir: Path = NOTEBOOKS_DIR, only: list[str] | None = None,
              errors_out: list[str] | None = None) -> list[NotebookSpec]:
    """:func:`notebook_spec` of every notebook (sorted by name), or of those whose name starts with one of ``only``.

    Raises :class:`ReleaseError` naming every notebook that cannot be released, unless
    ``errors_out`` is given: then those messages are appended to it and the others are returned.
    """
    paths = sorted(Path(notebooks_dir).glob("*.ipynb"))
    if only:
        paths = [p for p in paths if any(p.name.startswith(o) for o in only)]
    errors, specs = [], []
    for p in paths:
        try:
            specs.append(notebook_spec(p))
        except ReleaseError as exc:
            errors.append(str(exc))
    if errors and errors_out is None:
        raise ReleaseError("cannot release:\n  " + "\n  ".join(errors))
    if errors_out is not None:
        errors_out.extend(errors)
    return specs


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
# Which parts of course_lib are solutions
# ---------------------------------------------------------------------------------------------


def _module_file(mod: str) -> Path | None:
    base = REPO_ROOT.joinpath(*mod.split("."))
    if base.with_suffix(".py").exists():
        return base.with_suffix(".py")
    if (base / "__init__.py").exists():
        return base / "__init__.py"
    return None


def _module_name(path: Path) -> str:
    rel = path.relative_to(REPO_ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


_IMPORTS_CACHE: dict[tuple, dict[str, set[str]]] = {}


def module_imports(path: Path) -> dict[str, set[str]]:
    """Cached :func:`_module_imports` (keyed by the file's path, size and modification time)."""
    st = Path(path).stat()
    key = (str(path), st.st_size, st.st_mtime_ns)
    if key not in _IMPORTS_CACHE:
        _IMPORTS_CACHE[key] = _module_imports(Path(path))
    return {k: set(v) for k, v in _IMPORTS_CACHE[key].items()}


def _module_imports(path: Path) -> dict[str, set[str]]:
    """``{"top": modules imported when the module loads, "lazy": imported inside functions}`` (course_lib only).

    Imports inside ``try`` blocks that catch ImportError count as neither (they are optional).
    """
    tree = ast.parse(path.read_text())
    out: dict[str, set[str]] = {"top": set(), "lazy": set()}
    func_nodes = {id(n) for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
                  for n in ast.walk(f) if n is not f}
    for node in ast.walk(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            if _in_optional_import(tree, node):
                continue
            for mod, _ in resolve_import(node):
                if mod.startswith("course_lib"):
                    # importing a.b.c imports the packages a and a.b first
                    kind = "lazy" if id(node) in func_nodes else "top"
                    out[kind].add(mod)
    return out


def course_lib_modules() -> dict[str, Path]:
    files = sorted(p for p in (REPO_ROOT / "course_lib").rglob("*.py") if not SKIP_NAMES & set(p.parts))
    return {_module_name(p): p for p in files}


def solution_modules(specs: list[NotebookSpec]) -> dict[str, list[str]]:
    """``{module: [exercise names it holds the reference of]}`` over all notebooks."""
    out: dict[str, list[str]] = {}
    for s in specs:
        for m in s.solution_modules:
            out.setdefault(m, [])
        for e in s.exercises:
            if e.reference:
                mod, attr = e.reference.split(":")
                out.setdefault(mod, []).append(attr)
    return {m: sorted(set(v)) for m, v in sorted(out.items())}


@dataclass
class ReleasePlan:
    omit: list[str]  # modules left out of the kit
    redact: dict[str, list[str]]  # module -> exercise names replaced by stand-ins
    exercise_notebook: dict[str, str]  # exercise name -> notebook that teaches it
    notes: list[str] = field(default_factory=list)
    left_out_notebooks: list[str] = field(default_factory=list)  # demos that need the reference solutions


def release_plan(specs: list[NotebookSpec]) -> ReleasePlan:
    """Decide which course_lib modules the student kit leaves out and which it ships redacted.

    A solution module that a notebook needs outside its solution regions (directly or through
    the modules it loads) is redacted; any other solution module is left out, and so is every
    module that imports a left-out module (at load time or inside a function). Check modules
    (``course_lib.grading.*``) always ship: they import the reference only inside fixture builders.
    """
    mods = course_lib_modules()
    imports = {m: module_imports(p) for m, p in mods.items()}
    demos = [s for s in specs if not s.exercises]
    specs = [s for s in specs if s.exercises]
    sol = solution_modules(specs)
    needed: set[str] = set()
    todo = [m for s in specs for m in s.imports]
    while todo:
        m = todo.pop()
        if m in needed or m not in mods:
            continue
        needed.add(m)
        todo += sorted(imports[m]["top"])
        parts = m.split(".")
        todo += [".".join(parts[:k]) for k in range(1, len(parts))]
    omit = {m for m in sol if m not in needed and m in mods}
    grown = True
    while grown:
        grown = False
        for m in mods:
            if m in omit or m in needed or m.startswith("course_lib.grading") or m == "course_lib.__main__":
                continue
            if (imports[m]["top"] | imports[m]["lazy"]) & omit:
                omit.add(m)
                grown = True
    notes = []
    for m in sorted(needed):
        lazy = imports[m]["lazy"] & omit
        if lazy and not m.startswith("course_lib.grading"):
            notes.append(f"{m} is needed by a notebook but calls left-out {sorted(lazy)} inside functions")
    redact = {m: names for m, names in sol.items() if m in needed and m in mods}
    ex_nb = {e.name: e.notebook for s in specs for e in s.exercises}
    left_out = []
    for d in demos:
        reach, todo = set(), list(d.imports)
        while todo:
            m = todo.pop()
            if m in reach or m not in mods:
                continue
            reach.add(m)
            todo += sorted(imports[m]["top"] | imports[m]["lazy"])
        if reach & omit:
            left_out.append(d.name)
            notes.append(f"notebooks/{d.name} has no exercises and needs {sorted(reach & omit)[0]} (a reference "
                         "solution): it is not part of the student kit")
    return ReleasePlan(sorted(omit), redact, ex_nb, notes, left_out)


def redact_module(path: Path, names: list[str], exercise_notebook: dict[str, str], keep: set[str] = frozenset()) -> str:
    """The module's source with the top-level defs of ``names`` replaced by student stand-ins.

    Private helpers (``_name``) that only the removed code used are removed too, unless another
    module imports them (``keep``).
    """
    text = path.read_text()
    names = [n for n in names if n in exercise_notebook]
    for _ in range(20):  # remove defs, then helpers that became unused, until nothing changes
        tree = ast.parse(text)
        lines = text.splitlines()
        spans = []
        for node in tree.body:
            target = _bound_name(node)
            if target in names:
                spans.append((node, "stand_in", target))
        if not spans:
            used = _names_used(tree)
            for node in tree.body:
                target = _bound_name(node)
                if target and target.startswith("_") and not target.startswith("__") and target not in keep \
                        and target not in used[target]:
                    spans.append((node, "drop", target))
        if not spans:
            break
        for node, kind, target in sorted(spans, key=lambda s: -s[0].lineno):
            start = min([node.lineno] + [d.lineno for d in getattr(node, "decorator_list", [])]) - 1
            end = node.end_lineno
            if kind == "stand_in":
                nb = exercise_notebook[target]
                new = [
                    f"# {target}: an exercise of notebooks/{nb}; the student kit leaves its reference solution out.",
                    "# This stand-in calls your own " + target + " from the running notebook.",
                    "from course_lib.grading.student import stand_in as _kit_stand_in  # noqa: E402",
                    "",
                    f"{target} = _kit_stand_in({target!r}, {nb!r})",
                ]
            else:
                new = []
            lines[start:end] = new
        names = [n for n in names if n not in {t for _, k, t in spans if k == "stand_in"}]
        text = "\n".join(lines) + "\n"
        text = re.sub(r"\n{4,}", "\n\n\n", text)
    return text


def imported_names(module: str) -> set[str]:
    """Names that other course_lib modules import from ``module`` (``from module import a, b``)."""
    out: set[str] = set()
    for m, p in course_lib_modules().items():
        if m == module:
            continue
        out.update(_from_imports(p).get(module, ()))
    return out


_FROM_CACHE: dict[tuple, dict[str, set[str]]] = {}


def _from_imports(path: Path) -> dict[str, set[str]]:
    """``{module: names}`` of the ``from module import names`` statements of a file (cached by size and mtime)."""
    st = Path(path).stat()
    key = (str(path), st.st_size, st.st_mtime_ns)
    if key not in _FROM_CACHE:
        found: dict[str, set[str]] = {}
        for node in ast.walk(ast.parse(Path(path).read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                found.setdefault(node.module, set()).update(a.name for a in node.names)
        _FROM_CACHE[key] = found
    return _FROM_CACHE[key]


def _bound_name(node: ast.AST) -> str | None:
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        return node.name
    if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
        return node.targets[0].id
    if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
        return node.target.id
    return None


def _names_used(tree: ast.Module) -> dict[str, set[str]]:
    """For each top-level name: the names used anywhere *outside* its own definition."""

    class Uses(dict):
        def __missing__(self, key):
            found = set()
            for node in tree.body:
                if _bound_name(node) == key:
                    continue
                for n in ast.walk(node):
                    if isinstance(n, ast.Name):
                        found.add(n.id)
                    elif isinstance(n, ast.Attribute):
                        found.add(n.attr)
                    elif isinstance(n, ast.Constant) and isinstance(n.value, str):
                        found.update(re.findall(r"\w+", n.value))
            self[key] = found
            return found

    return Uses()


# ---------------------------------------------------------------------------------------------
# Writing the kit
# ---------------------------------------------------------------------------------------------

STUDENT_PYPROJECT = """\
[build-system]
requires = ["setuptools>=64"]
build-backend = "setuptools.build_meta"

[project]
name = "course_lib"
version = "{version}"
description = "Student kit of the SfM + NeRF course"
requires-python = ">=3.10"

[tool.setuptools.packages.find]
include = ["course_lib*"]

[tool.pytest.ini_options]
# `pytest` runs your notebooks with nbval: every check cell must print the reference verdict
# stored in the notebook. conftest.py sets COURSE_LIB_QUICK=1 (short training runs).
testpaths = ["notebooks"]
addopts = "--nbval-lax --nbval-current-env -p no:cacheprovider"
filterwarnings = ["ignore::DeprecationWarning:jupyter_client.*", "ignore::DeprecationWarning:zmq.*"]
"""

STUDENT_GITIGNORE = """\
.venv/
__pycache__/
*.pyc
.pytest_cache/
.ipynb_checkpoints/
outputs/
*.egg-info/
"""


def student_readme(specs: list[NotebookSpec], plan: ReleasePlan) -> str:
    rows = []
    for s in specs:
        if not s.exercises:
            continue
        names = ", ".join(f"`{e.name}`" for e in s.exercises)
        pts = sum(e.points for e in s.exercises)
        rows.append(f"| `notebooks/{s.name}` | {names} | {pts:g} |")
    total = sum(e.points for s in specs for e in s.exercises)
    redacted = sorted({n for names in plan.redact.values() for n in names})
    carry = ""
    if redacted:
        carry = (
            "\n## Using your earlier solutions\n\n"
            "Some parts of the kit build on functions that are exercises themselves (for example the NeRF\n"
            "trainer renders with `volume_render`). In this kit those library functions call **your own**\n"
            "function of the same name from the running notebook: "
            + ", ".join(f"`{n}`" for n in redacted)
            + ".\nIf a cell stops with `NotImplementedError: ... is an exercise of notebooks/...`, define your\n"
            "solution of that exercise in the notebook you are working on (paste its cell) and run it.\n"
        )
    n_nb = sum(1 for s in specs if s.exercises)
    return f"""# SfM + NeRF course kit: student release

{n_nb} notebooks take you from two photos to a 3-D reconstruction (Structure from Motion) and then
to a neural radiance field (NeRF). In each notebook you write a few functions; a **check cell**
after each exercise runs your function on test cases and prints what is right and, when something
is wrong, the likely mistake.

## Set up (once)

```bash
python -m venv .venv && . .venv/bin/activate
pip install -r environment.txt && pip install -e .
jupyter lab notebooks/
```

## Work on an exercise

1. Open the notebook and run it from the top.
2. Find the cells with `# YOUR CODE HERE` / `raise NotImplementedError`: replace those two lines
   with your code. Keep the function's name, its arguments and its docstring.
3. Run the check cell below it (`# NBVAL_CHECK_OUTPUT`). It prints ✔ for each passing check and
   ✘ with a hint otherwise. Do not edit check cells: the grader restores them and compares
   their output with the reference.
4. Every notebook starts from the reference result of the step before, so you can do them in any
   order.

## Check your whole kit

```bash
pytest            # runs every notebook with nbval; a check cell passes when it prints the reference verdict
pytest notebooks/01_fundamental_matrix.ipynb
```

## Exercises and points

| notebook | exercises | points |
|---|---|---|
{chr(10).join(rows)}
| **total** | | **{total:g}** |

## How your work is graded

The grader runs your notebooks with nbval (check cells are restored to the original and must
print the reference verdict) and, independently, runs each exercise function on *hidden* test
cases (new synthetic scenes) with a time limit, in a separate process that holds your code and this
kit's `course_lib` only, works in a copy of your folder, has no network and may write only there.
A function that loops is stopped at the limit and one that ends its process is named in the
feedback; either costs that exercise only. Per exercise, 90 % of the points come from the
hidden checks (the share of them that pass); the last 10 % come when all hidden checks pass and
the check cell in your notebook prints the reference verdict (run it top to bottom before you
hand in). There is no credit for an exercise that calls the kit's reference solution,
whose check cell was edited or printed by hand, whose checks were patched, or whose cell was
deleted or moved. Write your own code in the exercise cells; helper functions and imports in the
notebook are fine.
{carry}
## Data

`data/synthetic-building` (SfM) and `data/synthetic-building-nerf` (NeRF) are small scenes with
known ground truth, made by the kit. The course's own data sets are used with a one-line change in
the first code cell of each notebook (`DATA = course_data("wpi")`, see `course_lib/paths.py`).
"""


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
    out_dir.mkdir(parents=True, exist_ok=True)
    for rel, data in sorted(files.items()):
        dst = out_dir / rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        dst.write_bytes(data)
    return json.loads(files["RELEASE_MANIFEST.json"])


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
    omit_files = set(INSTRUCTOR_ONLY)
    mods = course_lib_modules()
    for m in plan.omit:
        omit_files.add(str(mods[m].relative_to(REPO_ROOT)))
    for p in _walk(REPO_ROOT / "course_lib"):
        rel = str(p.relative_to(REPO_ROOT))
        if rel in omit_files or p.suffix != ".py" and p.suffix not in (".json", ".txt", ".md"):
            continue
        mod = _module_name(p) if p.suffix == ".py" else None
        if mod in plan.redact:
            keep = imported_names(mod)
            files[rel] = redact_module(p, plan.redact[mod], plan.exercise_notebook, keep).encode()
        else:
            files[rel] = p.read_bytes()
    # data
    for p in _walk(REPO_ROOT / "data"):
        files[str(p.relative_to(REPO_ROOT))] = p.read_bytes()
    for name in COPIED_FILES:
        if (REPO_ROOT / name).exists():
            files[name] = (REPO_ROOT / name).read_bytes()
    from course_lib import __version__

    files["pyproject.toml"] = STUDENT_PYPROJECT.format(version=__version__).encode()
    files[".gitignore"] = STUDENT_GITIGNORE.encode()
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
        "notes": plan.notes,
        "files": {k: _sha(v) for k, v in sorted(files.items())},
    }
    files["RELEASE_MANIFEST.json"] = (json.dumps(manifest, indent=1, sort_keys=True, ensure_ascii=False) + "\n").encode()
    return files


# ---------------------------------------------------------------------------------------------
# Verification: the released notebooks run in the released kit
# ---------------------------------------------------------------------------------------------

ALLOWED_ERRORS = ("NotImplementedError",)
#: Errors allowed after a cell that stopped: names it would have defined, files it would have written.
CONSEQUENCES = ("NameError", "KitInputError", "FileNotFoundError")


def verify_release(out_dir: Path, only: list[str] | None = None, timeout: float = 300.0) -> dict[str, list[str]]:
    """Execute the released notebooks inside the released kit and list what is wrong.

    The kernel sees the kit's own ``course_lib`` (``PYTHONPATH=out_dir``), so the left-out reference
    solutions are really absent. Allowed: cells that stop with ``NotImplementedError`` (an exercise
    not written yet, or a kit function that needs it) and, after such a cell, its consequences
    (``NameError`` for the names it would have defined, a missing file it would have written). Not allowed: any other error, an error in a check cell
    (checks turn a student's error into a verdict), or a check cell that prints nothing.

    Returns:
        ``{notebook: [problems]}`` (empty lists when the release is sound).
    """
    import os

    from nbclient import NotebookClient

    out_dir = Path(out_dir).resolve()
    problems: dict[str, list[str]] = {}
    paths = sorted((out_dir / "notebooks").glob("*.ipynb"))
    if only:
        paths = [p for p in paths if any(p.name.startswith(o) for o in only)]
    old_env = {k: os.environ.get(k) for k in ("PYTHONPATH", "COURSE_LIB_QUICK", "MPLBACKEND")}
    os.environ["PYTHONPATH"] = str(out_dir) + (os.pathsep + old_env["PYTHONPATH"] if old_env["PYTHONPATH"] else "")
    os.environ["COURSE_LIB_QUICK"] = "1"
    os.environ["MPLBACKEND"] = "Agg"
    try:
        for p in paths:
            nb = nbformat.read(p, as_version=4)
            probe = nbformat.v4.new_code_cell("import course_lib\nprint(course_lib.__file__)")
            nb.cells.insert(0, probe)
            client = NotebookClient(nb, timeout=timeout, kernel_name="python3", allow_errors=True,
                                    resources={"metadata": {"path": str(p.parent)}})
            client.execute()
            found, failed_before = [], False
            where = _stream_text(nb.cells.pop(0)).strip()
            if not where.startswith(str(out_dir)):
                found.append(f"the kernel imported course_lib from {where or '?'}, not from the kit")
            for i, cell in enumerate(nb.cells):
                if cell.cell_type != "code":
                    continue
                errors = [o for o in cell.outputs if o.output_type == "error"]
                is_check = cell.source.lstrip().startswith(CHECK_MARK)
                if is_check and (errors or not _stream_text(cell).strip()):
                    found.append(f"cell {i}: the check cell " + (f"raised {errors[0].ename}" if errors else "printed nothing"))
                for e in errors:
                    if e.ename in ALLOWED_ERRORS or (e.ename in CONSEQUENCES and failed_before):
                        failed_before = True
                        continue
                    found.append(f"cell {i}: {e.ename}: {e.evalue}")
                    failed_before = True
            problems[p.name] = found
    finally:
        for k, v in old_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return problems

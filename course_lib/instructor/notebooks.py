"""Reading the instructor notebooks: exercises, check cells, reference verdicts.

An exercise is a function (or class) of a code cell whose body holds a solution region, the
lines between ``# BEGIN SOLUTION`` and ``# END SOLUTION``; the check cell after it (first line
``# NBVAL_CHECK_OUTPUT``) calls ``check_<exercise>(<exercise>)`` from a module of
:mod:`course_lib.checks`, and its stored output is the reference verdict. :func:`notebook_spec`
reads all of this from one notebook; the release (:mod:`course_lib.instructor.release`) and the
grader (:mod:`course_lib.instructor.grade`) both read it from the instructor's notebooks, so the
reference verdicts never come from a file the student can edit.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path

import nbformat

from course_lib.paths import REPO_ROOT
from course_lib.validate import KitInputError

__all__ = ["BEGIN", "END", "CHECK_MARK", "NOTEBOOKS_DIR", "ReleaseError", "ExerciseSpec", "NotebookSpec",
           "notebook_spec", "kit_specs", "marker_regions", "python_source", "resolve_import", "optional_imports",
           "stream_text", "sha256", "execute_quick", "INSTRUCTOR_PACKAGE", "SKIP_NAMES", "module_name",
           "course_lib_modules", "file_key"]

BEGIN, END = "# BEGIN SOLUTION", "# END SOLUTION"
CHECK_MARK = "# NBVAL_CHECK_OUTPUT"
DEFAULT_POINTS = 10.0
NOTEBOOKS_DIR = REPO_ROOT / "notebooks"


class ReleaseError(KitInputError):
    """A notebook cannot be released (unbalanced or missing solution markers, unexecuted check cell)."""


@dataclass
class ExerciseSpec:
    """One exercise: a function (or class) of an exercise cell and the check cell after it."""

    notebook: str
    name: str
    cell: int  # index (among all cells) of the exercise cell
    check_cell: int  # index of its check cell
    check_module: str  # e.g. course_lib.checks.fundamental
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


def sha256(text: str | bytes) -> str:
    return hashlib.sha256(text.encode() if isinstance(text, str) else text).hexdigest()


#: Magics that run the Python code that follows them (``%time x = f()``, ``%%timeit`` over the cell): their code is
#: parsed and extracted like any other line.
TIMING_MAGICS = ("%time ", "%timeit ", "%%time", "%%timeit")


def python_source(source: str) -> str:
    """Cell source as ``ast`` can parse it: the code after a timing magic kept, every other IPython magic and shell
    line turned into ``pass`` (what the extracted exercise code reads)."""
    out = []
    for line in source.splitlines():
        s = line.lstrip()
        indent = line[: len(line) - len(s)]
        timing = next((m for m in TIMING_MAGICS if s.startswith(m) and not s.startswith("%%") or s.split()[:1] == [m]),
                      None)
        if timing and not timing.startswith("%%"):
            line = indent + s[len(timing):].lstrip()
        elif s.startswith(("%", "!")):
            line = indent + "pass  # " + s
        out.append(line)
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


def stream_text(cell) -> str:
    return "".join(o.get("text", "") for o in cell.get("outputs", []) if o.get("output_type") == "stream"
                   and o.get("name") == "stdout")


def execute_quick(nb, folder: Path, timeout: float, **env: str):
    """Execute ``nb`` in place, in a fresh kernel whose working folder is ``folder``, as nbval runs it: quick mode
    (``COURSE_LIB_QUICK=1``), no display, an error kept as the cell's output; ``env`` is set for the kernel too."""
    from nbclient import NotebookClient

    values = dict(COURSE_LIB_QUICK="1", MPLBACKEND="Agg", **env)
    old = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:  # only these keys are put back (mock.patch.dict would also undo what others set meanwhile, and cost an import)
        NotebookClient(nb, timeout=timeout, kernel_name="python3", allow_errors=True,
                       resources={"metadata": {"path": str(folder)}}).execute()
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return nb


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
            base = REPO_ROOT.joinpath(*sub.split("."))  # a module of the kit, or a name in one
            is_module = base.with_suffix(".py").exists() or (base / "__init__.py").exists()
            out.append((sub, None) if sub.startswith("course_lib") and is_module else (node.module, a.name))
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
        optional = optional_imports(tree)
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for mod, name in resolve_import(node):
                    if not mod.startswith("course_lib"):
                        continue
                    if node.lineno - 1 in region_lines:
                        sol_mods.add(mod)
                    elif id(node) not in optional:
                        mods.add(mod)
                    if mod.startswith("course_lib.checks.") and name and name.startswith("check_"):
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
            e = _checked_exercise(nb, path.name, i, tree, defined, check_imports)
            if e is not None:
                spec.exercises.append(e)
    spec.solution_modules = sorted(sol_mods)
    spec.imports = sorted(mods)
    if not any_region and not spec.exercises:
        return spec  # a notebook without exercises (a demo): released as it is, not graded
    if not spec.exercises:
        raise ReleaseError(f"{path.name}: solution regions but no check cell ('{CHECK_MARK}' on its first line)")
    return spec


def _checked_exercise(nb, notebook: str, i: int, tree: ast.Module, defined: dict[str, tuple[int, list[str]]],
                      check_imports: dict[str, str]) -> ExerciseSpec | None:
    """The exercise that check cell ``i`` of ``notebook`` checks (None: a marked cell that checks no exercise).

    Raises:
        ReleaseError: the cell calls no exercise, or one without solution markers before it, or has no stored
            verdict, or its check function is not imported from a check module.
    """
    cell, where = nb.cells[i], f"{notebook}, cell {i}"
    call = next((n for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)
                 and n.func.id.startswith("check_")), None)
    if call is None:
        return None  # nbval compares this cell's output, but it checks no exercise
    if not call.args or not isinstance(call.args[0], ast.Name):
        raise ReleaseError(f"{where}: a check cell must call check_<exercise>(<exercise>)")
    fn, ex = call.func.id, call.args[0].id
    if ex not in defined:
        raise ReleaseError(f"{where}: the check cell calls {fn}({ex}) but no exercise cell before it defines "
                           f"{ex} with '{BEGIN}' / '{END}' markers (missing solution markers)")
    verdict = stream_text(cell)
    if not verdict.strip():
        raise ReleaseError(f"{where}: the check cell has no stored verdict; execute the notebook before releasing")
    if fn not in check_imports:
        raise ReleaseError(f"{where}: {fn} is not imported from a course_lib.checks module in this notebook")
    ex_cell, texts = defined[ex]
    points = float(nb.cells[ex_cell].metadata.get("points", DEFAULT_POINTS))
    return ExerciseSpec(notebook=notebook, name=ex, cell=ex_cell, check_cell=i,
                        check_module=check_imports[fn], check_function=fn, check_source=cell.source,
                        check_sha256=sha256(cell.source), verdict=verdict, points=points,
                        reference=_reference_of(ex, texts) or library_definition(ex))


def optional_imports(tree: ast.Module) -> set[int]:
    """The ids of the nodes inside ``try:`` blocks whose handlers catch ImportError (an import there is optional)."""
    out: set[int] = set()
    for t in ast.walk(tree):
        if isinstance(t, ast.Try):
            names = {getattr(h.type, "id", None) for h in t.handlers} | {
                getattr(e, "id", None) for h in t.handlers if isinstance(h.type, ast.Tuple) for e in h.type.elts}
            if names & {"ImportError", "ModuleNotFoundError", "Exception", None}:
                out |= {id(n) for s in t.body for n in ast.walk(s)}
    return out


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


#: The package that only the instructor needs (release, grading, the hidden cases); it never ships.
INSTRUCTOR_PACKAGE = "course_lib.instructor"
SKIP_NAMES = {"__pycache__", ".ipynb_checkpoints", ".pytest_cache", ".DS_Store"}


def module_name(path: Path) -> str:
    rel = path.relative_to(REPO_ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def course_lib_modules() -> dict[str, Path]:
    """``{module name: file}`` of the course_lib modules that may ship (everything but the instructor package)."""
    files = sorted(p for p in (REPO_ROOT / "course_lib").rglob("*.py") if not SKIP_NAMES & set(p.parts))
    mods = {module_name(p): p for p in files}
    return {m: p for m, p in mods.items() if m != INSTRUCTOR_PACKAGE and not m.startswith(INSTRUCTOR_PACKAGE + ".")}


def file_key(path: Path) -> tuple[str, int, int]:
    """A file's path, size and modification time: the key of the caches of what a file defines and imports."""
    st = Path(path).stat()
    return str(path), st.st_size, st.st_mtime_ns


@functools.lru_cache(maxsize=None)
def _top_level_names(path: str, size: int, mtime_ns: int) -> set[str]:
    """Names of the top-level defs and classes of a file (cached by :func:`file_key`)."""
    try:
        return {n.name for n in _top_defs(ast.parse(Path(path).read_text()))}
    except SyntaxError:
        return set()


def library_definition(name: str) -> str | None:
    """``"module:name"`` of the course_lib module (outside the instructor package) that defines ``name`` at top level.

    The reference of an exercise whose solution region calls no library function (a one-line
    exercise such as ``psnr``) is the library's own function of that name, when there is one; None
    when no module, or more than one, defines it.
    """
    found = [m for m, p in course_lib_modules().items()
             if m != "course_lib.saved_solutions" and name in _top_level_names(*file_key(p))]
    return f"{found[0]}:{name}" if len(found) == 1 else None


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



"""Hidden checks: an exercise cut out of a submitted notebook, checked here on new cases while it runs elsewhere.

* :func:`extract_exercise` cuts the exercise out of the notebook: the top-level ``def`` (or
  ``class``) of its name in the cells before its check cell, plus the imports, helper functions
  and simple assignments it needs (transitively, the last binding of each name, as the notebook
  would see it when the check cell runs).
* :func:`scan_exercise` reads that code and flags what gets no credit: imports of the reference
  solutions (modules the student kit leaves out, or the graded exercise's own reference), of the
  check machinery, and dynamic tricks that could reach either (``exec``, ``__import__``,
  ``importlib``, ``sys``, ``gc``, ``inspect``, dunder attributes such as ``__globals__``...).
  :func:`scan_notebook` flags a notebook that patches or rebinds the checks, prints verdicts by
  hand or swaps ``print``.
* :func:`build_hidden_fixtures` makes the hidden cases: the fixture builders of the check modules
  (the instructor's full library) run again with every seeded ``numpy.random.default_rng`` salted
  by a grading-time seed, so the synthetic scenes are new; seed 0, which the checks reuse for the
  student's own RANSAC calls, is kept.
* :func:`run_hidden` runs the check function of the exercise *in this process* on those cases;
  the student's function it receives is a proxy for the same function in a sandboxed process
  (:class:`course_lib.grading.proxy.StudentProcess`) that holds only the student's code and the
  student release of ``course_lib``. :func:`run_reference` runs the instructor's solution here,
  for the expected verdicts. The scans are a second line of defence: what the student's code can
  reach is decided by that process, not by what the scans recognise.
"""

from __future__ import annotations

import ast
import builtins
import contextlib
import importlib
import io
import multiprocessing as mp
import os
import re
import shutil
import sys
import traceback
import types
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from course_lib.grading.release import python_source, resolve_import

__all__ = [
    "Extracted",
    "extract_exercise",
    "scan_exercise",
    "scan_notebook",
    "build_hidden_fixtures",
    "HiddenJob",
    "HiddenOutcome",
    "run_hidden",
    "run_check",
    "run_reference",
    "hidden_fixtures",
]

#: Modules exercise code may not import (they reach the interpreter, the files or the checks).
FORBIDDEN_MODULES = {
    "importlib", "gc", "inspect", "builtins", "ctypes", "sys", "subprocess", "signal", "pickle", "marshal",
    "types", "code", "codeop", "runpy", "multiprocessing", "threading", "os", "glob", "pathlib", "shutil",
    "tempfile", "io", "dill", "cloudpickle", "socket", "pty", "atexit", "faulthandler", "trace", "linecache",
}
#: Built-ins exercise code may not call.
FORBIDDEN_CALLS = {"exec", "eval", "compile", "__import__", "globals", "locals", "vars", "setattr", "delattr",
                   "open", "breakpoint", "input", "exit", "quit"}
#: Dunder attributes that are fine in exercise code (classes, operators).
ALLOWED_DUNDERS = {"__init__", "__call__", "__len__", "__getitem__", "__setitem__", "__repr__", "__str__",
                   "__iter__", "__next__", "__enter__", "__exit__", "__name__", "__eq__", "__hash__",
                   "__post_init__", "__contains__", "__add__", "__mul__", "__matmul__", "__neg__", "__sub__"}
#: Special methods exercise code may define (others, e.g. __eq__ or __array_ufunc__, could fool comparisons).
ALLOWED_METHOD_DUNDERS = {"__init__", "__call__", "__repr__", "__str__", "__len__", "__iter__", "__next__",
                          "__getitem__", "__post_init__", "__enter__", "__exit__"}
#: Names of the check machinery a notebook must not import or rebind.
CHECK_INTERNALS = {"Check", "CheckResult", "RESULTS", "FAILED", "load_fixture", "fixture_builder", "core",
                   "build_fixtures", "PASS", "FAIL"}


# ---------------------------------------------------------------------------------------------
# Extraction
# ---------------------------------------------------------------------------------------------


@dataclass
class Extracted:
    """The code of one exercise as cut out of a notebook."""

    name: str
    code: str  # imports + helpers + the def, in notebook order
    tree: ast.Module
    def_cell: int  # cell index of the def used
    problems: list[str] = field(default_factory=list)  # e.g. names the grader could not find


def _bound_names(node: ast.AST) -> list[str]:
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        return [node.name]
    if isinstance(node, (ast.Import, ast.ImportFrom)):
        return [(a.asname or a.name).split(".")[0] for a in node.names if a.name != "*"]
    targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(node, ast.AnnAssign) else []
    out = []
    for t in targets:
        for n in ast.walk(t):
            if isinstance(n, ast.Name):
                out.append(n.id)
    return out


def _local_names(node: ast.AST) -> set[str]:
    """Names bound inside a def or class (arguments, assignments, imports, nested defs, loop targets)."""
    out = set()
    for n in ast.walk(node):
        if n is node:
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                out |= _arg_names(n.args)
            continue
        if isinstance(n, ast.Name) and isinstance(n.ctx, (ast.Store, ast.Del)):
            out.add(n.id)
        elif isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            out.add(n.name)
            if not isinstance(n, ast.ClassDef):
                out |= _arg_names(n.args)
        elif isinstance(n, ast.Lambda):
            out |= _arg_names(n.args)
        elif isinstance(n, (ast.Import, ast.ImportFrom)):
            out |= {(a.asname or a.name).split(".")[0] for a in n.names}
        elif isinstance(n, ast.ExceptHandler) and n.name:
            out.add(n.name)
    return out


def _arg_names(a: ast.arguments) -> set[str]:
    return {x.arg for x in a.posonlyargs + a.args + a.kwonlyargs + [a.vararg, a.kwarg] if x is not None}


def _used_names(node: ast.AST) -> set[str]:
    """The free names of a top-level statement: what it needs from the notebook's globals."""
    loads = {n.id for n in ast.walk(node) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Load)}
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        outer = set()  # decorators, defaults, bases: evaluated in the notebook's scope
        exprs = list(getattr(node, "decorator_list", [])) + list(getattr(node, "bases", []))
        if not isinstance(node, ast.ClassDef):
            exprs += [d for d in node.args.defaults + node.args.kw_defaults if d is not None]
        for e in exprs:
            outer |= {n.id for n in ast.walk(e) if isinstance(n, ast.Name)}
        return (loads - _local_names(node)) | outer
    return loads


def _segment(src: str, node: ast.AST) -> str:
    lines = src.splitlines()
    start = min([node.lineno] + [d.lineno for d in getattr(node, "decorator_list", [])]) - 1
    return "\n".join(lines[start:node.end_lineno])


def code_cells(nb) -> list[tuple[int, str, ast.Module | None]]:
    """``[(cell index, python source, tree or None if it does not parse)]`` of the code cells."""
    out = []
    for i, cell in enumerate(nb.cells):
        if cell.cell_type != "code":
            continue
        src = python_source(cell.source)
        try:
            tree = ast.parse(src)
        except SyntaxError:
            tree = None
        out.append((i, src, tree))
    return out


def extract_exercise(nb, name: str, before_cell: int) -> Extracted | None:
    """Cut exercise ``name`` out of a notebook: its last top-level def before cell ``before_cell``, with what it needs.

    Returns None when no cell before ``before_cell`` defines ``name`` at top level.
    """
    stmts: list[tuple[int, str, ast.AST]] = []  # (cell, source, node) in notebook order
    syntax_errors = []
    for i, src, tree in code_cells(nb):
        if i >= before_cell:
            break
        if tree is None:
            syntax_errors.append(i)
            continue
        for node in tree.body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef, ast.Import, ast.ImportFrom,
                                 ast.Assign, ast.AnnAssign)):
                stmts.append((i, src, node))
    last: dict[str, int] = {}
    for k, (_, _, node) in enumerate(stmts):
        for n in _bound_names(node):
            last[n] = k
    if name not in last or not isinstance(stmts[last[name]][2], (ast.FunctionDef, ast.ClassDef,
                                                                    ast.AsyncFunctionDef)):
        return None
    need, todo, missing = set(), [last[name]], set()
    while todo:
        k = todo.pop()
        if k in need:
            continue
        need.add(k)
        node = stmts[k][2]
        for n in sorted(_used_names(node)):
            if n in last and last[n] != k:
                todo.append(last[n])
            elif n not in last and not hasattr(builtins, n):
                missing.add(n)
    parts = [_segment(stmts[k][1], stmts[k][2]) for k in sorted(need)]
    code = "\n\n".join(parts) + "\n"
    ex = Extracted(name, code, ast.parse(code), stmts[last[name]][0])
    # names bound inside functions (locals, comprehension variables) are not "missing"
    local = {n.id for n in ast.walk(ex.tree) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store)}
    local |= {a.arg for n in ast.walk(ex.tree) if isinstance(n, ast.arguments)
              for a in n.args + n.kwonlyargs + n.posonlyargs + ([n.vararg] if n.vararg else [])
              + ([n.kwarg] if n.kwarg else [])}
    local |= {n.name for n in ast.walk(ex.tree) if isinstance(n, (ast.FunctionDef, ast.ClassDef))}
    local |= {(a.asname or a.name).split(".")[0] for n in ast.walk(ex.tree) if isinstance(n, (ast.Import, ast.ImportFrom))
              for a in n.names}
    missing -= local
    missing -= {"__class__"}
    if missing:
        ex.problems.append("uses notebook names that no top-level def, import or assignment before its check cell "
                           f"defines: {', '.join(sorted(missing))} (the grader runs the function on its own)")
    return ex


# ---------------------------------------------------------------------------------------------
# Scans
# ---------------------------------------------------------------------------------------------


def scan_exercise(tree: ast.Module, reference: str | None, omitted: set[str]) -> list[str]:
    """Reasons why this exercise code gets no credit (empty list: nothing found).

    Args:
        tree: the extracted code.
        reference: ``"module:attribute"`` of the graded exercise's reference solution, or None.
        omitted: course_lib modules the student kit leaves out (reference solutions).
    """
    found: list[str] = []
    ref_mod, ref_attr = reference.split(":") if reference else (None, None)
    aliases: dict[str, str] = {}  # local name -> module
    for node in ast.walk(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            for mod, attr in resolve_import(node):
                top = mod.split(".")[0]
                if top in FORBIDDEN_MODULES:
                    found.append(f"imports {mod} (line {node.lineno}): exercise code may not reach the interpreter, "
                                 "files or other processes")
                if mod.startswith("course_lib.grading") or mod == "course_lib" and attr == "grading":
                    found.append(f"imports the check machinery {mod} (line {node.lineno})")
                if mod in omitted:
                    found.append(f"imports {mod} (line {node.lineno}), the instructor's reference solution, which is "
                                 "not part of the student kit")
                if ref_mod and mod == ref_mod and attr in (ref_attr, None, "*"):
                    if attr == ref_attr or attr == "*":
                        found.append(f"calls the reference solution {mod}.{ref_attr} (line {node.lineno})")
                for a in node.names:
                    aliases[(a.asname or a.name).split(".")[0]] = mod if attr is None else f"{mod}.{attr}"
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in FORBIDDEN_CALLS:
            found.append(f"calls {node.func.id}() (line {node.lineno}), which exercise code may not use")
        elif isinstance(node, ast.Name) and node.id in FORBIDDEN_CALLS | {"__builtins__"}:
            found.append(f"uses {node.id} (line {node.lineno}), which exercise code may not use")
        elif isinstance(node, ast.Attribute):
            if re.fullmatch(r"__\w+__", node.attr) and node.attr not in ALLOWED_DUNDERS:
                found.append(f"uses the attribute {node.attr} (line {node.lineno}), which exercise code may not use")
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.ctx, (ast.Store, ast.Del)):
            root = node.value
            while isinstance(root, ast.Attribute):
                root = root.value
            if isinstance(root, ast.Name) and root.id in aliases:
                found.append(f"assigns to {ast.unparse(node)} (line {node.lineno}): changing a library (monkeypatching) "
                             "is not allowed in exercise code")
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and re.fullmatch(r"__\w+__", node.name) \
                and node.name not in ALLOWED_METHOD_DUNDERS:
            found.append(f"defines the special method {node.name} (line {node.lineno}), which could change how the "
                         "checks compare results")
    if ref_mod:
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and node.attr == ref_attr and isinstance(node.value, ast.Name) \
                    and aliases.get(node.value.id) == ref_mod:
                found.append(f"calls the reference solution {ref_mod}.{ref_attr} (line {node.lineno})")
    return sorted(set(found))


def scan_notebook(nb, intact_check_cells: set[int], check_names: set[str],
                  verdicts: list[str] = ()) -> list[tuple[int, str]]:
    """``[(cell, reason)]``: code that tampers with the checks, anywhere in the notebook.

    Args:
        nb: the submitted notebook.
        intact_check_cells: indices of check cells identical to the reference (not scanned).
        check_names: the check functions the notebook's check cells call.
        verdicts: the reference verdicts of the notebook's check cells; a string in the code that
            holds one of their lines (or "checks passed") counts as a verdict printed by hand.
    """
    verdict_lines = {ln.strip() for v in verdicts for ln in v.splitlines() if "✔" in ln or "✘" in ln}
    found: list[tuple[int, str]] = []
    for i, src, tree in code_cells(nb):
        if i in intact_check_cells:
            continue
        if tree is None:
            continue
        grading_aliases = set()
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for mod, attr in resolve_import(node):
                    if not mod.startswith("course_lib.grading") and not (mod == "course_lib" and attr == "grading"):
                        continue
                    if isinstance(node, ast.Import) or attr is None or attr == "grading":
                        found.append((i, f"imports the check module {mod} itself"))
                        grading_aliases |= {(a.asname or a.name).split(".")[0] for a in node.names}
                    elif attr in CHECK_INTERNALS or mod.endswith(".core"):
                        found.append((i, f"imports {attr} from the check machinery"))
                    elif attr.startswith("check_") and (attr not in check_names):
                        pass
            targets = []
            if isinstance(node, (ast.Assign, ast.AugAssign, ast.AnnAssign)):
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and \
                    node.name in check_names | {"print"}:
                found.append((i, f"redefines {node.name}"))
            protected = check_names | {"print"}
            # any other binding of a check's name: for / with / except targets, :=, del, and import aliases
            if isinstance(node, ast.Name) and isinstance(node.ctx, (ast.Store, ast.Del)) and node.id in protected:
                found.append((i, f"rebinds {node.id}"))
            elif isinstance(node, ast.ExceptHandler) and node.name in protected:
                found.append((i, f"rebinds {node.name}"))
            elif isinstance(node, (ast.Import, ast.ImportFrom)):
                for a in node.names:
                    bound = (a.asname or a.name).split(".")[0]
                    legit = (isinstance(node, ast.ImportFrom) and (node.module or "").startswith("course_lib.grading")
                             and a.asname in (None, a.name) and a.name in check_names)
                    if bound in protected and not legit:
                        found.append((i, f"rebinds {bound} (by an import alias)"))
            for t in targets:
                for n in ast.walk(t):
                    if isinstance(n, ast.Attribute) and isinstance(n.ctx, ast.Store):
                        root = n.value
                        while isinstance(root, ast.Attribute):
                            root = root.value
                        if isinstance(root, ast.Name) and (root.id in check_names | grading_aliases | CHECK_INTERNALS
                                                           | {"builtins", "sys"}):
                            found.append((i, f"assigns to {ast.unparse(n)}"))
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in {"setattr", "delattr"}:
                found.append((i, f"calls {node.func.id}()"))
            if isinstance(node, ast.Attribute) and node.attr in {"__code__", "__globals__", "modules"} and \
                    not (node.attr == "modules" and not (isinstance(node.value, ast.Name) and node.value.id == "sys")):
                found.append((i, f"uses {ast.unparse(node)}"))
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and (
                    "checks passed" in node.value or any(ln.strip() in verdict_lines for ln in node.value.splitlines())):
                found.append((i, "prints a check verdict by hand"))
    return sorted(set(found))


# ---------------------------------------------------------------------------------------------
# Hidden fixtures
# ---------------------------------------------------------------------------------------------

#: Seeds the check functions reuse when they call the student's function (kept unsalted).
KEPT_SEEDS = {0}


def _salted_rng_factory(salt: int):
    original = np.random.default_rng

    def default_rng(seed=None):
        if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool) and int(seed) not in KEPT_SEEDS:
            return original(np.random.SeedSequence([int(salt) % 2**63, int(seed)]))
        return original(seed)

    return original, default_rng


def _build_hidden(out_dir: str, check_modules: list[str], salt: int) -> dict:
    from course_lib.grading import core

    single_thread_math()
    built = {}
    original, salted = _salted_rng_factory(salt)
    for mod_name in check_modules:
        mod = importlib.import_module(mod_name)
        names = [mod.FIXTURE] if isinstance(getattr(mod, "FIXTURE", None), str) else []
        for name in names:
            np.random.default_rng = salted
            try:
                arrays = core._BUILDERS[name]()
            finally:
                np.random.default_rng = original
            np.savez_compressed(Path(out_dir) / f"{name}.npz", **{k: np.asarray(v) for k, v in arrays.items()})
            built[name] = sorted(arrays)
    return built


#: Hidden fixtures held in the grader's memory (folder -> name -> arrays); forked runs read them from here.
_MEMORY: dict[str, dict[str, dict[str, np.ndarray]]] = {}


def hold_in_memory(fixtures_dir: Path) -> None:
    """Load every fixture of ``fixtures_dir`` into this process, for the forked runs to use."""
    held = {}
    for p in sorted(Path(fixtures_dir).glob("*.npz")):
        with np.load(p, allow_pickle=False) as z:
            held[p.stem] = {k: z[k] for k in z.files}
    _MEMORY[str(fixtures_dir)] = held


def build_hidden_fixtures(out_dir: Path, check_modules: list[str], salt: int, timeout: float = 600) -> dict:
    """Write the hidden fixtures of ``check_modules`` into ``out_dir`` (public fixtures copied first).

    Runs in a forked process (the reference library builds them; torch stays out of this process).
    """
    from course_lib.paths import FIXTURES_DIR

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for p in sorted(Path(FIXTURES_DIR).glob("*.npz")):
        shutil.copyfile(p, out_dir / p.name)
    res = _in_child(_build_hidden, (str(out_dir), sorted(set(check_modules)), int(salt)), timeout)
    if "error" in res or "value" not in res:
        raise RuntimeError(f"building the hidden cases failed: {res.get('error', res)}")
    hold_in_memory(out_dir)
    return res["value"]


# ---------------------------------------------------------------------------------------------
# Running one exercise
# ---------------------------------------------------------------------------------------------


@dataclass
class HiddenJob:
    name: str  # the exercise
    code: str  # the extracted code
    check_module: str
    check_function: str
    fixtures_dir: str
    reference: str | None = None  # "module:attr" of the graded exercise's reference
    allow_reference: bool = False  # the instructor's self-test
    submission: str | None = None  # the student's folder (its copy is the working directory)


@dataclass
class HiddenOutcome:
    status: str  # "ok", "timeout", "exit", "error"
    lines: list[str] = field(default_factory=list)  # the verdict lines ("  ✔ ..." / "  ✘ ...")
    message: str = ""
    seconds: float = 0.0
    result: object = None  # the CheckResult of the hidden checks (computed in the grader's process)
    sandbox: dict = field(default_factory=dict)  # what the student's process was confined by

    @property
    def passing(self) -> list[str]:
        return [ln.strip()[2:] for ln in self.lines if ln.strip().startswith("✔")]

    @property
    def failing(self) -> list[str]:
        return [ln.strip()[2:] for ln in self.lines if ln.strip().startswith("✘")]


@contextlib.contextmanager
def hidden_fixtures(fixtures_dir: str):
    """Within the block, the check modules of this process read the hidden cases (from memory when held)."""
    from course_lib.grading import core

    if fixtures_dir not in _MEMORY:
        hold_in_memory(Path(fixtures_dir))
    stored = _MEMORY[fixtures_dir]

    def load_fixture(name: str) -> dict[str, np.ndarray]:
        if name not in stored:
            raise FileNotFoundError(f"fixture {name!r} is not among the hidden cases")
        return {k: v.copy() for k, v in stored[name].items()}

    saved = []
    for m in list(sys.modules.values()):
        if getattr(m, "__name__", "").startswith("course_lib.grading") and hasattr(m, "load_fixture"):
            saved.append((m, m.load_fixture))
            m.load_fixture = load_fixture
    try:
        yield
    finally:
        for m, fn in saved:
            m.load_fixture = fn


def run_check(check_module: str, check_function: str, fixtures_dir: str, obj) -> tuple[object, str]:
    """Run a check function in this process on the hidden cases; ``(CheckResult or None, printed text)``."""
    from course_lib.grading import core

    check_fn = getattr(importlib.import_module(check_module), check_function)
    saved = dict(core.RESULTS)
    core.RESULTS.clear()
    out = io.StringIO()
    try:
        with hidden_fixtures(fixtures_dir), contextlib.redirect_stdout(out):
            check_fn(obj)
        results = list(core.RESULTS.values())
    finally:
        core.RESULTS.clear()
        core.RESULTS.update(saved)
    return (results[-1] if results else None), out.getvalue()


def run_reference(job: HiddenJob) -> HiddenOutcome:
    """The instructor's solution on the hidden cases, in the grader's own process (the calibration)."""
    import time

    t0 = time.perf_counter()
    module = types.ModuleType("__reference__")
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            exec(compile(job.code, "<instructor notebook>", "exec"), module.__dict__)  # noqa: S102 - the instructor's
        result, _ = run_check(job.check_module, job.check_function, job.fixtures_dir, module.__dict__.get(job.name))
    except Exception as exc:  # noqa: BLE001
        return HiddenOutcome("error", message=f"the reference run failed: {type(exc).__name__}: {exc}",
                             seconds=time.perf_counter() - t0)
    lines = list(result.lines) if result is not None else []
    return HiddenOutcome("ok" if result is not None else "error", lines=lines, result=result,
                         message="" if result is not None else "the check recorded no verdict",
                         seconds=time.perf_counter() - t0)


def run_hidden(job: HiddenJob, timeout: float = 60.0, isolation=None) -> HiddenOutcome:
    """Run the hidden checks of one exercise: the check here, the student's function in its own process.

    Args:
        job: the exercise, its extracted code and its check.
        timeout: wall-clock seconds for everything the student's process does for this exercise.
        isolation: the grading run's :class:`course_lib.grading.proxy.Isolation`.
    """
    import time

    from course_lib.grading.proxy import RemoteFunction, StudentProcess

    t0 = time.perf_counter()
    torch = job.check_module.startswith("course_lib.grading.nerf")
    with StudentProcess(isolation, job.code, job.name, job.submission, timeout, torch=torch) as proc:
        hello = proc.hello
        if proc.ended:
            return HiddenOutcome("timeout" if proc.event == "timeout" else "exit", message=proc.ended,
                                 seconds=time.perf_counter() - t0)
        if not hello.get("ok"):
            return HiddenOutcome("error", message=f"defining {job.name} failed: {hello.get('type')}: "
                                 f"{hello.get('message')}{hello.get('where', '')}", seconds=time.perf_counter() - t0,
                                 sandbox=hello.get("sandbox", {}))
        if not hello.get("found"):
            return HiddenOutcome("error", message=f"the exercise code does not define {job.name}",
                                 seconds=time.perf_counter() - t0, sandbox=hello.get("sandbox", {}))
        try:
            result, _ = run_check(job.check_module, job.check_function, job.fixtures_dir, RemoteFunction(proc, job.name))
        except Exception as exc:  # noqa: BLE001 - a check that cannot finish is the grader's problem, reported
            return HiddenOutcome("error", message=f"the grader failed: {type(exc).__name__}: {exc}",
                                 seconds=time.perf_counter() - t0, sandbox=hello.get("sandbox", {}))
        dt = time.perf_counter() - t0
        if proc.ended:
            status = "timeout" if proc.event == "timeout" else "exit"
            return HiddenOutcome(status, lines=list(result.lines) if result else [], message=proc.ended, seconds=dt,
                                 result=result, sandbox=hello.get("sandbox", {}))
    if result is None:
        return HiddenOutcome("error", message="the check recorded no verdict", seconds=dt)
    return HiddenOutcome("ok", lines=list(result.lines), result=result, seconds=dt, sandbox=hello.get("sandbox", {}))


def single_thread_math() -> None:
    """One thread for OpenBLAS (numpy, scipy) and torch in this process: the same numbers on every run."""
    from course_lib.threads import set_blas_threads

    set_blas_threads(1)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)


def _child_main(conn, fn, args):
    try:
        value = fn(*args)
        conn.send({"value": value})
    except BaseException as exc:  # noqa: BLE001
        try:
            conn.send({"error": f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=3)}"})
        except Exception:  # noqa: BLE001
            pass
    finally:
        conn.close()
        os._exit(0)


def _in_child(fn, args, timeout: float) -> dict:
    """Run ``fn(*args)`` in a forked process; ``{"value": ...}``, ``{"error": ...}`` or ``{"timeout": True}``."""
    ctx = mp.get_context("fork")
    parent, child = ctx.Pipe(duplex=False)
    p = ctx.Process(target=_child_main, args=(child, fn, args), daemon=True)
    p.start()
    child.close()
    try:
        if parent.poll(timeout):
            try:
                return parent.recv()
            except EOFError:
                return {"crashed": True}
        return {"timeout": True}
    finally:
        if p.is_alive():
            p.kill()
        p.join(5)
        parent.close()

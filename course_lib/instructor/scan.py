"""Scans of submitted code: a second line of defence behind the sandbox.

What the student's code can reach is decided by the process it runs in
(:mod:`course_lib.instructor.sandbox`), not by what these scans recognise. They flag what gets no
credit however it runs:

* :func:`scan_exercise`: exercise code that imports the reference solutions (modules the student
  kit leaves out, or the graded exercise's own reference), the check machinery or the instructor
  package, or uses dynamic tricks that could reach them (``exec``, ``__import__``, ``importlib``,
  ``sys``, ``gc``, ``inspect``, dunder attributes such as ``__globals__``...);
* :func:`scan_notebook`: a notebook that patches or rebinds the checks, prints verdicts by hand,
  swaps ``print`` or the interpreter's output (under any name: ``import sys as s``), or runs code the
  grader cannot read (``%run``, ``%load``, ``%%capture``, ``!cmd``, ``get_ipython()``): it reads the code
  IPython runs for each cell (:func:`as_ipython_runs`), not the cell with its magics left out.
"""

from __future__ import annotations

import ast
import re

from course_lib.exercises import EXERCISES
from course_lib.instructor.notebooks import resolve_import

__all__ = ["scan_exercise", "scan_notebook", "as_ipython_runs", "FORBIDDEN_MODULES", "FORBIDDEN_CALLS"]

#: Modules exercise code may not import (they reach the interpreter, the files or the checks).
FORBIDDEN_MODULES = {
    "importlib", "gc", "inspect", "builtins", "ctypes", "sys", "subprocess", "signal", "pickle", "marshal",
    "types", "code", "codeop", "runpy", "multiprocessing", "threading", "os", "glob", "pathlib", "shutil",
    "tempfile", "io", "dill", "cloudpickle", "socket", "pty", "atexit", "faulthandler", "trace", "linecache",
    # modules that resolve a name given as a string (pkgutil.resolve_name, pydoc.locate, ...)
    "pkgutil", "pydoc", "imp", "zipimport", "modulefinder", "site", "sysconfig",
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
CHECK_INTERNALS = {"Check", "CheckResult", "RESULTS", "FAILED", "load_fixture", "core",
                   "build_fixtures", "PASS", "FAIL"}


#: Sub-packages of course_lib that hold the check machinery or the instructor's tools.
CHECK_PACKAGES = ("checks", "instructor")


def _is_check_module(mod: str, attr: str | None) -> bool:
    """True for an import of the check machinery or the instructor package (``course_lib.checks...``)."""
    return any(mod == f"course_lib.{p}" or mod.startswith(f"course_lib.{p}.") or (mod == "course_lib" and attr == p)
               for p in CHECK_PACKAGES)


def scan_exercise(tree: ast.Module, reference: str | None, omitted: set[str]) -> list[str]:
    """Reasons why this exercise code gets no credit (empty list: nothing found).

    Args:
        tree: the extracted code.
        reference: ``"module:attribute"`` of the graded exercise's reference solution, or None.
        omitted: course_lib modules the student kit leaves out (reference solutions).
    """
    found: list[str] = []
    ref_mod, ref_attr = reference.split(":") if reference else (None, None)
    engines = EXERCISES[ref_attr].engines if ref_attr in EXERCISES else ()
    aliases: dict[str, str] = {}  # local name -> module
    for node in ast.walk(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            for mod, attr in resolve_import(node):
                top = mod.split(".")[0]
                if top in FORBIDDEN_MODULES:
                    found.append(f"imports {mod} (line {node.lineno}): exercise code may not reach the interpreter, "
                                 "files or other processes")
                if _is_check_module(mod, attr):
                    found.append(f"imports the check machinery {mod if attr is None else mod + '.' + attr} "
                                 f"(line {node.lineno})")
                for engine in engines:
                    if f"{mod}.{attr}" == engine or (attr is None and engine.startswith(mod + ".")
                                                     and isinstance(node, ast.ImportFrom)):
                        found.append(f"imports {engine} (line {node.lineno}), the kit's engine that computes "
                                     f"{ref_attr} with your own functions: write {ref_attr} yourself")
                if mod in omitted:
                    found.append(f"imports {mod} (line {node.lineno}), the instructor's reference solution, which is "
                                 "not part of the student kit")
                if ref_mod and mod == ref_mod and attr in (ref_attr, None, "*"):
                    if attr == ref_attr or attr == "*":
                        found.append(f"calls the reference solution {mod}.{ref_attr} (line {node.lineno})")
                for a in node.names:
                    if isinstance(node, ast.Import) and not a.asname:  # `import a.b.c` binds the package a
                        aliases[a.name.split(".")[0]] = a.name.split(".")[0]
                    else:
                        aliases[a.asname or a.name] = mod if attr is None else f"{mod}.{attr}"
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
    found += _reached_by_name(tree, aliases, f"{ref_mod}.{ref_attr}" if ref_mod else None, omitted)
    for node in ast.walk(tree):  # an engine built on the graded exercise, reached by an attribute chain
        path = _dotted(node, aliases) if isinstance(node, ast.Attribute) else None
        if path in engines:
            found.append(f"calls {path} (line {node.lineno}), the kit's engine that computes {ref_attr} with your "
                         f"own functions: write {ref_attr} yourself")
    return sorted(set(found))


def _dotted(node: ast.AST, aliases: dict[str, str]) -> str | None:
    """``course_lib.nerf.train.psnr`` for ``train.psnr`` when ``train`` is an alias of ``course_lib.nerf.train``."""
    attrs = []
    while isinstance(node, ast.Attribute):
        attrs.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name) or node.id not in aliases:
        return None
    return ".".join([aliases[node.id]] + attrs[::-1])


def _reached_by_name(tree: ast.Module, aliases: dict[str, str], reference: str | None, omitted: set[str]) -> list[str]:
    """Routes to the reference by attribute chains and ``getattr`` on the kit's modules.

    Any chain of attributes from an imported module (``course_lib.nerf.train.psnr``) is resolved
    through the import aliases; ``getattr`` on a kit module counts too. Names built from strings at
    run time are not chased here: what stops them is the design (the student's process holds the
    student kit only, and the kit holds no implementation of any exercise; see
    tests/instructor/test_release.py).
    """
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute):
            path = _dotted(node, aliases)
            if path and reference and (path == reference or path.startswith(reference + ".")):
                found.append(f"calls the reference solution {reference} (line {node.lineno})")
            elif path and any(path == m or path.startswith(m + ".") for m in omitted):
                found.append(f"reaches {path} (line {node.lineno}), the instructor's reference solution, which is "
                             "not part of the student kit")
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("getattr", "hasattr") \
                and node.args and (_dotted(node.args[0], aliases) or "").startswith("course_lib"):
            found.append(f"uses {node.func.id}() on the kit's module {_dotted(node.args[0], aliases)} (line "
                         f"{node.lineno}): call the kit's functions by their names")
    return found


#: Modules whose attributes a notebook may not assign to (the interpreter's output, the kernel), under any name.
INTERPRETER_MODULES = {"sys", "builtins", "IPython", "ipykernel"}
#: IPython commands a notebook may use (``%matplotlib inline``, ``%time``...): the code of a timing magic is scanned
#: like the cell's own; every other magic, shell command or call of the shell (``%run``, ``%load``, ``%%capture``,
#: ``!cmd``, ``get_ipython()...``) runs code the grader cannot read before nbval, and is named.
ALLOWED_MAGICS = {"matplotlib", "time", "timeit", "pinfo", "pinfo2", "autoreload"}
_TIMING = {"time", "timeit"}


def as_ipython_runs(source: str) -> tuple[list[ast.Module], list[str]]:
    """The code IPython runs for a cell (its own transformation of magics, shell lines and escapes), as trees to scan
    (the cell's, and the code inside its timing magics), and the reasons against its other IPython commands.

    A cell that does not parse after IPython's transformation does not run under nbval either (a syntax error)."""
    from IPython.core.inputtransformer2 import TransformerManager

    try:
        tree = ast.parse(TransformerManager().transform_cell(source))
    except (SyntaxError, ValueError, RecursionError, MemoryError, IndexError):
        return [], []
    trees, reasons = [tree], []
    for node in ast.walk(tree):
        if isinstance(node, ast.Name) and node.id == "get_ipython":
            call = _shell_call(tree, node)
            if call is None:
                reasons.append("uses get_ipython(), the shell that runs code the grader cannot scan")
                continue
            method, args = call
            name = args[0] if args else None
            body = args[-1] if method == "run_cell_magic" else (args[1] if len(args) > 1 else "")
            if name in _TIMING:
                body = re.sub(r"^(\s*-[nrp]\s*\d+|\s*-[tcqo](?=\s))*\s*", "", body)  # %timeit -n 3 -r 2 code
            allowed = name in ALLOWED_MAGICS or f"{name} {body}".strip() in ("load_ext autoreload",) or \
                (name == "config" and re.fullmatch(r"InlineBackend\.\w+\s*=\s*[\w'\".{}:, ]*", body or ""))
            if method in ("run_line_magic", "run_cell_magic") and allowed and \
                    not (name in _TIMING and body.lstrip().startswith("-")) and \
                    not (method == "run_cell_magic" and name not in _TIMING):
                if name in _TIMING:
                    more, why = as_ipython_runs(body)
                    trees += more
                    reasons += why
                continue
            what = {"system": "!", "getoutput": "!"}.get(method, "%%" if method == "run_cell_magic" else "%")
            reasons.append(f"runs the IPython command {what}{name if what != '!' else ''}"
                           f"{'' if what != '!' else ' (a shell command)'}, which runs code the grader cannot scan; "
                           "write the code in the notebook's cells")
    return trees, sorted(set(reasons))


def _shell_call(tree: ast.Module, name: ast.Name) -> tuple[str, list[str]] | None:
    """``(method, constant args)`` when ``name`` is the ``get_ipython`` of ``get_ipython().method("...", ...)``."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and \
                isinstance(node.func.value, ast.Call) and node.func.value.func is name and not node.func.value.args:
            args = [a.value for a in node.args if isinstance(a, ast.Constant) and isinstance(a.value, str)]
            if len(args) == len(node.args) and not node.keywords:
                return node.func.attr, args
            return None
    return None


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
    cells = []  # (cell, the code IPython runs for it), the code of its timing magics included
    for i, cell in enumerate(nb.cells):
        if cell.cell_type != "code" or i in intact_check_cells:
            continue
        trees, reasons = as_ipython_runs(cell.source)
        found += [(i, r) for r in reasons]
        cells += [(i, t) for t in trees]
    interpreter = {(a.asname or a.name).split(".")[0] for _, t in cells for node in ast.walk(t)
                   if isinstance(node, (ast.Import, ast.ImportFrom)) for a in node.names
                   if ((node.module or a.name) if isinstance(node, ast.ImportFrom) else a.name).split(".")[0]
                   in INTERPRETER_MODULES}  # names bound to sys, builtins, IPython... (import sys as s)
    for i, tree in cells:
        grading_aliases = set()
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for mod, attr in resolve_import(node):
                    if not _is_check_module(mod, attr):
                        continue
                    if isinstance(node, ast.Import) or attr is None or attr in CHECK_PACKAGES:
                        found.append((i, f"imports the check module {mod} itself"))
                        grading_aliases |= {(a.asname or a.name).split(".")[0] for a in node.names}
                    elif attr in CHECK_INTERNALS or mod.endswith(".core"):
                        found.append((i, f"imports {attr} from the check machinery"))
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
                    legit = (isinstance(node, ast.ImportFrom) and (node.module or "").startswith("course_lib.checks.")
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
                                                           | INTERPRETER_MODULES | interpreter):
                            found.append((i, f"assigns to {ast.unparse(n)}"))
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in {"setattr", "delattr"}:
                found.append((i, f"calls {node.func.id}()"))
            if isinstance(node, ast.Attribute) and node.attr in {"__code__", "__globals__", "modules"} and \
                    not (node.attr == "modules" and not (isinstance(node.value, ast.Name)
                                                         and node.value.id in interpreter | {"sys"})):
                found.append((i, f"uses {ast.unparse(node)}"))
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and (
                    "checks passed" in node.value or any(ln.strip() in verdict_lines for ln in node.value.splitlines())):
                found.append((i, "prints a check verdict by hand"))
    return sorted(set(found))



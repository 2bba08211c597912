"""The scan of an exercise's code: a second line of defence behind the sandbox.

What the student's code can reach is decided by the process it runs in
(:mod:`course_lib.instructor.sandbox`), not by what this scan recognises. :func:`scan_exercise` flags
what gets no credit however it runs: exercise code that imports the reference solutions (modules the
student kit leaves out, or the graded exercise's own reference), the check machinery or the instructor
package, or uses dynamic tricks that could reach them (``exec``, ``__import__``, ``importlib``, ``sys``,
``gc``, ``inspect``, dunder attributes such as ``__globals__``...).

The rest of a notebook is not scanned: no verdict is read from what it prints. The hidden checks run in
the grader on the exercise's code alone, and the check cells' verdicts of the nbval share are computed by
the grader too (:mod:`course_lib.instructor.hidden`), so a notebook that patches the checks, swaps
``print`` or ``sys.stdout``, or runs code through IPython's commands changes no point.
"""

from __future__ import annotations

import ast
import re

from course_lib.exercises import EXERCISES
from course_lib.instructor.notebooks import resolve_import

__all__ = ["scan_exercise", "FORBIDDEN_MODULES", "FORBIDDEN_CALLS"]

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

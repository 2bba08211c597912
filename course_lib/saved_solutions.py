"""A student's own solutions, where the kit needs them: saved when their cell runs, found by later notebooks.

The student kit (``python -m course_lib release``) leaves the reference solutions out. Where the
kit builds on an exercise (the NeRF trainer renders with ``volume_render``, the SfM pipeline
chains notebooks 01-05; :mod:`course_lib.exercises`), it calls a **stand-in**
(:func:`stand_in`) that calls the student's own function instead:

1. the function of that name defined in the running notebook (``__main__``), when there is one;
2. else the **saved solution**: running an exercise's cell in the student kit saves the function,
   with what it needs from the notebook (its imports, helper functions and classes, constants), to
   ``solutions/<name>.py`` beside the notebooks (d2l's ``#@save`` idea, done when the cell runs:
   :func:`install` registers an IPython ``post_run_cell`` hook). Only a cell that itself defines the
   exercise at top level saves it: the kit's own code (a fallback inside ``try``/``except``) never is. Later notebooks, in a fresh kernel,
   under ``pytest`` (nbval) or in the grader, load it from there; nothing is copied by hand;
3. else a ``NotImplementedError`` that names the notebook and the exercise to finish.

Where the saved solutions live: ``$COURSE_LIB_SOLUTIONS`` if set, else ``solutions/`` at the root of
the student kit. The grader sets the variable to a folder of its own, so it decides what stands in
for earlier exercises (for example the references: a file ``<name>.py`` that defines ``<name>``, so
that a mistake is not charged twice), and sets ``COURSE_LIB_SAVE_SOLUTIONS=0`` so that running a
submission's cells saves nothing there. The instructor's kit saves nothing unless the variable is set.

Introduced in ``notebooks/06_nerf_data_and_rays.ipynb`` (and used from notebook 05 on).
"""

from __future__ import annotations

import ast
import builtins
import importlib
import importlib.util
import inspect
import linecache
import os
import symtable
import sys
import types
from pathlib import Path
from typing import Any, Callable

from course_lib.exercise_table import EXERCISES
from course_lib.paths import REPO_ROOT

__all__ = ["stand_in", "find_student_solution", "solutions_dir", "save_solution", "solution_source",
           "load_saved_solution", "is_stub", "install", "STUB_LINE"]

#: The line the release puts where a solution was (:func:`course_lib.instructor.release.stub_source`).
STUB_LINE = 'raise NotImplementedError("your code here")'
#: Where the student kit keeps the saved solutions, relative to its root.
SOLUTIONS_FOLDER = "solutions"
_SAVED_PREFIX = "_course_lib_saved_"


def is_student_kit() -> bool:
    """True in a student kit (it has the release manifest at its root); the instructor's kit is not one."""
    return (REPO_ROOT / "RELEASE_MANIFEST.json").exists()


def solutions_dir() -> Path | None:
    """The folder of the saved solutions: ``$COURSE_LIB_SOLUTIONS``, else ``solutions/`` of a student kit, else None."""
    env = os.environ.get("COURSE_LIB_SOLUTIONS")
    if env:
        return Path(env)
    return REPO_ROOT / SOLUTIONS_FOLDER if is_student_kit() else None


# ---------------------------------------------------------------------------------------------
# Finding the student's function
# ---------------------------------------------------------------------------------------------


def _usable(obj: Any) -> bool:
    return obj is not None and callable(obj) and not getattr(obj, "__kit_stand_in__", False)


def find_student_solution(name: str) -> Any:
    """The student's ``name``: the running notebook's (``__main__``), else the saved one, else None.

    Raises:
        RuntimeError: a saved solution exists but does not load (the message says which file and why).
    """
    main = sys.modules.get("__main__")
    mine = getattr(main, name, None) if main is not None else None
    if _usable(mine):
        return mine
    return load_saved_solution(name)


def stand_in(name: str, notebook: str, module: str | None = None) -> Callable:
    """A function that forwards to the student's ``name`` (:func:`find_student_solution`).

    Args:
        name: the exercise's name (a function or class of the notebook).
        notebook: the notebook that teaches it, e.g. ``"08_nerf_rendering_and_training.ipynb"``.
        module: the module the stand-in is an attribute of (so that it can be imported by name).

    Returns:
        A callable with the exercise's name; calling it calls the student's function. Where there is
        none, or the student's function is still the stub, it raises ``NotImplementedError`` that
        names the notebook and the exercise to finish.
    """

    def forward(*args, **kwargs):
        mine = find_student_solution(name)
        if mine is None:
            where = solutions_dir()
            saved = f" (it saves your function to {where / (name + '.py')}, where the kit finds it)" if where else ""
            raise NotImplementedError(
                f"{name} is an exercise of notebooks/{notebook}, and the kit needs your {name} here. Write it in "
                f"notebooks/{notebook} and run its cell{saved}; then run this cell again."
            )
        try:
            return mine(*args, **kwargs)
        except NotImplementedError as exc:
            raise NotImplementedError(
                f"your {name} (the exercise of notebooks/{notebook}) is not written yet ({exc}): finish it there, "
                "run its cell, then run this cell again"
            ) from exc

    forward.__name__ = forward.__qualname__ = name
    if module:
        forward.__module__ = module
    forward.__kit_stand_in__ = True
    forward.__doc__ = f"Stand-in for the exercise {name} of notebooks/{notebook}: calls your own {name}."
    return forward


# ---------------------------------------------------------------------------------------------
# The source of a solution, with what it needs from the notebook
# ---------------------------------------------------------------------------------------------


def is_stub(obj: Any) -> bool:
    """True for an exercise still as the release wrote it (its body raises the stub's ``NotImplementedError``)."""
    try:
        return STUB_LINE in _definition_source(obj, obj.__name__)
    except (OSError, TypeError, ValueError):
        return False


def _cell_definition(lines: list[str], name: str, lineno: int | None) -> str | None:
    """The top-level ``def``/``class name`` of a cell's source (the one at ``lineno`` if given, else the last)."""
    text = "".join(lines)
    try:
        tree = ast.parse(text)
    except SyntaxError:
        return None
    found = None
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.name == name:
            start = min([node.lineno] + [d.lineno for d in node.decorator_list])
            if lineno is None or start <= lineno <= node.end_lineno:
                found = "".join(text.splitlines(keepends=True)[start - 1:node.end_lineno])
    return found


def _history_definition(name: str) -> str | None:
    """The last cell run in this IPython kernel that defines ``name`` at top level (its definition only)."""
    ipython = sys.modules.get("IPython")
    shell = ipython.get_ipython() if ipython is not None else None
    if shell is None:
        return None
    for cell in reversed(list(shell.user_ns.get("_ih", []))):
        if name in cell:
            src = _cell_definition(cell.splitlines(keepends=True), name, None)
            if src:
                return src
    return None


def _definition_source(obj: Any, name: str) -> str:
    """The source of a function's or class's top-level definition (decorators included).

    Functions are found through their code object (IPython keeps every cell in ``linecache``);
    classes through a method's code object, else through the kernel's input history.
    """
    codes = []
    if isinstance(obj, types.FunctionType):
        codes = [obj.__code__]
    elif isinstance(obj, type):
        for v in vars(obj).values():
            f = getattr(v, "__func__", v)
            if isinstance(f, types.FunctionType) and f.__code__.co_filename != "<string>":  # not made by dataclass
                codes.append(f.__code__)
    for code in codes:
        lines = linecache.getlines(code.co_filename)
        src = _cell_definition(lines, name, code.co_firstlineno) if lines else None
        if src:
            return src
    src = _history_definition(name)
    if src:
        return src
    return inspect.getsource(obj)  # a module with a file (not a notebook)


def _global_names(src: str) -> list[str]:
    """The global names a top-level definition reads (decorators, defaults, bases and bodies), in order."""
    table = symtable.symtable(src, "<solution>", "exec")
    out: list[str] = []

    def walk(t: symtable.SymbolTable) -> None:
        for s in t.get_symbols():
            top = t.get_type() == "module"
            if s.is_referenced() and (top or s.is_global()) and s.get_name() not in out:
                out.append(s.get_name())
        for c in t.get_children():
            walk(c)

    walk(table)
    return out


_CONSTANTS = (int, float, complex, bool, str, bytes, type(None))


def _literal(value: Any, depth: int = 0) -> bool:
    if isinstance(value, _CONSTANTS):
        return True
    if isinstance(value, (tuple, list, set, frozenset)) and depth < 3 and len(value) <= 1000:
        return all(_literal(v, depth + 1) for v in value)
    if isinstance(value, dict) and depth < 3 and len(value) <= 1000:
        return all(_literal(k, depth + 1) and _literal(v, depth + 1) for k, v in value.items())
    return False


def _importable(value: Any) -> tuple[str, str] | None:
    """``(module, qualname)`` where ``value`` can be imported from, or None."""
    mod, qual = getattr(value, "__module__", None), getattr(value, "__qualname__", None)
    if not mod or not qual or mod == "__main__" or "." in qual or "<" in qual:
        return None
    try:
        if getattr(importlib.import_module(mod), qual) is value:
            return mod, qual
    except Exception:  # noqa: BLE001 - any failure means: not importable by name
        return None
    return None


def solution_source(name: str, obj: Any, namespace: dict) -> tuple[str, list[str]]:
    """Python source that defines ``name`` as ``obj`` does, with what it needs from ``namespace``.

    The definition of ``obj`` (a function or class of the notebook) and, for every global name it
    reads: the import of a module or of an importable object (``import torch``, ``from
    scipy.optimize import least_squares``), the definition of a function or class of the notebook
    (recursively), or a constant (numbers, strings, tuples and the like).

    Returns:
        ``(source, problems)``: ``problems`` names what could not be carried (a notebook variable
        that is neither of these, e.g. an array); the source leaves it out.
    """
    imports: list[str] = []
    defs: list[str] = []
    consts: list[str] = []
    problems: list[str] = []
    done: set[str] = set()

    def visit(n: str, value: Any) -> None:
        if n in done:
            return
        done.add(n)
        if isinstance(value, types.ModuleType):
            mod = value.__name__
            imports.append(f"import {mod}" if mod == n else f"import {mod} as {n}")
            return
        where = _importable(value)
        if where is not None:
            mod, qual = where
            imports.append(f"from {mod} import {qual}" + ("" if qual == n else f" as {n}"))
            return
        if isinstance(value, (types.FunctionType, type)) and getattr(value, "__module__", None) == "__main__":
            try:
                src = _definition_source(value, value.__name__)
            except (OSError, TypeError) as exc:
                problems.append(f"{n}: its source is not available ({exc})")
                return
            for dep in _global_names(src):
                if dep == value.__name__ or hasattr(builtins, dep):
                    continue
                if dep in namespace:
                    visit(dep, namespace[dep])
            defs.append(src.rstrip() + "\n" + (f"\n\n{n} = {value.__name__}\n" if value.__name__ != n else ""))
            return
        if _literal(value):
            consts.append(f"{n} = {value!r}")
            return
        problems.append(f"{n} (a {type(value).__name__} of the notebook)")

    visit(name, obj)
    parts = [p for p in ("\n".join(sorted(set(imports), key=imports.index)), "\n".join(consts)) if p]
    return "\n\n\n".join(parts + ["\n\n\n".join(d.rstrip() for d in defs)]) + "\n", problems


# ---------------------------------------------------------------------------------------------
# Saving and loading
# ---------------------------------------------------------------------------------------------


def save_solution(name: str, obj: Any, namespace: dict, folder: Path | None = None) -> Path | None:
    """Save the student's exercise ``name`` (with what it needs) to ``<folder>/<name>.py``; the path, or None.

    Nothing is saved for a stub. Problems (a notebook variable the solution reads that cannot be
    carried) are written into the file as a comment and printed once.
    """
    folder = solutions_dir() if folder is None else Path(folder)
    if folder is None or is_stub(obj):
        return None

    nb = EXERCISES[name].notebook if name in EXERCISES else "a notebook"
    src, problems = solution_source(name, obj, namespace)
    head = [f"# Your {name} (the exercise of notebooks/{nb}), saved by the kit when you ran its cell.",
            "# The kit's trainer, pipeline and later notebooks use it. Change it in the notebook and run the cell",
            "# again; edits here are overwritten."]
    if problems:
        head.append("# Not saved (define it inside the function or the cell): " + "; ".join(problems))
        print(f"note: your {name} was saved to {folder / (name + '.py')}, without: {'; '.join(problems)} -- later "
              "notebooks will miss it; compute it inside the function")
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.py"
    tmp = path.with_suffix(".py.tmp")
    tmp.write_text("\n".join(head) + "\n\n" + src)
    tmp.replace(path)
    return path


_LOADED: dict[str, tuple[tuple, Any]] = {}


def load_saved_solution(name: str) -> Any:
    """The saved ``name`` from :func:`solutions_dir`, or None where there is none (loaded once per file version).

    Raises:
        RuntimeError: the file exists but does not run or does not define ``name``.
    """
    folder = solutions_dir()
    path = folder / f"{name}.py" if folder is not None else None
    if path is None or not path.is_file():
        return None
    st = path.stat()
    key = (str(path), st.st_mtime_ns, st.st_size)
    if name in _LOADED and _LOADED[name][0] == key:
        return _LOADED[name][1]
    mod_name = _SAVED_PREFIX + name
    spec = importlib.util.spec_from_file_location(mod_name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[mod_name] = module  # dataclasses look their module up here
    try:
        spec.loader.exec_module(module)
    except Exception as exc:
        sys.modules.pop(mod_name, None)
        raise RuntimeError(f"your saved {name} ({path}) does not load: {type(exc).__name__}: {exc}. Run its cell "
                           "in its notebook again (that saves it anew)") from exc
    obj = getattr(module, name, None)
    if obj is None:
        raise RuntimeError(f"{path} does not define {name}: run the exercise's cell in its notebook again")
    _LOADED[name] = (key, obj)
    return obj


# ---------------------------------------------------------------------------------------------
# The IPython hook: running an exercise's cell saves it
# ---------------------------------------------------------------------------------------------


def _cell_exercises(shell, raw_cell: str) -> set[str]:
    """The exercises a cell defines itself: its top-level ``def``/``class`` statements with an exercise's name.

    A definition inside an ``if``/``try`` (the kit's own fallbacks, e.g. notebook 02's OpenCV
    ``triangulate_linear`` where the reference is left out), one made by a call, or one imported is not
    the student's exercise cell and is never saved.
    """
    try:
        source = shell.transform_cell(raw_cell) if hasattr(shell, "transform_cell") else raw_cell
        tree = ast.parse(source)
    except (SyntaxError, ValueError, TypeError):
        return set()
    return {node.name for node in tree.body
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.name in EXERCISES}


class _Saver:
    """After every cell: save each exercise the cell itself defines at top level (not the stubs, not the kit's code)."""

    def __init__(self, shell):
        self.shell = shell
        self.seen: dict[str, int] = {}

    def __call__(self, result=None) -> None:
        info = getattr(result, "info", None)
        raw = getattr(info, "raw_cell", None)
        if not isinstance(raw, str):
            return
        ns = self.shell.user_ns
        for name in sorted(_cell_exercises(self.shell, raw)):
            obj = ns.get(name)
            if obj is None or self.seen.get(name) == id(obj):
                continue
            self.seen[name] = id(obj)
            if not isinstance(obj, (types.FunctionType, type)) or getattr(obj, "__module__", None) != "__main__":
                continue
            try:
                save_solution(name, obj, ns)
            except Exception as exc:  # noqa: BLE001 - saving never breaks the student's cell
                print(f"note: the kit could not save your {name} for later notebooks ({type(exc).__name__}: {exc}); "
                      "later notebooks will say it is missing -- run this cell again after fixing what it names")


def install(shell=None) -> bool:
    """Register the saving hook in the running IPython kernel (once); True if it is registered.

    Only in a student kit, or where ``$COURSE_LIB_SOLUTIONS`` is set, and not with
    ``COURSE_LIB_SAVE_SOLUTIONS=0``; a no-op elsewhere (plain Python, the instructor's kit).
    """
    if solutions_dir() is None or os.environ.get("COURSE_LIB_SAVE_SOLUTIONS", "1").lower() in ("0", "false", "no"):
        return False
    if shell is None:
        ipython = sys.modules.get("IPython")
        shell = ipython.get_ipython() if ipython is not None else None
    if shell is None or not hasattr(shell, "events"):
        return False
    if any(isinstance(cb, _Saver) for cb in shell.events.callbacks.get("post_run_cell", [])):
        return True
    shell.events.register("post_run_cell", _Saver(shell))
    return True

"""A student release filled with the honest-student catalogue (``tests/checks/catalogue``): a submission.

Each honest solution is a module-level function (or class) of a catalogue module. Put into a
notebook, it is renamed to its exercise (``eight_point__svd_style`` becomes ``eight_point``) and
brought with the imports and module-level helpers it uses (transitively), as a student would
write them in the exercise cell. Calls of *other* exercises (``ransac_fundamental`` calls
``eight_point``) stay calls: in the notebook they reach the student's own earlier solution.
"""

from __future__ import annotations

import ast
import atexit
import functools
import importlib
import inspect
import shutil
import tempfile
from pathlib import Path

import nbformat

from course_lib.instructor.notebooks import NOTEBOOKS_DIR, kit_specs, python_source
from course_lib.instructor.release import write_release
from tests.checks.catalogue import Honest, collect

__all__ = ["honest_source", "honest_submission", "choose", "exercise_names"]


def exercise_names() -> set[str]:
    return {e.name for s in kit_specs() for e in s.exercises}


def _top_level(tree: ast.Module) -> dict[str, ast.stmt]:
    out: dict[str, ast.stmt] = {}
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            out[node.name] = node
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            for a in node.names:
                out[(a.asname or a.name).split(".")[0]] = node
        elif isinstance(node, ast.Assign):
            for t in node.targets:
                for n in ast.walk(t):
                    if isinstance(n, ast.Name):
                        out[n.id] = node
    return out


def needed_nodes(tree: ast.Module, top: dict, roots: list, exclude: set[str]) -> list:
    """The module-level statements of ``tree`` that ``roots`` use, transitively, in the module's order
    (``top``: :func:`_top_level`; names in ``exclude`` are not followed)."""
    need, todo = [], list(roots)
    while todo:
        node = todo.pop()
        if node in need:
            continue
        need.append(node)
        for n in ast.walk(node):
            if isinstance(n, ast.Name) and n.id in top and n.id not in exclude and top[n.id] is not node:
                todo.append(top[n.id])
    order = {id(n): k for k, n in enumerate(tree.body)}
    return sorted(need, key=lambda n: order[id(n)])


def honest_source(h: Honest) -> str:
    """The code of one honest solution as it goes into its exercise cell (imports, helpers, the def)."""
    module = importlib.import_module(h.fn.__module__)
    tree = ast.parse(inspect.getsource(module))
    top = _top_level(tree)
    others = exercise_names() - {h.exercise}
    root = top[h.fn.__name__]
    parts = []
    for node in needed_nodes(tree, top, [root], others):
        if node is root:
            node = ast.parse(ast.unparse(node)).body[0]
            node.name = h.exercise
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("tests"):
            continue
        parts.append(ast.unparse(node))
    return "\n\n\n".join(parts) + "\n"


def choose(variant: bool) -> dict[str, Honest]:
    """One honest solution per exercise: the main one (named as its exercise), or a variant where there is one."""
    out: dict[str, Honest] = {}
    for h in collect("HONEST"):
        if not h.fn.__module__.startswith("tests.checks.catalogue"):
            continue  # the reference itself: not a student's code
        main = h.fn.__name__ == h.exercise
        if variant:
            if h.exercise not in out or (not main and out[h.exercise].fn.__name__ == h.exercise):
                out[h.exercise] = h
        elif main:
            out[h.exercise] = h
    return out


def _replace_def(source: str, name: str, code: str) -> str:
    tree = ast.parse(python_source(source))
    node = next(n for n in tree.body if getattr(n, "name", None) == name)
    start = min([node.lineno] + [d.lineno for d in getattr(node, "decorator_list", [])]) - 1
    lines = source.splitlines()
    return "\n".join(lines[:start] + code.rstrip("\n").splitlines() + lines[node.end_lineno:]) + "\n"


@functools.lru_cache(maxsize=1)
def _release() -> Path:
    """The student release, written once per process (about 1.4 s each): the instructor notebooks it is made from
    do not change while the tests run. Removed when the process ends."""
    folder = Path(tempfile.mkdtemp(prefix="honest-release-"))
    atexit.register(shutil.rmtree, folder, True)
    write_release(folder / "kit")
    return folder / "kit"


def honest_submission(dest: Path, variant: bool = False, notebooks: list[str] | None = None,
                      picked: dict[str, Honest] | None = None) -> tuple[Path, set[str]]:
    """Write the student release to ``dest`` (a new folder) with every exercise that has an honest solution filled in.

    Args:
        picked: ``{exercise: solution}`` to fill in instead of :func:`choose`'s (the main ones fill the rest).

    Returns:
        the submission folder and the exercises that were filled in.
    """
    shutil.copytree(_release(), dest)  # a copy of this process's release (dest: a new folder)
    picked = {**choose(variant), **(picked or {})}
    filled = set()
    for spec in kit_specs(NOTEBOOKS_DIR, only=notebooks):
        path = Path(dest) / "notebooks" / spec.name
        if not spec.exercises or not path.exists():
            continue
        nb = nbformat.read(path, as_version=4)
        for e in spec.exercises:
            if e.name in picked:
                nb.cells[e.cell].source = _replace_def(nb.cells[e.cell].source, e.name, honest_source(picked[e.name]))
                filled.add(e.name)
        nbformat.write(nb, path)
    return Path(dest), filled

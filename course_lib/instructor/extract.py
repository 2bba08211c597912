"""Cutting one exercise out of a submitted notebook, with exactly what it needs.

:func:`extract_exercise` takes the top-level ``def`` (or ``class``) of the exercise's name in the
cells before its check cell, plus the imports, helper functions and assignments it needs
(transitively, the last binding of each name, as the notebook would see it when the check cell
runs). The grader runs that code, and nothing else of the notebook, in the student's process
(:mod:`course_lib.instructor.student_process`).
"""

from __future__ import annotations

import ast
import builtins
from dataclasses import dataclass, field

from course_lib.instructor.notebooks import python_source

__all__ = ["Extracted", "extract_exercise", "code_cells"]


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



"""Cutting one exercise out of a submitted notebook, with exactly what it needs.

:func:`extract_exercise` takes the top-level ``def`` (or ``class``) of the exercise's name in the
cells before its check cell, plus every earlier top-level statement that the exercise's result can
depend on, in notebook order: a backward slice over the notebook's top-level statements. The
grader runs that code, and nothing else of the notebook, in the student's process
(:mod:`course_lib.instructor.student_process`).

A statement is kept when it *touches* a needed name:

* it binds it (assignment of any form, ``import``, ``def``, ``class``, ``for`` / ``with`` / ``except``
  targets, ``:=``, ``del``); an unconditional simple binding (``x = ...``, ``import x``,
  ``def x``) ends the search for earlier bindings of that name;
* it changes the object bound to it: item or attribute assignment (``OPTS["sign"] = 1.0``,
  ``cfg.scale = 2``), augmented assignment, a method call used as a statement
  (``OPTS.update(...)``, ``torch.set_default_dtype(...)``), or a call of a function whose body
  assigns it through ``global``.

What a kept statement reads is needed in turn. Names are resolved with :mod:`symtable`, so
nested defs, lambdas, comprehensions, class bodies, decorators, defaults, annotations and
``global`` declarations count exactly as Python scopes them; the free names of a function body
are needed both where the function is defined and when the check calls it, so a module constant
that a later cell changes is seen with the value it has when the check cell runs. ``from m import
*`` statements are always kept (what they bind is unknown here); ``from __future__`` imports go
first. Two statements on one line (``a = 1; b = 2``) are cut apart.
"""

from __future__ import annotations

import ast
import bisect
import builtins
import functools
import re
import symtable
from dataclasses import dataclass, field

from course_lib.instructor.notebooks import python_source

__all__ = ["Extracted", "Statement", "code_cells", "extract_exercise", "top_level_statements"]

#: Names every module has (the student's code runs as a module called ``__main__``).
MODULE_NAMES = {"__name__", "__file__", "__doc__", "__builtins__", "__spec__", "__loader__", "__package__",
                "__class__"}
FUTURE_ANNOTATIONS = "from __future__ import annotations\n"
_SIMPLE_BINDINGS = (ast.Assign, ast.AnnAssign, ast.Import, ast.ImportFrom, ast.FunctionDef, ast.AsyncFunctionDef,
                    ast.ClassDef)


@dataclass
class Extracted:
    """The code of one exercise as cut out of a notebook."""

    name: str
    code: str  # the statements it needs + the def, in notebook order
    def_cell: int  # cell index of the def used
    problems: list[str] = field(default_factory=list)  # e.g. names the grader could not find


@dataclass
class Statement:
    """One top-level statement of a notebook and the names it binds, changes and reads.

    Attributes:
        cell: the index of its cell (among all cells).
        node: its syntax tree.
        text: its source (only this statement, even when it shares a line with another).
        binds: names it (re)binds at top level.
        kills: names it surely rebinds (unconditional simple bindings): earlier bindings are dead.
        changes: names whose object it changes in place (item, attribute, method call, ``global``).
        reads: names it reads, at once or later (the free names of the functions it defines).
        global_writes: for a top-level ``def``: the names its body assigns through ``global``.
        star: whether it is ``from m import *``.
    """

    cell: int
    node: ast.stmt
    text: str
    binds: set[str] = field(default_factory=set)
    kills: set[str] = field(default_factory=set)
    changes: set[str] = field(default_factory=set)
    reads: set[str] = field(default_factory=set)
    global_writes: set[str] = field(default_factory=set)
    star: bool = False

    @property
    def is_def(self) -> bool:
        return isinstance(self.node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))

    @property
    def is_future(self) -> bool:
        return isinstance(self.node, ast.ImportFrom) and self.node.module == "__future__"


def code_cells(cells) -> list[tuple[int, str, ast.Module | None]]:
    """``[(cell index, python source, tree or None if it does not parse)]`` of the code cells among ``cells``
    (a notebook's ``(cell type, source)`` pairs)."""
    out = []
    for i, (kind, source) in enumerate(cells):
        if kind != "code":
            continue
        src = python_source(source)
        try:
            tree = ast.parse(src)
        except SyntaxError:
            tree = None
        out.append((i, src, tree))
    return out


def _segment(src: str, node: ast.stmt) -> str:
    """The source of one top-level statement (with its decorators; cut apart from others on its line).

    As :func:`ast.get_source_segment`, but with the cell's lines split once (:func:`_lines`), not once per statement
    (which made a cell of thousands of statements quadratic)."""
    decorators = getattr(node, "decorator_list", [])
    lines = _lines(src)
    if decorators:
        start = min(d.lineno for d in decorators) - 1
        return "\n".join(ln.rstrip("\r\n") for ln in lines[start:node.end_lineno])
    try:
        a, b = node.lineno - 1, node.end_lineno - 1
        if a == b:
            text = lines[a].encode()[node.col_offset:node.end_col_offset].decode()
        else:
            text = "".join([lines[a].encode()[node.col_offset:].decode(), *lines[a + 1:b],
                            lines[b].encode()[:node.end_col_offset].decode()])
    except (AttributeError, IndexError, TypeError, UnicodeDecodeError):
        text = ""
    return text or ast.unparse(node)


@functools.lru_cache(maxsize=8)
def _lines(src: str) -> list[str]:
    """``src``'s lines with their ends, split as the parser counts them (``\\r\\n``, ``\\n``, ``\\r``; not a form feed)."""
    return re.findall(r"[^\r\n]*(?:\r\n|\r|\n)|[^\r\n]+$", src)


def _root_name(expr: ast.AST) -> str | None:
    """``OPTS`` for ``OPTS["a"].b[0]``; None when the chain does not start at a name."""
    while isinstance(expr, (ast.Attribute, ast.Subscript, ast.Starred)):
        expr = expr.value
    return expr.id if isinstance(expr, ast.Name) else None


def _module_level_nodes(node: ast.AST):
    """The nodes of a statement that run when it runs: not the bodies of the functions and lambdas it defines."""
    todo = [node]
    while todo:
        n = todo.pop()
        yield n
        if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)):
            todo += list(n.decorator_list) + [d for d in n.args.defaults + n.args.kw_defaults if d is not None]
        elif isinstance(n, ast.Lambda):
            todo += [d for d in n.args.defaults + n.args.kw_defaults if d is not None]
        else:
            todo += list(ast.iter_child_nodes(n))


def _changed_names(node: ast.AST, nodes=None) -> set[str]:
    """Names whose object the statement changes in place: item/attribute stores and deletes, method-call statements."""
    out: set[str] = set()
    for n in _module_level_nodes(node) if nodes is None else nodes:
        if isinstance(n, (ast.Attribute, ast.Subscript)) and isinstance(n.ctx, (ast.Store, ast.Del)):
            root = _root_name(n)
            if root:
                out.add(root)
        elif isinstance(n, ast.AugAssign) and isinstance(n.target, ast.Name):
            out.add(n.target.id)
        elif isinstance(n, ast.Expr) and isinstance(n.value, ast.Call) and isinstance(n.value.func, ast.Attribute):
            root = _root_name(n.value.func)
            if root:
                out.add(root)
    return out


def _called_names(node: ast.stmt) -> set[str]:
    return {n.func.id for n in _module_level_nodes(node) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}


def _scope_names(table: symtable.SymbolTable) -> tuple[set[str], set[str]]:
    """``(read, written)``: global names the nested scopes of ``table`` read, and assign through ``global``."""
    read: set[str] = set()
    written: set[str] = set()
    for child in table.get_children():
        for s in child.get_symbols():
            if s.is_global() and s.is_referenced():
                read.add(s.get_name())
            if s.is_declared_global() and s.is_assigned():
                written.add(s.get_name())
        r, w = _scope_names(child)
        read |= r
        written |= w
    return read, written


def analyse(cell: int, src: str, node: ast.stmt, lazy_annotations: bool = False) -> Statement:
    """The :class:`Statement` of one top-level statement of a cell whose (magic-free) source is ``src``.

    ``lazy_annotations``: an earlier cell ran ``from __future__ import annotations`` (IPython keeps
    it for the later cells), so annotations are not evaluated and read nothing.
    """
    text = _segment(src, node)
    st = Statement(cell, node, text)
    try:
        table = symtable.symtable(FUTURE_ANNOTATIONS * lazy_annotations + text, "<cell>", "exec")
    except SyntaxError:  # e.g. 'await' outside a function: kept as it is, reads what it names
        names = {n.id for n in ast.walk(node) if isinstance(n, ast.Name)}
        st.reads, st.binds = names, names
        return st
    for s in table.get_symbols():
        if lazy_annotations and s.get_name() == "annotations" and not st.is_future:
            continue
        if s.is_referenced():
            st.reads.add(s.get_name())
        if s.is_assigned() or s.is_imported():
            st.binds.add(s.get_name())
    nested_reads, nested_writes = _scope_names(table)
    st.reads |= nested_reads
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
        # names its body rebinds through `global`, or whose global object it changes in place
        st.global_writes = nested_writes | (_changed_names(node, ast.walk(node)) & nested_reads)
    st.changes = _changed_names(node)
    st.reads |= {n.target.id for n in ast.walk(node) if isinstance(n, ast.AugAssign)
                 and isinstance(n.target, ast.Name)} & st.binds
    st.star = isinstance(node, ast.ImportFrom) and any(a.name == "*" for a in node.names)
    if isinstance(node, _SIMPLE_BINDINGS) and not (isinstance(node, ast.AnnAssign) and node.value is None):
        st.kills = set(st.binds) - st.reads
    return st


def top_level_statements(nb, before_cell: int) -> tuple[list[Statement], list[int]]:
    """The analysed top-level statements of the code cells before ``before_cell``, and the cells that do not parse.

    The whole notebook is parsed and analysed once (the last few notebooks are kept): every exercise of a notebook
    takes its prefix, so the grader's work on a notebook is linear in its size, not in its size times its exercises.
    """
    stmts, bad = _analysed(tuple((c.cell_type, c.source) for c in nb.cells))
    return [s for s in stmts if s.cell < before_cell], [i for i in bad if i < before_cell]


@functools.lru_cache(maxsize=4)
def _analysed(cells: tuple[tuple[str, str], ...]) -> tuple[list[Statement], list[int]]:
    stmts: list[Statement] = []
    bad = []
    lazy = False
    for i, src, tree in code_cells(cells):
        if tree is None:
            bad.append(i)
            continue
        for node in tree.body:
            lazy = lazy or (isinstance(node, ast.ImportFrom) and node.module == "__future__"
                            and any(a.name == "annotations" for a in node.names))
            stmts.append(analyse(i, src, node, lazy))
    return stmts, bad


def _slice(stmts: list[Statement], name: str) -> tuple[set[int], set[str]]:
    """Indices of the statements ``name`` needs (a backward slice), and the names still unbound before them all.

    A name is needed at the end (the check calls ``name``, and every function kept may read its free names then) and
    just before each kept statement that reads it; where it is needed, the statements before that point which bind or
    change it are kept, back to one that surely rebinds it. Linear: for each name, each statement that touches it is
    walked over once (a walk stops where an earlier walk of the same name passed), so a chain of thousands of
    helpers costs thousands of steps, not their square.
    """
    writers = {s.node.name: s.global_writes for s in stmts if s.is_def and s.global_writes}
    touching: dict[str, list[int]] = {}
    for k, s in enumerate(stmts):
        changes = s.changes | {n for f in _called_names(s.node) & set(writers) for n in writers[f]}
        for n in s.binds | changes:
            touching.setdefault(n, []).append(k)
    keep: set[int] = set()
    todo: list[int] = []
    walked: dict[str, set[int]] = {}
    at_end: set[str] = set()
    unbound: set[str] = set()

    def walk(n: str, before: int) -> None:
        ks, seen = touching.get(n, []), walked.setdefault(n, set())
        i = bisect.bisect_left(ks, before) - 1
        while i >= 0:
            k = ks[i]
            if k in seen:
                return
            seen.add(k)
            if k not in keep:
                keep.add(k)
                todo.append(k)
            if n in stmts[k].kills:
                return
            i -= 1
        unbound.add(n)

    def need(n: str, before: int) -> None:
        if n not in at_end:  # a name any kept statement reads is read again when the check calls the function
            at_end.add(n)
            walk(n, len(stmts))
        walk(n, before)

    for k, s in enumerate(stmts):
        if s.star:  # what it binds is unknown: always kept
            keep.add(k)
            todo.append(k)
    need(name, len(stmts))
    while todo:
        k = todo.pop()
        for n in stmts[k].reads:
            need(n, k)
    return keep, unbound


def extract_exercise(nb, name: str, before_cell: int) -> Extracted | None:
    """Cut exercise ``name`` out of a notebook: its last top-level def before cell ``before_cell``, with what it needs.

    Returns None when no cell before ``before_cell`` defines ``name`` with a top-level ``def`` or ``class``.
    """
    stmts, _ = top_level_statements(nb, before_cell)
    defs = [s for s in stmts if s.is_def and s.node.name == name]
    if not defs:
        return None
    keep, unbound = _slice(stmts, name)
    kept = [stmts[k] for k in sorted(keep)]
    kept = [s for s in kept if s.is_future] + [s for s in kept if not s.is_future]
    code = "\n\n".join(s.text for s in kept) + "\n"
    ex = Extracted(name, code, defs[-1].cell)
    bound = set().union(*(s.binds | s.global_writes for s in kept))  # a loop variable is read where it is bound
    missing = {n for n in unbound - bound if not hasattr(builtins, n) and n not in MODULE_NAMES}
    if missing and not any(s.star for s in kept):
        ex.problems.append("uses notebook names that no top-level def, import or assignment before its check cell "
                           f"defines: {', '.join(sorted(missing))} (the grader runs the function on its own)")
    return ex

"""Fill a student release with the literal-student catalogue, the way a student fills it.

A student replaces each stub (``# YOUR CODE HERE`` + ``raise NotImplementedError("your code
here")``) with the body of their function and keeps the released signature and docstring. So
does :func:`fill_release`: for every stub of every released notebook it finds the function (or
method) around it, takes the body of the catalogue's function of that name
(:mod:`tests.student.literal`), indents it to the stub, and puts the imports and module-level
helpers the body needs at the top of the cell (those the notebook does not define already).

A stub whose function has no literal solution, or whose released signature differs from the
catalogue's, is an error that names both: the catalogue is kept in step with the released text.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import textwrap
from dataclasses import dataclass
from pathlib import Path

import nbformat

from course_lib.instructor.notebooks import python_source
from tests.student.literal import MODULES

__all__ = ["FillError", "LiteralSolution", "catalogue", "fill_source", "fill_notebook", "fill_release"]

STUB = "# YOUR CODE HERE"
PACKAGE = "tests.student.literal"


class FillError(Exception):
    """A released stub the catalogue cannot fill (no solution, or a different signature)."""


@dataclass
class LiteralSolution:
    """One function (or method) of the catalogue."""

    qualname: str  # "eight_point", "NeRF.forward"
    module: str  # "tests.student.literal.nb01"
    node: ast.FunctionDef
    tree: ast.Module  # its module
    source: str  # its module's source

    def body(self) -> str:
        """The lines after the signature and docstring, dedented."""
        lines = self.source.splitlines()
        first = self.node.body[0]
        has_doc = isinstance(first, ast.Expr) and isinstance(getattr(first, "value", None), ast.Constant) \
            and isinstance(first.value.value, str)
        start = first.end_lineno if has_doc else first.lineno - 1
        return textwrap.dedent("\n".join(lines[start:self.node.end_lineno])).strip("\n")

    def signature(self) -> str:
        return ast.unparse(self.node.args)


def _functions(tree: ast.Module) -> dict[str, ast.FunctionDef]:
    """``{qualname: def}`` of the module's top-level functions and the methods of its top-level classes."""
    out: dict[str, ast.FunctionDef] = {}
    for node in tree.body:
        if isinstance(node, ast.FunctionDef):
            out[node.name] = node
        elif isinstance(node, ast.ClassDef):
            for sub in node.body:
                if isinstance(sub, ast.FunctionDef):
                    out[f"{node.name}.{sub.name}"] = sub
    return out


def catalogue() -> dict[str, LiteralSolution]:
    """Every function and method defined in the catalogue's modules, by qualified name."""
    out: dict[str, LiteralSolution] = {}
    for short in MODULES:
        module = importlib.import_module(f"{PACKAGE}.{short}")
        source = inspect.getsource(module)
        tree = ast.parse(source)
        for qualname, node in _functions(tree).items():
            if qualname in out:
                raise FillError(f"{qualname} is defined twice in the catalogue "
                                f"({out[qualname].module}, {module.__name__})")
            out[qualname] = LiteralSolution(qualname, module.__name__, node, tree, source)
    return out


def bound_names(nb) -> set[str]:
    """Names a notebook binds at the top level of its code cells (imports, defs, classes, assignments)."""
    names: set[str] = set()
    for cell in nb.cells:
        if cell.cell_type != "code":
            continue
        try:
            tree = ast.parse(python_source(cell.source))
        except SyntaxError:
            continue
        for node in tree.body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                names.add(node.name)
            elif isinstance(node, (ast.Import, ast.ImportFrom)):
                names.update((a.asname or a.name).split(".")[0] for a in node.names)
            elif isinstance(node, (ast.Assign, ast.AnnAssign, ast.AugAssign)):
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                names.update(n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name))
    return names


def _module_level(tree: ast.Module) -> dict[str, ast.stmt]:
    """``{name: statement}`` of the module's top-level imports, functions and classes."""
    out: dict[str, ast.stmt] = {}
    for node in tree.body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            for a in node.names:
                out[(a.asname or a.name).split(".")[0]] = node
        elif isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            out[node.name] = node
    return out


def _used_names(code: str) -> set[str]:
    return {n.id for n in ast.walk(ast.parse(code)) if isinstance(n, ast.Name)}


def _preamble(sol: LiteralSolution, body: str, notebook_names: set[str], stubbed: set[str]) -> list[str]:
    """The imports and module-level helpers the body needs that the notebook does not bind."""
    top = _module_level(sol.tree)
    need: list[ast.stmt] = []
    todo = sorted(_used_names(body))
    seen: set[str] = set()
    while todo:
        name = todo.pop()
        if name in seen or name in notebook_names or name in stubbed or name not in top:
            continue
        seen.add(name)
        node = top[name]
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("tests"):
            raise FillError(f"{sol.qualname} uses {name}, which the notebook does not define (the catalogue imports it "
                            f"from {node.module})")
        if node not in need:
            need.append(node)
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            todo += sorted(_used_names(ast.get_source_segment(sol.source, node)))
    order = {id(n): k for k, n in enumerate(sol.tree.body)}
    imports = [n for n in need if isinstance(n, (ast.Import, ast.ImportFrom))]
    helpers = [n for n in need if not isinstance(n, (ast.Import, ast.ImportFrom))]
    return [ast.get_source_segment(sol.source, n) for n in sorted(imports, key=lambda n: order[id(n)])] + \
        [ast.get_source_segment(sol.source, n) for n in sorted(helpers, key=lambda n: order[id(n)])]


def _enclosing(tree: ast.Module, line: int) -> list[ast.AST]:
    """The chain of top-level def/class (and the def inside a class) around a 1-based line."""
    chain: list[ast.AST] = []
    body = tree.body
    while True:
        node = next((n for n in body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))
                     and n.lineno <= line <= n.end_lineno), None)
        if node is None:
            return chain
        chain.append(node)
        body = node.body


def _kept_before_stub(node: ast.FunctionDef, lines: list[str], k: int) -> list[str]:
    """The released lines of a function between its docstring and the stub at line index ``k`` (stripped)."""
    first = node.body[0]
    start = first.end_lineno if isinstance(first, ast.Expr) and isinstance(getattr(first, "value", None),
                                                                            ast.Constant) else first.lineno - 1
    return [ln.strip() for ln in lines[start:k] if ln.strip() and not ln.strip().startswith("#")]


def _after(body: str, kept: list[str]) -> str:
    """The body without its first lines where they repeat what the released stub keeps before the stub
    (``super().__init__()`` of a module's ``__init__``)."""
    lines = body.splitlines()
    code = [i for i, ln in enumerate(lines) if ln.strip() and not ln.strip().startswith("#")]
    if kept and len(code) >= len(kept) and [lines[i].strip() for i in code[:len(kept)]] == kept:
        lines = lines[code[len(kept) - 1] + 1:]
    return "\n".join(lines).strip("\n")


def fill_source(source: str, solutions: dict[str, LiteralSolution], notebook_names: set[str],
                where: str = "cell") -> tuple[str, list[str]]:
    """A cell's source with every stub replaced by the body of the catalogue's function of that name.

    Returns:
        the new source and the qualified names filled in (e.g. ``["NeRF.__init__", "NeRF.forward"]``).
    """
    lines = source.splitlines()
    stubs = [k for k, ln in enumerate(lines) if ln.strip() == STUB and k + 1 < len(lines)
             and lines[k + 1].strip().startswith("raise NotImplementedError")]
    if not stubs:
        return source, []
    tree = ast.parse(python_source(source))
    filled, preamble = [], []
    for k in reversed(stubs):
        chain = _enclosing(tree, k + 1)
        defs = [n for n in chain if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
        if not defs:
            raise FillError(f"{where}: a stub at line {k + 1} outside any function")
        qualname = ".".join(n.name for n in chain[: chain.index(defs[0]) + 1])
        sol = solutions.get(qualname)
        if sol is None:
            raise FillError(f"{where}: no literal solution for {qualname} in {PACKAGE} (write one from the released "
                            "notebook's text and stub)")
        released = ast.unparse(defs[0].args)
        if released != sol.signature():
            raise FillError(f"{where}: the released stub is {qualname}({released}) but the literal catalogue has "
                            f"{qualname}({sol.signature()}) ({sol.module}): update it from the released text")
        indent = lines[k][: len(lines[k]) - len(lines[k].lstrip())]
        body = _after(sol.body(), _kept_before_stub(defs[0], lines, k))
        lines[k:k + 2] = textwrap.indent(body, indent).splitlines()
        stubbed = {qualname.split(".")[0]}
        preamble += [p for p in _preamble(sol, body, notebook_names, stubbed) if p not in preamble]
        filled.append(qualname)
    head = "\n".join(preamble) + "\n\n\n" if preamble else ""
    return head + "\n".join(lines) + ("\n" if source.endswith("\n") else ""), filled[::-1]


def fill_notebook(path: Path, solutions: dict[str, LiteralSolution] | None = None) -> list[str]:
    """Fill every stub of one released notebook in place; returns the qualified names filled in."""
    solutions = solutions if solutions is not None else catalogue()
    nb = nbformat.read(path, as_version=4)
    names = bound_names(nb)
    filled: list[str] = []
    for i, cell in enumerate(nb.cells):
        if cell.cell_type != "code":
            continue
        cell.source, done = fill_source(cell.source, solutions, names, f"{Path(path).name}, cell {i}")
        filled += done
    nbformat.write(nb, path)
    return filled


def fill_release(kit: Path) -> dict[str, list[str]]:
    """Fill every released notebook of the kit at ``kit`` with the catalogue; ``{notebook: [filled names]}``."""
    solutions = catalogue()
    return {p.name: fill_notebook(p, solutions) for p in sorted((Path(kit) / "notebooks").glob("*.ipynb"))}

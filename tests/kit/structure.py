"""The shape of ``course_lib`` read from its own source: imports, private names, function and module sizes.

``python -m tests.kit.structure [ROOT]`` prints the report for the checkout at ``ROOT`` (default:
this one), so a state before a change can be measured from ``git worktree add /tmp/before REV``.
:mod:`tests.kit.test_structure` holds the rules that must stay true. Everything is read with
:mod:`ast` (no module is imported):

* **import graph**: an edge ``a -> b`` for every ``import``/``from ... import`` of a course_lib module
  ``b`` in module ``a``, at the top or *deferred* (inside a function); ``from pkg import name`` points
  at ``pkg.name`` where that is a module, else at ``pkg``. Parent packages that Python imports on
  the way are not edges (they are no circle of the code's making). Imports under ``if TYPE_CHECKING``
  are left out.
* **private names across modules**: ``from course_lib.m import _name`` and ``alias._name`` where
  ``alias`` is a course_lib module, in a module other than the one that defines ``_name``.
* **function lengths**: ``def`` line to last line (docstring and nested functions included).
"""

from __future__ import annotations

import ast
import sys
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


@dataclass
class Module:
    name: str
    path: Path
    lines: int
    tree: ast.Module
    doc_first_line: str
    #: ``{target module: "top" | "deferred"}`` (top wins where both)
    imports: dict[str, str] = field(default_factory=dict)


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _type_checking_nodes(tree: ast.Module) -> set[int]:
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            out |= {id(n) for b in node.body for n in ast.walk(b)}
    return out


def _function_nodes(tree: ast.Module) -> set[int]:
    return {id(n) for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
            for n in ast.walk(f) if n is not f}


def _resolve(node: ast.ImportFrom, mod: Module) -> str:
    if not node.level:
        return node.module or ""
    base = mod.name.split(".")
    is_pkg = mod.path.name == "__init__.py"
    base = base if is_pkg else base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def load(root: Path = REPO, package: str = "course_lib") -> dict[str, Module]:
    """``{module name: Module}`` of every ``.py`` file of ``root/package`` with its course_lib imports."""
    mods: dict[str, Module] = {}
    for p in sorted((root / package).rglob("*.py")):
        if "__pycache__" in p.parts:
            continue
        src = p.read_text()
        tree = ast.parse(src)
        doc = ast.get_docstring(tree) or ""
        mods[module_name(p, root)] = Module(module_name(p, root), p, len(src.splitlines()), tree,
                                            doc.strip().splitlines()[0] if doc.strip() else "")
    for mod in mods.values():
        skip, deferred = _type_checking_nodes(mod.tree), _function_nodes(mod.tree)
        for node in ast.walk(mod.tree):
            if id(node) in skip:
                continue
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _resolve(node, mod)
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]
            for t in targets:
                while t and t not in mods:  # import a.b.c where c is a name
                    t = t.rpartition(".")[0]
                if t.startswith(package) and t in mods and t != mod.name:
                    kind = "deferred" if id(node) in deferred else "top"
                    if mod.imports.get(t) != "top":
                        mod.imports[t] = kind
    return mods


def cycles(mods: dict[str, Module]) -> list[list[str]]:
    """The import circles: one shortest circle through each strongly connected group of modules (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    groups: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in mods[v].imports:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    sys.setrecursionlimit(max(10000, sys.getrecursionlimit()))
    for v in sorted(mods):
        if v not in index:
            visit(v)
    return [_shortest_circle(mods, g) for g in sorted(groups)]


def _shortest_circle(mods: dict[str, Module], group: list[str]) -> list[str]:
    start, inside = group[0], set(group)
    paths = {start: [start]}
    frontier = [start]
    while frontier:
        nxt = []
        for v in frontier:
            for w in sorted(mods[v].imports):
                if w == start:
                    return paths[v] + [start]
                if w in inside and w not in paths:
                    paths[w] = paths[v] + [w]
                    nxt.append(w)
        frontier = nxt
    return group


def describe_circle(mods: dict[str, Module], circle: list[str]) -> str:
    hops = [f"{a} -{'(deferred)' if mods[a].imports[b] == 'deferred' else ''}> {b}" for a, b in zip(circle, circle[1:])]
    return "; ".join(hops)


def private_uses(mods: dict[str, Module], package: str = "course_lib") -> list[str]:
    """``"user:line uses module._name"`` for every private name taken from another course_lib module."""
    out = []
    for mod in mods.values():
        aliases: dict[str, str] = {}  # local name -> course_lib module
        for node in ast.walk(mod.tree):
            if isinstance(node, ast.Import):
                for a in node.names:
                    if a.name in mods and a.asname:
                        aliases[a.asname] = a.name
            elif isinstance(node, ast.ImportFrom):
                base = _resolve(node, mod)
                for a in node.names:
                    full = f"{base}.{a.name}"
                    if full in mods:
                        aliases[a.asname or a.name] = full
                    elif base in mods and base != mod.name and a.name.startswith("_") and not a.name.startswith("__"):
                        out.append(f"{mod.name}:{node.lineno} uses {base}.{a.name}")
        for node in ast.walk(mod.tree):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases \
                    and node.attr.startswith("_") and not node.attr.startswith("__") and aliases[node.value.id] != mod.name:
                out.append(f"{mod.name}:{node.lineno} uses {aliases[node.value.id]}.{node.attr}")
    return sorted(set(out))


def functions(mods: dict[str, Module]) -> list[tuple[int, str]]:
    """``[(lines, "module:line qualified.name"), ...]`` of every function and method, longest first."""
    out = []

    def walk(node, mod: Module, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                out.append((child.end_lineno - child.lineno + 1, f"{mod.name}:{child.lineno} {prefix}{child.name}"))
                walk(child, mod, f"{prefix}{child.name}.")
            elif isinstance(child, ast.ClassDef):
                walk(child, mod, f"{prefix}{child.name}.")
            else:
                walk(child, mod, prefix)

    for mod in mods.values():
        walk(mod.tree, mod, "")
    return sorted(out, key=lambda r: (-r[0], r[1]))


def folder_lines(mods: dict[str, Module]) -> dict[str, int]:
    """Lines of Python per folder of the package (``course_lib`` itself: its top-level files)."""
    out: dict[str, int] = {}
    for m in mods.values():
        parts = m.name.split(".")
        key = parts[1] if len(parts) > 2 or m.path.name == "__init__.py" and len(parts) > 1 else "(top level)"
        out[key] = out.get(key, 0) + m.lines
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))


def report(root: Path = REPO, long_over: int = 80, large_over: int = 500, mods: dict[str, Module] | None = None) -> str:
    """The figures as text (of ``mods`` where given, else of the checkout at ``root``)."""
    mods = load(root) if mods is None else mods
    lines = [f"course_lib at {root}: {len(mods)} modules, {sum(m.lines for m in mods.values())} lines"]
    edges = sum(len(m.imports) for m in mods.values())
    deferred = sorted(f"{m.name} -> {t}" for m in mods.values() for t, k in m.imports.items() if k == "deferred")
    lines.append(f"import graph: {edges} edges among course_lib modules, {len(deferred)} of them deferred (in a function)")
    lines += [f"  deferred: {d}" for d in deferred]
    circ = cycles(mods)
    lines.append(f"import circles: {len(circ)}")
    lines += [f"  {describe_circle(mods, c)}" for c in circ]
    priv = private_uses(mods)
    lines.append(f"private names used across modules: {len(priv)}")
    lines += [f"  {p}" for p in priv]
    fns = functions(mods)
    outside = [f for f in fns if ".instructor." not in f[1].split()[0] + "."]
    lines.append(f"functions over {long_over} lines: {sum(n > long_over for n, _ in fns)} "
                 f"({sum(n > long_over for n, _ in outside)} outside instructor/); the longest:")
    lines += [f"  {n:4d} {where}" for n, where in fns[:8]]
    big = sorted((m for m in mods.values() if m.lines > large_over), key=lambda m: -m.lines)
    lines.append(f"modules over {large_over} lines: {len(big)}")
    lines += [f"  {m.lines:4d} {m.name}: {m.doc_first_line}" for m in big]
    lines.append("lines per folder:")
    total = sum(m.lines for m in mods.values())
    lines += [f"  {k:12s} {v:6d} ({100 * v / total:4.1f} %)" for k, v in folder_lines(mods).items()]
    return "\n".join(lines)


if __name__ == "__main__":
    print(report(Path(sys.argv[1]).resolve() if len(sys.argv) > 1 else REPO))

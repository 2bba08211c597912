"""Which parts of ``course_lib`` the student kit ships, leaves out, or ships redacted.

A module is a *solution module* when a solution region of a notebook imports it. Solution modules
that no released notebook needs are left out, with every module that imports them
(:func:`release_plan`); solution modules that the kit itself builds on (the NeRF trainer imports
:mod:`course_lib.nerf.render`) are shipped *redacted* (:func:`redact_module`): their exercise
functions are replaced by a stand-in that calls the student's own function of the same name
(:mod:`course_lib.saved_solutions`). The instructor package never ships.

Every exercise is accounted for in every shipped module, not only in the module its solution
region imports: a top-level ``def``, ``class`` or assignment of an exercise's name in any module
that ships is redacted too (:func:`exercise_definitions`). The plan's
:attr:`ReleasePlan.implementations` says, per exercise, where its implementation went (left out,
replaced by a stand-in, or shipped, with the reason); the release manifest carries it.
"""

from __future__ import annotations

import ast
import functools
import re
from dataclasses import dataclass, field
from pathlib import Path

from course_lib.instructor.notebooks import (
    NotebookSpec,
    course_lib_modules,
    file_key,
    optional_imports,
    resolve_import,
)

__all__ = ["ReleasePlan", "release_plan", "solution_modules", "redact_module", "imported_names", "exercise_definitions"]


@functools.lru_cache(maxsize=None)
def _imports(path: str, size: int, mtime_ns: int) -> tuple[dict[str, set[str]], dict[str, set[str]]]:
    """``{"top": modules imported when the module loads, "lazy": imported inside functions}`` (course_lib only;
    imports inside ``try`` blocks that catch ImportError count as neither: they are optional), and ``{module: names}``
    of its ``from module import names`` statements (cached by :func:`~course_lib.instructor.notebooks.file_key`)."""
    tree = ast.parse(Path(path).read_text())
    out: dict[str, set[str]] = {"top": set(), "lazy": set()}
    names: dict[str, set[str]] = {}
    func_nodes = {id(n) for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
                  for n in ast.walk(f) if n is not f}
    optional = optional_imports(tree)
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            names.setdefault(node.module, set()).update(a.name for a in node.names)
        if isinstance(node, (ast.Import, ast.ImportFrom)) and id(node) not in optional:
            for mod, _ in resolve_import(node):
                if mod.startswith("course_lib"):
                    out["lazy" if id(node) in func_nodes else "top"].add(mod)
    return out, names


def solution_modules(specs: list[NotebookSpec]) -> dict[str, list[str]]:
    """``{module: [exercise names it holds the reference of]}`` over all notebooks.

    Only modules that solution regions import count; an exercise whose reference is merely a
    library function of the same name (:func:`course_lib.instructor.notebooks.library_definition`)
    is accounted for by :func:`_account_for_exercises`.
    """
    out: dict[str, list[str]] = {}
    for s in specs:
        for m in s.solution_modules:
            out.setdefault(m, [])
        for e in s.exercises:
            if e.reference and e.reference.split(":")[0] in s.solution_modules:  # not a library_definition
                mod, attr = e.reference.split(":")
                out.setdefault(mod, []).append(attr)
    return {m: sorted(set(v)) for m, v in sorted(out.items())}


@dataclass
class ReleasePlan:
    omit: list[str]  # modules left out of the kit
    redact: dict[str, list[str]]  # module -> exercise names replaced by stand-ins
    exercise_notebook: dict[str, str]  # exercise name -> notebook that teaches it
    notes: list[str] = field(default_factory=list)
    left_out_notebooks: list[str] = field(default_factory=list)  # demos that need the reference solutions
    #: exercise -> {"left out": [modules], "stand-in": [modules], "ships": ["module: why"]}: where each
    #: definition of the exercise's name in course_lib went
    implementations: dict[str, dict[str, list[str]]] = field(default_factory=dict)


def exercise_definitions(path: Path, names: set[str]) -> dict[str, bool]:
    """``{exercise name: whether the module itself uses it}`` for the names of ``names`` a module defines at top level.

    A definition is a top-level ``def``, ``class`` or assignment of the name; "uses it" means
    that some other top-level statement of the module reads the name (so a stand-in would change
    what the module's own functions compute).
    """
    tree = ast.parse(Path(path).read_text())
    out: dict[str, bool] = {}
    for node in tree.body:
        name = _bound_name(node)
        if name in names:
            out[name] = False
    for node in tree.body:
        own = _bound_name(node)
        for n in ast.walk(node):
            if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Load) and n.id in out and n.id != own:
                out[n.id] = True
    return out


def _account_for_exercises(plan: ReleasePlan, mods: dict[str, Path]) -> None:
    """Redact every top-level definition of an exercise's name in the shipped modules; record where each went.

    A definition that the module's own code calls, of an exercise whose reference lives elsewhere,
    is not replaced (the kit's own code would then need the student's function in notebooks
    that do not teach it): it ships, and :attr:`ReleasePlan.implementations` and the notes say so.
    """
    names = set(plan.exercise_notebook)
    omit = set(plan.omit)
    for m, path in sorted(mods.items()):
        if m == "course_lib.saved_solutions":
            continue
        for name, used_inside in sorted(exercise_definitions(path, names).items()):
            where = plan.implementations.setdefault(name, {"left out": [], "stand-in": [], "ships": []})
            if m in omit:
                where["left out"].append(m)
            elif name in plan.redact.get(m, []) or not used_inside:
                if name not in plan.redact.get(m, []):
                    plan.redact.setdefault(m, []).append(name)
                where["stand-in"].append(m)
            else:
                where["ships"].append(f"{m}: the module's own code calls it (a stand-in would make the kit need "
                                      f"the student's {name} outside {plan.exercise_notebook[name]})")
                plan.notes.append(f"{m}.{name} implements the exercise {name} and ships: the module's own code "
                                  "calls it; compute it inline there or take it from the caller")
    for m in plan.redact:
        plan.redact[m] = sorted(plan.redact[m])


def release_plan(specs: list[NotebookSpec]) -> ReleasePlan:
    """Decide which course_lib modules the student kit leaves out and which it ships redacted.

    A solution module that a notebook needs outside its solution regions (directly or through
    the modules it loads) is redacted; any other solution module is left out, and so is every
    module that imports a left-out module (at load time or inside a function; imports inside a
    ``try`` that catches ImportError are optional and do not count). The instructor package
    (:data:`~course_lib.instructor.notebooks.INSTRUCTOR_PACKAGE`) never ships; the checks (``course_lib.checks``)
    import no solution module, so they always ship (a test enforces it).
    """
    mods = course_lib_modules()
    imports = {m: _imports(*file_key(p))[0] for m, p in mods.items()}
    demos = [s for s in specs if not s.exercises]
    specs = [s for s in specs if s.exercises]
    sol = solution_modules(specs)
    parents = lambda m: [m.rsplit(".", k)[0] for k in range(1, m.count(".") + 1)]  # noqa: E731 - a.b.c loads a, a.b
    needed = _closure([m for s in specs for m in s.imports], mods, lambda m: sorted(imports[m]["top"]) + parents(m))
    omit = {m for m in sol if m not in needed and m in mods}
    grown = True
    while grown:
        grown = False
        for m in mods:
            if m in omit or m in needed or m == "course_lib.__main__":
                continue
            if (imports[m]["top"] | imports[m]["lazy"]) & omit:
                omit.add(m)
                grown = True
    notes = []
    for m in sorted(needed):
        lazy = imports[m]["lazy"] & omit
        if lazy:
            notes.append(f"{m} is needed by a notebook but calls left-out {sorted(lazy)} inside functions")
    redact = {m: names for m, names in sol.items() if m in needed and m in mods}
    ex_nb = {e.name: e.notebook for s in specs for e in s.exercises}
    left_out = []
    for d in demos:
        reach = _closure(d.imports, mods, lambda m: imports[m]["top"] | imports[m]["lazy"])
        if reach & omit:
            left_out.append(d.name)
            notes.append(f"notebooks/{d.name} has no exercises and needs {sorted(reach & omit)[0]} (a reference "
                         "solution): it is not part of the student kit")
    plan = ReleasePlan(sorted(omit), redact, ex_nb, notes, left_out)
    _account_for_exercises(plan, mods)
    return plan


def _closure(start: list[str], mods: dict, follow) -> set[str]:
    """The modules of ``mods`` reached from ``start`` by following ``follow(module)``."""
    seen, todo = set(), list(start)
    while todo:
        m = todo.pop()
        if m not in seen and m in mods:
            seen.add(m)
            todo += follow(m)
    return seen


def redact_module(path: Path, names: list[str], exercise_notebook: dict[str, str], keep: set[str] = frozenset()) -> str:
    """The module's source with the top-level defs of ``names`` replaced by student stand-ins.

    Private helpers (``_name``) that only the removed code used are removed too, unless another
    module imports them (``keep``).
    """
    text = path.read_text()
    names = [n for n in names if n in exercise_notebook]
    for _ in range(20):  # remove defs, then helpers that became unused, until nothing changes
        tree = ast.parse(text)
        lines = text.splitlines()
        spans = []
        for node in tree.body:
            target = _bound_name(node)
            if target in names:
                spans.append((node, "stand_in", target))
        if not spans:
            for node in tree.body:
                target = _bound_name(node)
                if target and target.startswith("_") and not target.startswith("__") and target not in keep \
                        and target not in _used_outside(tree, target):
                    spans.append((node, "drop", target))
        if not spans:
            break
        for node, kind, target in sorted(spans, key=lambda s: -s[0].lineno):
            start = min([node.lineno] + [d.lineno for d in getattr(node, "decorator_list", [])]) - 1
            end = node.end_lineno
            if kind == "stand_in":
                nb = exercise_notebook[target]
                new = [
                    f"# {target}: an exercise of notebooks/{nb}; the student kit leaves its reference solution out.",
                    "# This stand-in calls your own " + target + " from the running notebook.",
                    "from course_lib.saved_solutions import stand_in as _kit_stand_in  # noqa: E402",
                    "",
                    f"{target} = _kit_stand_in({target!r}, {nb!r}, __name__)",
                ]
            else:
                new = []
            lines[start:end] = new
        names = [n for n in names if n not in {t for _, k, t in spans if k == "stand_in"}]
        text = "\n".join(lines) + "\n"
        text = re.sub(r"\n{4,}", "\n\n\n", text)
    return text


def imported_names(module: str) -> set[str]:
    """Names that other course_lib modules import from ``module`` (``from module import a, b``)."""
    out: set[str] = set()
    for m, p in course_lib_modules().items():
        if m == module:
            continue
        out.update(_imports(*file_key(p))[1].get(module, ()))
    return out


def _bound_name(node: ast.AST) -> str | None:
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        return node.name
    if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
        return node.targets[0].id
    if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
        return node.target.id
    return None


def _used_outside(tree: ast.Module, name: str) -> set[str]:
    """The names (and words of strings) used anywhere in the module *outside* the top-level definition of ``name``."""
    found = set()
    for node in tree.body:
        if _bound_name(node) != name:
            for n in ast.walk(node):
                if isinstance(n, ast.Name):
                    found.add(n.id)
                elif isinstance(n, ast.Attribute):
                    found.add(n.attr)
                elif isinstance(n, ast.Constant) and isinstance(n.value, str):
                    found.update(re.findall(r"\w+", n.value))
    return found

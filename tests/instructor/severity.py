"""The severity table through the real grader (issue 29): ``python -m tests.instructor.severity``.

Two measurements, each a student release filled with the honest catalogue's main solutions and one
mistake of the catalogue (``tests/checks/catalogue``) in its exercise, graded by the real grader (with
``allow_reference``: the catalogue's mistakes call the reference for the exercise's other steps):

* **every defining mistake at least half docked**: each mistake that breaks a defining property, its
  exercise graded on the hidden checks: at most 4.5 of 10 points;
* **each mistake charged once**: a mistake in an exercise that a later exercise of the same notebook calls
  (``normalize_points`` → ``eight_point`` → ``ransac_fundamental``, ``triangulate_linear`` →
  ``choose_pose``, ``pnp_linear`` → ``pnp_ransac``, the residuals and the sparsity → ``bundle_adjust``),
  its notebook graded with nbval: every other exercise of the notebook keeps full marks (10 of 10).

Mistakes written with a factory (``_rays(signs=...)``, ``_variant(...)``) are pasted as the factory's code
and one line that calls it with the mistake's arguments.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import sys
import tempfile
from pathlib import Path

import nbformat

from course_lib.instructor.grade import grade_submission, prepare_hidden
from course_lib.instructor.notebooks import NOTEBOOKS_DIR, kit_specs
from tests.checks.catalogue import Mistake, collect
from tests.instructor.honest import _replace_def, _top_level, exercise_names, honest_submission, needed_nodes

#: The catalogue's own names, never part of a mistake's code (``M = Mistake``, the lists).
CATALOGUE_NAMES = {"M", "Mistake", "Honest", "MISTAKES", "HONEST", "TRIVIAL", "DETAIL"}
#: Later exercises of the same notebook call these: their mistakes must cost only themselves.
CALLED = ("normalize_points", "eight_point", "sampson_distance", "triangulate_linear", "pnp_linear",
          "reprojection_residuals", "jacobian_sparsity")


def _module_nodes(module, root_names: list[str], exclude: set[str]) -> list[str]:
    """The source of ``root_names`` of ``module`` with the module-level code they use (transitively), in order;
    names imported from ``tests.checks.catalogue`` are brought as their source from there."""
    tree = ast.parse(inspect.getsource(module))
    top = _top_level(tree)
    exclude = set(exclude) | CATALOGUE_NAMES
    extra: list[str] = []
    parts = []
    for node in needed_nodes(tree, top, [top[n] for n in root_names], exclude):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("tests"):
            src = importlib.import_module(node.module)
            used = [a.name for a in node.names if a.name not in ("Honest", "Mistake")]
            extra += _module_nodes(src, [u for u in used if u in _top_level(ast.parse(inspect.getsource(src)))], exclude)
            continue
        parts.append(ast.unparse(node))
    return extra + parts


def _bind(exercise: str, name: str, is_class: bool) -> str:
    """A top-level ``def`` (or ``class``) of the exercise's name around ``name``, as the grader cuts exercises out."""
    if is_class:
        return f"class {exercise}({name}):\n    pass"
    return f"def {exercise}(*args, **kwargs):\n    return {name}(*args, **kwargs)"


def mistake_source(m: Mistake) -> str:
    """The code of a mistake as it goes into its exercise cell (defining the exercise's name)."""
    fn = m.fn
    module = importlib.import_module(fn.__module__)
    others = exercise_names() - {m.exercise}
    if "<locals>" not in fn.__qualname__:
        parts = _module_nodes(module, [fn.__name__], others)
        if fn.__name__ != m.exercise:
            parts.append(_bind(m.exercise, fn.__name__, inspect.isclass(fn)))
        return "\n\n\n".join(parts) + "\n"
    factory = fn.__qualname__.split(".")[0]
    params = inspect.signature(getattr(module, factory)).parameters
    cells = {}
    funcs = [fn] if inspect.isfunction(fn) else [v for v in vars(fn).values() if inspect.isfunction(v)]
    for f in funcs:
        for name, cell in zip(f.__code__.co_freevars, f.__closure__ or ()):
            if name in params:
                cells[name] = cell.cell_contents
    args = ", ".join(f"{k}={v!r}" for k, v in cells.items())
    parts = _module_nodes(module, [factory], others)
    parts.append(f"_made = {factory}({args})")
    parts.append(_bind(m.exercise, "_made", inspect.isclass(fn)))
    return "\n\n\n".join(parts) + "\n"


def _submission(dest: Path, m: Mistake, nb: str) -> Path:
    sub, _ = honest_submission(dest, notebooks=[nb])
    for spec in kit_specs(NOTEBOOKS_DIR, only=[nb]):
        path = sub / "notebooks" / spec.name
        nbk = nbformat.read(path, as_version=4)
        for e in spec.exercises:
            if e.name == m.exercise:
                nbk.cells[e.cell].source = _replace_def(nbk.cells[e.cell].source, e.name, mistake_source(m))
        nbformat.write(nbk, path)
    return sub


def _notebook_of(exercise: str) -> str:
    return next(s.name[:2] for s in kit_specs() if any(e.name == exercise for e in s.exercises))


def main(argv: list[str]) -> None:
    only = set(argv)
    defining = [m for m in collect("MISTAKES") if m.defining and (not only or m.exercise in only)]
    chained = []
    for ex in CALLED:
        mine = [m for m in collect("MISTAKES") if m.exercise == ex and (not only or ex in only)]
        chained += mine[:2]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        hidden = prepare_hidden([s for s in kit_specs() if s.exercises], 2031, tmp / "hidden")
        print("defining mistakes, hidden checks of their exercise (points of 10; at most 4.5 wanted)")
        worst = 0.0
        for k, m in enumerate(defining):
            nb = _notebook_of(m.exercise)
            try:
                report = grade_submission(_submission(tmp / f"d{k}", m, nb), notebooks=[nb], exercises=[m.exercise],
                                          hidden=hidden, run_nbval=False, allow_reference=True)
                g = report["exercises"][0]
                pts, status = g["points"], g["status"]
            except Exception as exc:  # noqa: BLE001 - a row of the table
                pts, status = float("nan"), f"error {type(exc).__name__}: {exc}"
            worst = max(worst, pts if pts == pts else 0.0)
            print(f"  {m.exercise + ': ' + m.name:<62} {pts:>5.2f}  {status}  ({m.defining})")
            sys.stdout.flush()
        print(f"  the most any defining mistake kept: {worst:.2f} of 10\n")
        print("mistakes in exercises that later exercises call: their notebook graded with nbval")
        docked_elsewhere = 0
        for k, m in enumerate(chained):
            nb = _notebook_of(m.exercise)
            try:
                report = grade_submission(_submission(tmp / f"c{k}", m, nb), notebooks=[nb], hidden=hidden,
                                          run_nbval=True, allow_reference=True)
                own = next(g for g in report["exercises"] if g["name"] == m.exercise)
                others = [(g["name"], g["points"], g["feedback"][0]) for g in report["exercises"]
                          if g["name"] != m.exercise]
            except Exception as exc:  # noqa: BLE001
                print(f"  {m.exercise}: {m.name}: error {type(exc).__name__}: {exc}")
                continue
            hurt = [(n, p) for n, p, _ in others if p < 10.0]
            docked_elsewhere += len(hurt)
            later = ", ".join(f"{n} {p:g}" for n, p, _ in others)
            print(f"  {m.exercise + ': ' + m.name:<62} own {own['points']:>5.2f}; others: {later}")
            sys.stdout.flush()
        print(f"  exercises docked for a mistake in another exercise: {docked_elsewhere}")


if __name__ == "__main__":
    main(sys.argv[1:])

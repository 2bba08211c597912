"""Where each exercise and its check cell are in a submitted notebook, and what is wrong with that.

The grader gives no credit to an exercise whose cell was deleted or moved, or whose check cell
was edited or deleted; :func:`place_exercises` finds them. The notebook that nbval runs is the student's with
the reference check cells put back (:func:`restored`) and its package installs left out (:func:`without_installs`).
"""

from __future__ import annotations

import ast
import json
import re
from dataclasses import dataclass

import nbformat

from course_lib.instructor.extract import code_cells
from course_lib.instructor.notebooks import NotebookSpec

__all__ = ["Placement", "place_exercises", "restored", "without_installs"]


@dataclass
class Placement:
    check_cell: int | None
    check_state: str  # "intact", "edited", "deleted"
    issue: str | None = None  # "deleted", "reordered: ..."


def _lis_members(seq: list[int], orig: list[int] | None = None) -> set[int]:
    """Positions (into seq) of a longest strictly increasing subsequence.

    Among the longest ones, the one whose members moved least from ``orig`` (their original
    positions) is chosen, so that the cells reported as moved are the ones that moved.
    """
    n = len(seq)
    orig = orig or seq
    best = [(1, -abs(seq[i] - orig[i])) for i in range(n)]
    prev = [-1] * n
    for i in range(n):
        for j in range(i):
            cand = (best[j][0] + 1, best[j][1] - abs(seq[i] - orig[i]))
            if seq[j] < seq[i] and cand > best[i]:
                best[i], prev[i] = cand, j
    if not n:
        return set()
    k = max(range(n), key=lambda i: best[i])
    out = set()
    while k != -1:
        out.add(k)
        k = prev[k]
    return out


def place_exercises(nb, spec: NotebookSpec) -> dict[str, Placement]:
    """Where each exercise and its check cell are in the submitted notebook, and what is wrong with them."""
    cells = [(i, c.source) for i, c in enumerate(nb.cells) if c.cell_type == "code"]
    defs: dict[str, list[int]] = {}
    broken: dict[str, int] = {}
    names = {e.name for e in spec.exercises}
    for i, src, tree in code_cells((c.cell_type, c.source) for c in nb.cells):
        if tree is None:
            for n in names:
                if re.search(rf"^\s*(def|class) {re.escape(n)}\b", src, re.M):
                    broken.setdefault(n, i)
            continue
        for node in tree.body:
            if getattr(node, "name", None) in names and node.__class__.__name__ in ("FunctionDef", "ClassDef",
                                                                                   "AsyncFunctionDef"):
                defs.setdefault(node.name, []).append(i)
            # ``ransac_fundamental = my_ransac``: the exercise bound by assignment is defined in this cell too
            for target in (node.targets if isinstance(node, ast.Assign) else
                           [node.target] if isinstance(node, ast.AnnAssign) and node.value is not None else []):
                if isinstance(target, ast.Name) and target.id in names:
                    defs.setdefault(target.id, []).append(i)
    out: dict[str, Placement] = {}
    used: set[int] = set()
    for e in spec.exercises:  # intact check cells first: they are unambiguous
        intact = [i for i, src in cells if src == e.check_source and i not in used]
        if intact:
            out[e.name] = Placement(intact[0], "intact")
            used.add(intact[0])
    for e in spec.exercises:
        if e.name in out:
            continue
        edited = [i for i, src in cells if f"{e.check_function}(" in src and i not in used]
        start = min(defs.get(e.name, [broken.get(e.name, -1)]))
        marked = [i for i, src in cells if i > start >= 0 and i not in used
                  and src.lstrip().startswith("# NBVAL_CHECK_OUTPUT")]
        pick = edited or marked[:1]
        out[e.name] = Placement(pick[0], "edited") if pick else Placement(None, "deleted")
        if pick:
            used.add(pick[0])
    for e in spec.exercises:
        p = out[e.name]
        where = defs.get(e.name, [])
        if e.name in broken and not [c for c in where if p.check_cell is None or c < p.check_cell]:
            p.issue = (f"error: the cell defining {e.name} (cell {broken[e.name]}) is not valid Python; "
                       "fix the syntax error")
        elif not where:
            p.issue = f"deleted: no cell defines {e.name} any more"
        elif p.check_cell is not None and min(where) > p.check_cell:
            p.issue = f"reordered: {e.name} is defined after its check cell"
    # order of the exercises (by check cell, then by def) must be the original order
    present = [e for e in spec.exercises if out[e.name].check_cell is not None and out[e.name].issue is None]
    for key in ("check", "def"):
        seq = [out[e.name].check_cell if key == "check" else
               max(c for c in defs[e.name] if c < out[e.name].check_cell) for e in present]
        orig = [e.check_cell if key == "check" else e.cell for e in present]
        keep = _lis_members(seq, orig)
        for k, e in enumerate(present):
            if k not in keep and out[e.name].issue is None:
                out[e.name].issue = f"reordered: the {'check' if key == 'check' else 'exercise'} cell of {e.name} " \
                                    "was moved out of the original order"
    return out


def restored(nb, spec: NotebookSpec, places: dict[str, Placement]):
    """The notebook with its check cells restored to the reference source, without nbval's output marker.

    nbval runs each check cell and reports whether it ran without an error; what the cell prints is not compared
    (the grader computes the check's verdict itself, :func:`~course_lib.instructor.hidden.run_hidden`): code in the
    notebook could filter or forge printed output.
    """
    nb = nbformat.from_dict(json.loads(json.dumps(nb)))
    for e in spec.exercises:
        p = places[e.name]
        if p.check_cell is None:
            continue
        cell = nb.cells[p.check_cell]
        cell.source = "\n".join(ln for ln in e.check_source.splitlines() if ln.strip() != "# NBVAL_CHECK_OUTPUT")
        cell.outputs, cell.metadata, cell.execution_count = [], nbformat.NotebookNode(), None
    return nb


#: A package install in a cell (``!pip install numpy``, ``%pip install ...``, ``!python -m pip install``, conda):
#: the grader leaves it out (grading has no network, and the kit's environment holds every package it needs).
_INSTALL = re.compile(r"^\s*(?:!|%)\s*(?:(?:python3?|py)\s+-m\s+)?(?:pip3?|conda|mamba|micromamba|uv\s+pip)\s+install\b")


def without_installs(nb) -> tuple[object, list[tuple[int, str]]]:
    """``nb`` with each package-install line turned into ``pass``, and a neutral note ``(cell, text)`` for each."""
    notes = []
    for i, cell in enumerate(nb.cells):
        if cell.cell_type != "code" or "install" not in cell.source:
            continue
        lines = cell.source.splitlines()
        for k, line in enumerate(lines):
            if _INSTALL.match(line):
                notes.append((i, f"`{line.strip()[:120]}` was left out when the grader ran the notebook (grading has "
                                 "no network, and the kit's environment already holds every package the notebooks "
                                 "use); this costs nothing"))
                lines[k] = line[: len(line) - len(line.lstrip())] + "pass  # left out by the grader: " + line.strip()
        cell.source = "\n".join(lines)
    return nb, notes

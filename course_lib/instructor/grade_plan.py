"""What a grading run grades: the notebooks and exercises, the hidden cases and the reference's verdicts on them, and
each submitted notebook read and placed (the grades that its structure decides).

* :func:`specs_to_grade`: the instructor notebooks and exercises to grade, and every
  exercise of the kit in order (the earlier steps an exercise may call).
* :func:`prepare_hidden`: the hidden cases of a grading-time seed, and the reference's verdicts and times on them.
* :func:`plan_submission`: each submitted notebook (the grader's copy) read within the grader's limits, its exercises
  placed (:mod:`.placement`) and each exercise cut out (:mod:`.extract`); an exercise whose structure gives it no
  credit is graded here, the others wait for the hidden checks (:mod:`.grade_run`).
"""

from __future__ import annotations

import ast
import atexit
import contextlib
import importlib
import os
import re
import secrets
import shutil
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path

import nbformat

from course_lib.instructor.cgroups import Cgroup
from course_lib.instructor.extract import extract_exercise
from course_lib.instructor.grade_report import exc_text
from course_lib.instructor.hidden import HiddenJob, build_hidden_fixtures, hold_in_memory, run_reference
from course_lib.instructor.notebooks import NOTEBOOKS_DIR, ExerciseSpec, NotebookSpec, kit_specs, python_source
from course_lib.instructor.placement import Placement, place_exercises, restored, without_installs
from course_lib.instructor.settings import (
    MAX_CELL_NODES,
    MAX_CODE_BYTES,
    MAX_CODE_NODES,
    MAX_NOTEBOOK_BYTES,
    Clock,
    Isolation,
    student_library,
)
from course_lib.instructor.submission import SubmissionCopy
from course_lib.paths import FIXTURES_DIR
from course_lib.validate import KitInputError

__all__ = ["HiddenCases", "prepare_hidden", "ready_hidden", "exercise_key", "ExerciseGrade", "GradingRun",
           "specs_to_grade", "plan_submission"]


@dataclass
class HiddenCases:
    """The hidden cases of one grading run and the reference's verdicts on them."""

    salt: int
    fixtures_dir: Path
    reference_passing: dict[str, list[str]]  # "notebook::exercise" -> passing verdicts of the reference
    reference_notes: dict[str, str] = field(default_factory=dict)
    reference_results: dict[str, object] = field(default_factory=dict)  # "notebook::exercise" -> the reference's CheckResult
    reference_seconds: dict[str, float] = field(default_factory=dict)  # "notebook::exercise" -> the reference's time
    reference_jobs: dict[str, HiddenJob] = field(default_factory=dict)  # to time the reference again, next to a slow run
    library: Path | None = None  # the student release's course_lib + data, imported by the student's processes


def exercise_key(e: ExerciseSpec) -> str:
    """``"notebook::exercise"``: how the hidden cases key an exercise."""
    return f"{e.notebook}::{e.name}"


def _preload(specs: list[NotebookSpec]) -> None:
    """Import torch, the check modules and the references, and load the notebooks' own cases, once, so that forked
    runs start fast."""
    with contextlib.suppress(ImportError):  # pragma: no cover
        import torch  # noqa: F401
    hold_in_memory(FIXTURES_DIR)  # the notebooks' own cases, on which the check cells' verdicts are computed
    for s in specs:
        for e in s.exercises:
            for mod in (e.check_module, e.reference.split(":")[0] if e.reference else None):
                if mod:
                    with contextlib.suppress(ImportError):
                        importlib.import_module(mod)


def _temporary_student_library(notebooks_dir: Path) -> Path:
    """The student release's library in a temporary folder outside every folder the sandbox hides (removed at exit)."""
    lib = Path(tempfile.mkdtemp(prefix="course-student-kit-"))
    atexit.register(shutil.rmtree, lib, True)
    os.chmod(lib, 0o755)
    return student_library(lib, notebooks_dir)


def prepare_hidden(specs: list[NotebookSpec], salt: int, workdir: Path, notebooks_dir: Path = NOTEBOOKS_DIR) -> HiddenCases:
    """Build the hidden fixtures for a grading-time seed and run the instructor's solutions on them.

    The reference runs in this process (the expected results never leave it). The student release's
    library, which the student's processes import, is written next to the fixtures' folder.
    """
    _preload(specs)
    fdir = Path(workdir) / "hidden-fixtures"
    build_hidden_fixtures(fdir, [e.check_module for s in specs for e in s.exercises], salt)
    cases = HiddenCases(int(salt), fdir, {})
    cases.library = _temporary_student_library(notebooks_dir)
    for s in specs:
        nb = nbformat.read(Path(notebooks_dir) / s.name, as_version=4)
        for e in s.exercises:
            ex = extract_exercise(nb, e.name, e.check_cell)
            job = HiddenJob(e.name, ex.code, e.check_module, e.check_function, str(fdir), e.reference,
                            allow_reference=True)
            cases.reference_jobs[exercise_key(e)] = job
            out = run_reference(job)
            cases.reference_passing[exercise_key(e)] = out.passing
            if out.result is not None:
                cases.reference_results[exercise_key(e)] = out.result
            cases.reference_seconds[exercise_key(e)] = out.seconds
            if out.failing or out.status != "ok":
                cases.reference_notes[exercise_key(e)] = (f"the reference fails {len(out.failing)} hidden check(s) for this "
                                                  f"seed ({out.status} {out.message}); they are not counted")
    return cases


def ready_hidden(hidden: HiddenCases | None, specs: list[NotebookSpec], salt: int | None, work: Path,
                 notebooks_dir: Path) -> HiddenCases:
    """The hidden cases of this run (made here, with a random seed unless ``salt``, when ``hidden`` is None)."""
    if hidden is None:
        salt = secrets.randbits(62) if salt is None else int(salt)
        hidden = prepare_hidden(specs, salt, work, notebooks_dir)
    else:
        _preload(specs)
    if hidden.library is None:
        hidden.library = _temporary_student_library(notebooks_dir)
    return hidden


def specs_to_grade(notebooks_dir: Path, notebooks: list[str] | None,
                    exercises: list[str] | None) -> tuple[list[NotebookSpec], list[tuple[str, str | None]]]:
    """The instructor notebooks (and their exercises) to grade, and every exercise of the kit in order with its
    reference (the earlier steps an exercise may call)."""
    unreleasable: list[str] = []
    all_specs = kit_specs(notebooks_dir, errors_out=unreleasable)
    for err in unreleasable:
        if not notebooks or any(err.startswith(n) for n in notebooks):
            raise KitInputError(f"cannot grade against an instructor notebook that cannot be released: {err}")
    specs = [s for s in all_specs if s.exercises and (not notebooks or any(s.name.startswith(n) for n in notebooks))]
    if exercises:
        specs = [replace(s, exercises=[e for e in s.exercises if e.name in exercises]) for s in specs]
        specs = [s for s in specs if s.exercises]
    if not specs:
        raise KitInputError(f"no instructor notebook or exercise matches {notebooks or ''} {exercises or ''}")
    return specs, [(e.name, e.reference) for s in all_specs for e in s.exercises]


@dataclass
class ExerciseGrade:
    notebook: str
    name: str
    points: float
    max_points: float
    feedback: list[str]
    status: str  # full, detail, partial, zero, not attempted, timeout, exit, error, missing, deleted, reordered,
    # check-edited
    hidden: dict = field(default_factory=dict)
    nbval: str = "not run"


@dataclass
class GradingRun:
    """What the grading of one submission shares between its steps."""

    specs: list[NotebookSpec]
    hidden: HiddenCases
    iso: Isolation
    submission: SubmissionCopy  # the grader's copy of the submission (regular files only)
    timeout: float
    allow_reference: bool
    grades: list[ExerciseGrade] = field(default_factory=list)
    plans: list = field(default_factory=list)  # (spec, nb or None, placements, [(cell or None, note)])
    to_nbval: dict = field(default_factory=dict)  # notebook -> the notebook nbval runs (check cells restored)
    pending: dict = field(default_factory=dict)  # notebook -> [(grade, spec, extracted code)]
    sandbox_seen: dict = field(default_factory=dict)
    kit: list = field(default_factory=list)  # [(exercise, reference)] of the whole kit, in order (the earlier steps)
    clock: Clock = field(default_factory=lambda: Clock(None))  # the submission's one clock
    cgroup: Cgroup | None = None  # the submission's cgroup (its exercises' and notebooks' cgroups inside)
    judge_cells: bool = False  # nbval runs: the check cells' verdicts on the notebooks' own cases are computed too
    public: dict = field(default_factory=dict)  # (notebook, exercise) -> (what its check printed there, or None; why)


def _plan_notebook(run: GradingRun, s: NotebookSpec, path: Path) -> None:
    """Read one submitted notebook (the grader's copy) and place its exercises; never raises."""
    unread = lambda *why: run.plans.append((s, None, {}, [(None, w) for w in why]))  # noqa: E731 - no credit, why
    if not path.is_file():
        left_out = [r for r in run.submission.refused if r.split(":")[0] in (s.name, f"notebooks/{s.name}", "notebooks")]
        return unread(*[f"{s.name} is missing from the submission ({r})" for r in left_out[:1]])
    size = path.stat().st_size
    if size > MAX_NOTEBOOK_BYTES:
        return unread(f"{s.name} is {size / 2**20:.0f} MiB, more than the grader reads ({MAX_NOTEBOOK_BYTES >> 20} "
                      "MiB): clear its outputs and submit it again")
    try:
        nb = nbformat.read(path, as_version=4)
        code = sum(len(c.source.encode("utf-8", "replace")) for c in nb.cells if c.cell_type == "code")
        if code > MAX_CODE_BYTES:
            return unread(f"the code cells of {s.name} hold {code / 1024:.0f} KiB of source, more than the grader "
                          f"reads ({MAX_CODE_BYTES >> 10} KiB); none of it was graded")
        notes, nodes = _unparseable_cells(nb)
        if nodes > MAX_CODE_NODES:
            return unread(f"the code cells of {s.name} hold {nodes} syntax-tree nodes, more than the grader reads "
                          f"({MAX_CODE_NODES}); none of it was graded")
        places = place_exercises(nb, s)
        nbv, installs = without_installs(restored(nb, s, places))
    except Exception as exc:  # noqa: BLE001 - a notebook the grader cannot read is that notebook's verdict
        return unread(f"the notebook cannot be read by the grader: {exc_text(exc)}")
    run.plans.append((s, nb, places, notes + installs))
    run.to_nbval[s.name] = nbv


def _unparseable_cells(nb) -> tuple[list, int]:
    """Turn cells that ``ast`` cannot take apart (nested too deeply: RecursionError) into syntax errors, with a note;
    and count the syntax-tree nodes of the others (the grader's work on the notebook is linear in them).

    Such a cell is then graded like a cell with a syntax error (its exercise: "not valid Python").
    """
    notes, nodes = [], 0
    for i, cell in enumerate(nb.cells):
        if cell.cell_type != "code":
            continue
        try:
            tree = compile(python_source(cell.source), f"<cell {i}>", "exec", ast.PyCF_ONLY_AST)
            count = sum(1 for _ in ast.walk(tree))
            if count > MAX_CELL_NODES:
                raise OverflowError(f"{count} syntax-tree nodes, more than the grader reads in one cell "
                                    f"({MAX_CELL_NODES})")
            nodes += count
        except SyntaxError:
            continue
        except Exception as exc:  # noqa: BLE001 - RecursionError, MemoryError, ValueError (null bytes), OverflowError
            heads = [ln for ln in cell.source.splitlines() if re.match(r"\s*(def|class) \w+", ln)]
            cell.source = "\n".join(heads[:20] + [f"<not parsed by the grader: {type(exc).__name__}>"])
            why = str(exc) if isinstance(exc, OverflowError) else "statements nested too deeply or too large"
            notes.append((i, f"the grader cannot parse this cell ({type(exc).__name__}: {why}); it counts as a "
                             "syntax error"))
    return notes, nodes


def _structure(run: GradingRun, s: NotebookSpec, e: ExerciseSpec, nb, places: dict, notes: list) -> ExerciseGrade:
    """The grade of one exercise after the structure check (pending the hidden checks when it passes)."""
    g = ExerciseGrade(s.name, e.name, 0.0, e.points, [], "zero")
    if nb is None:
        g.status = "missing"
        g.feedback.append(notes[0][1] if notes else f"{s.name} is missing from the submission")
        return g
    try:
        verdict = _structure_verdict(e, places)
        if verdict is not None:
            g.status, msg = verdict
            g.feedback.append(msg)
            return g
        ex = extract_exercise(nb, e.name, places[e.name].check_cell)
        if ex is None:
            g.status = "deleted"
            g.feedback.append(f"no top-level def of {e.name} before its check cell; no credit")
            return g
    except Exception as exc:  # noqa: BLE001 - the grader never dies on a submission
        g.status = "error"
        g.feedback.append(f"the grader could not take {e.name} out of the notebook ({exc_text(exc)}); no credit")
        return g
    g.feedback += [f"note: your {e.name} {pr}" for pr in ex.problems]
    run.pending.setdefault(s.name, []).append((g, e, ex))
    return g


def _structure_verdict(e: ExerciseSpec, places: dict[str, Placement]) -> tuple[str, str] | None:
    """``(status, feedback)`` when the notebook's structure gives exercise ``e`` no credit, else None."""
    p = places[e.name]
    if p.issue:
        status, detail = p.issue.split(": ", 1)
        if status == "error":
            return status, f"{detail}; no credit"
        return status, (f"exercise cell {status}: {detail}; no credit. Keep every exercise cell, in its place, "
                        "followed by its check cell.")
    if p.check_state != "intact":
        return "check-edited", (f"the check cell of {e.name} was {'deleted' if p.check_state == 'deleted' else 'edited'}"
                                "; no credit. Check cells must stay as released (the grader restores them and runs "
                                "its own hidden checks).")
    return None


def plan_submission(run: GradingRun) -> None:
    """Read and place every notebook to grade (:func:`_plan_notebook`), and start each exercise's grade: final where
    the notebook's structure gives it no credit, else pending its hidden checks."""
    root = run.submission.root
    folder = root / "notebooks" if (root / "notebooks").is_dir() else root
    for s in run.specs:
        _plan_notebook(run, s, folder / s.name)
    for s, nb, places, notes in run.plans:
        for e in s.exercises:
            run.grades.append(_structure(run, s, e, nb, places, notes))

"""Grading a student submission: nbval against the stored reference verdicts, plus hidden checks.

``python -m course_lib grade SUBMISSION_DIR [--json REPORT.json] [--markdown FEEDBACK.md]``

For every exercise of the instructor notebooks (:func:`course_lib.instructor.notebooks.kit_specs`; the
reference verdicts and check cells come from the instructor's side, never from the submission):

1. **Structure.** The submitted notebook must still hold the exercise's ``def`` before its check
   cell, in the original order, and the check cell unedited. A deleted or moved exercise, or an
   edited or deleted check cell, gets no credit (and the report says which).
2. **Scans** (a second line of defence). The exercise's code (cut out with its imports and
   helpers, :func:`course_lib.instructor.extract.extract_exercise`) must not import the reference
   solutions or the check machinery; the notebook must not patch, rebind (by assignment, import
   alias, loop or ``with`` target) or imitate the checks (:func:`course_lib.instructor.scan.scan_notebook`).
3. **Hidden checks, sealed by design.** The exercise's check function runs *here*, in the
   grader's process, on hidden cases (the fixtures rebuilt with a grading-time seed), and the
   reference's verdicts on the same cases are computed here too. The student's function is a
   proxy (:mod:`course_lib.instructor.remote`): each call sends the inputs as data to a sandboxed
   process (:mod:`course_lib.instructor.student_process`) that holds only the student's extracted code and the *student release* of
   ``course_lib`` (no reference solution on its path or in its view of the disk), and the
   outputs come back as data (JSON and ``np.save`` arrays, never pickle). The check itself runs
   in a worker of the grader, in the exercise's cgroup. **One clock, one memory cap** per
   exercise (:func:`course_lib.instructor.settings.exercise_seconds`) and per submission
   (``submission_timeout``, a cgroup for all of it): the student's code, the decoding of its
   replies, the check's work on them and the earlier steps it calls back all count; a looping
   exercise is stopped at its limit, an exercise that ends the process is named (``os._exit``),
   and either costs only itself. Its score is :func:`course_lib.checks.core.score` of its hidden
   checks relative to the reference's; an exercise whose every call raised
   ``NotImplementedError`` (the released stub) is "not attempted", in one line.
   **Each exercise on its own:** the earlier exercises that its code calls (``ransac_fundamental``
   → ``eight_point``, ``pnp_ransac`` → ``pnp_linear``, ``NeRF`` → ``positional_encoding``, ...) are
   answered there by their reference, through a call-back to the grader
   (:mod:`course_lib.instructor.oracle`), so a mistake costs points once, in its own exercise.
4. **nbval.** The notebooks run under nbval, with a per-cell time limit, after their check cells
   are restored to the reference source and outputs, in the same sandbox (the student release on
   ``PYTHONPATH``, a temporary copy of the submission as working directory, resource limits,
   namespaces). A notebook whose exercise looped or exited in its hidden run is run again with
   that exercise cut short, so the loop costs its time limit once. **Each mistake charged once:**
   under nbval a later exercise runs the student's own earlier functions; when its check cell
   fails there and an earlier exercise it calls failed its own hidden checks, the cell is judged
   again with the reference standing in for those earlier exercises (its check on the notebook's
   cases, the call-back of step 3), so the earlier mistake does not cost the later exercise.
5. **Slow code is graded.** An exercise's budget (:data:`DEFAULT_TIMEOUT`, 120 s) lets correct but
   slow code finish (a dense Jacobian, a residual per view); the feedback says when it was slow.

Points per exercise (default 10): 90 % times the hidden score, plus 10 % when all hidden checks
pass *and* the notebook's check cell printed the reference verdict under nbval. What the sandbox
enforced on this machine is written into the report (``isolation``).

**Fail closed.** Before anything of a submission runs, the grader starts one sandbox and checks it
(:mod:`course_lib.instructor.sandbox.jail`); where it cannot be made or verified, grading stops with
one line (:class:`~course_lib.instructor.sandbox.jail.IsolationError`). ``insecure=True``
(``--insecure``, a trusted local run) grades without a sandbox and says so in the report and the
feedback.

**Feedback is data** (:func:`to_markdown`): every text that can hold the student's words (messages
of their exceptions, names of their files) is shown in fenced blocks, stripped of control
characters, each message and the whole feedback capped; the totals are written by the grader above
any of it.
"""

from __future__ import annotations

import ast
import atexit
import contextlib
import copy
import importlib
import math
import os
import re
import secrets
import shutil
import tempfile
import time
import unicodedata
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path

import nbformat

from course_lib.checks.core import score_against, score_reasons
from course_lib.instructor.cgroups import HOW_TO_ENABLE, Cgroup
from course_lib.instructor.extract import extract_exercise
from course_lib.instructor.hidden import HiddenJob, build_hidden_fixtures, run_hidden, run_reference
from course_lib.instructor.nbval_run import NbvalRun
from course_lib.instructor.notebooks import NOTEBOOKS_DIR, ExerciseSpec, NotebookSpec, kit_specs, python_source
from course_lib.instructor.oracle import earlier_steps
from course_lib.instructor.placement import Placement, place_exercises, restored
from course_lib.instructor.plan import release_plan
from course_lib.instructor.sandbox import container, jail
from course_lib.instructor.sandbox.jail import IsolationError
from course_lib.instructor.scan import scan_exercise, scan_notebook
from course_lib.instructor.settings import (
    DEFAULT_EXERCISE_SECONDS,
    DEFAULT_SUBMISSION_SECONDS,
    MAX_CELL_NODES,
    MAX_CODE_BYTES,
    MAX_CODE_NODES,
    MAX_NOTEBOOK_BYTES,
    Clock,
    Isolation,
    Limits,
    exercise_seconds,
    nbval_seconds,
    student_library,
)
from course_lib.instructor.student_process import StudentProcess
from course_lib.instructor.submission import SubmissionCopy, copy_submission
from course_lib.paths import FIXTURES_DIR, REPO_ROOT
from course_lib.validate import KitInputError

__all__ = ["HiddenCases", "prepare_hidden", "grade_submission", "preflight", "to_markdown", "HIDDEN_SHARE",
           "IsolationError", "plain_text", "plain_data"]

HIDDEN_SHARE = 0.9  # of an exercise's points: the hidden checks; the rest: nbval verdict (with all hidden passing)
MAX_FEEDBACK_LINES = 6
DEFAULT_TIMEOUT = DEFAULT_EXERCISE_SECONDS  # s for the hidden checks of one exercise (settings.exercise_seconds)
#: Characters of one feedback message, messages of one exercise, and bytes of the whole Markdown feedback (a GitHub
#: comment holds 65 536 characters).
MAX_MESSAGE_CHARS, MAX_MESSAGES, MAX_FEEDBACK_BYTES = 600, 16, 60_000
#: An exercise whose hidden checks take longer than this, and than 10 times the reference's (plus 5 s), is graded and
#: told that it is slow.
SLOW_NOTE_SECONDS = 20.0


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


def _key(e: ExerciseSpec) -> str:
    return f"{e.notebook}::{e.name}"


def _preload(specs: list[NotebookSpec]) -> None:
    """Import torch, the check modules and the references once, so that forked runs start fast."""
    try:
        import torch  # noqa: F401
    except ImportError:  # pragma: no cover
        pass
    for s in specs:
        for e in s.exercises:
            for mod in (e.check_module, e.reference.split(":")[0] if e.reference else None):
                if mod:
                    try:
                        importlib.import_module(mod)
                    except ImportError:
                        pass


def _select(specs: list[NotebookSpec], exercises: list[str] | None) -> list[NotebookSpec]:
    if not exercises:
        return specs
    out = []
    for s in specs:
        keep = [e for e in s.exercises if e.name in exercises]
        if keep:
            out.append(NotebookSpec(s.name, keep, s.solution_modules, s.imports))
    return out


def _temporary_student_library(notebooks_dir: Path) -> Path:
    """The student release's library in a temporary folder outside every folder the sandbox hides (removed at exit)."""
    lib = Path(tempfile.mkdtemp(prefix="course-student-kit-"))
    atexit.register(shutil.rmtree, lib, True)
    os.chmod(lib, 0o755)
    return student_library(lib, notebooks_dir)


def prepare_hidden(specs: list[NotebookSpec], salt: int, workdir: Path, notebooks_dir: Path = NOTEBOOKS_DIR,
                   timeout: float = 120.0) -> HiddenCases:
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
            cases.reference_jobs[_key(e)] = job
            out = run_reference(job)
            cases.reference_passing[_key(e)] = out.passing
            if out.result is not None:
                cases.reference_results[_key(e)] = out.result
            cases.reference_seconds[_key(e)] = out.seconds
            if out.failing or out.status != "ok":
                cases.reference_notes[_key(e)] = (f"the reference fails {len(out.failing)} hidden check(s) for this "
                                                  f"seed ({out.status} {out.message}); they are not counted")
    return cases


# ---------------------------------------------------------------------------------------------
# Grading
# ---------------------------------------------------------------------------------------------


@dataclass
class ExerciseGrade:
    notebook: str
    name: str
    points: float
    max_points: float
    feedback: list[str]
    status: str  # full, detail, partial, zero, not attempted, flagged, timeout, exit, error, missing, deleted, reordered,
    # check-edited, tampered
    hidden: dict = field(default_factory=dict)
    nbval: str = "not run"


def _find_notebooks(sub: Path) -> Path:
    if (sub / "notebooks").is_dir():
        return sub / "notebooks"
    return sub


@dataclass
class _Run:
    """What the grading of one submission shares between its steps."""

    specs: list[NotebookSpec]
    omitted: set[str]
    hidden: HiddenCases
    iso: Isolation
    submission: SubmissionCopy  # the grader's copy of the submission (regular files only)
    timeout: float
    allow_reference: bool
    grades: list[ExerciseGrade] = field(default_factory=list)
    plans: list = field(default_factory=list)  # (spec, nb or None, placements, tamper reasons)
    to_nbval: dict = field(default_factory=dict)  # notebook -> the notebook nbval runs (check cells restored)
    pending: dict = field(default_factory=dict)  # notebook -> [(grade, spec, extracted code)]
    sandbox_seen: dict = field(default_factory=dict)
    kit: list = field(default_factory=list)  # [(exercise, reference)] of the whole kit, in order (the earlier steps)
    clock: Clock = field(default_factory=lambda: Clock(None))  # the submission's one clock
    cgroup: Cgroup | None = None  # the submission's cgroup (its exercises' and notebooks' cgroups inside)
    steps_of: dict = field(default_factory=dict)  # (notebook, exercise) -> (extracted code, the earlier steps it calls)


def grade_submission(
    submission: Path,
    *,
    notebooks: list[str] | None = None,
    exercises: list[str] | None = None,
    hidden: HiddenCases | None = None,
    salt: int | None = None,
    timeout: float = DEFAULT_TIMEOUT,
    cell_timeout: float = 120.0,
    run_nbval: bool = True,
    allow_reference: bool = False,
    workdir: Path | None = None,
    notebooks_dir: Path = NOTEBOOKS_DIR,
    nbval_jobs: int = 2,
    limits: Limits | None = None,
    insecure: bool = False,
    submission_timeout: float = DEFAULT_SUBMISSION_SECONDS,
) -> dict:
    """Grade a submission folder (a student kit, or a folder of notebooks) and return the report dict.

    The submission is data: everything works on the grader's copy of it (regular files only, :func:`copy_submission`).

    Args:
        submission: the student's folder; notebooks are read from ``submission/notebooks`` if it exists.
        notebooks: grade only notebooks whose names start with one of these (e.g. ``["01", "02"]``).
        exercises: grade only these exercises.
        hidden: hidden cases prepared by :func:`prepare_hidden` (made here when None).
        salt: the hidden seed (random when None; it is written into the report).
        timeout: wall-clock seconds for the hidden checks of one exercise (its definitions, every call, the
            grader's checks of the results and the call-backs together, once its process started); at least 10
            times the reference's time on the same cases plus 5 s (:func:`~.settings.exercise_seconds`).
        cell_timeout: seconds for one notebook cell under nbval.
        run_nbval: run the notebooks under nbval.
        allow_reference: the instructor's self-test: calls of the reference solution are allowed.
        workdir: scratch folder (a temporary one when None).
        notebooks_dir: the instructor notebooks.
        nbval_jobs: notebooks run under nbval at the same time.
        limits: the students' processes' limits (default :class:`Limits`).
        insecure: grade without a sandbox (a trusted local run; the report and the feedback say so).
        submission_timeout: wall-clock seconds for everything of this submission (the hidden checks and nbval);
            what is not graded by then gets no credit, and the feedback says so.

    Raises:
        IsolationError: the students' code cannot be run isolated here (and ``insecure`` is False): one line that
            says what is missing and how to enable it. Nothing of the submission ran.
    """
    t0 = time.perf_counter()
    clock = Clock(submission_timeout)
    if not Path(submission).is_dir():
        raise KitInputError(f"{submission} is not a folder: pass the student's kit (or a folder with their notebooks)")
    specs, omitted, kit = _specs_to_grade(notebooks_dir, notebooks, exercises)
    if not insecure:
        preflight(notebooks_dir, limits)  # one line, and no grading, where the sandbox cannot be made or verified
    with _scratch(workdir) as work, _shared_folder() as shared:
        copy = copy_submission(submission, shared / "submission", max_total_bytes=(limits or Limits()).submission_bytes)
        hidden = _ready_hidden(hidden, specs, salt, work, notebooks_dir, timeout)
        iso = Isolation.for_grading(hidden.library if not allow_reference else REPO_ROOT,
                                    [work, Path(hidden.fixtures_dir)], notebooks_dir, self_test=allow_reference,
                                    insecure=insecure, limits=limits)
        iso.scratch = shared
        run = _Run(specs, omitted, hidden, iso, copy, timeout, allow_reference, kit=kit, clock=clock,
                   cgroup=None if insecure else Cgroup.create(iso.limits.submission_memory_bytes,
                                                               4 * iso.limits.processes_total))
        nbval_run = None
        run_nbval = run_nbval and not (container.enabled() and not insecure)  # container mode: no TCP for kernels
        try:
            for s in specs:
                _plan_notebook(run, s, _find_notebooks(copy.root) / s.name)
            nbval_run = _start_nbval(run, cell_timeout, nbval_jobs) if run_nbval and run.to_nbval else None
            for s, nb, places, tamper in run.plans:
                for e in s.exercises:
                    run.grades.append(_structure_and_scans(run, s, e, nb, places, tamper))
            _hidden_checks(run, nbval_run)
            if nbval_run is not None:
                _add_nbval(run, nbval_run)
        finally:
            if nbval_run is not None:
                nbval_run.stop()
            if run.cgroup is not None:
                run.cgroup.close()
        report = _report(run.grades, hidden, time.perf_counter() - t0, allow_reference)
        report["insecure"] = bool(insecure)
        report["budgets"] = {"exercise seconds (at least)": float(timeout),
                             "submission seconds": float(submission_timeout),
                             "nbval seconds per notebook": nbval_seconds(cell_timeout) if run_nbval else None,
                             "memory bytes per exercise": iso.limits.memory_total_bytes,
                             "memory bytes per submission": iso.limits.submission_memory_bytes if run.cgroup else None}
        report["submission"] = {"files": copy.files, "bytes": copy.bytes,
                                "left out": [_cap(r, 300) for r in copy.refused[:50]]}
        report["isolation"] = {"insecure": bool(insecure), "hidden checks": run.sandbox_seen,
                               "nbval": nbval_run.sandbox if nbval_run else
                               {"note": container.NBVAL_NOTE} if container.enabled() and not insecure else {}}
        return plain_data(report)


def preflight(notebooks_dir: Path = NOTEBOOKS_DIR, limits: Limits | None = None) -> None:
    """Make one sandbox and check it, before anything of a submission is read or run; and make sure that a cgroup can
    be made for the totals of a submission (unless container mode applies, :func:`~.sandbox.container.enabled`).

    Raises:
        IsolationError: it cannot be made or does not check out (one line: what is missing, how to enable it).
    """
    probe = Cgroup.create(64 << 20, 8)
    if probe is None and not container.enabled():
        raise IsolationError(jail.refusal("no cgroup can be made here, so a submission's processes would have no "
                                          "memory total", HOW_TO_ENABLE))
    if probe is not None:
        probe.close()
    with _shared_folder() as lib:  # an empty library: the sandbox itself is what is checked here
        iso = Isolation.for_grading(lib, [], notebooks_dir, limits=limits)
        iso.scratch = lib
        with StudentProcess(iso, "", "preflight", None, 30.0):
            pass


@contextlib.contextmanager
def _shared_folder():
    """The run's folder, outside the grader's scratch: the grader's copy of the submission (which the students'
    sandboxes show read-only) and each student's process's own folder; only the grader and the student's uid may
    enter it (:func:`~.sandbox.jail.private_folder`), and it is removed at the end, whatever ended inside it."""
    tmp = jail.private_folder("course-grade-submission-")
    try:
        yield tmp
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _ready_hidden(hidden: HiddenCases | None, specs: list[NotebookSpec], salt: int | None, work: Path,
                  notebooks_dir: Path, timeout: float) -> HiddenCases:
    """The hidden cases of this run (made here, with a random seed unless ``salt``, when ``hidden`` is None)."""
    if hidden is None:
        salt = secrets.randbits(62) if salt is None else int(salt)
        hidden = prepare_hidden(specs, salt, work, notebooks_dir, timeout=max(timeout, 120.0))
    else:
        _preload(specs)
    if hidden.library is None:
        hidden.library = _temporary_student_library(notebooks_dir)
    return hidden


def _specs_to_grade(notebooks_dir: Path, notebooks: list[str] | None,
                    exercises: list[str] | None) -> tuple[list[NotebookSpec], set[str], list[tuple[str, str | None]]]:
    """The instructor notebooks (and their exercises) to grade, the modules the release omits, and every exercise
    of the kit in order with its reference (the earlier steps an exercise may call)."""
    unreleasable: list[str] = []
    all_specs = kit_specs(notebooks_dir, errors_out=unreleasable)
    omitted = set(release_plan(all_specs).omit)
    for err in unreleasable:
        if not notebooks or any(err.startswith(n) for n in notebooks):
            raise KitInputError(f"cannot grade against an instructor notebook that cannot be released: {err}")
    specs = [s for s in all_specs if s.exercises and (not notebooks or any(s.name.startswith(n) for n in notebooks))]
    specs = _select(specs, exercises)
    if not specs:
        raise KitInputError(f"no instructor notebook or exercise matches {notebooks or ''} {exercises or ''}")
    return specs, omitted, [(e.name, e.reference) for s in all_specs for e in s.exercises]


@contextlib.contextmanager
def _scratch(workdir: Path | None):
    """The grader's scratch folder (a temporary one, removed at the end, when ``workdir`` is None)."""
    if workdir is not None:
        Path(workdir).mkdir(parents=True, exist_ok=True)
        yield Path(workdir)
        return
    with tempfile.TemporaryDirectory(prefix="course-grade-") as tmp:
        yield Path(tmp)


def _plan_notebook(run: _Run, s: NotebookSpec, path: Path) -> None:
    """Read one submitted notebook (the grader's copy), place its exercises and scan it; never raises."""
    if not path.is_file():
        left_out = [r for r in run.submission.refused if r.split(":")[0] in (s.name, f"notebooks/{s.name}", "notebooks")]
        why = [(None, f"{s.name} is missing from the submission ({left_out[0]})")] if left_out else []
        run.plans.append((s, None, {}, why))
        return
    size = path.stat().st_size
    if size > MAX_NOTEBOOK_BYTES:
        run.plans.append((s, None, {}, [(None, f"{s.name} is {size / 2**20:.0f} MiB, more than the grader reads "
                                               f"({MAX_NOTEBOOK_BYTES >> 20} MiB): clear its outputs and submit it "
                                               "again")]))
        return
    try:
        nb = nbformat.read(path, as_version=4)
        code = sum(len(c.source.encode("utf-8", "replace")) for c in nb.cells if c.cell_type == "code")
        if code > MAX_CODE_BYTES:
            run.plans.append((s, None, {}, [(None, f"the code cells of {s.name} hold {code / 1024:.0f} KiB of source, "
                                                   f"more than the grader reads ({MAX_CODE_BYTES >> 10} KiB); none of "
                                                   "it was graded")]))
            return
        notes, nodes = _unparseable_cells(nb)
        if nodes > MAX_CODE_NODES:
            run.plans.append((s, None, {}, [(None, f"the code cells of {s.name} hold {nodes} syntax-tree nodes, more "
                                                   f"than the grader reads ({MAX_CODE_NODES}); none of it was graded")]))
            return
        places = place_exercises(nb, s)
        intact = {p.check_cell for p in places.values() if p.check_state == "intact"}
        tamper = scan_notebook(nb, intact, {e.check_function for e in s.exercises}, [e.verdict for e in s.exercises])
        nbv = restored(nb, s, places)
    except Exception as exc:  # noqa: BLE001 - a notebook the grader cannot read is that notebook's verdict
        run.plans.append((s, None, {}, [(None, f"the notebook cannot be read by the grader: {_exc_text(exc)}")]))
        return
    run.plans.append((s, nb, places, tamper + notes))
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


def _exc_text(exc: BaseException) -> str:
    return _short(f"{type(exc).__name__}: {exc}", 300)


def _start_nbval(run: _Run, cell_timeout: float, jobs: int) -> NbvalRun:
    """Start nbval on every readable notebook (a notebook whose exercise loops is restarted later)."""
    nbval_run = NbvalRun(run.submission.root, run.iso, cell_timeout, jobs=jobs, timeout=nbval_seconds(cell_timeout),
                         deadline=run.clock.deadline, cgroup=run.cgroup)
    for name, nbv in run.to_nbval.items():
        nbval_run.submit(name, nbv)
    return nbval_run


def _structure_and_scans(run: _Run, s: NotebookSpec, e: ExerciseSpec, nb, places: dict, tamper: list) -> ExerciseGrade:
    """The grade of one exercise after the structure check and the scans (pending the hidden checks when they pass)."""
    g = ExerciseGrade(s.name, e.name, 0.0, e.points, [], "zero")
    if nb is None:
        g.status = "missing"
        g.feedback.append(tamper[0][1] if tamper else f"{s.name} is missing from the submission")
        return g
    try:
        verdict = _structure_verdict(e, places, tamper)
        if verdict is not None:
            g.status, msg = verdict
            g.feedback.append(msg)
            return g
        ex = extract_exercise(nb, e.name, places[e.name].check_cell)
        if ex is None:
            g.status = "deleted"
            g.feedback.append(f"no top-level def of {e.name} before its check cell; no credit")
            return g
        flags = scan_exercise(ex.tree, e.reference, run.omitted)
    except Exception as exc:  # noqa: BLE001 - the grader never dies on a submission
        g.status = "error"
        g.feedback.append(f"the grader could not take {e.name} out of the notebook ({_exc_text(exc)}); no credit")
        return g
    if run.allow_reference:
        # the instructor's notebooks call the reference and the kit's engines (which stand on the references there)
        flags = [f for f in flags if "reference solution" not in f and "the kit's engine" not in f]
    if flags:
        g.status = "flagged"
        g.feedback += [f"your {e.name} {f}" for f in flags[:4]]
        g.feedback.append("no credit: exercise code must be your own and may only use numpy/scipy/torch "
                          "and the kit's non-solution modules")
        return g
    g.feedback += [f"note: your {e.name} {pr}" for pr in ex.problems]
    run.pending.setdefault(s.name, []).append((g, e, ex))
    return g


def _structure_verdict(e: ExerciseSpec, places: dict[str, Placement], tamper: list) -> tuple[str, str] | None:
    """``(status, feedback)`` when the notebook's structure gives exercise ``e`` no credit, else None."""
    p = places[e.name]
    if p.issue:
        status, detail = p.issue.split(": ", 1)
        if status == "error":
            return status, f"{detail}; no credit"
        return status, (f"exercise cell {status}: {detail}; no credit. Keep every exercise cell, in its place, "
                        "followed by its check cell.")
    if p.check_state != "intact":
        edited_here = [r for c, r in tamper if c == p.check_cell and p.check_state == "edited"]
        msg = f"the check cell of {e.name} was {'deleted' if p.check_state == 'deleted' else 'edited'}"
        if edited_here:
            msg += f" ({'; '.join(sorted(set(edited_here)))})"
        return "check-edited", msg + ("; no credit. Check cells must stay as released (the grader restores them and "
                                      "runs its own hidden checks).")
    edited_cells = {q.check_cell for q in places.values() if q.check_state == "edited"}
    elsewhere = [(c, r) for c, r in tamper if c not in edited_cells]
    unparsed = [(c, r) for c, r in elsewhere if "cannot parse this cell" in r]
    elsewhere = [(c, r) for c, r in elsewhere if (c, r) not in unparsed]
    if elsewhere:
        return "tampered", ("the notebook tampers with the checks: " + "; ".join(
            f"cell {c}: {r}" for c, r in elsewhere[:4]) + ". No credit for this notebook's exercises.")
    return None


def _hidden_checks(run: _Run, nbval_run: NbvalRun | None) -> None:
    """The hidden checks of every pending exercise; a notebook whose exercise looped or ended is rerun under nbval."""
    for s, nb, places, _ in run.plans:
        ended = {}  # exercises whose process ran out of time or ended: their check cells are not run again
        for g, e, ex in run.pending.get(s.name, []):
            if run.clock.expired():
                g.status, g.points, seen = "timeout", 0.0, {}
                g.feedback.append(f"not graded: the time for grading the whole submission ({run.clock.seconds:g} s) "
                                  "ran out before this exercise")
                continue
            steps = earlier_steps(ex.code, e.name, run.kit)
            run.steps_of[(s.name, e.name)] = (ex, steps)
            try:
                seen = _grade_hidden(g, e, ex, run, steps)
            except IsolationError:
                raise  # no sandbox, no grading
            except Exception as exc:  # noqa: BLE001 - the grader never dies on a submission
                g.status, g.points, seen = "error", 0.0, {}
                g.feedback.append(f"{e.name}: the grader could not run its hidden checks ({_exc_text(exc)})")
            run.sandbox_seen = run.sandbox_seen or seen
            if g.status in ("timeout", "exit"):
                ended[e.name] = (g.feedback[-1], ex.def_cell)
        if nbval_run is not None and s.name in run.to_nbval and ended:
            nbval_run.restart(s.name, _without_ended(copy.deepcopy(run.to_nbval[s.name]), places, ended))


def _add_nbval(run: _Run, nbval_run: NbvalRun) -> None:
    """The nbval verdict of each check cell, and the last 10 % of an exercise whose hidden checks all pass."""
    results, nbval_notes = nbval_run.results()
    by_key = {(g.notebook, g.name): g for g in run.grades}
    for s, nb, places, _ in run.plans:
        if nb is None:
            continue
        for e in s.exercises:
            g, p = by_key[(s.name, e.name)], places[e.name]
            if p.check_cell is None:
                continue
            code_index = sum(1 for c in nb.cells[:p.check_cell] if c.cell_type == "code")
            r = results.get((s.name, code_index))
            g.nbval = "not run" if r is None else ("pass" if r == "pass" else "fail")
            if g.status != "full":
                continue
            weak = _weak_earlier(run, s.name, e.name)
            if g.nbval == "pass":
                g.points = round(e.points, 2)
                g.feedback[0] = (f"full marks: all {g.hidden['total']} hidden checks pass and the check cell "
                                 "prints the reference verdict")
            elif weak and _check_cell_with_reference(run, e):
                g.points, g.nbval = round(e.points, 2), "pass (reference standing in)"
                g.feedback[0] = (f"full marks: all {g.hidden['total']} hidden checks pass, and with the reference "
                                 f"standing in for your {' and '.join(weak)} (graded on its own) the check cell prints "
                                 "the reference verdict")
            else:
                why = nbval_notes.get(s.name) or (r if r else "no result")
                g.feedback.append(f"in your notebook the check cell of {e.name} does not print the reference "
                                  f"verdict when the notebook runs top to bottom ({_short(why)}); restart the "
                                  f"kernel, run all cells, and fix what differs (−{(1 - HIDDEN_SHARE) * 100:.0f} %)")


def _weak_earlier(run: _Run, notebook: str, name: str) -> list[str]:
    """The earlier exercises that ``name``'s code calls and whose own hidden checks did not all pass."""
    _, steps = run.steps_of.get((notebook, name), (None, {}))
    status = {g.name: g.status for g in run.grades}
    return [n for n in steps if status.get(n) not in (None, "full", "detail")]


def _check_cell_with_reference(run: _Run, e: ExerciseSpec) -> bool:
    """Whether the exercise's check cell prints the reference verdict with the reference standing in for the earlier
    exercises its code calls: its check on the notebook's own (public) cases, the student's function in the sandbox
    and the earlier steps answered by their references (the hidden checks' call-back, :mod:`.oracle`).

    Each mistake is charged once (issue 29): under nbval a later exercise runs the student's own earlier functions,
    so an earlier mistake would cost the later exercise its nbval share too; this is that share's verdict then.
    """
    ex, steps = run.steps_of[(e.notebook, e.name)]
    budget = exercise_seconds(run.timeout, run.hidden.reference_seconds.get(_key(e), 0.0), calls_back=True)
    if run.clock.expired():
        return False
    try:
        out = run_hidden(HiddenJob(e.name, ex.code, e.check_module, e.check_function, str(FIXTURES_DIR), e.reference,
                                   run.allow_reference, str(run.submission.root), steps), budget, run.iso,
                         cgroup_parent=run.cgroup, deadline=run.clock.deadline)
    except Exception:  # noqa: BLE001 - the grader never dies on a submission; the share stays unearned
        return False
    return out.status == "ok" and out.result is not None and out.result.ok


def _without_ended(nb, places: dict[str, Placement], ended: dict[str, tuple[str, int]]):
    """The notebook for nbval, with the exercises that looped or ended the process in the hidden run cut short.

    Their check cells raise at once, and their function is replaced (after its own cell) by one that
    raises, so that no later cell loops on it again: a looping exercise costs its time limit once.
    """
    for name, (why, def_cell) in ended.items():
        msg = f"not run again by the grader: {why}"
        nb.cells[places[name].check_cell].source = f"raise RuntimeError({msg!r})"
        nb.cells[def_cell].source += (f"\n\n\ndef {name}(*args, **kwargs):  # added by the grader\n"
                                      f"    raise RuntimeError({msg!r})\n")
    return nb


def _grade_hidden(g: ExerciseGrade, e: ExerciseSpec, ex, run: _Run, steps: dict[str, str]) -> dict:
    """Run the hidden checks of one exercise (its function in a sandboxed process) and fill in its grade.

    ``steps``: the earlier exercises its code calls, answered by their references (:mod:`.oracle`).
    Returns what the student's process was confined by.
    """
    hidden = run.hidden
    budget = exercise_seconds(run.timeout, hidden.reference_seconds.get(_key(e), 0.0), calls_back=bool(steps))
    out = run_hidden(HiddenJob(e.name, ex.code, e.check_module, e.check_function, str(hidden.fixtures_dir),
                               e.reference, run.allow_reference, str(run.submission.root), steps), budget, run.iso,
                     cgroup_parent=run.cgroup, deadline=run.clock.deadline)
    ref = hidden.reference_passing.get(_key(e), [])
    matched = sum((Counter(out.passing) & Counter(ref)).values())
    g.hidden = {"passed": matched, "total": len(ref), "seconds": round(out.seconds, 1), "budget seconds": budget,
                "memory": out.memory}
    if out.status == "timeout":
        g.status = "timeout"
        g.feedback.append(f"{e.name} did not finish on the hidden cases: {out.message}. No credit; "
                          "the other exercises were graded.")
        return out.sandbox
    if not out.attempted:
        g.status = "not attempted"
        g.feedback = [f"not attempted: your {e.name} still raises NotImplementedError (the released stub)"]
        return out.sandbox
    if out.status == "exit":
        g.status = "exit"
        g.feedback.append(f"{e.name}: {out.message} while its hidden checks ran. No credit; the other exercises "
                          "were graded.")
        return out.sandbox
    if out.status != "ok" or out.result is None:
        g.status = "error"
        g.feedback.append(f"{e.name}: {out.message}")
        return out.sandbox
    reference = hidden.reference_results.get(_key(e))
    frac = score_against(out.result, reference) if reference is not None else 0.0
    g.points = round(e.points * HIDDEN_SHARE * frac, 2)
    g.status = "full" if frac >= 1 else ("partial" if frac > 0 else "zero")
    details = out.result.details_failed
    if not ref:
        g.feedback.append("no hidden check could be calibrated for this exercise (instructor: see the notes)")
    elif frac >= 1 and details:
        g.status = "detail"
        g.feedback.append(f"the hidden checks pass, but not in the documented form (−{(1 - HIDDEN_SHARE) * 10:g} "
                          "point: the share of a perfect exercise): " + "; ".join(details[:MAX_FEEDBACK_LINES]))
    elif frac >= 1:
        g.feedback.append(f"all {len(ref)} hidden checks pass")
    else:
        why = score_reasons(out.result, reference) if reference is not None else []
        g.feedback.append(f"{matched} of {len(ref)} hidden checks pass (new synthetic cases), "
                          f"{frac * 100:.0f} % of the hidden-check points"
                          + (f" ({'; '.join(why)}: the scoring rule, README)" if why else "") + ". What failed:")
        fails = out.failing or [f"{ln}: not passed" for ln in sorted((Counter(ref) - Counter(out.passing)))]
        g.feedback += [f"✘ {ln}" for ln in fails[:MAX_FEEDBACK_LINES]]
        missing = _not_run(out.result, reference)
        if missing:
            g.feedback.append(f"{missing} hidden check(s) did not run (a call returned nothing usable before them); "
                              "they count as failed")
        if len(fails) > MAX_FEEDBACK_LINES:
            g.feedback.append(f"... and {len(fails) - MAX_FEEDBACK_LINES} more")
    slow = _slowness(hidden, e, out.seconds)
    if slow:
        g.feedback.append(f"note: correct answers earn their points however long they take within the time limit, "
                          f"but your {e.name} is slow: {slow} ({_SLOW_HINTS.get(e.name, _SLOW_HINT)})")
    if _key(e) in hidden.reference_notes:
        g.feedback.append("note: " + hidden.reference_notes[_key(e)])
    return out.sandbox


#: A note on speed only when the student's hidden checks take this many times as long as the reference's, both
#: timed one after the other on the same machine (so the note does not depend on the machine or its load).
SLOW_RATIO = 10.0


def _slowness(hidden: HiddenCases, e: ExerciseSpec, seconds: float) -> str | None:
    """A machine-independent note on a slow exercise, or None.

    A wall time beyond ``SLOW_NOTE_SECONDS`` and 10x the reference's calibration run only selects the candidates;
    the note itself compares with the reference timed again *right after* the student's run, on the same hidden
    cases and machine, and says the ratio (rounded to a coarse step) without seconds: a busy machine slows both.
    """
    ref0 = hidden.reference_seconds.get(_key(e), 0.0)
    job = hidden.reference_jobs.get(_key(e))
    if seconds <= max(SLOW_NOTE_SECONDS, 10 * ref0 + 5) or job is None:
        return None
    now = run_reference(job)
    if now.status != "ok" or now.seconds <= 0:
        return None
    ratio = seconds / max(now.seconds, 0.05)
    if ratio < SLOW_RATIO:
        return None
    step = 10.0 ** math.floor(math.log10(ratio))
    return (f"its hidden checks took about {math.floor(ratio / step) * step:g} times as long as the reference's on the "
            "same cases, timed one after the other on the same machine")


#: What usually makes an exercise slow: Python loops where numpy works on all rows at once.
_SLOW_HINT = "look for Python loops over points, matches or rays that numpy can do on all rows at once"
_SLOW_HINTS = {
    "triangulate_nonlinear": "one residual function for all views and points, vectorized, is much faster",
    "pnp_nonlinear": "compute the residuals of all points at once, without a Python loop",
    "bundle_adjust": "vectorize the residuals and give least_squares the Jacobian's sparsity (jac_sparsity)",
}


def _not_run(result, reference) -> int:
    """How many point checks the reference recorded on these cases and the student's run did not record at all."""
    if reference is None:
        return 0
    points = sum(1 for v in reference.verdicts if v.kind == "points")
    return max(0, points - sum(1 for v in result.verdicts if v.kind == "points"))


def _short(text: str, n: int = 160) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= n else text[: n - 3] + "..."


def _cap(text: str, n: int = MAX_MESSAGE_CHARS) -> str:
    """``text`` on one line, plain (:func:`plain_text`), at most ``n`` characters (student text is data)."""
    text = " ".join(plain_text(str(text)).split())
    return text if len(text) <= n else text[: n - 30] + f" ... ({len(text) - n + 30} characters left out)"


#: ANSI escape sequences (removed whole, so that no "[31m" is left behind).
_ANSI = re.compile(r"\x1b\[[0-9;?]*[ -/]*[@-~]|\x1b[@-_]")
#: Categories never shown from a student's text: controls, format characters (bidi marks and overrides, zero-width
#: joiners, the soft hyphen, U+061C, U+206A-F, U+FFF9-B, the tag characters U+E0000-E007F that spell hidden text),
#: surrogates, private use, unassigned code points, line and paragraph separators.
_HIDDEN_CATEGORIES = {"Cc", "Cf", "Cs", "Co", "Cn", "Zl", "Zp"}
#: Variation selectors (invisible, and a known way to smuggle bytes behind a visible character).
_SELECTORS = ((0xFE00, 0xFE0F), (0xE0100, 0xE01EF), (0x180B, 0x180F))


def _hidden_char(c: str) -> bool:
    o = ord(c)
    return unicodedata.category(c) in _HIDDEN_CATEGORIES or any(a <= o <= b for a, b in _SELECTORS)


def plain_text(text: str) -> str:
    """``text`` as plain data: ANSI escapes removed; every control, format (bidi, zero-width, soft hyphen, tag
    characters), surrogate, private-use, unassigned or separator character and variation selector written as its
    escape (``\\u202e``); tabs and newlines kept. The one sanitiser of everything the report and the feedback show."""
    text = _ANSI.sub("", text)
    if text.isascii():
        return _ASCII_CONTROL.sub(_escape, text)
    return "".join(_escape_char(c) if c not in "\t\n" and _hidden_char(c) else c for c in text)


_ASCII_CONTROL = re.compile(r"[\x00-\x08\x0b-\x1f\x7f]")


def _escape(m: re.Match) -> str:
    return _escape_char(m.group())


def _escape_char(c: str) -> str:
    o = ord(c)
    return f"\\x{o:02x}" if o < 0x100 else (f"\\u{o:04x}" if o < 0x10000 else f"\\U{o:08x}")


def plain_data(obj):
    """``obj`` (a report: dicts, lists, strings, numbers) with every string, keys included, made :func:`plain_text`."""
    if isinstance(obj, str):
        return plain_text(obj)
    if isinstance(obj, dict):
        return {plain_data(k): plain_data(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain_data(v) for v in obj]
    return obj


def _report(grades: list[ExerciseGrade], hidden: HiddenCases, seconds: float, allow_reference: bool) -> dict:
    notebooks = []
    for name in sorted({g.notebook for g in grades}):
        gs = [g for g in grades if g.notebook == name]
        notebooks.append({"notebook": name, "points": round(sum(g.points for g in gs), 2),
                          "max_points": round(sum(g.max_points for g in gs), 2)})
    return {
        "total": round(sum(g.points for g in grades), 2),
        "max": round(sum(g.max_points for g in grades), 2),
        "hidden_seed": hidden.salt,
        "instructor_self_test": allow_reference,
        "seconds": round(seconds, 1),
        "notebooks": notebooks,
        "exercises": [dict(asdict(g), feedback=[_cap(f, 2000) for f in g.feedback[:MAX_MESSAGES]]) for g in grades],
    }


def to_markdown(report: dict) -> str:
    """Feedback for the student, as Markdown (also the GitHub job summary and the CI template's issue comment).

    Feedback is data: the grader writes the title, the totals and the table of points (exercise names come from the
    instructor's notebooks) before any text that can hold the student's words; every such text (the feedback
    messages, which quote the student's exceptions, and the names of their files) is shown in a fenced block whose
    fence is longer than any run of backticks in it, without control characters, each message at most
    :data:`MAX_MESSAGE_CHARS` characters and :data:`MAX_MESSAGES` per exercise; the whole feedback stays under
    :data:`MAX_FEEDBACK_BYTES` (the details of the last exercises are left out, saying so, past it).
    """
    report = plain_data(report)
    head = ["# Grading feedback", "", f"**Total: {report['total']:g} / {report['max']:g} points**", ""]
    if report.get("insecure"):
        head += ["**Graded with `--insecure`: your code ran without the grader's sandbox (a trusted local run).**", ""]
    head += ["| notebook | exercise | points | status | seconds |", "|---|---|---:|---|---:|"]
    for g in report["exercises"]:
        secs = g.get("hidden", {}).get("seconds")
        head.append(f"| {g['notebook']} | `{g['name']}` | {g['points']:g} / {g['max_points']:g} | {g['status']} | "
                    f"{'' if secs is None else format(secs, 'g')} |")
    head.append("")
    tail = [f"<sub>hidden seed {report['hidden_seed']}, graded in {report['seconds']:g} s{_sandbox_line(report)}"
            "</sub>", ""]
    left_out = report.get("submission", {}).get("left out", [])
    if left_out:
        tail = ["## Files of your submission the grader did not copy", "",
                *_fenced([_cap(r, 300) for r in left_out[:20]]), ""] + tail
    budget = MAX_FEEDBACK_BYTES - len("\n".join(head + tail).encode()) - 400
    body: list[str] = []
    skipped = 0
    for nb in report["notebooks"]:
        part = [f"## {nb['notebook']}: {nb['points']:g} / {nb['max_points']:g}", ""]
        for g in (g for g in report["exercises"] if g["notebook"] == nb["notebook"]):
            part += [f"### `{g['name']}`: {g['points']:g} / {g['max_points']:g}", ""]
            lines = [f"- {_cap(f)}" for f in g["feedback"][:MAX_MESSAGES]]
            if len(g["feedback"]) > MAX_MESSAGES:
                lines.append(f"- ... and {len(g['feedback']) - MAX_MESSAGES} more messages")
            if g["nbval"] != "not run":
                lines.append(f"- nbval check cell: {g['nbval']}")
            block = _fenced(lines) + [""] if lines else []
            if len("\n".join(body + part + block).encode()) > budget:
                skipped += 1
                block = ["*(details left out: the feedback is capped at "
                         f"{MAX_FEEDBACK_BYTES // 1000} kB; your instructor has them all)*", ""]
            part += block
        body += part
    return "\n".join(head + body + tail) + "\n"


def _fenced(lines: list[str]) -> list[str]:
    """``lines`` as one fenced block of plain text (a fence longer than any run of backticks inside)."""
    longest = max((len(m) for ln in lines for m in re.findall(r"`+", ln)), default=0)
    fence = "`" * max(3, longest + 1)
    return [fence + "text", *lines, fence]


def _sandbox_line(report: dict) -> str:
    """One line on what confined the student's code (from the report's ``isolation``)."""
    box = report.get("isolation", {}).get("hidden checks", {})
    if report.get("insecure"):
        return "; no sandbox (--insecure)"
    if not isinstance(box, dict) or not box:
        return ""
    if box.get("tool") == "container mode":
        return "; container mode: an unprivileged uid, no network, the hidden cases closed to it, totals"
    if box.get("namespaces") is True and box.get("read_only") is True:
        totals = "cgroup totals" if "whole process tree" in str(box.get("memory", "")) else "per-process limits"
        return f"; sandbox: bubblewrap, namespaces, no network, an allow-listed read-only file system, {totals}"
    return "; sandbox: unknown"

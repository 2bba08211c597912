"""Grading a student submission, from start to report: hidden checks, plus nbval with the grader's own verdicts.

``python -m course_lib grade SUBMISSION_DIR [--json REPORT.json] [--markdown FEEDBACK.md]``

For every exercise of the instructor notebooks (:func:`course_lib.instructor.notebooks.kit_specs`; the
reference verdicts and check cells come from the instructor's side, never from the submission):

1. **Structure.** The submitted notebook must still hold the exercise's ``def`` before its check
   cell, in the original order, and the check cell unedited. A deleted or moved exercise, or an
   edited or deleted check cell, gets no credit (and the report says which).
2. **Scan** (a second line of defence). The exercise's code (cut out with its imports and
   helpers, :func:`course_lib.instructor.extract.extract_exercise`) must not import the reference
   solutions or the check machinery (:func:`course_lib.instructor.scan.scan_exercise`). The rest of
   the notebook is not scanned: no verdict is read from what it prints (step 4).
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
4. **nbval, and a verdict no notebook can forge.** The notebooks run under nbval, with a per-cell
   time limit, after their check cells are restored to the reference source, in the same sandbox
   (the student release on ``PYTHONPATH``, a temporary copy of the submission as working directory,
   resource limits, namespaces); package installs (``!pip install``) are left out, with a neutral
   note. nbval says whether each check cell runs when the notebook runs top to bottom; what the cell
   prints is not compared (code in the notebook could filter or forge it). The check cell's verdict
   comes from the grader: when the hidden checks all pass, the same worker runs the check on the
   notebook's own cases with the student's function, the earlier steps it calls answered by their
   references (**each mistake charged once**, in its own exercise), and compares what it prints with
   the reference verdict. A notebook whose exercise looped or exited in its hidden run is run again
   with that exercise cut short, so the loop costs its time limit once.
5. **Slow code is graded.** An exercise's budget (:data:`DEFAULT_TIMEOUT`, 120 s) lets correct but
   slow code finish (a dense Jacobian, a residual per view); the feedback says when it was slow.

Points per exercise (default 10): 90 % times the hidden score, plus 10 % when all hidden checks
pass, the notebook runs top to bottom through the check cell under nbval, and the check on the
notebook's own cases, run by the grader, prints the reference verdict. What the sandbox
enforced on this machine is written into the report (``isolation``).

**Fail closed.** Before anything of a submission runs, the grader starts one sandbox and checks it
(:mod:`course_lib.instructor.sandbox.jail`); where it cannot be made or verified, grading stops with
one line (:class:`~course_lib.instructor.sandbox.jail.IsolationError`). ``insecure=True``
(``--insecure``, a trusted local run) grades without a sandbox and says so in the report and the
feedback.

This module runs a grading from start to report (:func:`grade_submission`); the steps live in three modules:
:mod:`~course_lib.instructor.grade_plan` (what is graded: the notebooks, the hidden cases, steps 1 and 2),
:mod:`~course_lib.instructor.grade_run` (running it: steps 3 to 5) and :mod:`~course_lib.instructor.grade_report`
(the report and the feedback, which is data: every text that can hold the student's words is fenced, capped and
made plain by one sanitiser, :func:`~course_lib.instructor.grade_report.plain_text`).
"""

from __future__ import annotations

import contextlib
import shutil
import tempfile
import time
from pathlib import Path

from course_lib.instructor.cgroups import HOW_TO_ENABLE, Cgroup
from course_lib.instructor.grade_plan import (
    ExerciseGrade,
    GradingRun,
    HiddenCases,
    plan_submission,
    prepare_hidden,
    ready_hidden,
    specs_to_grade,
)
from course_lib.instructor.grade_report import (
    MAX_FEEDBACK_BYTES,
    MAX_MESSAGE_CHARS,
    MAX_MESSAGES,
    cap,
    grading_report,
    plain_data,
    plain_text,
    to_markdown,
)
from course_lib.instructor.grade_run import HIDDEN_SHARE, add_nbval, hidden_checks, start_nbval
from course_lib.instructor.nbval_run import NbvalRun
from course_lib.instructor.notebooks import NOTEBOOKS_DIR
from course_lib.instructor.sandbox import container, jail
from course_lib.instructor.sandbox.jail import IsolationError
from course_lib.instructor.settings import (
    DEFAULT_EXERCISE_SECONDS,
    DEFAULT_SUBMISSION_SECONDS,
    Clock,
    Isolation,
    Limits,
    nbval_seconds,
)
from course_lib.instructor.student_process import StudentProcess
from course_lib.instructor.submission import copy_submission
from course_lib.paths import REPO_ROOT
from course_lib.validate import KitInputError

__all__ = ["HiddenCases", "ExerciseGrade", "prepare_hidden", "grade_submission", "preflight", "to_markdown",
           "HIDDEN_SHARE", "IsolationError", "plain_text", "plain_data", "DEFAULT_TIMEOUT", "MAX_FEEDBACK_BYTES",
           "MAX_MESSAGE_CHARS", "MAX_MESSAGES"]

DEFAULT_TIMEOUT = DEFAULT_EXERCISE_SECONDS  # s for the hidden checks of one exercise (settings.exercise_seconds)


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
    if not Path(submission).is_dir():
        raise KitInputError(f"{submission} is not a folder: pass the student's kit (or a folder with their notebooks)")
    specs, omitted, kit = specs_to_grade(notebooks_dir, notebooks, exercises)
    if not insecure:
        preflight(notebooks_dir, limits)  # one line, and no grading, where the sandbox cannot be made or verified
    with _scratch(workdir) as work, _shared_folder() as shared:
        copy = copy_submission(submission, shared / "submission", max_total_bytes=(limits or Limits()).submission_bytes)
        hidden = ready_hidden(hidden, specs, salt, work, notebooks_dir, timeout)
        iso = Isolation.for_grading(hidden.library if not allow_reference else REPO_ROOT,
                                    [work, Path(hidden.fixtures_dir)], notebooks_dir, self_test=allow_reference,
                                    insecure=insecure, limits=limits)
        iso.scratch = shared
        run = GradingRun(specs, omitted, hidden, iso, copy, timeout, allow_reference, kit=kit,
                         clock=Clock(submission_timeout),
                         cgroup=None if insecure else Cgroup.create(iso.limits.submission_memory_bytes,
                                                                     4 * iso.limits.processes_total))
        nbval_run = None
        run_nbval = run_nbval and not (container.enabled() and not insecure)  # container mode: no TCP for kernels
        try:
            plan_submission(run)
            nbval_run = start_nbval(run, cell_timeout, nbval_jobs) if run_nbval and run.to_nbval else None
            run.judge_cells = nbval_run is not None
            hidden_checks(run, nbval_run)
            if nbval_run is not None:
                add_nbval(run, nbval_run)
        finally:
            if nbval_run is not None:
                nbval_run.stop()
            if run.cgroup is not None:
                run.cgroup.close()
        budgets = {"exercise seconds (at least)": float(timeout), "submission seconds": float(submission_timeout),
                   "nbval seconds per notebook": nbval_seconds(cell_timeout) if run_nbval else None}
        return _report_of(run, nbval_run, time.perf_counter() - t0, budgets)


def _report_of(run: GradingRun, nbval_run: NbvalRun | None, seconds: float, budgets: dict) -> dict:
    """The report of a finished grading: points and feedback, budgets, the submission's copy, the isolation."""
    insecure = run.iso.insecure
    notes = {s.name: [f"cell {c}: {r}" for c, r in n if c is not None] for s, nb, _, n in run.plans if nb is not None}
    report = grading_report(run.grades, run.hidden.salt, seconds, run.allow_reference, notes)
    report["insecure"] = bool(insecure)
    report["budgets"] = dict(budgets, **{
        "memory bytes per exercise": run.iso.limits.memory_total_bytes,
        "memory bytes per submission": run.iso.limits.submission_memory_bytes if run.cgroup else None})
    report["submission"] = {"files": run.submission.files, "bytes": run.submission.bytes,
                            "left out": [cap(r, 300) for r in run.submission.refused[:50]]}
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


@contextlib.contextmanager
def _scratch(workdir: Path | None):
    """The grader's scratch folder (a temporary one, removed at the end, when ``workdir`` is None)."""
    if workdir is not None:
        Path(workdir).mkdir(parents=True, exist_ok=True)
        yield Path(workdir)
        return
    with tempfile.TemporaryDirectory(prefix="course-grade-") as tmp:
        yield Path(tmp)

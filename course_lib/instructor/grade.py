"""Grading a student submission, from start to report: hidden checks, plus nbval with the grader's own verdicts.

``python -m course_lib grade SUBMISSION_DIR [--json REPORT.json] [--markdown FEEDBACK.md]``

For every exercise of the instructor notebooks (the check cells and reference verdicts come from the instructor's
side, never from the submission), :func:`grade_submission` runs four steps, each in the module named:

1. **Structure** (:mod:`.grade_plan`): the submitted notebook must still hold the exercise's ``def`` before its
   check cell, in the original order, and the check cell unedited; else no credit, and the report says which.
2. **Hidden checks, sealed by design** (:mod:`.grade_run`, :mod:`.hidden`): the exercise's check runs in a worker of
   the grader on hidden cases (the fixtures rebuilt with a grading-time seed), the student's function in a sandboxed
   process that holds only the student's code and the student release of ``course_lib`` (:mod:`.student_process`);
   the earlier exercises it calls are answered by their references (:mod:`.oracle`), so each mistake costs points
   once. **One clock, one memory cap** per exercise and per submission count everything the submission causes.
3. **nbval, and a verdict no notebook can forge** (:mod:`.nbval_run`): the notebooks run under nbval in the same
   sandbox, check cells restored; the check cell's verdict is computed by the grader, on the notebook's own cases.
4. **Slow code is graded**: an exercise's budget (:data:`~.settings.DEFAULT_EXERCISE_SECONDS`) lets correct but slow
   code finish; the feedback says when it was slow.

Points per exercise (default 10): 90 % times the hidden score (:func:`course_lib.checks.core.score_against` the
reference's), plus 10 % when all hidden checks pass, the notebook runs top to bottom through the check cell, and
the grader's check on the notebook's own cases prints the reference verdict. The report and the feedback
(:mod:`.grade_report`) are data: student text fenced, capped and made plain by one sanitiser.

**Fail closed.** Before anything of a submission runs, the grader starts one sandbox and checks it
(:mod:`course_lib.instructor.sandbox.jail`); where it cannot be made or verified, grading stops with one line
(:class:`~course_lib.instructor.sandbox.jail.IsolationError`). ``insecure=True`` (``--insecure``, a trusted local
run) grades without a sandbox and says so in the report and the feedback.
"""

from __future__ import annotations

import contextlib
import shutil
import tempfile
import time
from pathlib import Path

from course_lib.instructor.cgroups import HOW_TO_ENABLE, Cgroup
from course_lib.instructor.grade_plan import (
    GradingRun,
    HiddenCases,
    plan_submission,
    prepare_hidden,
    ready_hidden,
    specs_to_grade,
)
from course_lib.instructor.grade_report import (
    MAX_FEEDBACK_BYTES,
    cap,
    grading_report,
    plain_data,
    plain_text,
    to_markdown,
)
from course_lib.instructor.grade_run import HIDDEN_SHARE, add_nbval, hidden_checks, start_nbval
from course_lib.instructor.nbval_run import NbvalRun
from course_lib.instructor.notebooks import NOTEBOOKS_DIR
from course_lib.instructor.sandbox import container, jail, launch
from course_lib.instructor.sandbox.jail import IsolationError
from course_lib.instructor.settings import (
    DEFAULT_CELL_SECONDS,
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

__all__ = ["HiddenCases", "prepare_hidden", "grade_submission", "preflight", "to_markdown", "HIDDEN_SHARE",
           "IsolationError", "plain_text", "plain_data", "MAX_FEEDBACK_BYTES"]


def grade_submission(
    submission: Path,
    *,
    notebooks: list[str] | None = None,
    exercises: list[str] | None = None,
    hidden: HiddenCases | None = None,
    salt: int | None = None,
    timeout: float = DEFAULT_EXERCISE_SECONDS,
    cell_timeout: float = DEFAULT_CELL_SECONDS,
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
        timeout: wall-clock seconds for the hidden checks of one exercise, at the least
            (:func:`~.settings.exercise_seconds`).
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
    specs, kit = specs_to_grade(notebooks_dir, notebooks, exercises)
    if not insecure:
        preflight(notebooks_dir, limits)  # one line, and no grading, where the sandbox cannot be made or verified
    with _scratch(workdir) as work, _shared_folder() as shared:
        work = Path(work)
        copy = copy_submission(submission, shared / "submission", max_total_bytes=(limits or Limits()).submission_bytes)
        hidden = ready_hidden(hidden, specs, salt, work, notebooks_dir)
        iso = Isolation.for_grading(hidden.library if not allow_reference else REPO_ROOT,
                                    [work, Path(hidden.fixtures_dir)], notebooks_dir, self_test=allow_reference,
                                    insecure=insecure, limits=limits, scratch=shared)
        run = GradingRun(specs, hidden, iso, copy, timeout, allow_reference, kit=kit,
                         clock=Clock(submission_timeout),
                         cgroup=None if insecure else Cgroup.create(iso.limits.submission_memory_bytes,
                                                                     4 * iso.limits.processes_total))
        nbval_run = None
        run_nbval = run_nbval and launch.mode_of(iso) != launch.CONTAINER  # container mode: no TCP for kernels
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
                           {"note": container.NBVAL_NOTE} if launch.mode_of(run.iso) == launch.CONTAINER else {}}
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
        iso = Isolation.for_grading(lib, [], notebooks_dir, limits=limits, scratch=lib)
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


def _scratch(workdir: Path | None):
    """The grader's scratch folder: ``workdir``, else a temporary one (removed at the end)."""
    if workdir is None:
        return tempfile.TemporaryDirectory(prefix="course-grade-")
    Path(workdir).mkdir(parents=True, exist_ok=True)
    return contextlib.nullcontext(workdir)

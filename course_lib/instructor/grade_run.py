"""Running what a grading run planned: the hidden checks of each exercise, nbval of each notebook, and the last share.

* :func:`hidden_checks`: each pending exercise's check runs in a worker of the grader on the hidden cases, its
  function in a sandboxed student's process (:func:`~course_lib.instructor.hidden.run_hidden`), on the exercise's
  clock and under its memory cap; its points are :func:`course_lib.checks.core.score_against` the reference's. A
  notebook whose exercise looped or ended is run again under nbval with that exercise cut short.
* :func:`start_nbval` and :func:`add_nbval`: the notebooks under nbval in the same sandbox, and the last 10 % of each
  exercise whose hidden checks all pass: the notebook runs top to bottom through its check cell, and the check on
  the notebook's own cases, run by the grader, prints the reference verdict (never what the kernel printed).
"""

from __future__ import annotations

import copy
import math
from collections import Counter

from course_lib.checks.core import score_against, score_reasons
from course_lib.instructor.grade_plan import ExerciseGrade, GradingRun, HiddenCases, exercise_key
from course_lib.instructor.grade_report import exc_text, short
from course_lib.instructor.hidden import HiddenJob, run_hidden, run_reference
from course_lib.instructor.nbval_run import NbvalRun
from course_lib.instructor.notebooks import ExerciseSpec
from course_lib.instructor.oracle import earlier_steps
from course_lib.instructor.placement import Placement
from course_lib.instructor.sandbox.jail import IsolationError
from course_lib.instructor.settings import exercise_seconds, nbval_seconds
from course_lib.paths import FIXTURES_DIR

__all__ = ["HIDDEN_SHARE", "start_nbval", "hidden_checks", "add_nbval"]

HIDDEN_SHARE = 0.9  # of an exercise's points: the hidden checks; the rest: the nbval share (with all hidden passing)
MAX_FEEDBACK_LINES = 6  # failed hidden checks named in an exercise's feedback
#: An exercise whose hidden checks take longer than this, and than 10 times the reference's (plus 5 s), is graded and
#: told that it is slow.
SLOW_NOTE_SECONDS = 20.0


def start_nbval(run: GradingRun, cell_timeout: float, jobs: int) -> NbvalRun:
    """Start nbval on every readable notebook (a notebook whose exercise loops is restarted later)."""
    nbval_run = NbvalRun(run.submission.root, run.iso, cell_timeout, jobs=jobs, timeout=nbval_seconds(cell_timeout),
                         deadline=run.clock.deadline, cgroup=run.cgroup)
    for name, nbv in run.to_nbval.items():
        nbval_run.submit(name, nbv)
    return nbval_run


def hidden_checks(run: GradingRun, nbval_run: NbvalRun | None) -> None:
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
            try:
                seen = _grade_hidden(g, e, ex, run, steps)
            except IsolationError:
                raise  # no sandbox, no grading
            except Exception as exc:  # noqa: BLE001 - the grader never dies on a submission
                g.status, g.points, seen = "error", 0.0, {}
                g.feedback.append(f"{e.name}: the grader could not run its hidden checks ({exc_text(exc)})")
            run.sandbox_seen = run.sandbox_seen or seen
            if g.status in ("timeout", "exit"):
                ended[e.name] = (g.feedback[-1], ex.def_cell)
        if nbval_run is not None and s.name in run.to_nbval and ended:
            nbval_run.restart(s.name, _without_ended(copy.deepcopy(run.to_nbval[s.name]), places, ended))


def _grade_hidden(g: ExerciseGrade, e: ExerciseSpec, ex, run: GradingRun, steps: dict[str, str]) -> dict:
    """Run the hidden checks of one exercise (its function in a sandboxed process) and fill in its grade.

    ``steps``: the earlier exercises its code calls, answered by their references (:mod:`.oracle`).
    Returns what the student's process was confined by.
    """
    hidden = run.hidden
    budget = exercise_seconds(run.timeout, hidden.reference_seconds.get(exercise_key(e), 0.0), calls_back=bool(steps))
    out = run_hidden(HiddenJob(e.name, ex.code, e.check_module, e.check_function, str(hidden.fixtures_dir),
                               e.reference, run.allow_reference, str(run.submission.root), steps,
                               public_dir=str(FIXTURES_DIR) if run.judge_cells else None,
                               reference_result=hidden.reference_results.get(exercise_key(e))), budget, run.iso,
                     cgroup_parent=run.cgroup, deadline=run.clock.deadline)
    run.public[(e.notebook, e.name)] = (out.public, out.public_note)
    ref = hidden.reference_passing.get(exercise_key(e), [])
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
    reference = hidden.reference_results.get(exercise_key(e))
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
    if exercise_key(e) in hidden.reference_notes:
        g.feedback.append("note: " + hidden.reference_notes[exercise_key(e)])
    return out.sandbox


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


#: A note on speed only when the student's hidden checks take this many times as long as the reference's, both
#: timed one after the other on the same machine (so the note does not depend on the machine or its load).
SLOW_RATIO = 10.0


def _slowness(hidden: HiddenCases, e: ExerciseSpec, seconds: float) -> str | None:
    """A machine-independent note on a slow exercise, or None.

    A wall time beyond ``SLOW_NOTE_SECONDS`` and 10x the reference's calibration run only selects the candidates;
    the note itself compares with the reference timed again *right after* the student's run, on the same hidden
    cases and machine, and says the ratio (rounded to a coarse step) without seconds: a busy machine slows both.
    """
    ref0 = hidden.reference_seconds.get(exercise_key(e), 0.0)
    job = hidden.reference_jobs.get(exercise_key(e))
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


def add_nbval(run: GradingRun, nbval_run: NbvalRun) -> None:
    """The last 10 % of each exercise whose hidden checks all pass, from two things the grader sees itself.

    * **The notebook runs top to bottom** through the exercise's check cell: nbval, in the sandbox, ran the cell
      without an error (what it prints is not compared: code in the notebook could filter or forge that).
    * **The check cell's verdict**: the exercise's check on the notebook's own cases, run by the grader with the
      student's function in the sandbox and the earlier steps it calls answered by their references (each mistake
      is charged once, in its own exercise), prints the reference verdict (:func:`~.hidden.run_hidden`).
    """
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
            g.nbval = "not run" if r is None else ("ran" if r == "pass" else "fail")
            if g.status == "full":
                _judge_check_cell(g, e, r or nbval_notes.get(s.name) or "no result", run.public.get((s.name, e.name)))


def _judge_check_cell(g: ExerciseGrade, e: ExerciseSpec, cell: str, public: tuple[str | None, str] | None) -> None:
    """Full marks, or the feedback on the part of the nbval share that failed (``cell``: nbval's result of the check
    cell; ``public``: what the check printed on the notebook's own cases, and why not when None)."""
    printed, why = public or (None, "not run")
    differs = _first_difference(printed, e.verdict) if printed is not None else why
    if cell == "pass" and not differs:
        g.points, g.nbval = round(e.points, 2), "pass"
        g.feedback[0] = (f"full marks: all {g.hidden['total']} hidden checks pass, the notebook runs top to bottom "
                         "through the check cell, and the check on the notebook's own cases prints the reference "
                         "verdict")
        return
    g.nbval = "fail"
    share = f"(−{(1 - HIDDEN_SHARE) * 100:.0f} %)"
    if cell != "pass":
        g.feedback.append(f"in your notebook the check cell of {e.name} does not run when the notebook runs top to "
                          f"bottom ({short(cell)}); restart the kernel, run all cells, and fix what fails {share}")
    if differs:
        g.feedback.append(f"the check of {e.name} on the notebook's own cases (run by the grader with your function) "
                          f"does not print the reference verdict: {short(differs, 300)} {share}")


def _first_difference(printed: str, verdict: str) -> str:
    """The first line where the check's printed verdict differs from the reference's ("" when they are the same)."""
    got, want = printed.rstrip().splitlines(), verdict.rstrip().splitlines()
    for k in range(max(len(got), len(want))):
        a, b = (got[k] if k < len(got) else ""), (want[k] if k < len(want) else "")
        if a.rstrip() != b.rstrip():
            return f"line {k + 1} is {a.strip()!r}, the reference's is {b.strip()!r}"
    return ""

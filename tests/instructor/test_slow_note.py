"""The grader's note on a slow exercise compares with the reference timed right after it: no seconds, no load."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

from course_lib.instructor import grade_run
from course_lib.instructor.grade_plan import HiddenCases, exercise_key
from course_lib.instructor.hidden import HiddenOutcome


def _hidden(ref_seconds: float):
    e = SimpleNamespace(notebook="01_x.ipynb", name="ransac_fundamental")
    h = HiddenCases(0, Path("."), {})
    h.reference_seconds[exercise_key(e)] = ref_seconds
    h.reference_jobs[exercise_key(e)] = object()
    return h, e


def test_the_note_is_a_ratio_to_the_reference_timed_again_and_never_seconds(monkeypatch):
    h, e = _hidden(2.0)
    for now in (2.0, 4.0):  # the same student run (39 s) on a quiet and on a busy machine: the reference slows too
        monkeypatch.setattr(grade_run, "run_reference", lambda job, now=now: HiddenOutcome("ok", seconds=now))
        assert grade_run._slowness(h, e, 39.0 * now / 2.0) == ("its hidden checks took about 10 times as long as the "
                                                           "reference's on the same cases, timed one after the other "
                                                           "on the same machine")


def test_no_note_when_the_reference_is_as_slow_right_then(monkeypatch):
    """A run that the calibration's timing would call slow, but the machine is just busy: no note."""
    h, e = _hidden(2.0)
    monkeypatch.setattr(grade_run, "run_reference", lambda job: HiddenOutcome("ok", seconds=8.0))
    assert grade_run._slowness(h, e, 39.0) is None
    assert grade_run._slowness(h, e, 12.0) is None  # below the screen: the reference is not even run again

"""The check machinery behind every check cell, and the stored fixtures being current."""

import numpy as np
import pytest

from course_lib.grading import core
from course_lib.grading.core import FAILED, Check


def test_check_reports_pass_and_fail(capsys):
    with Check("demo") as c:
        c.expect(True, "first is fine", "never shown")
        c.expect(False, "never shown", "second failed: did you transpose?")
    out = capsys.readouterr().out
    assert out.splitlines() == ["demo", "  ✔ first is fine", "  ✘ second failed: did you transpose?", "  1 of 2 checks passed"]
    assert core.RESULTS["demo"].passed == 1


def test_check_turns_student_exceptions_into_verdicts(capsys):
    def broken(x):
        return x[10]

    def todo(x):
        raise NotImplementedError

    with Check("student") as c:
        assert c.call(broken, np.zeros(3), case="tiny case") is FAILED
        assert c.call(todo, np.zeros(3), case="tiny case") is FAILED
    out = capsys.readouterr().out
    assert "tiny case: your function raised IndexError" in out
    assert "not implemented yet" in out


def test_check_does_not_let_student_modify_inputs():
    a = np.ones(3)

    def mutate(x):
        x[:] = 0
        return x

    with Check("mutation") as c:
        c.call(mutate, a, case="c")
    assert np.all(a == 1)


def test_shape_check(capsys):
    with Check("shape") as c:
        assert c.shape(np.zeros((3, 3)), (3, 3), "F")
        assert not c.shape(np.zeros((3, 4)), (3, 3), "F")
        assert not c.shape(np.full((2,), np.nan), (None,), "d")
    out = capsys.readouterr().out
    assert "F has shape (3, 3)" in out and "expected (3, 3)" in out and "NaN" in out


def test_a_crashing_check_is_a_verdict_not_a_traceback(capsys):
    with Check("crash") as c:
        raise RuntimeError("boom")
    assert "the check could not finish: RuntimeError: boom" in capsys.readouterr().out


def test_fixtures_are_current():
    """Rebuild every fixture from the reference and compare with the committed files."""
    diffs = core.build_fixtures(write=False)
    if not diffs:
        pytest.skip("no fixture builders registered")
    stale = {k: v for k, v in diffs.items() if v}
    assert not stale, f"stale fixtures (run: python -m course_lib fixtures): {stale}"

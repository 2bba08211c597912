"""The check machinery behind every check cell, and the stored fixtures being current."""

import numpy as np
import pytest

from course_lib.checks import core
from course_lib.checks.core import FAILED, Check


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


def test_shape_is_a_gate_that_earns_no_points(capsys):
    with Check("gate demo") as c:
        c.shape(np.zeros((3, 3)), (3, 3), "F")
        c.expect(True, "value right", "")
        c.expect(False, "", "value wrong")
    r = core.RESULTS["gate demo"]
    assert (r.passed, r.total) == (2, 3)  # the printed count keeps every check
    assert r.points == (1, 2) and core.score(r) == 0.5  # the passing gate earns nothing
    with Check("gate only") as c:
        c.shape(np.zeros((3, 3)), (3, 3), "F")
    assert core.score(core.RESULTS["gate only"]) == 0.0  # no points for shape alone
    with Check("gate fails") as c:
        c.shape(np.zeros((3, 4)), (3, 3), "F")
        c.expect(True, "other case right", "")
    assert core.score(core.RESULTS["gate fails"]) == 0.5  # a failed gate counts as a failed check
    assert "expected (3, 3)" in capsys.readouterr().out


def test_a_failed_defining_property_caps_the_score_and_leads_the_verdict(capsys):
    core.declare_defining("defining demo", {"rank 2": "what makes F a fundamental matrix"})
    with Check("defining demo") as c:
        for k in range(9):
            c.expect(True, f"case {k} fits", "")
        c.expect(False, "", "case 9: F has rank 3: enforce rank 2", defining="rank 2")
        c.expect(True, "case 10: F has rank 2", "", defining="rank 2")
    r = core.RESULTS["defining demo"]
    assert r.passed == 10 and r.total == 11 and r.defining_failed == ["rank 2"]
    assert core.score(r) == core.DEFINING_CAP == 0.5  # 10/11 without the cap
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "defining demo"
    assert "defining property fails: rank 2" in lines[1] and "half of the points" in lines[1]
    assert lines[2] == "  ✘ case 9: F has rank 3: enforce rank 2"  # the failing check follows it
    assert lines[-1] == "  10 of 11 checks passed"
    assert r.lines == lines[1:-1]  # the result holds the lines as printed (the grader's feedback uses them)


def test_a_defining_property_must_be_declared():
    with pytest.raises(ValueError, match="not a declared defining property"):
        Check("undeclared").expect(True, "x", "y", defining="rank 2")


def test_passing_defining_checks_print_as_before(capsys):
    core.declare_defining("defining pass", {"det R = +1": "a rotation"})
    with Check("defining pass") as c:
        c.expect(True, "R is a rotation", "", defining="det R = +1")
    assert capsys.readouterr().out.splitlines() == ["defining pass", "  ✔ R is a rotation", "  all 1 checks passed"]
    assert core.score(core.RESULTS["defining pass"]) == 1.0


def test_score_of_a_result_without_verdicts_is_passed_over_total():
    assert core.score(core.CheckResult("by hand", 3, 4)) == 0.75
    assert core.score(core.CheckResult("empty", 0, 0)) == 0.0


# --------------------------------------------------------------------------- missing answers, notes, the reference's count


def test_a_function_that_returns_none_fails_its_call(capsys):
    with Check("returns_none") as c:
        out = c.call(lambda x: None, 1, case="a case")
        assert out is FAILED
    text = capsys.readouterr().out
    assert "returned None" in text and "0 of 1 checks passed" in text


def test_blame_earlier_names_the_failed_earlier_exercise(capsys):
    with Check("earlier_one") as c:
        c.expect(False, "", "wrong")
    with Check("later_one") as c:
        c.expect(False, "", "also wrong")
        c.blame_earlier("earlier_one", "never_run")
    text = capsys.readouterr().out
    assert "note: your earlier_one failed its own checks above and later_one calls it" in text
    with Check("later_two") as c:
        c.expect(True, "fine", "")
        c.blame_earlier("earlier_one")
    assert "note:" not in capsys.readouterr().out  # nothing to blame when the exercise passes


def test_score_against_counts_checks_that_did_not_run(capsys):
    from course_lib.checks.core import RESULTS, score_against

    with Check("counted") as c:
        for k in range(4):
            c.expect(True, f"case {k} ok", "")
    reference = RESULTS["counted"]
    with Check("counted") as c:  # the student's run stopped after two cases
        c.expect(True, "case 0 ok", "")
        c.expect(True, "case 1 ok", "")
    student = RESULTS["counted"]
    capsys.readouterr()
    assert student.ok and core.score(student) == 1.0  # on its own it looks perfect
    assert score_against(student, reference) == 0.5  # against the reference's count it is not


def test_a_failed_detail_costs_no_hidden_points_but_the_exercise_is_not_perfect(capsys):
    from course_lib.checks.core import RESULTS

    with Check("with_detail") as c:
        c.expect(True, "the maths is right", "")
        c.detail(False, "", "correct maths, but not the order the docstring asks for")
    result = RESULTS["with_detail"]
    capsys.readouterr()
    assert core.score(result) == 1.0 and not result.ok
    assert result.details_failed == ["correct maths, but not the order the docstring asks for"]

"""The check machinery behind every check cell, and the stored fixtures being current."""

import numpy as np
import pytest

from course_lib.checks import core
from course_lib.checks.core import FAILED, RESULTS, Check, calls_name


def test_check_reports_pass_and_fail(capsys):
    with Check("demo") as c:
        c.expect(True, "first is fine", "never shown")
        c.expect(False, "never shown", "second failed: did you transpose?")
    out = capsys.readouterr().out
    assert out.splitlines() == ["demo", "  ✔ first is fine", "  ✘ second failed: did you transpose?", "  1 of 2 checks passed",
                                "  scoring: 50% of the hidden-check points on these cases: 1 of 2 point checks fail "
                                "(each costs an equal share)"]
    assert core.RESULTS["demo"].passed == 1


def test_the_scoring_line_names_the_rule_that_cost_points(capsys):
    """Gates earn nothing and a failed one counts as a failed check; a failed defining property caps at half."""
    core.declare_defining("demo2", {"rank 2": "F is singular"})
    with Check("demo2") as c:
        c.expect(True, "F has shape (3, 3)", "", kind="gate")
        c.expect(False, "", "F has shape (4, 4)", kind="gate")
        for k in range(6):
            c.expect(True, f"value {k} right", "")
        c.expect(False, "", "F has rank 3", defining="rank 2")
    line = capsys.readouterr().out.splitlines()[-1]
    assert line.startswith("  scoring: 50% of the hidden-check points")
    assert "1 of 7 point checks fail" in line and "1 shape/dtype gate(s) fail" in line
    assert "the defining property 'rank 2' fails: capped at 50% (the other checks alone would give 75%)" in line
    assert core.score(core.RESULTS["demo2"]) == 0.5
    core.DEFINING.pop("demo2")


def test_the_scoring_rule_is_written_once_and_quoted_where_it_is_read():
    from course_lib.instructor.release import student_readme
    from course_lib.instructor.notebooks import kit_specs
    from course_lib.instructor.plan import release_plan
    from course_lib.paths import REPO_ROOT

    for doc in ("README.md", "docs/mistakes.md"):
        assert core.SCORING_RULE in (REPO_ROOT / doc).read_text(), f"{doc} does not quote core.SCORING_RULE"
    specs = kit_specs()
    assert core.SCORING_RULE in student_readme(specs, release_plan(specs))


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
    with Check("crash"):
        raise RuntimeError("boom")
    assert "the check could not finish: RuntimeError: boom" in capsys.readouterr().out


def test_shape_is_a_gate_that_earns_no_points(capsys):
    with Check("gate demo") as c:
        c.shape(np.zeros((3, 3)), (3, 3), "F")
        c.expect(True, "value right", "")
        c.expect(False, "", "value wrong")
    r = core.RESULTS["gate demo"]
    assert (r.passed, r.total) == (2, 3)  # the printed count keeps every check
    assert core.score(r) == 0.5  # the passing gate earns nothing
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
    assert lines[-2] == "  10 of 11 checks passed" and "capped at 50%" in lines[-1]
    assert r.lines == lines[1:-2]  # the result holds the lines as printed (the grader's feedback uses them)


def test_a_defining_property_must_be_declared():
    with pytest.raises(ValueError, match="not a declared defining property"):
        Check("undeclared").expect(True, "x", "y", defining="rank 2")


def test_passing_defining_checks_print_as_before(capsys):
    core.declare_defining("defining pass", {"det R = +1": "a rotation"})
    with Check("defining pass") as c:
        c.expect(True, "R is a rotation", "", defining="det R = +1")
    assert capsys.readouterr().out.splitlines() == ["defining pass", "  ✔ R is a rotation", "  all 1 checks passed"]
    assert core.score(core.RESULTS["defining pass"]) == 1.0


def test_score_of_a_result_without_verdicts_is_zero():
    """Points come from recorded verdicts only: a result that claims passes without them earns nothing."""
    assert core.score(core.CheckResult("by hand", 3, 4)) == 0.0
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
    assert "note: later_one calls your earlier_one, whose check failed: fix earlier_one first" in text
    assert "never_run" not in text  # without the student's function: only a check that failed is named
    with Check("later_two") as c:
        c.expect(True, "fine", "")
        c.blame_earlier("earlier_one")
    assert "note:" not in capsys.readouterr().out  # nothing to blame when the exercise passes


def _never_run_step(x):
    return x


def _helper(x):
    return _never_run_step(x)


def test_blame_earlier_names_only_what_the_code_calls_also_a_check_that_never_ran(capsys):
    def later(x):
        return _helper(x) + 1  # calls the earlier step through a helper of its module

    def inline(x):
        return x + 1  # wrote the step inline: calls no earlier exercise

    RESULTS.pop("_never_run_step", None)
    with Check("later_three") as c:
        c.expect(False, "", "wrong")
        c.blame_earlier("_never_run_step", "earlier_one", fn=later)
    text = capsys.readouterr().out
    assert "note: later_three calls your _never_run_step, whose check has not run in this kernel: fix " \
           "_never_run_step first (run its check cell)" in text
    assert "earlier_one" not in text  # failed, but later does not call it
    with Check("later_four") as c:
        c.expect(False, "", "wrong")
        c.blame_earlier("_never_run_step", fn=inline)
    assert "note:" not in capsys.readouterr().out
    assert calls_name(print, "x") is None and calls_name(Check, "RESULTS") is True


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
    with Check("counted") as c:  # every case right, but a gate fails (n_iters never adapts)
        for k in range(4):
            c.expect(True, f"case {k} ok", "")
        c.gate(False, "", "n_iters = 2000: update the number of iterations")
    capsys.readouterr()
    assert score_against(RESULTS["counted"], reference) == 4 / 5 == core.score(RESULTS["counted"])


def test_a_failed_detail_costs_no_hidden_points_but_the_exercise_is_not_perfect(capsys):
    from course_lib.checks.core import RESULTS

    with Check("with_detail") as c:
        c.expect(True, "the maths is right", "")
        c.detail(False, "", "correct maths, but not the order the docstring asks for")
    result = RESULTS["with_detail"]
    capsys.readouterr()
    assert core.score(result) == 1.0 and not result.ok
    assert result.details_failed == ["correct maths, but not the order the docstring asks for"]


# ----------------------------------------------------------------- nothing usable fails its case (issue 18, item 5)


@pytest.mark.parametrize("junk, phrase", [
    (None, "returned None"),
    (float("nan"), "returned NaN"),
    (np.float32("nan"), "returned NaN"),
])
def test_a_call_that_returns_nothing_usable_fails(junk, phrase, capsys):
    with Check("unusable") as c:
        assert c.call(lambda: junk, case="a case") is FAILED
    out = capsys.readouterr().out
    assert phrase in out and "0 of 1 checks passed" in out


@pytest.mark.parametrize("value, phrase", [
    ("junk", "is a str, expected a numeric array of shape (3,)"),
    ({"a": 1}, "is a dict, expected a numeric array"),
    (object(), "is a object, expected a numeric array"),
    ((np.zeros(2), np.zeros(3)), "is a tuple of 2 items, expected a numeric array"),
    (np.zeros((3, 1)), "has shape (3, 1), expected (3,)"),
    (np.array([1.0, np.nan, 0.0]), "contains NaN or inf"),
])
def test_shape_fails_on_anything_that_is_not_the_array_asked_for(value, phrase, capsys):
    with Check("not an array") as c:
        assert not c.shape(value, (3,), "d")
    out = capsys.readouterr().out
    assert phrase in out and "0 of 1 checks passed" in out


def test_shape_reads_torch_tensors_on_any_device_and_with_grad(capsys):
    torch = pytest.importorskip("torch")
    with Check("tensor") as c:
        assert c.shape(torch.zeros(3, requires_grad=True), (3,), "d")
    assert "all 1 checks passed" in capsys.readouterr().out


def test_a_check_that_stops_with_an_error_is_a_failed_verdict(capsys):
    with Check("stopped") as c:
        c.call(lambda: np.ones(3), case="first")
        c.expect(True, "first: right", "")
        raise ValueError("the check's own bug")
    out = capsys.readouterr().out
    assert "the check could not finish" in out
    assert core.RESULTS["stopped"].passed == 1 and core.RESULTS["stopped"].total == 2


def test_a_case_whose_result_no_check_could_use_counts_as_failed(capsys):
    def lenient_to_array(v):  # a check helper that gives up silently on what it cannot read
        try:
            return np.asarray(v, dtype=float)
        except (TypeError, ValueError):
            return None

    with Check("silent skip") as c:
        z = lenient_to_array(c.call(lambda: "junk", case="evaluation"))
        if z is not None:
            c.expect(True, "evaluation: right", "")
        z = lenient_to_array(c.call(lambda: np.ones(2), case="training"))
        if z is not None:
            c.expect(True, "training: right", "")
    out = capsys.readouterr().out
    assert "evaluation: the result could not be checked" in out
    assert core.score(core.RESULTS["silent skip"]) == 0.5


def test_a_last_call_whose_result_led_to_no_verdict_counts_as_failed(capsys):
    with Check("repeat call") as c:
        d = c.call(lambda: np.ones(3), case="pair")
        c.expect(d.sum() == 3, "pair: right", "pair: wrong")
        d2 = c.call(lambda: np.zeros(0), case="pair")  # the same case, called again (e.g. with a scaled input)
        if d2.shape == d.shape:
            c.gate(np.allclose(d, d2), "pair: scale-invariant", "pair: depends on the scale")
    out = capsys.readouterr().out
    assert "pair: the result of the last call could not be checked" in out
    assert not core.RESULTS["repeat call"].ok


def test_a_correct_run_gets_no_extra_lines(capsys):
    with Check("clean") as c:
        for case in ("a", "b"):
            v = c.call(lambda: np.ones(2), case=case)
            c.shape(v, (2,), f"{case}: v")
            c.expect(True, f"{case}: right", "")
    assert capsys.readouterr().out.splitlines()[-1] == "  all 4 checks passed"


_UNCOPIED = object()


def _same(a, b) -> bool:
    """Whether two calls' arguments are equal (arrays element by element, NaN equal to NaN)."""
    if a is _UNCOPIED:
        return False
    if type(a).__module__ == "torch" and type(a) is type(b):
        import torch

        return a.shape == b.shape and a.dtype == b.dtype and bool(torch.equal(a, b))
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and a.shape == b.shape
                and a.dtype == b.dtype and np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"))
    if isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)):
        return type(a) is type(b) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, np.random.Generator) and isinstance(b, np.random.Generator):
        return _same(a.bit_generator.state, b.bit_generator.state)
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    try:
        return bool(a == b) and type(a) is type(b)
    except Exception:  # noqa: BLE001 (objects without a plain equality: not the same call)
        return False


def _leave_as(live, after) -> None:
    """Put ``live``'s generators and arrays in the state a recorded call left their copies ``after`` in."""
    if isinstance(live, np.random.Generator):
        live.bit_generator.state = after.bit_generator.state
    elif isinstance(live, np.ndarray) and live.flags.writeable:
        np.copyto(live, after)
    elif isinstance(live, (tuple, list)):
        for x, y in zip(live, after):
            _leave_as(x, y)
    elif isinstance(live, dict):
        for k in live:
            _leave_as(live[k], after[k])


@pytest.mark.parametrize("junk", [None, "junk", float("nan"), object(), (np.zeros(2), np.zeros(3)), np.zeros((0,)),
                                  (None, None)], ids=["None", "str", "nan", "object", "ragged", "empty", "Nones"])
def test_no_check_of_the_kit_passes_a_function_that_returns_junk_for_one_call(junk):
    """Every check, with the reference solution answering every call but one, which returns junk: never all passed."""
    import contextlib
    import copy
    import importlib
    import io

    from course_lib.instructor.notebooks import kit_specs

    holes = []
    for spec in kit_specs():
        for e in spec.exercises:
            if not e.reference or e.name in ("bundle_adjust", "NeRF"):  # a wrapper / a class: no plain reference call
                continue
            mod, attr = e.reference.split(":")
            ref = getattr(importlib.import_module(mod), attr)
            check = getattr(importlib.import_module(e.check_module), e.check_function)
            answers = []  # (arguments, answer) of each call of the clean run, in order

            def counting(*a, _answers=answers, _ref=ref, **kw):
                try:
                    before = copy.deepcopy((a, kw))
                except Exception:  # noqa: BLE001 (e.g. a tensor in a graph: this call is computed again each time)
                    before = _UNCOPIED
                out = _ref(*a, **kw)
                try:  # the answer, and the arguments as the call left them (a generator's state moved on)
                    _answers.append((before, copy.deepcopy(out), copy.deepcopy((a, kw))))
                except Exception:  # noqa: BLE001
                    _answers.append((_UNCOPIED, None, None))
                return out

            with contextlib.redirect_stdout(io.StringIO()):
                check(counting)
            for k in range(len(answers)):
                seen = [0]

                def sabotaged(*a, _k=k, _seen=seen, _ref=ref, **kw):
                    i = _seen[0]
                    _seen[0] += 1
                    if i == _k:
                        return junk
                    if i < len(answers) and _same(answers[i][0], (a, kw)):
                        # the reference's answer to the same call, computed once; the arguments left as it left them
                        _leave_as((a, kw), answers[i][2])
                        return copy.deepcopy(answers[i][1])
                    return _ref(*a, **kw)

                with contextlib.redirect_stdout(io.StringIO()):
                    check(sabotaged)
                result = core.RESULTS[e.name]
                if result.ok or core.score(result) >= 1.0:
                    holes.append(f"{e.name}, call {k + 1} of {len(answers)}")
    assert holes == []

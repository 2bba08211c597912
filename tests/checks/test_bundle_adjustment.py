"""Tests of notebook 05's checks (course_lib.checks.bundle_adjustment): the reference passes, forms and sequences are judged right."""

from __future__ import annotations

import pytest

from course_lib.checks import bundle_adjustment as gba
from course_lib.checks.core import RESULTS, load_fixture, score
from course_lib.sfm import bundle_adjustment as ref
from course_lib.sfm import visibility as rvi


def run_check(check, fn, capsys):
    check(fn)
    text = capsys.readouterr().out
    return text, RESULTS[text.splitlines()[0]]


def reference_bundle_adjust(K, R_cw, t_cw, X, uv, callback=None):
    """The notebook's solution: the reference, reporting the iterations (not the start) to the callback."""
    hook = None if callback is None else (lambda it, R, t, Xk, cost: callback(R, t, Xk) if it > 0 else None)
    res = ref.bundle_adjust(K, R_cw, t_cw, X, uv, callback=hook)
    return res.R_cw, res.t_cw, res.X


@pytest.mark.parametrize("check, fn", [
    (gba.check_visibility_matrix, rvi.visibility_matrix),
    (gba.check_reprojection_residuals, ref.reprojection_residuals),
    (gba.check_jacobian_sparsity, ref.jacobian_sparsity),
    (gba.check_bundle_adjustment, reference_bundle_adjust),
])
def test_checks_pass_with_the_reference(check, fn, capsys):
    text, result = run_check(check, fn, capsys)
    assert result.ok, text
    assert "✘" not in text


def test_an_int_visibility_matrix_is_a_detail_not_a_mistake(capsys):
    text, result = run_check(gba.check_visibility_matrix, lambda uv: rvi.visibility_matrix(uv).astype(int), capsys)
    assert not result.ok and score(result) == 1.0, text
    assert "correct values" in text and "bool array" in text


def test_the_minimum_is_the_optimum_not_where_a_few_evaluations_stop():
    """The stored minimum is below what 3 evaluations of least_squares reach by more than the check's tolerance."""
    from scipy.optimize import least_squares

    from course_lib.starting_points import observation_arrays

    f = load_fixture(gba.FIXTURE)
    K, R0, t0, X0, uv = (f[f"ba_{s}"] for s in ("K", "R0", "t0", "X0", "uv"))
    M, N = len(R0), len(X0)
    cam, pt, obs = observation_arrays(uv)
    res = least_squares(ref.reprojection_residuals, ref.pack_params(R0, t0, X0), max_nfev=3, method="trf",
                        x_scale="jac", jac_sparsity=ref.jacobian_sparsity(M, N, cam, pt), args=(M, N, cam, pt, obs, K))
    assert res.cost > float(f["ba_final_cost"]) * (1 + 10 * gba.COST_RTOL)


def test_the_shipped_check_holds_no_residual_function():
    """Issue 18: the residuals of the mistakes are stored arrays, made on the instructor's side."""
    import inspect

    names = [n for n, o in vars(gba).items() if inspect.isfunction(o) and o.__module__ == gba.__name__]
    for n in names:
        params = inspect.signature(getattr(gba, n)).parameters
        assert len(params) != 7 or n.startswith("check_"), f"{n} has the signature of reprojection_residuals"
    f = load_fixture(gba.FIXTURE)
    assert all(f"res_syn_var_{name}" in f for name in gba.RESIDUAL_VARIANTS)

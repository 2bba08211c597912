"""Tests of notebook 04's checks (course_lib.checks.pnp) and its step input: the reference passes, classic mistakes are named."""

from __future__ import annotations

import numpy as np
import pytest

from course_lib.conventions import skew
from course_lib.conventions import to_homogeneous
from course_lib.checks import pnp as gpnp
from course_lib.checks.core import RESULTS
from course_lib.sfm import pnp as ref


def run_check(check, fn, capsys):
    check(fn)
    text = capsys.readouterr().out
    return text, RESULTS[text.splitlines()[0]]


@pytest.mark.parametrize("check, fn", [
    (gpnp.check_pnp_linear, ref.pnp_linear),
    (gpnp.check_pnp_ransac, ref.pnp_ransac),
    (gpnp.check_pnp_nonlinear, ref.pnp_nonlinear),
])
def test_checks_pass_with_the_reference(check, fn, capsys):
    text, result = run_check(check, fn, capsys)
    assert result.ok, text
    assert "✘" not in text


def _raw_P(X, x, K, pixels=False):
    """The DLT's P (no conditioning, no sign fix): what a student computes first."""
    xn = x if pixels else (to_homogeneous(x) @ np.linalg.inv(K).T)[:, :2]
    Xh = to_homogeneous(X)
    A = np.zeros((2 * len(X), 12))
    A[0::2, 0:4], A[0::2, 8:12] = -Xh, xn[:, :1] * Xh
    A[1::2, 4:8], A[1::2, 8:12] = -Xh, xn[:, 1:] * Xh
    return np.linalg.svd(A, full_matrices=False)[2][-1].reshape(3, 4)


def _no_orthogonalization(X, x, K):
    P = _raw_P(X, x, K)
    P = P if np.linalg.det(P[:, :3]) > 0 else -P
    s = np.cbrt(np.linalg.det(P[:, :3]))
    return P[:, :3] / s, P[:, 3] / s


def _no_sign_fix(X, x, K):
    P = _raw_P(X, x, K)
    P = -P if np.linalg.det(P[:, :3]) > 0 else P  # the unlucky sign
    U, S, Vt = np.linalg.svd(P[:, :3])
    return U @ Vt, P[:, 3] / S.mean()


def _pixels(X, x, K):
    P = _raw_P(X, x, K, pixels=True)
    P = P if np.linalg.det(P[:, :3]) > 0 else -P
    U, S, Vt = np.linalg.svd(P[:, :3])
    return U @ Vt, P[:, 3] / S.mean()


def _with(transform):
    def fn(X, x, K):
        R, t = ref.pnp_linear(X, x, K)
        return transform(R, t)
    return fn


def _nl_gd(X, x, K, R, t):
    R1, t1 = ref.pnp_nonlinear(X, x, K, R, t)
    return R1, t + 3.0 * (t1 - t)  # an overshooting step


def _nl_halfway(X, x, K, R, t):
    """Stops halfway between the start and the optimum (on the rotation manifold)."""
    from scipy.spatial.transform import Rotation

    R1, t1 = ref.pnp_nonlinear(X, x, K, R, t)
    w = Rotation.from_matrix(R1 @ R.T).as_rotvec()
    return Rotation.from_rotvec(0.5 * w).as_matrix() @ R, 0.5 * (t + t1)


def _nl_nine(X, x, K, R, t):
    R1, t1 = ref.pnp_nonlinear(X, x, K, R, t)
    return R1 * 1.01, t1


def textbook_pnp_linear(X, x, K):
    """The DLT as the notebook teaches it, written plainly: no conditioning of the 3-D points."""
    P = _raw_P(X, x, K)
    P = P if np.linalg.det(P[:, :3]) > 0 else -P
    U, S, Vt = np.linalg.svd(P[:, :3])
    R = U @ Vt
    xn = to_homogeneous(x) @ np.linalg.inv(K).T
    A = np.concatenate([skew(v) for v in xn])
    b = -np.concatenate([skew(v) @ (R @ Xj) for v, Xj in zip(xn, X)])
    return R, np.linalg.lstsq(A, b, rcond=None)[0]


def sigma_scaled_pnp_linear(X, x, K):
    """The DLT with t = P[:, 3] / sigma_1 (no re-estimation of t)."""
    P = _raw_P(X, x, K)
    P = P if np.linalg.det(P[:, :3]) > 0 else -P
    U, S, Vt = np.linalg.svd(P[:, :3])
    return U @ Vt, P[:, 3] / S[0]


def textbook_pnp_ransac(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    """Plain RANSAC: best 6-point sample by inlier count, adaptive stop, one refit on its inliers."""
    n, best, need, it = len(X), None, max_iters, 0
    while it < min(need, max_iters):
        it += 1
        s = rng.choice(n, 6, replace=False)
        R, t = textbook_pnp_linear(X[s], x[s], K)
        inl = ref.pnp_reprojection_errors(X, x, K, R, t) < threshold_px
        if best is None or inl.sum() > best.sum():
            best = inl
            w = inl.mean()
            need = int(np.ceil(np.log(1 - confidence) / np.log(1 - w**6))) if 0 < w < 1 else max_iters
    R, t = textbook_pnp_linear(X[best], x[best], K)
    return ref.PnPResult(R, t, ref.pnp_reprojection_errors(X, x, K, R, t) < threshold_px, it)


def textbook_pnp_nonlinear(X, x, K, R, t):
    """Quaternion parametrization, default least_squares settings."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    from course_lib.conventions import project

    def res(p):
        return (project(K, Rotation.from_quat(p[:4]).as_matrix(), p[4:], X) - x).ravel()

    p = least_squares(res, np.r_[Rotation.from_matrix(R).as_quat(), t]).x
    return Rotation.from_quat(p[:4]).as_matrix(), p[4:]


@pytest.mark.parametrize("check, fn", [
    (gpnp.check_pnp_linear, textbook_pnp_linear),
    (gpnp.check_pnp_linear, sigma_scaled_pnp_linear),
    (gpnp.check_pnp_ransac, textbook_pnp_ransac),
    (gpnp.check_pnp_nonlinear, textbook_pnp_nonlinear),
])
def test_checks_pass_a_textbook_implementation(check, fn, capsys):
    text, result = run_check(check, fn, capsys)
    assert result.ok, text


@pytest.mark.parametrize("check, fn, words", [
    (gpnp.check_pnp_linear, _no_orthogonalization, "orthogonalize the 3 x 3 block"),
    (gpnp.check_pnp_linear, _no_sign_fix, "det R = -1"),
    (gpnp.check_pnp_linear, _with(lambda R, t: (-R, t)), "det R = -1"),
    (gpnp.check_pnp_linear, _with(lambda R, t: (R.T, t)), "R_wc"),
    (gpnp.check_pnp_linear, _with(lambda R, t: (R, -R.T @ t)), "C vs t"),
    (gpnp.check_pnp_linear, _with(lambda R, t: (R, -t)), "behind the camera"),
    (gpnp.check_pnp_linear, _with(lambda R, t: (R, 2.5 * t)), "wrong scale"),
    (gpnp.check_pnp_linear, _pixels, "pixel coordinates"),
    (gpnp.check_pnp_ransac, lambda X, x, K, rng, **kw: ref.PnPResult(*(lambda r: (r.R_cw, r.t_cw, ~r.inliers, r.n_iters))(
        ref.pnp_ransac(X, x, K, rng, **kw))), "inverted"),
    (gpnp.check_pnp_ransac, lambda X, x, K, rng, **kw: (lambda r: (r.R_cw, r.t_cw, np.flatnonzero(r.inliers), r.n_iters))(
        ref.pnp_ransac(X, x, K, rng, **kw)), "not the inlier indices"),
    (gpnp.check_pnp_ransac, lambda X, x, K, rng, **kw: (lambda r: (r.R_cw.T, r.t_cw, r.inliers, r.n_iters))(
        ref.pnp_ransac(X, x, K, rng, **kw)), "R_wc"),
    (gpnp.check_pnp_nonlinear, _nl_gd, "increased the RMS reprojection error"),
    (gpnp.check_pnp_nonlinear, lambda X, x, K, R, t: (R.copy(), t.copy()), "did not move"),
    (gpnp.check_pnp_nonlinear, _nl_nine, "not a rotation"),
    (gpnp.check_pnp_nonlinear, _nl_halfway, "to convergence"),
])
def test_checks_name_the_mistake(check, fn, words, capsys):
    text, result = run_check(check, fn, capsys)
    assert not result.ok
    assert words in text, text

"""Notebook 04 (PnP): classic mistakes, honest solutions and trivial answers, run through its checks."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from course_lib.checks import pnp as gpn
from course_lib.sfm import pnp as rpn
from tests.checks.catalogue import Honest, Mistake, _h

# ============================================================================ buggy versions
# Each is written as a student would write it (often the reference with one line changed).

# -- 04: pnp_linear ------------------------------------------------------------------------------------
def pnp_linear_no_orthogonalization(X, x, K):
    xn = (np.linalg.inv(K) @ _h(x).T).T
    rows = []
    for Xi, (u, v, _) in zip(_h(X), xn):
        rows.append(np.concatenate([Xi, np.zeros(4), -u * Xi]))
        rows.append(np.concatenate([np.zeros(4), Xi, -v * Xi]))
    P = np.linalg.svd(np.array(rows))[2][-1].reshape(3, 4)
    if np.linalg.det(P[:, :3]) < 0:
        P = -P
    s = np.cbrt(np.linalg.det(P[:, :3]))
    return P[:, :3] / s, P[:, 3] / s


def pnp_linear_no_sign_fix(X, x, K):
    xn = (np.linalg.inv(K) @ _h(x).T).T
    rows = []
    for Xi, (u, v, _) in zip(_h(X), xn):
        rows.append(np.concatenate([Xi, np.zeros(4), -u * Xi]))
        rows.append(np.concatenate([np.zeros(4), Xi, -v * Xi]))
    P = np.linalg.svd(np.array(rows))[2][-1].reshape(3, 4)
    P = -P if np.linalg.det(P[:, :3]) > 0 else P  # the sign the SVD happened to give, made the wrong one
    U, S, Vt = np.linalg.svd(P[:, :3])
    return U @ Vt, P[:, 3] / S[0]


def pnp_linear_transposed(X, x, K):
    R, t = rpn.pnp_linear(X, x, K)
    return R.T, t


def pnp_linear_center_as_t(X, x, K):
    R, t = rpn.pnp_linear(X, x, K)
    return R, -R.T @ t


def pnp_linear_pixels(X, x, K):
    return rpn.pnp_linear(X, x, np.eye(3))  # the DLT on the pixels themselves


def pnp_linear_raw_scale(X, x, K):
    Xh = _h(X)
    xn = _h(x) @ np.linalg.inv(K).T
    A = np.zeros((2 * len(X), 12))
    A[0::2, 0:4], A[0::2, 8:12] = Xh, -xn[:, :1] * Xh
    A[1::2, 4:8], A[1::2, 8:12] = Xh, -xn[:, 1:2] * Xh
    P = np.linalg.svd(A)[2][-1].reshape(3, 4)
    P = P if np.linalg.det(P[:, :3]) > 0 else -P
    U, _, Vt = np.linalg.svd(P[:, :3])
    return U @ Vt, P[:, 3]  # t not divided by the scale of P


# -- 04: pnp_ransac -------------------------------------------------------------------------------------
def _pnp_ransac(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000, squared=False, refit=True,
                invert=False, stale=False, adaptive=True, own_rng=False, fixed_confidence=None, normalized=False,
                fixed_threshold=None):
    n, best, it, need = len(X), None, 0, max_iters
    g = np.random if own_rng else rng
    thr = threshold_px if fixed_threshold is None else fixed_threshold
    p = confidence if fixed_confidence is None else fixed_confidence

    def inliers(R, t):
        if normalized:  # the error in normalized coordinates, compared with a threshold in pixels
            Kn = np.eye(3)
            e = np.linalg.norm(_project(Kn, R, t, X) - (_h(x) @ np.linalg.inv(K).T)[:, :2], axis=1)
        else:
            e = rpn.pnp_reprojection_errors(X, x, K, _near_rot(R), t)
        return (e**2 if squared else e) < thr

    while it < min(need, max_iters):
        it += 1
        idx = g.choice(n, 6, replace=False)
        R, t = rpn.pnp_linear(X[idx], x[idx], K)
        inl = inliers(R, t)
        if best is None or inl.sum() > best[2].sum():
            best = (R, t, inl)
            w = inl.mean()
            if adaptive:
                need = np.log(1 - p) / np.log(1 - w**6) if 0 < w < 1 else (1 if w >= 1 else max_iters)
    R, t, inl = best
    if refit and inl.sum() >= 6:
        R, t = rpn.pnp_linear(X[inl], x[inl], K)
        if not stale:
            inl = inliers(R, t)
    return rpn.PnPResult(R, t, ~inl if invert else inl, it)


def _project(K, R, t, X):
    xh = (X @ R.T + t) @ K.T
    return xh[:, :2] / xh[:, 2:]


def _near_rot(R):
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt


def pnp_ransac_squared(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    return _pnp_ransac(X, x, K, rng, threshold_px, confidence, max_iters, squared=True)


def pnp_ransac_inverted(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    return _pnp_ransac(X, x, K, rng, threshold_px, confidence, max_iters, invert=True)


def pnp_ransac_no_refit(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    return _pnp_ransac(X, x, K, rng, threshold_px, confidence, max_iters, refit=False)


def pnp_ransac_stale_mask(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    return _pnp_ransac(X, x, K, rng, threshold_px, confidence, max_iters, stale=True)


def pnp_ransac_global_rng(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    return _pnp_ransac(X, x, K, rng, threshold_px, confidence, max_iters, own_rng=True)


def pnp_ransac_fixed_iterations(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    return _pnp_ransac(X, x, K, rng, threshold_px, confidence, max_iters, adaptive=False)


def pnp_ransac_ignores_confidence(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    return _pnp_ransac(X, x, K, rng, threshold_px, confidence, max_iters, fixed_confidence=0.99)


def pnp_ransac_normalized_error(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    return _pnp_ransac(X, x, K, rng, threshold_px, confidence, max_iters, normalized=True)


def pnp_ransac_constant_threshold(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    return _pnp_ransac(X, x, K, rng, threshold_px, confidence, max_iters, fixed_threshold=2.0)


# -- 04: pnp_nonlinear ------------------------------------------------------------------------------------
def pnp_nonlinear_unchanged(X, x, K, R_cw, t_cw):
    return R_cw.copy(), t_cw.copy()


def pnp_nonlinear_nine_entries(X, x, K, R_cw, t_cw):
    from scipy.optimize import least_squares

    def res(p):
        R, t = p[:9].reshape(3, 3), p[9:]
        xc = X @ R.T + t
        return ((xc @ K.T)[:, :2] / xc[:, 2:] - x).ravel()

    p = least_squares(res, np.concatenate([R_cw.ravel(), t_cw])).x
    return p[:9].reshape(3, 3), p[9:]


def pnp_nonlinear_nine_entries_svd(X, x, K, R_cw, t_cw):
    from scipy.optimize import least_squares

    def res(p):
        xc = X @ p[:9].reshape(3, 3).T + p[9:]
        xh = xc @ K.T
        return (xh[:, :2] / xh[:, 2:] - x).ravel()

    p = least_squares(res, np.concatenate([R_cw.ravel(), t_cw])).x
    U, _, Vt = np.linalg.svd(p[:9].reshape(3, 3))
    return U @ Vt, p[9:]


def _rotvec_solve(X, x, K, R_cw, t_cw, depth=True, only_t=False, max_nfev=None):
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    r0 = Rotation.from_matrix(R_cw).as_rotvec()

    def res(p):
        r, t = (r0, p) if only_t else (p[:3], p[3:])
        xh = (X @ Rotation.from_rotvec(r).as_matrix().T + t) @ K.T
        return ((xh[:, :2] / xh[:, 2:]) if depth else xh[:, :2]).ravel() - x.ravel()

    p = least_squares(res, t_cw.copy() if only_t else np.concatenate([r0, t_cw]), max_nfev=max_nfev).x
    return (R_cw.copy(), p) if only_t else (Rotation.from_rotvec(p[:3]).as_matrix(), p[3:])


def pnp_nonlinear_no_depth_division(X, x, K, R_cw, t_cw):
    return _rotvec_solve(X, x, K, R_cw, t_cw, depth=False)


def pnp_nonlinear_only_t(X, x, K, R_cw, t_cw):
    return _rotvec_solve(X, x, K, R_cw, t_cw, only_t=True)


def pnp_nonlinear_two_evaluations(X, x, K, R_cw, t_cw):
    return _rotvec_solve(X, x, K, R_cw, t_cw, max_nfev=2)


def pnp_nonlinear_returns_R_wc(X, x, K, R_cw, t_cw):
    R, t = _rotvec_solve(X, x, K, R_cw, t_cw)
    return R.T, t


# ============================================================================ honest solutions
# Written from the textbook (Hartley & Zisserman, ch. 7; the notebook's equations), not from course_lib;
# calls of other exercises by name.

def pnp_linear(X, x, K):
    xn = np.column_stack([x, np.ones(len(x))]) @ np.linalg.inv(K).T
    mu = X.mean(axis=0)
    s = np.sqrt(3.0) / np.linalg.norm(X - mu, axis=1).mean()
    T = np.diag([s, s, s, 1.0])
    T[:3, 3] = -s * mu
    Xh = np.column_stack([(X - mu) * s, np.ones(len(X))])
    A = np.zeros((2 * len(X), 12))
    A[0::2, 0:4] = Xh
    A[0::2, 8:12] = -xn[:, :1] * Xh
    A[1::2, 4:8] = Xh
    A[1::2, 8:12] = -xn[:, 1:2] * Xh
    P = np.linalg.svd(A)[2][-1].reshape(3, 4) @ T
    if np.linalg.det(P[:, :3]) < 0:
        P = -P
    U, _, Vt = np.linalg.svd(P[:, :3])
    R = U @ Vt
    rows, rhs = [], []
    for (a, b, c), Xj in zip(xn, X):
        S = np.array([[0.0, -c, b], [c, 0.0, -a], [-b, a, 0.0]])
        rows.append(S)
        rhs.append(-S @ (R @ Xj))
    t = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
    return R, t


def pnp_ransac(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    n = len(X)

    def errors(R, t):
        Xc = X @ R.T + t
        uvw = Xc @ K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            e = np.linalg.norm(uvw[:, :2] / uvw[:, 2:] - x, axis=1)
        e[Xc[:, 2] <= 0] = np.inf
        return e

    best_R, best_t, best = None, None, np.zeros(n, dtype=bool)
    n_iters, needed = 0, max_iters
    while n_iters < min(needed, max_iters):
        n_iters += 1
        sample = rng.choice(n, 6, replace=False)
        R, t = pnp_linear(X[sample], x[sample], K)
        inl = errors(R, t) < threshold_px
        if best_R is None or inl.sum() > best.sum():
            best_R, best_t, best = R, t, inl
            w = inl.mean()
            needed = 1 if w == 1 else (np.log(1 - confidence) / np.log(1 - w**6) if w > 0 else max_iters)
    if best.sum() >= 6:
        best_R, best_t = pnp_linear(X[best], x[best], K)
        best = errors(best_R, best_t) < threshold_px
    return best_R, best_t, best, n_iters


def pnp_nonlinear(X, x, K, R_cw, t_cw):
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    def residuals(p):
        Xc = X @ Rotation.from_rotvec(p[:3]).as_matrix().T + p[3:]
        uvw = Xc @ K.T
        return (uvw[:, :2] / uvw[:, 2:3] - x).ravel()

    p0 = np.concatenate([Rotation.from_matrix(R_cw).as_rotvec(), t_cw])
    p = least_squares(residuals, p0).x
    return Rotation.from_rotvec(p[:3]).as_matrix(), p[3:]


# -- other valid styles
def pnp_linear_loops_no_conditioning(X, x, K):
    """Two equations per point built in a loop, no conditioning of the 3-D points, t from the cross products."""
    Kinv = np.linalg.inv(K)
    A = []
    for Xj, xj in zip(X, x):
        u, v, _ = Kinv @ np.array([xj[0], xj[1], 1.0])
        Xh = np.append(Xj, 1.0)
        A.append(np.concatenate([-Xh, np.zeros(4), u * Xh]))
        A.append(np.concatenate([np.zeros(4), -Xh, v * Xh]))
    P = np.linalg.svd(np.array(A))[2][-1].reshape(3, 4)
    P *= np.sign(np.linalg.det(P[:, :3]))
    U, _, Vt = np.linalg.svd(P[:, :3])
    R = U @ Vt
    A_t, b_t = [], []
    for Xj, xj in zip(X, x):
        m = Kinv @ np.array([xj[0], xj[1], 1.0])
        S = np.cross(np.eye(3), m)  # S @ y = m x y ... up to sign: rows are e_i x m
        A_t.append(S)
        b_t.append(-S @ (R @ Xj))
    t = np.linalg.lstsq(np.vstack(A_t), np.concatenate(b_t), rcond=None)[0]
    return R, t


def pnp_ransac_for_loop_dataclass(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    """A for loop with a break, samples from rng.permutation, a dataclass result."""
    from course_lib.conventions import project

    best = None
    count = 0
    for count in range(1, max_iters + 1):
        idx = rng.permutation(len(X))[:6]
        R, t = pnp_linear(X[idx], x[idx], K)
        front = (X @ R.T + t)[:, 2] > 0
        inl = front & (np.linalg.norm(project(K, R, t, X) - x, axis=1) < threshold_px)
        if best is None or inl.sum() > best[2].sum():
            best = (R, t, inl)
        w = best[2].sum() / len(X)
        if w >= 1 or (w > 0 and count >= np.log(1 - confidence) / np.log(1 - w**6)):
            break
    R, t = pnp_linear(X[best[2]], x[best[2]], K)
    front = (X @ R.T + t)[:, 2] > 0
    inl = front & (np.linalg.norm(project(K, R, t, X) - x, axis=1) < threshold_px)
    return PoseResult(R, t, inl, count)


@dataclass
class PoseResult:
    R_cw: np.ndarray
    t_cw: np.ndarray
    inliers: np.ndarray
    n_iters: int


def pnp_nonlinear_quaternion(X, x, K, R_cw, t_cw):
    """A unit quaternion (normalized inside the residual) and t; the trust-region solver with x_scale."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    def res(p):
        R = Rotation.from_quat(p[:4] / np.linalg.norm(p[:4])).as_matrix()
        xh = (X @ R.T + p[4:]) @ K.T
        return (xh[:, :2] / xh[:, 2:] - x).ravel()

    p = least_squares(res, np.r_[Rotation.from_matrix(R_cw).as_quat(), t_cw], x_scale="jac").x
    return Rotation.from_quat(p[:4] / np.linalg.norm(p[:4])).as_matrix(), p[4:]


# ============================================================================ the catalogue

M = Mistake
MISTAKES = [
    M("pnp_linear", "R not orthogonalized", gpn.check_pnp_linear, pnp_linear_no_orthogonalization,
      ("not a rotation", "orthogonalize"), defining="R is a rotation"),
    M("pnp_linear", "sign of P not fixed", gpn.check_pnp_linear, pnp_linear_no_sign_fix, ("det r = -1",),
      defining="R is a rotation"),
    M("pnp_linear", "R_wc returned", gpn.check_pnp_linear, pnp_linear_transposed, ("you returned r_wc",)),
    M("pnp_linear", "C returned as t", gpn.check_pnp_linear, pnp_linear_center_as_t, ("c vs t",)),
    M("pnp_linear", "DLT on pixel coordinates", gpn.check_pnp_linear, pnp_linear_pixels, ("pixel coordinates",)),
    M("pnp_linear", "t not divided by the scale of P", gpn.check_pnp_linear, pnp_linear_raw_scale,
      ("wrong scale",)),
    M("pnp_ransac", "squared error vs threshold", gpn.check_pnp_ransac, pnp_ransac_squared, ("squared reprojection error",)),
    M("pnp_ransac", "inverted inlier mask", gpn.check_pnp_ransac, pnp_ransac_inverted, ("inverted",)),
    M("pnp_ransac", "no final refit", gpn.check_pnp_ransac, pnp_ransac_no_refit, ("refit pnp_linear on all",)),
    M("pnp_ransac", "mask of the best sample after the refit", gpn.check_pnp_ransac, pnp_ransac_stale_mask,
      ("recompute the inliers with the final pose",)),
    M("pnp_ransac", "np.random instead of rng", gpn.check_pnp_ransac, pnp_ransac_global_rng,
      ("not from np.random",)),
    M("pnp_ransac", "fixed iteration count", gpn.check_pnp_ransac, pnp_ransac_fixed_iterations,
      ("n_iters = 1000", "log(1 - confidence)")),
    M("pnp_ransac", "confidence ignored", gpn.check_pnp_ransac, pnp_ransac_ignores_confidence,
      ("the confidence argument",)),
    M("pnp_ransac", "error in normalized coordinates", gpn.check_pnp_ransac, pnp_ransac_normalized_error,
      ("in pixels",)),
    M("pnp_ransac", "threshold_px ignored", gpn.check_pnp_ransac, pnp_ransac_constant_threshold,
      ("whatever threshold_px was passed",)),
    M("pnp_nonlinear", "returns the start", gpn.check_pnp_nonlinear, pnp_nonlinear_unchanged, ("did not move",)),
    M("pnp_nonlinear", "optimizes the 9 entries of R", gpn.check_pnp_nonlinear, pnp_nonlinear_nine_entries,
      ("not a rotation",)),
    M("pnp_nonlinear", "9 entries of R, then an SVD", gpn.check_pnp_nonlinear, pnp_nonlinear_nine_entries_svd,
      ("9 entries of r", "rotation vector")),
    M("pnp_nonlinear", "projection not divided by z", gpn.check_pnp_nonlinear, pnp_nonlinear_no_depth_division,
      ("not divided by the depth",)),
    M("pnp_nonlinear", "only t optimized", gpn.check_pnp_nonlinear, pnp_nonlinear_only_t, ("only t moved",)),
    M("pnp_nonlinear", "stopped after 2 evaluations", gpn.check_pnp_nonlinear, pnp_nonlinear_two_evaluations,
      ("not at the least-squares optimum",)),
    M("pnp_nonlinear", "returns R_wc", gpn.check_pnp_nonlinear, pnp_nonlinear_returns_R_wc, ("you returned r_wc",)),
]

#: Correct solutions: they must score full marks.
HONEST = [
    Honest("pnp_linear", "textbook, conditioned, t by least squares", gpn.check_pnp_linear, pnp_linear),
    Honest("pnp_ransac", "textbook, returns a tuple", gpn.check_pnp_ransac, pnp_ransac),
    Honest("pnp_nonlinear", "rotation vector, default least_squares", gpn.check_pnp_nonlinear, pnp_nonlinear),
    Honest("pnp_linear", "loops, no conditioning", gpn.check_pnp_linear, pnp_linear_loops_no_conditioning),
    Honest("pnp_ransac", "for loop with break, a dataclass", gpn.check_pnp_ransac, pnp_ransac_for_loop_dataclass),
    Honest("pnp_nonlinear", "unit quaternion", gpn.check_pnp_nonlinear, pnp_nonlinear_quaternion),
    Honest("pnp_linear", "the reference solution", gpn.check_pnp_linear, rpn.pnp_linear),
    Honest("pnp_ransac", "the reference solution", gpn.check_pnp_ransac, rpn.pnp_ransac),
    Honest("pnp_nonlinear", "the reference solution", gpn.check_pnp_nonlinear, rpn.pnp_nonlinear),
]


def _trivial() -> list:
    z = np.zeros  # noqa: F841
    return [
        (gpn.check_pnp_linear, lambda X, x, K: (np.eye(3), z(3))),
        (gpn.check_pnp_ransac, lambda X, x, K, rng, **k: (np.eye(3), z(3), np.ones(len(X), bool), 1)),
        (gpn.check_pnp_nonlinear, lambda X, x, K, R, t: (np.eye(3), t)),
    ]


#: Constants of the right shape: they pass the shape gates and trivially satisfied properties, and must earn nothing.
TRIVIAL = _trivial()


# ============================================================================ issue 29: written as students write them
# From the notebook's text and the stub's docstring, with an error students make; then valid variants.

def _dlt29(xn, X):
    rows = []
    for (u, v), Xi in zip(xn, X):
        Xh = np.append(Xi, 1.0)
        rows.append(np.concatenate([Xh, np.zeros(4), -u * Xh]))
        rows.append(np.concatenate([np.zeros(4), Xh, -v * Xh]))
    return np.linalg.svd(np.array(rows))[2][-1]


def pnp_linear_row_vector_Kinv(X, x, K):  # x_n = x_h @ K⁻¹: row vectors multiplied without the transpose
    xn = np.column_stack([x, np.ones(len(x))]) @ np.linalg.inv(K)
    P = _dlt29(xn[:, :2], X).reshape(3, 4)
    if np.linalg.det(P[:, :3]) < 0:
        P = -P
    U, S, Vt = np.linalg.svd(P[:, :3])
    return U @ Vt, P[:, 3] / S.mean()


def pnp_linear_reshape_4x3(X, x, K):  # the 12-vector reshaped (4, 3) and transposed, column by column
    xn = (np.linalg.inv(K) @ np.column_stack([x, np.ones(len(x))]).T).T
    P = _dlt29(xn[:, :2], X).reshape(4, 3).T
    if np.linalg.det(P[:, :3]) < 0:
        P = -P
    U, S, Vt = np.linalg.svd(P[:, :3])
    return U @ Vt, P[:, 3] / S.mean()


def pnp_linear_flip_only_R(X, x, K):  # det < 0 fixed on R alone, t keeps the sign the SVD gave
    xn = (np.linalg.inv(K) @ np.column_stack([x, np.ones(len(x))]).T).T
    P = _dlt29(xn[:, :2], X).reshape(3, 4)
    U, S, Vt = np.linalg.svd(P[:, :3])
    R = U @ Vt
    t = P[:, 3] / S.mean()
    if np.linalg.det(R) < 0:
        R = -R
    return R, t


def _ransac29(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000, rule="right", sample=6, own=False):
    g = np.random.default_rng(0) if own else rng
    n, best, n_iters, N = len(X), None, 0, max_iters
    def errs(R, t):
        Xc = X @ R.T + t
        q = Xc @ K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            e = np.linalg.norm(q[:, :2] / q[:, 2:] - x, axis=1)
        if rule != "no_cheirality":
            e[Xc[:, 2] <= 0] = np.inf
        return e
    def inl_of(R, t):
        e = errs(R, t)
        return e < threshold_px**2 if rule == "squared_threshold" else e < threshold_px
    while n_iters < min(N, max_iters):
        n_iters += 1
        idx = g.choice(n, sample, replace=False)
        try:
            R, t = rpn.pnp_linear(X[idx], x[idx], K)
        except Exception:  # noqa: BLE001 - a degenerate sample
            continue
        inl = inl_of(R, t)
        if best is None or inl.sum() > best[2].sum():
            best = (R, t, inl)
            w = inl.mean()
            N = 1 if w == 1 else (np.log(1 - confidence) / np.log(1 - w**6) if w > 0 else max_iters)
    R, t, inl = best
    if inl.sum() >= 6:
        R, t = rpn.pnp_linear(X[inl], x[inl], K)
        inl = inl_of(R, t)
    return R, t, inl, n_iters


def pnp_ransac_no_cheirality(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    return _ransac29(X, x, K, rng, threshold_px, confidence, max_iters, rule="no_cheirality")


def pnp_ransac_threshold_squared(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    return _ransac29(X, x, K, rng, threshold_px, confidence, max_iters, rule="squared_threshold")  # e < thr²


def pnp_ransac_own_seeded_generator(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    return _ransac29(X, x, K, rng, threshold_px, confidence, max_iters, own=True)  # default_rng(0), rng unused


def pnp_ransac_four_point_samples(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    return _ransac29(X, x, K, rng, threshold_px, confidence, max_iters, sample=4)  # "P3P uses 4": too few for the DLT


def _rv29(X, x, K, R_cw, t_cw, free="both", scalar=False, flat=True):
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    r0 = Rotation.from_matrix(R_cw).as_rotvec()

    def res(p):
        r = p[:3] if free != "t" else r0
        t = p[3:] if free == "both" else (t_cw if free == "R" else p)
        q = (X @ Rotation.from_rotvec(r).as_matrix().T + t) @ K.T
        e = q[:, :2] / q[:, 2:] - x
        if scalar:
            return np.sum(e**2)
        return e.ravel() if flat else e

    p0 = r0 if free == "R" else np.concatenate([r0, t_cw])
    p = least_squares(res, p0).x
    return Rotation.from_rotvec(p[:3]).as_matrix(), (t_cw.copy() if free == "R" else p[3:])


def pnp_nonlinear_only_R(X, x, K, R_cw, t_cw):  # the rotation optimized, t kept at the start
    return _rv29(X, x, K, R_cw, t_cw, free="R")


def pnp_nonlinear_scalar_residual(X, x, K, R_cw, t_cw):  # the sum of squares returned to least_squares
    return _rv29(X, x, K, R_cw, t_cw, scalar=True)


def pnp_nonlinear_residual_not_flat(X, x, K, R_cw, t_cw):  # the (N, 2) residual array, not raveled
    return _rv29(X, x, K, R_cw, t_cw, flat=False)


# -- valid variants -----------------------------------------------------------------------------------------------
def pnp_linear__float32(X, x, K):
    """The DLT in float32, R and t returned as float32."""
    X, x, K = X.astype(np.float32), x.astype(np.float32), K.astype(np.float32)
    xn = np.column_stack([x, np.ones(len(x), np.float32)]) @ np.linalg.inv(K).T
    mu = X.mean(axis=0)
    s = np.float32(np.sqrt(3.0)) / np.linalg.norm(X - mu, axis=1).mean()
    T = np.diag(np.array([s, s, s, 1], np.float32))
    T[:3, 3] = -s * mu
    Xh = np.column_stack([(X - mu) * s, np.ones(len(X), np.float32)])
    A = np.zeros((2 * len(X), 12), np.float32)
    A[0::2, 0:4], A[0::2, 8:12] = Xh, -xn[:, :1] * Xh
    A[1::2, 4:8], A[1::2, 8:12] = Xh, -xn[:, 1:2] * Xh
    P = np.linalg.svd(A)[2][-1].reshape(3, 4) @ T
    P = P if np.linalg.det(P[:, :3]) > 0 else -P
    U, S, Vt = np.linalg.svd(P[:, :3])
    R = (U @ Vt).astype(np.float32)
    M = np.concatenate([np.cross(np.eye(3, dtype=np.float32), m) for m in xn])  # rows e_i x m: (m x .)ᵀ
    b = -np.concatenate([np.cross(np.eye(3, dtype=np.float32), m) @ (R @ Xj) for m, Xj in zip(xn, X)])
    t = np.linalg.lstsq(M, b, rcond=None)[0].astype(np.float32)
    return R, t


def pnp_nonlinear__rodrigues_by_hand_lm(X, x, K, R_cw, t_cw):
    """Rodrigues' formula written by hand, method='lm' (Levenberg-Marquardt), returns float32."""
    from scipy.optimize import least_squares

    def rot(r):
        th = np.linalg.norm(r)
        if th < 1e-12:
            return np.eye(3)
        k = r / th
        Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        return np.eye(3) + np.sin(th) * Kx + (1 - np.cos(th)) * Kx @ Kx

    c = np.clip((np.trace(R_cw) - 1) / 2, -1, 1)
    th = np.arccos(c)
    axis = np.array([R_cw[2, 1] - R_cw[1, 2], R_cw[0, 2] - R_cw[2, 0], R_cw[1, 0] - R_cw[0, 1]])
    r0 = np.zeros(3) if th < 1e-12 else axis / (2 * np.sin(th)) * th

    def res(p):
        q = (X @ rot(p[:3]).T + p[3:]) @ K.T
        return (q[:, :2] / q[:, 2:] - x).ravel()

    p = least_squares(res, np.concatenate([r0, t_cw]), method="lm", xtol=1e-12, ftol=1e-12).x
    return rot(p[:3]).astype(np.float32), p[3:].astype(np.float32)


MISTAKES += [
    M("pnp_linear", "x_h @ K⁻¹ (no transpose)", gpn.check_pnp_linear, pnp_linear_row_vector_Kinv,
      ("reprojection",), batch="29"),
    M("pnp_linear", "P reshaped (4, 3)ᵀ", gpn.check_pnp_linear, pnp_linear_reshape_4x3, ("reprojection",),
      batch="29"),
    M("pnp_linear", "det fixed on R alone", gpn.check_pnp_linear, pnp_linear_flip_only_R, ("translation off",),
      batch="29"),
    M("pnp_ransac", "no cheirality test", gpn.check_pnp_ransac, pnp_ransac_no_cheirality, ("behind",), batch="29"),
    M("pnp_ransac", "e < threshold²", gpn.check_pnp_ransac, pnp_ransac_threshold_squared, ("threshold",),
      batch="29"),
    M("pnp_ransac", "own default_rng(0)", gpn.check_pnp_ransac, pnp_ransac_own_seeded_generator, ("seed",),
      batch="29"),
    M("pnp_ransac", "4-point samples", gpn.check_pnp_ransac, pnp_ransac_four_point_samples, ("6",), batch="29"),
    M("pnp_nonlinear", "only R optimized", gpn.check_pnp_nonlinear, pnp_nonlinear_only_R, ("optimum",),
      batch="29"),
    M("pnp_nonlinear", "scalar residual", gpn.check_pnp_nonlinear, pnp_nonlinear_scalar_residual, ("optimum",),
      batch="29"),
    M("pnp_nonlinear", "(N, 2) residual", gpn.check_pnp_nonlinear, pnp_nonlinear_residual_not_flat,
      ("1-d",), batch="29"),
]

HONEST += [
    Honest("pnp_linear", "float32 throughout", gpn.check_pnp_linear, pnp_linear__float32),
    Honest("pnp_nonlinear", "Rodrigues by hand, method='lm', float32 results", gpn.check_pnp_nonlinear,
           pnp_nonlinear__rodrigues_by_hand_lm),
]

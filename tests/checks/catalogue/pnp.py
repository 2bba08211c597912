"""Notebook 04 (PnP): classic mistakes, honest solutions and trivial answers, run through its checks."""

from __future__ import annotations

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


# -- 04: pnp_ransac -------------------------------------------------------------------------------------
def _pnp_ransac(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000, squared=False, refit=True,
                invert=False):
    from course_lib.conventions import project

    n, best, it = len(X), None, 0
    while it < max_iters:
        it += 1
        idx = rng.choice(n, 6, replace=False)
        R, t = rpn.pnp_linear(X[idx], x[idx], K)
        e = np.linalg.norm(project(K, R, t, X) - x, axis=1)
        inl = (e**2 if squared else e) < threshold_px
        if best is None or inl.sum() > best[2].sum():
            best = (R, t, inl)
        if it >= 200:
            break
    R, t, inl = best
    if refit:
        R, t = rpn.pnp_linear(X[inl], x[inl], K)
        e = np.linalg.norm(project(K, R, t, X) - x, axis=1)
        inl = (e**2 if squared else e) < threshold_px
    return rpn.PnPResult(R, t, ~inl if invert else inl, it)


def pnp_ransac_squared(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    return _pnp_ransac(X, x, K, rng, threshold_px, confidence, max_iters, squared=True)


def pnp_ransac_inverted(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    return _pnp_ransac(X, x, K, rng, threshold_px, confidence, max_iters, invert=True)


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


def pnp_nonlinear_no_depth_division(X, x, K, R_cw, t_cw):
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    def res(p):  # the projection is not divided by its depth
        R = Rotation.from_rotvec(p[:3]).as_matrix()
        return ((X @ R.T + p[3:]) @ K.T)[:, :2].ravel() - x.ravel()

    p = least_squares(res, np.concatenate([Rotation.from_matrix(R_cw).as_rotvec(), t_cw])).x
    return Rotation.from_rotvec(p[:3]).as_matrix(), p[3:]

# ============================================================================ the catalogue

M = Mistake
MISTAKES = [
    M("pnp_linear", "R not orthogonalized", gpn.check_pnp_linear, pnp_linear_no_orthogonalization,
      ("not orthonormal", "orthogonalize"), defining="R is a rotation"),
    M("pnp_linear", "sign of P not fixed", gpn.check_pnp_linear, pnp_linear_no_sign_fix, ("det r = -1",),
      defining="R is a rotation"),
    M("pnp_linear", "R_wc returned", gpn.check_pnp_linear, pnp_linear_transposed, ("transposed",)),
    M("pnp_ransac", "squared error vs threshold", gpn.check_pnp_ransac, pnp_ransac_squared, ("squared error",)),
    M("pnp_ransac", "inverted inlier mask", gpn.check_pnp_ransac, pnp_ransac_inverted, ("inverted",)),
    M("pnp_nonlinear", "returns the start", gpn.check_pnp_nonlinear, pnp_nonlinear_unchanged, ("did not move",)),
    M("pnp_nonlinear", "optimizes the 9 entries of R", gpn.check_pnp_nonlinear, pnp_nonlinear_nine_entries,
      ("not a rotation",)),
    M("pnp_nonlinear", "projection not divided by z", gpn.check_pnp_nonlinear, pnp_nonlinear_no_depth_division,
      ("divided by its depth",)),
]

#: Correct solutions: they must score full marks.
HONEST = [
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

"""The mistake catalogue: classic buggy versions of every exercise, run through its check.

Each entry of :data:`CATALOGUE` is one classic mistake: a buggy version of an exercise (written
as a student would), the check function of its notebook, and the words its verdict must contain
to *name* the mistake (the one sentence that says what to change). The tests assert, for every
entry, that the check fails it (caught), that the verdict names it (named), and, for a mistake
that breaks a defining property (see :func:`course_lib.grading.core.declare_defining`), that
:func:`course_lib.grading.core.score` gives at most half of the points and that the printed
verdict leads with the property. The honest reference solutions must score 1, and every
declared defining property must be tested on at least three cases.

Run ``python tests/checks/test_mistakes.py`` for the table: caught N/N, named N/N, and the points per
mistake (out of the grader's 10 per exercise: 90 % from this score, 10 % from the nbval verdict,
which a failing check never earns). docs/mistakes.md explains how to add a mistake.
"""

from __future__ import annotations

import contextlib
import io
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from course_lib.grading import core  # noqa: E402
from course_lib.grading import bundle_adjustment as gba  # noqa: E402
from course_lib.grading import essential as ges  # noqa: E402
from course_lib.grading import fundamental as gfu  # noqa: E402
from course_lib.grading import nerf_data as gnd  # noqa: E402
from course_lib.grading import nerf_model as gnm  # noqa: E402
from course_lib.grading import nerf_rendering as gnr  # noqa: E402
from course_lib.grading import pnp as gpn  # noqa: E402
from course_lib.grading import triangulation as gtr  # noqa: E402
from course_lib.sfm import bundle_adjustment as rba  # noqa: E402
from course_lib.sfm import essential as res  # noqa: E402
from course_lib.sfm import fundamental as rfu  # noqa: E402
from course_lib.sfm import pnp as rpn  # noqa: E402
from course_lib.sfm import triangulation as rtr  # noqa: E402
from course_lib.sfm import visibility as rvi  # noqa: E402

#: Points per exercise in the grader and the share of them that comes from the hidden checks.
POINTS, HIDDEN_SHARE = 10.0, 0.9


@dataclass
class Mistake:
    """One classic mistake: a buggy version of an exercise and what its verdict must say."""

    exercise: str
    name: str  # the mistake, in a few words
    check: Callable  # the check function of the notebook
    fn: Callable  # the buggy version
    names: tuple[str, ...]  # the verdict names the mistake: all of these (lower case) appear in it
    defining: str | None = None  # the defining property it breaks, if any


def run_check(check: Callable, fn: Callable) -> tuple[core.CheckResult, str]:
    """Run a check function on ``fn``; return its CheckResult and printed verdict."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        check(fn)
    out = buf.getvalue()
    exercise = out.splitlines()[0].strip()
    return core.RESULTS[exercise], out


# ============================================================================ buggy versions
# Each is written as a student would write it (often the reference with one line changed).

def _h(x):
    return np.column_stack([x, np.ones(len(x))])


# -- 01: normalize_points -----------------------------------------------------------------------
def normalize_no_centroid(x):
    s = np.sqrt(2) / np.linalg.norm(x - x.mean(0), axis=1).mean()
    T = np.diag([s, s, 1.0])
    return x * s, T


def normalize_mean_one(x):
    c = x.mean(0)
    s = 1.0 / np.linalg.norm(x - c, axis=1).mean()
    T = np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1.0]])
    return (x - c) * s, T


def normalize_two_scales(x):
    c = x.mean(0)
    s = np.sqrt(2) / np.abs(x - c).mean(0) / np.sqrt(2)
    T = np.array([[s[0], 0, -s[0] * c[0]], [0, s[1], -s[1] * c[1]], [0, 0, 1.0]])
    return (x - c) * s, T


def normalize_T_inverted(x):
    xn, T = rfu.normalize_points(x)
    return xn, np.linalg.inv(T)


# -- 01: eight_point ----------------------------------------------------------------------------
def _eight(x1, x2, normalize=True, rank2=True, transpose=False):
    if normalize:
        x1n, T1 = rfu.normalize_points(x1)
        x2n, T2 = rfu.normalize_points(x2)
    else:
        x1n, x2n, T1, T2 = x1, x2, np.eye(3), np.eye(3)
    a, b = (x2n, x1n) if transpose else (x1n, x2n)
    u1, v1 = a.T
    u2, v2 = b.T
    A = np.stack([u2 * u1, u2 * v1, u2, v2 * u1, v2 * v1, v2, u1, v1, np.ones_like(u1)], axis=1)
    F = np.linalg.svd(A)[2][-1].reshape(3, 3)
    if rank2:
        U, s, Vt = np.linalg.svd(F)
        F = U @ np.diag([s[0], s[1], 0.0]) @ Vt
    Ta, Tb = (T2, T1) if transpose else (T1, T2)
    F = Tb.T @ F @ Ta
    return F / np.linalg.norm(F)


def eight_point_no_rank2(x1, x2):
    return _eight(x1, x2, rank2=False)


def eight_point_unnormalized(x1, x2):
    return _eight(x1, x2, normalize=False)


def eight_point_transposed(x1, x2):
    return _eight(x1, x2, transpose=True)


# -- 01: sampson_distance -----------------------------------------------------------------------
def sampson_squared(F, x1, x2):
    return rfu.sampson_distance(F, x1, x2) ** 2


def sampson_algebraic(F, x1, x2):
    return np.abs(np.sum(_h(x2) * (_h(x1) @ F.T), axis=1))


def sampson_one_sided(F, x1, x2):
    l2 = _h(x1) @ F.T
    return np.abs(np.sum(_h(x2) * l2, axis=1)) / np.hypot(l2[:, 0], l2[:, 1])


# -- 01: ransac_fundamental ---------------------------------------------------------------------
def _ransac(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000, error="sampson", refit=True,
            adaptive=True, own_rng=False):
    n = len(x1)
    best, n_iters, need = None, 0, max_iters
    g = np.random.default_rng() if own_rng else rng
    while n_iters < min(need, max_iters):
        n_iters += 1
        idx = g.choice(n, 8, replace=False)
        F = rfu.eight_point(x1[idx], x2[idx])
        if error == "sampson":
            inl = rfu.sampson_distance(F, x1, x2) < threshold_px
        elif error == "algebraic":
            inl = np.abs(np.sum(_h(x2) * (_h(x1) @ F.T), axis=1)) < threshold_px
        else:
            inl = rfu.sampson_distance(F, x1, x2) ** 2 < threshold_px
        if best is None or inl.sum() > best[1].sum():
            best = (F, inl)
            w = inl.mean()
            if adaptive and 0 < w < 1:
                need = math.log(1 - confidence) / math.log(1 - w**8)
            elif adaptive:
                need = 0
    F, inl = best
    if refit and inl.sum() >= 8:
        F = rfu.eight_point(x1[inl], x2[inl])
    return rfu.RansacResult(F, inl, n_iters)


def ransac_algebraic(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    return _ransac(x1, x2, rng, threshold_px, confidence, max_iters, error="algebraic")


def ransac_no_refit(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    return _ransac(x1, x2, rng, threshold_px, confidence, max_iters, refit=False)


def ransac_fixed_iterations(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    return _ransac(x1, x2, rng, threshold_px, confidence, max_iters, adaptive=False)


def ransac_global_rng(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    return _ransac(x1, x2, rng, threshold_px, confidence, max_iters, own_rng=True)


# -- 02: essential_from_fundamental ---------------------------------------------------------------
def essential_uncorrected(F, K):
    E = K.T @ F @ K
    return E / np.linalg.norm(E) * np.sqrt(2)


def essential_wrong_order(F, K):
    U, _, Vt = np.linalg.svd(K @ F @ K.T)
    return U @ np.diag([1.0, 1.0, 0.0]) @ Vt


# -- 02: pose_candidates --------------------------------------------------------------------------
_W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def _candidates(E, fix_det=True, order="documented", centre=True):
    U, _, Vt = np.linalg.svd(E)
    u3 = U[:, 2]
    combos = [(R0, t) for R0 in (U @ _W @ Vt, U @ _W.T @ Vt) for t in (u3, -u3)]
    if order == "sign_first":  # (W, +), (Wᵀ, +), (W, -), (Wᵀ, -)
        combos = [combos[0], combos[2], combos[1], combos[3]]
    Rs, Cs = [], []
    for R, t in combos:
        C = -R.T @ t if centre else t
        if fix_det and np.linalg.det(R) < 0:
            R, C = -R, -C
        Rs.append(R)
        Cs.append(C / np.linalg.norm(C))
    return np.stack(Rs), np.stack(Cs)


def pose_candidates_no_det_fix(E):
    return _candidates(E, fix_det=False)


def pose_candidates_other_order(E):
    return _candidates(E, order="sign_first")


def pose_candidates_t_for_C(E):
    return _candidates(E, centre=False)


# -- 03: triangulate_linear -----------------------------------------------------------------------
def _dlt(P1, P2, x1, x2, swap=False, divide=True, largest=False):
    out = []
    for a, b in zip(x1, x2):
        Pa, Pb = (P2, P1) if swap else (P1, P2)
        A = np.stack([a[0] * Pa[2] - Pa[0], a[1] * Pa[2] - Pa[1], b[0] * Pb[2] - Pb[0], b[1] * Pb[2] - Pb[1]])
        Xh = np.linalg.svd(A)[2][0 if largest else -1]
        out.append(Xh[:3] / Xh[3] if divide else Xh)
    return np.array(out)


def triangulate_swapped_cameras(P1, P2, x1, x2):
    return _dlt(P1, P2, x1, x2, swap=True)


def triangulate_homogeneous(P1, P2, x1, x2):
    return _dlt(P1, P2, x1, x2, divide=False)


def triangulate_largest_vector(P1, P2, x1, x2):
    return _dlt(P1, P2, x1, x2, largest=True)


def triangulate_squeezed(P1, P2, x1, x2):
    return np.squeeze(rtr.triangulate_linear(P1, P2, x1, x2))


# -- 03: choose_pose --------------------------------------------------------------------------------
def _choose(R, C, K, x1, x2, test):
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    Xs, fronts = [], []
    for k in range(4):
        t = -R[k] @ C[k]
        X = rtr.triangulate_linear(P1, K @ np.hstack([R[k], t[:, None]]), x1, x2)
        Xs.append(X)
        fronts.append(test(R[k], C[k], X))
    counts = np.array([f.sum() for f in fronts])
    k = int(np.argmax(counts))
    return rtr.PoseChoice(R[k], -R[k] @ C[k], Xs[k], fronts[k], counts, k)


def choose_pose_camera1_only(R, C, K, x1, x2):
    return _choose(R, C, K, x1, x2, lambda Rk, Ck, X: X[:, 2] > 0)


def choose_pose_camera2_only(R, C, K, x1, x2):
    return _choose(R, C, K, x1, x2, lambda Rk, Ck, X: (X - Ck) @ Rk[2] > 0)


def choose_pose_no_centre(R, C, K, x1, x2):
    return _choose(R, C, K, x1, x2, lambda Rk, Ck, X: (X[:, 2] > 0) & (X @ Rk[2] > 0))


# -- 03: triangulate_nonlinear -------------------------------------------------------------------------
def triangulate_nonlinear_unchanged(K, R_cws, t_cws, uv, X0):
    return np.array(X0, copy=True)


def triangulate_nonlinear_two_views(K, R_cws, t_cws, uv, X0):
    return rtr.triangulate_nonlinear(K, R_cws[:2], t_cws[:2], uv[:, :2], X0)


def triangulate_nonlinear_no_depth_division(K, R_cws, t_cws, uv, X0):
    from scipy.optimize import least_squares

    out = []
    for j in range(len(X0)):
        seen = [i for i in range(len(R_cws)) if np.isfinite(uv[j, i]).all()]

        def res(X):  # the projection is not divided by its depth
            return np.concatenate([(K @ (R_cws[i] @ X + t_cws[i]))[:2] - uv[j, i] for i in seen])

        out.append(least_squares(res, X0[j]).x)
    return np.array(out)


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


# -- 05: visibility_matrix, reprojection_residuals, jacobian_sparsity, bundle_adjust ----------------------
def visibility_transposed(track_uv):
    return rvi.visibility_matrix(track_uv).T


def visibility_inverted(track_uv):
    return ~rvi.visibility_matrix(track_uv)


def residuals_2d(params, n_cameras, n_points, camera_idx, point_idx, uv, K):
    return rba.reprojection_residuals(params, n_cameras, n_points, camera_idx, point_idx, uv, K).reshape(-1, 2)


def residuals_R_wc(params, n_cameras, n_points, camera_idx, point_idx, uv, K):
    R, t, X = rba.unpack_params(params, n_cameras, n_points)
    xc = np.einsum("kji,kj->ki", R[camera_idx], X[point_idx]) + t[camera_idx]
    xh = xc @ K.T
    return (xh[:, :2] / xh[:, 2:] - uv).ravel()


def residuals_no_depth_division(params, n_cameras, n_points, camera_idx, point_idx, uv, K):
    R, t, X = rba.unpack_params(params, n_cameras, n_points)
    xc = np.einsum("kij,kj->ki", R[camera_idx], X[point_idx]) + t[camera_idx]
    return ((xc @ K.T)[:, :2] - uv).ravel()


def sparsity_nine_per_camera(n_cameras, n_points, camera_idx, point_idx):
    import scipy.sparse as sp

    A = sp.lil_matrix((2 * len(camera_idx), 9 * n_cameras + 3 * n_points), dtype=int)
    for k, (cm, pt) in enumerate(zip(camera_idx, point_idx)):
        for r in (2 * k, 2 * k + 1):
            A[r, 9 * cm: 9 * cm + 9] = 1
            A[r, 9 * n_cameras + 3 * pt: 9 * n_cameras + 3 * pt + 3] = 1
    return A


def sparsity_no_offset(n_cameras, n_points, camera_idx, point_idx):
    A = np.zeros((2 * len(camera_idx), 6 * n_cameras + 3 * n_points), dtype=int)
    for k, (cm, pt) in enumerate(zip(camera_idx, point_idx)):
        A[2 * k: 2 * k + 2, 6 * cm: 6 * cm + 6] = 1
        A[2 * k: 2 * k + 2, 3 * pt: 3 * pt + 3] = 1
    return A


def sparsity_not_interleaved(n_cameras, n_points, camera_idx, point_idx):
    A = rba.jacobian_sparsity(n_cameras, n_points, camera_idx, point_idx).toarray()
    return np.concatenate([A[0::2], A[1::2]])


def _ba(K, R_cw, t_cw, X, uv, callback=None, nine=False, max_nfev=None, call_back=True, points_only=False):
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    cam, pt, obs = gba.observation_arrays(uv)
    M, N = len(R_cw), len(X)

    def unpack(p):
        if nine:
            R = p[: 9 * M].reshape(M, 3, 3)
            t = p[9 * M: 12 * M].reshape(M, 3)
            return R, t, p[12 * M:].reshape(N, 3)
        return rba.unpack_params(p, M, N)

    def res(p):
        R, t, Y = unpack(p)
        xc = np.einsum("kij,kj->ki", R[cam], Y[pt]) + t[cam]
        xh = xc @ K.T
        return (xh[:, :2] / xh[:, 2:] - obs).ravel()

    if points_only:  # the cameras are not optimized: only the points move
        def res_pts(q):
            return res(np.concatenate([rba.pack_params(R_cw, t_cw, X)[: 6 * M], q]))

        q = least_squares(res_pts, X.ravel()).x
        sol = type("Sol", (), {"x": np.concatenate([rba.pack_params(R_cw, t_cw, X)[: 6 * M], q])})
    elif nine:
        p0 = np.concatenate([R_cw.ravel(), t_cw.ravel(), X.ravel()])
        sol = least_squares(res, p0, max_nfev=max_nfev or 50)
    else:
        p0 = rba.pack_params(R_cw, t_cw, X)
        J = rba.jacobian_sparsity(M, N, cam, pt)
        sol = least_squares(res, p0, jac_sparsity=J, x_scale="jac", max_nfev=max_nfev, method="trf")
    R, t, Y = unpack(sol.x)
    if callback is not None and call_back:
        callback(R, t, Y)
    del Rotation
    return R, t, Y


def ba_nine_entries(K, R_cw, t_cw, X, uv, callback=None):
    return _ba(K, R_cw, t_cw, X, uv, callback, nine=True)


def ba_points_only(K, R_cw, t_cw, X, uv, callback=None):
    return _ba(K, R_cw, t_cw, X, uv, callback, points_only=True)


def ba_no_callback(K, R_cw, t_cw, X, uv, callback=None):
    return _ba(K, R_cw, t_cw, X, uv, callback, call_back=False)


# -- 06: get_rays, stratified_samples, query_points, positional_encoding ----------------------------------
def _torch():
    import torch

    return torch


def get_rays_opengl(H, W, K, c2w):
    torch = _torch()
    K = torch.as_tensor(K, dtype=torch.float32)
    c2w = torch.as_tensor(c2w, dtype=torch.float32)
    u, v = torch.meshgrid(torch.arange(W, dtype=torch.float32), torch.arange(H, dtype=torch.float32), indexing="xy")
    d = torch.stack([(u - K[0, 2]) / K[0, 0], -(v - K[1, 2]) / K[1, 1], -torch.ones_like(u)], -1)
    rays_d = d @ c2w[:3, :3].T
    return c2w[:3, 3].expand(rays_d.shape), rays_d


def get_rays_ij(H, W, K, c2w):
    from course_lib.nerf.rays import get_rays

    o, d = get_rays(H, W, K, c2w)  # as with torch.meshgrid(arange(W), arange(H), indexing="ij"): (W, H, 3)
    return o.transpose(0, 1), d.transpose(0, 1)


def stratified_no_jitter(near, far, n_samples, n_rays, perturb, generator=None):
    torch = _torch()
    return torch.linspace(near, far, n_samples).expand(n_rays, n_samples).clone()


def stratified_wide_jitter(near, far, n_samples, n_rays, perturb, generator=None):
    torch = _torch()
    z = torch.linspace(near, far, n_samples).expand(n_rays, n_samples).clone()
    if perturb:
        z = z + (torch.rand(n_rays, n_samples, generator=generator) - 0.5) * (far - near) * 0.3
    return z


def stratified_same_jitter(near, far, n_samples, n_rays, perturb, generator=None):
    from course_lib.nerf.rays import stratified_samples

    torch = _torch()
    z = stratified_samples(near, far, n_samples, 1, perturb, generator=generator)
    return z.expand(n_rays, n_samples).clone() if perturb else torch.linspace(near, far, n_samples).expand(
        n_rays, n_samples).clone()


def query_swapped(rays_o, rays_d, z_vals):
    return rays_d[:, None, :] + z_vals[..., None] * rays_o[:, None, :]


def query_no_origin(rays_o, rays_d, z_vals):
    return z_vals[..., None] * rays_d[:, None, :]


def query_normalized(rays_o, rays_d, z_vals):
    d = rays_d / rays_d.norm(dim=-1, keepdim=True)
    return rays_o[:, None, :] + z_vals[..., None] * d[:, None, :]


def encoding_no_identity(x, n_freqs, include_input=True):
    from course_lib.nerf.encoding import positional_encoding

    return positional_encoding(x, n_freqs, include_input=False)


def encoding_no_pi(x, n_freqs, include_input=True):
    torch = _torch()
    parts = [x] if include_input else []
    for k in range(n_freqs):
        parts += [torch.sin(2.0**k * x), torch.cos(2.0**k * x)]
    return torch.cat(parts, -1)


# -- 07: NeRF, psnr -------------------------------------------------------------------------------------
def _nerf_classes():
    torch = _torch()
    from torch.nn import functional as F

    from course_lib.nerf.model import NeRF

    class NeRFSigmoidDensity(NeRF):
        def forward(self, pts, viewdirs=None):
            rgb, _ = super().forward(pts, viewdirs)
            return rgb, torch.sigmoid(self.sigma_head(self.trunk_features(pts))[..., 0])

    class NeRFNoSkip(NeRF):
        def __init__(self, *args, **kw):
            kw["skips"] = ()
            super().__init__(*args, **kw)

    class NeRFNoDensityActivation(NeRF):
        def forward(self, pts, viewdirs=None):
            rgb, _ = super().forward(pts, viewdirs)
            return rgb, self.sigma_head(self.trunk_features(pts))[..., 0]

    class NeRFSkipOrder(NeRF):
        def trunk_features(self, pts):
            from course_lib.nerf.encoding import positional_encoding

            x = positional_encoding(pts, self.pos_freqs)
            h = x
            for i, layer in enumerate(self.trunk):
                h = F.relu(layer(h))
                if i in self.skips:
                    h = torch.cat([h, x], dim=-1)
            return h

    return NeRFSigmoidDensity, NeRFNoSkip, NeRFNoDensityActivation, NeRFSkipOrder


def psnr_sign(mse):
    return 10 * _torch().log10(mse)


def psnr_natural_log(mse):
    return -10 * _torch().log(mse)


def psnr_right(mse):
    return -10 * _torch().log10(mse)


# -- 08: volume_render ------------------------------------------------------------------------------------
def _render(form="alpha_T", delta="norm", cumprod="exclusive"):
    def volume_render(rgb, sigma, z_vals, rays_d, white_background=True):
        torch = _torch()
        out = gnr.render_variant(rgb.numpy(), sigma.numpy(), z_vals.numpy(), rays_d.numpy(), white=white_background,
                                 delta=delta, cumprod=cumprod, form=form)
        return {k: torch.as_tensor(v) for k, v in out.items()}

    return volume_render


# ============================================================================ the catalogue

def _catalogue() -> list[Mistake]:
    sig, noskip, noact, skiporder = _nerf_classes()
    M = Mistake
    return [
        # 01
        M("normalize_points", "centroid not removed", gfu.check_normalize_points, normalize_no_centroid,
          ("subtract the mean",)),
        M("normalize_points", "mean distance 1", gfu.check_normalize_points, normalize_mean_one, ("mean distance is 1",)),
        M("normalize_points", "one scale per axis", gfu.check_normalize_points, normalize_two_scales,
          ("different scales",)),
        M("normalize_points", "T inverted", gfu.check_normalize_points, normalize_T_inverted, ("t is the inverse",)),
        M("eight_point", "no rank-2 step", gfu.check_eight_point, eight_point_no_rank2, ("rank 3", "enforce rank 2"),
          defining="rank 2"),
        M("eight_point", "not normalized", gfu.check_eight_point, eight_point_unnormalized, ("not normalized",)),
        M("eight_point", "F transposed", gfu.check_eight_point, eight_point_transposed, ("transposed f",)),
        M("sampson_distance", "squared error", gfu.check_sampson_distance, sampson_squared, ("squared error",)),
        M("sampson_distance", "algebraic error", gfu.check_sampson_distance, sampson_algebraic, ("algebraic error",)),
        M("sampson_distance", "one-sided distance", gfu.check_sampson_distance, sampson_one_sided,
          ("its epipolar line only",)),
        M("ransac_fundamental", "threshold on the algebraic error", gfu.check_ransac_fundamental, ransac_algebraic,
          ("algebraic error", "sampson_distance(f, x1, x2) < threshold_px")),
        M("ransac_fundamental", "no final refit", gfu.check_ransac_fundamental, ransac_no_refit, ("refit",)),
        M("ransac_fundamental", "fixed iteration count", gfu.check_ransac_fundamental, ransac_fixed_iterations,
          ("n_iters = 2000",)),
        M("ransac_fundamental", "np.random instead of rng", gfu.check_ransac_fundamental, ransac_global_rng,
          ("from the rng argument",)),
        # 02
        M("essential_from_fundamental", "singular values not corrected", ges.check_essential_from_fundamental,
          essential_uncorrected, ("not corrected", "(1, 1, 0)"), defining="singular values (1, 1, 0)"),
        M("essential_from_fundamental", "K F Kᵀ", ges.check_essential_from_fundamental, essential_wrong_order,
          ("k f kᵀ",)),
        M("pose_candidates", "det R = -1 not fixed", ges.check_pose_candidates, pose_candidates_no_det_fix,
          ("det -1", "flip the sign of both r and c"), defining="det R = +1"),
        M("pose_candidates", "candidates in another order", ges.check_pose_candidates, pose_candidates_other_order,
          ("another order", "the docstring fixes"), defining="documented order"),
        M("pose_candidates", "t returned as C", ges.check_pose_candidates, pose_candidates_t_for_C,
          ("not the camera centre",)),
        # 03
        M("triangulate_linear", "P1 and P2 swapped in A", gtr.check_triangulate_linear, triangulate_swapped_cameras,
          ("cameras are swapped",)),
        M("triangulate_linear", "no division by X_h[3]", gtr.check_triangulate_linear, triangulate_homogeneous,
          ("divide by the last coordinate",)),
        M("triangulate_linear", "largest singular vector", gtr.check_triangulate_linear, triangulate_largest_vector,
          ("largest singular value",)),
        M("triangulate_linear", "N = 1 squeezed", gtr.check_triangulate_linear, triangulate_squeezed,
          ("keep the points axis",)),
        M("choose_pose", "cheirality on camera 1 only", gtr.check_choose_pose, choose_pose_camera1_only,
          ("checks only camera 1",), defining="in front of both cameras"),
        M("choose_pose", "cheirality on camera 2 only", gtr.check_choose_pose, choose_pose_camera2_only,
          ("checks only camera 2",), defining="in front of both cameras"),
        M("choose_pose", "cheirality forgets the centre", gtr.check_choose_pose, choose_pose_no_centre,
          ("forgets the centre",), defining="in front of both cameras"),
        M("triangulate_nonlinear", "returns X0", gtr.check_triangulate_nonlinear, triangulate_nonlinear_unchanged,
          ("did not move",)),
        M("triangulate_nonlinear", "only two views", gtr.check_triangulate_nonlinear, triangulate_nonlinear_two_views,
          ("only the first two views",)),
        M("triangulate_nonlinear", "projection not divided by z", gtr.check_triangulate_nonlinear,
          triangulate_nonlinear_no_depth_division, ("divided by its depth",)),
        # 04
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
        # 05
        M("visibility_matrix", "transposed", gba.check_visibility_matrix, visibility_transposed, ("transpose",)),
        M("visibility_matrix", "inverted", gba.check_visibility_matrix, visibility_inverted, ("not",)),
        M("reprojection_residuals", "(K, 2) instead of (2K,)", gba.check_reprojection_residuals, residuals_2d,
          ("flat",)),
        M("reprojection_residuals", "R_wc instead of R_cw", gba.check_reprojection_residuals, residuals_R_wc,
          ("r_wc",)),
        M("reprojection_residuals", "no division by the depth", gba.check_reprojection_residuals,
          residuals_no_depth_division, ("depth",)),
        M("jacobian_sparsity", "9 parameters per camera", gba.check_jacobian_sparsity, sparsity_nine_per_camera,
          ("9 per camera",)),
        M("jacobian_sparsity", "point columns without the 6M offset", gba.check_jacobian_sparsity, sparsity_no_offset,
          ("point columns",)),
        M("jacobian_sparsity", "rows not interleaved", gba.check_jacobian_sparsity, sparsity_not_interleaved,
          ("interleaved",)),
        M("bundle_adjust", "optimizes the 9 entries of R", gba.check_bundle_adjustment, ba_nine_entries,
          ("not a rotation",)),
        M("bundle_adjust", "cameras not optimized", gba.check_bundle_adjustment, ba_points_only,
          ("some parameters are not optimized",)),
        M("bundle_adjust", "callback never called", gba.check_bundle_adjustment, ba_no_callback,
          ("never called",)),
        # 06
        M("get_rays", "OpenGL camera axes", gnd.check_get_rays, get_rays_opengl, ("opengl",)),
        M("get_rays", "meshgrid ij", gnd.check_get_rays, get_rays_ij, ("meshgrid",)),
        M("stratified_samples", "no jitter in training", gnd.check_stratified_samples, stratified_no_jitter,
          ("no jitter",)),
        M("stratified_samples", "jitter wider than a bin", gnd.check_stratified_samples, stratified_wide_jitter,
          ("leave their bin",)),
        M("stratified_samples", "one jitter for all rays", gnd.check_stratified_samples, stratified_same_jitter,
          ("the same jitter",)),
        M("query_points", "o and d swapped", gnd.check_query_points, query_swapped, ("swapped",)),
        M("query_points", "origin missing", gnd.check_query_points, query_no_origin, ("rays_o is missing",)),
        M("query_points", "directions normalized", gnd.check_query_points, query_normalized,
          ("directions are normalized",)),
        M("positional_encoding", "no identity term", gnd.check_positional_encoding, encoding_no_identity,
          ("identity term",)),
        M("positional_encoding", "no pi", gnd.check_positional_encoding, encoding_no_pi, ("pi factor",)),
        # 07
        M("NeRF", "sigmoid on the density", gnm.check_nerf_model, sig, ("sigmoid", "torch.relu"),
          defining="ReLU density"),
        M("NeRF", "no activation on the density", gnm.check_nerf_model, noact, ("no activation",),
          defining="ReLU density"),
        M("NeRF", "no skip connection", gnm.check_nerf_model, noskip, ("no skip connection",), defining="skip input"),
        M("NeRF", "skip concatenated as [h, γ(x)]", gnm.check_nerf_model, skiporder, ("[h, γ(x)]",),
          defining="skip input"),
        M("psnr", "sign flipped", gnm.check_psnr, psnr_sign, ("sign is flipped",)),
        M("psnr", "natural logarithm", gnm.check_psnr, psnr_natural_log, ("base-10",)),
        # 08
        M("volume_render", "no Δ in α", gnr.check_volume_render, _render(delta="none"), ("forgot delta",),
          defining="Δ in α"),
        M("volume_render", "weights forget α", gnr.check_volume_render, _render(form="T"),
          ("weights forget alpha",)),
        M("volume_render", "weights forget T", gnr.check_volume_render, _render(form="alpha"),
          ("forget the transmittance",)),
        M("volume_render", "inclusive cumprod", gnr.check_volume_render, _render(cumprod="inclusive"),
          ("inclusive cumprod",)),
        M("volume_render", "Δ not scaled by |d|", gnr.check_volume_render, _render(delta="plain"),
          ("not scaled by |d|",)),
    ]


CATALOGUE = _catalogue()

#: The honest solutions: (check, function) for every exercise.
REFERENCES = [
    (gfu.check_normalize_points, rfu.normalize_points), (gfu.check_eight_point, rfu.eight_point),
    (gfu.check_sampson_distance, rfu.sampson_distance), (gfu.check_ransac_fundamental, rfu.ransac_fundamental),
    (ges.check_essential_from_fundamental, res.essential_from_fundamental),
    (ges.check_pose_candidates, res.pose_candidates), (gtr.check_triangulate_linear, rtr.triangulate_linear),
    (gtr.check_choose_pose, rtr.choose_pose), (gtr.check_triangulate_nonlinear, rtr.triangulate_nonlinear),
    (gpn.check_pnp_linear, rpn.pnp_linear), (gpn.check_pnp_ransac, rpn.pnp_ransac),
    (gpn.check_pnp_nonlinear, rpn.pnp_nonlinear), (gnm.check_psnr, psnr_right),
    (gnr.check_volume_render, _render()),
]


def _nerf_reference():
    from course_lib.nerf.model import NeRF

    return NeRF


def _verdict(m: Mistake):
    result, out = run_check(m.check, m.fn)
    lines = out.lower()
    caught = not result.ok
    named = caught and all(w.lower() in lines for w in m.names)
    return result, out, caught, named


@pytest.mark.parametrize("m", CATALOGUE, ids=[f"{m.exercise}: {m.name}" for m in CATALOGUE])
def test_mistake_is_caught_named_and_weighed(m: Mistake):
    result, out, caught, named = _verdict(m)
    assert caught, f"the check passes the mistake '{m.name}':\n{out}"
    assert named, f"the verdict does not name '{m.name}' (expected {m.names}):\n{out}"
    frac = core.score(result)
    assert frac < 1.0
    if m.defining:
        assert m.defining in result.defining_failed, f"'{m.name}' should break '{m.defining}':\n{out}"
        assert frac <= core.DEFINING_CAP, f"'{m.name}' breaks '{m.defining}' but scores {frac:.2f}:\n{out}"
        first = out.splitlines()[1]
        assert "defining property" in first and m.defining in first, f"the verdict does not lead with it:\n{out}"


def test_catalogue_size():
    per_exercise: dict[str, int] = {}
    for m in CATALOGUE:
        per_exercise[m.exercise] = per_exercise.get(m.exercise, 0) + 1
    assert len(CATALOGUE) >= 40
    assert min(per_exercise.values()) >= 2, per_exercise


@pytest.mark.parametrize("check, fn", REFERENCES + [(gnm.check_nerf_model, None)],
                         ids=[c.__name__ for c, _ in REFERENCES] + ["check_nerf_model"])
def test_reference_scores_full_and_tests_each_defining_property_three_times(check, fn):
    result, out = run_check(check, fn if fn is not None else _nerf_reference())
    assert result.ok and core.score(result) == 1.0, out
    for prop in core.DEFINING.get(result.exercise, {}):
        n = sum(1 for v in result.verdicts if v.defining == prop)
        assert n >= 3, f"{result.exercise}: defining property '{prop}' is tested on {n} cases, expected >= 3\n{out}"


# ============================================================================ trivial answers
# Constants of the right shape: they satisfy every shape check and many properties (rank 2, a
# rotation, unit norm, the same result for the same seed), and must earn nothing.

def _trivial():
    torch = _torch()

    def ba_identity(K, R, t, X, uv, callback=None):
        if callback is not None:
            callback(R, t, X)
        return R, t, X

    class ConstantNeRF(torch.nn.Module):
        def __init__(self, **kw):
            super().__init__()
            self.layer = torch.nn.Linear(3, 4)

        def forward(self, pts, viewdirs):
            return torch.full((*pts.shape[:-1], 3), 0.5), torch.zeros(pts.shape[:-1])

    z = np.zeros
    return [
        (gfu.check_normalize_points, lambda x: (z(x.shape), np.eye(3))),
        (gfu.check_normalize_points, lambda x: (x.copy(), np.eye(3))),
        (gfu.check_eight_point, lambda x1, x2: np.eye(3)),
        (gfu.check_eight_point, lambda x1, x2: np.diag([1.0, 1.0, 0.0]) / np.sqrt(2)),
        (gfu.check_sampson_distance, lambda F, x1, x2: np.ones(len(x1))),
        (gfu.check_ransac_fundamental, lambda x1, x2, rng, threshold_px=1.0, **k: (np.eye(3), np.ones(len(x1), bool), 1)),
        (ges.check_essential_from_fundamental, lambda F, K: np.diag([1.0, 1.0, 0.0])),
        (ges.check_pose_candidates, lambda E: (np.stack([np.eye(3)] * 4), np.tile([1.0, 0.0, 0.0], (4, 1)))),
        (gtr.check_triangulate_linear, lambda P1, P2, x1, x2: z((len(x1), 3))),
        (gtr.check_choose_pose, lambda R, C, K, x1, x2: (R[0], -R[0] @ C[0], z((len(x1), 3)), np.ones(len(x1), bool),
                                                         np.array([len(x1), 0, 0, 0]))),
        (gtr.check_triangulate_nonlinear, lambda K, R, t, uv, X0: X0 * 1.0001),
        (gpn.check_pnp_linear, lambda X, x, K: (np.eye(3), z(3))),
        (gpn.check_pnp_ransac, lambda X, x, K, rng, **k: (np.eye(3), z(3), np.ones(len(X), bool), 1)),
        (gpn.check_pnp_nonlinear, lambda X, x, K, R, t: (np.eye(3), t)),
        (gba.check_visibility_matrix, lambda track_uv: z(track_uv.shape[:2], bool)),
        (gba.check_reprojection_residuals, lambda p, M, N, ci, pi, uv, K: z(2 * len(ci))),
        (gba.check_jacobian_sparsity, lambda M, N, ci, pi: np.ones((2 * len(ci), 6 * M + 3 * N))),
        (gba.check_bundle_adjustment, ba_identity),
        (gnd.check_get_rays, lambda H, W, K, c2w: (torch.zeros(H, W, 3), torch.zeros(H, W, 3))),
        (gnd.check_stratified_samples, lambda near, far, S, R, perturb, generator=None: torch.zeros(R, S)),
        (gnd.check_query_points, lambda o, d, zv: torch.zeros(*zv.shape, 3)),
        (gnd.check_positional_encoding, lambda x, L, include_input=True: torch.zeros(
            *x.shape[:-1], x.shape[-1] * (int(include_input) + 2 * L))),
        (gnm.check_nerf_model, ConstantNeRF),
        (gnm.check_psnr, lambda mse: torch.tensor(0.0)),
        (gnr.check_volume_render, lambda rgb, sigma, zv, d, white_background=True: {
            "rgb_map": torch.zeros(rgb.shape[0], 3), "depth_map": torch.zeros(sigma.shape[0]),
            "acc_map": torch.zeros(sigma.shape[0]), "weights": torch.zeros_like(sigma)}),
    ]


TRIVIAL = _trivial()


@pytest.mark.parametrize("check, fn", TRIVIAL, ids=[f"{c.__name__}-{k}" for k, (c, _) in enumerate(TRIVIAL)])
def test_a_trivial_answer_earns_nothing(check, fn):
    result, out = run_check(check, fn)
    assert core.score(result) == 0.0, out


def main() -> None:
    """Print the catalogue table: caught, named, points (of the grader's 10 per exercise)."""
    rows, caught_n, named_n = [], 0, 0
    for m in CATALOGUE:
        result, out, caught, named = _verdict(m)
        caught_n += caught
        named_n += named
        frac = core.score(result)
        pts = POINTS * HIDDEN_SHARE * frac
        rows.append((m.exercise, m.name, caught, named, m.defining or "", pts))
    w = max(len(r[0]) + len(r[1]) for r in rows) + 3
    print(f"{'exercise: mistake':<{w}} caught named  points/10  defining property")
    for ex, name, caught, named, prop, pts in rows:
        print(f"{ex + ': ' + name:<{w}} {'yes' if caught else 'NO':>6} {'yes' if named else 'NO':>5} {pts:>9.2f}  {prop}")
    print(f"caught {caught_n}/{len(rows)}, named {named_n}/{len(rows)}; "
          f"{sum(1 for r in rows if r[4])} mistakes break a defining property, "
          f"max points among them {max(r[5] for r in rows if r[4]):.2f}/10")


if __name__ == "__main__":
    main()

"""Sparse Levenberg-Marquardt for bundle adjustment, with the Schur complement on the points.

This is the kit's ONE bundle adjuster: :func:`course_lib.sfm.bundle_adjustment.adjust`
(the lesson, 6 parameters per camera, ``K`` fixed) and ``python -m course_lib ba`` (the "Bundle
Adjustment in the Large" problems, 9 parameters per camera) both call :func:`solve`. What changes
between them is only the camera model, a small object with two methods (:class:`CameraModel`).

Problem
    Cameras ``c_i`` (``M x n`` parameters), points ``X_j`` (``N x 3``), observations ``k`` of point
    ``pt_idx[k]`` in camera ``cam_idx[k]`` at ``obs[k]``. Residual ``r_k = project(c_i, X_j) - obs_k``
    (2 numbers), cost ``0.5 sum_k rho(|r_k|^2)`` with ``rho(s) = s`` (least squares) or a robust
    loss (``"huber"``, ``"soft_l1"``, ``"cauchy"``, defined as in ``scipy.optimize.least_squares``).

Normal equations (one Gauss-Newton / LM step)
    With ``A_k = d r_k / d c_i`` (2 x n) and ``B_k = d r_k / d X_j`` (2 x 3), analytic, and robust
    weights ``w_k`` (IRLS: ``w_k = rho'(|r_k|^2)``)::

        [U + lam D_U     W      ] [dc]   [-g_c]     U_i = sum_{k in i} w A^T A  (n x n per camera)
        [W^T        V + lam D_V ] [dX] = [-g_X]     V_j = sum_{k in j} w B^T B  (3 x 3 per point)
                                                    W_ij = w A_k^T B_k,  g = J^T w r

    ``D = diag(J^T W J)`` (clamped to [1e-6, 1e32] as in Ceres): Marquardt's scale-invariant damping.

Schur complement (why BA scales)
    ``V`` is block diagonal (a point only touches itself), so it is inverted 3x3 block by 3x3 block
    in one batched numpy call, and the points are eliminated::

        S dc = -g_c + W V^-1 g_X,     S = U + lam D_U - W V^-1 W^T      (the reduced camera system, nM x nM)
        dX = -V^-1 (g_X + W^T dc)

    ``S`` has a non-zero ``n x n`` block (i, l) only when cameras i and l see a common point.
    Each such block is ONE matrix product over the points the two cameras share (``Y^T W`` with
    ``Y = V^-1 W^T`` of their observations stacked), so Python loops over camera pairs, never over
    points or observations. ``S`` is small (441 x 441 for the 49 Ladybug cameras) and solved densely
    by Cholesky; above ``dense_limit`` unknowns it is assembled sparse and solved with
    ``scipy.sparse.linalg.spsolve`` (SuperLU). Most of an iteration goes to ``W V^-1 W^T`` and the
    Jacobian's blocks, little to the factorization. BLAS is held to one thread meanwhile
    (:func:`course_lib.threads.single_threaded_blas`): its threads only cost time on products this small.

Damping strategy
    Nielsen's (the one in Ceres): the gain ratio ``rho = actual / predicted decrease``; a step is
    taken when ``rho > 1e-3``, then ``lam *= max(1/3, 1 - (2 rho - 1)^3)``; otherwise ``lam *= nu``,
    ``nu *= 2``; ``lam`` stays within ``[LAM_MIN, LAM_MAX]``. Stops when the relative decrease of
    the cost in a step is below ``ftol`` (Ceres' ``function_tolerance``), the step is below ``xtol``
    relative to the parameters, the gradient is below ``gtol``, or after ``max_iterations`` steps.

Gauge
    Reprojections do not change under a similarity of the world (7 degrees of freedom), so
    ``J^T J`` is singular along 7 directions. :func:`solve` takes masks of fixed parameters: the
    lesson's :func:`~course_lib.sfm.bundle_adjustment.adjust` fixes one camera and one
    translation coordinate of a second one; for BAL problems (like Ceres and the SciPy cookbook)
    nothing is fixed: the damping ``lam D`` makes every step well defined, the gauge drifts freely
    and harmlessly, and the cost (which is gauge-invariant) is what is compared.

Camera models
    :class:`PinholeCamera` (the lesson: rotation vector + t, 6 parameters, ``K`` fixed, the kit's
    OpenCV axes) and :class:`BALCamera` (rotation vector, t, f, k1, k2, 9 parameters, BAL's axes;
    see :mod:`course_lib.data.bal`). Both rotation parametrizations are the rotation vector
    ``r`` with ``R = exp([r]_x)`` and additive updates ``r + dr``; the derivative is
    ``d(R X)/dr = -[R X]_x R J_r(r)`` with ``J_r`` the right Jacobian of SO(3).

Introduced in ``notebooks/05_bundle_adjustment.ipynb`` ("How does this scale?").
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg
from scipy.spatial.transform import Rotation

from course_lib.threads import single_threaded_blas
from course_lib.validate import KitInputError, intrinsics

__all__ = [
    "CameraModel",
    "PinholeCamera",
    "BALCamera",
    "SimpleRadialCamera",
    "rotvec_to_matrix",
    "right_jacobian_so3",
    "residuals",
    "jacobian",
    "NormalEquations",
    "normal_equations",
    "schur_solve",
    "reduced_camera_sparsity",
    "LMResult",
    "solve",
]


#: Bounds of the damping (Ceres: 1 / max_trust_region_radius and 1 / min_trust_region_radius,
#: with a larger floor so that a point seen once keeps a well-conditioned 3x3 block).
LAM_MIN, LAM_MAX = 1e-10, 1e16


# ---------------------------------------------------------------------------------------------
# Rotations
# ---------------------------------------------------------------------------------------------


def rotvec_to_matrix(rvec: np.ndarray) -> np.ndarray:
    """``(M, 3, 3)`` rotation matrices ``exp([r]_x)`` of rotation vectors ``(M, 3)`` (Rodrigues)."""
    return Rotation.from_rotvec(np.asarray(rvec, float).reshape(-1, 3)).as_matrix().reshape(-1, 3, 3)


def _skew_rows(v: np.ndarray) -> np.ndarray:
    """``(K, 3, 3)`` cross-product matrices of the rows of ``v (K, 3)``."""
    S = np.zeros((len(v), 3, 3))
    S[:, 0, 1], S[:, 0, 2] = -v[:, 2], v[:, 1]
    S[:, 1, 0], S[:, 1, 2] = v[:, 2], -v[:, 0]
    S[:, 2, 0], S[:, 2, 1] = -v[:, 1], v[:, 0]
    return S


def right_jacobian_so3(rvec: np.ndarray) -> np.ndarray:
    """``(M, 3, 3)`` right Jacobians of SO(3), ``exp([r + d]_x) ~ exp([r]_x) exp([J_r(r) d]_x)``.

    ``J_r(r) = I - (1 - cos a)/a^2 [r]_x + (a - sin a)/a^3 [r]_x^2`` with ``a = |r|`` (Taylor
    series below ``a = 1e-4``).
    """
    rvec = np.asarray(rvec, float).reshape(-1, 3)
    a = np.linalg.norm(rvec, axis=1)
    small = a < 1e-4
    a_safe = np.where(small, 1.0, a)
    c1 = np.where(small, 0.5 - a**2 / 24.0, (1.0 - np.cos(a_safe)) / a_safe**2)
    c2 = np.where(small, 1.0 / 6.0 - a**2 / 120.0, (a_safe - np.sin(a_safe)) / a_safe**3)
    S = _skew_rows(rvec)
    return np.eye(3) - c1[:, None, None] * S + c2[:, None, None] * (S @ S)


def _mm(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Batched small matrix product ``(K, a, b) @ (K, b, c) -> (K, a, c)``."""
    return np.matmul(A, B)


def _rigid(cameras: np.ndarray, X: np.ndarray, cam_idx: np.ndarray, with_jacobian: bool):
    """``P = R(r) X + t`` per observation, and optionally ``dP/dr`` (K, 3, 3) and ``R`` per observation."""
    R = rotvec_to_matrix(cameras[:, :3])
    Rk = R[cam_idx]
    RX = np.einsum("kij,kj->ki", Rk, X)
    P = RX + cameras[cam_idx, 3:6]
    if not with_jacobian:
        return P, None, None
    RJ = (R @ right_jacobian_so3(cameras[:, :3]))[cam_idx]
    dP_dr = -_mm(_skew_rows(RX), RJ)
    return P, dP_dr, Rk


# ---------------------------------------------------------------------------------------------
# Camera models
# ---------------------------------------------------------------------------------------------


class CameraModel(Protocol):
    """What :func:`solve` needs from a camera model.

    Attributes:
        n_params: parameters per camera (``n``).
        param_names: their names, for messages and docs.
    """

    n_params: int
    param_names: tuple[str, ...]

    def project(self, cameras: np.ndarray, X: np.ndarray, cam_idx: np.ndarray) -> np.ndarray:
        """Project the observation's point ``X[k]`` (``(K, 3)``, gathered per observation) with
        camera ``cameras[cam_idx[k]]`` (``cameras``: ``(M, n)``); returns ``(K, 2)``."""

    def project_jacobian(self, cameras: np.ndarray, X: np.ndarray, cam_idx: np.ndarray):
        """Like :meth:`project`, also returning ``d proj / d camera`` ``(K, 2, n)`` and
        ``d proj / d X`` ``(K, 2, 3)``: ``(proj, J_cam, J_pt)``."""


class PinholeCamera:
    """The lesson's camera: ``K`` fixed (shared), 6 parameters ``(r, t_cw)`` in the kit's OpenCV axes.

    ``x_c = R(r) X + t``, ``(u, v) = (K x_c)[:2] / z_c`` (:func:`course_lib.conventions.project`).
    The projection is notebook 05's exercise ``reprojection_residuals`` (called with observations
    at 0: in the instructor's kit the reference, in the student kit the student's own; see
    :mod:`course_lib.exercises`); the Jacobian is the kit's, analytic.
    """

    param_names = ("rx", "ry", "rz", "tx", "ty", "tz")
    n_params = 6

    def __init__(self, K: np.ndarray):
        self.K = intrinsics(K)

    def project(self, cameras, X, cam_idx):
        from course_lib.exercises import call

        n = len(cam_idx)
        params = np.concatenate([np.asarray(cameras, float).ravel(), np.asarray(X, float).ravel()])
        r = call("reprojection_residuals", params, len(cameras), n, np.asarray(cam_idx, np.int64), np.arange(n),
                 np.zeros((n, 2)), self.K)
        return r.reshape(n, 2)

    def project_jacobian(self, cameras, X, cam_idx):
        proj = self.project(cameras, X, cam_idx)
        P, dP_dr, Rk = _rigid(cameras, X, cam_idx, True)
        K = self.K
        x, y, z = P[:, 0], P[:, 1], P[:, 2]
        iz = 1.0 / z
        fx, s, fy = K[0, 0], K[0, 1], K[1, 1]
        G = np.zeros((len(z), 2, 3))  # d proj / d P
        G[:, 0, 0] = fx * iz
        G[:, 0, 1] = s * iz
        G[:, 0, 2] = -(fx * x + s * y) * iz**2
        G[:, 1, 1] = fy * iz
        G[:, 1, 2] = -fy * y * iz**2
        J_cam = np.empty((len(z), 2, 6))
        J_cam[:, :, 0:3] = _mm(G, dP_dr)
        J_cam[:, :, 3:6] = G
        return proj, J_cam, _mm(G, Rk)


class BALCamera:
    """The camera of "Bundle Adjustment in the Large": 9 parameters ``(r, t, f, k1, k2)``.

    ``P = R(r) X + t``, ``p = -P[:2] / P.z``, ``proj = f (1 + k1 |p|^2 + k2 |p|^4) p`` (pixels from
    the image centre, y up, camera looking down -z; see :mod:`course_lib.data.bal`).
    """

    param_names = ("rx", "ry", "rz", "tx", "ty", "tz", "f", "k1", "k2")
    n_params = 9

    def project(self, cameras, X, cam_idx):
        P, _, _ = _rigid(cameras, X, cam_idx, False)
        p = -P[:, :2] / P[:, 2:3]
        n = (p**2).sum(axis=1)
        f, k1, k2 = cameras[cam_idx, 6], cameras[cam_idx, 7], cameras[cam_idx, 8]
        return (f * (1.0 + k1 * n + k2 * n**2))[:, None] * p

    def project_jacobian(self, cameras, X, cam_idx):
        P, dP_dr, Rk = _rigid(cameras, X, cam_idx, True)
        iz = 1.0 / P[:, 2]
        p = -P[:, :2] * iz[:, None]
        n = (p**2).sum(axis=1)
        f, k1, k2 = cameras[cam_idx, 6], cameras[cam_idx, 7], cameras[cam_idx, 8]
        rad = 1.0 + k1 * n + k2 * n**2
        proj = (f * rad)[:, None] * p
        # d proj / d p = f (rad I + 2 (k1 + 2 k2 n) p p^T);  d p / d P = -[[1/z, 0, -x/z^2], [0, 1/z, -y/z^2]]
        c = 2.0 * f * (k1 + 2.0 * k2 * n)
        fr = f * rad
        Dp = c[:, None, None] * (p[:, :, None] * p[:, None, :])
        Dp[:, 0, 0] += fr
        Dp[:, 1, 1] += fr
        # G = Dp @ dp/dP, with dp/dP = [[-iz, 0, -p_x iz], [0, -iz, -p_y iz]] (since -x/z = p_x)
        G = np.empty((len(n), 2, 3))
        G[:, :, 0] = -Dp[:, :, 0] * iz[:, None]
        G[:, :, 1] = -Dp[:, :, 1] * iz[:, None]
        G[:, :, 2] = -(Dp[:, :, 0] * p[:, 0, None] + Dp[:, :, 1] * p[:, 1, None]) * iz[:, None]
        J_cam = np.empty((len(n), 2, 9))
        J_cam[:, :, 0:3] = _mm(G, dP_dr)
        J_cam[:, :, 3:6] = G
        J_cam[:, :, 6] = rad[:, None] * p
        J_cam[:, :, 7] = (f * n)[:, None] * p
        J_cam[:, :, 8] = (f * n**2)[:, None] * p
        return proj, J_cam, _mm(G, Rk)


class SimpleRadialCamera:
    """COLMAP's ``SIMPLE_RADIAL`` camera with its intrinsics *shared* by all cameras and refined.

    Per camera 6 parameters ``(r, t_cw)`` (the kit's OpenCV axes, as :class:`PinholeCamera`); shared
    by every camera 2 parameters ``(f, k1)`` (:attr:`n_shared`), the principal point ``(cx, cy)``
    fixed. ``P = R(r) X + t``, ``(x, y) = P[:2] / P.z``, ``d = 1 + k1 (x^2 + y^2)``,
    ``(u, v) = f d (x, y) + (cx, cy)`` (:func:`course_lib.data.camera.distort`).

    Args:
        principal_point: ``(cx, cy)`` in pixels (kit convention).
    """

    param_names = ("rx", "ry", "rz", "tx", "ty", "tz")
    n_params = 6
    shared_names = ("f", "k1")
    n_shared = 2

    def __init__(self, principal_point):
        self.c = np.asarray(principal_point, float).reshape(2)

    def project(self, cameras, X, cam_idx, shared):
        P, _, _ = _rigid(cameras, X, cam_idx, False)
        xy = P[:, :2] / P[:, 2:3]
        f, k1 = shared
        return f * (1.0 + k1 * (xy**2).sum(axis=1))[:, None] * xy + self.c

    def project_jacobian(self, cameras, X, cam_idx, shared):
        """``(proj (K, 2), J_cam (K, 2, 6), J_pt (K, 2, 3), J_shared (K, 2, 2))``."""
        P, dP_dr, Rk = _rigid(cameras, X, cam_idx, True)
        iz = 1.0 / P[:, 2]
        xy = P[:, :2] * iz[:, None]
        r2 = (xy**2).sum(axis=1)
        f, k1 = shared
        d = 1.0 + k1 * r2
        proj = (f * d)[:, None] * xy + self.c
        # d proj / d xy = f (d I + 2 k1 xy xyᵀ);  d xy / d P = [[1/z, 0, -x/z], [0, 1/z, -y/z]]
        Dxy = (2.0 * f * k1) * (xy[:, :, None] * xy[:, None, :])
        Dxy[:, 0, 0] += f * d
        Dxy[:, 1, 1] += f * d
        G = np.empty((len(iz), 2, 3))
        G[:, :, 0] = Dxy[:, :, 0] * iz[:, None]
        G[:, :, 1] = Dxy[:, :, 1] * iz[:, None]
        G[:, :, 2] = -(Dxy[:, :, 0] * xy[:, 0, None] + Dxy[:, :, 1] * xy[:, 1, None]) * iz[:, None]
        J_cam = np.empty((len(iz), 2, 6))
        J_cam[:, :, 0:3] = _mm(G, dP_dr)
        J_cam[:, :, 3:6] = G
        J_sh = np.stack([d[:, None] * xy, (f * r2)[:, None] * xy], axis=2)
        return proj, J_cam, _mm(G, Rk), J_sh


# ---------------------------------------------------------------------------------------------
# Residuals and the sparse Jacobian
# ---------------------------------------------------------------------------------------------


def _check_problem(model, cameras, points, cam_idx, pt_idx, obs=None):
    n = model.n_params
    cameras = np.asarray(cameras, float)
    points = np.asarray(points, float)
    if cameras.ndim != 2 or cameras.shape[1] != n:
        raise KitInputError(f"cameras has shape {cameras.shape}: expected (M, {n}) for {type(model).__name__} {model.param_names}")
    if points.ndim != 2 or points.shape[1] != 3:
        raise KitInputError(f"points has shape {points.shape}: expected (N, 3), points as rows")
    cam_idx = np.asarray(cam_idx)
    pt_idx = np.asarray(pt_idx)
    if cam_idx.ndim != 1 or pt_idx.shape != cam_idx.shape:
        raise KitInputError(f"cam_idx {cam_idx.shape} and pt_idx {pt_idx.shape} must be 1-D and of the same length (one per observation)")
    if len(cam_idx) == 0:
        raise KitInputError("there are no observations: nothing to adjust")
    if not (np.issubdtype(cam_idx.dtype, np.integer) and np.issubdtype(pt_idx.dtype, np.integer)):
        raise KitInputError("cam_idx and pt_idx must be integer arrays")
    if cam_idx.min() < 0 or cam_idx.max() >= len(cameras):
        raise KitInputError(f"cam_idx has values outside 0..{len(cameras) - 1}")
    if pt_idx.min() < 0 or pt_idx.max() >= len(points):
        raise KitInputError(f"pt_idx has values outside 0..{len(points) - 1}")
    if not np.isfinite(cameras).all():
        raise KitInputError("cameras contains NaN or inf")
    if not np.isfinite(points[pt_idx]).all():
        raise KitInputError("an observed point has NaN or inf coordinates: triangulate it or drop its observations")
    out = [cameras, points, cam_idx.astype(np.int64), pt_idx.astype(np.int64)]
    if obs is not None:
        obs = np.asarray(obs, float)
        if obs.shape != (len(cam_idx), 2):
            raise KitInputError(f"obs has shape {obs.shape}: expected ({len(cam_idx)}, 2), one pixel per observation")
        if not np.isfinite(obs).all():
            raise KitInputError("obs contains NaN or inf: list only the observations that exist")
        out.append(obs)
    return out


def residuals(model: CameraModel, cameras, points, cam_idx, pt_idx, obs) -> np.ndarray:
    """Reprojection residuals ``project - observed``.

    Args:
        model: a :class:`CameraModel` (:class:`PinholeCamera` or :class:`BALCamera`).
        cameras: ``(M, n)`` camera parameters. points: ``(N, 3)``.
        cam_idx, pt_idx: ``(K,)`` int. obs: ``(K, 2)`` observed pixels.

    Returns:
        ``(K, 2)`` residuals in pixels (``0.5 * sum(r**2)`` is the cost).
    """
    cameras, points, cam_idx, pt_idx, obs = _check_problem(model, cameras, points, cam_idx, pt_idx, obs)
    return model.project(cameras, points[pt_idx], cam_idx) - obs


def jacobian(model: CameraModel, cameras, points, cam_idx, pt_idx) -> sp.csr_matrix:
    """The analytic Jacobian of :func:`residuals` (flattened row-major) as a sparse matrix.

    Args:
        model, cameras, points, cam_idx, pt_idx: as in :func:`residuals`.

    Returns:
        ``(2K, nM + 3N)`` ``csr_matrix``; columns ``[c_0, ..., c_{M-1}, X_0, ..., X_{N-1}]`` (the
        SciPy cookbook's layout), rows ``2k, 2k+1`` the two coordinates of observation ``k``.
    """
    cameras, points, cam_idx, pt_idx = _check_problem(model, cameras, points, cam_idx, pt_idx)
    _, A, B = model.project_jacobian(cameras, points[pt_idx], cam_idx)
    M, n = cameras.shape
    cols = np.hstack([n * cam_idx[:, None] + np.arange(n), n * M + 3 * pt_idx[:, None] + np.arange(3)])
    cols = np.repeat(cols, 2, axis=0)
    data = np.concatenate([A, B], axis=2).reshape(-1, n + 3)
    indptr = np.arange(0, cols.size + 1, n + 3)
    return sp.csr_matrix((data.ravel(), cols.ravel(), indptr), shape=(2 * len(cam_idx), n * M + 3 * len(points)))


def reduced_camera_sparsity(n_cameras: int, n_params: int, cam_idx, pt_idx) -> sp.csr_matrix:
    """Sparsity of the reduced camera system ``S``: block (i, l) is non-zero when i and l share a point.

    Returns:
        ``(n M, n M)`` sparse 0/1 matrix.
    """
    cam_idx = np.asarray(cam_idx, np.int64)
    pt_idx = np.asarray(pt_idx, np.int64)
    vis = sp.csr_matrix((np.ones(len(cam_idx)), (cam_idx, pt_idx)), shape=(n_cameras, int(pt_idx.max()) + 1))
    C = (vis @ vis.T).tocoo()
    C.data[:] = 1.0
    return sp.csr_matrix(sp.kron(C, np.ones((n_params, n_params))))


# ---------------------------------------------------------------------------------------------
# Normal equations and the Schur complement
# ---------------------------------------------------------------------------------------------


class _Structure:
    """Index bookkeeping that depends only on which camera sees which point (built once).

    The observations must be sorted by camera (:func:`solve` sorts them), so that the rows of
    camera ``i`` are the slice ``cam_start[i]:cam_start[i + 1]``.
    """

    def __init__(self, n_cameras: int, n_points: int, n: int, cam_idx: np.ndarray, pt_idx: np.ndarray):
        if np.any(np.diff(cam_idx) < 0):
            raise ValueError("_Structure needs the observations sorted by camera")
        self.M, self.N, self.n = n_cameras, n_points, n
        K = len(cam_idx)
        self.cam_idx, self.pt_idx = cam_idx, pt_idx
        self.cam_start = np.searchsorted(cam_idx, np.arange(n_cameras + 1))
        self.to_pt = sp.csr_matrix((np.ones(K), (pt_idx, np.arange(K))), shape=(n_points, K))
        self.to_cam = sp.csr_matrix((np.ones(K), (cam_idx, np.arange(K))), shape=(n_cameras, K))
        self.seen = np.zeros(n_points, bool)
        self.seen[pt_idx] = True
        # Pairs (k, l) of observations of the same point with camera(k) <= camera(l): the terms of
        # W V^-1 W^T (its upper block triangle), grouped by camera pair (i, l).
        order = np.argsort(pt_idx, kind="stable")
        counts = np.bincount(pt_idx, minlength=n_points)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        nk = counts[pt_idx]
        pk = np.repeat(np.arange(K), nk)
        offs = np.arange(pk.size) - np.repeat(np.cumsum(nk) - nk, nk)
        pl = order[np.repeat(starts[pt_idx], nk) + offs]
        keep = cam_idx[pk] < cam_idx[pl]  # the diagonal blocks (k == l) are summed camera by camera
        pk, pl = pk[keep], pl[keep]
        cp = cam_idx[pk] * n_cameras + cam_idx[pl]
        o = np.argsort(cp, kind="stable")
        self.pair_k, self.pair_l = pk[o], pl[o]
        self.block_ids, first = np.unique(cp[o], return_index=True)
        self.block_bounds = np.append(first, len(o))
        self.n_pairs = len(o) + K

    def reduced_blocks(self, Yt: np.ndarray, Wt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The blocks of ``W V^-1 W^T``: ``(diag (M, n, n), off (n_blocks, n, n))``.

        ``diag[i] = sum_{k in i} W_k V_j^-1 W_k^T`` and ``off[q]`` the same sum over the points
        that cameras ``i < l`` (``divmod(block_ids[q], M)``) share. ``Yt (K, 3, n)`` holds
        ``V_j^-1 W_k^T`` and ``Wt (K, 3, n)`` holds ``W_k^T``; each block is ONE matrix product
        over all the points of the camera or camera pair.
        """
        n = self.n
        diag = np.empty((self.M, n, n))
        Yf, Wf = Yt.reshape(-1, n), Wt.reshape(-1, n)
        c = 3 * self.cam_start
        for i in range(self.M):  # observations of camera i are contiguous: no gather
            np.matmul(Yf[c[i] : c[i + 1]].T, Wf[c[i] : c[i + 1]], out=diag[i])
        Yg = Yt[self.pair_k].reshape(-1, n)  # (3 P, n)
        Wg = Wt[self.pair_l].reshape(-1, n)
        off = np.empty((len(self.block_ids), n, n))
        b = 3 * self.block_bounds
        for q in range(len(self.block_ids)):
            np.matmul(Yg[b[q] : b[q + 1]].T, Wg[b[q] : b[q + 1]], out=off[q])
        return diag, off


def _outer2(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """``P_k^T Q_k`` for blocks ``P (K, 2, a)``, ``Q (K, 2, b)`` -> ``(K, a, b)``."""
    return np.matmul(np.swapaxes(P, 1, 2), Q)


@dataclass
class NormalEquations:
    """The blocks of ``J^T W J`` and ``J^T W r`` (weights from the robust loss).

    Attributes:
        U: ``(M, n, n)`` camera blocks. V: ``(N, 3, 3)`` point blocks. Wt: ``(K, 3, n)`` the
        off-diagonal block of each observation, transposed (``B_k^T w A_k``). g_c: ``(M, n)``.
        g_p: ``(N, 3)``. U_ss, U_cs, Z, g_s: the blocks of the shared parameters (or None).
    """

    U: np.ndarray
    V: np.ndarray
    Wt: np.ndarray
    g_c: np.ndarray
    g_p: np.ndarray
    #: With shared parameters (``p`` of them, :class:`SimpleRadialCamera`): ``U_ss (p, p)``,
    #: ``U_cs (M, n, p)``, ``Z (N, p, 3)`` (point blocks, ``C^T w B`` summed), ``g_s (p,)``; else None.
    U_ss: np.ndarray | None = None
    U_cs: np.ndarray | None = None
    Z: np.ndarray | None = None
    g_s: np.ndarray | None = None


def normal_equations(structure: _Structure, r: np.ndarray, A: np.ndarray, B: np.ndarray, w: np.ndarray,
                     C: np.ndarray | None = None) -> NormalEquations:
    """Accumulate the blocks of the normal equations from the per-observation Jacobian blocks.

    Args:
        structure: bookkeeping of the (camera-sorted) observations.
        r: ``(K, 2)`` residuals. A: ``(K, 2, n)``, B: ``(K, 2, 3)`` Jacobian blocks. w: ``(K,)`` weights.
        C: ``(K, 2, p)`` Jacobian blocks of the parameters shared by all cameras, or None.
    """
    st = structure
    n = A.shape[2]
    Aw = A * w[:, None, None]
    Bw = B * w[:, None, None]
    U = np.empty((st.M, n, n))
    g_c = np.empty((st.M, n))
    p = 0 if C is None else C.shape[2]
    U_cs = None if C is None else np.empty((st.M, n, p))
    for i in range(st.M):  # one matrix product per camera over all its observations
        s, e = st.cam_start[i], st.cam_start[i + 1]
        Ai = A[s:e].reshape(-1, n)
        Awi = Aw[s:e].reshape(-1, n)
        U[i] = Awi.T @ Ai
        g_c[i] = Awi.T @ r[s:e].ravel()
        if C is not None:
            U_cs[i] = Awi.T @ C[s:e].reshape(-1, p)
    V = (st.to_pt @ _outer2(Bw, B).reshape(len(B), 9)).reshape(st.N, 3, 3)
    Wt = _outer2(Bw, A)
    g_p = st.to_pt @ (Bw[:, 0] * r[:, :1] + Bw[:, 1] * r[:, 1:])
    if C is None:
        return NormalEquations(U, V, Wt, g_c, g_p)
    Cw = C * w[:, None, None]
    U_ss = np.einsum("kai,kaj->ij", Cw, C)
    Z = (st.to_pt @ _outer2(Cw, B).reshape(len(B), 3 * p)).reshape(st.N, p, 3)
    g_s = np.einsum("kai,ka->i", Cw, r)
    return NormalEquations(U, V, Wt, g_c, g_p, U_ss, U_cs, Z, g_s)


def _damping(D: np.ndarray) -> np.ndarray:
    return np.clip(D, 1e-6, 1e32)


def schur_solve(structure: _Structure, ne: NormalEquations, lam: float, free_cam: np.ndarray, dense_limit: int = 4000,
                free_shared: np.ndarray | None = None):
    """Solve the damped normal equations by eliminating the points (Schur complement).

    Args:
        structure: the problem's index bookkeeping.
        ne: :class:`NormalEquations`.
        lam: damping; the system is ``(J^T J + lam D) delta = -J^T r``, ``D = diag(J^T J)`` clamped.
        free_cam: ``(M, n)`` bool, False for camera parameters held fixed (gauge).
        dense_limit: up to this many camera unknowns the reduced system is solved densely.
        free_shared: ``(p,)`` bool, False for shared parameters held fixed (with ``ne.U_ss``).

    Returns:
        ``(dc (M, n), dp (N, 3), ds (p,) or None, predicted_decrease)``. The shared parameters
        border the reduced camera system: ``[[S, S_cs], [S_csᵀ, S_ss]]`` with
        ``S_cs = U_cs - W V^-1 Zᵀ`` and ``S_ss = U_ss + lam D_s - Z V^-1 Zᵀ``.
    """
    st = structure
    M, n = st.M, st.n
    pt = st.pt_idx
    shared = ne.U_ss is not None
    Vdiag = _damping(np.einsum("jii->ji", ne.V))
    Vd = ne.V + lam * Vdiag[:, :, None] * np.eye(3)
    Vd[~st.seen] = np.eye(3)  # points without observations do not move
    try:
        Vinv = np.linalg.inv(Vd)
    except np.linalg.LinAlgError:  # a point seen once is free along its ray when lam is tiny
        Vinv = np.linalg.pinv(Vd)
    Yt = _mm(Vinv[pt], ne.Wt)  # (K, 3, n): V_j^-1 W_k^T
    diag, blocks = st.reduced_blocks(Yt, ne.Wt)
    Udiag = _damping(np.einsum("kii->ki", ne.U))
    q = np.einsum("jab,jb->ja", Vinv, ne.g_p)  # V^-1 g_X
    rhs = -(ne.g_c - st.to_cam @ np.einsum("kab,ka->kb", ne.Wt, q[pt])).ravel()
    fixed = ~free_cam.ravel()
    if shared:
        p_sh = len(ne.g_s)
        ZV = np.einsum("jab,jbc->jac", ne.Z, Vinv)  # (N, p, 3): Z_j V_j^-1
        Sdiag = _damping(np.diag(ne.U_ss).copy())
        S_ss = ne.U_ss + lam * np.diag(Sdiag) - np.einsum("jac,jdc->ad", ZV, ne.Z)
        S_cs = ne.U_cs - (st.to_cam @ np.einsum("kan,kpa->knp", Yt, ne.Z[pt]).reshape(len(pt), n * p_sh)).reshape(M, n, p_sh)
        rhs = np.concatenate([rhs, -(ne.g_s - np.einsum("jab,jb->a", ZV, ne.g_p))])
        fixed = np.concatenate([fixed, ~np.asarray(free_shared, bool) if free_shared is not None else np.zeros(p_sh, bool)])
    rhs[fixed] = 0.0
    bi, bl = np.divmod(st.block_ids, M)
    nS = n * M + (p_sh if shared else 0)
    if n * M <= dense_limit:
        S = np.zeros((M, M, n, n))
        S[bi, bl] = -blocks
        S[bl, bi] = -np.transpose(blocks, (0, 2, 1))
        S[np.arange(M), np.arange(M)] = ne.U + lam * Udiag[:, :, None] * np.eye(n) - diag
        S = S.transpose(0, 2, 1, 3).reshape(n * M, n * M)
        if shared:
            S = np.block([[S, S_cs.reshape(n * M, p_sh)], [S_cs.reshape(n * M, p_sh).T, S_ss]])
        S[fixed, :] = 0.0
        S[:, fixed] = 0.0
        S[fixed, fixed] = 1.0
        try:
            delta = scipy.linalg.cho_solve(scipy.linalg.cho_factor(S, check_finite=False), rhs, check_finite=False)
        except np.linalg.LinAlgError:
            delta = np.linalg.lstsq(S, rhs, rcond=None)[0]
    else:
        data = np.concatenate([-blocks, -np.transpose(blocks, (0, 2, 1)), ne.U + lam * Udiag[:, :, None] * np.eye(n) - diag])
        rows = np.concatenate([bi, bl, np.arange(M)])
        cols = np.concatenate([bl, bi, np.arange(M)])
        order = np.lexsort((cols, rows))
        indptr = np.searchsorted(rows[order], np.arange(M + 1))
        S = sp.bsr_matrix((data[order], cols[order], indptr), shape=(n * M, n * M)).tocsr()
        if shared:
            Scs = sp.csr_matrix(S_cs.reshape(n * M, p_sh))
            S = sp.bmat([[S, Scs], [Scs.T, sp.csr_matrix(S_ss)]]).tocsr()
        keep = sp.diags((~fixed).astype(float))
        S = (keep @ S @ keep + sp.diags(fixed.astype(float))).tocsc()
        delta = scipy.sparse.linalg.spsolve(S, rhs)
    dc = delta[: n * M].reshape(M, n)
    ds = delta[n * M: nS] if shared else None
    tmp = ne.g_p + st.to_pt @ np.einsum("kab,kb->ka", ne.Wt, dc[st.cam_idx])
    if shared:
        tmp = tmp + np.einsum("jpa,p->ja", ne.Z, ds)
    dp = -np.einsum("jab,jb->ja", Vinv, tmp)
    # predicted decrease of the quadratic model: 0.5 * delta^T (lam D delta - g)
    pred = 0.5 * (
        float(np.sum(dc * (lam * Udiag * dc - ne.g_c))) + float(np.sum(dp * (lam * Vdiag * dp - ne.g_p)))
    )
    if shared:
        pred += 0.5 * float(np.sum(ds * (lam * Sdiag * ds - ne.g_s)))
    return dc, dp, ds, pred


# ---------------------------------------------------------------------------------------------
# Robust loss
# ---------------------------------------------------------------------------------------------


def _robust(loss: str, s: np.ndarray, f_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """``(rho, weight)`` for squared residual norms ``s``: cost ``0.5 * sum(rho)``, IRLS weight ``rho'``.

    ``rho(s) = f^2 rho0(s / f^2)`` as in :func:`scipy.optimize.least_squares`.
    """
    if loss == "linear":
        return s, np.ones_like(s)
    z = s / f_scale**2
    if loss == "huber":
        big = z > 1.0
        rho0 = np.where(big, 2.0 * np.sqrt(z) - 1.0, z)
        w = np.where(big, 1.0 / np.sqrt(np.maximum(z, 1.0)), 1.0)
    elif loss == "soft_l1":
        rho0 = 2.0 * (np.sqrt(1.0 + z) - 1.0)
        w = 1.0 / np.sqrt(1.0 + z)
    elif loss == "cauchy":
        rho0 = np.log1p(z)
        w = 1.0 / (1.0 + z)
    else:
        raise KitInputError(f"loss={loss!r}: expected 'linear', 'huber', 'soft_l1' or 'cauchy'")
    return f_scale**2 * rho0, w


# ---------------------------------------------------------------------------------------------
# The solver
# ---------------------------------------------------------------------------------------------


@dataclass
class LMResult:
    """What :func:`solve` returns.

    Attributes:
        cameras: ``(M, n)`` refined camera parameters. points: ``(N, 3)`` refined points
            (points without observations unchanged).
        initial_cost, final_cost: ``0.5 * sum(|r|^2)`` over all observations (pixels^2), without
            the robust loss, so runs with and without it compare.
        cost_history: that cost at the start and after every accepted step.
        iterations: accepted steps. n_solves: linear systems solved (accepted + rejected steps).
        seconds: wall-clock time of :func:`solve`.
        success, message: why it stopped.
        shared: ``(p,)`` refined shared parameters (a model with ``n_shared``), else None.
    """

    cameras: np.ndarray
    points: np.ndarray
    initial_cost: float
    final_cost: float
    cost_history: list[float] = field(default_factory=list)
    iterations: int = 0
    n_solves: int = 0
    seconds: float = 0.0
    success: bool = True
    message: str = ""
    shared: np.ndarray | None = None


def solve(
    model: CameraModel,
    cameras: np.ndarray,
    points: np.ndarray,
    cam_idx: np.ndarray,
    pt_idx: np.ndarray,
    obs: np.ndarray,
    *,
    fixed_cameras: np.ndarray | None = None,
    loss: str = "linear",
    f_scale: float = 1.0,
    max_iterations: int = 100,
    ftol: float = 1e-6,
    xtol: float = 1e-10,
    gtol: float = 1e-10,
    lam0: float = 1e-4,
    dense_limit: int = 4000,
    callback: Callable[[int, np.ndarray, np.ndarray, float], None] | None = None,
    shared: np.ndarray | None = None,
    fixed_shared: np.ndarray | None = None,
) -> LMResult:
    """Bundle adjustment by sparse Levenberg-Marquardt with the Schur complement on the points.

    Args:
        model: camera model (:class:`PinholeCamera`, :class:`BALCamera`, or your own with
            ``n_params``, ``project`` and ``project_jacobian``).
        cameras: ``(M, n)`` initial camera parameters.
        points: ``(N, 3)`` initial points (rows without observations may be NaN).
        cam_idx, pt_idx: ``(K,)`` int, camera and point of each observation.
        obs: ``(K, 2)`` observed pixels.
        fixed_cameras: ``(M, n)`` bool, True for parameters held fixed (the gauge); default none.
        loss: ``"linear"`` or a robust loss (``"huber"``, ``"soft_l1"``, ``"cauchy"``, as in
            ``least_squares``), applied by reweighting (IRLS).
        f_scale: pixels where the robust loss starts to flatten.
        max_iterations: at most this many accepted steps.
        ftol: stop when an accepted step lowers the cost by less than ``ftol * cost`` (Ceres'
            ``function_tolerance``; ``1e-4`` is enough for the BAL benchmark).
        xtol: stop when ``|step| < xtol * (xtol + |params|)``.
        gtol: stop when the largest gradient entry is below ``gtol``.
        lam0: initial damping (Ceres: 1 / initial trust region radius 1e4).
        dense_limit: size of the reduced camera system up to which it is solved densely.
        callback: ``callback(iteration, cameras, points, cost)`` at the start and after each
            accepted step (cost without the robust loss).
        shared: ``(p,)`` initial parameters shared by all cameras, for a model with ``n_shared = p``
            (:class:`SimpleRadialCamera`: the focal length and ``k1``); they border the reduced
            camera system (:func:`schur_solve`).
        fixed_shared: ``(p,)`` bool, True for shared parameters held fixed; default none.

    Returns:
        :class:`LMResult`.

    Raises:
        KitInputError: shapes or indices do not fit together, or an observed point projects to
            infinity at the start.

    Introduced in ``notebooks/05_bundle_adjustment.ipynb`` ("How does this scale?").
    """
    with single_threaded_blas():
        return _lm(
            model, cameras, points, cam_idx, pt_idx, obs, fixed_cameras, loss, f_scale,
            max_iterations, ftol, xtol, gtol, lam0, dense_limit, callback, shared, fixed_shared,
        )


def _lm(model, cameras, points, cam_idx, pt_idx, obs, fixed_cameras, loss, f_scale,
        max_iterations, ftol, xtol, gtol, lam0, dense_limit, callback, shared=None, fixed_shared=None):
    """The body of :func:`solve`."""
    t_start = time.perf_counter()
    cameras, points, cam_idx, pt_idx, obs = _check_problem(model, cameras, points, cam_idx, pt_idx, obs)
    if loss not in ("linear", "huber", "soft_l1", "cauchy"):
        raise KitInputError(f"loss={loss!r}: expected 'linear', 'huber', 'soft_l1' or 'cauchy'")
    M, n = cameras.shape
    N = len(points)
    free_cam = np.ones((M, n), bool) if fixed_cameras is None else ~np.asarray(fixed_cameras, bool)
    if free_cam.shape != (M, n):
        raise KitInputError(f"fixed_cameras has shape {free_cam.shape}: expected ({M}, {n})")
    seen = np.zeros(N, bool)
    seen[pt_idx] = True
    order = np.argsort(cam_idx, kind="stable")  # observations camera by camera (see _Structure)
    cam_idx, pt_idx, obs = cam_idx[order], pt_idx[order], obs[order]
    st = _Structure(M, N, n, cam_idx, pt_idx)
    cams = cameras.copy()
    pts = np.where(seen[:, None], points, 0.0)
    free_obs = free_cam[cam_idx].astype(float)  # (K, n): zero the columns of fixed camera parameters
    n_sh = int(getattr(model, "n_shared", 0))
    if n_sh:
        if shared is None or np.shape(shared) != (n_sh,) or not np.isfinite(shared).all():
            raise KitInputError(f"shared has shape {np.shape(shared)}: {type(model).__name__} needs its {n_sh} shared "
                                f"parameters {model.shared_names} as finite numbers")
        sh = np.asarray(shared, float).copy()
        free_sh = np.ones(n_sh, bool) if fixed_shared is None else ~np.asarray(fixed_shared, bool).reshape(n_sh)
    else:
        sh, free_sh = None, None

    def project(c, X, shp):
        return model.project(c, X[pt_idx], cam_idx) if shp is None else model.project(c, X[pt_idx], cam_idx, shp)

    def evaluate(c, X, shp=None):
        r = project(c, X, shp) - obs
        s = (r**2).sum(axis=1)
        rho, w = _robust(loss, s, f_scale)
        return r, w, 0.5 * float(rho.sum()), 0.5 * float(s.sum())

    r, w, cost, plain = evaluate(cams, pts, sh)
    if not np.isfinite(cost):
        raise KitInputError("some observed points project to infinity at the start (depth 0): check the initial cameras and points")
    history = [plain]
    initial_cost = plain
    if callback is not None:
        callback(0, cams.copy(), np.where(seen[:, None], pts, points), plain)
    lam, nu = lam0, 2.0
    n_iter = n_solves = 0
    success, message = False, "the maximum number of iterations is reached"
    while n_iter < max_iterations:
        if sh is None:
            _, A, B = model.project_jacobian(cams, pts[pt_idx], cam_idx)
            C = None
        else:
            _, A, B, C = model.project_jacobian(cams, pts[pt_idx], cam_idx, sh)
            C = C * free_sh[None, None, :]
        A = A * free_obs[:, None, :]
        ne = normal_equations(st, r, A, B, w, C)
        gmax = max(np.abs(ne.g_c).max(initial=0.0), np.abs(ne.g_p[seen]).max(initial=0.0),
                   0.0 if C is None else np.abs(ne.g_s).max(initial=0.0))
        if gmax < gtol:
            success, message = True, "the gradient is below gtol"
            break
        accepted = False
        while not accepted:
            n_solves += 1
            dc, dp, ds, pred = schur_solve(st, ne, lam, free_cam, dense_limit, free_sh)
            dp[~seen] = 0.0
            c_new, p_new = cams + dc, pts + dp
            sh_new = None if sh is None else sh + ds
            r_new, w_new, cost_new, plain_new = evaluate(c_new, p_new, sh_new)
            rho = (cost - cost_new) / pred if pred > 0 else -1.0
            if np.isfinite(cost_new) and rho > 1e-3:
                accepted = True
                step_norm = np.sqrt(np.sum(dc**2) + np.sum(dp**2))
                x_norm = np.sqrt(np.sum(cams**2) + np.sum(pts**2))
                rel = (cost - cost_new) / max(cost, 1e-300)
                cams, pts, r, w, cost, plain, sh = c_new, p_new, r_new, w_new, cost_new, plain_new, sh_new
                lam = max(lam * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), LAM_MIN)
                nu = 2.0
                n_iter += 1
                history.append(plain)
                if callback is not None:
                    callback(n_iter, cams.copy(), np.where(seen[:, None], pts, points), plain)
                if rel < ftol:
                    success, message = True, f"the relative decrease of the cost is below ftol={ftol:g}"
                elif step_norm < xtol * (xtol + x_norm):
                    success, message = True, f"the step is below xtol={xtol:g}"
            else:
                lam *= nu
                nu *= 2.0
                if lam > LAM_MAX:
                    break
        if not accepted:
            success, message = True, "no step decreases the cost (converged to the precision available)"
            break
        if success:
            break
    points_out = np.where(seen[:, None], pts, points)
    return LMResult(
        cameras=cams,
        points=points_out,
        initial_cost=initial_cost,
        final_cost=plain,
        cost_history=history,
        iterations=n_iter,
        n_solves=n_solves,
        seconds=time.perf_counter() - t_start,
        success=success,
        message=message,
        shared=sh,
    )

"""The bundle-adjustment problem: its checks, residuals, sparse Jacobian and robust loss (Ceres' ``Problem``).

Cameras ``c_i`` (``M x n`` parameters), points ``X_j`` (``N x 3``), observations ``k`` of point
``pt_idx[k]`` in camera ``cam_idx[k]`` at ``obs[k]``; residual ``r_k = project(c_i, X_j) - obs_k``;
cost ``0.5 sum_k rho(|r_k|^2)``. The whole method: :mod:`course_lib.sfm.lm`.

Introduced in ``notebooks/05_bundle_adjustment.ipynb`` ("How does this scale?").
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from course_lib.sfm.lm.cameras import CameraModel
from course_lib.validate import KitInputError

__all__ = ["check_problem", "residuals", "jacobian", "reduced_camera_sparsity", "robust_loss"]


def check_problem(model, cameras, points, cam_idx, pt_idx, obs=None):
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
    cameras, points, cam_idx, pt_idx, obs = check_problem(model, cameras, points, cam_idx, pt_idx, obs)
    return model.project(cameras, points[pt_idx], cam_idx) - obs


def jacobian(model: CameraModel, cameras, points, cam_idx, pt_idx) -> sp.csr_matrix:
    """The analytic Jacobian of :func:`residuals` (flattened row-major) as a sparse matrix.

    Args:
        model, cameras, points, cam_idx, pt_idx: as in :func:`residuals`.

    Returns:
        ``(2K, nM + 3N)`` ``csr_matrix``; columns ``[c_0, ..., c_{M-1}, X_0, ..., X_{N-1}]`` (the
        SciPy cookbook's layout), rows ``2k, 2k+1`` the two coordinates of observation ``k``.
    """
    cameras, points, cam_idx, pt_idx = check_problem(model, cameras, points, cam_idx, pt_idx)
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


def robust_loss(loss: str, s: np.ndarray, f_scale: float) -> tuple[np.ndarray, np.ndarray]:
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

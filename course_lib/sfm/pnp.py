"""Perspective-n-Point: the pose of a new camera from 2D-3D correspondences.

Step 4 of the SfM chain (notebook ``04_pnp.ipynb``): once some points are triangulated, a new
image whose features match those points can be registered without any epipolar geometry.

1. :func:`pnp_linear` -- the direct linear transform on *normalized* coordinates
   ``x_n = K⁻¹ x_h``: each correspondence gives two linear equations in the 12 entries of
   ``P = λ [R | t]``; the solution (right singular vector of the smallest singular value) is
   turned into a rotation by an SVD (``R = U Vᵀ``, det +1) and ``t`` is divided by the same
   scale ``λ``. Needs N >= 6 points in general position (not all on one plane).
2. :func:`pnp_ransac` -- the same on random 6-point samples, scored by the reprojection error in
   pixels, with the adaptive number of iterations, then refit on all inliers.
3. :func:`pnp_nonlinear` -- minimize the reprojection error over the six pose parameters
   (rotation vector + translation) with :func:`scipy.optimize.least_squares`.

Poses follow :mod:`course_lib.conventions`: ``x_cam = R_cw X + t_cw``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from course_lib import validate
from course_lib.conventions import project, to_homogeneous, world_to_camera

__all__ = ["pnp_linear", "PnPResult", "pnp_ransac", "pnp_nonlinear", "pnp_reprojection_errors"]

MIN_POINTS = 6


def _inputs(X, x, K, min_count: int, why: str):
    K = validate.intrinsics(K)
    X, x = validate.matching_points(X, x, min_count=0, names=("X", "x"), dims=(3, 2))
    if X.shape[0] < min_count:
        raise validate.KitInputError(
            f"X has {X.shape[0]} rows: {why} needs at least {min_count} 2D-3D correspondences"
        )
    return X, x, K


def _dlt(X: np.ndarray, xn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unchecked linear PnP on normalized image coordinates ``xn (N, 2)``; returns (R_cw, t_cw)."""
    # Condition the 3-D points: centre them and scale to mean distance sqrt(3).
    mu = X.mean(axis=0)
    d = np.sqrt(((X - mu) ** 2).sum(axis=1)).mean()
    s = np.sqrt(3.0) / d if d > 0 else 1.0
    T = np.diag([s, s, s, 1.0])
    T[:3, 3] = -s * mu
    Xh = to_homogeneous((X - mu) * s)  # (N, 4)
    n = X.shape[0]
    A = np.zeros((2 * n, 12))
    u, v = xn[:, :1], xn[:, 1:]
    # u (p3 . X) - p1 . X = 0 ;  v (p3 . X) - p2 . X = 0, unknowns p = [p1, p2, p3] (rows of P)
    A[0::2, 0:4] = -Xh
    A[0::2, 8:12] = u * Xh
    A[1::2, 4:8] = -Xh
    A[1::2, 8:12] = v * Xh
    _, _, Vt = np.linalg.svd(A, full_matrices=False)  # Vt is (12, 12); U (2N, 2N) is never needed
    P = Vt[-1].reshape(3, 4) @ T  # undo the conditioning: P_world = P_normalized @ T
    M = P[:, :3]
    if np.linalg.det(M) < 0:  # P is known up to a scale lambda that may be negative:
        P = -P  # lambda > 0  <=>  det(M) > 0, and then the points are in front (z > 0)
        M = P[:, :3]
    U, S, Vt3 = np.linalg.svd(M)
    R = U @ Vt3  # the closest rotation (det +1 since det M > 0)
    # t = P[:, 3] / mean(S) has the scale of the rotation block, but the scale is a noisy estimate
    # (near-planar scenes make it worse); with R fixed, t solves the linear equations
    # [x_n]x (R X + t) = 0 in the least-squares sense, which is as cheap and much more accurate.
    S_x = _skew_rows(to_homogeneous(xn))  # (N, 3, 3)
    A = S_x.reshape(-1, 3)
    b = -(S_x @ (X @ R.T)[:, :, None]).reshape(-1)
    t = np.linalg.solve(A.T @ A, A.T @ b) if np.linalg.cond(A.T @ A) < 1e12 else P[:, 3] / S.mean()
    return R, t


def _skew_rows(v: np.ndarray) -> np.ndarray:
    """``(N, 3, 3)`` cross-product matrices of the rows of ``v (N, 3)``."""
    S = np.zeros((v.shape[0], 3, 3))
    S[:, 0, 1], S[:, 0, 2] = -v[:, 2], v[:, 1]
    S[:, 1, 0], S[:, 1, 2] = v[:, 2], -v[:, 0]
    S[:, 2, 0], S[:, 2, 1] = -v[:, 1], v[:, 0]
    return S


def pnp_linear(X: np.ndarray, x: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear PnP (DLT) on normalized image coordinates.

    With ``x_n = K⁻¹ [u, v, 1]ᵀ`` and ``P = λ [R | t]`` (3x4, 12 unknowns), each correspondence
    gives ``u_n (p3ᵀ X_h) - p1ᵀ X_h = 0`` and ``v_n (p3ᵀ X_h) - p2ᵀ X_h = 0``. ``P`` is the
    right singular vector of the smallest singular value (the 3-D points are centred and scaled
    first, for conditioning). Its sign is chosen so that ``det P[:, :3] > 0`` (then the points
    lie in front of the camera); ``P[:, :3] = U S Vᵀ`` gives ``R = U Vᵀ``. The translation with
    the same scale would be ``P[:, 3] / mean(S)``; instead, with ``R`` fixed, ``t`` is solved
    from the linear equations ``[x_n]ₓ (R X + t) = 0`` (least squares), which is consistent
    with ``R`` and far less sensitive to noise and to near-planar scenes.

    Args:
        X: ``(N, 3)`` world points, N >= 6, not all on one plane.
        x: ``(N, 2)`` their pixels ``(u, v)`` in the new image.
        K: ``(3, 3)`` intrinsics.

    Returns:
        ``R_cw (3, 3)`` with det +1 and ``t_cw (3,)`` of the new camera.

    Raises:
        KitInputError: fewer than 6 correspondences, NaNs, mismatched counts, singular K,
            coplanar points.

    Introduced in notebooks/04_pnp.ipynb
    """
    X, x, K = _inputs(X, x, K, MIN_POINTS, "linear PnP")
    sv = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    if sv[2] <= 1e-9 * max(sv[0], 1e-300):
        raise validate.KitInputError(
            f"the {X.shape[0]} points of X lie on one plane (or line): the 12-unknown DLT is degenerate for "
            "coplanar points; add points off the plane"
        )
    xn = (to_homogeneous(x) @ np.linalg.inv(K).T)[:, :2]
    return _dlt(X, xn)


def pnp_reprojection_errors(X: np.ndarray, x: np.ndarray, K: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray) -> np.ndarray:
    """Reprojection errors in pixels, ``inf`` for points behind the camera.

    Args:
        X: ``(N, 3)`` world points. x: ``(N, 2)`` pixels. K: ``(3, 3)``. R_cw: ``(3, 3)``. t_cw: ``(3,)``.

    Returns:
        ``(N,)`` distances in pixels.

    Introduced in notebooks/04_pnp.ipynb
    """
    X, x, K = _inputs(X, x, K, 0, "")
    R_cw = validate.rotation(R_cw, "R_cw", atol=1e-5)
    t_cw = validate.vector3(t_cw, "t_cw")
    return _errors(X, x, K, R_cw, t_cw)


def _errors(X, x, K, R, t) -> np.ndarray:
    z = world_to_camera(R, t, X)[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        e = np.linalg.norm(project(K, R, t, X) - x, axis=1)
    e[~(z > 0)] = np.inf
    return e


@dataclass
class PnPResult:
    """The outcome of :func:`pnp_ransac`.

    Attributes:
        R_cw: ``(3, 3)`` rotation of the registered camera.
        t_cw: ``(3,)`` its translation.
        inliers: ``(N,)`` bool, reprojection error below the threshold (and in front).
        n_iters: number of RANSAC iterations run.
    """

    R_cw: np.ndarray
    t_cw: np.ndarray
    inliers: np.ndarray
    n_iters: int


def _local_optimization(X, x, xn, K, best: tuple, threshold_px: float, score) -> tuple:
    """Refit a new best ``(R, t, inliers, key)`` of :func:`pnp_ransac`; the better of it and the refits.

    From 6 noisy points the DLT is poor (it fits 11 parameters), so refit on the points within a
    loose, then tighter threshold of the new best model, and keep the refit whenever it gains inliers.
    """
    for mult in (4.0, 2.0, 1.0, 1.0):
        err = _errors(X, x, K, best[0], best[1])
        near = err < mult * threshold_px
        if near.sum() < 2 * MIN_POINTS:
            continue
        R, t = _dlt(X[near], xn[near])
        inl, key = score(R, t)
        if key > best[3]:
            best = (R, t, inl, key)
    return best


def pnp_ransac(X: np.ndarray, x: np.ndarray, K: np.ndarray, rng: np.random.Generator, threshold_px: float = 2.0,
               confidence: float = 0.999, max_iters: int = 1000) -> PnPResult:
    """Robust PnP: linear PnP on random 6-point samples, scored by reprojection error.

    Each iteration draws 6 distinct correspondences, solves :func:`pnp_linear` and counts the
    points whose reprojection error is below ``threshold_px`` (points behind the camera never
    count). Whenever a sample beats the best model so far, the model is refit on the points
    within 4, 2 and 1 times the threshold (from many points the linear estimate is far less
    noisy than from 6), keeping each refit that gains inliers ("locally optimized" RANSAC). The number of iterations adapts to the best
    inlier ratio ``w`` found so far: ``N = log(1 - confidence) / log(1 - w^6)``.

    Args:
        X: ``(N, 3)`` world points, N >= 6.
        x: ``(N, 2)`` pixels in the new image.
        K: ``(3, 3)`` intrinsics.
        rng: seeded ``numpy.random.Generator``.
        threshold_px: inlier threshold on the reprojection error, pixels.
        confidence: probability of drawing at least one all-inlier sample.
        max_iters: upper bound on the iterations.

    Returns:
        :class:`PnPResult` ``(R_cw, t_cw, inliers (N,) bool, n_iters)``.

    Raises:
        KitInputError: bad input, or no sample gave a pose with 6 or more inliers (the
            correspondences do not match, or K is wrong); a pipeline may catch it and skip the image.

    Introduced in notebooks/04_pnp.ipynb
    """
    X, x, K = _inputs(X, x, K, MIN_POINTS, "PnP RANSAC")
    if not isinstance(rng, np.random.Generator):
        raise validate.KitInputError("rng must be a numpy Generator: pass np.random.default_rng(seed)")
    if not threshold_px > 0:
        raise validate.KitInputError(f"threshold_px={threshold_px}: it must be a positive number of pixels")
    if not 0 < confidence < 1:
        raise validate.KitInputError(f"confidence={confidence}: it must lie strictly between 0 and 1")
    n = X.shape[0]
    xn = (to_homogeneous(x) @ np.linalg.inv(K).T)[:, :2]

    def score(R, t):
        err = _errors(X, x, K, R, t)
        inl = err < threshold_px
        return inl, (int(inl.sum()), -float(np.minimum(err, threshold_px).sum()))  # count, then MSAC tie-break

    best = (None, None, np.zeros(n, dtype=bool), (-1, 0.0))
    needed = max_iters
    it = 0
    while it < min(needed, max_iters):
        it += 1
        sample = rng.choice(n, MIN_POINTS, replace=False)
        R, t = _dlt(X[sample], xn[sample])
        if not np.isfinite(t).all():
            continue
        inl, key = score(R, t)
        if key <= best[3]:
            continue
        best = _local_optimization(X, x, xn, K, (R, t, inl, key), threshold_px, score)
        w = best[3][0] / n
        if w >= 1.0:
            needed = it
        elif w > 0:
            denom = np.log(1.0 - w**MIN_POINTS)
            needed = int(np.ceil(np.log(1.0 - confidence) / denom)) if denom < 0 else max_iters
    R, t, inl, key = best
    if key[0] < MIN_POINTS:
        raise validate.KitInputError(
            f"PnP RANSAC found no pose with {MIN_POINTS} or more inliers within {threshold_px} px "
            f"after {it} iterations: check that X and x correspond (same rows) and that K is right"
        )
    return PnPResult(R, t, inl, it)


def pnp_nonlinear(
    X: np.ndarray, x: np.ndarray, K: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Refine a camera pose by minimizing the reprojection error.

    The pose is parametrized by a rotation vector ``ω`` (axis times angle, ``R = exp([ω]×)``,
    via :class:`scipy.spatial.transform.Rotation`) and ``t``; the six parameters minimize
    ``Σ_j ||π(K, R(ω), t, X_j) - x_j||²`` with :func:`scipy.optimize.least_squares`, starting
    from ``(R_cw, t_cw)`` (e.g. the result of :func:`pnp_ransac`). Pass inliers only.

    Args:
        X: ``(N, 3)`` world points, N >= 3.
        x: ``(N, 2)`` their pixels.
        K: ``(3, 3)`` intrinsics.
        R_cw: ``(3, 3)`` initial rotation (det +1).
        t_cw: ``(3,)`` initial translation.

    Returns:
        Refined ``R_cw (3, 3)`` and ``t_cw (3,)``.

    Introduced in notebooks/04_pnp.ipynb
    """
    X, x, K = _inputs(X, x, K, 3, "non-linear PnP")
    R_cw = validate.rotation(R_cw, "R_cw", atol=1e-5)
    t_cw = validate.vector3(t_cw, "t_cw")
    # imported here, as in triangulation.triangulate_nonlinear: a tenth of a second that PnP RANSAC never needs
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    p0 = np.concatenate([Rotation.from_matrix(R_cw).as_rotvec(), t_cw])

    def residuals(p):
        R = Rotation.from_rotvec(p[:3]).as_matrix()
        return (project(K, R, p[3:], X) - x).ravel()

    sol = least_squares(residuals, p0, method="trf", x_scale="jac", xtol=1e-12, ftol=1e-12, max_nfev=200)
    p = sol.x
    return Rotation.from_rotvec(p[:3]).as_matrix(), p[3:].copy()

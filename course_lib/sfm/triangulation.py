"""Triangulation: from two (or more) calibrated views and matched pixels to 3-D points.

Step 3 of the SfM chain (notebook ``03_triangulation.ipynb``):

1. :func:`triangulate_linear` -- the direct linear transform (DLT) per point: each view gives two
   linear equations in the homogeneous point ``X_h`` (``u p3ᵀX_h - p1ᵀX_h = 0`` and
   ``v p3ᵀX_h - p2ᵀX_h = 0``, with ``p_kᵀ`` the rows of ``P``); the solution is the right singular
   vector of the smallest singular value, divided by its last coordinate. All points are solved
   at once with a batched SVD.
2. :func:`choose_pose` -- of the four ``(R, C)`` candidates of an essential matrix, keep the one
   that puts the most triangulated points in front of both cameras (cheirality:
   ``z > 0`` in camera 1 and ``r3ᵀ(X - C) > 0`` in camera 2).
3. :func:`triangulate_nonlinear` -- refine the points by minimizing the reprojection error over
   every view that sees them, with :func:`scipy.optimize.least_squares` and a sparse analytic
   Jacobian (each point only moves its own residuals, so the Jacobian is block-diagonal).

Conventions (see :mod:`course_lib.conventions`): poses are ``R_cw, t_cw`` with
``x_cam = R_cw X + t_cw``; in the two-view case camera 1 is ``R = I, t = 0``; points are rows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from course_lib import validate
from course_lib.conventions import project, translation_from_center

__all__ = [
    "triangulate_linear",
    "PoseChoice",
    "choose_pose",
    "in_front_of_both",
    "reprojection_errors",
    "triangulate_nonlinear",
]


def _projection(P, name: str) -> np.ndarray:
    try:
        P = np.asarray(P, dtype=float)
    except (TypeError, ValueError):
        raise validate.KitInputError(f"{name} must be a numeric (3, 4) projection matrix K [R | t]") from None
    if P.shape != (3, 4):
        hint = " (did you pass K or R instead of P = K [R | t]?)" if P.shape == (3, 3) else ""
        raise validate.KitInputError(f"{name} has shape {P.shape}: expected the (3, 4) projection matrix{hint}")
    if not np.isfinite(P).all():
        raise validate.KitInputError(f"{name} contains NaN or inf")
    if np.linalg.matrix_rank(P[:, :3]) < 3:
        raise validate.KitInputError(f"{name}[:, :3] is singular: a projection matrix K [R | t] has an invertible left 3x3 block")
    return P


def triangulate_linear(P1: np.ndarray, P2: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation of matched pixels seen by two cameras.

    For each correspondence the 4x4 system ``A X_h = 0`` stacks, for each camera with rows
    ``p1ᵀ, p2ᵀ, p3ᵀ`` and pixel ``(u, v)``, the equations ``u p3ᵀ - p1ᵀ`` and ``v p3ᵀ - p2ᵀ``.
    Each row is scaled to unit norm (better conditioning; the solution is unchanged), the
    solution is the last right singular vector of ``A``, and the point is ``X_h[:3] / X_h[3]``.
    All N systems are solved at once with a batched SVD.

    Args:
        P1: ``(3, 4)`` projection matrix ``K [R_cw | t_cw]`` of camera 1.
        P2: ``(3, 4)`` projection matrix of camera 2.
        x1: ``(N, 2)`` pixels ``(u, v)`` in image 1.
        x2: ``(N, 2)`` matching pixels in image 2 (row k of both is one correspondence).

    Returns:
        ``(N, 3)`` world points, rows; ``inf`` or very large for points at infinity.

    Raises:
        KitInputError: wrong shapes, NaNs, mismatched counts, or a singular ``P``.

    Introduced in notebooks/03_triangulation.ipynb
    """
    P1 = _projection(P1, "P1")
    P2 = _projection(P2, "P2")
    x1, x2 = validate.matching_points(x1, x2, min_count=1, why="triangulation")
    A = np.stack(
        [
            x1[:, :1] * P1[2] - P1[0],
            x1[:, 1:] * P1[2] - P1[1],
            x2[:, :1] * P2[2] - P2[0],
            x2[:, 1:] * P2[2] - P2[1],
        ],
        axis=1,
    )  # (N, 4, 4): one 4x4 system per point
    A /= np.linalg.norm(A, axis=2, keepdims=True)
    _, _, Vt = np.linalg.svd(A)
    Xh = Vt[:, -1, :]  # (N, 4): right singular vector of the smallest singular value
    with np.errstate(divide="ignore", invalid="ignore"):
        return Xh[:, :3] / Xh[:, 3:]


@dataclass
class PoseChoice:
    """The pose of camera 2 picked by the cheirality test, with its triangulated points.

    Attributes:
        R_cw: ``(3, 3)`` rotation of camera 2 (camera 1 is ``R = I, t = 0``).
        t_cw: ``(3,)`` translation of camera 2, ``t_cw = -R_cw @ C`` (unit norm, like ``C``).
        X: ``(N, 3)`` points triangulated with the chosen pose.
        in_front: ``(N,)`` bool, True where the point is in front of both cameras.
        counts: ``(4,)`` int, number of points in front of both cameras for each candidate.
        index: which candidate (0..3) was chosen.
    """

    R_cw: np.ndarray
    t_cw: np.ndarray
    X: np.ndarray
    in_front: np.ndarray
    counts: np.ndarray
    index: int = 0


def _candidates(R, C) -> tuple[np.ndarray, np.ndarray]:
    R = np.asarray(R, dtype=float)
    C = np.asarray(C, dtype=float)
    if R.shape != (4, 3, 3):
        raise validate.KitInputError(f"R has shape {R.shape}: expected the (4, 3, 3) rotations of the four pose candidates")
    if C.shape != (4, 3):
        raise validate.KitInputError(f"C has shape {C.shape}: expected the (4, 3) camera centres of the four pose candidates")
    for k in range(4):
        validate.rotation(R[k], f"R[{k}]", atol=1e-5)
    if not np.isfinite(C).all():
        raise validate.KitInputError("C contains NaN or inf")
    return R, C


def in_front_of_both(R_cw: np.ndarray, C: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Cheirality test for the two-view case: ``z > 0`` in camera 1 and ``r3ᵀ(X - C) > 0`` in camera 2.

    Args:
        R_cw: ``(3, 3)`` rotation of camera 2. C: ``(3,)`` its centre. X: ``(N, 3)`` points.

    Returns:
        ``(N,)`` bool.

    Introduced in notebooks/03_triangulation.ipynb
    """
    X = np.asarray(X, float)
    with np.errstate(invalid="ignore"):
        return (X[:, 2] > 0) & ((X - np.asarray(C, float).reshape(1, 3)) @ np.asarray(R_cw, float)[2] > 0)


def choose_pose(R: np.ndarray, C: np.ndarray, K: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> PoseChoice:
    """Disambiguate the four pose candidates of an essential matrix by cheirality.

    Camera 1 is ``K [I | 0]``. For each candidate ``k`` camera 2 is ``K [R[k] | -R[k] C[k]]``;
    the matches are triangulated with :func:`triangulate_linear` and a point counts when it is in
    front of both cameras: ``z > 0`` in camera 1 and ``r3ᵀ (X - C) > 0`` in camera 2 (``r3ᵀ``
    the third row of ``R[k]``). The candidate with the most such points wins.

    Args:
        R: ``(4, 3, 3)`` candidate rotations (camera from world, det +1), e.g. from
            :func:`course_lib.sfm.essential.pose_candidates`.
        C: ``(4, 3)`` candidate centres of camera 2.
        K: ``(3, 3)`` intrinsics (both images).
        x1: ``(N, 2)`` pixels in image 1 (inlier matches).
        x2: ``(N, 2)`` matching pixels in image 2.

    Returns:
        :class:`PoseChoice` with ``R_cw, t_cw`` of camera 2, the points ``X (N, 3)``, the mask
        ``in_front (N,)`` and ``counts (4,)``.

    Introduced in notebooks/03_triangulation.ipynb
    """
    R, C = _candidates(R, C)
    K = validate.intrinsics(K)
    x1, x2 = validate.matching_points(x1, x2, min_count=1, why="choosing the pose")
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    Xs, masks = [], []
    for k in range(4):
        t = translation_from_center(R[k], C[k])
        X = triangulate_linear(P1, K @ np.hstack([R[k], t[:, None]]), x1, x2)
        Xs.append(X)
        masks.append(in_front_of_both(R[k], C[k], X))
    counts = np.array([m.sum() for m in masks], dtype=int)
    best = int(np.argmax(counts))
    return PoseChoice(R[best].copy(), translation_from_center(R[best], C[best]), Xs[best], masks[best], counts, best)


def reprojection_errors(K: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray, X: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Distance in pixels between observed pixels and the projections of the points.

    Args:
        K: ``(3, 3)`` intrinsics. R_cw: ``(3, 3)``. t_cw: ``(3,)``.
        X: ``(N, 3)`` world points.
        x: ``(N, 2)`` observed pixels of the same points in this camera.

    Returns:
        ``(N,)`` errors ``||project(K, R_cw, t_cw, X) - x||`` in pixels.

    Introduced in notebooks/03_triangulation.ipynb
    """
    K = validate.intrinsics(K)
    R_cw = validate.rotation(R_cw, "R_cw", atol=1e-5)
    t_cw = validate.vector3(t_cw, "t_cw")
    X, x = validate.matching_points(X, x, names=("X", "x"), dims=(3, 2))
    return np.linalg.norm(project(K, R_cw, t_cw, X) - x, axis=1)


# ------------------------------------------------------------------------------------------------
# Non-linear triangulation
# ------------------------------------------------------------------------------------------------


def _multiview_inputs(K, R_cws, t_cws, uv, X0):
    K = validate.intrinsics(K)
    R_cws = np.asarray(R_cws, dtype=float)
    t_cws = np.asarray(t_cws, dtype=float)
    if R_cws.ndim != 3 or R_cws.shape[1:] != (3, 3):
        raise validate.KitInputError(f"R_cws has shape {R_cws.shape}: expected (V, 3, 3), one rotation per view")
    V = R_cws.shape[0]
    if t_cws.shape != (V, 3):
        raise validate.KitInputError(f"t_cws has shape {t_cws.shape}: expected ({V}, 3), one translation per view in R_cws")
    for k in range(V):
        validate.rotation(R_cws[k], f"R_cws[{k}]", atol=1e-5)
    if not np.isfinite(t_cws).all():
        raise validate.KitInputError("t_cws contains NaN or inf")
    X0 = validate.points(X0, "X0", 3)
    uv = np.asarray(uv, dtype=float)
    if uv.ndim == 2 and V == 1:
        uv = uv[:, None, :]
    if uv.shape != (X0.shape[0], V, 2):
        raise validate.KitInputError(
            f"uv has shape {uv.shape}: expected (N, V, 2) = ({X0.shape[0]}, {V}, 2), "
            "the pixels of each of the N points in each of the V views (NaN where unseen)"
        )
    if np.isinf(uv).any():
        raise validate.KitInputError("uv contains inf: mark unseen observations with NaN")
    return K, R_cws, t_cws, uv, X0


def triangulate_nonlinear(
    K: np.ndarray,
    R_cws: np.ndarray,
    t_cws: np.ndarray,
    uv: np.ndarray,
    X0: np.ndarray,
    max_nfev: int = 50,
) -> np.ndarray:
    """Refine 3-D points by minimizing their reprojection error over all views that see them.

    Minimizes, jointly for all points but independently per point,

    .. math:: \\sum_j \\sum_{i \\in V(j)} \\| \\pi(K, R_i, t_i, X_j) - x_{ij} \\|^2

    with :func:`scipy.optimize.least_squares` (trust region, sparse analytic Jacobian: each
    residual pair depends on the three coordinates of its point only). Points seen in fewer than
    two views are returned unchanged (their depth is not observable).

    Args:
        K: ``(3, 3)`` intrinsics shared by the views.
        R_cws: ``(V, 3, 3)`` rotations of the views (camera from world).
        t_cws: ``(V, 3)`` translations of the views.
        uv: ``(N, V, 2)`` observed pixels, NaN where point j is not seen in view i.
        X0: ``(N, 3)`` initial points, e.g. from :func:`triangulate_linear`.
        max_nfev: most function evaluations of the solver.

    Returns:
        ``(N, 3)`` refined points.

    Introduced in notebooks/03_triangulation.ipynb
    """
    # imported here: scipy.optimize (and scipy.spatial, which it loads) take a tenth of a second,
    # and most callers of this module (linear triangulation, the pose choice) never need them
    import scipy.sparse as sp
    from scipy.optimize import least_squares

    K, R_cws, t_cws, uv, X0 = _multiview_inputs(K, R_cws, t_cws, uv, X0)
    seen = np.isfinite(uv).all(axis=2)  # (N, V)
    X = X0.copy()
    ok = seen.sum(axis=1) >= 2
    if not ok.any():
        return X
    pts_all = np.flatnonzero(ok)
    obs_pt, obs_view = np.nonzero(seen[pts_all])  # indices into pts_all, views
    obs_uv = uv[pts_all[obs_pt], obs_view]  # (O, 2)
    Rs, ts = R_cws[obs_view], t_cws[obs_view]  # (O, 3, 3), (O, 3)
    fx, s, cx, fy, cy = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    n_obs, n_pts = obs_pt.size, pts_all.size

    def camera_points(p):
        Xp = p.reshape(-1, 3)[obs_pt]
        return np.einsum("oij,oj->oi", Rs, Xp) + ts

    def residuals(p):
        Xc = camera_points(p)
        x, y = Xc[:, 0] / Xc[:, 2], Xc[:, 1] / Xc[:, 2]
        return np.stack([fx * x + s * y + cx - obs_uv[:, 0], fy * y + cy - obs_uv[:, 1]], axis=1).ravel()

    rows = np.repeat(np.arange(2 * n_obs), 3)
    cols = (3 * obs_pt[:, None, None] + np.arange(3)[None, None, :]).repeat(2, axis=1).ravel()

    def jacobian(p):
        Xc = camera_points(p)
        iz = 1.0 / Xc[:, 2]
        x, y = Xc[:, 0] * iz, Xc[:, 1] * iz
        # d(u, v)/d(Xc): u = fx x + s y + cx, v = fy y + cy with x = X/Z, y = Y/Z
        dxy = np.zeros((n_obs, 2, 3))
        dxy[:, 0, 0] = fx * iz
        dxy[:, 0, 1] = s * iz
        dxy[:, 0, 2] = -(fx * x + s * y) * iz
        dxy[:, 1, 1] = fy * iz
        dxy[:, 1, 2] = -fy * y * iz
        J = dxy @ Rs  # chain rule: d Xc / d X = R
        return sp.csr_matrix((J.ravel(), (rows, cols)), shape=(2 * n_obs, 3 * n_pts))

    sol = least_squares(residuals, X0[pts_all].ravel(), jac=jacobian, method="trf", tr_solver="lsmr",
                        x_scale="jac", max_nfev=max_nfev, xtol=1e-10, ftol=1e-10)
    X[pts_all] = sol.x.reshape(-1, 3)
    return X

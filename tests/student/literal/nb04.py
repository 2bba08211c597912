"""Notebook 04, Perspective-n-Point: the literal student's exercises."""

import math

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation


def pnp_linear(X, x, K):
    """Linear PnP (DLT) on normalized image coordinates.

    Args:
        X: (N, 3) world points, N >= 6, not all on one plane.
        x: (N, 2) their pixels (u, v) in the new image.
        K: (3, 3) intrinsics.

    Returns:
        (R_cw, t_cw): (3, 3) rotation with det +1 and (3,) translation of the new camera
        (x_cam = R_cw @ X + t_cw); t_cw re-estimated by least squares with R_cw fixed.
    """
    N = len(X)
    if N < 6:
        raise ValueError(f"pnp_linear needs at least 6 correspondences, got {N}")
    xn = np.hstack([x, np.ones((N, 1))]) @ np.linalg.inv(K).T     # normalized (u^, v^, 1)
    # the tip: centre and scale the 3-D points (Hartley), undo with P <- P T
    c = X.mean(axis=0)
    s = np.sqrt(3) / np.linalg.norm(X - c, axis=1).mean()
    T = np.array([[s, 0, 0, -s * c[0]],
                  [0, s, 0, -s * c[1]],
                  [0, 0, s, -s * c[2]],
                  [0, 0, 0, 1]])
    Xh = np.hstack([s * (X - c), np.ones((N, 1))])
    A = np.zeros((2 * N, 12))
    A[0::2, 0:4] = Xh
    A[0::2, 8:12] = -xn[:, 0:1] * Xh
    A[1::2, 4:8] = Xh
    A[1::2, 8:12] = -xn[:, 1:2] * Xh
    _, _, Vt = np.linalg.svd(A)
    P = Vt[-1].reshape(3, 4) @ T
    if np.linalg.det(P[:, :3]) < 0:      # sign: lambda > 0
        P = -P
    U, S, Vt = np.linalg.svd(P[:, :3])   # the closest rotation
    R = U @ Vt
    # t: least squares of [x^]_x t = -[x^]_x R X_j over all points
    rows, rhs = [], []
    for j in range(N):
        u, v, w = xn[j]
        skew = np.array([[0, -w, v], [w, 0, -u], [-v, u, 0]])
        rows.append(skew)
        rhs.append(-skew @ R @ X[j])
    t = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
    return R, t


def pnp_ransac(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    """Robust PnP: linear PnP on random 6-point samples, scored by the reprojection error.

    Args:
        X: (N, 3) world points, N >= 6.
        x: (N, 2) pixels in the new image.
        K: (3, 3) intrinsics.
        rng: numpy Generator, the only source of randomness.
        threshold_px: inlier threshold on the reprojection error, in pixels.
        confidence: probability of drawing at least one all-inlier sample.
        max_iters: the most samples drawn.

    Returns:
        (R_cw (3, 3), t_cw (3,), inliers (N,) bool mask over all N correspondences, n_iters int);
        the reference returns the same four fields as a dataclass, course_lib.sfm.pnp.PnPResult.
    """
    N = len(X)
    if N < 6:
        raise ValueError(f"pnp_ransac needs at least 6 correspondences, got {N}")

    def inliers_of(R, t):
        X_cam = X @ R.T + t
        proj = X_cam @ K.T
        proj = proj[:, :2] / proj[:, 2:3]
        error = np.linalg.norm(proj - x, axis=1)
        return (error < threshold_px) & (X_cam[:, 2] > 0)

    best_inliers, best_count = None, -1
    n_needed = max_iters
    n_iters = 0
    while n_iters < min(n_needed, max_iters):
        sample = rng.choice(N, 6, replace=False)
        n_iters += 1
        R, t = pnp_linear(X[sample], x[sample], K)
        inliers = inliers_of(R, t)
        count = int(inliers.sum())
        if count > best_count:
            best_count, best_inliers = count, inliers
            all_inlier = (count / N) ** 6
            if all_inlier >= 1.0:
                n_needed = 0
            elif 1 - all_inlier < 1:
                n_needed = math.ceil(math.log(1 - confidence) / math.log(1 - all_inlier))
    R, t = pnp_linear(X[best_inliers], x[best_inliers], K)   # refit on all inliers of the best model
    return R, t, inliers_of(R, t), n_iters


def pnp_nonlinear(X, x, K, R_cw, t_cw):
    """Refine a camera pose by minimizing the reprojection error (rotation vector + translation).

    Args:
        X: (N, 3) world points (inliers only).
        x: (N, 2) their pixels.
        K: (3, 3) intrinsics.
        R_cw: (3, 3) initial rotation (det +1).
        t_cw: (3,) initial translation.

    Returns:
        (R_cw, t_cw): the refined (3, 3) rotation and (3,) translation.
    """
    def residuals(p):
        R = Rotation.from_rotvec(p[:3]).as_matrix()
        proj = (X @ R.T + p[3:]) @ K.T
        return (proj[:, :2] / proj[:, 2:3] - x).ravel()

    p0 = np.concatenate([Rotation.from_matrix(R_cw).as_rotvec(), t_cw])
    result = least_squares(residuals, p0)
    return Rotation.from_rotvec(result.x[:3]).as_matrix(), result.x[3:]

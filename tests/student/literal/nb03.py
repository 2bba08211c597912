"""Notebook 03, triangulation: the literal student's exercises."""

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix


def triangulate_linear(P1, P2, x1, x2):
    """Linear (DLT) triangulation of matched pixels seen by two cameras.

    Args:
        P1: (3, 4) projection matrix K [R_cw | t_cw] of camera 1.
        P2: (3, 4) projection matrix of camera 2.
        x1: (N, 2) pixels (u, v) in image 1.
        x2: (N, 2) matching pixels in image 2 (row k of both is one correspondence).

    Returns:
        X: (N, 3) world points (rows), already divided by the homogeneous coordinate.
    """
    # the four rows of A for every point at once: A has shape (N, 4, 4)
    A = np.stack([
        x1[:, 0:1] * P1[2] - P1[0],
        x1[:, 1:2] * P1[2] - P1[1],
        x2[:, 0:1] * P2[2] - P2[0],
        x2[:, 1:2] * P2[2] - P2[1],
    ], axis=1)
    A = A / np.linalg.norm(A, axis=2, keepdims=True)   # unit rows: better conditioned, same solution
    _, _, Vt = np.linalg.svd(A)
    Xh = Vt[:, -1, :]                                   # (N, 4)
    return Xh[:, :3] / Xh[:, 3:4]


def choose_pose(R, C, K, x1, x2):
    """Disambiguate the four pose candidates of an essential matrix by cheirality.

    Camera 1 is K [I | 0]; candidate k puts camera 2 at K [R[k] | -R[k] @ C[k]].

    Args:
        R: (4, 3, 3) candidate rotations R_cw of camera 2 (det +1).
        C: (4, 3) candidate centres of camera 2 (unit length).
        K: (3, 3) intrinsics of both images.
        x1: (N, 2) pixels in image 1.
        x2: (N, 2) matching pixels in image 2.

    Returns:
        (R_cw (3, 3), t_cw (3,), X (N, 3), in_front (N,) bool, counts (4,) int) of the chosen
        candidate: its rotation and translation t_cw = -R_cw @ C, the points triangulated with
        it, which of them lie in front of both cameras, and for every candidate the number of
        points in front of both cameras. (A PoseChoice dataclass with these fields is fine too.)
    """
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    counts = np.zeros(4, dtype=int)
    found = []
    for k in range(4):
        t = -R[k] @ C[k]
        P2 = K @ np.hstack([R[k], t[:, None]])
        X = triangulate_linear(P1, P2, x1, x2)
        in_front = (X[:, 2] > 0) & ((X - C[k]) @ R[k][2] > 0)   # depth in camera 1 and in camera 2
        counts[k] = in_front.sum()
        found.append((R[k], t, X, in_front))
    best = int(np.argmax(counts))
    R_cw, t_cw, X, in_front = found[best]
    return R_cw, t_cw, X, in_front, counts


def triangulate_nonlinear(K, R_cws, t_cws, uv, X0):
    """Refine 3-D points by minimizing their reprojection error over all views that see them.

    Args:
        K: (3, 3) intrinsics shared by the views.
        R_cws: (V, 3, 3) rotations of the views (camera from world).
        t_cws: (V, 3) translations of the views.
        uv: (N, V, 2) observed pixels of point j in view i, NaN where the view does not see it.
        X0: (N, 3) initial points (e.g. from triangulate_linear).

    Returns:
        X: (N, 3) refined points.
    """
    N = len(X0)
    seen = ~np.isnan(uv).any(axis=2)               # (N, V): leave out the views that do not see a point
    point_of, view_of = np.nonzero(seen)            # one entry per observation
    observed = uv[point_of, view_of]                # (n_obs, 2)

    def residuals(p):
        X = p.reshape(N, 3)
        X_cam = np.einsum("kij,kj->ki", R_cws[view_of], X[point_of]) + t_cws[view_of]
        x = X_cam @ K.T
        return (x[:, :2] / x[:, 2:3] - observed).ravel()

    # each point only touches its own residuals: a block-diagonal Jacobian
    sparsity = lil_matrix((2 * len(point_of), 3 * N), dtype=int)
    for k, j in enumerate(point_of):
        sparsity[2 * k:2 * k + 2, 3 * j:3 * j + 3] = 1
    result = least_squares(residuals, X0.ravel(), jac_sparsity=sparsity)
    return result.x.reshape(N, 3)

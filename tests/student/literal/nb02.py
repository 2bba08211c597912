"""Notebook 02, the essential matrix and the relative pose: the literal student's exercises."""

import numpy as np


def essential_from_fundamental(F, K):
    """The essential matrix E = K^T F K, corrected to singular values (1, 1, 0).

    Args:
        F: (3, 3) fundamental matrix with x2h^T F x1h = 0 (pixels, any scale).
        K: (3, 3) intrinsics shared by both images.

    Returns:
        E: (3, 3) essential matrix, E = U diag(1, 1, 0) V^T where U, V come from the SVD of
            K^T F K; y2^T E y1 = 0 for normalized coordinates y = K^-1 (u, v, 1).
    """
    U, S, Vt = np.linalg.svd(K.T @ F @ K)
    return U @ np.diag([1.0, 1.0, 0.0]) @ Vt


def pose_candidates(E):
    """The four relative poses (R, C) of camera 2 allowed by an essential matrix.

    Camera 1 is at R = I, C = 0. With E = U diag(1, 1, 0) V^T and W the 90-degree rotation
    about z: R in {U W V^T, U W^T V^T}, t = +-U[:, 2], C = -R^T t. If det R = -1, flip the
    sign of both R and C.

    Args:
        E: (3, 3) essential matrix (y2^T E y1 = 0), any scale.

    Returns:
        R: (4, 3, 3) rotations R_cw of camera 2, det = +1, in the order
            (U W V^T, +), (U W V^T, -), (U W^T V^T, +), (U W^T V^T, -).
        C: (4, 3) unit-length centres of camera 2 (t_cw = -R[k] @ C[k]).
    """
    U, S, Vt = np.linalg.svd(E)
    W = np.array([[0.0, -1.0, 0.0],
                  [1.0, 0.0, 0.0],
                  [0.0, 0.0, 1.0]])
    Rs, Cs = [], []
    for R in (U @ W @ Vt, U @ W.T @ Vt):
        for sign in (+1, -1):
            t = sign * U[:, 2]
            C = -R.T @ t
            if np.linalg.det(R) < 0:
                Rs.append(-R)
                Cs.append(-C)
            else:
                Rs.append(R)
                Cs.append(C)
    return np.array(Rs), np.array(Cs)

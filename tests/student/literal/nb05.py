"""Notebook 05, bundle adjustment: the literal student's exercises."""

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

from course_lib.starting_points import observation_arrays  # imported by the notebook's first cells


# --- given by the notebook (section 2), not exercises ------------------------------------------
def pack_params(R_cw, t_cw, X):
    """(M, 3, 3), (M, 3), (N, 3) -> the (6M + 3N,) parameter vector [r_0, t_0, ..., X_0, ...]."""
    cams = np.hstack([Rotation.from_matrix(R_cw).as_rotvec(), t_cw])
    return np.concatenate([cams.ravel(), np.asarray(X, float).ravel()])


def unpack_params(params, n_cameras, n_points):
    """The inverse of pack_params: R_cw (M, 3, 3), t_cw (M, 3), X (N, 3)."""
    cams = params[: 6 * n_cameras].reshape(n_cameras, 6)
    R_cw = Rotation.from_rotvec(cams[:, :3]).as_matrix().reshape(n_cameras, 3, 3)
    return R_cw, cams[:, 3:].copy(), params[6 * n_cameras :].reshape(n_points, 3).copy()


# --- exercises ---------------------------------------------------------------------------------


def visibility_matrix(track_uv):
    """The visibility matrix of a set of tracks.

    Args:
        track_uv: (T, M, 2) pixel (u, v) of point j in image i at [j, i], NaN where the point is not seen.

    Returns:
        (T, M) bool array V with V[j, i] True when point j is seen in image i (the transpose of
        the handout's V_ij, because points are rows).
    """
    return ~np.isnan(track_uv).any(axis=2)


def reprojection_residuals(params, n_cameras, n_points, camera_idx, point_idx, uv, K):
    """The residual vector of bundle adjustment: projected minus observed pixels.

    Args:
        params: (6M + 3N,) parameters [r_0, t_0, r_1, t_1, ..., X_0, X_1, ...]; r_i is the rotation
            vector of R_cw of camera i (x_cam = R_cw X + t_cw).
        n_cameras: M. n_points: N.
        camera_idx: (K,) int, camera of observation k.
        point_idx: (K,) int, point of observation k.
        uv: (K, 2) observed pixels.
        K: (3, 3) intrinsics.

    Returns:
        (2K,) residuals [u_0' - u_0, v_0' - v_0, u_1' - u_1, ...] in pixels (u and v interleaved).
    """
    R_cw, t_cw, X = unpack_params(params, n_cameras, n_points)
    X_cam = np.einsum("kij,kj->ki", R_cw[camera_idx], X[point_idx]) + t_cw[camera_idx]
    x = X_cam @ K.T
    projected = x[:, :2] / x[:, 2:3]
    return (projected - uv).ravel()


def jacobian_sparsity(n_cameras, n_points, camera_idx, point_idx):
    """Which entries of the bundle-adjustment Jacobian can be non-zero.

    Args:
        n_cameras: M. n_points: N.
        camera_idx: (K,) int, camera of observation k.
        point_idx: (K,) int, point of observation k.

    Returns:
        (2K, 6M + 3N) 0/1 matrix (scipy.sparse, e.g. lil_matrix, or a dense array): rows 2k and
        2k + 1 have ones in the 6 columns of camera camera_idx[k] (6c ... 6c + 5) and in the 3
        columns of point point_idx[k] (6M + 3j ... 6M + 3j + 2).
    """
    n_obs = len(camera_idx)
    S = lil_matrix((2 * n_obs, 6 * n_cameras + 3 * n_points), dtype=int)
    k = np.arange(n_obs)
    for s in range(6):
        S[2 * k, 6 * camera_idx + s] = 1
        S[2 * k + 1, 6 * camera_idx + s] = 1
    for s in range(3):
        S[2 * k, 6 * n_cameras + 3 * point_idx + s] = 1
        S[2 * k + 1, 6 * n_cameras + 3 * point_idx + s] = 1
    return S


def bundle_adjust(K, R_cw, t_cw, X, uv, callback=None):
    """Refine all cameras and points by minimizing the reprojection error.

    Args:
        K: (3, 3) intrinsics (fixed).
        R_cw: (M, 3, 3) initial rotations. t_cw: (M, 3) initial translations.
        X: (N, 3) initial points.
        uv: (N, M, 2) observed pixels, NaN where point j is not seen in image i.
        callback: optional; call callback(R_cw, t_cw, X) after every iteration (least_squares
            accepts callback=f with f(x) called on the current parameter vector).

    Returns:
        (R_cw (M, 3, 3), t_cw (M, 3), X (N, 3)) after bundle adjustment.
    """
    M, N = len(R_cw), len(X)
    camera_idx, point_idx, uv_obs = observation_arrays(uv)
    p0 = pack_params(R_cw, t_cw, X)

    def after_iteration(x):
        callback(*unpack_params(x, M, N))

    res = least_squares(reprojection_residuals, p0, jac_sparsity=jacobian_sparsity(M, N, camera_idx, point_idx),
                        method="trf", x_scale="jac", args=(M, N, camera_idx, point_idx, uv_obs, K),
                        callback=after_iteration if callback is not None else None)
    return unpack_params(res.x, M, N)

"""Notebook 05 (bundle adjustment): classic mistakes, honest solutions and trivial answers, run through its checks."""

from __future__ import annotations

import numpy as np

from course_lib.checks import bundle_adjustment as gba
from course_lib.sfm import bundle_adjustment as rba
from course_lib.sfm import visibility as rvi
from tests.checks.catalogue import Mistake

# ============================================================================ buggy versions
# Each is written as a student would write it (often the reference with one line changed).

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

# ============================================================================ the catalogue

M = Mistake
MISTAKES = [
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
]

#: Correct solutions: they must score full marks.
HONEST = [

]


def ba_identity(K, R, t, X, uv, callback=None):
    if callback is not None:
        callback(R, t, X)
    return R, t, X


def _trivial() -> list:
    z = np.zeros  # noqa: F841
    return [
        (gba.check_visibility_matrix, lambda track_uv: z(track_uv.shape[:2], bool)),
        (gba.check_reprojection_residuals, lambda p, M, N, ci, pi, uv, K: z(2 * len(ci))),
        (gba.check_jacobian_sparsity, lambda M, N, ci, pi: np.ones((2 * len(ci), 6 * M + 3 * N))),
        (gba.check_bundle_adjustment, ba_identity),
    ]


#: Constants of the right shape: they pass the shape gates and trivially satisfied properties, and must earn nothing.
TRIVIAL = _trivial()

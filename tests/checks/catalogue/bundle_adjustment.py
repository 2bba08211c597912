"""Notebook 05 (bundle adjustment): classic mistakes, honest solutions and trivial answers, run through its checks."""

from __future__ import annotations

import numpy as np
import scipy.sparse
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from course_lib.checks import bundle_adjustment as gba
from course_lib.sfm import bundle_adjustment as rba
from course_lib.sfm import visibility as rvi
from course_lib.starting_points import observation_arrays
from tests.checks.catalogue import Honest, Mistake

# ============================================================================ buggy versions
# Each is written as a student would write it (often the reference with one line changed).

# -- 05: visibility_matrix ------------------------------------------------------------------------------
def visibility_transposed(track_uv):
    return rvi.visibility_matrix(track_uv).T


def visibility_inverted(track_uv):
    return ~rvi.visibility_matrix(track_uv)


def visibility_compared_with_nan(track_uv):
    return track_uv[..., 0] != np.nan  # always True: NaN equals nothing


def visibility_not_reduced(track_uv):
    return ~np.isnan(track_uv)


# -- 05: reprojection_residuals -------------------------------------------------------------------------
def _residuals(params, n_cameras, n_points, camera_idx, point_idx, uv, K, transpose=False, divide=True,
               points_first=False, use_K=True, euler=False, flat=True):
    if points_first:
        X, cams = params[: 3 * n_points].reshape(-1, 3), params[3 * n_points:].reshape(-1, 6)
    else:
        cams, X = params[: 6 * n_cameras].reshape(-1, 6), params[6 * n_cameras:].reshape(-1, 3)
    rot = Rotation.from_euler("xyz", cams[:, :3]) if euler else Rotation.from_rotvec(cams[:, :3])
    R = rot.as_matrix().reshape(-1, 3, 3)
    if transpose:
        R = np.transpose(R, (0, 2, 1))
    xc = np.einsum("kij,kj->ki", R[camera_idx], X[point_idx]) + cams[camera_idx, 3:]
    xh = xc @ (K if use_K else np.eye(3)).T
    r = (xh[:, :2] / xh[:, 2:] if divide else xh[:, :2]) - uv
    return r.ravel() if flat else r


def residuals_2d(params, n_cameras, n_points, camera_idx, point_idx, uv, K):
    return _residuals(params, n_cameras, n_points, camera_idx, point_idx, uv, K, flat=False)


def residuals_R_wc(params, n_cameras, n_points, camera_idx, point_idx, uv, K):
    return _residuals(params, n_cameras, n_points, camera_idx, point_idx, uv, K, transpose=True)


def residuals_no_depth_division(params, n_cameras, n_points, camera_idx, point_idx, uv, K):
    return _residuals(params, n_cameras, n_points, camera_idx, point_idx, uv, K, divide=False)


def residuals_points_first(params, n_cameras, n_points, camera_idx, point_idx, uv, K):
    return _residuals(params, n_cameras, n_points, camera_idx, point_idx, uv, K, points_first=True)


def residuals_no_K(params, n_cameras, n_points, camera_idx, point_idx, uv, K):
    return _residuals(params, n_cameras, n_points, camera_idx, point_idx, uv, K, use_K=False)


def residuals_euler(params, n_cameras, n_points, camera_idx, point_idx, uv, K):
    return _residuals(params, n_cameras, n_points, camera_idx, point_idx, uv, K, euler=True)


def residuals_not_interleaved(params, n_cameras, n_points, camera_idx, point_idx, uv, K):
    return _residuals(params, n_cameras, n_points, camera_idx, point_idx, uv, K, flat=False).T.ravel()


# -- 05: jacobian_sparsity ------------------------------------------------------------------------------
def sparsity_nine_per_camera(n_cameras, n_points, camera_idx, point_idx):
    A = scipy.sparse.lil_matrix((2 * len(camera_idx), 9 * n_cameras + 3 * n_points), dtype=int)
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


def sparsity_u_rows_only(n_cameras, n_points, camera_idx, point_idx):
    A = np.zeros((2 * len(camera_idx), 6 * n_cameras + 3 * n_points), dtype=int)
    for k, (cm, pt) in enumerate(zip(camera_idx, point_idx)):
        A[2 * k, 6 * cm: 6 * cm + 6] = 1
        A[2 * k, 6 * n_cameras + 3 * pt: 6 * n_cameras + 3 * pt + 3] = 1
    return A


def sparsity_transposed(n_cameras, n_points, camera_idx, point_idx):
    return rba.jacobian_sparsity(n_cameras, n_points, camera_idx, point_idx).T


# -- 05: bundle_adjust ------------------------------------------------------------------------------------
def _ba(K, R_cw, t_cw, X, uv, callback=None, nine=False, max_nfev=None, when="iterations", points_only=False,
        loss="linear"):
    cam, pt, obs = observation_arrays(uv)
    M, N = len(R_cw), len(X)

    def unpack(p):
        if nine:
            return p[: 9 * M].reshape(M, 3, 3), p[9 * M: 12 * M].reshape(M, 3), p[12 * M:].reshape(N, 3)
        return rba.unpack_params(p, M, N)

    def res(p):
        if callback is not None and when == "evaluations":
            callback(*unpack(p))
        R, t, Y = unpack(p)
        xh = (np.einsum("kij,kj->ki", R[cam], Y[pt]) + t[cam]) @ K.T
        return (xh[:, :2] / xh[:, 2:] - obs).ravel()

    if callback is not None and when == "before":
        callback(R_cw, t_cw, X)
    cb = (lambda x: callback(*unpack(x))) if callback is not None and when == "iterations" else None
    if points_only:  # the cameras are not optimized: only the points move
        cams = rba.pack_params(R_cw, t_cw, X)[: 6 * M]
        Jp = rba.jacobian_sparsity(M, N, cam, pt)[:, 6 * M:]
        q = least_squares(lambda q: res(np.concatenate([cams, q])), X.ravel(), jac_sparsity=Jp, callback=cb and (
            lambda x: callback(*unpack(np.concatenate([cams, x]))))).x
        p = np.concatenate([cams, q])
    elif nine:
        S = rba.jacobian_sparsity(M, N, cam, pt).toarray()
        J = np.hstack([np.repeat(S[:, 0: 6 * M: 6], 9, axis=1), np.repeat(S[:, 3: 6 * M: 6], 3, axis=1), S[:, 6 * M:]])
        p = least_squares(res, np.concatenate([R_cw.ravel(), t_cw.ravel(), X.ravel()]), jac_sparsity=J, max_nfev=20,
                          callback=cb).x
    else:
        J = rba.jacobian_sparsity(M, N, cam, pt)
        p = least_squares(res, rba.pack_params(R_cw, t_cw, X), jac_sparsity=J, x_scale="jac", max_nfev=max_nfev,
                          loss=loss, method="trf", callback=cb).x
    return unpack(p)


def ba_nine_entries(K, R_cw, t_cw, X, uv, callback=None):
    return _ba(K, R_cw, t_cw, X, uv, callback, nine=True)


def ba_points_only(K, R_cw, t_cw, X, uv, callback=None):
    return _ba(K, R_cw, t_cw, X, uv, callback, points_only=True)


def ba_no_callback(K, R_cw, t_cw, X, uv, callback=None):
    return _ba(K, R_cw, t_cw, X, uv, None)


def ba_callback_before(K, R_cw, t_cw, X, uv, callback=None):
    return _ba(K, R_cw, t_cw, X, uv, callback, when="before")


def ba_callback_every_evaluation(K, R_cw, t_cw, X, uv, callback=None):
    return _ba(K, R_cw, t_cw, X, uv, callback, when="evaluations")


def ba_three_evaluations(K, R_cw, t_cw, X, uv, callback=None):
    return _ba(K, R_cw, t_cw, X, uv, callback, max_nfev=3)


def ba_drops_observations(K, R_cw, t_cw, X, uv, callback=None):
    """Solves, drops the observations more than 1 px off, solves again: the minimum of another cost."""
    R, t, Y = _ba(K, R_cw, t_cw, X, uv, callback)
    cam, pt, obs = observation_arrays(uv)
    e = np.linalg.norm(rba.reprojection_residuals(rba.pack_params(R, t, Y), len(R), len(Y), cam, pt, obs, K)
                       .reshape(-1, 2), axis=1)
    uv = uv.copy()
    uv[pt[e > 1.0], cam[e > 1.0]] = np.nan
    return _ba(K, R, t, Y, uv, callback)


# ============================================================================ honest solutions
# Written from the notebook's equations and the SciPy cookbook's bundle adjustment, not from course_lib;
# calls of other exercises by name. pack_params and unpack_params are the notebook's given helpers.

def pack_params(R_cw, t_cw, X):
    cams = np.hstack([Rotation.from_matrix(R_cw).as_rotvec(), t_cw])
    return np.concatenate([cams.ravel(), np.asarray(X, float).ravel()])


def unpack_params(params, n_cameras, n_points):
    cams = params[: 6 * n_cameras].reshape(n_cameras, 6)
    R_cw = Rotation.from_rotvec(cams[:, :3]).as_matrix().reshape(n_cameras, 3, 3)
    return R_cw, cams[:, 3:].copy(), params[6 * n_cameras:].reshape(n_points, 3).copy()


def visibility_matrix(track_uv):
    return ~np.isnan(track_uv).any(axis=2)


def reprojection_residuals(params, n_cameras, n_points, camera_idx, point_idx, uv, K):
    cams = params[: 6 * n_cameras].reshape(n_cameras, 6)
    points = params[6 * n_cameras:].reshape(n_points, 3)
    R = Rotation.from_rotvec(cams[camera_idx, :3]).as_matrix()  # (K, 3, 3), one per observation
    x_cam = np.einsum("kij,kj->ki", R, points[point_idx]) + cams[camera_idx, 3:]
    x_img = x_cam @ K.T
    return (x_img[:, :2] / x_img[:, 2:3] - uv).ravel()


def jacobian_sparsity(n_cameras, n_points, camera_idx, point_idx):
    m = 2 * len(camera_idx)
    A = scipy.sparse.lil_matrix((m, 6 * n_cameras + 3 * n_points), dtype=int)
    i = np.arange(len(camera_idx))
    for s in range(6):
        A[2 * i, 6 * camera_idx + s] = 1
        A[2 * i + 1, 6 * camera_idx + s] = 1
    for s in range(3):
        A[2 * i, 6 * n_cameras + 3 * point_idx + s] = 1
        A[2 * i + 1, 6 * n_cameras + 3 * point_idx + s] = 1
    return A


def bundle_adjust(K, R_cw, t_cw, X, uv, callback=None):
    M, N = len(R_cw), len(X)
    camera_idx, point_idx, uv_obs = observation_arrays(uv)
    p0 = pack_params(R_cw, t_cw, X)
    hook = None if callback is None else (lambda x: callback(*unpack_params(x, M, N)))
    res = least_squares(reprojection_residuals, p0, jac_sparsity=jacobian_sparsity(M, N, camera_idx, point_idx),
                        method="trf", x_scale="jac", args=(M, N, camera_idx, point_idx, uv_obs, K), callback=hook)
    return unpack_params(res.x, M, N)


# -- other valid styles
def visibility_matrix_loops(track_uv):
    """Loops over points and images, both coordinates tested for finiteness."""
    T, M = track_uv.shape[:2]
    V = np.zeros((T, M), dtype=bool)
    for j in range(T):
        for i in range(M):
            V[j, i] = bool(np.isfinite(track_uv[j, i, 0]) and np.isfinite(track_uv[j, i, 1]))
    return V


def reprojection_residuals_rodrigues(params, n_cameras, n_points, camera_idx, point_idx, uv, K):
    """Rodrigues' formula by hand, a loop over observations, observed minus projected."""
    out = np.empty(2 * len(camera_idx))
    for k, (c, j) in enumerate(zip(camera_idx, point_idx)):
        r, t = params[6 * c: 6 * c + 3], params[6 * c + 3: 6 * c + 6]
        Xj = params[6 * n_cameras + 3 * j: 6 * n_cameras + 3 * j + 3]
        theta = np.linalg.norm(r)
        if theta < 1e-12:
            Xr = Xj + np.cross(r, Xj)
        else:
            a = r / theta
            Xr = Xj * np.cos(theta) + np.cross(a, Xj) * np.sin(theta) + a * (a @ Xj) * (1 - np.cos(theta))
        u, v, w = K @ (Xr + t)
        out[2 * k], out[2 * k + 1] = uv[k, 0] - u / w, uv[k, 1] - v / w
    return out


def jacobian_sparsity_dense(n_cameras, n_points, camera_idx, point_idx):
    """A dense 0/1 array built with fancy indexing."""
    A = np.zeros((2 * len(camera_idx), 6 * n_cameras + 3 * n_points), dtype=np.uint8)
    rows = np.repeat(np.arange(2 * len(camera_idx)), 1)
    cam_cols = 6 * np.repeat(camera_idx, 2)[:, None] + np.arange(6)
    pt_cols = 6 * n_cameras + 3 * np.repeat(point_idx, 2)[:, None] + np.arange(3)
    A[rows[:, None], cam_cols] = 1
    A[rows[:, None], pt_cols] = 1
    return A


def bundle_adjust_fixed_first_camera(K, R_cw, t_cw, X, uv, callback=None):
    """The gauge fixed by holding camera 0, the callback with the OptimizeResult signature."""
    M, N = len(R_cw), len(X)
    cam, pt, obs = observation_arrays(uv)
    full0 = pack_params(R_cw, t_cw, X)
    first = full0[:6]

    def fun(q):
        return reprojection_residuals(np.concatenate([first, q]), M, N, cam, pt, obs, K)

    def report(intermediate_result):
        callback(*unpack_params(np.concatenate([first, intermediate_result.x]), M, N))

    S = jacobian_sparsity(M, N, cam, pt)
    S = scipy.sparse.csr_matrix(S)[:, 6:]
    res = least_squares(fun, full0[6:], jac_sparsity=S, method="trf", x_scale="jac",
                        callback=None if callback is None else report)
    return unpack_params(np.concatenate([first, res.x]), M, N)


# ============================================================================ the catalogue

M = Mistake
MISTAKES = [
    M("visibility_matrix", "transposed", gba.check_visibility_matrix, visibility_transposed, ("transpose",)),
    M("visibility_matrix", "inverted", gba.check_visibility_matrix, visibility_inverted, ("inverted",)),
    M("visibility_matrix", "!= np.nan", gba.check_visibility_matrix, visibility_compared_with_nan,
      ("np.isnan", "always true")),
    M("visibility_matrix", "last axis not reduced", gba.check_visibility_matrix, visibility_not_reduced,
      ("reduce the last axis",)),
    M("reprojection_residuals", "(K, 2) instead of (2K,)", gba.check_reprojection_residuals, residuals_2d,
      ("flat",)),
    M("reprojection_residuals", "R_wc instead of R_cw", gba.check_reprojection_residuals, residuals_R_wc,
      ("r_wc",)),
    M("reprojection_residuals", "no division by the depth", gba.check_reprojection_residuals,
      residuals_no_depth_division, ("depth",)),
    M("reprojection_residuals", "points first in params", gba.check_reprojection_residuals, residuals_points_first,
      ("cameras first",)),
    M("reprojection_residuals", "K missing", gba.check_reprojection_residuals, residuals_no_K, ("k is missing",)),
    M("reprojection_residuals", "Euler angles", gba.check_reprojection_residuals, residuals_euler,
      ("rotation vector", "euler")),
    M("reprojection_residuals", "u's then v's", gba.check_reprojection_residuals, residuals_not_interleaved,
      ("not interleaved",)),
    M("jacobian_sparsity", "9 parameters per camera", gba.check_jacobian_sparsity, sparsity_nine_per_camera,
      ("9 per camera",)),
    M("jacobian_sparsity", "point columns without the 6M offset", gba.check_jacobian_sparsity, sparsity_no_offset,
      ("offset 6m",)),
    M("jacobian_sparsity", "rows not interleaved", gba.check_jacobian_sparsity, sparsity_not_interleaved,
      ("interleaved",)),
    M("jacobian_sparsity", "only the u row", gba.check_jacobian_sparsity, sparsity_u_rows_only,
      ("only row 2k",)),
    M("jacobian_sparsity", "transposed", gba.check_jacobian_sparsity, sparsity_transposed,
      ("rows are residuals",)),
    M("bundle_adjust", "optimizes the 9 entries of R", gba.check_bundle_adjustment, ba_nine_entries,
      ("not a rotation",)),
    M("bundle_adjust", "cameras not optimized", gba.check_bundle_adjustment, ba_points_only,
      ("cameras did not move",)),
    M("bundle_adjust", "callback never called", gba.check_bundle_adjustment, ba_no_callback,
      ("never called",)),
    M("bundle_adjust", "callback once, before solving", gba.check_bundle_adjustment, ba_callback_before,
      ("called once with the starting state",)),
    M("bundle_adjust", "callback at every evaluation", gba.check_bundle_adjustment, ba_callback_every_evaluation,
      ("every evaluation",)),
    M("bundle_adjust", "stopped after 3 evaluations", gba.check_bundle_adjustment, ba_three_evaluations,
      ("stopped before the minimum",)),
    M("bundle_adjust", "observations beyond 1 px dropped", gba.check_bundle_adjustment, ba_drops_observations,
      ("not the least-squares minimum",)),
]

#: Correct solutions: they must score full marks.
HONEST = [
    Honest("visibility_matrix", "NaN test", gba.check_visibility_matrix, visibility_matrix),
    Honest("reprojection_residuals", "rotation vectors, einsum", gba.check_reprojection_residuals,
           reprojection_residuals),
    Honest("jacobian_sparsity", "SciPy cookbook, lil_matrix", gba.check_jacobian_sparsity, jacobian_sparsity),
    Honest("bundle_adjust", "least_squares as the hints say", gba.check_bundle_adjustment, bundle_adjust),
    Honest("visibility_matrix", "loops, isfinite", gba.check_visibility_matrix, visibility_matrix_loops),
    Honest("reprojection_residuals", "Rodrigues by hand, observed minus projected", gba.check_reprojection_residuals,
           reprojection_residuals_rodrigues),
    Honest("jacobian_sparsity", "dense uint8 array", gba.check_jacobian_sparsity, jacobian_sparsity_dense),
    Honest("bundle_adjust", "camera 0 fixed (gauge)", gba.check_bundle_adjustment, bundle_adjust_fixed_first_camera),
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


# ============================================================================ issue 29: written as students write them
# From the notebook's text and the stub's docstring, with an error students make; then valid variants (among them
# the honest but slow: residuals one observation at a time, a dense Jacobian).

def visibility_u_positive(track_uv):  # "seen" tested as u > 0: a pixel at u <= 0 counts as unseen
    return track_uv[..., 0] > 0


def residuals_indices_swapped(params, n_cameras, n_points, camera_idx, point_idx, uv, K):  # camera_idx <-> point_idx
    cams = params[: 6 * n_cameras].reshape(-1, 6)
    pts = params[6 * n_cameras:].reshape(-1, 3)
    c, j = point_idx % n_cameras, camera_idx  # the point index used for the camera and the other way round
    R = Rotation.from_rotvec(cams[c, :3]).as_matrix()
    xc = np.einsum("kij,kj->ki", R, pts[j]) + cams[c, 3:]
    q = xc @ K.T
    return (q[:, :2] / q[:, 2:] - uv).ravel()


def residuals_no_principal_point(params, n_cameras, n_points, camera_idx, point_idx, uv, K):  # f x / z only
    cams = params[: 6 * n_cameras].reshape(-1, 6)
    pts = params[6 * n_cameras:].reshape(-1, 3)
    R = Rotation.from_rotvec(cams[camera_idx, :3]).as_matrix()
    xc = np.einsum("kij,kj->ki", R, pts[point_idx]) + cams[camera_idx, 3:]
    proj = np.column_stack([K[0, 0] * xc[:, 0] / xc[:, 2], K[1, 1] * xc[:, 1] / xc[:, 2]])
    return (proj - uv).ravel()


def residuals_t_as_centre(params, n_cameras, n_points, camera_idx, point_idx, uv, K):  # x_cam = R (X - t)
    cams = params[: 6 * n_cameras].reshape(-1, 6)
    pts = params[6 * n_cameras:].reshape(-1, 3)
    R = Rotation.from_rotvec(cams[camera_idx, :3]).as_matrix()
    xc = np.einsum("kij,kj->ki", R, pts[point_idx] - cams[camera_idx, 3:])
    q = xc @ K.T
    return (q[:, :2] / q[:, 2:] - uv).ravel()


def sparsity_rotation_columns_only(n_cameras, n_points, camera_idx, point_idx):  # 3 camera columns, not 6
    A = scipy.sparse.lil_matrix((2 * len(camera_idx), 6 * n_cameras + 3 * n_points), dtype=int)
    for k, (c, j) in enumerate(zip(camera_idx, point_idx)):
        for r in (2 * k, 2 * k + 1):
            A[r, 6 * c: 6 * c + 3] = 1
            A[r, 6 * n_cameras + 3 * j: 6 * n_cameras + 3 * j + 3] = 1
    return A


def sparsity_point_stride_one(n_cameras, n_points, camera_idx, point_idx):  # point j's columns at 6M + j, no 3j
    A = scipy.sparse.lil_matrix((2 * len(camera_idx), 6 * n_cameras + 3 * n_points), dtype=int)
    for k, (c, j) in enumerate(zip(camera_idx, point_idx)):
        for r in (2 * k, 2 * k + 1):
            A[r, 6 * c: 6 * c + 6] = 1
            A[r, 6 * n_cameras + j: 6 * n_cameras + j + 3] = 1
    return A


def _ba29(K, R_cw, t_cw, X, uv, callback=None, dtype=float, cameras_only=False, loss="linear", cb_params=False):
    M, N = len(R_cw), len(X)
    cam, pt, obs = observation_arrays(uv)
    p0 = pack_params(R_cw, t_cw, X)
    S = jacobian_sparsity(M, N, cam, pt)
    if cameras_only:  # the points are left where they are: only the 6M camera parameters go to the solver
        Xf = p0[6 * M:]
        fun = lambda q: reprojection_residuals(np.concatenate([q, Xf]), M, N, cam, pt, obs, K)  # noqa: E731
        hook = None if callback is None else (lambda q: callback(*unpack_params(np.concatenate([q, Xf]), M, N)))
        q = least_squares(fun, p0[: 6 * M], jac_sparsity=scipy.sparse.csr_matrix(S)[:, : 6 * M], x_scale="jac",
                          method="trf", callback=hook).x
        return unpack_params(np.concatenate([q, Xf]), M, N)

    def fun(p):
        return reprojection_residuals(p, M, N, cam, pt, obs, K).astype(dtype)

    hook = None
    if callback is not None:
        hook = (lambda x: callback(x)) if cb_params else (lambda x: callback(*unpack_params(x, M, N)))
    res = least_squares(fun, p0, jac_sparsity=S, method="trf", x_scale="jac", loss=loss, callback=hook)
    return unpack_params(res.x, M, N)


def ba_float32_residuals(K, R_cw, t_cw, X, uv, callback=None):  # residuals cast to float32 "to save memory"
    return _ba29(K, R_cw, t_cw, X, uv, callback, dtype=np.float32)


def ba_points_not_optimized(K, R_cw, t_cw, X, uv, callback=None):
    return _ba29(K, R_cw, t_cw, X, uv, callback, cameras_only=True)


def ba_soft_l1(K, R_cw, t_cw, X, uv, callback=None):  # a robust loss "against outliers": another cost
    return _ba29(K, R_cw, t_cw, X, uv, callback, loss="soft_l1")


def ba_callback_gets_params(K, R_cw, t_cw, X, uv, callback=None):  # callback(x): the parameter vector, as scipy does
    return _ba29(K, R_cw, t_cw, X, uv, callback, cb_params=True)


# -- valid variants -----------------------------------------------------------------------------------------------
def visibility_matrix__all_nan(track_uv):
    """Unseen where both coordinates are NaN (they always come together)."""
    return ~np.all(np.isnan(track_uv), axis=-1)


def reprojection_residuals__float32(params, n_cameras, n_points, camera_idx, point_idx, uv, K):
    """The residuals computed and returned in float32."""
    p = np.asarray(params, np.float32)
    cams = p[: 6 * n_cameras].reshape(n_cameras, 6)
    pts = p[6 * n_cameras:].reshape(n_points, 3)
    R = Rotation.from_rotvec(cams[camera_idx, :3]).as_matrix().astype(np.float32)
    xc = np.einsum("kij,kj->ki", R, pts[point_idx]) + cams[camera_idx, 3:]
    q = xc @ K.astype(np.float32).T
    return (q[:, :2] / q[:, 2:] - uv.astype(np.float32)).ravel()


def reprojection_residuals__per_observation(params, n_cameras, n_points, camera_idx, point_idx, uv, K):
    """Slow but correct: a Rotation object per observation, in a Python loop."""
    r = []
    for c, j, (u, v) in zip(camera_idx, point_idx, uv):
        cam = params[6 * c: 6 * c + 6]
        Xj = params[6 * n_cameras + 3 * j: 6 * n_cameras + 3 * j + 3]
        x = K @ (Rotation.from_rotvec(cam[:3]).apply(Xj) + cam[3:])
        r += [x[0] / x[2] - u, x[1] / x[2] - v]
    return np.array(r)


def jacobian_sparsity__bool_kron(n_cameras, n_points, camera_idx, point_idx):
    """A dense bool array: one-hot rows of cameras and points expanded with np.kron."""
    cams = np.kron(np.eye(n_cameras, dtype=bool)[camera_idx], np.ones((2, 6), dtype=bool))
    pts = np.kron(np.eye(n_points, dtype=bool)[point_idx], np.ones((2, 3), dtype=bool))
    return np.hstack([cams, pts])


def bundle_adjust__dense_jacobian(K, R_cw, t_cw, X, uv, callback=None):
    """Slow but correct: no jac_sparsity, so least_squares estimates the whole dense Jacobian."""
    M, N = len(R_cw), len(X)
    cam, pt, obs = observation_arrays(uv)
    res = least_squares(reprojection_residuals, pack_params(R_cw, t_cw, X), x_scale="jac",
                        args=(M, N, cam, pt, obs, K),
                        callback=None if callback is None else (lambda x: callback(*unpack_params(x, M, N))))
    return unpack_params(res.x, M, N)


def bundle_adjust__no_x_scale(K, R_cw, t_cw, X, uv, callback=None):
    """least_squares' defaults apart from the sparsity (no x_scale), callback through the keyword form."""
    M, N = len(R_cw), len(X)
    cam, pt, obs = observation_arrays(uv)

    def report(intermediate_result):
        if callback is not None:
            callback(*unpack_params(intermediate_result.x, M, N))

    res = least_squares(lambda p: reprojection_residuals(p, M, N, cam, pt, obs, K), pack_params(R_cw, t_cw, X),
                        jac_sparsity=jacobian_sparsity(M, N, cam, pt), callback=report)
    return unpack_params(res.x, M, N)


MISTAKES += [
    M("visibility_matrix", "seen tested as u > 0", gba.check_visibility_matrix, visibility_u_positive,
      ("entries",), batch="29"),
    M("reprojection_residuals", "camera_idx and point_idx swapped", gba.check_reprojection_residuals,
      residuals_indices_swapped, ("max difference",), batch="29"),
    M("reprojection_residuals", "principal point missing", gba.check_reprojection_residuals,
      residuals_no_principal_point, ("max difference",), batch="29"),
    M("reprojection_residuals", "x_cam = R (X - t)", gba.check_reprojection_residuals, residuals_t_as_centre,
      ("max difference",), batch="29"),
    M("jacobian_sparsity", "3 columns per camera", gba.check_jacobian_sparsity, sparsity_rotation_columns_only,
      ("differ",), batch="29"),
    M("jacobian_sparsity", "point columns 6M + j", gba.check_jacobian_sparsity, sparsity_point_stride_one,
      ("6m + 3j",), batch="29"),
    M("bundle_adjust", "points not optimized", gba.check_bundle_adjustment, ba_points_not_optimized,
      ("points",), batch="29"),
    M("bundle_adjust", "soft_l1 loss", gba.check_bundle_adjustment, ba_soft_l1, ("minimum",), batch="29"),
    M("bundle_adjust", "callback(x) with the parameter vector", gba.check_bundle_adjustment, ba_callback_gets_params,
      ("callback",), batch="29"),
]

HONEST += [
    Honest("visibility_matrix", "NaN in both coordinates", gba.check_visibility_matrix, visibility_matrix__all_nan),
    Honest("reprojection_residuals", "float32", gba.check_reprojection_residuals, reprojection_residuals__float32),
    Honest("reprojection_residuals", "one observation at a time (slow)", gba.check_reprojection_residuals,
           reprojection_residuals__per_observation),
    Honest("jacobian_sparsity", "dense bool, np.kron", gba.check_jacobian_sparsity, jacobian_sparsity__bool_kron),
    Honest("bundle_adjust", "dense Jacobian (slow)", gba.check_bundle_adjustment, bundle_adjust__dense_jacobian),
    Honest("bundle_adjust", "no x_scale, keyword callback", gba.check_bundle_adjustment, bundle_adjust__no_x_scale),
    # written as a mistake (issue 29's probe: residuals cast to float32), it reaches the minimum: valid
    Honest("bundle_adjust", "residuals cast to float32", gba.check_bundle_adjustment, ba_float32_residuals),
]


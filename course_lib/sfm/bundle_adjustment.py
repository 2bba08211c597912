"""Bundle adjustment: refine all cameras and points together by minimizing the reprojection error.

The objective is the sum over the observed (point, camera) pairs, i.e. over the ones with
:math:`V_{ij} = 1` in the visibility matrix (:mod:`course_lib.sfm.visibility`)::

    min_{R_i, t_i, X_j}  sum_{(i,j): V_ij = 1}  || project(K, R_i, t_i, X_j) - x_ij ||^2

with the intrinsics ``K`` fixed (the P3 data comes calibrated).

Parameters
    Camera ``i`` is 6 numbers: the rotation vector ``r_i`` (axis times angle, radians, so
    ``R_cw = exp([r_i]_x)``, :class:`scipy.spatial.transform.Rotation`) and ``t_cw``; point ``j`` is
    ``X_j``. The parameter vector is laid out as in the SciPy cookbook's bundle adjustment::

        params = [r_0, t_0, r_1, t_1, ..., r_{M-1}, t_{M-1}, X_0, X_1, ..., X_{N-1}]   # 6M + 3N

Residuals
    One pair per observation ``k`` (camera ``camera_idx[k]``, point ``point_idx[k]``):
    ``r[2k:2k+2] = project(K, R, t, X) - uv[k]`` in pixels, so the cost is ``0.5 * sum(r**2)``.

Jacobian
    Analytic and sparse: the two rows of observation ``k`` are non-zero only in the 6 columns of
    its camera and the 3 columns of its point (a ``2 x 6`` and a ``2 x 3`` block). With the
    camera-frame point ``x_c = R X + t = (x, y, z)`` and ``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]``::

        d(u, v)/d x_c = [[fx/z, s/z, -(fx x + s y)/z^2],
                         [0,    fy/z, -fy y/z^2       ]]
        d x_c / d X = R,    d x_c / d t = I,    d x_c / d r = -[R X]_x R J_r(r)

    where ``J_r`` is the right Jacobian of SO(3),
    ``J_r(r) = I - (1 - cos a)/a^2 [r]_x + (a - sin a)/a^3 [r]_x^2`` with ``a = |r|``.
    The tests compare it with finite differences.

Gauge (the ambiguity BA cannot resolve)
    Images alone fix the scene only up to a similarity (7 degrees of freedom: rotation,
    translation, scale). :func:`adjust` removes them by holding camera ``ref_camera``
    (default 0) fixed (6 parameters) and one coordinate of the translation of a second camera,
    ``scale_camera`` (default: the one farthest from ``ref_camera``): the coordinate ``k`` with the
    largest ``|R_s (C_s - C_ref)|_k``, the direction in which a change of scale about the fixed
    camera would move ``t_s``. The result therefore keeps the input's world frame and scale.
    ``fix_scale=False`` leaves the scale free (the trust region keeps it from drifting).

Solver
    ``method="lm"`` (default): the kit's one sparse bundle adjuster, :func:`course_lib.sfm.lm.solve`
    (Levenberg-Marquardt, the points eliminated by the Schur complement, the small reduced camera
    system solved exactly, robust losses by iteratively reweighted least squares) with the camera
    model :class:`course_lib.sfm.lm.PinholeCamera` (``K`` fixed, 6 parameters) and the gauge above
    as fixed parameters; the same solver runs the "Bundle Adjustment in the Large" problems
    (``python -m course_lib ba``, 9 parameters per camera). ``method="trf"``:
    :func:`scipy.optimize.least_squares` (``x_scale="jac"``, ``lsmr`` on the same analytic sparse
    Jacobian), optionally with its robust losses (``loss="huber"``, ``f_scale`` in pixels). Both
    reach the same minimum (tested).

Who computes what
    :func:`adjust` is the kit's bundle adjuster (the SfM pipeline's, ``python -m course_lib sfm``).
    It projects with the exercise :func:`reprojection_residuals` and takes the Jacobian's columns
    from the exercise :func:`jacobian_sparsity` (:mod:`course_lib.exercises`): in the instructor's
    kit the references below, in the student kit the student's own functions of notebook 05.
    :func:`bundle_adjust` is the reference of the notebook's exercise (it calls :func:`adjust`).

Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from course_lib.conventions import camera_center
from course_lib.exercises import call
from course_lib.sfm import lm
from course_lib.sfm.visibility import observation_list
from course_lib.threads import single_threaded_blas
from course_lib import validate
from course_lib.validate import KitInputError, intrinsics, rotation

__all__ = ["pack_params", "unpack_params", "reprojection_residuals", "jacobian_sparsity", "reprojection_jacobian",
           "BAResult", "bundle_adjust", "adjust", "reprojection_error_stats"]


# ---------------------------------------------------------------------------------------------
# Parameters
# ---------------------------------------------------------------------------------------------


def pack_params(R_cw: np.ndarray, t_cw: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Stack cameras and points into one parameter vector.

    Args:
        R_cw: ``(M, 3, 3)`` rotations. t_cw: ``(M, 3)`` translations. X: ``(N, 3)`` points.

    Returns:
        ``(6M + 3N,)``: per camera its rotation vector and ``t_cw``, then the points.
    """
    R_cw = np.asarray(R_cw, float).reshape(-1, 3, 3)
    rvec = Rotation.from_matrix(R_cw).as_rotvec()
    cams = np.hstack([rvec, np.asarray(t_cw, float).reshape(-1, 3)])
    return np.concatenate([cams.ravel(), np.asarray(X, float).ravel()])


def unpack_params(params: np.ndarray, n_cameras: int, n_points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The inverse of :func:`pack_params`: ``R_cw (M, 3, 3), t_cw (M, 3), X (N, 3)``."""
    params = np.asarray(params, float)
    if params.shape != (6 * n_cameras + 3 * n_points,):
        raise KitInputError(
            f"params has shape {params.shape}: expected (6 * {n_cameras} + 3 * {n_points},) = ({6 * n_cameras + 3 * n_points},)"
        )
    cams = params[: 6 * n_cameras].reshape(n_cameras, 6)
    R = Rotation.from_rotvec(cams[:, :3]).as_matrix().reshape(n_cameras, 3, 3)
    return R, cams[:, 3:].copy(), params[6 * n_cameras :].reshape(n_points, 3).copy()


def _check_indices(n_cameras, n_points, camera_idx, point_idx):
    camera_idx = np.asarray(camera_idx)
    point_idx = np.asarray(point_idx)
    if camera_idx.ndim != 1 or point_idx.shape != camera_idx.shape:
        raise KitInputError(
            f"camera_idx {camera_idx.shape} and point_idx {point_idx.shape} must be 1-D and of the same length (one per observation)"
        )
    if not (np.issubdtype(camera_idx.dtype, np.integer) and np.issubdtype(point_idx.dtype, np.integer)):
        raise KitInputError("camera_idx and point_idx must be integer arrays (indices of cameras and points)")
    if len(camera_idx) and (camera_idx.min() < 0 or camera_idx.max() >= n_cameras):
        raise KitInputError(f"camera_idx has values outside 0..{n_cameras - 1}")
    if len(point_idx) and (point_idx.min() < 0 or point_idx.max() >= n_points):
        raise KitInputError(f"point_idx has values outside 0..{n_points - 1}")
    return camera_idx.astype(np.int64), point_idx.astype(np.int64)


# ---------------------------------------------------------------------------------------------
# Residuals and Jacobian
# ---------------------------------------------------------------------------------------------


def reprojection_residuals(
    params: np.ndarray,
    n_cameras: int,
    n_points: int,
    camera_idx: np.ndarray,
    point_idx: np.ndarray,
    uv: np.ndarray,
    K: np.ndarray,
) -> np.ndarray:
    """The residual vector of bundle adjustment (projected minus observed pixels).

    Args:
        params: ``(6M + 3N,)`` parameters laid out as in :func:`pack_params`.
        n_cameras: M. n_points: N.
        camera_idx: ``(K_obs,)`` int, camera of each observation.
        point_idx: ``(K_obs,)`` int, point of each observation.
        uv: ``(K_obs, 2)`` observed pixels.
        K: ``(3, 3)`` intrinsics.

    Returns:
        ``(2 K_obs,)``: ``[u_0' - u_0, v_0' - v_0, u_1' - u_1, ...]`` in pixels.

    Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
    """
    R, t, X = unpack_params(params, n_cameras, n_points)
    xc = (R[camera_idx] * X[point_idx][:, None, :]).sum(axis=2) + t[camera_idx]
    xh = xc @ np.asarray(K, float).T
    proj = xh[:, :2] / xh[:, 2:3]
    return (proj - np.asarray(uv, float)).ravel()


def jacobian_sparsity(n_cameras: int, n_points: int, camera_idx: np.ndarray, point_idx: np.ndarray) -> sp.csr_matrix:
    """Which entries of the Jacobian can be non-zero.

    Args:
        n_cameras: M. n_points: N.
        camera_idx, point_idx: ``(K_obs,)`` int, camera and point of each observation.

    Returns:
        ``(2 K_obs, 6M + 3N)`` sparse 0/1 matrix: rows ``2k, 2k+1`` have ones in the 6 columns of
        camera ``camera_idx[k]`` and the 3 columns of point ``point_idx[k]``.

    Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
    """
    camera_idx, point_idx = _check_indices(n_cameras, n_points, camera_idx, point_idx)
    cam_cols = 6 * camera_idx[:, None] + np.arange(6)
    pt_cols = 6 * n_cameras + 3 * point_idx[:, None] + np.arange(3)
    cols = np.repeat(np.hstack([cam_cols, pt_cols]), 2, axis=0)  # (2K, 9): rows 2k and 2k+1
    data = np.ones(cols.shape, dtype=np.int8)
    return _csr_from_blocks(data, cols, 6 * n_cameras + 3 * n_points)


def _block_columns(n_cameras: int, n_points: int, camera_idx: np.ndarray, point_idx: np.ndarray) -> np.ndarray:
    """``(2K, 9)`` column indices of the nine non-zeros of each residual row, from the exercise :func:`jacobian_sparsity`.

    Raises:
        KitInputError: the pattern does not have 9 entries in every row (the message says where).
    """
    S = call("jacobian_sparsity", n_cameras, n_points, camera_idx, point_idx)
    S = sp.csr_matrix(S)
    shape = (2 * len(camera_idx), 6 * n_cameras + 3 * n_points)
    if S.shape != shape:
        raise KitInputError(f"jacobian_sparsity returned shape {S.shape}: expected (2K, 6M + 3N) = {shape}")
    S.eliminate_zeros()
    S.sort_indices()
    per_row = np.diff(S.indptr)
    if (per_row != 9).any():
        r = int(np.flatnonzero(per_row != 9)[0])
        raise KitInputError(f"jacobian_sparsity has {per_row[r]} non-zeros in row {r}: every residual row has 9 (the 6 "
                            "columns of its camera and the 3 of its point)")
    return S.indices.reshape(-1, 9).astype(np.int64)


def _csr_from_blocks(data: np.ndarray, cols: np.ndarray, n_cols: int) -> sp.csr_matrix:
    n_rows, per_row = cols.shape
    indptr = np.arange(0, n_rows * per_row + 1, per_row)
    return sp.csr_matrix((data.ravel(), cols.ravel(), indptr), shape=(n_rows, n_cols))


def _jacobian_blocks(params, n_cameras, n_points, camera_idx, point_idx, K):
    """``(K_obs, 2, 9)`` Jacobian blocks: columns 0-2 rotation vector, 3-5 t, 6-8 the point.

    Computed by :meth:`course_lib.sfm.lm.PinholeCamera.project_jacobian` (see the module
    docstring for the formulas).
    """
    cams = params[: 6 * n_cameras].reshape(n_cameras, 6)
    X = params[6 * n_cameras :].reshape(n_points, 3)
    _, J_cam, J_pt = lm.PinholeCamera(K).project_jacobian(cams, X[point_idx], camera_idx)
    return np.concatenate([J_cam, J_pt], axis=2)


def reprojection_jacobian(
    params: np.ndarray,
    n_cameras: int,
    n_points: int,
    camera_idx: np.ndarray,
    point_idx: np.ndarray,
    K: np.ndarray,
) -> sp.csr_matrix:
    """The analytic Jacobian of :func:`reprojection_residuals` with respect to ``params``.

    Args:
        params: ``(6M + 3N,)`` parameters (:func:`pack_params`).
        n_cameras: M. n_points: N.
        camera_idx, point_idx: ``(K_obs,)`` int.
        K: ``(3, 3)`` intrinsics.

    Returns:
        ``(2 K_obs, 6M + 3N)`` ``scipy.sparse.csr_matrix`` with the sparsity of :func:`jacobian_sparsity`.

    Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
    """
    camera_idx, point_idx = _check_indices(n_cameras, n_points, camera_idx, point_idx)
    params = np.asarray(params, float)
    blocks = _jacobian_blocks(params, n_cameras, n_points, camera_idx, point_idx, np.asarray(K, float))
    cols = _block_columns(n_cameras, n_points, camera_idx, point_idx)
    return _csr_from_blocks(blocks.reshape(-1, 9), cols, 6 * n_cameras + 3 * n_points)


def reprojection_error_stats(errors: np.ndarray) -> dict[str, float]:
    """``{"rms", "mean", "median", "max"}`` of per-observation reprojection errors (pixels)."""
    e = np.asarray(errors, float)
    if e.size == 0:
        return {"rms": float("nan"), "mean": float("nan"), "median": float("nan"), "max": float("nan")}
    return {
        "rms": float(np.sqrt(np.mean(e**2))),
        "mean": float(np.mean(e)),
        "median": float(np.median(e)),
        "max": float(np.max(e)),
    }


# ---------------------------------------------------------------------------------------------
# Levenberg-Marquardt with the Schur complement: the kit's one sparse solver, course_lib.sfm.lm
# ---------------------------------------------------------------------------------------------


def _schur_lm(x0_full, free, n_cameras, n_points, obs, K, loss, f_scale, max_iterations, ftol, xtol, record):
    """Levenberg-Marquardt with the points eliminated by the Schur complement (:func:`course_lib.sfm.lm.solve`).

    The camera model is :class:`course_lib.sfm.lm.PinholeCamera` (``K`` fixed, 6 parameters, the
    layout of :func:`pack_params`); the gauge arrives as the ``free`` mask. The same solver runs
    the "Bundle Adjustment in the Large" problems (``python -m course_lib ba``).
    """
    M, N = n_cameras, n_points
    cams0 = x0_full[: 6 * M].reshape(M, 6)
    X0 = x0_full[6 * M :].reshape(N, 3)

    def on_step(it, cams, pts, cost):
        if it > 0:  # adjust records the start itself
            record(np.concatenate([cams.ravel(), pts.ravel()]), it)

    res = lm.solve(
        lm.PinholeCamera(K), cams0, X0, obs.camera_idx, obs.point_idx, obs.uv,
        fixed_cameras=~free[: 6 * M].reshape(M, 6), loss=loss, f_scale=f_scale,
        max_iterations=max_iterations, ftol=ftol, xtol=xtol, callback=on_step,
    )
    p = np.concatenate([res.cameras.ravel(), res.points.ravel()])
    return p, res.iterations, res.n_solves, res.success, res.message


# ---------------------------------------------------------------------------------------------
# The bundle adjuster
# ---------------------------------------------------------------------------------------------


@dataclass
class BAResult:
    """What :func:`adjust` returns.

    Attributes:
        R_cw: ``(M, 3, 3)`` refined rotations. t_cw: ``(M, 3)``. X: ``(N, 3)`` refined points
            (rows of points without observations are returned unchanged).
        point_idx, camera_idx: ``(K_obs,)`` the observations that entered the sum.
        initial_errors, final_errors: ``(K_obs,)`` reprojection error of each observation
            (Euclidean distance in pixels) before and after.
        initial_rms, final_rms: ``sqrt(mean(error**2))`` over the observations (pixels).
        initial_mean, final_mean: ``mean(error)`` (pixels).
        n_iterations: iterations of the solver (``"lm"``: accepted steps; ``"trf"``: Jacobian
            evaluations).
        n_evaluations: residual evaluations (``"lm"``: linear systems solved).
        seconds: wall-clock time of the optimization.
        cost_history: ``0.5 * sum(r**2)`` at the start and after every iteration (with a robust
            loss, still the plain squared error, so the values are comparable).
        iterates: ``[(R_cw, t_cw, X), ...]`` the start and every iteration, if ``keep_iterates``.
        gauge: a sentence describing how the gauge was fixed.
        success, message: from :func:`scipy.optimize.least_squares`.
    """

    R_cw: np.ndarray
    t_cw: np.ndarray
    X: np.ndarray
    point_idx: np.ndarray
    camera_idx: np.ndarray
    initial_errors: np.ndarray
    final_errors: np.ndarray
    n_iterations: int
    n_evaluations: int
    seconds: float
    cost_history: list[float] = field(default_factory=list)
    iterates: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list)
    gauge: str = ""
    success: bool = True
    message: str = ""
    method: str = "lm"

    @property
    def initial_rms(self) -> float:
        return reprojection_error_stats(self.initial_errors)["rms"]

    @property
    def final_rms(self) -> float:
        return reprojection_error_stats(self.final_errors)["rms"]

    @property
    def initial_mean(self) -> float:
        return reprojection_error_stats(self.initial_errors)["mean"]

    @property
    def final_mean(self) -> float:
        return reprojection_error_stats(self.final_errors)["mean"]

    def summary(self) -> str:
        return (
            f"bundle adjustment: {len(self.point_idx)} observations, {self.n_iterations} iterations, "
            f"{self.seconds:.2f} s; reprojection error rms {self.initial_rms:.3f} -> {self.final_rms:.3f} px, "
            f"mean {self.initial_mean:.3f} -> {self.final_mean:.3f} px"
        )


def _check_ba_inputs(K, R_cw, t_cw, X, uv, method, loss, ref_camera):
    """Checked ``K, R_cw, t_cw, X, uv`` as float arrays and the observations of ``uv``."""
    K = intrinsics(K)
    R_cw = np.asarray(R_cw, float)
    if R_cw.ndim != 3 or R_cw.shape[1:] != (3, 3):
        raise KitInputError(f"R_cw has shape {R_cw.shape}: expected (M, 3, 3), one rotation per camera")
    M = R_cw.shape[0]
    for i in range(M):
        rotation(R_cw[i], f"R_cw[{i}]", atol=1e-5)
    t_cw = np.asarray(t_cw, float)
    if t_cw.shape != (M, 3):
        raise KitInputError(f"t_cw has shape {t_cw.shape}: expected ({M}, 3), one translation per camera of R_cw")
    if not np.isfinite(t_cw).all():
        raise KitInputError("t_cw contains NaN or inf")
    X = np.asarray(X, float)
    if X.ndim != 2 or X.shape[1] != 3:
        raise KitInputError(f"X has shape {X.shape}: expected (N, 3), points as rows")
    uv = np.asarray(uv, float)
    if uv.shape != (X.shape[0], M, 2):
        raise KitInputError(
            f"uv has shape {uv.shape}: expected (N, M, 2) = ({X.shape[0]}, {M}, 2), the pixel of point j in image i at [j, i], NaN where unseen"
        )
    validate.choice(method, "method", METHODS)
    validate.choice(loss, "loss", LOSSES)
    if not 0 <= ref_camera < M:
        raise KitInputError(f"ref_camera={ref_camera} is not a camera index (0..{M - 1})")
    return K, R_cw, t_cw, X, _observations(X, uv)


def _observations(X: np.ndarray, uv: np.ndarray):
    """The observations of ``uv (N, M, 2)``: at least one, of points with coordinates, in two cameras or more."""
    obs = observation_list(uv)
    if len(obs) == 0:
        raise KitInputError("uv has no observations (all NaN): nothing to adjust")
    bad_X = ~np.isfinite(X[obs.point_idx]).all(axis=1)
    if bad_X.any():
        j = int(obs.point_idx[bad_X][0])
        raise KitInputError(f"X[{j}] is NaN but the point has observations in uv: triangulate it or drop its observations")
    seen_cams = np.unique(obs.camera_idx)
    if len(seen_cams) < 2:
        raise KitInputError(f"only camera(s) {seen_cams.tolist()} have observations: bundle adjustment needs at least two")
    return obs


def _gauge(R_cw, t_cw, obs, n_points: int, ref_camera: int, scale_camera: int | None, fix_scale: bool):
    """Which of the ``6M + 3N`` parameters are free, and a sentence that says how the gauge was fixed.

    Held fixed: ``ref_camera`` (6 parameters), cameras and points without observations (their
    columns are zero), and with ``fix_scale`` the coordinate of ``scale_camera``'s translation
    that a change of scale about ``ref_camera`` would move most (module docstring).
    """
    M = len(R_cw)
    seen_cams = np.zeros(M, bool)
    seen_cams[obs.camera_idx] = True
    seen_pts = np.zeros(n_points, dtype=bool)
    seen_pts[obs.point_idx] = True
    free = np.concatenate([np.repeat(seen_cams, 6), np.repeat(seen_pts, 3)])
    free[6 * ref_camera : 6 * ref_camera + 6] = False
    if not fix_scale:
        return free, f"camera {ref_camera} fixed, scale free"
    C = np.stack([camera_center(R, t) for R, t in zip(R_cw, t_cw)])
    if scale_camera is None:
        d = np.where(seen_cams, np.linalg.norm(C - C[ref_camera], axis=1), -1.0)
        d[ref_camera] = -1.0
        scale_camera = int(np.argmax(d))
    if not 0 <= scale_camera < M or scale_camera == ref_camera:
        raise KitInputError(f"scale_camera={scale_camera} must be a camera index other than ref_camera={ref_camera}")
    direction = R_cw[scale_camera] @ (C[scale_camera] - C[ref_camera])
    if np.linalg.norm(direction) < 1e-12:
        raise KitInputError(
            f"cameras {ref_camera} and {scale_camera} have the same centre: the scale cannot be fixed by their baseline"
        )
    k = int(np.argmax(np.abs(direction)))
    free[6 * scale_camera + 3 + k] = False
    return free, f"camera {ref_camera} fixed, t_cw[{scale_camera}][{k}] fixed (scale)"


@dataclass
class _Problem:
    """Bundle adjustment over the free parameters: residuals and sparse Jacobian of the reduced vector.

    ``x0_full (6M + 3N,)`` is the start (points without observations filled with 0), ``free`` the
    mask of :func:`_gauge`; a reduced vector ``xr`` holds the free entries only.
    """

    K: np.ndarray
    obs: object  # course_lib.sfm.visibility.Observations
    n_cameras: int
    n_points: int
    x0_full: np.ndarray
    free: np.ndarray

    def __post_init__(self):
        self.free_idx = np.flatnonzero(self.free)
        # Column map full -> reduced (-1 = fixed); the kept pattern is the same at every evaluation.
        col_map = -np.ones(self.free.size, dtype=np.int64)
        col_map[self.free_idx] = np.arange(self.free_idx.size)
        cols_red = col_map[_block_columns(self.n_cameras, self.n_points, self.obs.camera_idx, self.obs.point_idx)]
        self.keep = cols_red >= 0
        self.indptr = np.concatenate([[0], np.cumsum(self.keep.sum(axis=1))])
        self.cols_kept = cols_red[self.keep]

    def full(self, xr: np.ndarray) -> np.ndarray:
        p = self.x0_full.copy()
        p[self.free_idx] = xr
        return p

    def residuals_full(self, p: np.ndarray) -> np.ndarray:
        o = self.obs
        r = call("reprojection_residuals", p, self.n_cameras, self.n_points, o.camera_idx, o.point_idx, o.uv, self.K)
        return r.reshape(-1)

    def residuals(self, xr: np.ndarray) -> np.ndarray:
        return self.residuals_full(self.full(xr))

    def jacobian(self, xr: np.ndarray) -> sp.csr_matrix:
        o = self.obs
        blocks = _jacobian_blocks(self.full(xr), self.n_cameras, self.n_points, o.camera_idx, o.point_idx, self.K)
        blocks = blocks.reshape(-1, 9)
        return sp.csr_matrix((blocks[self.keep], self.cols_kept, self.indptr), shape=(2 * len(o), self.free_idx.size))

    def errors(self, p: np.ndarray) -> np.ndarray:
        """``(K_obs,)`` reprojection error of every observation (pixels) at the full vector ``p``."""
        return np.linalg.norm(self.residuals_full(p).reshape(-1, 2), axis=1)


class _Recorder:
    """The cost after every iteration, and the iterates / the user's callback when asked for."""

    def __init__(self, problem: _Problem, X0: np.ndarray, keep_iterates: bool, callback):
        self.problem, self.X0 = problem, X0
        self.keep_iterates, self.callback = keep_iterates, callback
        self.history: list[float] = []
        self.iterates: list = []

    def __call__(self, p_full: np.ndarray, it: int) -> None:
        r = self.problem.residuals_full(p_full)
        cost = 0.5 * float(r @ r)
        self.history.append(cost)
        if self.keep_iterates or self.callback is not None:
            Rk, tk, Xk = self.unpack(p_full)
            if self.keep_iterates:
                self.iterates.append((Rk, tk, Xk))
            if self.callback is not None:
                self.callback(it, Rk, tk, Xk, cost)

    def unpack(self, p_full: np.ndarray):
        """``R_cw, t_cw, X`` of a full vector, points without observations as given."""
        Rk, tk, Xk = unpack_params(p_full, self.problem.n_cameras, self.problem.n_points)
        unseen = ~self.problem.free[6 * self.problem.n_cameras :].reshape(-1, 3).any(axis=1)
        Xk[unseen] = self.X0[unseen]
        return Rk, tk, Xk


def _solve_trf(problem: _Problem, record: _Recorder, loss, f_scale, max_iterations, ftol, xtol, verbose):
    """:func:`scipy.optimize.least_squares` (trust region, ``lsmr``) on the reduced problem."""
    from scipy.optimize import least_squares

    res = least_squares(
        problem.residuals, problem.x0_full[problem.free_idx], jac=problem.jacobian, method="trf", x_scale="jac",
        loss=loss, f_scale=f_scale, max_nfev=max_iterations, ftol=ftol, xtol=xtol, gtol=1e-10,
        tr_solver="lsmr", verbose=verbose,
        callback=lambda intermediate_result: record(problem.full(intermediate_result.x), len(record.history)),
    )
    n_iter = int(res.njev if res.njev is not None else len(record.history) - 1)
    return problem.full(res.x), n_iter, int(res.nfev), bool(res.success), str(res.message)


#: Solvers of :func:`adjust` and robust losses, with what they are (for the messages).
METHODS = {"lm": "the kit's Schur-complement Levenberg-Marquardt", "trf": "scipy's least_squares"}
LOSSES = {"linear": "plain least squares", "huber": "robust", "soft_l1": "robust", "cauchy": "robust"}


def adjust(K: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray, X: np.ndarray, uv: np.ndarray, *, method: str = "lm",
           loss: str = "linear", f_scale: float = 1.0, max_iterations: int = 100, ftol: float = 1e-8, xtol: float = 1e-10,
           ref_camera: int = 0, scale_camera: int | None = None, fix_scale: bool = True,
           callback: Callable[[int, np.ndarray, np.ndarray, np.ndarray, float], None] | None = None,
           keep_iterates: bool = False, verbose: int = 0) -> BAResult:
    """Refine cameras and points by minimizing the reprojection error over all observations.

    Args:
        K: ``(3, 3)`` intrinsics, shared by all cameras and held fixed.
        R_cw: ``(M, 3, 3)`` initial rotations (camera from world).
        t_cw: ``(M, 3)`` initial translations.
        X: ``(N, 3)`` initial points; rows may be NaN for points with no observation in ``uv``.
        uv: ``(N, M, 2)`` observed pixels, NaN where point j is not seen in image i (only the
            observations you want in the sum: drop outliers first, or use a robust ``loss``).
        method: ``"lm"`` (default): the kit's Levenberg-Marquardt that eliminates the points with
            the Schur complement and solves the small reduced camera system exactly (fast, a few
            iterations); ``"trf"``: :func:`scipy.optimize.least_squares` (trust region, ``lsmr``
            on the sparse Jacobian, ``x_scale="jac"``). Both use the same residuals, analytic
            Jacobian and gauge, and reach the same minimum.
        loss: ``"linear"`` (plain least squares) or a robust loss (``"huber"``, ``"soft_l1"``,
            ``"cauchy"``, defined as in ``least_squares``; ``"lm"`` applies it by reweighting).
        f_scale: pixels at which the robust loss starts to flatten.
        max_iterations: at most this many iterations (``"lm"``: accepted steps; ``"trf"``:
            function evaluations).
        ftol, xtol: stopping tolerances of ``least_squares``.
        ref_camera: the camera held fixed (gauge: position and orientation of the world).
        scale_camera: the camera one of whose translation coordinates is held fixed (gauge: the
            scale); default the camera farthest from ``ref_camera``.
        fix_scale: if False, only ``ref_camera`` is fixed and the scale stays free.
        callback: called as ``callback(iteration, R_cw, t_cw, X, cost)`` at the start (iteration
            0) and after every iteration, e.g. to draw progress.
        keep_iterates: store every iterate in ``BAResult.iterates`` (for a slider over iterations).
        verbose: passed to ``least_squares``.

    Returns:
        :class:`BAResult`.

    Raises:
        KitInputError: shapes do not match, a rotation is not a rotation, an observed point has
            no coordinates, or fewer than two cameras see anything.

    Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
    """
    K, R_cw, t_cw, X, obs = _check_ba_inputs(K, R_cw, t_cw, X, uv, method, loss, ref_camera)
    M, N = R_cw.shape[0], X.shape[0]
    free, gauge = _gauge(R_cw, t_cw, obs, N, ref_camera, scale_camera, fix_scale)
    problem = _Problem(K, obs, M, N, pack_params(R_cw, t_cw, np.where(np.isfinite(X), X, 0.0)), free)
    e0 = problem.errors(problem.x0_full)
    if not np.isfinite(e0).all():
        raise KitInputError("some observed points project to infinity (depth 0 in a camera): check the initial poses and points")
    record = _Recorder(problem, X, keep_iterates, callback)
    record(problem.x0_full, 0)
    t0 = time.perf_counter()
    if method == "lm":
        with single_threaded_blas():
            p_out, n_iter, n_eval, success, message = _schur_lm(
                problem.x0_full, free, M, N, obs, K, loss, f_scale, max_iterations, ftol, xtol, record
            )
    else:
        p_out, n_iter, n_eval, success, message = _solve_trf(problem, record, loss, f_scale, max_iterations, ftol, xtol, verbose)
    seconds = time.perf_counter() - t0
    R_out, t_out, X_out = record.unpack(p_out)
    return BAResult(
        R_cw=R_out, t_cw=t_out, X=X_out, point_idx=obs.point_idx, camera_idx=obs.camera_idx,
        initial_errors=e0, final_errors=problem.errors(p_out), n_iterations=n_iter, n_evaluations=n_eval,
        seconds=seconds, cost_history=record.history, iterates=record.iterates, gauge=gauge,
        success=success, message=message, method=method,
    )


def bundle_adjust(K: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray, X: np.ndarray, uv: np.ndarray, **options) -> BAResult:
    """The reference of the exercise ``bundle_adjust``: :func:`adjust`, with the same arguments.

    Args:
        K, R_cw, t_cw, X, uv: as :func:`adjust`. **options: any keyword of :func:`adjust`.

    Returns:
        :class:`BAResult` (the notebook's exercise returns ``(R_cw, t_cw, X)``).

    Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
    """
    return adjust(K, R_cw, t_cw, X, uv, **options)

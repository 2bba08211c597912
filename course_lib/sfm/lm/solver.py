"""The Levenberg-Marquardt loop of the bundle adjuster: damping, steps, stopping (Ceres' ``Solver``).

:func:`solve` checks the problem (:mod:`course_lib.sfm.lm.problem`), solves one damped linear
system a step (:mod:`course_lib.sfm.lm.linear_solver`) and adapts the damping as Ceres does. The
whole method: :mod:`course_lib.sfm.lm`.

Introduced in ``notebooks/05_bundle_adjustment.ipynb`` ("How does this scale?").
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from course_lib.sfm.lm.cameras import CameraModel
from course_lib.sfm.lm.linear_solver import BlockStructure, normal_equations, schur_solve
from course_lib.sfm.lm.problem import check_problem, robust_loss
from course_lib.threads import single_threaded_blas
from course_lib.validate import KitInputError

__all__ = ["LAM_MIN", "LAM_MAX", "LMResult", "solve"]


#: Bounds of the damping (Ceres: 1 / max_trust_region_radius and 1 / min_trust_region_radius,
#: with a larger floor so that a point seen once keeps a well-conditioned 3x3 block).
LAM_MIN, LAM_MAX = 1e-10, 1e16


@dataclass
class LMResult:
    """What :func:`solve` returns.

    Attributes:
        cameras: ``(M, n)`` refined camera parameters. points: ``(N, 3)`` refined points
            (points without observations unchanged).
        initial_cost, final_cost: ``0.5 * sum(|r|^2)`` over all observations (pixels^2), without
            the robust loss, so runs with and without it compare.
        cost_history: that cost at the start and after every accepted step.
        iterations: accepted steps. n_solves: linear systems solved (accepted + rejected steps).
        seconds: wall-clock time of :func:`solve`.
        success, message: why it stopped.
        shared: ``(p,)`` refined shared parameters (a model with ``n_shared``), else None.
    """

    cameras: np.ndarray
    points: np.ndarray
    initial_cost: float
    final_cost: float
    cost_history: list[float] = field(default_factory=list)
    iterations: int = 0
    n_solves: int = 0
    seconds: float = 0.0
    success: bool = True
    message: str = ""
    shared: np.ndarray | None = None


def solve(
    model: CameraModel,
    cameras: np.ndarray,
    points: np.ndarray,
    cam_idx: np.ndarray,
    pt_idx: np.ndarray,
    obs: np.ndarray,
    *,
    fixed_cameras: np.ndarray | None = None,
    loss: str = "linear",
    f_scale: float = 1.0,
    max_iterations: int = 100,
    ftol: float = 1e-6,
    xtol: float = 1e-10,
    gtol: float = 1e-10,
    lam0: float = 1e-4,
    dense_limit: int = 4000,
    callback: Callable[[int, np.ndarray, np.ndarray, float], None] | None = None,
    shared: np.ndarray | None = None,
    fixed_shared: np.ndarray | None = None,
) -> LMResult:
    """Bundle adjustment by sparse Levenberg-Marquardt with the Schur complement on the points.

    Args:
        model: camera model (:class:`PinholeCamera`, :class:`BALCamera`, or your own with
            ``n_params``, ``project`` and ``project_jacobian``).
        cameras: ``(M, n)`` initial camera parameters.
        points: ``(N, 3)`` initial points (rows without observations may be NaN).
        cam_idx, pt_idx: ``(K,)`` int, camera and point of each observation.
        obs: ``(K, 2)`` observed pixels.
        fixed_cameras: ``(M, n)`` bool, True for parameters held fixed (the gauge); default none.
        loss: ``"linear"`` or a robust loss (``"huber"``, ``"soft_l1"``, ``"cauchy"``, as in
            ``least_squares``), applied by reweighting (IRLS).
        f_scale: pixels where the robust loss starts to flatten.
        max_iterations: at most this many accepted steps.
        ftol: stop when an accepted step lowers the cost by less than ``ftol * cost`` (Ceres'
            ``function_tolerance``; ``1e-4`` is enough for the BAL benchmark).
        xtol: stop when ``|step| < xtol * (xtol + |params|)``.
        gtol: stop when the largest gradient entry is below ``gtol``.
        lam0: initial damping (Ceres: 1 / initial trust region radius 1e4).
        dense_limit: size of the reduced camera system up to which it is solved densely.
        callback: ``callback(iteration, cameras, points, cost)`` at the start and after each
            accepted step (cost without the robust loss).
        shared: ``(p,)`` initial parameters shared by all cameras, for a model with ``n_shared = p``
            (:class:`SimpleRadialCamera`: the focal length and ``k1``); they border the reduced
            camera system (:func:`schur_solve`).
        fixed_shared: ``(p,)`` bool, True for shared parameters held fixed; default none.

    Returns:
        :class:`LMResult`.

    Raises:
        KitInputError: shapes or indices do not fit together, or an observed point projects to
            infinity at the start.

    Introduced in ``notebooks/05_bundle_adjustment.ipynb`` ("How does this scale?").
    """
    with single_threaded_blas():
        return _lm(
            model, cameras, points, cam_idx, pt_idx, obs, fixed_cameras, loss, f_scale,
            max_iterations, ftol, xtol, gtol, lam0, dense_limit, callback, shared, fixed_shared,
        )


class _Iterate:
    """The parameters of one LM iterate and their residuals: cameras ``(M, n)``, points ``(N, 3)``, shared ``(p,)``
    or None, residuals ``r (K, 2)``, IRLS weights ``w (K,)``, the robust ``cost`` and the ``plain`` one."""

    def __init__(self, cams, pts, sh, evaluated):
        self.cams, self.pts, self.sh = cams, pts, sh
        self.r, self.w, self.cost, self.plain = evaluated


class _Problem:
    """What stays fixed while :func:`solve` iterates: the checked, camera-sorted observations and the masks.

    Raises:
        KitInputError: as :func:`solve` says.
    """

    def __init__(self, model, cameras, points, cam_idx, pt_idx, obs, fixed_cameras, loss, f_scale, dense_limit,
                 fixed_shared):
        cameras, points, cam_idx, pt_idx, obs = check_problem(model, cameras, points, cam_idx, pt_idx, obs)
        if loss not in ("linear", "huber", "soft_l1", "cauchy"):
            raise KitInputError(f"loss={loss!r}: expected 'linear', 'huber', 'soft_l1' or 'cauchy'")
        M, n = cameras.shape
        N = len(points)
        free_cam = np.ones((M, n), bool) if fixed_cameras is None else ~np.asarray(fixed_cameras, bool)
        if free_cam.shape != (M, n):
            raise KitInputError(f"fixed_cameras has shape {free_cam.shape}: expected ({M}, {n})")
        self.seen = np.zeros(N, bool)
        self.seen[pt_idx] = True
        order = np.argsort(cam_idx, kind="stable")  # observations camera by camera (see BlockStructure)
        self.cam_idx, self.pt_idx, self.obs = cam_idx[order], pt_idx[order], obs[order]
        self.st = BlockStructure(M, N, n, self.cam_idx, self.pt_idx)
        self.model, self.loss, self.f_scale, self.dense_limit = model, loss, f_scale, dense_limit
        self.cameras, self.points, self.free_cam = cameras, points, free_cam
        self.free_obs = free_cam[self.cam_idx].astype(float)  # (K, n): zero the columns of fixed camera parameters
        n_sh = int(getattr(model, "n_shared", 0))
        self.free_sh = None
        if n_sh:
            self.free_sh = np.ones(n_sh, bool) if fixed_shared is None else ~np.asarray(fixed_shared, bool).reshape(n_sh)

    def start(self, shared) -> _Iterate:
        """The first iterate: the given cameras, the points (0 where unobserved), the shared parameters."""
        n_sh = int(getattr(self.model, "n_shared", 0))
        sh = None
        if n_sh:
            if shared is None or np.shape(shared) != (n_sh,) or not np.isfinite(shared).all():
                raise KitInputError(f"shared has shape {np.shape(shared)}: {type(self.model).__name__} needs its {n_sh} "
                                    f"shared parameters {self.model.shared_names} as finite numbers")
            sh = np.asarray(shared, float).copy()
        cams, pts = self.cameras.copy(), np.where(self.seen[:, None], self.points, 0.0)
        it = _Iterate(cams, pts, sh, self.evaluate(cams, pts, sh))
        if not np.isfinite(it.cost):
            raise KitInputError("some observed points project to infinity at the start (depth 0): check the initial "
                                "cameras and points")
        return it

    def evaluate(self, c, X, shp=None):
        """``(r (K, 2), w (K,), robust cost, plain cost)`` at cameras ``c``, points ``X``, shared ``shp``."""
        m, X_k = self.model, X[self.pt_idx]
        proj = m.project(c, X_k, self.cam_idx) if shp is None else m.project(c, X_k, self.cam_idx, shp)
        r = proj - self.obs
        s = (r**2).sum(axis=1)
        rho, w = robust_loss(self.loss, s, self.f_scale)
        return r, w, 0.5 * float(rho.sum()), 0.5 * float(s.sum())

    def points_out(self, pts: np.ndarray) -> np.ndarray:
        """The points of an iterate, the unobserved ones as given."""
        return np.where(self.seen[:, None], pts, self.points)

    def linearize(self, it: _Iterate):
        """The normal equations at ``it`` and the largest gradient entry."""
        if it.sh is None:
            _, A, B = self.model.project_jacobian(it.cams, it.pts[self.pt_idx], self.cam_idx)
            C = None
        else:
            _, A, B, C = self.model.project_jacobian(it.cams, it.pts[self.pt_idx], self.cam_idx, it.sh)
            C = C * self.free_sh[None, None, :]
        A = A * self.free_obs[:, None, :]
        ne = normal_equations(self.st, it.r, A, B, it.w, C)
        gmax = max(np.abs(ne.g_c).max(initial=0.0), np.abs(ne.g_p[self.seen]).max(initial=0.0),
                   0.0 if C is None else np.abs(ne.g_s).max(initial=0.0))
        return ne, gmax

    def step(self, it: _Iterate, ne, lam: float):
        """The damped step from ``it``: ``(the new iterate, gain ratio, |step|)``."""
        dc, dp, ds, pred = schur_solve(self.st, ne, lam, self.free_cam, self.dense_limit, self.free_sh)
        dp[~self.seen] = 0.0
        c_new, p_new = it.cams + dc, it.pts + dp
        sh_new = None if it.sh is None else it.sh + ds
        new = _Iterate(c_new, p_new, sh_new, self.evaluate(c_new, p_new, sh_new))
        rho = (it.cost - new.cost) / pred if pred > 0 else -1.0
        return new, rho, np.sqrt(np.sum(dc**2) + np.sum(dp**2))


def _lm(model, cameras, points, cam_idx, pt_idx, obs, fixed_cameras, loss, f_scale,
        max_iterations, ftol, xtol, gtol, lam0, dense_limit, callback, shared=None, fixed_shared=None):
    """The body of :func:`solve`: Nielsen's damping around :class:`_Problem`'s steps."""
    t_start = time.perf_counter()
    prob = _Problem(model, cameras, points, cam_idx, pt_idx, obs, fixed_cameras, loss, f_scale, dense_limit, fixed_shared)
    it = prob.start(shared)
    history = [it.plain]
    if callback is not None:
        callback(0, it.cams.copy(), prob.points_out(it.pts), it.plain)
    lam, nu = lam0, 2.0
    n_iter = n_solves = 0
    success, message = False, "the maximum number of iterations is reached"
    while n_iter < max_iterations and not success:
        ne, gmax = prob.linearize(it)
        if gmax < gtol:
            success, message = True, "the gradient is below gtol"
            break
        while True:
            n_solves += 1
            new, rho, step_norm = prob.step(it, ne, lam)
            if np.isfinite(new.cost) and rho > 1e-3:
                break
            lam *= nu
            nu *= 2.0
            if lam > LAM_MAX:
                new = None
                break
        if new is None:
            success, message = True, "no step decreases the cost (converged to the precision available)"
            break
        x_norm = np.sqrt(np.sum(it.cams**2) + np.sum(it.pts**2))
        rel = (it.cost - new.cost) / max(it.cost, 1e-300)
        it = new
        lam = max(lam * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), LAM_MIN)
        nu = 2.0
        n_iter += 1
        history.append(it.plain)
        if callback is not None:
            callback(n_iter, it.cams.copy(), prob.points_out(it.pts), it.plain)
        if rel < ftol:
            success, message = True, f"the relative decrease of the cost is below ftol={ftol:g}"
        elif step_norm < xtol * (xtol + x_norm):
            success, message = True, f"the step is below xtol={xtol:g}"
    return LMResult(cameras=it.cams, points=prob.points_out(it.pts), initial_cost=history[0], final_cost=it.plain,
                    cost_history=history, iterations=n_iter, n_solves=n_solves, seconds=time.perf_counter() - t_start,
                    success=success, message=message, shared=it.sh)

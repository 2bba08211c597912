"""The mapper's bundle adjustments: local around a new image, of the whole model, with the intrinsics where refined (COLMAP's ``AdjustLocalBundle`` / ``AdjustGlobalBundle``).

:class:`MapperBundleAdjustment` is the part of :class:`course_lib.sfm.mapper.IncrementalMapper`
that decides when and over what to bundle-adjust (OpenSfM's ``ShouldBundle``) and writes the
results back into the model. The solvers: :func:`course_lib.sfm.bundle_adjustment.adjust` (the
lesson's) and :func:`course_lib.sfm.lm.solve`.

Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from course_lib.conventions import camera_center
from course_lib.sfm import lm
from course_lib.sfm.bundle_adjustment import adjust
from course_lib.sfm.observations import ObservationManager

__all__ = ["MapperBundleAdjustment", "REFINE_FROM_IMAGES", "CONVERGED_BA_ITERATIONS", "CONVERGED_BA_FTOL"]

#: Registered images from which the BAs of the whole model refine the intrinsics (two views
#: hardly constrain the focal length).
REFINE_FROM_IMAGES = 3
#: Iteration cap and relative cost tolerance of :meth:`MapperBundleAdjustment.converge_intrinsics`: at a narrow
#: field of view the focal length lies along a flat valley of the cost (it trades off against the depths), where
#: the incremental BAs' 5 iterations move it 4-9 % a time and a tolerance of 1e-4 stops early.
CONVERGED_BA_ITERATIONS, CONVERGED_BA_FTOL = 100, 1e-8


class MapperBundleAdjustment(ObservationManager):
    """The bundle-adjustment stages of :class:`~course_lib.sfm.mapper.IncrementalMapper`."""

    def local_images(self, new: int) -> np.ndarray:
        """``(M,)`` bool: image ``new`` and the ``ba_local_num_images - 1`` registered images that share the most points with it."""
        inl = self.inlier
        shared = inl[inl[:, new]].sum(axis=0).astype(float)
        shared[~self.registered] = -1.0
        shared[new] = np.inf
        order = np.argsort(-shared, kind="stable")[: self.opts.ba_local_num_images]
        out = np.zeros(self.M, bool)
        out[order[shared[order] > 0]] = True
        return out

    def adjust_bundle(self, loss: str, f_scale: float, max_iterations: int, ftol: float = 1e-4,
                      points: np.ndarray | None = None, cameras: np.ndarray | None = None) -> dict:
        """Bundle adjustment of the registered cameras and the points (all, or the ``(T,)`` bool ``points``).

        ``cameras`` (``(M,)`` bool): a **local** BA -- only these cameras and the points they see
        move; the other registered cameras that see those points are held fixed (their observations
        count). Without it, the whole model (gauge: the initial pair's first camera and the scale),
        with the focal length and ``k1`` refined where the mapper refines the intrinsics
        (:meth:`_adjust_with_intrinsics`). With no observation to adjust it does nothing and says
        so (``{"skipped": ...}``).
        """
        local = cameras is not None
        pts_mask = self.has_X if points is None else self.has_X & points
        if local:
            pts_mask = pts_mask & (self.inlier & cameras[None, :]).any(axis=1)
        pts = np.flatnonzero(pts_mask)
        cams = np.flatnonzero(self.registered & (self.inlier[pts].any(axis=0) | (cameras if local else self.registered)))
        if len(pts) == 0 or len(cams) < 2:
            return {"skipped": "no points to adjust"}
        if not local and self.refine and self.registered.sum() >= self.refine_from_images:
            return self._adjust_with_intrinsics(cams, pts, loss, f_scale, max_iterations, ftol)
        if not local:
            uv = np.where(self.inlier[np.ix_(pts, cams)][..., None], self.uv[np.ix_(pts, cams)], np.nan)
            res = adjust(self.K, self.R[cams], self.t[cams], self.X[pts], uv, loss=loss, f_scale=f_scale,
                         max_iterations=max_iterations, ref_camera=int(np.flatnonzero(cams == self.ref)[0]),
                         ftol=ftol, xtol=1e-10)
            self.R[cams], self.t[cams], self.X[pts] = res.R_cw, res.t_cw, res.X
            return {"kind": "global", "iterations": res.n_iterations, "rms_before": round(res.initial_rms, 4),
                    "rms_after": round(res.final_rms, 4), "seconds": round(res.seconds, 3), "gauge": res.gauge}
        free = cameras[cams]
        fixed = np.zeros((len(cams), 6), bool)
        fixed[~free] = True
        gauge = f"{int((~free).sum())} cameras around held fixed"
        if (~free).sum() < 2:  # fewer than two fixed cameras leave the gauge (or the scale) free: fix it here
            gauge = self._fix_gauge(cams, fixed)
        res = self._solve(lm.PinholeCamera(self.K), cams, pts, self.uv, fixed, loss, f_scale, max_iterations, ftol)
        return {"kind": "local", "images": [int(i) for i in cams[free]], "iterations": res["iterations"],
                "rms_before": res["rms_before"], "rms_after": res["rms_after"], "seconds": res["seconds"], "gauge": gauge}

    def _refine_points(self, points: np.ndarray) -> int:
        """The ``(T,)`` bool ``points`` refined with every camera held (least squares over their observations in use); how many.

        The BA's solver (:func:`course_lib.sfm.lm.solve`) with no camera free: each point is a 3x3 system of its own,
        solved for all at once (the exercise ``triangulate_nonlinear`` of notebook 03 minimises the same cost through
        ``scipy.optimize.least_squares``: 4x slower on 1 500 points, 0.2 of 1.2 s of ``run_sfm`` on the 5 WPI photos).
        """
        pts = np.flatnonzero(points & self.has_X)
        cams = np.flatnonzero(self.registered)
        if len(pts) == 0 or len(cams) < 2:
            return 0
        self._solve(lm.PinholeCamera(self.K), cams, pts, self.uv, np.ones((len(cams), 6), bool), "linear", 1.0,
                    CONVERGED_BA_ITERATIONS, 1e-10)
        return int(len(pts))

    def _fix_gauge(self, cams: np.ndarray, fixed: np.ndarray) -> str:
        """Hold the gauge of a BA over ``cams``: the reference camera (or the first) and one coordinate of the farthest one."""
        ref = int(np.flatnonzero(cams == self.ref)[0]) if self.ref in cams else int(np.argmax(fixed.all(axis=1))) \
            if fixed.all(axis=1).any() else 0
        fixed[ref] = True
        C = np.stack([camera_center(self.R[i], self.t[i]) for i in cams])
        d = np.linalg.norm(C - C[ref], axis=1)
        d[fixed.all(axis=1)] = -1.0
        s = int(np.argmax(d))
        if d[s] <= 0:
            return f"camera {int(cams[ref])} fixed"
        k = int(np.argmax(np.abs(self.R[cams[s]] @ (C[s] - C[ref]))))
        fixed[s, 3 + k] = True
        return f"camera {int(cams[ref])} fixed, t_cw[{int(cams[s])}][{k}] fixed (scale)"

    def _solve(self, model, cams: np.ndarray, pts: np.ndarray, uv_all: np.ndarray, fixed: np.ndarray, loss: str,
               f_scale: float, max_iterations: int, ftol: float, shared=None, fixed_shared=None) -> dict:
        """:func:`course_lib.sfm.lm.solve` over cameras ``cams`` and points ``pts`` (observations: :attr:`inlier`); the results written back."""
        obs = self.inlier[np.ix_(pts, cams)]
        pi, ci = np.nonzero(obs)
        uv = uv_all[pts[pi], cams[ci]]
        params = np.hstack([Rotation.from_matrix(self.R[cams]).as_rotvec(), self.t[cams]])
        kw = {} if shared is None else {"shared": shared, "fixed_shared": fixed_shared}
        res = lm.solve(model, params, self.X[pts], ci, pi, uv, fixed_cameras=fixed, loss=loss, f_scale=f_scale,
                       max_iterations=max_iterations, ftol=ftol, xtol=1e-10, **kw)
        self.R[cams] = Rotation.from_rotvec(res.cameras[:, :3]).as_matrix()
        self.t[cams] = res.cameras[:, 3:]
        self.X[pts] = res.points
        n = max(len(pi), 1)
        return {"iterations": res.iterations, "rms_before": round(float(np.sqrt(2 * res.initial_cost / n)), 4),
                "rms_after": round(float(np.sqrt(2 * res.final_cost / n)), 4), "seconds": round(res.seconds, 3),
                "shared": res.shared}

    def _adjust_with_intrinsics(self, cams, pts, loss, f_scale, max_iterations, ftol) -> dict:
        """A BA of the whole model that also refines the focal length and ``k1`` (:class:`~course_lib.sfm.lm.SimpleRadialCamera`).

        It works on the photos' own pixels. ``k1`` is held until the model holds
        ``refine_k1_from_images`` images (a few views hardly fix it, and a wild ``k1`` bends the model), and
        where the field of view is so narrow that ``k1 = 0.1`` would move the image's corners by less than
        ``min_k1_effect_px`` (there ``k1`` trades off against the focal length instead of being measured; it is
        set to 0). A
        result outside the sane range (focal length more than ``max_focal_change`` from the prior,
        ``|k1| > max_k1``) is rejected: the cameras and points go back and the BA is redone with ``k1``
        held, and where that is rejected too, with the intrinsics held.
        """
        o = self.opts
        saved = self.R.copy(), self.t.copy(), self.X.copy()
        fixed = np.zeros((len(cams), 6), bool)
        gauge = self._fix_gauge(cams, fixed)
        model = lm.SimpleRadialCamera(self.K[:2, 2])
        f0 = self.K0[0, 0]
        W, H = self.image_size
        r = np.hypot(max(self.K[0, 2], W - 1 - self.K[0, 2]), max(self.K[1, 2], H - 1 - self.K[1, 2])) / self.K[0, 0]
        narrow = 0.1 * r**3 * self.K[0, 0] < o.min_k1_effect_px
        hold_k1 = self.registered.sum() < o.refine_k1_from_images or narrow
        k1_start = 0.0 if narrow else self.k1  # a k1 that cannot be measured is none
        while True:
            res = self._solve(model, cams, pts, self.uv_raw, fixed, loss, f_scale, max_iterations, ftol,
                              shared=np.array([self.K[0, 0], k1_start]), fixed_shared=np.array([False, hold_k1]))
            f, k1 = (float(v) for v in res.pop("shared"))
            ok = np.isfinite([f, k1]).all() and f0 / o.max_focal_change <= f <= f0 * o.max_focal_change and abs(k1) <= o.max_k1
            entry = {"images": int(self.registered.sum()), "f": round(f, 3), "k1": round(k1, 6), "accepted": bool(ok),
                     **({"k1_held": True} if hold_k1 else {})}
            self.intrinsics_log.append(entry)
            if ok or hold_k1:
                break
            self.R[:], self.t[:], self.X[:] = saved
            hold_k1 = True
        if not ok:
            self.R[:], self.t[:], self.X[:] = saved
            self.refine = False
            out = self.adjust_bundle(loss, f_scale, max_iterations, ftol, points=np.isin(np.arange(self.T), pts))
            self.refine = True
            out["intrinsics"] = {**entry, "note": "rejected: outside the sane range; held"}
            return out
        K = self.K.copy()
        K[0, 0] = K[1, 1] = f
        self.set_intrinsics(K, k1)
        return {"kind": "global", **res, "gauge": gauge, "intrinsics": entry}

    def converge_intrinsics(self) -> dict:
        """A BA of the whole model with the intrinsics, run until it converges, then filtering: the focal length the
        registered images hold (:data:`CONVERGED_BA_ITERATIONS`, :data:`CONVERGED_BA_FTOL`; the incremental BAs stop
        after ``ba_max_iterations`` and move it only part of the way).

        Returns:
            The intrinsics' row of the BA (``f``, ``k1``, ``accepted``: within ``max_focal_change`` of the prior, as
            :meth:`_adjust_with_intrinsics` checks), with its ``seconds``; ``{}`` where the intrinsics are not refined
            (yet).
        """
        o = self.opts
        out = self.adjust_bundle(o.ba_loss, o.ba_f_scale, CONVERGED_BA_ITERATIONS, ftol=CONVERGED_BA_FTOL)
        if "intrinsics" not in out:
            return {}
        self.filter_points()
        return {**out["intrinsics"], "seconds": out.get("seconds")}

    def should_bundle(self) -> bool:
        """Whether the whole model is due a bundle adjustment (OpenSfM's ``ShouldBundle``): up to 6 images
        always, then when it has grown by ``ba_images_ratio`` since the last one."""
        n = int(self.registered.sum())
        return self.opts.bundle_adjustment == "incremental" and (n <= 6 or n >= self.opts.ba_images_ratio * self.n_at_last_ba)

    def _adjust_and_filter(self, stage: dict, global_ba: bool, new: int | None = None) -> None:
        """A BA of the whole model (``global_ba``) or a local one around image ``new``, then filtering; numbers into ``stage``."""
        o = self.opts
        if global_ba:
            self.n_at_last_ba = int(self.registered.sum())
            stage["ba"] = self.adjust_bundle(o.ba_loss, o.ba_f_scale, o.ba_max_iterations)
            stage["filter"] = self.filter_points()
            stage["reprojection_after_ba"] = self.observation_stats()
            return
        local = self.local_images(new)
        points = (self.inlier & local[None, :]).any(axis=1)
        stage["ba"] = self.adjust_bundle(o.ba_loss, o.ba_f_scale, o.ba_local_max_iterations, cameras=local)
        stage["filter"] = self.filter_points(points=points)
        stage["reprojection_after_ba"] = self.observation_stats(points)

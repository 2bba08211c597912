"""The observations of a growing model: which are in use, their reprojection errors, and filtering them (COLMAP's ``ObservationManager``).

:class:`ObservationManager` is the part of :class:`course_lib.sfm.mapper.IncrementalMapper` that
reads and filters the model's observations. It works on the mapper's arrays, indexed by track ``j``
and image ``i``: ``uv_raw``/``uv`` ``(T, M, 2)`` (the photos' pixels / undistorted), ``candidate``
``(T, M)`` (observation not rejected), ``registered`` ``(M,)``, ``R``, ``t`` (``cam_from_world``),
``X`` ``(T, 3)`` (NaN where a track has no point), ``K``, ``k1`` and ``opts``
(:class:`~course_lib.sfm.mapper_options.MapperOptions`).

Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
"""

from __future__ import annotations

import numpy as np

from course_lib.conventions import camera_center, projection_matrix
from course_lib.data.camera import undistort_pixels
from course_lib.sfm.reconstruction import error_summary, triangulation_angles_deg

__all__ = ["ObservationManager"]


class ObservationManager:
    """The model's observations: in use, their errors, filtering (the base of :class:`~course_lib.sfm.mapper.IncrementalMapper`)."""

    def set_intrinsics(self, K: np.ndarray, k1: float) -> None:
        """Use ``K`` and the radial term ``k1``: :attr:`uv` becomes the undistorted pixels of the tracks."""
        self.K, self.k1 = np.asarray(K, float), float(k1)
        self._two_view: dict = {}  # the pairs' matches and calibrated poses on these pixels (two_view)
        self.uv = undistort_pixels(self.uv_raw, self.K, self.k1)

    def undistort(self, x: np.ndarray) -> np.ndarray:
        """Pixels ``(N, 2)`` as the photos show them -> where the pinhole :attr:`K` sees them."""
        return undistort_pixels(x, self.K, self.k1)

    @property
    def has_X(self) -> np.ndarray:
        """``(T,)`` tracks with a point."""
        return np.isfinite(self.X).all(axis=1)

    @property
    def inlier(self) -> np.ndarray:
        """``(T, M)`` observations in use: candidate, registered image, triangulated point."""
        return self.candidate & self.registered[None, :] & self.has_X[:, None]

    def centers(self) -> np.ndarray:
        """``(M, 3)`` camera centres, NaN where unregistered."""
        C = np.full((self.M, 3), np.nan)
        for i in np.flatnonzero(self.registered):
            C[i] = camera_center(self.R[i], self.t[i])
        return C

    def errors(self, points: np.ndarray | None = None) -> np.ndarray:
        """``(T, M)`` reprojection errors of the observations in use (of the ``(T,)`` bool ``points`` only), NaN elsewhere.

        Computed for the observations only (one batched projection), not for the whole ``(T, M)`` grid.
        """
        use = self.inlier if points is None else self.inlier & points[:, None]
        pi, ci = np.nonzero(use)
        E = np.full((self.T, self.M), np.nan)
        if len(pi):
            xc = np.einsum("kij,kj->ki", self.R[ci], self.X[pi]) + self.t[ci]
            xh = xc @ self.K.T
            with np.errstate(divide="ignore", invalid="ignore"):
                e = np.linalg.norm(xh[:, :2] / xh[:, 2:3] - self.uv[pi, ci], axis=1)
            e[~(xc[:, 2] > 0)] = np.inf
            E[pi, ci] = e
        return E

    def observation_stats(self, points: np.ndarray | None = None) -> dict[str, float]:
        return error_summary(self.errors(points))

    def _P(self, i: int) -> np.ndarray:
        return projection_matrix(self.K, self.R[i], self.t[i])

    def filter_points(self, max_reproj_px: float | None = None, min_angle_deg: float | None = None,
                      points: np.ndarray | None = None) -> dict:
        """Drop observations that reproject badly, then points with < 2 observations or a small angle.

        ``points``: the ``(T,)`` bool points to check (default all; after a local BA, its points).
        """
        thr = self.opts.max_reproj_px if max_reproj_px is None else max_reproj_px
        angle = self.opts.min_angle_deg if min_angle_deg is None else min_angle_deg
        sel = self.has_X if points is None else self.has_X & points
        js = np.flatnonzero(sel)
        bad = self.inlier[js] & ~(self.errors(sel)[js] <= thr)
        self.candidate[js] &= ~bad
        inl = self.inlier[js]
        ang = triangulation_angles_deg(self.X[js], np.nan_to_num(self.centers()), inl)
        drop = (inl.sum(axis=1) < 2) | (ang < angle)
        self.X[js[drop]] = np.nan
        return {"observations_removed": int(bad.sum()), "points_removed": int(drop.sum())}

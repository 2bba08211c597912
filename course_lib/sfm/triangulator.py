"""Triangulating the tracks of a growing model, checking and re-triangulating them (COLMAP's ``IncrementalTriangulator``).

:class:`IncrementalTriangulator` is the part of :class:`course_lib.sfm.mapper.IncrementalMapper`
that gives tracks their points: from a newly registered image and every registered partner, again
after the model has moved (:meth:`IncrementalTriangulator.retriangulate`). The triangulation itself is the exercise of notebook
03, called through :func:`course_lib.exercises.call`.

Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
"""

from __future__ import annotations

import numpy as np

from course_lib.exercises import call, caller
from course_lib.sfm.observations import ObservationManager
from course_lib.sfm.reconstruction import reprojection_error_matrix, triangulation_angles_deg

__all__ = ["IncrementalTriangulator"]


class IncrementalTriangulator(ObservationManager):
    """The triangulation stages of :class:`~course_lib.sfm.mapper.IncrementalMapper`."""

    def triangulate_image(self, new: int) -> int:
        """Triangulate the tracks image ``new`` shares with every registered image (widest baseline first); new points."""
        regs = [k for k in np.flatnonzero(self.registered) if k != new]
        todo = ~self.has_X & self.candidate[:, new]
        C = self.centers()
        X0 = np.full((self.T, 3), np.nan)
        # each track is triangulated from the new image and its farthest registered partner
        regs.sort(key=lambda k: -np.linalg.norm(C[k] - C[new]))
        for k in regs:
            js = np.flatnonzero(todo & self.candidate[:, k] & ~np.isfinite(X0).all(axis=1))
            if len(js):
                X0[js] = call("triangulate_linear", self._P(new), self._P(k), self.uv[js, new], self.uv[js, k])
        js = np.flatnonzero(np.isfinite(X0).all(axis=1))
        if len(js) == 0:
            return 0
        # the non-linear refinement is left to the bundle adjustment that follows, where there is one
        refine = caller("triangulate_nonlinear") if self.opts.bundle_adjustment != "incremental" else None
        return self._accept(js, X0[js], refine)

    def _accept(self, js: np.ndarray, X0: np.ndarray, refine=None) -> int:
        """Check linearly triangulated tracks ``js`` (``X0 (len(js), 3)``) against all registered views, refine, keep the good ones.

        Observations that reproject farther than ``max_reproj_px`` from the linear estimate are
        dropped, the point is refined non-linearly over the remaining ones (where a refinement
        ``refine``, the exercise ``triangulate_nonlinear`` of notebook 03, is given), checked
        again, and kept if at least two observations in front of their cameras remain and its
        triangulation angle is at least ``min_angle_deg``. Dropped observations are rejected for good.
        """
        o = self.opts
        regs = np.flatnonzero(self.registered)
        good = np.isfinite(X0).all(axis=1)
        js, X0 = js[good], X0[good]
        if len(js) == 0:
            return 0
        mask = self.candidate[js][:, regs]
        uv = np.where(mask[..., None], self.uv[js][:, regs], np.nan)
        E = reprojection_error_matrix(self.K, self.R[regs], self.t[regs], X0, uv)
        uv[~(E <= o.max_reproj_px)] = np.nan
        two = np.isfinite(uv).all(axis=2).sum(axis=1) >= 2
        X = X0.copy()
        if two.any() and refine is not None:
            X[two] = refine(self.K, self.R[regs], self.t[regs], uv[two], X0[two])
        E = reprojection_error_matrix(self.K, self.R[regs], self.t[regs], X, uv)
        ok_obs = E <= o.max_reproj_px
        ang = triangulation_angles_deg(X, self.centers()[regs], ok_obs)
        ok = (ok_obs.sum(axis=1) >= 2) & (ang >= o.min_angle_deg) & np.isfinite(X).all(axis=1)
        sub = self.candidate[js]
        sub[:, regs] &= ~(mask & ~ok_obs)
        self.candidate[js] = sub
        self.X[js[ok]] = X[ok]
        return int(ok.sum())

    def retriangulate(self) -> dict:
        """Triangulate tracks that failed earlier, and give back rejected observations that fit now.

        * **Track completion**: an observation of a triangulated point that was rejected earlier
          (it reprojected badly from a point or camera that has moved since) is used again if it
          now reprojects within ``max_reproj_px``.
        * **Re-triangulation**: a track without a point that is seen in two or more registered
          images gets all its observations back and is triangulated again (linear, from its two
          observing cameras farthest apart, checked as in :meth:`triangulate_image`; the next BA
          refines it): early on, its cameras may have been poorly placed.
        """
        regs = np.flatnonzero(self.registered)
        seen = self.visible & self.registered[None, :]
        rejected = seen & ~self.candidate & self.has_X[:, None]
        E = reprojection_error_matrix(self.K, self.R, self.t, self.X, np.where(rejected[..., None], self.uv, np.nan))
        back = rejected & (E <= self.opts.max_reproj_px)
        self.candidate |= back
        todo = ~self.has_X & (seen.sum(axis=1) >= 2)
        self.candidate[np.ix_(todo, regs)] |= self.visible[np.ix_(todo, regs)]
        C = self.centers()
        X0 = np.full((self.T, 3), np.nan)
        pairs = sorted(((a, b) for ia, a in enumerate(regs) for b in regs[ia + 1:]), key=lambda ab: -np.linalg.norm(C[ab[0]] - C[ab[1]]))
        for a, b in pairs:  # widest baseline first
            js = np.flatnonzero(todo & seen[:, a] & seen[:, b] & ~np.isfinite(X0).all(axis=1))
            if len(js):
                X0[js] = call("triangulate_linear", self._P(a), self._P(b), self.uv[js, a], self.uv[js, b])
        js = np.flatnonzero(np.isfinite(X0).all(axis=1))
        n_new = self._accept(js, X0[js]) if len(js) else 0
        return {"observations_back": int(back.sum()), "tracks_tried": int(todo.sum()), "points_new": int(n_new)}

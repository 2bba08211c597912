"""Registering the next image of a growing model: which image next, PnP, and the structure-less fallback (COLMAP's ``RegisterNextImage``).

:class:`ImageRegistration` is the part of :class:`course_lib.sfm.mapper.IncrementalMapper` that
adds a camera to the model; :func:`spread_score` ranks the candidates as COLMAP's visibility
pyramid does. It uses the mapper's model (:class:`~course_lib.sfm.observations.ObservationManager`)
and its verified pairs (``pairs``, :meth:`~course_lib.sfm.mapper.IncrementalMapper.two_view`).

Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
"""

from __future__ import annotations

import numpy as np

from course_lib.conventions import invert_pose, rotation_angle_deg
from course_lib.exercises import call
from course_lib.sfm.observations import ObservationManager
from course_lib.sfm.reconstruction import reprojection_error_matrix
from course_lib.sfm.structureless import pair_sampson, pose_from_partners, refine_on_partners
from course_lib.validate import KitInputError

__all__ = ["ImageRegistration", "spread_score"]


def spread_score(uv: np.ndarray, image_size: tuple[int, int], levels: int = 6) -> int:
    """How many and how spread out the pixels ``uv (N, 2)`` are: COLMAP's visibility pyramid score.

    At level ``l = 1..levels`` the image is cut into ``2^l x 2^l`` cells; every occupied cell adds
    ``2^l``. Many points in one corner score less than fewer points over the whole image, which
    makes a better-conditioned PnP.
    """
    uv = np.asarray(uv, float).reshape(-1, 2)
    if len(uv) == 0:
        return 0
    W, H = image_size
    score = 0
    for lev in range(1, levels + 1):
        n = 2 ** lev
        cu = np.clip((uv[:, 0] / W * n).astype(int), 0, n - 1)
        cv = np.clip((uv[:, 1] / H * n).astype(int), 0, n - 1)
        score += n * len(np.unique(cu * n + cv))
    return int(score)


class ImageRegistration(ObservationManager):
    """The registration stages of :class:`~course_lib.sfm.mapper.IncrementalMapper`."""

    def next_images(self, skip=()) -> list[tuple[int, int]]:
        """``[(image, correspondences), ...]`` of the unregistered images not in ``skip``, best first.

        Ranked by :func:`spread_score` of the pixels of their 2D-3D correspondences (features whose
        track has a point), ties by image number. Images of earlier models are among them: a model
        that reaches them can be merged with that model (:meth:`merge`).
        """
        todo = [i for i in range(self.M) if not (self.registered[i] or i in skip)]
        has_X = self.has_X
        rows = []
        for i in todo:
            js = np.flatnonzero(has_X & self.candidate[:, i])
            rows.append((spread_score(self.uv[js, i], self.image_size), len(js), i))
        rows.sort(key=lambda r: (-r[0], -r[1], r[2]))
        return [(i, n) for _, n, i in rows]

    def register_next_image(self, i: int) -> tuple[dict | None, str | None]:
        """PnP RANSAC + non-linear PnP for image ``i``: ``(info, None)``, or ``(None, why it failed)``.

        Where PnP fails and ``structure_less_fallback`` is on, the image is registered from its
        matches with the registered images alone (:meth:`register_from_pairs`), as COLMAP does.
        """
        info, why = self._register_pnp(i)
        if info is not None or not self.opts.structure_less_fallback:
            return info, why
        info, why_pairs = self.register_from_pairs(i)
        return (info, None) if info is not None else (None, f"{why}; from its matches alone: {why_pairs}")

    def register_from_pairs(self, i: int) -> tuple[dict | None, str | None]:
        """Register image ``i`` from its verified matches with registered images, without 3-D points (COLMAP's structure-less fallback).

        The five-point pose of ``i`` relative to each registered partner gives its rotation and
        the direction of its centre; two or more partners that agree on the rotation and see it
        from different places fix the centre (:func:`course_lib.sfm.structureless.pose_from_partners`),
        which is then refined on all their matches
        (:func:`course_lib.sfm.structureless.refine_on_partners`). The pose must explain
        ``min_pnp_inliers`` of the matches within ``f_threshold_px`` (Sampson distance) and
        ``min_pnp_inlier_ratio`` of them. The two-view tracks it shares with the partners can then
        be triangulated (:meth:`triangulate_image`).

        Returns:
            ``(info, None)`` as :meth:`register_next_image` (``correspondences``: the 2D-2D matches,
            ``pnp_inliers``: those the pose explains, ``structure_less``: the partners), or ``(None, why)``.
        """
        o = self.opts
        rows = []
        for k in np.flatnonzero(self.registered):
            key = (min(i, k), max(i, k))
            if key not in self.pairs:
                continue
            x_a, x_b, choice, inl = self.two_view(*key)
            if choice is None:
                continue
            R_ki, t_ki = (choice.R_cw, choice.t_cw) if k == key[0] else invert_pose(choice.R_cw, choice.t_cw)
            x_k, x_i = (x_a, x_b) if k == key[0] else (x_b, x_a)
            rows.append((int(k), R_ki, t_ki, x_k, x_i, int(inl.sum())))
        if len(rows) < 2:
            return None, f"{len(rows)} registered image(s) with verified matches, two are needed"
        ks = [r[0] for r in rows]
        found, why = pose_from_partners(self.R[ks], self.t[ks], np.stack([r[1] for r in rows]), np.stack([r[2] for r in rows]),
                                        np.array([r[5] for r in rows], float))
        if found is None:
            return None, why
        R, t, used = found
        partners = [(self.R[r[0]], self.t[r[0]], r[3], r[4]) for r, u in zip(rows, used) if u]
        R, t = refine_on_partners(self.K, R, t, partners)
        n_all = sum(len(p[2]) for p in partners)
        n_in = sum(int((pair_sampson(self.K, *p[:2], R, t, *p[2:]) <= o.f_threshold_px).sum()) for p in partners)
        if n_in < o.min_pnp_inliers or n_in < o.min_pnp_inlier_ratio * n_all:
            return None, (f"the pose from {len(partners)} partners explains {n_in} of their {n_all} matches within "
                          f"{o.f_threshold_px} px, need {o.min_pnp_inliers} and {o.min_pnp_inlier_ratio:.0%}")
        self.R[i], self.t[i] = R, t
        self.registered[i] = True
        return {"correspondences": n_all, "pnp_inliers": n_in, "ransac_iterations": 0,
                "structure_less": [self.names[r[0]] for r, u in zip(rows, used) if u]}, None

    def _register_pnp(self, i: int) -> tuple[dict | None, str | None]:
        """PnP RANSAC + non-linear PnP on image ``i``'s 2D-3D correspondences: ``(info, None)`` or ``(None, why)``."""
        o = self.opts
        js = np.flatnonzero(self.has_X & self.candidate[:, i])
        need = max(6, o.min_pnp_inliers)
        if len(js) < need:
            return None, f"too few 2D-3D matches: {len(js)} of its features see triangulated points, PnP needs {need}"
        try:
            res = call("pnp_ransac", self.X[js], self.uv[js, i], self.K, self.rng, threshold_px=o.pnp_threshold_px)
        except KitInputError as exc:
            return None, f"PnP RANSAC failed on {len(js)} 2D-3D matches ({exc})"
        inl = np.asarray(res.inliers, bool)
        if inl.sum() < o.min_pnp_inliers:
            return None, (f"too few PnP inliers: {int(inl.sum())} of {len(js)} 2D-3D matches within {o.pnp_threshold_px} px, "
                          f"need {o.min_pnp_inliers}")
        if inl.sum() < o.min_pnp_inlier_ratio * len(js):
            return None, (f"too small a share of PnP inliers: {int(inl.sum())} of {len(js)} 2D-3D matches within "
                          f"{o.pnp_threshold_px} px, need {o.min_pnp_inlier_ratio:.0%} (look-alike texture?)")
        X, uv = self.X[js], self.uv[js, i]
        R, t = call("pnp_nonlinear", X[inl], uv[inl], self.K, res.R_cw, res.t_cw)
        R, t, inl, second = self._second_opinion(X, uv, inl, R, t)
        R, t, inl, retried = self._retry_if_unusual(X, uv, inl, R, t)
        self.R[i], self.t[i] = R, t
        self.registered[i] = True
        self.candidate[js[~inl], i] = False
        median = _inlier_median(X, uv, inl, self.K, R, t)
        self.pnp_medians.append(median)
        return {"correspondences": int(len(js)), "pnp_inliers": int(inl.sum()), "ransac_iterations": int(res.n_iters),
                "pnp_median_px": round(median, 3), **second, **retried}, None

    def _pose_fit(self, X: np.ndarray, uv: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, float]:
        """A pose on all ``(N,)`` 2D-3D matches: ``(inliers, cost)``, its errors within ``pnp_threshold_px`` and its
        MSAC cost, the squared reprojection errors truncated at that threshold.

        Lower cost is better. Unlike the inlier count, it tells apart two poses that explain the same
        matches within the threshold but one of them much more closely (the two basins of a narrow
        field of view: 141 and 140 inliers, median errors 0.45 and 1.17 px).
        """
        thr = self.opts.pnp_threshold_px
        e = _errors(X, uv, self.K, R, t)
        return e < thr, float(np.sum(np.minimum(e, thr) ** 2))

    def _retry_if_unusual(self, X: np.ndarray, uv: np.ndarray, inl: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple:
        """Where the pose fits its inliers unusually badly, PnP RANSAC again (fresh draws); the lowest cost of :meth:`_pose_fit` kept.

        At a narrow field of view a rotation and a sideways shift of the camera move the image
        alike, and PnP has two nearly equal poses (the rendered ring at 3x the guessed focal length:
        two poses 15 degrees apart with 141 and 140 of 158 inliers); RANSAC's draws decide which
        one it returns, and a non-linear refinement from either stays there. The wrong one shows as
        a median error of its inliers well above the model's other registrations' (1.17 px against
        0.45-0.74). So where the median is over ``pnp_retry_factor`` times the median of this
        model's earlier registrations (three or more), up to ``pnp_retries`` more RANSAC runs (until the
        best pose's median is usual), each refined, compete with the pose on all ``(N,)`` matches
        (``info``: ``pnp_retries`` run, and ``retry_turn_deg`` where another pose won).
        """
        o = self.opts
        done = self.pnp_medians
        if o.pnp_retries <= 0 or len(done) < 3:
            return R, t, inl, {}
        usual = o.pnp_retry_factor * float(np.median(done))
        median = _inlier_median(X, uv, inl, self.K, R, t)
        if median <= usual:
            return R, t, inl, {}
        best, cost, n = (R, t, inl), self._pose_fit(X, uv, R, t)[1], 0
        while n < o.pnp_retries and median > usual:
            n += 1
            try:
                res = call("pnp_ransac", X, uv, self.K, self.rng, threshold_px=o.pnp_threshold_px)
            except KitInputError:
                continue
            keep = np.asarray(res.inliers, bool)
            R2, t2 = call("pnp_nonlinear", X[keep], uv[keep], self.K, res.R_cw, res.t_cw)
            inl2, c2 = self._pose_fit(X, uv, R2, t2)
            if c2 < cost:
                best, cost, median = (R2, t2, inl2), c2, _inlier_median(X, uv, inl2, self.K, R2, t2)
        info = {"pnp_retries": n}
        turn = rotation_angle_deg(best[0], R)
        if turn >= 0.5:
            info["retry_turn_deg"] = round(float(turn), 2)
        return (*best, info)

    def _second_opinion(self, X: np.ndarray, uv: np.ndarray, inl: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple:
        """The pose of PnP RANSAC against a second start, the one of lower robust error kept: ``(R, t, inliers, info)``.

        A narrow field of view over a nearly flat part of the scene makes two poses explain the
        points almost equally (the flip of a shallow scene: the rendered ring at twice the guessed
        focal length registered one view 29 degrees off at a median error of 0.96 px, where the right
        pose has a third of it), and RANSAC's linear start may land in the wrong one. OpenCV's
        SQPnP (a global minimum over all rotations) on the inliers gives the second start; both are
        refined (non-linear PnP), scored on all ``(N,)`` 2D-3D matches (inliers within
        ``pnp_threshold_px``, then the truncated error), and the better kept (``info`` says where it was
        the second one).
        """
        import cv2

        ok, rvec, tvec = cv2.solvePnP(X[inl], uv[inl], self.K, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            return R, t, inl, {}
        R2, t2 = call("pnp_nonlinear", X[inl], uv[inl], self.K, cv2.Rodrigues(rvec)[0], tvec.ravel())
        (inl1, cost1), (inl2, cost2) = self._pose_fit(X, uv, R, t), self._pose_fit(X, uv, R2, t2)
        if (int(inl2.sum()), -cost2) <= (int(inl1.sum()), -cost1):
            return R, t, inl, {}
        turn = rotation_angle_deg(R2, R)
        info = {"second_start_deg": round(float(turn), 2)} if turn >= 0.5 else {}
        return R2, t2, inl2, info


def _inlier_median(X: np.ndarray, uv: np.ndarray, inl: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> float:
    """The median reprojection error (pixels) of a pose's inliers ``inl (N,)`` among ``(N,)`` 2D-3D matches."""
    return float(np.median(_errors(X[inl], uv[inl], K, R, t)))


def _errors(X: np.ndarray, uv: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(N,)`` reprojection errors (pixels) of ``(N, 3)`` points seen at ``(N, 2)`` pixels by one camera.

    Points behind the camera get ``inf``. (Not the PnP module's own: that one holds exercises, and this module
    ships with notebook 05.)
    """
    return reprojection_error_matrix(K, R[None], t[None], X, uv[:, None])[:, 0]

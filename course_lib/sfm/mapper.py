"""The incremental mapper: one object that holds a growing model, whose methods are the stages.

Shaped like COLMAP's ``IncrementalMapper`` (``src/colmap/sfm/incremental_mapper.h``) and
OpenSfM's ``reconstruction.py``. The stage methods change the model and return numbers;
:func:`course_lib.sfm.pipeline.run_sfm` is the controller (COLMAP's ``IncrementalMapperController``):
it calls them in this order, times them, and records their numbers and printed lines in a
:class:`~course_lib.sfm.mapper_report.MapperReport`:

1. :meth:`IncrementalMapper.find_initial_pair` yields candidate pairs in the order they are
   tried: first the images with the most verified correspondences to other images (summed over
   their verified pairs: the part of the match graph that can grow), then, for each, its partners
   ranked by the number of points triangulated in front of both cameras with an angle of at least
   ``init_min_angle_deg`` (a long baseline). The relative pose is the calibrated one: the
   five-point essential matrix, refined (:func:`course_lib.sfm.initial_pair.calibrated_pose`).
   Pairs that a homography explains (pure rotation, a plane) or whose matches do not move
   (identical photos) are named and skipped (:func:`~course_lib.sfm.initial_pair.pair_degeneracy`);
   pairs of a plane with enough structure off it (``"mostly planar"``) are tried after all others.
2. :meth:`IncrementalMapper.initialize` places the pair (camera ``a`` is the world frame, the
   baseline has length 1), triangulates, bundle-adjusts and filters; a pair that keeps fewer than
   ``init_min_points`` points is dropped and the next candidate tried (bundle adjustment is never
   called on nothing).
3. :meth:`IncrementalMapper.register_next_image`: PnP RANSAC then non-linear PnP on the image
   ranked first by the number *and spread* of its 2D-3D correspondences (:func:`spread_score`, as
   COLMAP's visibility pyramid). An image that sees too few triangulated points for PnP is
   registered from its matches with two or more registered images instead
   (:meth:`IncrementalMapper.register_from_pairs`, COLMAP's structure-less fallback; a ring whose
   views overlap their neighbours but hardly the views two steps away has only two-view tracks
   at its weak links). Images that fail are retried after every new registration.
   :meth:`IncrementalMapper.add_image` does steps 3-5 for one image.
4. :meth:`IncrementalMapper.triangulate_image`: the tracks the new image shares with *every*
   registered image (widest baseline first), so links grow beyond the initial pair's.
5. :meth:`IncrementalMapper.adjust_bundle` and :meth:`IncrementalMapper.filter_points` after each
   registration, by COLMAP's policy: a **local** BA of the new image and the ``ba_local_num_images``
   - 1 images that share the most points with it (the cameras around them held fixed), and a BA of
   the **whole** model when it has grown by ``ba_images_ratio`` since the last one, so the cost of
   a registration does not grow with the model. Where K was estimated (no calibration file), the
   BAs of the whole model also refine the focal length and ``k1`` (``SIMPLE_RADIAL``, shared by
   all images; :class:`course_lib.sfm.lm.SimpleRadialCamera`). When registration stalls with
   images left, :meth:`IncrementalMapper.retriangulate` (tracks that failed earlier, rejected
   observations that fit now) and the failed images are tried again.
6. :meth:`IncrementalMapper.finish`: re-triangulation, noise estimate, the final filtering and BA.

When a model cannot grow further and two or more images are left, ``run_sfm`` starts a new model
from those (:meth:`IncrementalMapper.begin_model`), as COLMAP does; it may register the images of
earlier models, and :meth:`IncrementalMapper.merge` carries it into an earlier model it overlaps. All thresholds are fields of
:class:`~course_lib.sfm.mapper_options.MapperOptions`, each with COLMAP's default beside it.

The steps of notebooks 02-04 are called through :func:`course_lib.exercises.call`, exactly as their
stubs document: in the instructor's kit they are the reference solutions, in the student kit the
student's own functions. The bundle adjustments (:func:`course_lib.sfm.bundle_adjustment.adjust`)
project with the exercise ``reprojection_residuals`` of notebook 05.

Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
"""

from __future__ import annotations

import numpy as np

from course_lib.conventions import camera_center
from course_lib.exercises import call, caller
from course_lib.sfm.initial_pair import H_INLIER_RATIO, InitialPair, calibrated_pose, pair_degeneracy
from course_lib.sfm.mapper_ba import REFINE_FROM_IMAGES, MapperBundleAdjustment
from course_lib.sfm.mapper_options import MapperOptions
from course_lib.sfm.merging import carry, similarity_ransac
from course_lib.sfm.reconstruction import Reconstruction, reprojection_error_matrix, triangulation_angles_deg
from course_lib.sfm.registration import ImageRegistration, spread_score
from course_lib.sfm.relocalization import relocalize
from course_lib.sfm.triangulator import IncrementalTriangulator
from course_lib.validate import KitInputError

__all__ = ["MapperOptions", "IncrementalMapper", "InitialPair", "pair_degeneracy", "spread_score", "final_thresholds",
           "H_INLIER_RATIO"]


#: The final BA leaves out two-view points when every camera keeps this many observations of points seen three or more times.
MIN_MULTIVIEW_OBSERVATIONS = 30
#: Median of the Rayleigh distribution over sigma: the reprojection error (a 2-D distance) of
#: observations with Gaussian noise sigma per coordinate has median sigma * sqrt(2 ln 2).
RAYLEIGH_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))
#: Share of observations beyond 3 sigma above which the errors count as heavy-tailed (Gaussian
#: noise puts about 1 % there, SIFT matches 10-16 % on the course data and the embedded scene).
HEAVY_TAIL_SHARE = 0.08


def final_thresholds(errors: np.ndarray, max_reproj_px, f_scale, loss: str) -> tuple[float, float, float, float, str]:
    """Threshold, loss and loss scale of the final BA: as given, or from the error distribution.

    The noise ``sigma`` (pixels per coordinate) is estimated robustly from the median of the
    reprojection ``errors`` (any shape, NaN ignored). ``None`` threshold: ``4 sigma`` within
    [1, 4] px (about 1 in 3000 good observations is beyond 4 sigma). ``loss="auto"``: the Cauchy
    loss where the errors have a heavy tail (more than :data:`HEAVY_TAIL_SHARE` of them beyond
    ``3 sigma``, as SIFT's have), plain least squares (``"linear"``, the most accurate for
    Gaussian noise) otherwise. ``None`` scale: ``2 sigma``, at least 0.3 px.

    Returns:
        ``(threshold_px, f_scale_px, sigma_px, tail_share, loss)``.
    """
    e = errors[np.isfinite(errors)]
    sigma = float(np.median(e) / RAYLEIGH_MEDIAN) if len(e) else 1.0
    tail = float(np.mean(e > 3.0 * sigma)) if len(e) else 0.0
    thr = float(np.clip(4.0 * sigma, 1.0, 4.0)) if max_reproj_px is None else float(max_reproj_px)
    fs = max(0.3, 2.0 * sigma) if f_scale is None else float(f_scale)
    if loss == "auto":
        loss = "cauchy" if tail > HEAVY_TAIL_SHARE else "linear"
    return thr, fs, sigma, tail, loss


class IncrementalMapper(ImageRegistration, IncrementalTriangulator, MapperBundleAdjustment):
    """The state of one growing model and the stages that change it (COLMAP's ``IncrementalMapper``).

    The tracks (``track_uv``) are shared by every model; each model has its own poses, points and
    observation flags, all indexed by track ``j`` and image ``i``. A later model starts from two
    images no earlier model registered (``used``) but may register images of earlier models as it
    grows; one that shares enough of them with an earlier model is merged into it (:meth:`merge`).
    The intrinsics (``K``, ``k1``) belong to the camera and carry over from one model to the next.

    Its stages live in four parts, as COLMAP's: the observations and their filtering
    (:class:`~course_lib.sfm.observations.ObservationManager`), registration
    (:class:`~course_lib.sfm.registration.ImageRegistration`), triangulation
    (:class:`~course_lib.sfm.triangulator.IncrementalTriangulator`) and bundle adjustment
    (:class:`~course_lib.sfm.mapper_ba.MapperBundleAdjustment`); this class holds the model and the
    initial pair, grows, finishes and merges models.

    Args:
        data: the :class:`course_lib.data.p3.P3Data` (its ``image_names`` and ``matches``).
        pairs: ``{(i, j): (F (3, 3), inliers (N,) bool)}`` the verified pairs.
        track_uv: ``(T, M, 2)`` pixels of the verified tracks as the photos show them, NaN where unseen.
        K: ``(3, 3)`` (the prior, where ``refine_intrinsics``). image_size: ``(W, H)``.
        options: :class:`MapperOptions`. rng: seeded ``numpy.random.Generator`` (PnP RANSAC draws from it).
        refine_intrinsics: refine the focal length and ``k1`` (``SIMPLE_RADIAL``) in the BAs of the
            whole model; :attr:`uv` then holds the undistorted pixels (where the pinhole ``K`` sees them).
        refine_from_images: the BAs of the whole model refine the intrinsics from this many registered images
            on (:data:`~course_lib.sfm.mapper_ba.REFINE_FROM_IMAGES`; more where ``K`` came from a converged BA of
            an earlier mapping, which a few views would only move away from the truth).
    """

    def __init__(self, data, pairs: dict, track_uv: np.ndarray, K: np.ndarray, image_size, options: MapperOptions, rng,
                 refine_intrinsics: bool = False, refine_from_images: int = REFINE_FROM_IMAGES):
        self.matches, self.names = data.matches, list(data.image_names)
        self.pairs, self.image_size, self.opts, self.rng = pairs, tuple(image_size), options, rng
        self.uv_raw = np.asarray(track_uv, float)
        self.T, self.M = self.uv_raw.shape[:2]
        self.visible = np.isfinite(self.uv_raw).all(axis=2)
        self.refine = bool(refine_intrinsics)
        self.refine_from_images = int(refine_from_images)
        self.K0 = np.asarray(K, float)
        self.set_intrinsics(self.K0, 0.0)
        self.intrinsics_log: list[dict] = []
        self.used = np.zeros(self.M, bool)  # images of earlier (or discarded) models
        self.degenerate: dict[tuple[int, int], dict] = {}
        self._scored: dict[tuple[int, int], InitialPair | None] = {}
        self._degenerate_checked: set = set()
        self.failed_starts: dict[tuple[int, int], int] = {}  # pairs that kept too few points: how many
        self.begin_model()

    # --- state ------------------------------------------------------------------------------------

    def begin_model(self) -> None:
        """An empty model: no image registered, no point, every observation a candidate."""
        M, T = self.M, self.T
        self.candidate = self.visible.copy()  # observation not (yet) rejected
        self.registered = np.zeros(M, dtype=bool)
        self.R, self.t = np.full((M, 3, 3), np.nan), np.full((M, 3), np.nan)
        self.X = np.full((T, 3), np.nan)
        self.ref = -1  # the camera that fixes the gauge (the initial pair's first)
        self.n_at_last_ba = 0  # registered images at the last bundle adjustment of the whole model
        self.pnp_medians: list[float] = []  # median PnP error of each registration (px): what is usual here

    def state(self) -> dict:
        """A copy of the model (registration, poses, points, observation flags, gauge), to :meth:`merge` with later."""
        return {"registered": self.registered.copy(), "R": self.R.copy(), "t": self.t.copy(), "X": self.X.copy(),
                "candidate": self.candidate.copy(), "ref": self.ref}


    # --- initial pair ---------------------------------------------------------------------------------

    def connectivity(self) -> np.ndarray:
        """``(M,)`` verified correspondences of each free image: inliers summed over its pairs with other free images."""
        conn = np.zeros(self.M)
        for (i, j), (_, inl) in self.pairs.items():
            if not (self.used[i] or self.used[j]):
                conn[i] += inl.sum()
                conn[j] += inl.sum()
        return conn

    def verified_matches(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        """The verified matches of pair ``(a, b)``, undistorted: ``x1, x2 (N, 2)``."""
        inl = self.pairs[(a, b)][1]
        pm = self.matches[(a, b)]
        return self.undistort(pm.x1[inl]), self.undistort(pm.x2[inl])

    def is_degenerate(self, a: int, b: int) -> bool:
        """Whether pair ``(a, b)`` cannot start a model (:func:`pair_degeneracy`); such pairs, and the
        ``"mostly planar"`` ones (tried after the others), are named in :attr:`degenerate`."""
        if (a, b) not in self._degenerate_checked:
            x1, x2 = self.verified_matches(a, b)
            kind, ratio = pair_degeneracy(x1, x2, self.K, self.opts.f_threshold_px, self.opts.init_min_points)
            self._degenerate_checked.add((a, b))
            if kind:
                self.degenerate[(a, b)] = {"pair": [a, b], "names": [self.names[a], self.names[b]], "kind": kind,
                                           "homography_share": round(ratio, 3), "f_inliers": len(x1)}
        return (a, b) in self.degenerate and not self.mostly_planar(a, b)

    def mostly_planar(self, a: int, b: int) -> bool:
        """Whether pair ``(a, b)`` sees mostly a plane, with enough off it to start a model when no other pair can."""
        return self.degenerate.get((a, b), {}).get("kind") == "mostly planar"

    def two_view(self, a: int, b: int):
        """The verified pair ``(a, b)``: its undistorted matches and their calibrated pose, computed once.

        Returns:
            ``(x1, x2, choice, inliers)``: the matches (:meth:`verified_matches`) and
            :func:`calibrated_pose`'s result (pose of ``b`` with ``a`` at the origin; ``choice`` None
            where no essential matrix fits). The initial pair's score (:meth:`score_pair`) and the
            structure-less registration (:meth:`register_from_pairs`) share it; it is recomputed
            after the intrinsics change (:meth:`set_intrinsics`).
        """
        if (a, b) not in self._two_view:
            x1, x2 = self.verified_matches(a, b)
            try:
                choice, inl = calibrated_pose(x1, x2, self.K, self.opts.init_max_error_px, int(self.rng.integers(2**31 - 1)))
            except KitInputError:
                choice, inl = None, None
            self._two_view[(a, b)] = (x1, x2, choice, inl)
        return self._two_view[(a, b)]

    def score_pair(self, a: int, b: int) -> InitialPair | None:
        """The two-view start of pair ``(a, b)`` (camera ``a`` at the origin), or None where it is degenerate.

        The calibrated pose of the pair's verified matches (:meth:`two_view`); the score counts its
        inliers triangulated in front of both cameras under ``init_min_angle_deg`` or more.
        """
        if (a, b) in self._scored:
            return self._scored[(a, b)]
        result = None
        if not self.is_degenerate(a, b):
            x1, _, choice, inl = self.two_view(a, b)
            if choice is not None:
                C2 = camera_center(choice.R_cw, choice.t_cw)
                ang = triangulation_angles_deg(choice.X, np.stack([np.zeros(3), C2]), np.ones((len(x1), 2), bool))
                front = choice.in_front & inl
                good = front & (ang >= self.opts.init_min_angle_deg)
                med = float(np.median(ang[front])) if front.any() else 0.0
                result = InitialPair((a, b), choice, int(good.sum()), len(x1), med, int(inl.sum()))
        self._scored[(a, b)] = result
        return result

    def find_initial_pair(self):
        """Yield the candidate initial pairs among the free images, in the order to try them (COLMAP's order).

        First images by :meth:`connectivity` (the most verified correspondences to the most
        images); for each, its partners with at least ``min_pair_inliers`` verified matches that are
        not degenerate and score at least ``init_min_points``, best score first. The ``"mostly
        planar"`` pairs come after all others, best score first. At most ``init_max_trials`` pairs;
        each once.
        """
        o = self.opts
        if o.initial_pair is not None and not self.used.any():
            a, b = sorted(int(v) for v in o.initial_pair)
            if (a, b) not in self.pairs:
                raise KitInputError(f"initial_pair={o.initial_pair}: that pair has no verified matches (too few?)")
            yield self.score_pair(a, b) or InitialPair((a, b), None, 0, int(self.pairs[(a, b)][1].sum()), 0.0)
            return
        conn, n = self.connectivity(), 0
        eligible = [k for k, (_, inl) in self.pairs.items()
                    if not self.used[list(k)].any() and inl.sum() >= o.min_pair_inliers]
        eligible = [k for k in eligible if not self.is_degenerate(*k)]  # all checked: every degenerate pair is named
        planar = [k for k in eligible if self.mostly_planar(*k)]
        eligible = [k for k in eligible if k not in planar]
        done: set = set()
        groups = [[k for k in eligible if first in k] for first in sorted(np.flatnonzero(conn > 0), key=lambda i: (-conn[i], i))]
        for group in groups + [planar]:
            found = [self.score_pair(*k) for k in group if k not in done and k not in self.failed_starts]
            done |= set(group)
            found = sorted((c for c in found if c is not None and c.score >= o.init_min_points),
                           key=lambda c: (c.score, c.inliers), reverse=True)
            for c in found:
                if n >= o.init_max_trials:
                    return
                n += 1
                yield c

    def use_options(self, options: MapperOptions) -> None:
        """Go on with other options (e.g. :func:`course_lib.sfm.mapper_options.relaxed`); the pair scores are recomputed."""
        self.opts = options
        self._scored.clear()  # the scores count points above the angle

    def initialize(self, pair: InitialPair) -> dict | None:
        """Start a model from ``pair``: triangulate, bundle-adjust and filter.

        Returns:
            The stage's numbers (``new_points``, ``points``, reprojection errors before and after
            the BA, ``ba``, ``filter``), or None when too few points remain (the model is reset and
            :attr:`failed_starts` records the pair with its points).
        """
        self.begin_model()
        (a, b), o = pair.images, self.opts
        if pair.choice is None:
            return None
        self.R[a], self.t[a] = np.eye(3), np.zeros(3)
        self.R[b], self.t[b] = pair.choice.R_cw, pair.choice.t_cw
        self.registered[[a, b]] = True
        self.ref = a
        js = np.flatnonzero(self.candidate[:, a] & self.candidate[:, b])
        n_new = 0
        if len(js):
            X0 = call("triangulate_linear", self._P(a), self._P(b), self.uv[js, a], self.uv[js, b])
            # as in triangulate_image: the BA that follows refines the points, where there is one
            n_new = self._accept(js, X0, caller("triangulate_nonlinear") if o.bundle_adjustment != "incremental" else None)
        stage = {"new_points": n_new, "points": int(self.has_X.sum()), "reprojection_before_ba": self.observation_stats()}
        if o.bundle_adjustment == "incremental" and n_new >= o.init_min_points:  # never a BA on (almost) nothing
            self._adjust_and_filter(stage, global_ba=True)
        n = int(self.has_X.sum())
        if n < o.init_min_points:
            self.failed_starts[(a, b)] = n
            self.begin_model()
            return None
        return stage

    # --- growing and finishing a model ----------------------------------------------------------------

    def add_image(self, i: int) -> tuple[dict | None, str | None]:
        """Register image ``i``, triangulate its new tracks, then a local or global BA and filtering.

        Returns:
            ``(numbers, None)``: the PnP numbers of :meth:`register_next_image`, ``new_points``,
            ``points``, the reprojection errors before and after the BA, ``ba``, ``filter`` and
            ``points_after``; or ``(None, why it did not register)``.
        """
        info, why = self.register_next_image(i)
        if info is None:
            return None, why
        n_new = self.triangulate_image(i)
        stage = {**info, "new_points": n_new, "points": int(self.has_X.sum())}
        if self.opts.bundle_adjustment == "incremental":
            global_ba = self.should_bundle()
            near = self.local_images(i) if not global_ba else None
            points = None if global_ba else (self.inlier & near[None, :]).any(axis=1)
            stage["reprojection_before_ba"] = self.observation_stats(points)
            self._adjust_and_filter(stage, global_ba, i)
        else:
            stage["reprojection_before_ba"] = self.observation_stats()
        stage["points_after"] = int(self.has_X.sum())
        return stage, None

    def _multiview_points(self) -> np.ndarray | None:
        """``(T,)`` points seen in 3+ images, or None when some camera has too few of them.

        A point seen in two images cannot reveal a wrong match: any pixel near the epipolar line
        triangulates to a point that fits both exactly (on synthetic scenes with 30 % random
        outliers, a third of the two-view points hold one). So where every camera has at least
        :data:`MIN_MULTIVIEW_OBSERVATIONS` observations of points seen three or more times, the
        final BA refines the cameras with those only, and the two-view points are refined
        afterwards with the cameras fixed (they stay in the model). With a robust loss (heavy-tailed
        errors, as on real photos, where most points are two-view points) a last BA over all points
        follows.
        """
        inl = self.inlier
        multi = inl.sum(axis=1) >= 3
        cams = np.flatnonzero(self.registered)
        if not (inl[multi][:, cams].sum(axis=0) >= MIN_MULTIVIEW_OBSERVATIONS).all() or multi[self.has_X].all():
            return None
        return multi

    def finish(self) -> dict:
        """The final stage: re-triangulation, noise estimate, filtering, and the final bundle adjustment.

        Observations beyond ``4 sigma`` (within [1, 4] px) are removed and a final BA polishes the
        result (:func:`final_thresholds`); where enough points are seen three or more times, the
        cameras are refined with those first and the two-view points after them
        (:meth:`_multiview_points`). Returns the stage's numbers.
        """
        o = self.opts
        st = {"reprojection_before_ba": self.observation_stats()}
        if o.bundle_adjustment != "none":
            if o.bundle_adjustment == "final":
                st["ba_robust"] = self.adjust_bundle(o.ba_loss, o.ba_f_scale, o.final_ba_max_iterations)
            st["retriangulation"] = self.retriangulate()
            thr, fs, sigma, tail, loss = final_thresholds(self.errors(), o.final_max_reproj_px, o.final_ba_f_scale, o.final_ba_loss)
            st.update(noise_sigma_px=round(sigma, 4), tail_share=round(tail, 4), ba_loss=loss, max_reproj_px=round(thr, 4),
                      ba_f_scale=round(fs, 4))
            st["filter"] = self.filter_points(thr)
            multi = self._multiview_points()
            st["ba"] = self.adjust_bundle(loss, fs, o.final_ba_max_iterations, ftol=1e-6, points=multi)
            if multi is not None:
                st["ba"]["two_view_points_refined_after"] = self._refine_points(~multi)
                if loss != "linear":
                    # a robust loss bounds the pull of a wrong two-view point: let them all take part at the end
                    st["filter_mid"] = self.filter_points(thr)
                    st["ba_all_points"] = self.adjust_bundle(loss, fs, o.final_ba_max_iterations, ftol=1e-6)
            st["filter_after"] = self.filter_points(thr)
            st["relocalization"] = relocalize(self, thr, o.relocalize_tries, self.rng)
            if st["relocalization"]["replaced"]:  # a pose moved to another solution: the model settles around it
                st["ba_after_relocalization"] = self.adjust_bundle(loss, fs, o.final_ba_max_iterations, ftol=1e-6)
                st["filter_after"] = self.filter_points(thr)
            st["reprojection_after_ba"] = self.observation_stats()
        return st

    def merge(self, earlier: dict) -> tuple[dict | None, str | None]:
        """Merge the current model into an ``earlier`` one (its :meth:`state`) that shares registered images with it.

        A similarity (scale, rotation, translation) from the current model's frame to the earlier
        one's is found by RANSAC on the points both models triangulated (the same tracks): three
        points give a candidate (:func:`course_lib.alignment.align_similarity`); a point carried
        over is an inlier when it reprojects within ``max_reproj_px`` in every image of the earlier
        model that observes it. The best candidate is refitted on its inliers. Where at least
        ``merge_min_inlier_ratio`` of the common points (and ``init_min_points``) are inliers, the
        images only the current model has are carried into the earlier frame with their points --
        or, where the current model is the larger, the earlier model's into the current frame -- the
        larger model keeping its own poses and points where both have one
        (:mod:`course_lib.sfm.merging`); a bundle adjustment of the whole model and filtering follow.
        The merged model is the current one, in the larger model's frame and gauge.

        Returns:
            ``(numbers, None)``: ``shared_images``, ``common_points``, ``inliers``, ``scale``,
            ``images_added`` and ``points_added`` (what the smaller model brought), and the BA's
            numbers; or ``(None, why not)``, the current model unchanged.
        """
        o = self.opts
        shared = earlier["registered"] & self.registered
        if shared.sum() < o.merge_min_shared_images:
            return None, f"{int(shared.sum())} shared images, need {o.merge_min_shared_images}"
        X_e = earlier["X"]
        common = np.flatnonzero(self.has_X & np.isfinite(X_e).all(axis=1))
        if len(common) < 3:
            return None, f"{len(common)} points in common, need 3"
        regs_e = np.flatnonzero(earlier["registered"])
        seen_e = earlier["candidate"][np.ix_(common, regs_e)]
        uv_e = np.where(seen_e[..., None], self.uv[np.ix_(common, regs_e)], np.nan)

        def agrees(s, Rs, Ts, rows):
            E = reprojection_error_matrix(self.K, earlier["R"][regs_e], earlier["t"][regs_e],
                                          s * self.X[common[rows]] @ Rs.T + Ts, uv_e[rows])
            bad = np.where(np.isfinite(uv_e[rows][..., 0]), ~(E <= o.max_reproj_px), False)
            return ~bad.any(axis=1) & seen_e[rows].any(axis=1)

        found = similarity_ransac(self.X[common], X_e[common], agrees, self.rng)
        if found is None:
            return None, f"no similarity carries {len(common)} common points onto the earlier model"
        (s, Rs, Ts), best = found
        if best.sum() < max(o.merge_min_inlier_ratio * len(common), o.init_min_points) or s <= 0:
            return None, (f"one similarity carries only {int(best.sum())} of the {len(common)} common points onto the "
                          f"earlier model (need {o.merge_min_inlier_ratio:.0%} and {o.init_min_points})")
        mine = self.state()
        if mine["registered"].sum() >= earlier["registered"].sum():  # the larger model is the base
            merged, new_images, new_points = carry(mine, earlier, 1.0 / s, Rs.T, -Rs.T @ Ts / s)
        else:
            merged, new_images, new_points = carry(earlier, mine, s, Rs, Ts)
        self.R, self.t, self.X, self.candidate = merged["R"], merged["t"], merged["X"], merged["candidate"]
        self.registered, self.ref = merged["registered"], merged["ref"]
        stage = {"shared_images": int(shared.sum()), "common_points": int(len(common)), "inliers": int(best.sum()),
                 "scale": round(float(s), 6), "images_added": [int(i) for i in new_images], "points_added": int(len(new_points)),
                 "reprojection_before_ba": self.observation_stats()}
        if o.bundle_adjustment == "incremental":
            self._adjust_and_filter(stage, global_ba=True)
        return stage, None

    def end_model(self, rgb: np.ndarray) -> Reconstruction:
        """The current model as a :class:`Reconstruction` (its images leave the pool of later models); the
        controller gives it its ``report`` (:meth:`course_lib.sfm.mapper_report.MapperReport.model_report`)."""
        self.used |= self.registered
        return Reconstruction(K=self.K.copy(), image_names=list(self.names), image_size=self.image_size,
                              registered=self.registered.copy(), R_cw=self.R.copy(), t_cw=self.t.copy(), X=self.X.copy(),
                              rgb=rgb.copy(), track_uv=self.uv.copy(), inlier=self.inlier.copy(), k1=self.k1,
                              camera_model=self.camera_model)

    @property
    def camera_model(self) -> str:
        """``"SIMPLE_RADIAL"`` where the focal length and ``k1`` are refined, else ``"PINHOLE"``."""
        return "SIMPLE_RADIAL" if self.refine else "PINHOLE"

    def camera(self) -> dict:
        """The camera the model used: ``model``, ``K``, ``k1``; where refined, the prior focal length and the refinements."""
        camera = {"model": self.camera_model, "K": np.round(self.K, 4).tolist(), "k1": round(self.k1, 6)}
        if self.refine:
            camera.update(prior_focal_px=round(float(self.K0[0, 0]), 3), refinements=list(self.intrinsics_log))
        return camera

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
from scipy.spatial.transform import Rotation

from course_lib.conventions import camera_center, invert_pose, projection_matrix
from course_lib.data.camera import undistort_pixels
from course_lib.exercises import call, caller
from course_lib.sfm import lm
from course_lib.sfm.bundle_adjustment import adjust
from course_lib.sfm.initial_pair import H_INLIER_RATIO, InitialPair, calibrated_pose, pair_degeneracy
from course_lib.sfm.mapper_options import MapperOptions
from course_lib.sfm.merging import carry, similarity_ransac
from course_lib.sfm.structureless import pair_sampson, pose_from_partners, refine_on_partners
from course_lib.sfm.reconstruction import Reconstruction, error_summary, reprojection_error_matrix, triangulation_angles_deg
from course_lib.validate import KitInputError

__all__ = ["MapperOptions", "IncrementalMapper", "InitialPair", "pair_degeneracy", "spread_score", "final_thresholds",
           "H_INLIER_RATIO"]


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


#: The final BA leaves out two-view points when every camera keeps this many observations of points seen three or more times.
MIN_MULTIVIEW_OBSERVATIONS = 30
#: Median of the Rayleigh distribution over sigma: the reprojection error (a 2-D distance) of
#: observations with Gaussian noise sigma per coordinate has median sigma * sqrt(2 ln 2).
RAYLEIGH_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))
#: Share of observations beyond 3 sigma above which the errors count as heavy-tailed (Gaussian
#: noise puts about 1 % there, SIFT matches 10-16 % on the course data and the embedded scene).
HEAVY_TAIL_SHARE = 0.08
#: Registered images from which the BAs of the whole model refine the intrinsics (two views
#: hardly constrain the focal length).
REFINE_FROM_IMAGES = 3


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


class IncrementalMapper:
    """The state of one growing model and the stages that change it (COLMAP's ``IncrementalMapper``).

    The tracks (``track_uv``) are shared by every model; each model has its own poses, points and
    observation flags, all indexed by track ``j`` and image ``i``. A later model starts from two
    images no earlier model registered (``used``) but may register images of earlier models as it
    grows; one that shares enough of them with an earlier model is merged into it (:meth:`merge`).
    The intrinsics (``K``, ``k1``) belong to the camera and carry over from one model to the next.

    Args:
        data: the :class:`course_lib.data.p3.P3Data` (its ``image_names`` and ``matches``).
        pairs: ``{(i, j): (F (3, 3), inliers (N,) bool)}`` the verified pairs.
        track_uv: ``(T, M, 2)`` pixels of the verified tracks as the photos show them, NaN where unseen.
        K: ``(3, 3)`` (the prior, where ``refine_intrinsics``). image_size: ``(W, H)``.
        options: :class:`MapperOptions`. rng: seeded ``numpy.random.Generator`` (PnP RANSAC draws from it).
        refine_intrinsics: refine the focal length and ``k1`` (``SIMPLE_RADIAL``) in the BAs of the
            whole model; :attr:`uv` then holds the undistorted pixels (where the pinhole ``K`` sees them).
    """

    def __init__(self, data, pairs: dict, track_uv: np.ndarray, K: np.ndarray, image_size, options: MapperOptions, rng,
                 refine_intrinsics: bool = False):
        self.matches, self.names = data.matches, list(data.image_names)
        self.pairs, self.image_size, self.opts, self.rng = pairs, tuple(image_size), options, rng
        self.uv_raw = np.asarray(track_uv, float)
        self.T, self.M = self.uv_raw.shape[:2]
        self.visible = np.isfinite(self.uv_raw).all(axis=2)
        self.refine = bool(refine_intrinsics)
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

    def state(self) -> dict:
        """A copy of the model (registration, poses, points, observation flags, gauge), to :meth:`merge` with later."""
        return {"registered": self.registered.copy(), "R": self.R.copy(), "t": self.t.copy(), "X": self.X.copy(),
                "candidate": self.candidate.copy(), "ref": self.ref}

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

    # --- initial pair ---------------------------------------------------------------------------------

    def connectivity(self) -> np.ndarray:
        """``(M,)`` verified correspondences of each free image: inliers summed over its pairs with other free images."""
        conn = np.zeros(self.M)
        for (i, j), (_, inl) in self.pairs.items():
            if not (self.used[i] or self.used[j]):
                conn[i] += inl.sum()
                conn[j] += inl.sum()
        return conn

    def _pair_inliers(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        """The verified matches of pair ``(a, b)``, undistorted: ``x1, x2 (N, 2)``."""
        inl = self.pairs[(a, b)][1]
        pm = self.matches[(a, b)]
        return self.undistort(pm.x1[inl]), self.undistort(pm.x2[inl])

    def is_degenerate(self, a: int, b: int) -> bool:
        """Whether pair ``(a, b)`` cannot start a model (:func:`pair_degeneracy`); such pairs, and the
        ``"mostly planar"`` ones (tried after the others), are named in :attr:`degenerate`."""
        if (a, b) not in self._degenerate_checked:
            x1, x2 = self._pair_inliers(a, b)
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
            ``(x1, x2, choice, inliers)``: the matches (:meth:`_pair_inliers`) and
            :func:`calibrated_pose`'s result (pose of ``b`` with ``a`` at the origin; ``choice`` None
            where no essential matrix fits). The initial pair's score (:meth:`score_pair`) and the
            structure-less registration (:meth:`register_from_pairs`) share it; it is recomputed
            after the intrinsics change (:meth:`set_intrinsics`).
        """
        if (a, b) not in self._two_view:
            x1, x2 = self._pair_inliers(a, b)
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

    # --- registration -----------------------------------------------------------------------------------

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
        self.R[i], self.t[i] = call("pnp_nonlinear", self.X[js[inl]], self.uv[js[inl], i], self.K, res.R_cw, res.t_cw)
        self.registered[i] = True
        self.candidate[js[~inl], i] = False
        return {"correspondences": int(len(js)), "pnp_inliers": int(inl.sum()), "ransac_iterations": int(res.n_iters)}, None

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

    # --- filtering and bundle adjustment ------------------------------------------------------------------

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
        if not local and self.refine and self.registered.sum() >= REFINE_FROM_IMAGES:
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
        ``min_k1_effect_px`` (there ``k1`` trades off against the focal length instead of being measured). A
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
        hold_k1 = self.registered.sum() < o.refine_k1_from_images or 0.1 * r**3 * self.K[0, 0] < o.min_k1_effect_px
        while True:
            res = self._solve(model, cams, pts, self.uv_raw, fixed, loss, f_scale, max_iterations, ftol,
                              shared=np.array([self.K[0, 0], self.k1]), fixed_shared=np.array([False, hold_k1]))
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

    def _refine_points(self, points: np.ndarray) -> int:
        """Non-linear triangulation of the ``(T,)`` bool ``points`` with the cameras fixed; returns how many."""
        js = np.flatnonzero(points & self.has_X)
        if len(js) == 0:
            return 0
        regs = np.flatnonzero(self.registered)
        uv = np.where(self.inlier[js][:, regs][..., None], self.uv[js][:, regs], np.nan)
        self.X[js] = call("triangulate_nonlinear", self.K, self.R[regs], self.t[regs], uv, self.X[js])
        return int(len(js))

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

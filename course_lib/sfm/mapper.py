"""The incremental mapper: one object that holds a growing model, whose methods are the stages.

Shaped like COLMAP's ``IncrementalMapper`` (``src/colmap/sfm/incremental_mapper.h``) and
OpenSfM's ``reconstruction.py``. :func:`course_lib.sfm.pipeline.run_sfm` drives it:

1. :meth:`IncrementalMapper.find_initial_pair` yields candidate pairs in the order they are
   tried: first the images with the most verified correspondences to other images (summed over
   their verified pairs: the part of the match graph that can grow), then, for each, its partners
   ranked by the number of points triangulated in front of both cameras with an angle of at least
   ``init_min_angle_deg`` (a long baseline). Pairs that a homography explains (pure rotation, a
   plane) are named and skipped (:func:`pair_degeneracy`).
2. :meth:`IncrementalMapper.initialize` places the pair (camera ``a`` is the world frame, the
   baseline has length 1), triangulates, bundle-adjusts and filters; a pair that keeps fewer than
   ``init_min_points`` points is dropped and the next candidate tried (bundle adjustment is never
   called on nothing).
3. :meth:`IncrementalMapper.register_next_image`: PnP RANSAC then non-linear PnP on the image
   ranked first by the number *and spread* of its 2D-3D correspondences (:func:`spread_score`, as
   COLMAP's visibility pyramid). Images that fail are retried after every new registration.
4. :meth:`IncrementalMapper.triangulate_image`: the tracks the new image shares with *every*
   registered image (widest baseline first), so links grow beyond the initial pair's.
5. :meth:`IncrementalMapper.adjust_bundle` and :meth:`IncrementalMapper.filter_points` after each
   registration; when registration stalls with images left, :meth:`IncrementalMapper.retriangulate`
   (tracks that failed earlier, rejected observations that fit now) and the failed images are
   tried again.
6. :meth:`IncrementalMapper.finish`: re-triangulation, noise estimate, the final filtering and BA.

When a model cannot grow further and two or more images are left, ``run_sfm`` starts a new model
from those (:meth:`IncrementalMapper.begin_model`), as COLMAP does. All thresholds are fields of
:class:`MapperOptions`, each with COLMAP's default beside it.

The steps of notebooks 02-04 are called through :func:`course_lib.exercises.call`, exactly as their
stubs document: in the instructor's kit they are the reference solutions, in the student kit the
student's own functions. The bundle adjustments (:func:`course_lib.sfm.bundle_adjustment.adjust`)
project with the exercise ``reprojection_residuals`` of notebook 05.

Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, fields

import numpy as np

from course_lib.conventions import camera_center, projection_matrix
from course_lib.exercises import call, caller
from course_lib.sfm.bundle_adjustment import adjust
from course_lib.sfm.reconstruction import Reconstruction, error_summary, reprojection_error_matrix, triangulation_angles_deg
from course_lib.validate import KitInputError

__all__ = ["MapperOptions", "IncrementalMapper", "InitialPair", "pair_degeneracy", "spread_score", "final_thresholds"]


@dataclass
class MapperOptions:
    """Every setting of the incremental mapper, with COLMAP's default (``IncrementalMapper::Options``,
    ``IncrementalPipelineOptions``) where it has one.

    The kit's data sets are small (5-20 images, 800x600 px), so a few thresholds are looser than
    COLMAP's; each is stated.

    Attributes:
        f_threshold_px: RANSAC threshold on the Sampson distance for the pairs (px); only matches
            within it join tracks. (COLMAP two-view ``max_error`` 4 px.)
        min_pair_matches: a pair needs this many RANSAC inliers to give tracks. (COLMAP
            ``min_num_matches`` 15, ``min_num_inliers`` 15.)
        pnp_threshold_px: PnP RANSAC threshold on the reprojection error (px). (COLMAP
            ``abs_pose_max_error`` 12 px.)
        min_pnp_inliers: an image registers with at least this many PnP inliers. (COLMAP
            ``abs_pose_min_num_inliers`` 30.)
        max_reproj_px: observations reprojecting farther are dropped during the run. (COLMAP
            ``filter_max_reproj_error`` 4 px.)
        final_max_reproj_px: the threshold before the final BA; None: 4 x the noise level estimated
            from the median reprojection error, within [1, 4] px.
        min_angle_deg: smallest triangulation angle of a kept point. (COLMAP
            ``filter_min_tri_angle`` 1.5 deg.)
        init_min_angle_deg: angle a point of a candidate initial pair must have to count in its
            score. (COLMAP asks a *median* angle of ``init_min_tri_angle`` 16 deg: too strict for a
            walk past a building.)
        min_pair_inliers: RANSAC inliers a pair needs to be an initial pair. (COLMAP
            ``init_min_num_inliers`` 100.)
        init_min_points: points an initial pair must score, and keep after triangulation, BA and
            filtering, to start a model; otherwise the next candidate is tried. (COLMAP: > 0.)
        init_max_trials: candidate pairs tried per model at most. (COLMAP ``init_num_trials`` 200.)
        init_relaxations: when no pair starts the first model, ``min_pair_inliers`` and
            ``init_min_angle_deg`` are halved and the candidates tried again, up to this many
            times. (COLMAP relaxes ``init_min_num_inliers`` and ``init_min_tri_angle`` the same way,
            twice each.)
        multiple_models: start new models from the images left when registration stalls.
            (COLMAP ``multiple_models`` true.)
        max_models: the most models. (COLMAP ``max_num_models`` 50.)
        min_model_size: a model after the first one is kept only with this many images; its images
            are then left out with the reason. (COLMAP ``min_model_size`` 10, or 80 % of the images
            where fewer.)
        bundle_adjustment: ``"incremental"`` (after every registration and at the end),
            ``"final"`` (once at the end) or ``"none"`` (the result *before* BA: notebook 05's
            starting point).
        ba_loss, ba_f_scale: robust loss of the intermediate BAs. (COLMAP: plain squares; the kit's
            Huber at 1 px bounds the pull of the outliers that its looser thresholds let in.)
        ba_max_iterations: iteration cap of each BA during the growth. These only have to bring
            the new image and its points close enough for the next registration: the final BA
            polishes (on the benchmark scenes 5 instead of 10 leaves the poses the same to 1 %
            and saves about a quarter of the mapper's time). (COLMAP
            ``ba_local_max_num_iterations`` 25, with a local BA that refines only the 6 images
            nearest the new one.)
        final_ba_max_iterations: iteration cap of each final BA. (COLMAP
            ``ba_global_max_num_iterations`` 50.)
        ba_images_ratio: with ``"incremental"``, a registration is followed by a BA of the whole
            model when the model has grown by this factor since the last one (always up to 6
            images); in between, only the new points are refined (non-linear triangulation, the
            cameras fixed) and filtered. Default 1.0: after every registration (on 16 views, 1.2
            saves about 15 % of the CPU time and changes the rotation error by +-10 %: 0.137 ->
            0.156 deg on ``ring-groups-s0`` of ``benchmarks/sfm_vs_colmap.py`` (instructor's kit), 1.11x COLMAP's;
            the kit keeps every BA and makes the growth's BAs short instead, ``ba_max_iterations``).
            (COLMAP ``ba_global_images_ratio`` 1.1, with a local BA of the 6 nearest images after
            every registration; OpenSfM ``bundle_new_points_ratio`` 1.2.)
        final_ba_loss, final_ba_f_scale: loss of the final BA; ``"auto"``: Cauchy at ``f_scale``
            (None: twice the estimated noise, at least 0.3 px) when the errors have a heavy tail
            (SIFT), plain least squares otherwise (:func:`final_thresholds`).
        initial_pair: force the initial pair ``(i, j)`` (0-based) of the first model.
        verbose: print one line per stage.
    """

    f_threshold_px: float = 2.0
    min_pair_matches: int = 16
    pnp_threshold_px: float = 8.0
    min_pnp_inliers: int = 20
    max_reproj_px: float = 4.0
    final_max_reproj_px: float | None = None
    min_angle_deg: float = 1.0
    init_min_angle_deg: float = 2.0
    min_pair_inliers: int = 50
    init_min_points: int = 20
    init_max_trials: int = 50
    init_relaxations: int = 2
    multiple_models: bool = True
    max_models: int = 10
    min_model_size: int = 3
    bundle_adjustment: str = "incremental"
    ba_loss: str = "huber"
    ba_f_scale: float = 1.0
    ba_max_iterations: int = 5
    final_ba_max_iterations: int = 20
    ba_images_ratio: float = 1.0
    final_ba_loss: str = "auto"
    final_ba_f_scale: float | None = None
    initial_pair: tuple[int, int] | None = None
    verbose: bool = False

    @classmethod
    def from_keywords(cls, options: "MapperOptions | None" = None, **overrides) -> "MapperOptions":
        """``options`` (or the defaults) with ``overrides`` replaced; a name that is no field is an error."""
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(overrides) - names)
        if unknown:
            raise KitInputError(f"unknown SfM option(s) {unknown}: the options are {sorted(names)}")
        base = asdict(options) if options is not None else {}
        opts = cls(**{**base, **overrides})
        if opts.bundle_adjustment not in ("incremental", "final", "none"):
            raise KitInputError(f"bundle_adjustment={opts.bundle_adjustment!r}: expected 'incremental', 'final' or 'none'")
        return opts

    def summary(self) -> dict:
        """The options the report records."""
        keep = ("f_threshold_px", "pnp_threshold_px", "max_reproj_px", "final_max_reproj_px", "min_angle_deg",
                "bundle_adjustment", "ba_loss", "ba_f_scale", "final_ba_loss", "final_ba_f_scale", "init_min_points",
                "min_model_size", "multiple_models")
        return {k: getattr(self, k) for k in keep}


#: A pair whose F inliers a homography explains this well is degenerate for a two-view start.
H_INLIER_RATIO = 0.8


def pair_degeneracy(x1: np.ndarray, x2: np.ndarray, K: np.ndarray, threshold_px: float) -> tuple[str, float]:
    """Is a pair's geometry a homography (pure rotation or a planar scene), where F and E are ill-defined?

    A homography ``H`` (OpenCV's RANSAC, ``threshold_px``) is fitted to the pair's F inliers. If it
    explains more than :data:`H_INLIER_RATIO` of them, the pair cannot start a reconstruction:
    if ``K⁻¹ H K`` is a rotation (equal singular values), the camera only turned (no baseline,
    nothing to triangulate), otherwise the points lie on a plane (F is not unique).

    Args:
        x1, x2: ``(N, 2)`` inlier matches. K: ``(3, 3)``. threshold_px: pixels.

    Returns:
        ``(kind, ratio)``: kind ``""`` (fine), ``"pure rotation"`` or ``"planar"``; the share of the
        matches the homography explains.
    """
    import cv2

    if len(x1) < 8:
        return "", 0.0
    # 200 samples of 4 find a homography that explains 80 % of the matches with certainty
    # (1 - 0.8^4)^200 < 1e-40; OpenCV's default of 2000 costs 10x more on the pairs where none does
    H, mask = cv2.findHomography(x1.astype(np.float64), x2.astype(np.float64), cv2.RANSAC, threshold_px,
                                 maxIters=200, confidence=0.999)
    if H is None:
        return "", 0.0
    ratio = float(mask.ravel().astype(bool).mean())
    if ratio <= H_INLIER_RATIO:
        return "", ratio
    s = np.linalg.svd(np.linalg.inv(K) @ H @ K, compute_uv=False)
    return ("pure rotation" if s[0] / s[2] < 1.02 else "planar"), ratio


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


@dataclass
class InitialPair:
    """A candidate initial pair: ``images (a, b)``, the two-view ``choice`` (``choose_pose``'s result with
    ``R_cw, t_cw, X, in_front, counts``, :func:`course_lib.exercises.call`; camera ``a`` at the origin), ``score`` (points in front with an angle >= ``init_min_angle_deg``),
    RANSAC ``inliers`` and the ``median_angle_deg`` of the points in front."""

    images: tuple[int, int]
    choice: object
    score: int
    inliers: int
    median_angle_deg: float

    def row(self) -> dict:
        return {"images": list(self.images), "score": self.score, "ransac_inliers": self.inliers,
                "median_angle_deg": round(self.median_angle_deg, 2)}


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


class IncrementalMapper:
    """The state of one growing model and the stages that change it (COLMAP's ``IncrementalMapper``).

    The tracks (``track_uv``) are shared by every model; each model has its own poses, points and
    observation flags, all indexed by track ``j`` and image ``i``. Images registered in an earlier
    model (``used``) take no part in a later one.

    Args:
        data: the :class:`course_lib.data.p3.P3Data` (its ``image_names`` and ``matches``).
        pairs: ``{(i, j): (F (3, 3), inliers (N,) bool)}`` the verified pairs.
        track_uv: ``(T, M, 2)`` pixels of the verified tracks, NaN where unseen.
        K: ``(3, 3)``. image_size: ``(W, H)``. options: :class:`MapperOptions`.
        rng: seeded ``numpy.random.Generator`` (PnP RANSAC draws from it).
    """

    def __init__(self, data, pairs: dict, track_uv: np.ndarray, K: np.ndarray, image_size, options: MapperOptions, rng):
        self.matches, self.names = data.matches, list(data.image_names)
        self.pairs, self.K, self.image_size, self.opts, self.rng = pairs, K, tuple(image_size), options, rng
        self.uv = np.asarray(track_uv, float)
        self.T, self.M = self.uv.shape[:2]
        self.visible = np.isfinite(self.uv).all(axis=2)
        self.used = np.zeros(self.M, bool)  # images of earlier (or discarded) models
        self.degenerate: dict[tuple[int, int], dict] = {}
        self._scored: dict[tuple[int, int], InitialPair | None] = {}
        self._degenerate_checked: set = set()
        self.failed_starts: dict[tuple[int, int], int] = {}  # pairs that kept too few points: how many
        self.say = print if options.verbose else (lambda *a, **k: None)
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
        self.stages: list[dict] = []
        self.seconds: dict[str, float] = {}
        self.initial: dict = {}
        self.reasons = {}  # why an image did not register in this model (its latest attempt)

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

    def errors(self) -> np.ndarray:
        """``(T, M)`` reprojection errors of the observations in use, NaN elsewhere."""
        return reprojection_error_matrix(self.K, self.R, self.t, self.X, np.where(self.inlier[..., None], self.uv, np.nan))

    def observation_stats(self) -> dict[str, float]:
        return error_summary(self.errors())

    def _P(self, i: int) -> np.ndarray:
        return projection_matrix(self.K, self.R[i], self.t[i])

    # --- initial pair ---------------------------------------------------------------------------------

    def connectivity(self) -> np.ndarray:
        """``(M,)`` verified correspondences of each free image: RANSAC inliers summed over its pairs with other free images."""
        conn = np.zeros(self.M)
        for (i, j), (_, inl) in self.pairs.items():
            if not (self.used[i] or self.used[j]):
                conn[i] += inl.sum()
                conn[j] += inl.sum()
        return conn

    def is_degenerate(self, a: int, b: int) -> bool:
        """Whether a homography explains pair ``(a, b)`` (:func:`pair_degeneracy`); such pairs are named in :attr:`degenerate`."""
        if (a, b) not in self._degenerate_checked:
            inl = self.pairs[(a, b)][1]
            pm = self.matches[(a, b)]
            kind, ratio = pair_degeneracy(pm.x1[inl], pm.x2[inl], self.K, self.opts.f_threshold_px)
            self._degenerate_checked.add((a, b))
            if kind:
                self.degenerate[(a, b)] = {"pair": [a, b], "names": [self.names[a], self.names[b]], "kind": kind,
                                           "homography_share": round(ratio, 3), "f_inliers": int(inl.sum())}
        return (a, b) in self.degenerate

    def score_pair(self, a: int, b: int) -> InitialPair | None:
        """The two-view start of pair ``(a, b)`` (camera ``a`` at the origin), or None where it is degenerate."""
        if (a, b) in self._scored:
            return self._scored[(a, b)]
        F, inl = self.pairs[(a, b)]
        pm = self.matches[(a, b)]
        x1, x2 = pm.x1[inl], pm.x2[inl]
        result = None
        if not self.is_degenerate(a, b):
            try:
                E = call("essential_from_fundamental", F, self.K)
                choice = call("choose_pose", *call("pose_candidates", E), self.K, x1, x2)
            except KitInputError:
                choice = None
            if choice is not None:
                C2 = camera_center(choice.R_cw, choice.t_cw)
                ang = triangulation_angles_deg(choice.X, np.stack([np.zeros(3), C2]), np.ones((len(x1), 2), bool))
                good = choice.in_front & (ang >= self.opts.init_min_angle_deg)
                med = float(np.median(ang[choice.in_front])) if choice.in_front.any() else 0.0
                result = InitialPair((a, b), choice, int(good.sum()), int(inl.sum()), med)
        self._scored[(a, b)] = result
        return result

    def find_initial_pair(self):
        """Yield the candidate initial pairs among the free images, in the order to try them (COLMAP's order).

        First images by :meth:`connectivity` (the most verified correspondences to the most
        images); for each, its partners with at least ``min_pair_inliers`` RANSAC inliers that are
        not degenerate and score at least ``init_min_points``, best score first. At most
        ``init_max_trials`` pairs; each once.
        """
        o = self.opts
        if o.initial_pair is not None and not self.used.any():
            a, b = sorted(int(v) for v in o.initial_pair)
            if (a, b) not in self.pairs:
                raise KitInputError(f"initial_pair={o.initial_pair}: that pair has no RANSAC result (too few matches?)")
            yield self.score_pair(a, b) or InitialPair((a, b), None, 0, int(self.pairs[(a, b)][1].sum()), 0.0)
            return
        conn, n = self.connectivity(), 0
        eligible = [k for k, (_, inl) in self.pairs.items()
                    if not self.used[list(k)].any() and inl.sum() >= o.min_pair_inliers]
        eligible = [k for k in eligible if not self.is_degenerate(*k)]  # all checked: every degenerate pair is named
        done: set = set()
        for first in sorted(np.flatnonzero(conn > 0), key=lambda i: (-conn[i], i)):
            found = [self.score_pair(*k) for k in eligible if first in k and k not in done and k not in self.failed_starts]
            done |= {k for k in eligible if first in k}
            found = sorted((c for c in found if c is not None and c.score >= o.init_min_points),
                           key=lambda c: (c.score, c.inliers), reverse=True)
            for c in found:
                if n >= o.init_max_trials:
                    return
                n += 1
                yield c

    def relax_initialization(self) -> dict:
        """Halve ``min_pair_inliers`` and ``init_min_angle_deg`` (COLMAP's relaxation when no model starts); the new values."""
        from dataclasses import replace

        self.opts = replace(self.opts, min_pair_inliers=max(self.opts.min_pair_matches, self.opts.min_pair_inliers // 2),
                            init_min_angle_deg=self.opts.init_min_angle_deg / 2.0)
        self._scored.clear()  # the scores count points above the angle
        self.say(f"no pair starts a model: relaxed to min_pair_inliers={self.opts.min_pair_inliers}, "
                 f"init_min_angle_deg={self.opts.init_min_angle_deg}")
        return {"min_pair_inliers": self.opts.min_pair_inliers, "init_min_angle_deg": self.opts.init_min_angle_deg}

    def initialize(self, pair: InitialPair) -> bool:
        """Start a model from ``pair``: triangulate, bundle-adjust and filter; False (model reset) if too few points remain."""
        t0 = time.perf_counter()
        self.begin_model()
        (a, b), o = pair.images, self.opts
        if pair.choice is None:
            return False
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
        stage = {"stage": "initial pair", "images": [a, b], "new_points": n_new, "points": int(self.has_X.sum()),
                 "reprojection_before_ba": self.observation_stats()}
        if o.bundle_adjustment == "incremental" and n_new >= o.init_min_points:  # never a BA on (almost) nothing
            self._adjust_and_filter(stage)
        stage["seconds"] = round(time.perf_counter() - t0, 3)
        n = int(self.has_X.sum())
        if n < o.init_min_points:
            self.say(f"initial pair {self.names[a]}, {self.names[b]}: only {n} points (need {o.init_min_points}); next candidate")
            self.failed_starts[(a, b)] = n
            self.begin_model()
            return False
        self.stages.append(stage)
        self.initial = {"images": [a, b], "names": [self.names[a], self.names[b]], "ransac_inliers": pair.inliers,
                        "score": pair.score, "points": n_new}
        self.seconds["initial_pair"] = time.perf_counter() - t0
        self.say(f"initial pair {self.names[a]}, {self.names[b]}: {n_new} points")
        return True

    # --- registration -----------------------------------------------------------------------------------

    def next_images(self, skip=()) -> list[tuple[int, int]]:
        """``[(image, correspondences), ...]`` of the free unregistered images not in ``skip``, best first.

        Ranked by :func:`spread_score` of the pixels of their 2D-3D correspondences (features whose
        track has a point), ties by image number.
        """
        todo = [i for i in range(self.M) if not (self.registered[i] or self.used[i] or i in skip)]
        has_X = self.has_X
        rows = []
        for i in todo:
            js = np.flatnonzero(has_X & self.candidate[:, i])
            rows.append((spread_score(self.uv[js, i], self.image_size), len(js), i))
        rows.sort(key=lambda r: (-r[0], -r[1], r[2]))
        return [(i, n) for _, n, i in rows]

    def register_next_image(self, i: int) -> tuple[dict | None, str | None]:
        """PnP RANSAC + non-linear PnP for image ``i``: ``(info, None)``, or ``(None, why it failed)``."""
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

    def _accept(self, js: np.ndarray, X0: np.ndarray, triangulate_nonlinear=None) -> int:
        """Check linearly triangulated tracks ``js`` (``X0 (len(js), 3)``) against all registered views, refine, keep the good ones.

        Observations that reproject farther than ``max_reproj_px`` from the linear estimate are
        dropped, the point is refined non-linearly over the remaining ones (where a refinement is
        given), checked again, and kept if at least two observations in front of their cameras
        remain and its triangulation angle is at least ``min_angle_deg``. Dropped observations are
        rejected for good.
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
        if two.any() and triangulate_nonlinear is not None:
            X[two] = triangulate_nonlinear(self.K, self.R[regs], self.t[regs], uv[two], X0[two])
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

    def filter_points(self, max_reproj_px: float | None = None, min_angle_deg: float | None = None) -> dict:
        """Drop observations that reproject badly, then points with < 2 observations or a small angle."""
        thr = self.opts.max_reproj_px if max_reproj_px is None else max_reproj_px
        angle = self.opts.min_angle_deg if min_angle_deg is None else min_angle_deg
        bad = self.inlier & ~(self.errors() <= thr)
        self.candidate &= ~bad
        inl = self.inlier
        ang = triangulation_angles_deg(np.where(self.has_X[:, None], self.X, 0.0), np.nan_to_num(self.centers()), inl)
        drop = self.has_X & ((inl.sum(axis=1) < 2) | (ang < angle))
        self.X[drop] = np.nan
        return {"observations_removed": int(bad.sum()), "points_removed": int(drop.sum())}

    def adjust_bundle(self, loss: str, f_scale: float, max_iterations: int, ftol: float = 1e-4,
                      points: np.ndarray | None = None) -> dict:
        """Bundle adjustment of the registered cameras and the points (all, or the ``(T,)`` bool ``points``).

        The gauge is the initial pair's first camera. With no observation to adjust it does nothing
        and says so (``{"skipped": ...}``).
        """
        cams = np.flatnonzero(self.registered)
        pts = np.flatnonzero(self.has_X if points is None else self.has_X & points)
        uv = np.where(self.inlier[np.ix_(pts, cams)][..., None], self.uv[np.ix_(pts, cams)], np.nan)
        if len(pts) == 0 or not np.isfinite(uv).any():
            return {"skipped": "no points to adjust"}
        res = adjust(self.K, self.R[cams], self.t[cams], self.X[pts], uv, loss=loss, f_scale=f_scale,
                            max_iterations=max_iterations, ref_camera=int(np.flatnonzero(cams == self.ref)[0]),
                            ftol=ftol, xtol=1e-10)
        self.R[cams], self.t[cams], self.X[pts] = res.R_cw, res.t_cw, res.X
        return {"iterations": res.n_iterations, "rms_before": round(res.initial_rms, 4), "rms_after": round(res.final_rms, 4),
                "seconds": round(res.seconds, 3), "gauge": res.gauge}

    def should_bundle(self) -> bool:
        """Whether the model is due a bundle adjustment (OpenSfM's ``ShouldBundle``): up to 6 images
        always, then when it has grown by ``ba_images_ratio`` since the last one."""
        n = int(self.registered.sum())
        return self.opts.bundle_adjustment == "incremental" and (n <= 6 or n >= self.opts.ba_images_ratio * self.n_at_last_ba)

    def _adjust_and_filter(self, stage: dict) -> None:
        self.n_at_last_ba = int(self.registered.sum())
        o = self.opts
        stage["ba"] = self.adjust_bundle(o.ba_loss, o.ba_f_scale, o.ba_max_iterations)
        stage["filter"] = self.filter_points()
        stage["reprojection_after_ba"] = self.observation_stats()

    # --- growing and finishing a model ----------------------------------------------------------------

    def grow(self) -> None:
        """Register images until none is left or none can be (a stall).

        The image ranked first by :meth:`next_images` is tried; one that fails waits until the next
        registration (new points may let it in). At a stall with images left, :meth:`retriangulate`
        runs once and the failed images are tried again if it brought points or observations back.
        """
        t_reg = time.perf_counter()
        failed: set[int] = set()
        retried = False
        while True:
            ranked = self.next_images(failed)
            if not ranked:
                if retried or not failed:
                    break
                t0 = time.perf_counter()
                info = self.retriangulate()
                self.stages.append({"stage": "retriangulate (stalled)", **info, "seconds": round(time.perf_counter() - t0, 3)})
                retried = True
                if info["points_new"] + info["observations_back"] == 0:
                    break
                failed.clear()
                continue
            i, n_corr = ranked[0]
            if self._register_and_grow(i, n_corr):
                failed.clear()  # new points may let a failed image in now
                retried = False
            else:
                failed.add(i)
        self.seconds["registration"] = time.perf_counter() - t_reg

    def _register_and_grow(self, i: int, n_corr: int) -> bool:
        """Register image ``i``, triangulate its new tracks, adjust and filter; the stage goes into :attr:`stages`."""
        t0 = time.perf_counter()
        info, why = self.register_next_image(i)
        if info is None:
            self.reasons[i] = why
            self.stages.append({"stage": "register", "image": i, "name": self.names[i], "registered": False,
                                "correspondences": n_corr, "note": why})
            self.say(f"not registered (yet): {self.names[i]}: {why}")
            return False
        had_X = self.has_X
        n_new = self.triangulate_image(i)
        stage = {"stage": "register", "image": i, "name": self.names[i], "registered": True, **info,
                 "new_points": n_new, "points": int(self.has_X.sum()), "reprojection_before_ba": self.observation_stats()}
        if self.should_bundle():
            self._adjust_and_filter(stage)
        elif self.opts.bundle_adjustment == "incremental":
            stage["points_refined"] = self._refine_points(self.candidate[:, i] & self.has_X & ~had_X)
            stage["filter"] = self.filter_points()
        stage["points_after"] = int(self.has_X.sum())
        stage["seconds"] = round(time.perf_counter() - t0, 3)
        self.stages.append(stage)
        self.say(f"registered {self.names[i]}: {info['pnp_inliers']}/{info['correspondences']} PnP inliers, "
                 f"{n_new} new points, {int(self.has_X.sum())} points")
        return True

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

    def finish(self) -> None:
        """The final stage: re-triangulation, noise estimate, filtering, and the final bundle adjustment.

        Observations beyond ``4 sigma`` (within [1, 4] px) are removed and a final BA polishes the
        result (:func:`final_thresholds`); where enough points are seen three or more times, the
        cameras are refined with those first and the two-view points after them
        (:meth:`_multiview_points`).
        """
        t0, o = time.perf_counter(), self.opts
        st = {"stage": "final", "reprojection_before_ba": self.observation_stats()}
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
        st["seconds"] = round(time.perf_counter() - t0, 3)
        self.stages.append(st)
        self.seconds["final_ba"] = time.perf_counter() - t0

    def end_model(self, rgb: np.ndarray) -> Reconstruction:
        """The current model as a :class:`Reconstruction` (its images leave the pool of later models).

        ``report`` holds this model's ``initial_pair``, ``stages``, ``final`` (without
        ``left_out``, which :func:`~course_lib.sfm.pipeline.run_sfm` adds once all models exist)
        and ``seconds``.
        """
        self.used |= self.registered
        rec = Reconstruction(K=self.K, image_names=list(self.names), image_size=self.image_size,
                             registered=self.registered.copy(), R_cw=self.R.copy(), t_cw=self.t.copy(), X=self.X.copy(),
                             rgb=rgb.copy(), track_uv=self.uv.copy(), inlier=self.inlier.copy())
        stats = rec.error_stats()
        rec.report = {"initial_pair": dict(self.initial), "stages": self.stages, "seconds": dict(self.seconds), "final": {
            "registered_images": rec.n_registered,
            "registered": [self.names[i] for i in np.flatnonzero(rec.registered)],
            "points": rec.n_points,
            "observations": int(rec.inlier.sum()),
            "mean_track_length": round(float(rec.inlier.sum() / max(rec.n_points, 1)), 3),
            "mean_reprojection_error_px": round(stats["mean"], 4),
            "median_reprojection_error_px": round(stats["median"], 4),
            "rms_reprojection_error_px": round(stats["rms"], 4),
            "max_reprojection_error_px": round(stats["max"], 4),
        }}
        return rec

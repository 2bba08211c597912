"""Incremental Structure from Motion on a P3 folder: the notebooks 01-05 chained into one pipeline.

:func:`run_sfm` takes the matches of a P3 folder (:func:`course_lib.data.p3.read_p3`) and returns
the largest model as a :class:`~course_lib.sfm.reconstruction.Reconstruction` (poses of the
registered images, 3-D points, inlier observations, a report of every stage), the other models in
its ``others``. It is the controller (COLMAP's ``IncrementalMapperController``): stage 1 is
:func:`course_lib.sfm.tracks.verified_pairs_and_tracks`, the rest are the methods of
:class:`~course_lib.sfm.mapper.IncrementalMapper` (shaped like COLMAP's ``IncrementalMapper``), which
return numbers; this module calls them in order, times them and records them in one
:class:`~course_lib.sfm.mapper_report.MapperReport` per model. Every setting is in one
:class:`~course_lib.sfm.mapper.MapperOptions`:

1. **Verified tracks** (notebook 01, :func:`course_lib.sfm.tracks.verified_pairs_and_tracks`):
   RANSAC on F for every image pair (the 8-point algorithm and the Sampson distance, samples
   solved in batches), then the tracks are joined from the *inlier* matches only, by union-find,
   trusted pairs first; a link that would put two features of one image into one track is
   refused, so the track is split there instead of being dropped. (The P3 reader's tracks, joined
   from the raw matches, are not used: a few wrong matches chain unrelated tracks.)
   Photos verified by ``match`` are checked by the five-point E as well: a pair whose E explains less
   than ``min_e_f_inlier_ratio`` of F's inliers (look-alike texture) gives no tracks.
2. **Initial pair** (notebooks 02, 03; ``find_initial_pair``, ``initialize``): the image with the
   most verified correspondences to other images first, then its partner with the most points
   triangulated at ``init_min_angle_deg`` or more; pure-rotation and planar pairs are named and
   skipped (a plane with enough structure off it, ``"mostly planar"``, is tried after the others,
   as COLMAP starts from planar pairs); a pair that keeps fewer than ``init_min_points`` points
   after triangulation and BA is dropped for the next. The calibrated five-point E, its four
   candidates and the cheirality test give the second camera; the first is the world frame
   (``R = I, t = 0``), the baseline has length 1.
3. **Registration** (notebook 04; ``register_next_image``): the image whose 2D-3D
   correspondences are the most and the most spread out next: PnP RANSAC then non-linear PnP; the
   pose needs ``min_pnp_inliers`` inliers and ``min_pnp_inlier_ratio`` of the matches (a pose that
   explains a fifth of them was found among look-alike texture). An image that sees too few points
   for PnP registers from its matches with two or more registered images (``register_from_pairs``,
   COLMAP's structure-less fallback). Images that fail are tried again after every registration.
   This is how UPenn images 5 and 6, which share no matches with images 1 and 2, come in.
4. **Triangulation** (notebook 03; ``triangulate_image``): the tracks the new image shares with
   every registered image, linear from its farthest partner, kept if in front, within
   ``max_reproj_px`` and seen under ``min_angle_deg`` or more.
5. **Bundle adjustment** (notebook 05; ``adjust_bundle``, ``filter_points``): after every
   registration (robust Huber loss, then observations beyond ``max_reproj_px`` are removed). When
   registration stalls with images left, ``retriangulate`` and try them again; at the end
   (``finish``) re-triangulation, a noise estimate from the median reprojection error, filtering at
   ``4 sigma`` and a final BA (plain least squares for Gaussian-like errors, Cauchy for SIFT's heavy
   tail; cameras first with the points seen three or more times).
6. **Several models**: where the model cannot grow and two or more images are left, a new model
   starts from two of those (as COLMAP does). It may register images of earlier models as it grows
   (models overlap, as COLMAP's do); one that shares images with an earlier model is merged into it
   where one similarity carries its points onto the earlier model's
   (:meth:`~course_lib.sfm.mapper.IncrementalMapper.merge`), and the merged model grows on. A ring
   that splits where one image has too few inliers from one side is closed from the other: on a
   24-view ring without a calibration file, 17 + 7 images became one model of 24. The largest
   model is returned, the others in ``others``.
7. **A camera without calibration** (``match`` without ``--K``: ``SIMPLE_RADIAL``, refined in the
   BAs of the whole model): where its focal length is a guess (no EXIF), stage 1 first estimates it
   from the verified pairs' fundamental matrices (:mod:`course_lib.sfm.self_calibration`, option
   ``self_calibration``) and checks the pairs with that K. While the first model grows, where its
   refined focal length moves more than ``focal_restart_change`` from the one it started from, a BA
   run to convergence says where the images put it, and the mapping starts again from there
   (:class:`_FocalWatch`, ``focal_restarts``), so a wrong start cannot lock in a wrong model. ``report["self_calibration"]`` and
   ``report["focal_restarts"]`` say what happened.

P3 data quirks handled upstream by the reader (:mod:`course_lib.data.p3`): duplicate rows are
merged, features are identified by equal coordinates. Matches contain outliers on purpose
(step 1). ``Reconstruction.track_uv`` holds the verified tracks (not ``P3Data.track_uv``).

Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from course_lib.sfm.mapper import IncrementalMapper, MapperOptions
from course_lib.sfm.mapper_ba import REFINE_FROM_IMAGES
from course_lib.sfm.mapper_options import relaxed
from course_lib.sfm.mapper_report import MapperReport
from course_lib.sfm.self_calibration import focal_from_fundamentals
from course_lib.sfm.tracks import verified_pairs_and_tracks
from course_lib.sfm.reconstruction import Reconstruction, image_size_of, reprojection_error_matrix, triangulation_angles_deg
from course_lib.threads import single_threaded_blas
from course_lib.validate import KitInputError, intrinsics

__all__ = ["Reconstruction", "MapperOptions", "run_sfm", "triangulation_angles_deg", "reprojection_error_matrix"]


def run_sfm(data, rng: np.random.Generator, options: MapperOptions | None = None, **overrides) -> Reconstruction:
    """Incremental SfM on a P3 data set: verified tracks, then one or more models grown by :class:`~course_lib.sfm.mapper.IncrementalMapper`.

    Args:
        data: a :class:`course_lib.data.p3.P3Data` (``K``, ``image_names``, ``track_uv``,
            ``track_rgb``, ``matches``; ``image_size`` if the images are present).
        rng: seeded ``numpy.random.Generator`` (RANSAC on F and PnP draw from it).
        options: :class:`~course_lib.sfm.mapper.MapperOptions` (default: its defaults).
        **overrides: any field of :class:`~course_lib.sfm.mapper.MapperOptions` by name, e.g.
            ``bundle_adjustment="none"`` (the result before BA, notebook 05's starting point).

    Returns:
        The largest model (most images, then most points) as a :class:`Reconstruction`; the other
        models, largest first, in its ``others``. Its ``report`` holds ``pairs`` (matches / RANSAC
        inliers per pair), ``tracks`` (raw and verified tracks, refused links),
        ``degenerate_pairs`` (pairs not used to start: ``"identical or near-identical photos"``,
        ``"pure rotation"`` or ``"planar"``; and ``"mostly planar"``: tried after the others),
        ``initial_pair``, ``stages`` (one entry per registration attempt: PnP inliers, new points,
        reprojection error before and after BA, seconds), ``left_out`` (each image not in this
        model, with the reason), ``final`` (registered images, points, observations, mean / median
        / rms reprojection error), ``models`` (one summary per model: images, points, folder name)
        and ``seconds``. Each model in ``others`` has the same keys for itself.

    Raises:
        KitInputError: bad data or options, or no image pair can start a model (the message says why).

    Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
    """
    t_start = time.perf_counter()
    opts = MapperOptions.from_keywords(options, **overrides)
    K = _check_inputs(data, rng)
    size = image_size_of(data)
    data = _by_photo_names(data)
    report: dict = {"n_images": len(data.image_names), "options": opts.summary()}
    with single_threaded_blas():
        refine = opts.refine_intrinsics if opts.refine_intrinsics is not None else bool(getattr(data.camera, "refine", False))
        calibrate = _self_calibration(data, opts, size, report) if refine else None
        pairs, tracks = verified_pairs_and_tracks(data, rng, opts.f_threshold_px, opts.min_pair_matches, report,
                                                  opts.min_e_f_inlier_ratio, calibrate)
        K = report["self_calibration"].pop("K") if "self_calibration" in report else K
        t_ransac = time.perf_counter() - t_start
        mapper, models, reasons, t_again = _map_with_focal_restarts(data, pairs, tracks, K, size, opts, rng, refine, report)
        t_ransac += t_again
    report["degenerate_pairs"] = list(mapper.degenerate.values())
    rec = _assemble(models, reasons, report)
    for m in [rec] + rec.others:  # the camera's prior is the one the data gave, the start the one the mapping began from
        if "prior_focal_px" in m.report.get("camera", {}):
            m.report["camera"]["start_focal_px"] = m.report["camera"]["prior_focal_px"]
            m.report["camera"]["prior_focal_px"] = round(float(intrinsics(data.K)[0, 0]), 3)
    rec.report["seconds"] = {"ransac_F": round(t_ransac, 3), **{k: round(v, 3) for k, v in rec.report["seconds"].items()},
                             "focal_restarts": round(sum(r["seconds"] for r in report["focal_restarts"]), 3),
                             "total": round(time.perf_counter() - t_start, 3)}
    _say_final(rec, opts.verbose)
    return rec


def _check_inputs(data, rng) -> np.ndarray:
    """The intrinsics of ``data`` after checking ``rng`` and the arrays run_sfm needs."""
    if not isinstance(rng, np.random.Generator):
        raise KitInputError(f"rng must be a numpy.random.Generator (np.random.default_rng(seed)), got {type(rng).__name__}")
    for attr in ("K", "image_names", "track_uv", "track_rgb", "matches"):
        if not hasattr(data, attr):
            raise KitInputError(f"data has no attribute {attr!r}: pass the P3Data returned by course_lib.data.p3.read_p3")
    K = intrinsics(data.K)
    uv = np.asarray(data.track_uv, float)
    M = len(data.image_names)
    if uv.ndim != 3 or uv.shape[1:] != (M, 2):
        raise KitInputError(f"data.track_uv has shape {uv.shape}: expected (T, {M}, 2) for {M} images")
    if M < 2:
        raise KitInputError(f"data has {M} image(s): SfM needs at least two")
    return K


#: A focal length has settled where two successive refinements differ by less than this (relative).
FOCAL_SETTLED = 0.02
#: A refined focal length this many times (or this fraction of) the start restarts the mapping without waiting
#: for it to settle: the start was plainly wrong, and a model grown on from it holds the focal length back.
FOCAL_JUMP = 1.5
#: A focal length that the converged BA (:meth:`~course_lib.sfm.mapper_ba.MapperBundleAdjustment.converge_intrinsics`)
#: puts this far (relative) from the start restarts the mapping; nearer, the model grows on. At 8 images that BA's
#: focal length scatters by 2-6 % on the narrow rings (f2k-ring-24: 1480-1573 px for 1536), so a 5 % rule restarted
#: them again and again.
FOCAL_CONVERGED_CHANGE = 0.1
#: Stage 1's calibrated check is redone after a focal restart where the focal length moved more than this
#: (relative) from the one it checked with (its 4 px Sampson threshold tolerates less).
RECHECK_FOCAL_CHANGE = 0.1


def _self_calibration(data, opts: MapperOptions, size, report: dict):
    """The function stage 1 calls on the verified pairs to self-calibrate the focal length, or None where it is not wanted.

    ``opts.self_calibration``: ``"auto"`` where the camera's focal length is a guess (``camera.json`` of
    ``match`` without ``--K`` and without EXIF), ``"always"`` wherever the intrinsics are refined. The
    function records :func:`course_lib.sfm.self_calibration.focal_from_fundamentals`'s result in
    ``report["self_calibration"]`` (with the K used, ``"K"``, which run_sfm takes out of the report) and
    returns the K with the estimated focal length (the guess where the pairs do not determine it).
    """
    guessed = str(getattr(data.camera, "source", "")).startswith("guess")
    if opts.self_calibration == "never" or (opts.self_calibration == "auto" and not guessed):
        return None

    def calibrate(verifications: dict) -> np.ndarray:
        t0 = time.perf_counter()
        K = intrinsics(data.K).copy()
        good = [v for v in verifications.values() if v.F is not None and v.n_inliers >= opts.min_pair_matches]
        est = focal_from_fundamentals(np.array([v.F for v in good]).reshape(-1, 3, 3), np.array([v.n_inliers for v in good]),
                                      size, float(K[0, 0]), (K[0, 2], K[1, 2]))
        if est.focal_px is not None:
            K[0, 0] = K[1, 1] = est.focal_px
        report["self_calibration"] = {**est.summary(), "seconds": round(time.perf_counter() - t0, 3), "K": K}
        if opts.verbose:
            print(f"self-calibration from {est.pairs} pairs: f = {est.focal_px:.1f} px (the guess was {est.guess_px:.1f})"
                  if est.focal_px is not None else f"self-calibration: {est.note}")
        return K

    return calibrate


def _by_photo_names(data):
    """``data`` with its images named as the user's photos (:attr:`course_lib.data.p3.P3Data.photo_names`: the names
    ``match`` read them under), so that the report, the COLMAP model and ``scene.html`` keep them; ``data`` itself
    where the names are the same (a course P3 folder)."""
    names = getattr(data, "photo_names", None)
    if names is None or list(names) == list(data.image_names) or not dataclasses.is_dataclass(data):
        return data
    return dataclasses.replace(data, image_names=list(names), source_names=None)


def _map_with_focal_restarts(data, pairs: dict, tracks, K: np.ndarray, size, opts: MapperOptions, rng, refine: bool,
                             report: dict) -> tuple:
    """The models of the verified pairs and tracks, the mapping started again where the first model's focal length moved.

    Where the intrinsics are refined, a :class:`_FocalWatch` watches the first model; where it raises
    :class:`_FocalMoved`, the mapping starts again from the refined focal length (the row goes to
    ``report["focal_restarts"]``), with stage 1 redone where its calibrated check used a focal length more
    than :data:`RECHECK_FOCAL_CHANGE` away.

    Returns:
        ``(mapper, models, reasons, seconds of stage 1 redone)``.
    """
    restarts = report["focal_restarts"] = []
    f_checked, t_again = float(K[0, 0]), 0.0  # the focal length of stage 1's calibrated check
    hold_until = REFINE_FROM_IMAGES  # a focal length from a converged BA is held until as many images hold it again
    while True:
        report["n_tracks"] = len(tracks.uv)
        tr = report["tracks"]
        if opts.verbose:
            print(f"{report['verification']}: {len(pairs)} pairs verified; {tr['verified_tracks']} tracks from {tr['verified_matches']} "
                  f"inlier matches ({tr['refused_links']} links refused: they joined two features of one image)")
        mapper = IncrementalMapper(data, pairs, tracks.uv, K, size, opts, rng, refine_intrinsics=refine,
                                   refine_from_images=hold_until)
        watch = _FocalWatch(float(K[0, 0]), opts) if refine and len(restarts) < opts.focal_restarts else None
        t_try = time.perf_counter()
        try:
            models, reasons = _build_models(mapper, tracks.rgb, pairs, watch)
            return mapper, models, reasons, t_again
        except _FocalMoved as moved:
            restarts.append({**moved.row, "seconds": round(time.perf_counter() - t_try, 3)})
            if opts.verbose:
                print(f"the focal length moved from {moved.row['from_px']:.1f} to {moved.row['to_px']:.1f} px while the first "
                      f"model grew ({moved.row['images']} images): starting again from {moved.row['to_px']:.1f} px")
            K = K.copy()
            K[0, 0] = K[1, 1] = moved.row["to_px"]
            hold_until = max(REFINE_FROM_IMAGES, moved.row["images"]) if moved.row["converged"] else REFINE_FROM_IMAGES
            if (getattr(data, "two_view", None) is not None and opts.min_e_f_inlier_ratio > 0
                    and abs(np.log(K[0, 0] / f_checked)) > np.log(1.0 + RECHECK_FOCAL_CHANGE)):  # its calibrated check used K
                t0 = time.perf_counter()
                pairs, tracks = verified_pairs_and_tracks(data, rng, opts.f_threshold_px, opts.min_pair_matches, report,
                                                          opts.min_e_f_inlier_ratio, lambda _, K=K: K)
                f_checked = float(K[0, 0])
                t_again += time.perf_counter() - t0


class _FocalMoved(Exception):
    """Raised while the first model grows when the refined focal length left the one it started from (:class:`_FocalWatch`)."""

    def __init__(self, row: dict):
        super().__init__(f"focal length moved: {row}")
        self.row = row


@dataclass
class _FocalWatch:
    """Watches the refined focal length while the first model grows: a wrong start must not lock in a wrong model.

    A model grown from a focal length far from the true one is distorted from its initial pair on;
    the bundle adjustments move the focal length towards the truth as images come in, but the
    model they move is already bent (a ring around the building, started 80 % too long, ended
    1.5 degrees off with the right focal length). So once the model holds ``focal_restart_min_images`` images (fewer
    hardly fix it; all of them in a smaller set) and its refined focal length is more than ``focal_restart_change``
    from the one it started from:

    * where it has moved :data:`FOCAL_JUMP` times away (the ring at 3x the guess, started from 370 px for 2304: 942 px
      at 8 images, then held at 1058 px, under ``max_focal_change`` of the start, by a model that went on to all 24
      images), or has settled (the last two refinements within :data:`FOCAL_SETTLED`), or at the model's end, the
      mapping starts again from it;
    * where it is still moving, a BA of the whole model is run to convergence, once a mapping
      (:meth:`~course_lib.sfm.mapper_ba.MapperBundleAdjustment.converge_intrinsics`): the incremental BAs' few
      iterations move it only part of the way (f2k-ring-24: 1012 px at 8 images where the converged BA gives 1543,
      the truth 1536; waiting for it to settle or reach 1.5x took three more restarts, 5.6 of 8.2 s of ``sfm``).
      Where that focal length is more than :data:`FOCAL_CONVERGED_CHANGE` from the start, the mapping starts again
      from it, and the new mapping holds it until it has as many images (a few views would move it away again:
      1543 -> 1240 px at 8 images); nearer, the model grows on, and from then on only a move of more than
      :data:`FOCAL_CONVERGED_CHANGE` restarts it.

    A set of ``focal_restart_min_images`` images or fewer is judged only when all of them are in the model; there a
    focal length under :data:`FOCAL_JUMP` from its start restarts nothing: the mapping would register the same images
    again, and the BAs of the whole model refine f as well (the course's 5 WPI and 6 UPenn photos without K: the same
    poses, within 0.003 deg, and focal length, within 0.3 px, in half the time of ``sfm``).

    At most ``focal_restarts`` restarts.
    """

    start_px: float
    opts: MapperOptions
    converged: bool = False  # this mapping's converged BA is done

    def check(self, mapper: IncrementalMapper, at_end: bool = False) -> None:
        n, f = int(mapper.registered.sum()), float(mapper.K[0, 0])
        moved = abs(np.log(f / self.start_px))
        if n < min(self.opts.focal_restart_min_images, mapper.M) or moved <= np.log1p(self.opts.focal_restart_change):
            return  # a few views hardly fix it, also at the end
        if mapper.M <= self.opts.focal_restart_min_images and moved <= np.log(FOCAL_JUMP):
            return  # a small set, all in the model: a restart maps the same images again; the final BA refines f
        fs = [e["f"] for e in mapper.intrinsics_log if e["accepted"]]
        settled = len(fs) >= 2 and abs(np.log(fs[-1] / fs[-2])) < np.log1p(FOCAL_SETTLED)
        # after the converged BA, a nearer focal length is within its scatter: the model grows on
        change = np.log1p(FOCAL_CONVERGED_CHANGE if self.converged else self.opts.focal_restart_change)
        if moved > np.log(FOCAL_JUMP) or ((settled or at_end) and moved > change):
            raise _FocalMoved(self._row(f, n, at_end, converged=False))
        if not self.converged:  # still moving: where do the images put it?
            self.converged = True
            row = mapper.converge_intrinsics()
            if row.get("accepted") and abs(np.log(row["f"] / self.start_px)) > np.log1p(FOCAL_CONVERGED_CHANGE):
                raise _FocalMoved(self._row(row["f"], n, at_end, converged=True))

    def _row(self, f: float, n: int, at_end: bool, converged: bool) -> dict:
        """The row of a restart in ``report["focal_restarts"]``."""
        return {"from_px": round(self.start_px, 3), "to_px": round(float(f), 3), "images": n, "at_end": bool(at_end),
                "converged": converged}


def _build_models(mapper: IncrementalMapper, rgb: np.ndarray, pairs: dict, watch: _FocalWatch | None = None) -> tuple[list, list]:
    """Grow models until no pair of the images left can start one; ``(models, reasons)``, one reasons dict per model.

    Each model has its :class:`~course_lib.sfm.mapper_report.MapperReport`, which becomes its
    ``report``. A later model that registers images of an earlier one is merged into it
    (:func:`_merge`) and the merged model grows on. A model after the first with fewer than
    ``min_model_size`` images is discarded; its images are left out with that reason. ``watch``: raise
    :class:`_FocalMoved` where the first model's focal length moves away from its start (:class:`_FocalWatch`).
    """
    opts = mapper.opts
    built: list[tuple] = []  # (Reconstruction, MapperReport, the mapper's state) per model
    discarded = {}
    while len(built) < opts.max_models and (~mapper.used).sum() >= 2:
        report = MapperReport(mapper.names, opts.verbose)
        _start_model(mapper, report, relax=not built)
        if not mapper.registered.any():
            if not built:
                raise KitInputError(_no_start_message(mapper, report.candidates, pairs))
            break
        _grow_and_finish(mapper, report, None if built else watch)
        report, built = _merge(mapper, report, built)
        rec = mapper.end_model(rgb)
        rec.report = report.model_report(rec, mapper.camera())
        if built and rec.n_registered < opts.min_model_size:
            why = (f"in a model of only {rec.n_registered} images ({', '.join(rec.report['final']['registered'])}): "
                   f"fewer than min_model_size={opts.min_model_size}, discarded")
            discarded.update({int(i): why for i in np.flatnonzero(rec.registered)})
            continue
        built.append((rec, report, mapper.state()))
        if not opts.multiple_models:
            break
    reasons = [dict(report.reasons) for _, report, _ in built]
    for r in reasons:
        r.update(discarded)
    return [rec for rec, _, _ in built], reasons


def _grow_and_finish(mapper: IncrementalMapper, report: MapperReport, watch: _FocalWatch | None = None) -> None:
    """Register what can be, finish, and give the images still left a last try (the final BA and re-triangulation may let them in)."""
    _grow(mapper, report, watch)
    _finish(mapper, report)
    if watch is not None:
        watch.check(mapper, at_end=True)
    n = int(mapper.registered.sum())
    _grow(mapper, report)
    if mapper.registered.sum() > n:
        _finish(mapper, report)


def _merge(mapper: IncrementalMapper, report: MapperReport, built: list) -> tuple[MapperReport, list]:
    """Merge the mapper's model into every earlier model it shares images with; ``(its report, the models left)``.

    Each merge (:meth:`~course_lib.sfm.mapper.IncrementalMapper.merge`) carries the smaller of the
    two models into the larger one's frame; the earlier model's report takes the later one's stages
    (:meth:`~course_lib.sfm.mapper_report.MapperReport.absorb`). After a merge the merged model grows
    on and is finished again: the images neither model could reach may register now.
    """
    merged = False
    for k in range(len(built)):
        rec, earlier, state = built[k]
        if not (state["registered"] & mapper.registered).any():
            continue
        t0 = time.perf_counter()
        numbers, why = mapper.merge(state)
        if numbers is None:
            names = rec.report["final"]["registered"]
            report.say(f"not merged with the earlier model of {len(names)} images ({', '.join(names[:3])}, ...): {why}")
            continue
        report = earlier.absorb(report, numbers, time.perf_counter() - t0)
        built[k] = None
        merged = True
    built = [b for b in built if b is not None]
    if merged:
        _grow_and_finish(mapper, report)
    return report, built


def _start_model(mapper: IncrementalMapper, report: MapperReport, relax: bool) -> None:
    """Try the candidate pairs until one starts a model; the rows of the pairs tried and the relaxations made go to ``report``.

    Where none does and ``relax`` (no model yet), the initialization is relaxed (a new options
    object, :func:`~course_lib.sfm.mapper_options.relaxed`) and the candidates tried again.
    """
    tried, made = report.candidates, report.relaxations
    t_search = time.perf_counter()  # the candidates are scored as they are yielded: the stage counts them
    mapper.begin_model()
    for step in range(mapper.opts.init_relaxations + 1 if relax else 1):
        if step:
            mapper.use_options(relaxed(mapper.opts))
            made.append({"min_pair_inliers": mapper.opts.min_pair_inliers, "init_min_angle_deg": mapper.opts.init_min_angle_deg})
            report.say(f"no pair starts a model: relaxed to min_pair_inliers={mapper.opts.min_pair_inliers}, "
                       f"init_min_angle_deg={mapper.opts.init_min_angle_deg}")
        for pair in mapper.find_initial_pair():
            tried.append(pair.row())
            t0 = time.perf_counter()
            numbers = mapper.initialize(pair)
            if numbers is not None:
                report.started(pair, numbers, time.perf_counter() - t0, time.perf_counter() - t_search)
                return
            if pair.images in mapper.failed_starts:
                report.start_failed(pair.images, mapper.failed_starts[pair.images], mapper.opts.init_min_points)


def _grow(mapper: IncrementalMapper, report: MapperReport, watch: _FocalWatch | None = None) -> None:
    """Register images until none is left or none can be (a stall).

    The image ranked first by :meth:`~course_lib.sfm.mapper.IncrementalMapper.next_images` is
    tried; one that fails waits until the next registration (new points may let it in). At a stall
    with images left, ``retriangulate`` runs once and the failed images are tried again if it
    brought points or observations back.
    """
    failed: set[int] = set()
    retried = False
    with report.timing("registration"):
        while True:
            ranked = mapper.next_images(failed)
            if not ranked:
                if retried or not failed:
                    break
                t0 = time.perf_counter()
                info = mapper.retriangulate()
                report.retriangulated(info, time.perf_counter() - t0)
                retried = True
                if info["points_new"] + info["observations_back"] == 0:
                    break
                failed.clear()
                continue
            i, n_corr = ranked[0]
            t0 = time.perf_counter()
            numbers, why = mapper.add_image(i)
            if numbers is None:
                report.not_registered(i, n_corr, why)
                failed.add(i)
            else:
                report.registered(i, numbers, time.perf_counter() - t0)
                if watch is not None:
                    watch.check(mapper)
                failed.clear()  # new points may let a failed image in now
                retried = False


def _finish(mapper: IncrementalMapper, report: MapperReport) -> None:
    """The model's final stage (:meth:`~course_lib.sfm.mapper.IncrementalMapper.finish`), timed and recorded."""
    t0 = time.perf_counter()
    numbers = mapper.finish()
    report.finished(numbers, time.perf_counter() - t0)


def _no_start_message(mapper: IncrementalMapper, tried: list, pairs: dict) -> str:
    """One line: why no image pair could start the reconstruction."""
    o = mapper.opts
    degenerate = [d for d in mapper.degenerate.values() if d["kind"] != "mostly planar"]
    why = "; ".join(f"{d['names'][0]}-{d['names'][1]}: {d['kind']}" + (
        " (no baseline: the matches do not move)" if d["kind"].startswith("identical") else
        f" (a homography explains {100 * d['homography_share']:.0f} % of the matches)") for d in degenerate[:6])
    msg = (f"no image pair can start the reconstruction: none has {o.min_pair_inliers} or more verified matches with "
           f"{o.init_min_points} or more points triangulated at {o.init_min_angle_deg} degrees or more")
    if tried:
        msg += (f"; the {len(tried)} pair(s) tried kept fewer than {o.init_min_points} points after triangulation and bundle "
                "adjustment")
    if degenerate:
        return msg + (f". Degenerate pairs: {why}. Take photos from different positions (not only turning the camera) "
                      "and of a scene that is not a single plane")
    return msg + (f": the matches are too few or too noisy ({len(pairs)} pair(s) verified)")


def _left_out(rec: Reconstruction, k: int, models: list, reasons: list, verified: set) -> list[dict]:
    """The images not in model ``k``, each with its reason."""
    rows = []
    for i in np.flatnonzero(~rec.registered):
        other = [m for m, r in enumerate(models) if r.registered[i]]
        if other:
            why = f"in model {other[0] + 1} ({model_folder(other[0])}/), which this model could not reach"
        elif i not in verified:
            why = "no verified matches with any other image (no pair passed RANSAC on F with enough inliers)"
        else:
            why = reasons[k].get(int(i)) or next((r[int(i)] for r in reasons if int(i) in r), "not registered")
        rows.append({"image": int(i), "name": rec.image_names[i], "reason": why})
    return rows


def model_folder(k: int) -> str:
    """The folder name of model ``k`` (0 = the largest): ``colmap``, ``colmap-1``, ``colmap-2``, ..."""
    return "colmap" if k == 0 else f"colmap-{k}"


def _assemble(models: list, reasons: list, shared: dict) -> Reconstruction:
    """The largest model with the others in ``others``; every report gets the shared keys, ``left_out`` and ``models``."""
    order = sorted(range(len(models)), key=lambda m: (-models[m].n_registered, -models[m].n_points, m))
    models, reasons = [models[m] for m in order], [reasons[m] for m in order]
    verified = {i for p in shared["pairs"] if "note" not in p for i in p["pair"]}
    summary = [{"model": k + 1, "folder": model_folder(k), "registered_images": r.n_registered,
                "registered": r.report["final"]["registered"], "points": r.n_points,
                "mean_reprojection_error_px": r.report["final"]["mean_reprojection_error_px"],
                "initial_pair": r.report["initial_pair"].get("names")} for k, r in enumerate(models)]
    for k, rec in enumerate(models):
        own = rec.report
        rec.report = {**shared, **own, "model": k + 1, "left_out": _left_out(rec, k, models, reasons, verified),
                      "models": summary}
        rec.report["final"]["left_out"] = {d["name"]: d["reason"] for d in rec.report["left_out"]}
    models[0].others = models[1:]
    return models[0]


def _say_final(rec: Reconstruction, verbose: bool) -> None:
    if not verbose:
        return
    M = len(rec.image_names)
    for d in rec.report["left_out"]:
        print(f"left out: {d['name']}: {d['reason']}")
    for m in [rec] + rec.others:
        s = m.error_stats()
        print(f"model {m.report['model']}: {m.n_registered}/{M} images, {m.n_points} points, mean reprojection error "
              f"{s['mean']:.3f} px")

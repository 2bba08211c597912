"""Every setting of the incremental mapper in one dataclass, :class:`MapperOptions`, and how to set one by name.

Each field has COLMAP's default beside it (``IncrementalMapper::Options``,
``IncrementalPipelineOptions``) where COLMAP has one. Options are never changed in place: a
changed copy is made (:meth:`MapperOptions.from_keywords`, :func:`relaxed`). The command line
reaches every field with ``--option KEY=VALUE`` (:func:`parse_assignments`).

Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
"""

from __future__ import annotations

import typing
from dataclasses import asdict, dataclass, fields, replace

from course_lib.validate import KitInputError

__all__ = ["MapperOptions", "relaxed", "parse_assignments"]


@dataclass(frozen=True)
class MapperOptions:
    """Every setting of the incremental mapper, with COLMAP's default where it has one.

    The kit's data sets are small (5-100 images, 400-1280 px), so a few thresholds are looser than
    COLMAP's; each is stated.

    Attributes:
        f_threshold_px: Sampson threshold for the pairs (px); only matches within it join tracks.
            (COLMAP two-view ``max_error`` 4 px.)
        min_pair_matches: a pair needs this many inliers to give tracks. (COLMAP
            ``min_num_matches`` 15, ``min_num_inliers`` 15.)
        min_e_f_inlier_ratio: on photos verified by ``match``, a pair whose five-point E explains
            less than this share of F's inliers gives no tracks (look-alike texture; 0: no check;
            :func:`course_lib.sfm.tracks.check_calibrated`). (COLMAP ``min_E_F_inlier_ratio`` 0.95,
            which labels such pairs rather than dropping them.)
        pnp_threshold_px: PnP RANSAC threshold on the reprojection error (px). (COLMAP
            ``abs_pose_max_error`` 12 px.)
        min_pnp_inliers: an image registers with at least this many PnP inliers. (COLMAP
            ``abs_pose_min_num_inliers`` 30.)
        min_pnp_inlier_ratio: ... and with at least this share of its 2D-3D matches among them: a
            pose that explains a fifth of them was found among look-alike texture. (COLMAP
            ``abs_pose_min_inlier_ratio`` 0.25.)
        structure_less_fallback: an image PnP cannot register (too few triangulated points among
            its features) is registered from its matches with two or more registered images
            instead (:meth:`course_lib.sfm.mapper.IncrementalMapper.register_from_pairs`). (COLMAP
            ``structure_less_registration_fallback``.)
        pnp_retries, pnp_retry_factor: where a new pose's inliers have a median error over
            ``pnp_retry_factor`` times the median of the model's earlier registrations, PnP RANSAC
            runs ``pnp_retries`` more times and the pose of lowest truncated error is kept (a narrow
            field of view has two nearly equal poses; 0: never).
            (:class:`course_lib.sfm.registration.ImageRegistration`). (COLMAP: none.)
        relocalize_tries: once a model is finished, PnP RANSAC runs this many times per registered image on
            the model's points; where it finds another pose, the one of lower cost after a local BA is kept
            (:func:`course_lib.sfm.relocalization.relocalize`; 0: never). (COLMAP: none.)
        max_reproj_px: observations reprojecting farther are dropped during the run. (COLMAP
            ``filter_max_reproj_error`` 4 px.)
        final_max_reproj_px: the threshold before the final BA; None: 4 x the noise level estimated
            from the median reprojection error, within [1, 4] px.
        min_angle_deg: smallest triangulation angle of a kept point. (COLMAP
            ``filter_min_tri_angle`` 1.5 deg.)
        init_min_angle_deg: angle a point of a candidate initial pair must have to count in its
            score. (COLMAP asks a *median* angle of ``init_min_tri_angle`` 16 deg: too strict for a
            walk past a building.)
        init_max_error_px: threshold of the initial pair's five-point RANSAC and pose refinement
            (Sampson distance, px). (COLMAP ``init_max_error`` 4 px.)
        min_pair_inliers: inliers a pair needs to be an initial pair. (COLMAP
            ``init_min_num_inliers`` 100.)
        init_min_points: points an initial pair must score, and keep after triangulation, BA and
            filtering, to start a model; otherwise the next candidate is tried. (COLMAP: > 0.)
        init_max_trials: candidate pairs tried per model at most. (COLMAP ``init_num_trials`` 200.)
        init_relaxations: when no pair starts the first model, ``min_pair_inliers`` and
            ``init_min_angle_deg`` are halved and the candidates tried again, up to this many
            times (:func:`relaxed`). (COLMAP relaxes ``init_min_num_inliers`` and
            ``init_min_tri_angle`` the same way, twice each.)
        multiple_models: start new models from the images left when registration stalls.
            (COLMAP ``multiple_models`` true.)
        max_models: the most models. (COLMAP ``max_num_models`` 50.)
        min_model_size: a model after the first one is kept only with this many images; its images
            are then left out with the reason. (COLMAP ``min_model_size`` 10, or 80 % of the images
            where fewer.)
        merge_min_shared_images: a later model that shares this many registered images with an
            earlier one is merged into it where the points agree
            (:meth:`course_lib.sfm.mapper.IncrementalMapper.merge`). A later model starts from two
            images no earlier model registered, but may register the images of earlier models as
            it grows (COLMAP's models overlap the same way).
        merge_min_inlier_ratio: the share of the points both models triangulated that one
            similarity must carry onto the other (within ``max_reproj_px`` in every image of the
            earlier model that sees them; at least ``init_min_points`` of them) for the merge to go ahead.
        bundle_adjustment: ``"incremental"`` (during the growth and at the end), ``"final"`` (once
            at the end) or ``"none"`` (the result *before* BA: notebook 05's starting point).
        ba_loss, ba_f_scale: robust loss of the BAs during the growth. (COLMAP: plain squares; the
            kit's Huber at 1 px bounds the pull of the outliers that its looser thresholds let in.)
        ba_max_iterations: iteration cap of each BA of the whole model during the growth. These only
            have to hold the model together for the next registration: the final BA polishes.
            (COLMAP ``ba_global_max_num_iterations`` 50.)
        ba_images_ratio: with ``"incremental"``, a registration is followed by a BA of the whole
            model (always up to 6 images) when the model has grown by this factor since the last
            one; the other registrations get a *local* BA (``ba_local_num_images``). (COLMAP
            ``ba_global_frames_ratio`` 1.1; OpenSfM ``bundle_new_points_ratio`` 1.2.)
        ba_local_num_images: the images a local BA refines: the new one and those that share the
            most points with it; the points they see are refined, the other cameras that see those
            points are held fixed. (COLMAP ``ba_local_num_images`` 6.)
        ba_local_max_iterations: iteration cap of a local BA. (COLMAP ``ba_local_max_num_iterations`` 25.)
        final_ba_max_iterations: iteration cap of each final BA. (COLMAP
            ``ba_global_max_num_iterations`` 50.)
        final_ba_loss, final_ba_f_scale: loss of the final BA; ``"auto"``: Cauchy at ``f_scale``
            (None: twice the estimated noise, at least 0.3 px) when the errors have a heavy tail
            (SIFT), plain least squares otherwise (:func:`course_lib.sfm.mapper.final_thresholds`).
        refine_intrinsics: refine the focal length and one radial term (``SIMPLE_RADIAL``, shared by
            all images) in the BAs of the whole model; None: where the P3 folder says K was
            estimated (``camera.json`` of ``match`` without ``--K``). (COLMAP
            ``ba_refine_focal_length`` and ``ba_refine_extra_params`` true.)
        max_focal_change: a refined focal length further than this factor from the prior is
            rejected (the BA is redone with the intrinsics held). (COLMAP ``max_focal_length_ratio`` 10.)
        max_k1: a refined ``|k1|`` above this is rejected likewise (the BA is then redone with ``k1``
            held). (COLMAP ``max_extra_param`` 1.)
        refine_k1_from_images: ``k1`` is held (the focal length alone refined) until the model holds
            this many images. (COLMAP: from the start.)
        min_k1_effect_px: ``k1`` is held where ``k1 = 0.1`` would move the image's corners by less than
            this (a narrow field of view: 640 px wide at f = 1536 px, 2.7 px), where it trades off against
            the focal length. (COLMAP: none.)
        self_calibration: estimate the focal length from the verified pairs before the mapper starts
            (:mod:`course_lib.sfm.self_calibration`), where the intrinsics are refined: ``"auto"`` where
            the focal length is a guess (no calibration file, no EXIF), ``"always"``, or ``"never"``.
            (COLMAP: none; it starts from the guess.)
        focal_restarts, focal_restart_change, focal_restart_min_images: where the intrinsics are
            refined and the focal length the first model has refined moves more than
            ``focal_restart_change`` (relative) from the one it started from, once it holds
            ``focal_restart_min_images`` images or at its end, the mapping starts again from the
            refined focal length (the first time, from a BA of the whole model run to convergence), at most
            ``focal_restarts`` times (0: never), so that a wrong prior cannot lock in a wrong model
            (:class:`course_lib.sfm.pipeline._FocalWatch`). (COLMAP: none.)
        initial_pair: force the initial pair ``(i, j)`` (0-based) of the first model.
        verbose: print one line per stage.
    """

    f_threshold_px: float = 2.0
    min_pair_matches: int = 16
    min_e_f_inlier_ratio: float = 0.9
    pnp_threshold_px: float = 8.0
    min_pnp_inliers: int = 20
    min_pnp_inlier_ratio: float = 0.25
    structure_less_fallback: bool = True
    pnp_retries: int = 3
    pnp_retry_factor: float = 1.4
    relocalize_tries: int = 2
    max_reproj_px: float = 4.0
    final_max_reproj_px: float | None = None
    min_angle_deg: float = 1.0
    init_min_angle_deg: float = 2.0
    init_max_error_px: float = 4.0
    min_pair_inliers: int = 50
    init_min_points: int = 20
    init_max_trials: int = 50
    init_relaxations: int = 2
    multiple_models: bool = True
    max_models: int = 10
    min_model_size: int = 3
    merge_min_shared_images: int = 1
    merge_min_inlier_ratio: float = 0.5
    bundle_adjustment: str = "incremental"
    ba_loss: str = "huber"
    ba_f_scale: float = 1.0
    ba_max_iterations: int = 5
    ba_images_ratio: float = 1.1
    ba_local_num_images: int = 6
    ba_local_max_iterations: int = 10
    final_ba_max_iterations: int = 20
    final_ba_loss: str = "auto"
    final_ba_f_scale: float | None = None
    refine_intrinsics: bool | None = None
    max_focal_change: float = 3.0
    max_k1: float = 1.0
    refine_k1_from_images: int = 8
    min_k1_effect_px: float = 5.0
    self_calibration: str = "auto"
    focal_restarts: int = 4
    focal_restart_change: float = 0.05
    focal_restart_min_images: int = 8
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
        if opts.self_calibration not in ("auto", "always", "never"):
            raise KitInputError(f"self_calibration={opts.self_calibration!r}: expected 'auto', 'always' or 'never'")
        if opts.ba_images_ratio < 1.0 or opts.ba_local_num_images < 2:
            raise KitInputError(f"ba_images_ratio={opts.ba_images_ratio}, ba_local_num_images={opts.ba_local_num_images}: "
                                "expected a ratio >= 1 and at least 2 images")
        return opts

    def summary(self) -> dict:
        """The options the report records."""
        keep = ("f_threshold_px", "min_e_f_inlier_ratio", "pnp_threshold_px", "max_reproj_px", "final_max_reproj_px", "min_angle_deg",
                "bundle_adjustment", "ba_loss", "ba_f_scale", "ba_images_ratio", "ba_local_num_images", "final_ba_loss",
                "final_ba_f_scale", "init_min_points", "min_model_size", "multiple_models",
                "merge_min_shared_images", "refine_intrinsics", "self_calibration")
        return {k: getattr(self, k) for k in keep}


def relaxed(opts: MapperOptions) -> MapperOptions:
    """A copy with ``min_pair_inliers`` and ``init_min_angle_deg`` halved (COLMAP's relaxation when no model starts)."""
    return replace(opts, min_pair_inliers=max(opts.min_pair_matches, opts.min_pair_inliers // 2),
                   init_min_angle_deg=opts.init_min_angle_deg / 2.0)


def _parse_value(name: str, text: str, kind):
    """``text`` as a value of the field type ``kind`` (int, float, bool, str, ``X | None``, a pair of ints)."""
    text = text.strip()
    args = typing.get_args(kind)
    if type(None) in args and text.lower() == "none":
        return None
    inner = next((a for a in args if a is not type(None)), kind) if args else kind
    try:
        if inner is bool:
            if text.lower() not in ("true", "false", "1", "0", "yes", "no"):
                raise ValueError
            return text.lower() in ("true", "1", "yes")
        if inner in (int, float, str):
            return inner(text)
        if typing.get_origin(inner) is tuple:
            a, b = (int(v) for v in text.replace("(", "").replace(")", "").split(","))
            return (a, b)
    except ValueError:
        pass
    what = {bool: "true or false", int: "an integer", float: "a number"}.get(inner, "two integers like 3,7")
    raise KitInputError(f"--option {name}={text}: expected {what}" + (" or none" if type(None) in args else ""))


def parse_assignments(items) -> dict:
    """``["KEY=VALUE", ...]`` (``sfm --option``) as ``{field: value}`` of :class:`MapperOptions`, each checked.

    Raises:
        KitInputError: one line naming the bad item: not ``KEY=VALUE``, no such option, or a value of the wrong type.
    """
    hints = typing.get_type_hints(MapperOptions)
    out = {}
    for item in items or ():
        key, sep, value = str(item).partition("=")
        key = key.strip()
        if not sep or not key:
            raise KitInputError(f"--option {item!r}: expected KEY=VALUE, e.g. --option min_pnp_inliers=30")
        if key not in hints:
            raise KitInputError(f"--option {key}: no such option; the options are {', '.join(sorted(hints))}")
        out[key] = _parse_value(key, value, hints[key])
    return out

"""SfM poses feed a NeRF: a COLMAP text model + its images -> a NeRF data set (Blender format).

The command ``python -m course_lib sfm-to-nerf SFM_OUT --images IMAGES_DIR --out NERF_DIR``
(:mod:`course_lib.data.cli_sfm_to_nerf`) calls :func:`sfm_to_nerf`.

A NeRF needs, for every training photo, the camera that took it: intrinsics and a
camera-to-world pose. Structure from Motion gives exactly that (this is what COLMAP is used for
in the NeRF paper's real scenes). This module converts the kit's reconstruction -- the COLMAP text
model that ``python -m course_lib sfm`` writes to ``SFM_OUT/colmap`` -- into a NeRF data set in
the Blender format (``transforms_train.json``, ``transforms_test.json``, ``images/``) that
:func:`course_lib.data.blender.load_blender` and ``python -m course_lib nerf train`` read.

Poses
    SfM stores ``R_cw, t_cw`` (camera from world, ``x_cam = R_cw X + t_cw``, OpenCV axes). NeRF
    wants camera-to-world: ``c2w = [[R_cw^T, C], [0, 1]]`` with the centre ``C = -R_cw^T t_cw``,
    still in OpenCV axes here. The flip to Blender's OpenGL axes (y up, z backwards) happens in
    :func:`course_lib.data.blender.write_blender` -- the one place in the kit that converts axes.

Centring and scale (a similarity of the whole scene)
    An SfM world has an arbitrary origin and scale. NeRF samples each ray between ``near`` and
    ``far``, and the fast preset's voxel grid covers a box, so the scene must sit in a known range.
    The original NeRF fixes ``near = 2, far = 6`` for its Blender scenes, whose objects fit in a
    sphere of radius about 1.5 at the origin, seen from cameras 4 units away. The kit's trainer does
    not fix them: :func:`course_lib.nerf.train.scene_bounds` derives a centre, a radius and
    ``near``/``far`` from the cameras (for the embedded scene: cameras 4 away, near 1.3, far 6.7).
    We therefore map the *sparse points' bounding sphere* to the unit sphere::

        X_nerf = scale * (X_sfm - center)

    with ``center`` the per-axis median of the triangulated points and ``radius`` the
    ``percentile`` (default 95th) of their distances to it (robust to stray points), ``scale = 1 /
    radius``. Rotations are unchanged; camera centres map like points. ``near``/``far`` for the
    sphere are written to ``sfm_to_nerf.json`` (``near = max(0.05, d_min - 1.5)``,
    ``far = d_max + 1.5`` with ``d`` the cameras' distances to the origin, i.e. the unit sphere
    plus the same 50 % margin as Blender's 2/6 around a radius-1.5 object at distance 4); the
    trainer's own :func:`~course_lib.nerf.train.scene_bounds` is used unless you pass them.

Images and intrinsics
    A ``SIMPLE_RADIAL`` model (``match`` without ``--K``: the focal length and ``k1`` refined by
    ``sfm``) is first undistorted: every photo is resampled onto the camera's pinhole part
    (:func:`course_lib.data.camera.undistort_image`), since a NeRF's rays are a pinhole's. Other
    distortion models are refused by :func:`course_lib.data.colmap.read_colmap_text` with a message.
    The Blender format knows one horizontal field of view: square pixels, principal point at the
    image centre ``((W-1)/2, (H-1)/2)`` (:func:`course_lib.data.blender.intrinsics_from_fov`). The
    photos are resized to ``size`` pixels wide (``cv2.INTER_AREA``; K scaled as in
    :func:`course_lib.data.cli_match.scale_intrinsics`), then, if the principal point is off
    centre or ``fx != fy``, resampled by the homography ``K_blender K^-1`` (the same rays, a
    new pinhole). ``camera_angle_x = 2 atan(W / (2 f))``.

Limits
    The unit-sphere mapping suits *object-centred* captures (cameras around the object, outside
    its sphere: the synthetic building, 2.9-3.1 units from the origin after the mapping). For a
    *forward-facing* capture such as the WPI facade (5 photos from one side) the cameras end up
    inside the points' sphere (0.43-0.51 from the origin) and far-away points dominate the
    radius; the NeRF paper handles such scenes with normalized device coordinates (LLFF), which
    the kit does not implement. The data set is still valid, but the fast preset's box will not
    fit it well.

Split
    Registered images in name order; every ``test_every``-th one (offset ``test_every // 2``) goes
    to ``test``, the others to ``train``. Unregistered images are left out (they have no pose).

Introduced in ``notebooks/10_photos_to_nerf.ipynb``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from course_lib.data import building as b
from course_lib.data.blender import intrinsics_from_fov, read_rgb, write_blender
from course_lib.data.building import NERF_RADIUS, orbit_camera
from course_lib.data.camera import undistort_image
from course_lib.data.cli_match import scale_intrinsics
from course_lib.data.colmap import read_colmap_text
from course_lib.data.p3 import SOURCE_NAMES_FILE
from course_lib.validate import KitInputError, intrinsics, output_dir

__all__ = ["NerfFrame", "normalization", "to_nerf_frame", "resample_images", "sfm_to_nerf", "orbit_c2w", "render_building_views"]

#: Margin of near/far around the unit sphere (Blender: near 2, far 6 around radius 1.5 at distance 4).
MARGIN = 1.5


@dataclass
class NerfFrame:
    """The similarity from the SfM world to the NeRF frame: ``X_nerf = scale * (X_sfm - center)``.

    Attributes:
        center: ``(3,)`` in SfM units. scale: NeRF units per SfM unit. radius: the points' sphere
        radius in SfM units (``scale = 1 / radius``).
    """

    center: np.ndarray
    scale: float
    radius: float

    def points(self, X: np.ndarray) -> np.ndarray:
        """``(N, 3)`` SfM points -> NeRF frame."""
        return self.scale * (np.asarray(X, float) - self.center)

    def c2w(self, R_cw: np.ndarray, t_cw: np.ndarray) -> np.ndarray:
        """``(M, 3, 3), (M, 3)`` SfM poses -> ``(M, 4, 4)`` camera-to-world in the NeRF frame, OpenCV axes."""
        R_cw = np.asarray(R_cw, float).reshape(-1, 3, 3)
        t_cw = np.asarray(t_cw, float).reshape(-1, 3)
        out = np.tile(np.eye(4), (len(R_cw), 1, 1))
        out[:, :3, :3] = np.transpose(R_cw, (0, 2, 1))
        C = -np.einsum("mji,mj->mi", R_cw, t_cw)  # C = -R^T t
        out[:, :3, 3] = self.points(C)
        return out


def normalization(X: np.ndarray, percentile: float = 95.0) -> NerfFrame:
    """The similarity that maps the sparse points' (robust) bounding sphere to the unit sphere.

    Args:
        X: ``(N, 3)`` triangulated points (NaN rows are ignored), N >= 4.
        percentile: the radius is this percentile of the distances to the median (100: all points).

    Returns:
        :class:`NerfFrame`.
    """
    X = np.asarray(X, float)
    if X.ndim != 2 or X.shape[1] != 3:
        raise KitInputError(f"X has shape {X.shape}: expected (N, 3) points")
    X = X[np.isfinite(X).all(axis=1)]
    if len(X) < 4:
        raise KitInputError(f"only {len(X)} triangulated points: the reconstruction is too sparse to place the scene for a NeRF")
    if not 50.0 <= float(percentile) <= 100.0:
        raise KitInputError(f"percentile = {percentile!r}: expected 50..100")
    c = np.median(X, axis=0)
    r = float(np.percentile(np.linalg.norm(X - c, axis=1), percentile))
    if not r > 0:
        raise KitInputError("all points coincide: cannot scale the scene")
    return NerfFrame(c, 1.0 / r, r)


def to_nerf_frame(R_cw, t_cw, X, percentile: float = 95.0) -> tuple[np.ndarray, NerfFrame]:
    """SfM poses and points -> ``c2w (M, 4, 4)`` in the NeRF frame (OpenCV axes) and the similarity used."""
    frame = normalization(X, percentile)
    return frame.c2w(R_cw, t_cw), frame


def resample_images(images: list[np.ndarray], K, width: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Resize photos to ``width`` pixels and re-centre them on a Blender camera (square pixels, centred).

    Args:
        images: M ``(H, W, 3|4)`` uint8 images of one size. K: ``(3, 3)`` of these images.
        width: output width W' (the height keeps the aspect ratio).

    Returns:
        ``images (M, H', W', C)`` uint8, the Blender ``K' (3, 3)``, ``camera_angle_x`` (radians).
    """
    import cv2

    K = intrinsics(K)
    H, W = images[0].shape[:2]
    width = int(width)
    if width < 8:
        raise KitInputError(f"size = {width}: expected an output width of at least 8 pixels")
    W2, H2 = width, max(int(round(H * width / W)), 8)
    Ks = scale_intrinsics(K, (W, H), (W2, H2))
    f = 0.5 * (Ks[0, 0] + Ks[1, 1])
    angle = float(2.0 * np.arctan(0.5 * W2 / f))
    Kb = intrinsics_from_fov(W2, H2, angle)
    Hm = Kb @ np.linalg.inv(Ks)  # pixels of the resized photo -> pixels of the Blender camera
    warp = not np.allclose(Hm, np.eye(3), atol=1e-4)
    out = []
    for im in images:
        if im.shape[:2] != (H, W):
            raise KitInputError(f"an image is {im.shape[1]}x{im.shape[0]}, another {W}x{H}: one camera, one size")
        r = cv2.resize(im, (W2, H2), interpolation=cv2.INTER_AREA) if (W2, H2) != (W, H) else im.copy()
        if warp:
            r = cv2.warpPerspective(r, Hm, (W2, H2), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        out.append(r)
    return np.stack(out), Kb, angle


def _find_model(sfm_out: Path) -> Path:
    for cand in (sfm_out / "colmap", sfm_out):
        if (cand / "images.txt").is_file():
            return cand
    raise KitInputError(f"no COLMAP text model in {sfm_out}: expected {sfm_out / 'colmap'}/images.txt "
                        "(the output of `python -m course_lib sfm ... --out SFM_OUT`) or the model folder itself")


def sfm_to_nerf(sfm_out, images_dir, out, size: int = 100, test_every: int = 8, percentile: float = 95.0,
                alpha_dir=None) -> dict:
    """Write a NeRF Blender data set from an SfM reconstruction (the ``sfm-to-nerf`` command).

    Args:
        sfm_out: the ``sfm`` command's output folder (holding ``colmap/``) or a COLMAP text model folder.
        images_dir: folder with the images named as in the model (e.g. the P3 folder).
        out: output folder (``transforms_train.json``, ``transforms_test.json``, ``images/``,
            ``sfm_to_nerf.json``).
        size: output image width in pixels.
        test_every: every n-th registered image is a test view (0: no test split).
        percentile: robust radius of the points' sphere (:func:`normalization`).
        alpha_dir: optional folder with RGBA versions of the images (same names); their alpha is kept.

    Returns:
        The summary written to ``out/sfm_to_nerf.json``.

    Introduced in ``notebooks/10_photos_to_nerf.ipynb``.
    """
    sfm_out, images_dir, out = Path(sfm_out), Path(images_dir), Path(out)
    if not sfm_out.exists():
        raise KitInputError(f"SfM output not found: {sfm_out}")
    if not images_dir.is_dir():
        raise KitInputError(f"image folder not found: {images_dir}")
    if int(test_every) < 0 or int(test_every) == 1:
        raise KitInputError(f"test_every = {test_every}: expected 0 (no test split) or >= 2")
    out = output_dir(out)
    model = read_colmap_text(_find_model(sfm_out))
    M = len(model.image_names)
    if M < 2:
        raise KitInputError(f"the model has {M} registered image(s): a NeRF needs several posed views")
    images = []
    p3_names = _p3_names(images_dir)
    for name in model.image_names:
        src = Path(alpha_dir) / name if alpha_dir is not None else images_dir / name
        if alpha_dir is None and not src.is_file() and name in p3_names:  # the photo's own name, its P3 copy here
            src = images_dir / p3_names[name]
        img = read_rgb(src, hint="it is named in the model: pass --images with the folder the SfM ran on")
        if img.dtype != np.uint8:
            img = (img / 257).astype(np.uint8)
        images.append(img)
    W0, H0 = model.image_size
    if images[0].shape[:2] != (H0, W0):
        raise KitInputError(f"{model.image_names[0]} is {images[0].shape[1]}x{images[0].shape[0]} but the model's camera is {W0}x{H0}")
    if model.k1 != 0.0:  # NeRF's rays are a pinhole's: resample the photos onto the camera's pinhole part first
        images = [undistort_image(im, model.K, model.k1) for im in images]
    imgs, Kb, angle = resample_images(images, model.K, size)
    c2w, frame = to_nerf_frame(model.R_cw, model.t_cw, model.X, percentile)
    idx = np.arange(M)
    test = (idx % test_every == test_every // 2) if test_every else np.zeros(M, bool)
    if test.all() or not (~test).any():
        raise KitInputError("no training views left: use a larger test_every")
    stems = [Path(n).with_suffix("").as_posix().replace("/", "_") for n in model.image_names]
    write_blender(out, "train", imgs[~test], c2w[~test], angle, names=[f"r_{s}" for s, t in zip(stems, test) if not t])
    if test.any():
        write_blender(out, "test", imgs[test], c2w[test], angle, names=[f"r_{s}" for s, t in zip(stems, test) if t])
    d = np.linalg.norm(c2w[:, :3, 3], axis=1)
    summary = {
        "source": str(sfm_out), "images_dir": str(images_dir),
        "similarity": "X_nerf = scale * (X_sfm - center); rotations unchanged; c2w in OpenCV axes before write_blender's flip",
        "center": frame.center.tolist(), "scale": frame.scale, "points_radius_sfm": frame.radius, "percentile": percentile,
        "camera_distance": [float(d.min()), float(d.max())],
        "near": float(max(0.05, d.min() - MARGIN)), "far": float(d.max() + MARGIN),
        "image_size": [int(imgs.shape[2]), int(imgs.shape[1])], "camera_angle_x": angle, "K": Kb.tolist(),
        "train": [n for n, t in zip(model.image_names, test) if not t],
        "test": [n for n, t in zip(model.image_names, test) if t],
        "points": int(np.isfinite(model.X).all(axis=1).sum()),
        "camera_model": model.camera_model, "undistorted_k1": float(model.k1),
    }
    (out / "sfm_to_nerf.json").write_text(json.dumps(summary, indent=1))
    return summary


def _p3_names(images_dir: Path) -> dict:
    """``{photo name: P3 name}`` of a P3 folder made by ``match`` (:data:`course_lib.data.p3.SOURCE_NAMES_FILE`), else empty:
    ``sfm`` names the images as the photos were named, the P3 folder holds them as ``1.png ...``."""
    path = images_dir / SOURCE_NAMES_FILE
    if not path.is_file():
        return {}
    try:
        return {str(r["source"]): str(r["p3_name"]) for r in json.loads(path.read_text())}
    except (ValueError, KeyError, TypeError):
        return {}


# ------------------------------------------------------------------- a capture with known poses


def orbit_c2w(n: int, elevations_deg=(25.0, 50.0), radius: float | None = None, span_deg: float = 360.0) -> np.ndarray:
    """Cameras on rings around the embedded NeRF scene's origin, all looking at it (a capture for SfM).

    ``n // len(elevations_deg)`` evenly spaced views per ring, each ring turned by half a step
    against the previous one, so neighbours are close enough for SIFT (18 degrees apart for 40 views).

    Args:
        n: number of views. elevations_deg: ring elevations. radius: distance (default
            :data:`course_lib.data.building.NERF_RADIUS`).
        span_deg: 360 for full rings; less for arcs centred on the building's front (azimuth
            -90 degrees, the street side), e.g. 180 for a half orbit with the same spacing at half the views.

    Returns:
        ``c2w (n', 4, 4)`` camera-to-world, OpenCV axes, in the NeRF frame of
        :func:`course_lib.data.building.make_nerf_dataset` (z up); ``n'`` is ``n`` rounded down
        to a multiple of the number of rings.

    Introduced in ``notebooks/10_photos_to_nerf.ipynb``.
    """
    radius = NERF_RADIUS if radius is None else float(radius)
    per = int(n) // len(elevations_deg)
    if per < 1:
        raise KitInputError(f"n = {n}: expected at least one view per ring ({len(elevations_deg)} rings)")
    out = []
    for k, e in enumerate(np.radians(np.asarray(elevations_deg, float))):
        span = np.radians(float(span_deg))
        step = span / per
        az = -0.5 * np.pi - 0.5 * span + (np.arange(per) + 0.5) * step if span_deg < 360 else np.arange(per) * step
        for a in az + (k - 0.5 * (len(elevations_deg) - 1)) * 0.5 * step * (span_deg < 360) + k * 0.5 * step * (span_deg >= 360):
            out.append(orbit_camera(radius, a, e))
    return np.stack(out)


def render_building_views(c2w: np.ndarray, size: int, supersample: int = 2, seed: int | None = None):
    """Render the embedded NeRF scene (building on its slab) from ``c2w`` as RGBA.

    Args:
        c2w: ``(N, 4, 4)`` camera-to-world, OpenCV axes, NeRF frame. size: W = H in pixels.
        supersample: rays per pixel per axis. seed: texture seed (default: the embedded scene's).

    Returns:
        ``images (N, size, size, 4)`` uint8 RGBA (transparent background) and ``K (3, 3)``
        (:data:`course_lib.data.building.NERF_CAMERA_ANGLE_X`).

    Introduced in ``notebooks/10_photos_to_nerf.ipynb``.
    """
    rng = np.random.default_rng((b.DEFAULT_SEED if seed is None else seed) + 1)  # as make_nerf_dataset
    surfaces = b.build_scene(rng, ground="slab", rho=40.0)
    K = intrinsics_from_fov(size, size, b.NERF_CAMERA_ANGLE_X)
    out = []
    for M in np.asarray(c2w, float):
        C_world = b.NERF_CENTER + M[:3, 3] / b.NERF_SCALE
        R_cw = M[:3, :3].T
        rgb, alpha = b.render(surfaces, K, R_cw, -R_cw @ C_world, (size, size), supersample=supersample, background="transparent")
        out.append(np.concatenate([rgb, alpha[..., None]], -1))
    return np.clip(np.round(np.stack(out) * 255), 0, 255).astype(np.uint8), K

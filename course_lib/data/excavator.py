"""A held-out NeRF scene: a toy excavator, ray cast by the building's renderer, at up to 800 x 800 px.

The NeRF presets are tuned on the embedded building (:mod:`course_lib.data.building`); their
speed and quality are reported on this scene too, which they were not tuned on (as lego's
originals would be, which the kit may not redistribute). Like lego it is a single object on a
transparent background, seen from the upper hemisphere, with parts of many sizes:

* two crawler tracks (tread bars) with an octagonal wheel at each end, on an undercarriage;
* an upper body turned by a seeded angle, with a printed sign on each side, a glazed cabin,
  a counterweight with hazard stripes, an exhaust pipe, hand rails on thin posts, lamps and
  fields of toy studs;
* a boom, a stick and a bucket with teeth at seeded angles, with thin hydraulic cylinders;
* small parts of 1-3 % of the object's size (cleats on the tracks, studs, posts): lego's kind of
  detail, a few pixels wide at 200 px.

Every part is a box or a prism of textured planar faces (:class:`~course_lib.data.building.Surface`,
procedural textures at 500 texels per unit: finer than a pixel at 800 px), shaded by the
building's sun. The frame is NeRF's (z up, the object within about ``[-0.8, 0.8] x [-1.2, 1.2] x
[-0.4, 1.0]``); the cameras look at the origin from 4 units away with lego's field of view
(0.6911 rad), training and test views drawn independently on the upper hemisphere (elevation
8-75 degrees), so no test view repeats a training view.

:func:`make_excavator_datasets` renders each view once at the largest size (2 x 2 rays per pixel)
and writes every size by area downscaling (``cv2.INTER_AREA`` of the RGBA image, as NeRF's
half-resolution loaders do): the 200 and 400 px scenes are the 800 px scene made smaller, as a
lego 200/400/800 split would be. It is made by a command of the instructor's repository,
``python benchmarks/nerf_speed.py --scene excavator`` (about 10 minutes on 2 cores, into the
git-ignored ``outputs/bench-excavator/``); the renders are never committed.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from course_lib.data.building import Surface, nerf_cameras
from course_lib.data.parts import Parts, paint, rot, write_object_datasets
from course_lib.data.textures import draw_sign, draw_window, value_noise
from course_lib.validate import KitInputError

__all__ = ["DEFAULT_SEED", "CAMERA_ANGLE_X", "build_excavator", "make_excavator_datasets"]

#: Seed of the scene the benchmarks report on (textures, angles, cameras).
DEFAULT_SEED = 32
#: Horizontal field of view (lego's).
CAMERA_ANGLE_X = 0.6911112070083618
#: Texels per unit of the procedural textures.
RHO = 500.0
GENERATOR = "course_lib.data.excavator v2"


# ============================================================================ textures


def _paint(rng, w, h, base, noise=0.12, cell=0.15):
    """:func:`~course_lib.data.parts.paint` at the excavator's texel density."""
    return paint(rng, w, h, base, RHO, noise, cell)


def _texture(kind: str, rng, w_u: float, h_u: float, colors: dict) -> np.ndarray:
    """A face texture of ``w_u x h_u`` units: ``(Ht, Wt, 3)`` float32 in [0, 1]."""
    w, h = max(4, int(math.ceil(w_u * RHO))), max(4, int(math.ceil(h_u * RHO)))
    if kind == "body":
        img = _paint(rng, w, h, colors["body"])
    elif kind == "sign":  # a body side with a printed sign (letters and shapes)
        img = np.ascontiguousarray(_paint(rng, w, h, colors["body"]))
        if w > 40 and h > 30:
            draw_sign(img, 0.12 * w, 0.2 * h, 0.6 * w, 0.6 * h, rng, RHO)
    elif kind == "tread":  # dark rubber with bars across the track every 0.06 units
        img = _paint(rng, w, h, (0.16, 0.16, 0.17), noise=0.3, cell=0.05)
        bar = (np.arange(w) % int(0.06 * RHO)) < int(0.022 * RHO)
        img[:, bar] *= 1.9
    elif kind == "hazard":  # diagonal yellow and black stripes
        yy, xx = np.mgrid[0:h, 0:w]
        stripe = ((xx + yy) // int(0.05 * RHO)) % 2 == 0
        img = np.where(stripe[..., None], np.float32([0.95, 0.78, 0.1]), np.float32([0.08, 0.08, 0.08]))
        img = img.astype(np.float32) * (1.0 + 0.08 * value_noise(rng, h, w, 0.1 * RHO, 2)[..., None])
    elif kind == "cabin":  # a window with a frame on the cabin's paint
        img = np.ascontiguousarray(_paint(rng, w, h, colors["cabin"]))
        if w > 30 and h > 30:
            draw_window(img, 0.12 * w, 0.12 * h, 0.76 * w, 0.6 * h, rng, RHO)
    elif kind == "metal":  # brushed steel: streaks along the part
        img = _paint(rng, w, h, (0.72, 0.73, 0.75), noise=0.05)
        img *= 1.0 + 0.12 * value_noise(rng, 1, w, 0.02 * RHO, 2)[0][None, :, None]
    elif kind == "wheel":
        img = _paint(rng, w, h, (0.3, 0.3, 0.32), noise=0.2, cell=0.04)
    elif kind == "hub":
        img = _paint(rng, w, h, colors["hub"], noise=0.1)
    else:
        raise KitInputError(f"texture kind {kind!r}")
    return np.clip(img, 0, 1).astype(np.float32)


# ============================================================================ parts


def build_excavator(rng: np.random.Generator) -> tuple[list[Surface], list[tuple]]:
    """The excavator's surfaces (NeRF frame, z up) and its parts' bounding spheres.

    Args:
        rng: seeded generator (colours, textures, the body's turn, the arm's angles).

    Returns:
        ``surfaces`` (list of :class:`~course_lib.data.building.Surface`) and ``groups`` for
        :func:`~course_lib.data.building.render`.
    """
    hue = rng.uniform(-0.06, 0.06, 3)
    colors = {"body": np.clip(np.array([0.93, 0.68, 0.12]) + hue, 0, 1), "cabin": np.clip(np.array([0.85, 0.2, 0.14]) + hue, 0, 1),
              "hub": np.clip(np.array([0.8, 0.62, 0.12]) + hue, 0, 1)}
    parts = Parts(lambda kind, w_u, h_u: _texture(kind, rng, w_u, h_u, colors))
    # undercarriage: two tracks with a wheel at each end
    for sx in (-1, 1):
        x = sx * 0.5
        parts.box("track", (x, 0, -0.235), (0.26, 1.44, 0.23), kinds="tread")
        for y in (-0.72, 0.72):
            parts.wheel("wheel", (x, y, -0.235), 0.124, 0.27)
    parts.box("frame", (0, 0, -0.22), (0.74, 0.9, 0.14), kinds="metal")
    # the upper body, turned about z
    yaw = rng.uniform(-0.5, 0.5)
    Rz = rot("z", yaw)
    T = lambda x, y, z: Rz @ np.array([x, y, z], float)  # noqa: E731
    parts.box("body", T(0, 0.02, 0.06), (1.0, 1.16, 0.34), Rz, kinds=["sign", "sign", "body", "body", "body", "body"])
    parts.box("cabin", T(0.24, -0.34, 0.45), (0.42, 0.42, 0.44), Rz, kinds="cabin", bottom=False)
    parts.box("counterweight", T(0, 0.5, 0.32), (0.9, 0.2, 0.18), Rz, kinds="hazard", bottom=False)
    parts.box("exhaust", T(-0.36, 0.3, 0.42), (0.04, 0.04, 0.38), Rz, kinds="metal", bottom=False)
    for i in range(2):
        for j in range(4):  # toy studs on the engine cover
            parts.box("stud", T(-0.4 + 0.09 * i, -0.05 + 0.09 * j, 0.25), (0.055, 0.055, 0.04), Rz, bottom=False)
    _details(parts, T, Rz)
    # the arm: boom up and forward, stick down, bucket; all in the body's turned frame
    boom_pitch = rng.uniform(0.55, 0.8)  # radians above the horizontal, towards -y (forward)
    stick_pitch = rng.uniform(-1.3, -0.9)
    base = np.array([-0.12, -0.45, 0.24])
    boom_dir = np.array([0, -math.cos(boom_pitch), math.sin(boom_pitch)])
    boom_len, stick_len = 0.72, 0.55
    Rb = rot("x", -boom_pitch)  # local +y (the box's long axis) -> -boom_dir's horizontal part ... pointing forward-up
    parts.box("boom", T(*(base + 0.5 * boom_len * boom_dir)), (0.11, boom_len, 0.09), Rz @ Rb)
    tip = base + boom_len * boom_dir
    stick_dir = np.array([0, -math.cos(stick_pitch), math.sin(stick_pitch)])
    Rs = rot("x", -stick_pitch)
    parts.box("stick", T(*(tip + 0.5 * stick_len * stick_dir)), (0.08, stick_len, 0.07), Rz @ Rs)
    for dx in (-0.075, 0.075):  # hydraulic cylinders beside the boom
        mid = base + 0.45 * boom_len * boom_dir + np.array([dx, 0, -0.05])
        parts.box("cylinder", T(*mid), (0.03, 0.55 * boom_len, 0.03), Rz @ Rb, kinds="metal")
    end = tip + stick_len * stick_dir
    Rk = rot("x", -stick_pitch - 1.2)
    parts.box("bucket", T(*(end + np.array([0, -0.06, -0.02]))), (0.24, 0.16, 0.12), Rz @ Rk, kinds="metal")
    with parts.group():
        for dx in (-0.09, -0.03, 0.03, 0.09):  # the bucket's teeth
            tooth = end + np.array([dx, 0.0, 0.0]) + Rk @ np.array([0.0, -0.09, -0.08])
            parts.box("tooth", T(*tooth), (0.025, 0.025, 0.06), Rz @ Rk, kinds="metal")
    return parts.surfaces, parts.groups


def _details(parts: Parts, T, Rz) -> None:
    """Small parts, lego-like: grousers on the tracks, studs on the body and the cabin, a hand rail, lamps."""
    for sx in (-1, 1):  # a grouser (a cleat across the track) every 0.072 units on its top and bottom
        for z in (-0.115, -0.355):
            for run in range(4):
                with parts.group():
                    for k in range(5):
                        y = -0.684 + 0.072 * (5 * run + k)
                        parts.box("grouser", (sx * 0.5, y, z), (0.27, 0.026, 0.022), kinds="tread")
    for i in range(5):  # studs on the front of the body, left of the cabin
        with parts.group():
            for j in range(4):
                parts.box("stud", T(-0.42 + 0.08 * i, -0.52 + 0.08 * j, 0.25), (0.05, 0.05, 0.035), Rz, bottom=False)
    with parts.group():
        for i in range(3):
            for j in range(3):  # studs on the cabin's roof
                parts.box("stud", T(0.12 + 0.12 * i, -0.46 + 0.12 * j, 0.685), (0.06, 0.06, 0.03), Rz, bottom=False)
    for sx in (-1, 1):  # a hand rail along each side of the engine cover: posts and a top bar
        with parts.group():
            for k in range(6):
                parts.box("post", T(sx * 0.47, -0.02 + 0.1 * k, 0.3), (0.018, 0.018, 0.1), Rz, kinds="metal", bottom=False)
            parts.box("rail", T(sx * 0.47, 0.23, 0.355), (0.022, 0.56, 0.018), Rz, kinds="metal")
    with parts.group():
        for dx in (0.1, 0.38):  # two lamps on the cabin's front
            parts.box("lamp", T(dx, -0.565, 0.6), (0.05, 0.03, 0.04), Rz, kinds="metal")


# ============================================================================ data sets


def make_excavator_datasets(root, sizes=(200, 400, 800), seed: int = DEFAULT_SEED, n_train: int = 100,
                            n_test: int = 25, verbose: bool = False) -> dict[int, Path]:
    """Render the excavator once at ``max(sizes)`` and write a Blender scene per size.

    Args:
        root: folder; writes ``root/excavator-SIZE/`` (``transforms_train.json``,
            ``transforms_test.json``, ``images/``, ``scene.json``) for each size.
        sizes: image sides in pixels; each must divide the largest one.
        seed: the scene's seed (textures, angles, cameras).
        n_train, n_test: views per split (independent random cameras on the upper hemisphere).
        verbose: print progress.

    Returns:
        ``{size: folder}``.
    """
    rng = np.random.default_rng(seed)
    surfaces, groups = build_excavator(rng)
    cams = {"train": nerf_cameras(rng, n_train), "test": nerf_cameras(rng, n_test)}
    info = {"seed": int(seed), "generator": GENERATOR,
            "world": "NeRF frame, z up; a toy excavator within about [-0.8, 0.8] x [-1.2, 1.2] x [-0.4, 1.0]; "
                     "cameras 4 units from the origin, train and test views drawn independently on the upper hemisphere"}
    return write_object_datasets(root, "excavator", surfaces, groups, cams, sizes, CAMERA_ANGLE_X, info, verbose)

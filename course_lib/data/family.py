"""The NeRF scene family: five seeded object scenes that differ where real scenes differ.

The fast preset's rules are chosen on the median and the worst of this family
(``python benchmarks/nerf_speed.py --ladder``), not on one scene. Each scene is built from
:mod:`course_lib.data.parts` (as the excavator is), ray cast with the building's renderer, and
written in NeRF's Blender format like lego: an object on a transparent background, 75 training
and 25 test views drawn independently on the upper hemisphere (elevation 8-75 degrees), looking
at the origin with lego's field of view, at any size that divides the rendered one (100-800 px).

=========  =========================================================================================
scene      what it tests
=========  =========================================================================================
bricks     fine detail everywhere: a toy-brick town of many small parts in many colours, a stud on
           every brick top (lego's kind of scene), the object about as large in the frame as lego
plant      thin structures: stems, leaves seen edge-on, a wire trellis 1/5 px wide at 100 px
crates     large flat textured faces (planks, printed labels, stone tiles) and an object that fills
           the frame: the cameras stand 3 units away, parts of it leave the frame
gloss      specular and dark materials: a black lacquered body, chrome, glossy red enamel; the
           highlights and mirrored sky move with the view (the scene needs view-dependent colour)
figurine   an object small in the frame: a toy robot about a fifth of the image wide
=========  =========================================================================================

``python -m course_lib`` does not ship these renders; ``benchmarks/nerf_speed.py`` makes them on
demand into the git-ignored ``outputs/`` (:func:`make_family_datasets`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from course_lib.data.building import nerf_cameras
from course_lib.data.excavator import CAMERA_ANGLE_X
from course_lib.data.parts import Parts, paint, rot, write_object_datasets
from course_lib.data.textures import blocks, draw_sign, value_noise
from course_lib.validate import KitInputError

__all__ = ["FamilyScene", "FAMILY", "DEFAULT_SEED", "build_family_scene", "family_cameras", "make_family_datasets"]

#: Seed of the scenes the benchmarks report on.
DEFAULT_SEED = 41
#: Texels per unit of the procedural textures (finer than a pixel at 800 px).
RHO = 500.0
GENERATOR = "course_lib.data.family v1"

_PALETTE = np.array([[0.80, 0.10, 0.10], [0.10, 0.30, 0.75], [0.95, 0.78, 0.10], [0.15, 0.55, 0.20],
                     [0.93, 0.93, 0.90], [0.12, 0.12, 0.13], [0.95, 0.50, 0.10], [0.55, 0.35, 0.20]])


# ============================================================================ textures


def _texture(kind: str, rng, w_u: float, h_u: float) -> np.ndarray:
    """A face texture of ``w_u x h_u`` units; ``kind`` is a material name, or ``"plastic:i"`` (palette colour i)."""
    w, h = max(4, int(math.ceil(w_u * RHO))), max(4, int(math.ceil(h_u * RHO)))
    name, _, arg = kind.partition(":")
    if name == "plastic":
        return paint(rng, w, h, _PALETTE[int(arg)], RHO, noise=0.08, cell=0.05)
    if name == "print":  # a brick with a printed tile (letters and shapes)
        img = np.ascontiguousarray(paint(rng, w, h, _PALETTE[int(arg)], RHO, noise=0.08, cell=0.05))
        if w > 16 and h > 12:
            draw_sign(img, 0.1 * w, 0.15 * h, 0.8 * w, 0.7 * h, rng, RHO)
        return img
    if name == "base":  # the base plate: grey with a fine grid of grooves every 0.05 units
        img = paint(rng, w, h, (0.45, 0.47, 0.45), RHO, noise=0.1, cell=0.1)
        grid = (np.arange(max(w, h)) % int(0.05 * RHO)) < 2
        img[grid[:h]] *= 0.6
        img[:, grid[:w]] *= 0.6
        return img
    if name == "leaf":  # green with a darker midrib and veins
        img = paint(rng, w, h, rng.uniform([0.12, 0.38, 0.08], [0.25, 0.6, 0.18]), RHO, noise=0.25, cell=0.04)
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        vein = (np.abs(xx - 0.5 * w) < 1.5) | (((yy + 0.6 * np.abs(xx - 0.5 * w)) % max(int(0.03 * RHO), 3)) < 1.5)
        img[vein] *= 0.55
        return img
    if name == "stem":
        return paint(rng, w, h, (0.30, 0.42, 0.15), RHO, noise=0.2, cell=0.02)
    if name == "wire":
        return paint(rng, w, h, (0.15, 0.15, 0.16), RHO, noise=0.1)
    if name == "pot":  # terracotta with bands
        img = paint(rng, w, h, (0.72, 0.36, 0.2), RHO, noise=0.2, cell=0.08)
        img[(np.arange(h) % int(0.12 * RHO)) < int(0.02 * RHO)] *= 0.75
        return img
    if name == "soil":
        img = paint(rng, w, h, (0.25, 0.17, 0.1), RHO, noise=0.5, cell=0.01)
        return img * (1.0 + 0.3 * value_noise(rng, h, w, 0.005 * RHO, 2)[..., None])
    if name == "wood":  # planks along the face with grain and dark gaps
        img = paint(rng, w, h, rng.uniform([0.55, 0.38, 0.2], [0.75, 0.55, 0.32]), RHO, noise=0.15, cell=0.3)
        grain = value_noise(rng, h, max(4, w // 40), 0.02 * RHO, 3)
        import cv2

        img *= 1.0 + 0.18 * cv2.resize(grain, (w, h), interpolation=cv2.INTER_LINEAR)[..., None]
        img[(np.arange(h) % int(0.18 * RHO)) < int(0.012 * RHO)] *= 0.35
        return img
    if name == "label":  # a plank face with a printed label
        img = np.ascontiguousarray(_texture("wood", rng, w_u, h_u))
        if w > 40 and h > 40:
            draw_sign(img, 0.15 * w, 0.25 * h, 0.7 * w, 0.5 * h, rng, RHO)
        return img
    if name == "tiles":  # stone tiles
        img = blocks(rng, h, w, RHO, (0.2, 0.2), 0.012, (0.6, 0.58, 0.52), shade=0.2, mortar=(0.3, 0.3, 0.28), offset=0.0)
        return img * (1.0 + 0.2 * value_noise(rng, h, w, 0.3 * RHO)[..., None])
    if name == "lacquer":  # black lacquer with a faint pattern
        return paint(rng, w, h, (0.05, 0.05, 0.06), RHO, noise=0.3, cell=0.1)
    if name == "chrome":
        img = paint(rng, w, h, (0.55, 0.56, 0.58), RHO, noise=0.05)
        return img * (1.0 + 0.1 * value_noise(rng, 1, w, 0.01 * RHO, 2)[0][None, :, None])
    if name == "enamel":
        return paint(rng, w, h, (0.6, 0.05, 0.04), RHO, noise=0.05)
    if name == "rubber":
        return paint(rng, w, h, (0.08, 0.08, 0.08), RHO, noise=0.3, cell=0.02)
    if name == "dial":  # a dark dial face with white ticks
        img = np.ascontiguousarray(paint(rng, w, h, (0.1, 0.1, 0.12), RHO, noise=0.1))
        if w > 20 and h > 12:
            draw_sign(img, 0.1 * w, 0.2 * h, 0.8 * w, 0.6 * h, rng, RHO, text="".join(rng.choice(list("0123456789"), 3)))
        return img
    if name == "robot":
        img = paint(rng, w, h, (0.75, 0.77, 0.8), RHO, noise=0.1, cell=0.03)
        img[(np.arange(h) % int(0.03 * RHO)) < 2] *= 0.7  # panel lines
        return img
    if name == "eye":
        return paint(rng, w, h, (0.1, 0.7, 0.95), RHO, noise=0.2, cell=0.01)
    raise KitInputError(f"texture kind {kind!r}")


# ============================================================================ scenes


def build_bricks(parts: Parts, rng) -> None:
    """A toy-brick town on a base plate: columns of bricks of random colours and heights, a stud on every top."""
    n, cell, brick_h = 8, 0.2, 0.12
    parts.box("plate", (0, 0, -0.43), (n * cell + 0.1, n * cell + 0.1, 0.06), kinds="base")
    heights = np.clip(np.round(3.0 + 2.5 * value_noise(rng, n, n, 3.0, 2) * 2 + rng.uniform(-1, 1, (n, n))), 0, 7).astype(int)
    for i in range(n):
        for j in range(n):
            x, y = (i - (n - 1) / 2) * cell, (j - (n - 1) / 2) * cell
            with parts.group():
                z = -0.4
                for k in range(heights[i, j]):
                    color = int(rng.integers(len(_PALETTE)))
                    kind = f"print:{color}" if rng.random() < 0.12 else f"plastic:{color}"
                    parts.box("brick", (x, y, z + 0.5 * brick_h), (cell - 0.006, cell - 0.006, brick_h - 0.004),
                              kinds=[kind, kind, kind, kind, f"plastic:{color}", f"plastic:{color}"], bottom=False)
                    z += brick_h
            top = int(rng.integers(len(_PALETTE)))
            with parts.group():  # 2 x 2 studs on the column's top (or on the plate): a small sphere of their own
                for dx in (-0.05, 0.05):
                    for dy in (-0.05, 0.05):
                        parts.prism("stud", (x + dx, y + dy, z + 0.017), 0.03, 0.034, rot("y", -math.pi / 2), sides=6,
                                    kind=f"plastic:{top}", cap=f"plastic:{top}", caps=(False, True))


def build_plant(parts: Parts, rng) -> None:
    """A potted plant: branching stems with leaves, inside a trellis of thin wires."""
    parts.prism("pot", (0, 0, -0.5), 0.32, 0.36, rot("y", -math.pi / 2), sides=10, kind="pot", cap="soil",
                caps=(False, True))

    def branch(p, d, length, depth):
        q = p + length * d
        parts.rod("stem", p, q, 0.018 * 0.7 ** (3 - depth) + 0.006, kind="stem")
        if depth == 0:
            _leaf(q, d)
            return
        for _ in range(int(rng.integers(2, 4))):
            nd = d + rng.normal(0, 0.55, 3)
            nd[2] = abs(nd[2]) + 0.2
            branch(q, nd / np.linalg.norm(nd), length * rng.uniform(0.55, 0.8), depth - 1)
        _leaf(0.5 * (p + q), d)

    def _leaf(p, d):
        side = np.cross(d, rng.normal(0, 1, 3))
        side /= np.linalg.norm(side)
        size = rng.uniform(0.07, 0.13)
        tip = d + rng.normal(0, 0.4, 3)
        tip = tip / np.linalg.norm(tip) * size * 1.8
        w = side * size * 0.5
        parts.panel("leaf", p - w, 2 * w, tip, "leaf", triangle=False)

    for k in range(3):
        a = 2 * math.pi * k / 3 + rng.uniform(-0.4, 0.4)
        d = np.array([0.3 * math.cos(a), 0.3 * math.sin(a), 1.0])
        branch(np.array([0.05 * math.cos(a), 0.05 * math.sin(a), -0.32]), d / np.linalg.norm(d), 0.45, 3)
    with parts.group():  # the trellis: 8 uprights and 3 hoops of 12 straight pieces, 0.006 units thick
        r = 0.62
        for k in range(8):
            a = 2 * math.pi * k / 8
            parts.rod("wire", (0.3 * math.cos(a), 0.3 * math.sin(a), -0.32), (r * math.cos(a), r * math.sin(a), 0.95),
                      0.006, kind="wire")
        for z, rr in ((0.1, 0.42), (0.5, 0.52), (0.9, 0.61)):
            for k in range(12):
                a0, a1 = 2 * math.pi * k / 12, 2 * math.pi * (k + 1) / 12
                parts.rod("wire", (rr * math.cos(a0), rr * math.sin(a0), z), (rr * math.cos(a1), rr * math.sin(a1), z),
                          0.006, kind="wire")


def build_crates(parts: Parts, rng) -> None:
    """Large crates stacked on a tiled floor slab: big flat faces of planks, labels and stone."""
    parts.box("floor", (0, 0, -0.9), (1.9, 1.9, 0.08), kinds="tiles")
    label = ["label", "label", "wood", "wood", "wood", "wood"]
    parts.box("crate", (-0.42, -0.35, -0.46), (0.95, 0.85, 0.8), rot("z", rng.uniform(-0.2, 0.2)), kinds=label)
    parts.box("crate", (0.5, -0.3, -0.56), (0.8, 0.95, 0.6), rot("z", rng.uniform(-0.2, 0.2)), kinds=label[::-1])
    parts.box("crate", (0.05, 0.5, -0.5), (1.4, 0.7, 0.72), rot("z", rng.uniform(-0.1, 0.1)), kinds=label)
    parts.box("crate", (-0.3, -0.25, 0.2), (0.62, 0.62, 0.52), rot("z", rng.uniform(-0.5, 0.5)), kinds=label)
    parts.box("crate", (0.25, 0.45, 0.11), (0.66, 0.5, 0.5), rot("z", rng.uniform(-0.4, 0.4)), kinds=label[::-1])
    parts.box("box", (0.2, -0.3, -0.08), (0.4, 0.4, 0.36), rot("z", rng.uniform(-0.6, 0.6)), kinds="tiles")


def build_gloss(parts: Parts, rng) -> None:
    """A black lacquered machine with a chrome drum, a red enamel kettle, rubber feet and a dial."""
    yaw = rot("z", rng.uniform(-0.4, 0.4))
    parts.box("body", yaw @ np.array([0, 0.1, -0.2]), (1.1, 0.7, 0.5), yaw, kinds=["lacquer"] * 2 + ["dial"] + ["lacquer"] * 3)
    parts.box("top", yaw @ np.array([0.25, 0.1, 0.17]), (0.55, 0.6, 0.24), yaw, kinds="lacquer", bottom=False)
    parts.prism("drum", yaw @ np.array([-0.32, 0.1, 0.15]), 0.2, 0.5, yaw @ rot("y", -math.pi / 2), sides=16,
                kind="chrome", cap="chrome", caps=(False, True))
    parts.prism("kettle", (0.55, -0.6, -0.27), 0.22, 0.36, rot("y", -math.pi / 2), sides=12, kind="enamel",
                cap="enamel", caps=(False, True))
    parts.prism("spout", (0.55, -0.85, -0.2), 0.035, 0.3, rot("z", math.pi / 2) @ rot("y", 0.5), sides=6,
                kind="chrome", cap="chrome")
    parts.box("handle", (0.55, -0.6, -0.0), (0.04, 0.3, 0.04), kinds="rubber")
    for sx in (-0.45, 0.45):
        for sy in (-0.25, 0.25):
            parts.box("foot", yaw @ np.array([sx, 0.1 + sy, -0.48]), (0.1, 0.1, 0.06), yaw, kinds="rubber")
    parts.box("tray", (-0.55, -0.65, -0.43), (0.5, 0.4, 0.04), rot("z", 0.3), kinds="chrome")


def build_figurine(parts: Parts, rng) -> None:
    """A toy robot about 0.9 units tall: body, head with eyes, arms, legs, an antenna."""
    s = 0.9
    R = rot("z", rng.uniform(0, 2 * math.pi))
    P = lambda x, y, z: R @ (s * np.array([x, y, z]))  # noqa: E731
    with parts.group():
        parts.box("body", P(0, 0, 0.05), s * np.array([0.36, 0.24, 0.34]), R, kinds=["robot", "robot", "robot", "print:2", "robot", "robot"])
        parts.box("head", P(0, 0, 0.36), s * np.array([0.26, 0.22, 0.2]), R, kinds="robot")
        for ex in (-0.06, 0.06):
            parts.box("eye", P(ex, -0.115, 0.38), s * np.array([0.05, 0.02, 0.05]), R, kinds="eye")
        for sx in (-1, 1):
            parts.box("arm", P(sx * 0.23, 0, 0.02), s * np.array([0.08, 0.08, 0.3]), R @ rot("y", sx * 0.25), kinds="robot")
            parts.box("leg", P(sx * 0.09, 0, -0.27), s * np.array([0.1, 0.12, 0.3]), R, kinds="plastic:5")
        parts.rod("antenna", P(0, 0, 0.46), P(0.05, 0, 0.62), s * 0.015, kind="wire")
        parts.box("tip", P(0.05, 0, 0.63), s * np.array([0.04, 0.04, 0.04]), R, kinds="plastic:0")


@dataclass(frozen=True)
class FamilyScene:
    """One scene of the family: how to build it, where its cameras stand, and what it tests."""

    build: Callable[[Parts, np.random.Generator], None]
    radius: float
    specular: tuple = ()
    about: str = ""


FAMILY: dict[str, FamilyScene] = {
    "bricks": FamilyScene(build_bricks, 4.0, about="fine detail everywhere: many small parts (lego-like)"),
    "plant": FamilyScene(build_plant, 4.0, about="thin structures: stems, leaves, wires"),
    "crates": FamilyScene(build_crates, 3.0, about="large flat textured faces; the object fills the frame"),
    "gloss": FamilyScene(build_gloss, 4.0, (("lacquer", 0.8), ("chrome", 1.0), ("enamel", 0.6), ("dial", 0.4)),
                         about="specular and dark materials"),
    "figurine": FamilyScene(build_figurine, 4.0, about="an object small in the frame"),
}


def _scene(name: str) -> FamilyScene:
    if name not in FAMILY:
        raise KitInputError(f"family scene {name!r}: choose one of {', '.join(FAMILY)}")
    return FAMILY[name]


def build_family_scene(name: str, rng: np.random.Generator):
    """The surfaces (NeRF frame, z up) and the parts' bounding spheres of the family scene ``name``.

    Args:
        name: one of :data:`FAMILY`.
        rng: seeded generator (colours, textures, layout).

    Returns:
        ``surfaces`` (list of :class:`~course_lib.data.building.Surface`) and ``groups`` for
        :func:`~course_lib.data.building.render`.
    """
    scene = _scene(name)
    parts = Parts(lambda kind, w_u, h_u: _texture(kind, rng, w_u, h_u), dict(scene.specular))
    scene.build(parts, rng)
    return parts.surfaces, parts.groups


def family_cameras(name: str, rng: np.random.Generator, n_train: int = 75, n_test: int = 25) -> dict[str, np.ndarray]:
    """``{"train": c2w, "test": c2w}`` (OpenCV axes) of the scene ``name``: independent random views on the upper hemisphere."""
    r = _scene(name).radius
    return {"train": nerf_cameras(rng, n_train, radius=r), "test": nerf_cameras(rng, n_test, radius=r)}


def make_family_datasets(root, names=None, sizes=(100, 200), seed: int = DEFAULT_SEED, n_train: int = 75,
                         n_test: int = 25, verbose: bool = False) -> dict[str, dict[int, Path]]:
    """Render each family scene once at ``max(sizes)`` and write ``root/NAME-SIZE/`` for every size.

    Args:
        root: the parent folder.
        names: scenes of :data:`FAMILY` (default: all).
        sizes: image sides in pixels; each must divide the largest one.
        seed: the family's seed; scene ``k`` of :data:`FAMILY` uses ``seed + k`` (textures, layout, cameras).
        n_train, n_test: views per split.
        verbose: print progress.

    Returns:
        ``{name: {size: folder}}``.
    """
    out = {}
    for name in (list(FAMILY) if names is None else list(names)):
        scene = _scene(name)
        rng = np.random.default_rng(seed + list(FAMILY).index(name))
        surfaces, groups = build_family_scene(name, rng)
        cams = family_cameras(name, rng, n_train, n_test)
        info = {"seed": int(seed), "scene": name, "generator": GENERATOR, "about": scene.about,
                "world": f"NeRF frame, z up; the object within about [-1, 1]^3 of the origin; cameras {scene.radius:g} "
                         "units from the origin, train and test views drawn independently on the upper hemisphere"}
        out[name] = write_object_datasets(root, name, surfaces, groups, cams, sizes, CAMERA_ANGLE_X, info, verbose)
    return out

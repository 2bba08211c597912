"""Object scenes of parts for NeRF: boxes, prisms and panels with procedural textures, and their data sets.

The held-out excavator (:mod:`course_lib.data.excavator`) and the scene family
(:mod:`course_lib.data.family`) are built from the same pieces:

* :class:`Parts` collects textured planar faces (:class:`~course_lib.data.building.Surface`) part
  by part -- a box, a prism (a wheel, a stud, a pot), a double-sided panel (a leaf) -- and the
  bounding sphere of each part (or of a :meth:`Parts.group` of small parts), so the grouped ray
  caster (:func:`~course_lib.data.building.cast_rays_grouped`) tests a part only with the rays near it;
* :func:`paint`: painted plastic (a base colour, soft blotches, fine speckle), the base of most textures;
* :func:`write_object_datasets`: renders the views once at the largest size (2 x 2 rays per
  pixel, transparent background) and writes every size by area downscaling (``cv2.INTER_AREA``
  of the RGBA image, as NeRF's half-resolution loaders do), in NeRF's Blender format.

Frame: NeRF's (z up); cameras look at the origin (:func:`~course_lib.data.building.nerf_cameras`).
"""

from __future__ import annotations

import json
import math
from contextlib import contextmanager
from pathlib import Path
from typing import Callable

import numpy as np

from course_lib.data.blender import intrinsics_from_fov, write_blender
from course_lib.data.building import Surface, render
from course_lib.data.textures import value_noise
from course_lib.validate import KitInputError

__all__ = ["Parts", "rot", "paint", "render_views", "write_object_datasets"]


def rot(axis: str, angle: float) -> np.ndarray:
    """The ``(3, 3)`` rotation by ``angle`` radians about the world axis ``"x"``, ``"y"`` or ``"z"``."""
    c, s = math.cos(angle), math.sin(angle)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    if axis == "z":
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    raise KitInputError(f"axis {axis!r}: expected 'x', 'y' or 'z'")


def paint(rng, w: int, h: int, base, rho: float, noise: float = 0.12, cell: float = 0.15) -> np.ndarray:
    """Painted plastic of ``w x h`` texels: ``base`` colour, soft blotches of ``cell`` units, fine speckle; ``(h, w, 3)`` float32."""
    img = np.ones((h, w, 3), np.float32) * np.asarray(base, np.float32)
    img *= 1.0 + noise * value_noise(rng, h, w, cell * rho, 3)[..., None]
    img *= 1.0 + 0.04 * rng.standard_normal((h, w, 1)).astype(np.float32)
    return img


class Parts:
    """Surfaces and their parts' bounding spheres (``groups`` of :func:`~course_lib.data.building.render`).

    Args:
        texture: ``texture(kind, w_units, h_units) -> (Ht, Wt, 3)`` float image of a face.
        specular: optional ``{kind: strength}``: faces of those kinds are glossy
            (:class:`~course_lib.data.building.Surface`'s ``specular``).
    """

    def __init__(self, texture: Callable[[str, float, float], np.ndarray], specular: dict | None = None):
        self.texture, self.specular = texture, dict(specular or {})
        self.surfaces: list[Surface] = []
        self.groups: list[tuple] = []
        self._open: tuple | None = None  # (first surface, corners so far) of a group of several parts

    @contextmanager
    def group(self):
        """Parts made inside the block share one bounding sphere (many small parts: fewer sphere tests)."""
        self._open = (len(self.surfaces), [])
        try:
            yield
        finally:
            first, corners = self._open
            self._open = None
            if corners:  # an empty block adds no group
                self._group(first, np.concatenate(corners))

    def face(self, name, origin, a, b, kind, triangle=False) -> None:
        """One textured face ``origin + s a + t b`` (a triangle: ``s + t <= 1``); not grouped (see :meth:`panel`)."""
        tex = self.texture(kind, float(np.linalg.norm(a)), float(np.linalg.norm(b)))
        self.surfaces.append(Surface(name, np.asarray(origin, float), np.asarray(a, float), np.asarray(b, float),
                                     np.clip(tex, 0, 1).astype(np.float32), triangle, self.specular.get(kind, 0.0)))

    def _group(self, first: int, corners: np.ndarray) -> None:
        if self._open is not None:
            self._open[1].append(corners)
            return
        center = 0.5 * (corners.min(axis=0) + corners.max(axis=0))
        self.groups.append((first, len(self.surfaces), center, float(np.linalg.norm(corners - center, axis=1).max()) + 1e-6))

    def box(self, name, center, size, R=np.eye(3), kinds="body", top=True, bottom=True):
        """A box of ``size (3,)`` (local x, y, z) centred at ``center``, turned by ``R``; ``kinds``: one or six
        (+x, -x, +y, -y, +z, -z)."""
        first = len(self.surfaces)
        c, (hx, hy, hz) = np.asarray(center, float), 0.5 * np.asarray(size, float)
        P = lambda x, y, z: c + R @ np.array([x, y, z], float)  # noqa: E731
        V = lambda x, y, z: R @ np.array([x, y, z], float)  # noqa: E731
        k = [kinds] * 6 if isinstance(kinds, str) else list(kinds)
        faces = [(P(hx, -hy, -hz), V(0, 2 * hy, 0), V(0, 0, 2 * hz)), (P(-hx, hy, -hz), V(0, -2 * hy, 0), V(0, 0, 2 * hz)),
                 (P(hx, hy, -hz), V(-2 * hx, 0, 0), V(0, 0, 2 * hz)), (P(-hx, -hy, -hz), V(2 * hx, 0, 0), V(0, 0, 2 * hz)),
                 (P(-hx, -hy, hz), V(2 * hx, 0, 0), V(0, 2 * hy, 0)), (P(-hx, hy, -hz), V(2 * hx, 0, 0), V(0, -2 * hy, 0))]
        for i, (o, a, b) in enumerate(faces):
            if (i == 4 and not top) or (i == 5 and not bottom):
                continue
            self.face(f"{name} {i}", o, a, b, k[i])
        corners = np.array([P(sx * hx, sy * hy, sz * hz) for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
        self._group(first, corners)

    def prism(self, name, center, radius, length, R=np.eye(3), sides=8, kind="wheel", cap="hub", caps=(True, True)):
        """A prism of ``sides`` faces around the local x axis (a wheel, a stud, a pot), turned by ``R``.

        ``caps``: which ends (-x, +x) are closed by a fan of triangles of texture ``cap``.
        """
        first = len(self.surfaces)
        c = np.asarray(center, float)
        ang = 2 * np.pi * (np.arange(sides) + 0.5) / sides
        ring = np.stack([np.zeros(sides), radius * np.cos(ang), radius * np.sin(ang)], axis=1) @ R.T
        ax = R @ np.array([length, 0.0, 0.0])
        for i in range(sides):
            p, q = ring[i], ring[(i + 1) % sides]
            self.face(f"{name} tread {i}", c + p - 0.5 * ax, q - p, ax, kind)
        for side, closed in zip((-0.5, 0.5), caps):
            if not closed:
                continue
            hub = c + side * ax
            for i in range(sides):
                self.face(f"{name} cap {i}", hub, ring[i], ring[(i + 1) % sides], cap, triangle=True)
        self._group(first, np.concatenate([c + ring - 0.5 * ax, c + ring + 0.5 * ax]))

    def wheel(self, name, center, radius, width, sides=8):
        """An octagonal prism along x with both ends capped: a wheel."""
        self.prism(name, center, radius, width, sides=sides)

    def panel(self, name, origin, a, b, kind, triangle=False):
        """One face as a part of its own (a leaf, a sign): seen from both sides, its own bounding sphere."""
        first = len(self.surfaces)
        self.face(name, origin, a, b, kind, triangle)
        o, a, b = (np.asarray(v, float) for v in (origin, a, b))
        self._group(first, np.array([o, o + a, o + b, o + a + b]))

    def rod(self, name, p, q, width, kind="metal"):
        """A thin square rod from ``p`` to ``q`` (a stem, a wire): a box along the segment."""
        p, q = np.asarray(p, float), np.asarray(q, float)
        d = q - p
        length = float(np.linalg.norm(d))
        y = d / length
        x = np.cross(y, [0.0, 0.0, 1.0] if abs(y[2]) < 0.9 else [1.0, 0.0, 0.0])
        x /= np.linalg.norm(x)
        R = np.stack([x, y, np.cross(x, y)], axis=1)  # local y along the rod
        self.box(name, 0.5 * (p + q), (width, length, width), R, kinds=kind)


# ============================================================================ data sets


def _resize_rgba(rgba: np.ndarray, size: int) -> np.ndarray:
    import cv2

    if rgba.shape[0] == size:
        return rgba
    return cv2.resize(rgba, (size, size), interpolation=cv2.INTER_AREA)


def render_views(surfaces, groups, c2w: np.ndarray, size: int, camera_angle_x: float, verbose: bool = False,
                 label: str = "") -> list[np.ndarray]:
    """RGBA renders ``(size, size, 4)`` float32 of the views ``c2w (N, 4, 4)`` (OpenCV axes), 2 x 2 rays per pixel."""
    K = intrinsics_from_fov(size, size, camera_angle_x)
    imgs = []
    for i, M in enumerate(c2w):
        R_cw = M[:3, :3].T
        rgb, alpha = render(surfaces, K, R_cw, -R_cw @ M[:3, 3], (size, size), supersample=2, background="transparent",
                            groups=groups)
        imgs.append(np.concatenate([rgb, alpha[..., None]], -1).astype(np.float32))
        if verbose and (i + 1) % 10 == 0:
            print(f"  {label}{i + 1}/{len(c2w)} views rendered at {size} px", flush=True)
    return imgs


def write_object_datasets(root, name: str, surfaces, groups, cams: dict, sizes, camera_angle_x: float, info: dict,
                          verbose: bool = False) -> dict[int, Path]:
    """Render ``cams`` once at ``max(sizes)`` and write ``root/NAME-SIZE/`` (Blender format) for each size.

    Args:
        root: the parent folder.
        name: the scene's name (the folders' prefix).
        surfaces, groups: the scene (:class:`Parts`).
        cams: ``{split: c2w (N, 4, 4)}`` (OpenCV axes, NeRF frame).
        sizes: image sides in pixels; each must divide the largest one.
        camera_angle_x: horizontal field of view (radians).
        info: written into each folder's ``scene.json`` with the sizes and the number of surfaces.
        verbose: print progress.

    Returns:
        ``{size: folder}``; each holds ``transforms_SPLIT.json``, ``images/`` and ``scene.json``.
    """
    sizes = sorted({int(s) for s in sizes})
    top = sizes[-1]
    if any(s < 8 or top % s for s in sizes):
        raise KitInputError(f"sizes {sizes}: expected sides of at least 8 px that divide the largest one ({top})")
    renders = {split: render_views(surfaces, groups, c2w, top, camera_angle_x, verbose, f"{name} {split}: ")
               for split, c2w in cams.items()}
    folders = {}
    for size in sizes:
        folder = Path(root) / f"{name}-{size}"
        for split, c2w in cams.items():
            imgs = np.stack([_resize_rgba(img, size) for img in renders[split]])
            write_blender(folder, split, imgs, c2w, camera_angle_x)
        meta = {**info, "image_size": [size, size], "rendered_at": top, "camera_angle_x": camera_angle_x,
                "n_surfaces": len(surfaces)}
        (folder / "scene.json").write_text(json.dumps(meta, indent=1))
        folders[size] = folder
        if verbose:
            print(f"wrote {folder}", flush=True)
    return folders

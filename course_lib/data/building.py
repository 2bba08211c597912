"""The kit's embedded scenes: a small textured building, rendered by ray casting, with ground truth.

One seeded generator makes both embedded data sets, so the kit runs (and is tested) without the
course's own data:

* ``data/synthetic-building/`` -- an SfM capture in the course's P3 format: 6 photos (800x600
  JPEG, K like the WPI camera) taken while walking past the building, SIFT features matched
  across all pairs with OpenCV (ratio test, so there are real outliers, as in the course data;
  :mod:`course_lib.data.features`), joined into tracks and written with :func:`course_lib.data.p3.write_p3`, plus
  ``ground_truth.json`` with the true cameras (read it with :func:`load_ground_truth`).
* ``data/synthetic-building-nerf/`` -- the same building (on a bounded base slab, no infinite
  ground) seen from ~100 views on the upper hemisphere at 100x100, RGBA with a transparent
  background, in NeRF's Blender format (:func:`course_lib.data.blender.write_blender`).

The scene
    World axes: **z up**, metres. A two-storey main block (8 m wide, 4 m deep, 5 m to the eaves)
    with a gable roof (ridge at 6.5 m), a one-storey wing (3 x 2 m) that sticks out 2 m towards the
    street, and a kiosk box in front: so the scene has depth and several planes, never a single
    one. Walls have procedural stone blocks, windows with frames, a door, signs with letters and
    posters; the roof has tiles; the ground has paving stones and grass. Every surface is a
    textured planar rectangle (or triangle, for the gables) with a per-face Lambertian shade.

The renderer
    A pinhole camera in the kit's conventions (:mod:`course_lib.conventions`: x right, y down,
    z forward, ``x_cam = R_cw X + t_cw``, pixel centre of the top-left pixel at (0, 0)). Each
    pixel is sampled 2x2 times (supersampling against aliasing); every ray is intersected with
    every surface (vectorized numpy), the nearest hit wins, its colour is the bilinear lookup in
    the surface's texture times its shade. Rays that miss see the sky (SfM) or are transparent
    (NeRF).

Regenerate with ``python -m course_lib make-data`` (same seed -> same files).

Introduced in ``notebooks/01_fundamental_matrix.ipynb`` (SfM) and
``notebooks/06_nerf_data_and_rays.ipynb`` (NeRF).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from course_lib.conventions import camera_center, invert_pose
from course_lib.data.blender import intrinsics_from_fov, write_blender
from course_lib.data.p3 import write_p3
from course_lib.data.tracks import tracks_from_images
from course_lib.data.synthetic import WPI_LIKE_K, look_at
from course_lib.data.textures import ground_texture, plain_texture, roof_texture, wall_texture
from course_lib.validate import KitInputError, file_in, intrinsics, rotation, vector3

__all__ = [
    "DEFAULT_SEED",
    "GENERATOR",
    "Surface",
    "build_scene",
    "render",
    "cast_rays",
    "cast_rays_grouped",
    "sfm_cameras",
    "nerf_cameras",
    "orbit_camera",
    "sfm_photos",
    "make_sfm_dataset",
    "make_nerf_dataset",
    "load_ground_truth",
    "epipolar_errors",
]

#: Seed of the committed data sets.
DEFAULT_SEED = 2024
#: Name and version written into ground_truth.json.
GENERATOR = "course_lib.data.building v1"
#: Image size of the SfM photos (W, H).
SFM_IMAGE_SIZE = (800, 600)
#: NeRF: scene centre (world, metres) and scale into the NeRF frame, camera distance, field of view.
NERF_CENTER = np.array([0.0, -1.0, 2.5])
NERF_SCALE = 0.2
NERF_RADIUS = 4.0
NERF_CAMERA_ANGLE_X = 0.8
NERF_SIZE = 100

_SUN = np.array([-0.45, -0.65, 0.62]) / np.linalg.norm([-0.45, -0.65, 0.62])


# ============================================================================ scene


@dataclass
class Surface:
    """A textured planar parallelogram ``X = origin + s a + t b``, ``s, t in [0, 1]``.

    Attributes:
        name: for debugging and documentation.
        origin: ``(3,)`` corner, world metres.
        a, b: ``(3,)`` edge vectors (``b`` runs "up" the texture).
        texture: ``(Ht, Wt, 3)`` float32 RGB in [0, 1]; texel ``(row, col)`` covers
            ``s = (col + 0.5) / Wt``, ``t = 1 - (row + 0.5) / Ht``.
        triangle: if True only the half ``s + t <= 1`` exists (the gables).
        specular: gloss in [0, 1]: 0 is matte (Lambertian, the building); above it the face
            mirrors a sky of that strength and shows the sun's highlight (Blinn-Phong), which
            change with the viewing direction (the family's glossy scene, :mod:`course_lib.data.family`).
    """

    name: str
    origin: np.ndarray
    a: np.ndarray
    b: np.ndarray
    texture: np.ndarray
    triangle: bool = False
    specular: float = 0.0

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.a, self.b)
        return n / np.linalg.norm(n)


def build_scene(rng: np.random.Generator, ground: str = "large", rho: float = 80.0) -> list[Surface]:
    """The building's surfaces with their procedural textures.

    Args:
        rng: seeded generator (textures only; the geometry is fixed).
        ground: ``"large"`` (a 30 x 30 m paved square for the SfM photos) or ``"slab"`` (a bounded
            11 x 9 m base slab, 0.3 m thick, for the NeRF views: no infinite ground).
        rho: texels per metre of the walls.

    Returns:
        List of :class:`Surface`.
    """
    V = lambda *v: np.array(v, float)  # noqa: E731
    S = []

    def add(name, o, a, b, tex, tri=False):
        S.append(Surface(name, V(*o), V(*a), V(*b), tex.astype(np.float32), tri))

    win = lambda x, z: (x, z, 1.0, 1.4)  # noqa: E731
    # main block: x in [-4, 4], y in [-2, 2], z in [0, 5]; the street is at y < 0
    add("main front", (-4, -2, 0), (8, 0, 0), (0, 0, 5), wall_texture(
        rng, 8, 5, rho, windows=[win(0.5, 1.0), win(2.3, 1.0), win(0.5, 3.2), win(2.3, 3.2), win(4.3, 3.2), win(6.2, 3.2)],
        doors=[(4.3, 0.0, 1.2, 2.3)], signs=[(0.4, 2.55, 3.0, 0.5, "COURSE KIT"), (3.9, 2.45, 0.7, 0.55), (6.0, 0.6, 0.9, 1.2)]))
    add("main left", (-4, 2, 0), (0, -4, 0), (0, 0, 5), wall_texture(
        rng, 4, 5, rho, windows=[win(0.6, 1.0), win(2.4, 3.2)], signs=[(2.2, 0.8, 1.2, 1.6), (0.3, 3.0, 1.4, 0.6, "SFM")],
        base=(0.66, 0.52, 0.40)))
    add("main right", (4, -2, 0), (0, 4, 0), (0, 0, 5), wall_texture(
        rng, 4, 5, rho, windows=[win(2.2, 1.0), win(1.0, 3.2)], signs=[(0.4, 3.3, 0.5, 1.0)], base=(0.66, 0.52, 0.40)))
    add("main back", (4, 2, 0), (-8, 0, 0), (0, 0, 5), wall_texture(
        rng, 8, 5, rho, windows=[win(1.0, 1.0), win(5.5, 1.0), win(1.0, 3.2), win(3.5, 3.2), win(5.5, 3.2)],
        signs=[(3.0, 0.8, 1.6, 1.0, "NERF")]))
    add("roof front", (-4, -2, 5), (8, 0, 0), (0, 2, 1.5), roof_texture(rng, 8, 2.5, rho))
    add("roof back", (4, 2, 5), (-8, 0, 0), (0, -2, 1.5), roof_texture(rng, 8, 2.5, rho))
    add("gable left", (-4, 2, 5), (0, -4, 0), (0, -2, 1.5), plain_texture(rng, 4, 2.5, rho, (0.85, 0.8, 0.68)), tri=True)
    add("gable right", (4, -2, 5), (0, 4, 0), (0, 2, 1.5), plain_texture(rng, 4, 2.5, rho, (0.85, 0.8, 0.68)), tri=True)
    # wing: x in [1, 4], y in [-4, -2], z in [0, 3] with a flat roof
    add("wing front", (1, -4, 0), (3, 0, 0), (0, 0, 3), wall_texture(
        rng, 3, 3, rho, windows=[(0.3, 0.9, 2.4, 1.5)], signs=[(0.5, 2.55, 2.0, 0.35, "CAFE 549")], base=(0.78, 0.74, 0.66)))
    add("wing left", (1, -2, 0), (0, -2, 0), (0, 0, 3), wall_texture(
        rng, 2, 3, rho, windows=[(0.5, 1.0, 1.0, 1.2)], signs=[(0.3, 2.3, 1.4, 0.45)], base=(0.78, 0.74, 0.66)))
    add("wing right", (4, -4, 0), (0, 2, 0), (0, 0, 3), wall_texture(rng, 2, 3, rho, signs=[(0.4, 0.8, 1.2, 1.4)], base=(0.78, 0.74, 0.66)))
    add("wing roof", (1, -4, 3), (3, 0, 0), (0, 2, 0), plain_texture(rng, 3, 2, rho, (0.35, 0.35, 0.38), 0.35, 0.15))
    # kiosk: x in [-3, -1.8], y in [-5.2, -4.2], z in [0, 1.3]
    kiosk = lambda w, h: wall_texture(rng, w, h, rho, signs=[(0.1, 0.2, w - 0.2, h - 0.4)], base=(0.3, 0.45, 0.6))  # noqa: E731
    add("kiosk front", (-3, -5.2, 0), (1.2, 0, 0), (0, 0, 1.3), kiosk(1.2, 1.3))
    add("kiosk left", (-3, -4.2, 0), (0, -1, 0), (0, 0, 1.3), kiosk(1.0, 1.3))
    add("kiosk right", (-1.8, -5.2, 0), (0, 1, 0), (0, 0, 1.3), kiosk(1.0, 1.3))
    add("kiosk back", (-1.8, -4.2, 0), (-1.2, 0, 0), (0, 0, 1.3), kiosk(1.2, 1.3))
    add("kiosk top", (-3, -5.2, 1.3), (1.2, 0, 0), (0, 1, 0), plain_texture(rng, 1.2, 1.0, rho, (0.8, 0.8, 0.8), 0.3, 0.1))
    if ground == "large":
        add("ground", (-15, -22, 0), (30, 0, 0), (0, 30, 0), ground_texture(rng, 30, 30, 40.0))
    elif ground == "slab":
        x0, x1, y0, y1, d = -5.5, 5.5, -6.0, 3.0, 0.3
        add("slab top", (x0, y0, 0), (x1 - x0, 0, 0), (0, y1 - y0, 0), ground_texture(rng, x1 - x0, y1 - y0, rho))
        side = lambda w: plain_texture(rng, w, d, rho, (0.45, 0.42, 0.4), 0.3, 0.1)  # noqa: E731
        add("slab front", (x0, y0, -d), (x1 - x0, 0, 0), (0, 0, d), side(x1 - x0))
        add("slab back", (x1, y1, -d), (x0 - x1, 0, 0), (0, 0, d), side(x1 - x0))
        add("slab left", (x0, y1, -d), (0, y0 - y1, 0), (0, 0, d), side(y1 - y0))
        add("slab right", (x1, y0, -d), (0, y1 - y0, 0), (0, 0, d), side(y1 - y0))
        add("slab bottom", (x0, y1, -d), (x1 - x0, 0, 0), (0, y0 - y1, 0), side(x1 - x0)[:1].repeat(8, 0))
    else:
        raise KitInputError(f"ground = {ground!r}: expected 'large' or 'slab'")
    return S


# ============================================================================ rendering


def cast_rays(surfaces: list[Surface], C: np.ndarray, d: np.ndarray):
    """Nearest hit of rays ``C + lam d`` (``lam > 0``) with the surfaces.

    Args:
        surfaces: the scene.
        C: ``(3,)`` common origin (the camera centre).
        d: ``(N, 3)`` directions (any length).

    Returns:
        ``lam (N,)`` (inf where nothing is hit), ``sid (N,)`` surface index (-1: miss),
        ``s (N,)``, ``t (N,)`` surface coordinates of the hit.
    """
    N = d.shape[0]
    best = np.full(N, np.inf)
    sid = np.full(N, -1, int)
    bs, bt = np.zeros(N), np.zeros(N)
    for k, S in enumerate(surfaces):
        n = np.cross(S.a, S.b)
        denom = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = ((S.origin - C) @ n) / denom
        q0 = C - S.origin
        G = np.array([[S.a @ S.a, S.a @ S.b], [S.a @ S.b, S.b @ S.b]])
        Gi = np.linalg.inv(G)
        qa = q0 @ S.a + lam * (d @ S.a)
        qb = q0 @ S.b + lam * (d @ S.b)
        s = Gi[0, 0] * qa + Gi[0, 1] * qb
        t = Gi[1, 0] * qa + Gi[1, 1] * qb
        ok = (lam > 1e-9) & (lam < best) & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1)
        if S.triangle:
            ok &= s + t <= 1
        best[ok], sid[ok], bs[ok], bt[ok] = lam[ok], k, s[ok], t[ok]
    return best, sid, bs, bt


def _bilinear(tex: np.ndarray, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    Ht, Wt = tex.shape[:2]
    x = np.clip(s * Wt - 0.5, 0, Wt - 1)
    y = np.clip((1.0 - t) * Ht - 0.5, 0, Ht - 1)
    x0, y0 = np.minimum(x.astype(int), Wt - 2), np.minimum(y.astype(int), Ht - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return ((1 - fy) * ((1 - fx) * tex[y0, x0] + fx * tex[y0, x0 + 1])
            + fy * ((1 - fx) * tex[y0 + 1, x0] + fx * tex[y0 + 1, x0 + 1]))


def _shade(surfaces, sid, d, rgb_out, s, t):
    for k, S in enumerate(surfaces):
        m = sid == k
        if not m.any():
            continue
        n = S.normal
        facing = np.where((d[m] @ n) < 0, 1.0, -1.0)[:, None] * n[None, :]  # normal towards the viewer
        shade = 0.5 + 0.6 * np.clip(facing @ _SUN, 0, 1)
        rgb_out[m] = _bilinear(S.texture, s[m], t[m]) * shade[:, None]
        if S.specular > 0:
            rgb_out[m] = _gloss(rgb_out[m], S.specular, facing, d[m])


def _gloss(rgb, specular, n, d):
    """A glossy face's colour: the diffuse ``rgb (M, 3)`` dimmed, plus the mirrored sky and the sun's highlight.

    ``n (M, 3)`` unit normals towards the viewer, ``d (M, 3)`` the rays' directions.
    """
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    mirror = d - 2.0 * np.sum(d * n, axis=1)[:, None] * n
    half = _SUN[None, :] - d
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    highlight = np.clip(np.sum(half * n, axis=1), 0, 1) ** 60
    fresnel = 0.06 + 0.6 * (1.0 - np.abs(np.sum(d * n, axis=1))) ** 4  # mirrors more at grazing angles
    return (1.0 - 0.5 * specular) * rgb + specular * (fresnel[:, None] * _sky(mirror) + 1.2 * highlight[:, None])


def _sky(d: np.ndarray) -> np.ndarray:
    e = np.clip(d[:, 2] / np.linalg.norm(d, axis=1), -0.2, 1)[:, None]
    return (1 - e) * np.array([0.78, 0.85, 0.93]) + e * np.array([0.35, 0.55, 0.85])


def cast_rays_grouped(surfaces: list[Surface], groups, C: np.ndarray, d: np.ndarray):
    """:func:`cast_rays` for a scene of parts: each part's surfaces are tested only by the rays near it.

    Args:
        surfaces: the scene. C: ``(3,)`` the rays' origin. d: ``(N, 3)`` directions.
        groups: list of ``(first, stop, center (3,), radius)``: surfaces ``first:stop`` lie inside
            the sphere ``(center, radius)``; a ray that misses the sphere cannot hit them.

    Returns:
        As :func:`cast_rays` (surface indices into ``surfaces``).
    """
    N = d.shape[0]
    best, sid = np.full(N, np.inf), np.full(N, -1, int)
    bs, bt = np.zeros(N), np.zeros(N)
    dn = d / np.linalg.norm(d, axis=1, keepdims=True)
    for first, stop, center, radius in groups:
        oc = np.asarray(center, float) - C
        along = dn @ oc  # distance along the ray to the point closest to the centre
        near = np.nonzero((oc @ oc - along * along <= radius * radius) & (along > -radius))[0]
        if near.size == 0:
            continue
        lam, k, s, t = cast_rays(surfaces[first:stop], C, d[near])
        better = lam < best[near]
        idx = near[better]
        best[idx], sid[idx], bs[idx], bt[idx] = lam[better], k[better] + first, s[better], t[better]
    return best, sid, bs, bt


def render(surfaces: list[Surface], K: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray, image_size: tuple[int, int],
           supersample: int = 2, background: str = "sky", chunk: int = 300_000, groups=None) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast an image of the scene.

    Args:
        surfaces: from :func:`build_scene`.
        K: ``(3, 3)`` intrinsics. R_cw: ``(3, 3)``. t_cw: ``(3,)`` (the kit's convention).
        image_size: ``(W, H)``.
        supersample: n, renders n x n rays per pixel (at offsets ``(k + 0.5) / n - 0.5``) and averages.
        background: ``"sky"`` (a gradient, alpha 1 everywhere) or ``"transparent"`` (alpha 0 where
            rays miss; the returned RGB is the mean over the hits, i.e. *not* premultiplied).
        chunk: rays per batch (memory).
        groups: optional bounding spheres of the scene's parts (:func:`cast_rays_grouped`): the same
            image, faster for scenes of many small parts.

    Returns:
        ``rgb (H, W, 3)`` float in [0, 1] and ``alpha (H, W)`` float in [0, 1] (fraction of hits).
    """
    K = intrinsics(K)
    R_cw = rotation(R_cw, "R_cw")
    t_cw = vector3(t_cw, "t_cw")
    W, H = (int(v) for v in image_size)
    n = int(supersample)
    C = camera_center(R_cw, t_cw)
    off = (np.arange(n) + 0.5) / n - 0.5
    rows = (np.arange(H)[:, None] + off[None, :]).ravel()  # (H n,) pixel v of the sub-rows
    cols = (np.arange(W)[:, None] + off[None, :]).ravel()  # (W n,)
    vv, uu = np.meshgrid(rows, cols, indexing="ij")
    pix = np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)], 1)
    d_cam = pix @ np.linalg.inv(K).T
    d = d_cam @ R_cw  # world directions: R_cw^T d_cam, row-wise
    rgb = np.zeros((d.shape[0], 3))
    hit = np.zeros(d.shape[0], bool)
    for a in range(0, d.shape[0], chunk):
        dd = d[a:a + chunk]
        lam, sid, s, t = cast_rays(surfaces, C, dd) if groups is None else cast_rays_grouped(surfaces, groups, C, dd)
        out = np.zeros((dd.shape[0], 3))
        _shade(surfaces, sid, dd, out, s, t)
        miss = sid < 0
        if background == "sky":
            out[miss] = _sky(dd[miss])
        rgb[a:a + chunk] = out
        hit[a:a + chunk] = ~miss
    rgb = rgb.reshape(H, n, W, n, 3)
    hit = hit.reshape(H, n, W, n).astype(float)
    if background == "sky":
        return np.clip(rgb.mean(axis=(1, 3)), 0, 1), np.ones((H, W))
    if background != "transparent":
        raise KitInputError(f"background = {background!r}: expected 'sky' or 'transparent'")
    cover = hit.sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        col = (rgb * hit[..., None]).sum(axis=(1, 3)) / cover[..., None]
    col[cover == 0] = 0
    return np.clip(col, 0, 1), cover / (n * n)


# ============================================================================ cameras


def _roll(R_cw: np.ndarray, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ R_cw


def sfm_cameras(rng: np.random.Generator, n_cameras: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Cameras of a student walking past the building, all looking at it.

    Centres spread over an arc around (0, -1) in front of the building, from -30 to +30 degrees,
    9.5-13.5 m away and 1.3-2.3 m high (eye height, a step, a low wall), each aimed at the
    building's middle with a few decimetres of jitter and a degree or two of roll.

    Note for evaluations: the centres lie within about 2 m of a line (singular values of the
    centred centres about 10.5, 1.9 and 0.2 m), so a similarity alignment of the *centres* alone
    pins the rotation about that line only to about (centre error / 2 m) radians; 1 cm of centre
    error costs up to 0.3 degrees there. Compare rotations after that alignment with this in mind
    (relative rotations between the cameras are alignment free).

    Returns:
        ``R_cw (M, 3, 3)``, ``t_cw (M, 3)``.
    """
    angles = np.radians(np.linspace(-30.0, 30.0, n_cameras)) + rng.normal(0, np.radians(1.5), n_cameras)
    radii = 11.5 + rng.uniform(-2.0, 2.0, n_cameras)
    heights = rng.uniform(1.3, 2.3, n_cameras)
    Rs, ts = [], []
    for a, r, h in zip(angles, radii, heights):
        C = np.array([r * np.sin(a), -1.0 - r * np.cos(a), h])
        target = np.array([0.0, -1.5, 2.6]) + rng.normal(0, [0.5, 0.3, 0.3])
        R, _ = look_at(C, target, up=(0.0, 0.0, 1.0))
        R = _roll(R, rng.normal(0, np.radians(1.5)))
        Rs.append(R)
        ts.append(-R @ C)
    return np.stack(Rs), np.stack(ts)


def orbit_camera(radius: float, azimuth: float, elevation: float) -> np.ndarray:
    """The ``(4, 4)`` camera-to-world matrix (OpenCV axes) of a camera on a sphere around the origin.

    The camera sits at ``radius`` from the origin at ``azimuth`` / ``elevation`` (radians, world z
    up) and looks at the origin with world +z up in the image.
    """
    C = radius * np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
    R_cw, t_cw = look_at(C, np.zeros(3), up=(0.0, 0.0, 1.0))
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = invert_pose(R_cw, t_cw)
    return M


def nerf_cameras(rng: np.random.Generator, n: int, kind: str = "random", radius: float | None = None) -> np.ndarray:
    """Camera-to-world matrices (OpenCV axes) in the NeRF frame, all looking at the origin.

    Args:
        rng: seeded generator.
        n: number of views.
        kind: ``"random"``: uniform on the upper hemisphere (elevation 8-75 degrees), distance
            ``radius``; ``"ring"``: n views on a circle at 30 degrees elevation.
        radius: the cameras' distance from the origin (None: :data:`NERF_RADIUS`).

    Returns:
        ``c2w (n, 4, 4)``: camera-to-world, OpenCV axes (x right, y down, z forward), in the NeRF
        frame ``X_nerf = NERF_SCALE * (X_world - NERF_CENTER)``.
    """
    if kind == "random":
        az = rng.uniform(0, 2 * np.pi, n)
        z = rng.uniform(np.sin(np.radians(8)), np.sin(np.radians(75)), n)  # uniform on the sphere's zone
        el = np.arcsin(z)
    elif kind == "ring":
        az = np.linspace(0, 2 * np.pi, n, endpoint=False) + np.radians(10)
        el = np.full(n, np.radians(30.0))
    else:
        raise KitInputError(f"kind = {kind!r}: expected 'random' or 'ring'")
    out = []
    for a, e in zip(az, el):
        out.append(orbit_camera(NERF_RADIUS if radius is None else float(radius), a, e))
    return np.stack(out)


# ============================================================================ features


def _to_uint8(rgb: np.ndarray) -> np.ndarray:
    return np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8)


# ============================================================================ data sets


def _jpeg_roundtrip(rgb_u8: np.ndarray, quality: int) -> tuple[bytes, np.ndarray]:
    import cv2

    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb_u8[:, :, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    dec = cv2.imdecode(buf, cv2.IMREAD_COLOR)[:, :, ::-1]
    return buf.tobytes(), np.ascontiguousarray(dec)


def sfm_photos(seed: int = DEFAULT_SEED, n_cameras: int = 6, quality: int = 88, count: int | None = None):
    """Render the SfM photos one by one (a generator), exactly as :func:`make_sfm_dataset` does.

    Args:
        seed, n_cameras, quality: as in :func:`make_sfm_dataset`.
        count: stop after this many photos (the first ones are identical to the full run's).

    Yields:
        First ``(K, R_cw (M, 3, 3), t_cw (M, 3))``, then per photo ``(jpeg_bytes, rgb (H, W, 3) uint8)``
        where ``rgb`` is the decoded JPEG (what the students get).
    """
    rng = np.random.default_rng(seed)
    surfaces = build_scene(rng, ground="large")
    K = WPI_LIKE_K.copy()
    R_cw, t_cw = sfm_cameras(rng, n_cameras)
    yield K, R_cw, t_cw
    for i in range(n_cameras if count is None else min(count, n_cameras)):
        rgb, _ = render(surfaces, K, R_cw[i], t_cw[i], SFM_IMAGE_SIZE, supersample=2)
        rgb = rgb + rng.normal(0, 1.5 / 255, rgb.shape)  # sensor noise
        yield _jpeg_roundtrip(_to_uint8(rgb), quality)


def make_sfm_dataset(folder, seed: int = DEFAULT_SEED, n_cameras: int = 6, quality: int = 88, verbose: bool = False) -> dict:
    """Render the SfM photos, match SIFT features and write a P3 folder with ground truth.

    Args:
        folder: output folder (e.g. ``data/synthetic-building``); existing P3 files are replaced.
        seed: the seed of everything random (textures, cameras, sensor noise).
        n_cameras: number of photos (5-6 is like the course data).
        quality: JPEG quality of the photos.
        verbose: print progress.

    Returns:
        Summary dict (tracks, raw matches per pair, track-building stats).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    names = [f"{i + 1}.jpg" for i in range(n_cameras)]
    photos = sfm_photos(seed, n_cameras, quality)
    K, R_cw, t_cw = next(photos)
    images = []
    for name, (data, dec) in zip(names, photos):
        (folder / name).write_bytes(data)
        images.append(dec)  # features are detected on what the students get: the decoded JPEG
        if verbose:
            print(f"rendered {name}", flush=True)
    track_uv, track_rgb, pairs, tstats = tracks_from_images(images)
    write_p3(folder, names, K, track_uv, track_rgb)  # images already written (JPEG bytes)
    gt = {
        "K": K.tolist(),
        "image_size": list(SFM_IMAGE_SIZE),
        "images": [{"name": n, "R_cw": R.tolist(), "t_cw": t.tolist()} for n, R, t in zip(names, R_cw, t_cw)],
        "seed": int(seed),
        "generator": GENERATOR,
        "world": "metres, z up; building x in [-4, 4], y in [-4, 2], z in [0, 6.5] (kiosk in front down to y = -5.2); cameras 9.5-13.5 m in front of it",
        "scene_size": float(np.linalg.norm([8.0, 6.0, 6.5])),
        "convention": "x_cam = R_cw @ X + t_cw; OpenCV camera axes (x right, y down, z forward)",
    }
    (folder / "ground_truth.json").write_text(json.dumps(gt, indent=1))
    summary = {"tracks": int(len(track_uv)), **tstats,
               "pairs": {f"{i + 1}-{j + 1}": int(len(x1)) for (i, j), (x1, _) in pairs.items()}}
    return summary


def make_nerf_dataset(folder, seed: int = DEFAULT_SEED, n_train: int = 100, n_val: int = 5, n_test: int = 12,
                      size: int = NERF_SIZE, splits=("train", "val", "test"), verbose: bool = False) -> dict:
    """Render the NeRF views (RGBA, transparent background) and write them in Blender format.

    The building stands on a bounded base slab; the NeRF frame is
    ``X_nerf = NERF_SCALE * (X_world - NERF_CENTER)`` (z up), so the scene fits in about
    ``[-1.1, 1.1] x [-1, 0.8] x [-0.6, 0.8]`` and the cameras sit :data:`NERF_RADIUS` from the origin.
    Train and val views are random on the upper hemisphere; test views are a ring at 30 degrees.

    Args:
        folder: output folder.
        seed: the seed (textures and cameras; the rendering itself is deterministic).
        n_train, n_val, n_test: views per split.
        size: image width = height in pixels.
        splits: the splits to render and write (the cameras of all three are always drawn, so a
            subset gives the same files as the full run).
        verbose: print progress.

    Returns:
        Summary dict (number of views per split).
    """
    folder = Path(folder)
    rng = np.random.default_rng(seed + 1)
    surfaces = build_scene(rng, ground="slab", rho=40.0)
    K = intrinsics_from_fov(size, size, NERF_CAMERA_ANGLE_X)
    cams = {"train": nerf_cameras(rng, n_train), "val": nerf_cameras(rng, n_val), "test": nerf_cameras(rng, n_test, "ring")}
    for split in splits:
        if split not in cams:
            raise KitInputError(f"split {split!r}: expected train, val or test")
        c2w = cams[split]
        imgs = []
        for M in c2w:
            C_world = NERF_CENTER + M[:3, 3] / NERF_SCALE
            R_cw = M[:3, :3].T
            rgb, alpha = render(surfaces, K, R_cw, -R_cw @ C_world, (size, size), supersample=2, background="transparent")
            imgs.append(np.concatenate([_to_uint8(rgb), _to_uint8(alpha[..., None])], -1))
        write_blender(folder, split, np.stack(imgs), c2w, NERF_CAMERA_ANGLE_X, names=[f"{split}_{i:03d}" for i in range(len(c2w))])
        if verbose:
            print(f"rendered {len(c2w)} {split} views", flush=True)
    info = {"seed": int(seed), "generator": GENERATOR, "nerf_center_world": NERF_CENTER.tolist(), "nerf_scale": NERF_SCALE,
            "radius": NERF_RADIUS, "camera_angle_x": NERF_CAMERA_ANGLE_X, "image_size": [size, size],
            "world": "NeRF frame: z up, X_nerf = nerf_scale * (X_world - nerf_center_world); world in metres"}
    (folder / "scene.json").write_text(json.dumps(info, indent=1))
    return {k: len(cams[k]) for k in splits}


# ============================================================================ ground truth


def load_ground_truth(folder) -> tuple[np.ndarray, list[str], np.ndarray, np.ndarray]:
    """Read ``ground_truth.json`` of a generated P3 folder.

    Args:
        folder: the folder (or the JSON file itself).

    Returns:
        ``K (3, 3)``, image names (M), ``R_cw (M, 3, 3)``, ``t_cw (M, 3)`` (the kit's convention).

    Introduced in ``notebooks/01_fundamental_matrix.ipynb``.
    """
    p = file_in(folder, "ground_truth.json", "ground truth not found: {path} (only the kit's generated scenes have ground_truth.json)")
    try:
        gt = json.loads(p.read_text())
        K = intrinsics(np.array(gt["K"], float))
        names = [im["name"] for im in gt["images"]]
        R_cw = np.array([im["R_cw"] for im in gt["images"]], float).reshape(-1, 3, 3)
        t_cw = np.array([im["t_cw"] for im in gt["images"]], float).reshape(-1, 3)
    except (KeyError, TypeError, ValueError, json.JSONDecodeError) as exc:
        raise KitInputError(f"{p}: not a valid ground_truth.json ({exc})") from None
    return K, names, R_cw, t_cw


def epipolar_errors(K, R_cw_i, t_cw_i, R_cw_j, t_cw_j, x1, x2) -> np.ndarray:
    """Sampson distance (pixels) of correspondences to the epipolar geometry of the true cameras.

    Args:
        K: ``(3, 3)``. R_cw_i, t_cw_i, R_cw_j, t_cw_j: the two true poses. x1, x2: ``(N, 2)`` pixels.

    Returns:
        ``(N,)`` distances in pixels (small for true matches; outliers are usually far).
    """
    R = R_cw_j @ R_cw_i.T  # j from i
    t = t_cw_j - R @ t_cw_i
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    Ki = np.linalg.inv(K)
    F = Ki.T @ tx @ R @ Ki
    h1 = np.c_[x1, np.ones(len(x1))]
    h2 = np.c_[x2, np.ones(len(x2))]
    Fx1, Ftx2 = h1 @ F.T, h2 @ F
    num = np.sum(h2 * Fx1, axis=1)
    den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    return np.abs(num) / np.sqrt(den)

"""Hard synthetic SfM scenes with ground truth: what students' own photo sets look like.

:func:`course_lib.data.synthetic.make_scene` is a walk past a facade where every image sees most
points. Photos that students take themselves break an incremental mapper in other ways; each
generator here makes one of them, as a :class:`~course_lib.data.synthetic.SyntheticScene` (write
it as a P3 folder with :func:`~course_lib.data.synthetic.write_scene_p3`):

* :func:`grouped_ring_scene` -- a ring of views around a small object whose views fall into two
  groups with weak links between them (a few dozen shared points), the strongest *pair* in the
  small group: a mapper that starts from the strongest pair stalls at 3 images.
* :func:`texture_poor_ring_scene` -- a ring around a texture-poor object: few features per image,
  few matches per pair (below the usual 50-100 inliers an initial pair asks for).
* :func:`near_duplicate_scene` -- a walk past a facade where some views were taken twice from the
  same spot, turned a little (pure-rotation pairs: the most matches, and no baseline).

World frame as the rest of the kit (:mod:`course_lib.conventions`): the object stands on the
``x-z`` plane, ``-y`` is up (``look_at``'s default).

Introduced in ``notebooks/05_bundle_adjustment.ipynb`` (the several-models case).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from course_lib.conventions import project, world_to_camera
from course_lib.data.synthetic import WPI_LIKE_K, SyntheticScene, look_at, make_scene

__all__ = ["ring_cameras", "cylinder_points", "observe", "grouped_ring_scene", "texture_poor_ring_scene", "near_duplicate_scene"]


def ring_cameras(rng: np.random.Generator, n_cameras: int, radius: float = 4.0, height: float = -0.6,
                 jitter: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """``R_cw (M, 3, 3), t_cw (M, 3)`` of M cameras evenly on a ring around the origin, looking at it.

    Camera ``i`` stands at azimuth ``360 i / M`` degrees, ``radius`` from the y axis, at ``y =
    height`` (above the object's middle: y is down), with centre and aim jittered by ``jitter``.
    """
    R_all, t_all = [], []
    for a in np.radians(np.arange(n_cameras) * 360.0 / n_cameras):
        C = np.array([radius * np.cos(a), height, radius * np.sin(a)]) + rng.normal(0.0, jitter, 3)
        R, t = look_at(C, rng.normal(0.0, jitter, 3))
        R_all.append(R)
        t_all.append(t)
    return np.stack(R_all), np.stack(t_all)


def cylinder_points(rng: np.random.Generator, n: int, radius: float = 1.0, half_height: float = 1.0,
                    azimuth_deg: tuple[float, float] = (0.0, 360.0)) -> tuple[np.ndarray, np.ndarray]:
    """``X (n, 3)`` points on the side of a vertical cylinder about the y axis and their outward normals ``(n, 3)``.

    The points are spread over ``azimuth_deg`` (a range of the angle in the x-z plane, degrees).
    """
    a = np.radians(rng.uniform(*azimuth_deg, n))
    normal = np.stack([np.cos(a), np.zeros(n), np.sin(a)], axis=1)
    X = radius * normal + np.stack([np.zeros(n), rng.uniform(-half_height, half_height, n), np.zeros(n)], axis=1)
    return X, normal


def observe(rng: np.random.Generator, K, R_cw, t_cw, X, normal=None, noise_px: float = 0.5, dropout: float = 0.15,
            outlier_fraction: float = 0.0, image_size=(800, 600), min_facing: float = 0.3) -> SyntheticScene:
    """Project the points into every camera; a point is seen when in the image, in front and facing the camera.

    Args:
        rng: seeded ``numpy.random.Generator``.
        K: ``(3, 3)``. R_cw: ``(M, 3, 3)``. t_cw: ``(M, 3)``. X: ``(N, 3)``.
        normal: ``(N, 3)`` outward unit normals, or None (points seen from everywhere). A point is
            seen only where the cosine between its normal and the direction to the camera is at
            least ``min_facing``.
        noise_px: Gaussian pixel noise per coordinate. dropout: probability that a visible point is
            not detected. outlier_fraction: share of observations moved to a uniform random pixel.

    Returns:
        :class:`~course_lib.data.synthetic.SyntheticScene`.
    """
    K = np.asarray(K, float)
    W, H = image_size
    M, N = len(R_cw), len(X)
    uv_true = np.full((N, M, 2), np.nan)
    for i in range(M):
        x = project(K, R_cw[i], t_cw[i], X)
        ok = world_to_camera(R_cw[i], t_cw[i], X)[:, 2] > 0
        ok &= (x[:, 0] >= 0) & (x[:, 0] <= W - 1) & (x[:, 1] >= 0) & (x[:, 1] <= H - 1)
        if normal is not None:
            d = -R_cw[i].T @ t_cw[i] - X
            ok &= np.einsum("ij,ij->i", normal, d / np.linalg.norm(d, axis=1, keepdims=True)) >= min_facing
        ok &= rng.random(N) >= dropout
        uv_true[ok, i] = x[ok]
    uv = uv_true + rng.normal(0.0, noise_px, uv_true.shape)
    visible = np.isfinite(uv[..., 0])
    outlier = visible & (rng.random(visible.shape) < outlier_fraction)
    uv[outlier] = rng.uniform([0.0, 0.0], [W - 1.0, H - 1.0], size=(int(outlier.sum()), 2))
    return SyntheticScene(K, np.asarray(R_cw, float), np.asarray(t_cw, float), np.asarray(X, float), uv, uv_true, outlier,
                          (W, H), float(noise_px))


def grouped_ring_scene(rng: np.random.Generator, n_cameras: int = 16, small_group: tuple[int, ...] = (13, 14, 15),
                       weak_links: int = 40, n_points: int = 1200, n_dense: int = 400, noise_px: float = 0.5,
                       outlier_fraction: float = 0.1) -> SyntheticScene:
    """A ring of views around a small object whose views fall into two groups with weak links between them.

    ``n_points`` points cover the side of a cylinder (radius 1, height 2) and ``n_dense`` more
    (a richly textured patch) the part that faces the ``small_group`` cameras, so the pairs of the
    small group share the most points. A point seen by both groups keeps the observations of the
    group that sees it more often only, except ``weak_links`` of them (chosen at random): the
    only tracks that link the groups.

    Returns:
        :class:`~course_lib.data.synthetic.SyntheticScene` (``outlier`` marks random-pixel outliers).
    """
    R, t = ring_cameras(rng, n_cameras)
    az = 360.0 * np.asarray(small_group) / n_cameras
    X, nrm = cylinder_points(rng, n_points)
    Xd, nd = cylinder_points(rng, n_dense, azimuth_deg=(az.min() - 10.0, az.max() + 10.0))
    sc = observe(rng, WPI_LIKE_K, R, t, np.concatenate([X, Xd]), np.concatenate([nrm, nd]), noise_px=noise_px,
                 outlier_fraction=outlier_fraction)
    small = np.zeros(n_cameras, bool)
    small[list(small_group)] = True
    seen = sc.visible
    cross = np.flatnonzero(seen[:, small].any(axis=1) & seen[:, ~small].any(axis=1))
    links = rng.choice(cross, size=min(weak_links, len(cross)), replace=False)
    for j in np.setdiff1d(cross, links):
        n_small, n_big = seen[j, small].sum(), seen[j, ~small].sum()
        keep = small if n_small > n_big or (n_small == n_big and rng.random() < 0.5) else ~small
        sc.uv[j, ~keep] = sc.uv_true[j, ~keep] = np.nan
        sc.outlier[j, ~keep] = False
    return sc


def texture_poor_ring_scene(rng: np.random.Generator, n_cameras: int = 16, n_points: int = 480, dropout: float = 0.3,
                            noise_px: float = 0.7, outlier_fraction: float = 0.15) -> SyntheticScene:
    """A ring of views around a texture-poor object: a few dozen features per image, 20-50 matches per pair.

    ``n_points`` points on a cylinder (radius 1, height 2) with a high ``dropout`` (weak corners
    are found in some views only), more noise and more outliers than a textured scene.
    """
    R, t = ring_cameras(rng, n_cameras)
    X, nrm = cylinder_points(rng, n_points)
    return observe(rng, WPI_LIKE_K, R, t, X, nrm, noise_px=noise_px, dropout=dropout, outlier_fraction=outlier_fraction)


def near_duplicate_scene(rng: np.random.Generator, n_cameras: int = 6, twins: tuple[int, ...] = (1, 3, 4),
                         turn_deg: float = 3.0, n_points: int = 400, noise_px: float = 0.5,
                         outlier_fraction: float = 0.1) -> SyntheticScene:
    """A walk past a facade (:func:`~course_lib.data.synthetic.make_scene`) where some views were taken twice.

    Each camera in ``twins`` gets a twin at the same centre, turned by ``turn_deg`` about the
    vertical: the pair shares nearly every feature (the most matches of the scene) and has no
    baseline (a pure rotation, nothing to triangulate). The twins are appended after the
    ``n_cameras`` cameras.
    """
    base = make_scene(rng, n_cameras=n_cameras, n_points=n_points, outlier_fraction=0.0)
    R, t = list(base.R_cw), list(base.t_cw)
    for i in twins:
        R2 = Rotation.from_euler("y", turn_deg, degrees=True).as_matrix() @ base.R_cw[i]
        R.append(R2)
        t.append(-R2 @ (-base.R_cw[i].T @ base.t_cw[i]))
    return observe(rng, base.K, np.stack(R), np.stack(t), base.X, None, noise_px=noise_px, dropout=0.15,
                   outlier_fraction=outlier_fraction)

"""Synthetic SfM scenes with known ground truth: the one scene fixture behind every SfM test.

A :class:`SyntheticScene` holds cameras (``R_cw, t_cw``), 3-D points and their projections with
known pixel noise and known outliers, so every step of the pipeline can be checked against the
truth: F and E against the ones built from the true poses, triangulated points against ``X``,
PnP against ``R_cw[i], t_cw[i]``, and bundle adjustment against the injected noise.

The embedded *rendered* scene (real images, SIFT matches) is made by :mod:`course_lib.data.building`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from course_lib.conventions import camera_center, project, world_to_camera
from course_lib.data.p3 import read_p3, write_p3

__all__ = ["SyntheticScene", "make_scene", "look_at", "write_scene_p3", "WPI_LIKE_K", "OUTLIER_KINDS"]

#: How :func:`make_scene` corrupts an outlier observation: ``"random"`` puts it at a uniform random
#: pixel; ``"swap"`` puts it exactly on the observation of *another* point in the same image (a
#: real feature matched to the wrong point, as repetitive facades produce). Written to a P3
#: folder, a swapped observation joins two tracks through that image (features are identified by
#: equal pixels), which is what makes it hard.
OUTLIER_KINDS = ("random", "swap")

#: Intrinsics like the WPI Unity Hall camera (800x600 after resizing), in pixels.
WPI_LIKE_K = np.array([[531.12, 0.0, 407.19], [0.0, 531.54, 313.31], [0.0, 0.0, 1.0]])


def look_at(C: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, -1.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """The ``(R_cw, t_cw)`` of a camera at ``C`` looking at ``target``.

    Args:
        C: ``(3,)`` camera centre in the world.
        target: ``(3,)`` point the optical axis (camera +z) passes through.
        up: ``(3,)`` world direction that should appear *up* in the image (camera -y).

    Returns:
        ``R_cw (3, 3)``, ``t_cw (3,)`` in the kit's convention (x_cam = R_cw X + t_cw).
    """
    C = np.asarray(C, float)
    z = np.asarray(target, float) - C
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up, float), z)  # camera x = right = (down) x (forward)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R_cw = np.stack([x, y, z])  # rows are the camera axes in world coordinates
    return R_cw, -R_cw @ C


@dataclass
class SyntheticScene:
    """Cameras, points and observations with ground truth.

    Attributes:
        K: ``(3, 3)`` intrinsics shared by all cameras.
        R_cw: ``(M, 3, 3)`` true rotations (camera from world).
        t_cw: ``(M, 3)`` true translations.
        X: ``(N, 3)`` true 3-D points.
        uv: ``(N, M, 2)`` observed pixels (noise and outliers included), NaN where not seen.
        uv_true: ``(N, M, 2)`` noiseless projections, NaN where not seen.
        outlier: ``(N, M)`` True where the observation was replaced by a wrong pixel (a random one
            or another point's observation, see ``outlier_kind``).
        image_size: ``(W, H)`` in pixels.
        noise_px: standard deviation of the Gaussian pixel noise per coordinate.
    """

    K: np.ndarray
    R_cw: np.ndarray
    t_cw: np.ndarray
    X: np.ndarray
    uv: np.ndarray
    uv_true: np.ndarray
    outlier: np.ndarray
    image_size: tuple[int, int]
    noise_px: float

    @property
    def n_cameras(self) -> int:
        return self.R_cw.shape[0]

    @property
    def visible(self) -> np.ndarray:
        """``(N, M)`` bool visibility matrix (point j seen in image i)."""
        return ~np.isnan(self.uv[..., 0])

    @property
    def centers(self) -> np.ndarray:
        """``(M, 3)`` true camera centres."""
        return np.stack([camera_center(R, t) for R, t in zip(self.R_cw, self.t_cw)])

    @property
    def scene_size(self) -> float:
        """The diameter of the point cloud's bounding box (the scale used for relative errors)."""
        return float(np.linalg.norm(self.X.max(0) - self.X.min(0)))

    def pair(self, i: int, j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Correspondences between images ``i`` and ``j``.

        Returns:
            ``x1 (K, 2)``, ``x2 (K, 2)`` observed pixels, ``inlier (K,)`` bool (neither
            observation is an outlier) and ``point_ids (K,)`` indices into ``X``.
        """
        both = self.visible[:, i] & self.visible[:, j]
        ids = np.flatnonzero(both)
        inlier = ~(self.outlier[ids, i] | self.outlier[ids, j])
        return self.uv[ids, i], self.uv[ids, j], inlier, ids


def make_scene(
    rng: np.random.Generator,
    n_cameras: int = 5,
    n_points: int = 400,
    noise_px: float = 0.5,
    outlier_fraction: float = 0.1,
    K: np.ndarray | None = None,
    image_size: tuple[int, int] = (800, 600),
    dropout: float = 0.15,
    outlier_kind: str = "random",
) -> SyntheticScene:
    """A small facade-like scene seen by cameras on an arc, with noise and outliers.

    The points fill a shallow box (8 x 5 x 3 world units) centred 10 units in front of the middle
    camera; cameras stand on an arc of about 30 degrees, all looking at the box centre, like a
    student walking past a building.

    Args:
        rng: seeded ``numpy.random.Generator``.
        n_cameras: M, at least 2.
        n_points: N.
        noise_px: Gaussian noise (pixels, per coordinate) added to every observation.
        outlier_fraction: fraction of observations replaced by wrong pixels.
        outlier_kind: ``"random"`` (uniform random pixels) or ``"swap"`` (the observation of
            another point in the same image, a correct observation of that point; see
            :data:`OUTLIER_KINDS`).
        K: ``(3, 3)`` intrinsics; default :data:`WPI_LIKE_K`.
        image_size: ``(W, H)``.
        dropout: probability that a visible point is nevertheless not observed in an image
            (so tracks have different lengths, as with real matching).

    Returns:
        A :class:`SyntheticScene`.
    """
    if n_cameras < 2:
        raise ValueError(f"n_cameras={n_cameras}: a scene needs at least 2 cameras")
    if outlier_kind not in OUTLIER_KINDS:
        raise ValueError(f"outlier_kind={outlier_kind!r}: expected one of {OUTLIER_KINDS}")
    K = WPI_LIKE_K.copy() if K is None else np.asarray(K, float)
    W, H = image_size
    target = np.array([0.0, 0.0, 10.0])
    X = target + rng.uniform([-4.0, -2.5, -1.5], [4.0, 2.5, 1.5], size=(n_points, 3))
    angles = np.radians(np.linspace(-15.0, 15.0, n_cameras)) + rng.normal(0.0, np.radians(1.0), n_cameras)
    R_all, t_all = [], []
    for a in angles:
        C = target + 10.0 * np.array([np.sin(a), 0.0, -np.cos(a)]) + rng.normal(0.0, 0.2, 3)
        look = target + rng.normal(0.0, 0.3, 3)
        R, t = look_at(C, look)
        R_all.append(R)
        t_all.append(t)
    R_cw, t_cw = np.stack(R_all), np.stack(t_all)

    uv_true = np.full((n_points, n_cameras, 2), np.nan)
    for i in range(n_cameras):
        depth = world_to_camera(R_cw[i], t_cw[i], X)[:, 2]
        x = project(K, R_cw[i], t_cw[i], X)
        ok = (depth > 0) & (x[:, 0] >= 0) & (x[:, 0] <= W - 1) & (x[:, 1] >= 0) & (x[:, 1] <= H - 1)
        ok &= rng.random(n_points) >= dropout
        uv_true[ok, i] = x[ok]
    uv = uv_true + rng.normal(0.0, noise_px, uv_true.shape)
    visible = ~np.isnan(uv[..., 0])
    outlier = visible & (rng.random(visible.shape) < outlier_fraction)
    if outlier_kind == "random":
        n_out = int(outlier.sum())
        uv[outlier] = rng.uniform([0.0, 0.0], [W - 1.0, H - 1.0], size=(n_out, 2))
    else:
        for i in range(n_cameras):
            bad = np.flatnonzero(outlier[:, i])
            donors = np.flatnonzero(visible[:, i] & ~outlier[:, i])
            if len(bad) == 0 or len(donors) == 0:
                continue
            # each wrong observation takes the (noisy) pixel of a different point's correct one
            pick = rng.choice(donors, size=len(bad), replace=len(bad) > len(donors))
            uv[bad, i] = uv[pick, i]
    return SyntheticScene(K, R_cw, t_cw, X, uv, uv_true, outlier, (W, H), float(noise_px))


def write_scene_p3(scene: SyntheticScene, folder):
    """Write a scene's observations as a P3 folder (no images) and read it back.

    Only points seen in two or more images are written (a P3 file holds matches). The scene's
    arrays are *not* changed; the P3 reader joins tracks by equal pixels, so with
    ``outlier_kind="swap"`` the tracks read back are chains of several points, as real matching
    files with repeated structures give.

    Args:
        scene: a :class:`SyntheticScene`.
        folder: output folder (created).

    Returns:
        ``(P3Data, keep)``: the data read back with :func:`course_lib.data.p3.read_p3` and ``keep
        (N,)`` bool, the points that were written.
    """
    keep = scene.visible.sum(axis=1) >= 2
    M = scene.n_cameras
    rgb = np.full((int(keep.sum()), 3), 128, np.uint8)
    write_p3(folder, [f"{i + 1}.png" for i in range(M)], scene.K, scene.uv[keep], rgb)
    return read_p3(folder, require_images=False), keep

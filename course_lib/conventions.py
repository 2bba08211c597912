"""The ONE place that states the kit's conventions: axes, pose direction, shapes, units.

Every other module follows this page; if you change a convention, change it here and nowhere else.

Camera axes (OpenCV and COLMAP)
    x points right, y points down, z points forward (out of the lens, into the scene).

Pixels
    A pixel coordinate is ``(u, v)``: ``u`` is the column (grows to the right), ``v`` is the row
    (grows downwards), the origin is the top-left corner of the image, the unit is the pixel.
    The centre of the top-left pixel is ``(0, 0)`` (OpenCV's convention); with that, an image of
    width W spans u in [-0.5, W - 0.5].

Intrinsics
    ``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` in pixels; the kit never uses skew (s = 0).

Poses are named by their direction
    ``R_cw, t_cw`` map a world point to the camera ("camera from world")::

        x_cam = R_cw @ X + t_cw

    The camera centre in the world is ``C = -R_cw.T @ t_cw`` and the projection matrix is
    ``P = K [R_cw | t_cw]``. A bare ``pose`` never appears in the kit. NeRF code may hold a local
    ``c2w`` (camera-to-world 3x4 or 4x4, *OpenCV axes*); the Blender/OpenGL convention
    (x right, y up, z backwards) is converted in exactly one loader, ``course_lib.data.blender``.

Shapes
    Points are rows: ``X`` has shape ``(N, 3)``, image points ``x1, x2`` have shape ``(N, 2)``;
    translations and centres have shape ``(3,)``; rotations ``(3, 3)`` with det = +1.
    Homogeneous points are rows too: ``(N, 3)`` for the image, ``(N, 4)`` for the world.

Observations
    What each image sees of each point is a ``(T, M, 2)`` array of pixels, ``uv[j, i]`` = point
    ``j`` in image ``i``, NaN where unseen; as a list (the terms of the bundle-adjustment sum) it is
    ``point_idx, camera_idx, uv_obs`` of the seen entries, point by point (:func:`observed_entries`).

Images
    Index ``i`` in code is 0-based. The P3 matching files number images from 1; the loader
    converts and keeps the file names in ``image_names``. Images are ``(H, W, 3)`` uint8 RGB
    (OpenCV's BGR is converted at the loader), NeRF images ``(H, W, 3)`` float in [0, 1].

Units
    World units are whatever the data defines (the embedded scene uses metres); reprojection
    errors are in pixels; angles in the public API are in radians unless a name ends in ``_deg``.

Randomness
    Every stochastic function takes an ``rng`` (``numpy.random.Generator`` or
    ``torch.Generator``); notebooks and tests seed once.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "to_homogeneous",
    "from_homogeneous",
    "skew",
    "fix_sign",
    "camera_center",
    "translation_from_center",
    "projection_matrix",
    "world_to_camera",
    "project",
    "invert_pose",
    "compose_poses",
    "rotation_angle_deg",
    "nearest_rotation",
    "observed_entries",
]


def to_homogeneous(x: np.ndarray) -> np.ndarray:
    """Append a column of ones.

    Args:
        x: ``(N, d)`` points.

    Returns:
        ``(N, d + 1)`` homogeneous points.
    """
    x = np.asarray(x, dtype=float)
    return np.concatenate([x, np.ones((*x.shape[:-1], 1))], axis=-1)


def from_homogeneous(xh: np.ndarray) -> np.ndarray:
    """Divide by the last coordinate and drop it.

    Args:
        xh: ``(N, d + 1)`` homogeneous points.

    Returns:
        ``(N, d)`` Euclidean points (inf/nan where the last coordinate is 0).
    """
    xh = np.asarray(xh, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return xh[..., :-1] / xh[..., -1:]


def skew(v: np.ndarray) -> np.ndarray:
    """The cross-product matrix ``[v]_x`` with ``skew(a) @ b == np.cross(a, b)``.

    Args:
        v: ``(3,)`` vector.

    Returns:
        ``(3, 3)`` skew-symmetric matrix.
    """
    x, y, z = np.asarray(v, dtype=float).reshape(3)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def fix_sign(a: np.ndarray) -> np.ndarray:
    """``a`` times the sign of its largest-magnitude entry: the kit's choice for what is defined up to sign.

    A fundamental matrix, a null vector or an SVD's singular vector comes out with either sign,
    and LAPACK's choice differs between CPUs; this fixes it (the entry of largest magnitude positive).

    Args:
        a: array of any shape, not all zero.

    Returns:
        array of the same shape.
    """
    a = np.asarray(a)
    return a * np.sign(a.flat[np.abs(a).argmax()])


def camera_center(R_cw: np.ndarray, t_cw: np.ndarray) -> np.ndarray:
    """Camera centre in world coordinates, ``C = -R_cw.T @ t_cw``; returns shape ``(3,)``."""
    return -np.asarray(R_cw, float).T @ np.asarray(t_cw, float).reshape(3)


def translation_from_center(R_cw: np.ndarray, C: np.ndarray) -> np.ndarray:
    """``t_cw = -R_cw @ C``, the inverse of :func:`camera_center`; returns shape ``(3,)``."""
    return -np.asarray(R_cw, float) @ np.asarray(C, float).reshape(3)


def projection_matrix(K: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray) -> np.ndarray:
    """``P = K [R_cw | t_cw]``, shape ``(3, 4)``."""
    return np.asarray(K, float) @ np.hstack([np.asarray(R_cw, float), np.asarray(t_cw, float).reshape(3, 1)])


def world_to_camera(R_cw: np.ndarray, t_cw: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Camera coordinates of world points, ``x_cam = R_cw X + t_cw`` row-wise.

    Args:
        R_cw: ``(3, 3)``. t_cw: ``(3,)``. X: ``(N, 3)`` world points.

    Returns:
        ``(N, 3)`` points in the camera frame (z > 0 is in front of the camera).
    """
    return np.asarray(X, float) @ np.asarray(R_cw, float).T + np.asarray(t_cw, float).reshape(1, 3)


def project(K: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Pinhole projection of world points to pixels.

    Args:
        K: ``(3, 3)`` intrinsics. R_cw: ``(3, 3)``. t_cw: ``(3,)``. X: ``(N, 3)``.

    Returns:
        ``(N, 2)`` pixel coordinates ``(u, v)``.
    """
    Xc = world_to_camera(R_cw, t_cw, X)
    return from_homogeneous(Xc @ np.asarray(K, float).T)


def invert_pose(R_ab: np.ndarray, t_ab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Invert a rigid transform: from ``(R_ab, t_ab)`` (a from b) return ``(R_ba, t_ba)``."""
    R_ab = np.asarray(R_ab, float)
    return R_ab.T, -R_ab.T @ np.asarray(t_ab, float).reshape(3)


def compose_poses(R_ab, t_ab, R_bc, t_bc) -> tuple[np.ndarray, np.ndarray]:
    """Chain rigid transforms: (a from b) after (b from c) gives (a from c)."""
    R_ab = np.asarray(R_ab, float)
    return R_ab @ np.asarray(R_bc, float), R_ab @ np.asarray(t_bc, float).reshape(3) + np.asarray(t_ab, float).reshape(3)


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """The angle in degrees of the rotation that takes ``R_b`` to ``R_a`` (geodesic distance).

    ``atan2(sin, cos)`` of the relative rotation ``R = R_a R_bᵀ`` (sin from its skew part, cos from its
    trace): exact for small angles too, where ``arccos`` of the trace turns float32 rounding (1e-7)
    into 0.03°.
    """
    R = np.asarray(R_a, float) @ np.asarray(R_b, float).T
    s = 0.5 * np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arctan2(s, c)))


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation closest to the ``(3, 3)`` matrix ``M`` in the Frobenius norm (by SVD, det = +1).

    Applied to a (weighted) sum of rotations it gives their chordal mean.
    """
    U, _, Vt = np.linalg.svd(np.asarray(M, float))
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def observed_entries(uv: np.ndarray, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The observation layout: the seen entries of ``uv (T, M, 2)``, point by point (row-major over ``(T, M)``).

    Args:
        uv: ``(T, M, 2)`` pixels of point ``j`` in image ``i`` at ``[j, i]``, NaN where not seen.
        mask: optional ``(T, M)`` bool; only entries that are seen *and* True here are listed.

    Returns:
        ``point_idx (K,)`` int64, ``camera_idx (K,)`` int64, ``uv_obs (K, 2)``: one row per observation.

    Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
    """
    uv = np.asarray(uv, float)
    seen = np.isfinite(uv).all(axis=2)
    if mask is not None:
        seen &= mask
    j, i = np.nonzero(seen)
    return j.astype(np.int64), i.astype(np.int64), uv[j, i]

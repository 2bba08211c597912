"""Compare a reconstruction with the ground truth, modulo the real ambiguity (a similarity).

A reconstruction from images alone is defined only up to a similarity transform (rotation,
translation and scale of the whole world), so poses and points are compared after aligning the
estimated camera centres (or points) to the true ones with Umeyama's method.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from course_lib.conventions import camera_center, rotation_angle_deg

__all__ = ["align_similarity", "PoseErrors", "pose_errors"]


def align_similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity with ``dst ≈ s * R @ src + t`` (Umeyama 1991).

    Args:
        src: ``(N, 3)`` points, N >= 3 and not collinear.
        dst: ``(N, 3)`` corresponding points.

    Returns:
        ``s`` (float), ``R (3, 3)`` with det = +1, ``t (3,)``.
    """
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    var_s = (a**2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var_s)
    return s, R, mu_d - s * R @ mu_s


@dataclass
class PoseErrors:
    """Per-camera errors after alignment: rotation (degrees) and centre distance (world units of the truth)."""

    rotation_deg: np.ndarray
    center: np.ndarray
    scale: float


def pose_errors(R_est, t_est, R_true, t_true) -> PoseErrors:
    """Rotation and centre errors of estimated cameras after a similarity alignment of the centres.

    Args:
        R_est, R_true: ``(M, 3, 3)`` rotations (camera from world), M >= 3.
        t_est, t_true: ``(M, 3)`` translations.

    Returns:
        :class:`PoseErrors` with arrays of shape ``(M,)``.
    """
    C_est = np.stack([camera_center(R, t) for R, t in zip(R_est, t_est)])
    C_true = np.stack([camera_center(R, t) for R, t in zip(R_true, t_true)])
    s, R_a, t_a = align_similarity(C_est, C_true)
    C_aligned = s * C_est @ R_a.T + t_a
    # A world rotated by R_a: R_cw' = R_cw @ R_a.T
    rot = np.array([rotation_angle_deg(Re @ R_a.T, Rt) for Re, Rt in zip(R_est, R_true)])
    return PoseErrors(rot, np.linalg.norm(C_aligned - C_true, axis=1), s)

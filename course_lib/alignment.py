"""Compare a reconstruction with the ground truth, modulo the real ambiguity (a similarity).

A reconstruction from images alone is defined only up to a similarity transform (rotation,
translation and scale of the whole world), so poses and points are compared after aligning the
estimated camera centres (or points) to the true ones with Umeyama's method.

Cameras are aligned on their rotations *and* centres (:func:`align_cameras`): the rotation of
the world from the camera rotations (well defined for any two or more cameras), then scale and
translation from the centres. A similarity fitted to the centres alone is ill-conditioned when the
cameras stand nearly on a line (a walk past a building): any roll about that line fits them
equally well, and the rotation errors it reports are the alignment's, not the reconstruction's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from course_lib.conventions import camera_center, nearest_rotation, rotation_angle_deg

__all__ = ["align_similarity", "align_cameras", "PoseErrors", "pose_errors"]


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


def align_cameras(R_est, t_est, R_true, t_true) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity ``(s, R, t)`` that maps the estimated world onto the true one, from rotations and centres.

    ``R`` is the rotation closest to all ``R_trueᵢᵀ R_estᵢ`` (a chordal mean, by SVD: the world
    rotation that best explains every camera's orientation); given ``R``, ``s`` and ``t`` are the
    least-squares fit of the centres, ``C_true ≈ s R C_est + t``.

    Args:
        R_est, R_true: ``(M, 3, 3)`` rotations (camera from world), M >= 2.
        t_est, t_true: ``(M, 3)`` translations.

    Returns:
        ``s`` (float), ``R (3, 3)``, ``t (3,)``; a camera maps as ``R_cw' = R_cw Rᵀ``, ``C' = s R C + t``.
    """
    R_est, R_true = np.asarray(R_est, float), np.asarray(R_true, float)
    C_est = np.stack([camera_center(R, t) for R, t in zip(R_est, t_est)])
    C_true = np.stack([camera_center(R, t) for R, t in zip(R_true, t_true)])
    # R_cw,true ≈ R_cw,est Rᵀ  <=>  R ≈ R_trueᵀ R_est: project their mean onto SO(3)
    R = nearest_rotation(np.einsum("mji,mjk->ik", R_true, R_est))
    a = (C_est - C_est.mean(0)) @ R.T
    b = C_true - C_true.mean(0)
    s = float((a * b).sum() / max((a**2).sum(), 1e-300))
    return s, R, C_true.mean(0) - s * R @ C_est.mean(0)


@dataclass
class PoseErrors:
    """Per-camera errors after alignment: rotation (degrees) and centre distance (world units of the truth)."""

    rotation_deg: np.ndarray
    center: np.ndarray
    scale: float


def pose_errors(R_est, t_est, R_true, t_true) -> PoseErrors:
    """Rotation and centre errors of estimated cameras after a similarity alignment (:func:`align_cameras`).

    Args:
        R_est, R_true: ``(M, 3, 3)`` rotations (camera from world), M >= 2.
        t_est, t_true: ``(M, 3)`` translations.

    Returns:
        :class:`PoseErrors` with arrays of shape ``(M,)``.
    """
    C_est = np.stack([camera_center(R, t) for R, t in zip(R_est, t_est)])
    C_true = np.stack([camera_center(R, t) for R, t in zip(R_true, t_true)])
    s, R_a, t_a = align_cameras(R_est, t_est, R_true, t_true)
    C_aligned = s * C_est @ R_a.T + t_a
    # A world rotated by R_a: R_cw' = R_cw @ R_a.T
    rot = np.array([rotation_angle_deg(Re @ R_a.T, Rt) for Re, Rt in zip(R_est, R_true)])
    return PoseErrors(rot, np.linalg.norm(C_aligned - C_true, axis=1), s)

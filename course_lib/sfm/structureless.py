"""Registering an image from its matches with registered images alone, when it sees too few points.

An image whose overlap with the model lies in features that only one registered image shares with
it (a ring of photos where each view overlaps its neighbours but hardly the views two steps away)
has two-view tracks with the model and no triangulated point: PnP has nothing to work with. COLMAP
(``IncrementalMapper``'s structure-less fallback, since 3.12) registers such an image from its
2D-2D correspondences with the registered images instead; this module does the same in two steps:

1. :func:`pose_from_partners`: the five-point relative pose of the image against each registered
   partner gives its rotation (``R_i = R_ki R_k``) and the direction of its centre from the
   partner's (``C_i = C_k + s_k d_k``, ``s_k > 0``). The rotations must agree (look-alike
   texture gives poses tens of degrees apart); the centre is where the rays from two or more
   partners, seen from different places, meet (least squares): the partners' known poses fix the
   scale.
2. :func:`refine_on_partners`: rotation and centre refined by least squares on the Sampson
   distances of the matches with every partner (the epipolar geometry the poses imply).

Introduced in ``notebooks/05_bundle_adjustment.ipynb`` (the mapper's stages).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from course_lib.conventions import camera_center, nearest_rotation, rotation_angle_deg
from course_lib.sfm.initial_pair import fundamental_from_pose, sampson_pixels

__all__ = ["pose_from_partners", "refine_on_partners", "pair_sampson"]


def pose_from_partners(R_k: np.ndarray, t_k: np.ndarray, R_ki: np.ndarray, t_ki: np.ndarray, weights: np.ndarray,
                       max_rotation_deg: float = 3.0, min_ray_angle_deg: float = 2.0):
    """The pose of a new image from its relative poses to registered partners, or ``(None, why)``.

    Args:
        R_k, t_k: ``(P, 3, 3)``, ``(P, 3)`` the partners' poses (camera from world).
        R_ki, t_ki: ``(P, 3, 3)``, ``(P, 3)`` the new image's pose relative to each partner
            (``x_i ~ R_ki X_k + s t_ki`` for a point ``X_k`` in partner ``k``'s camera frame; ``|t_ki| = 1``).
        weights: ``(P,)`` how much to trust each partner (its pose inliers).
        max_rotation_deg: partners whose rotation for the image differs more than this from the
            most trusted partner's are left out.
        min_ray_angle_deg: the rays of the centre must span at least this angle (else the scale is unknown).

    Returns:
        ``((R_cw (3, 3), t_cw (3,), used (P,) bool), None)`` or ``(None, why)``.
    """
    P = len(R_k)
    R_i = np.einsum("pij,pjk->pik", R_ki, R_k)
    best = int(np.argmax(weights))
    used = np.array([rotation_angle_deg(R_i[p], R_i[best]) <= max_rotation_deg for p in range(P)])
    if used.sum() < 2:
        return None, f"{P} registered partner(s), {int(used.sum())} with a rotation that agrees: two are needed to fix the scale"
    R = nearest_rotation(np.einsum("p,pij->ij", weights[used], R_i[used]))  # the agreeing rotations' weighted chordal mean
    C_k = np.stack([camera_center(R_k[p], t_k[p]) for p in range(P)])
    d = -np.einsum("ji,pj->pi", R, t_ki)  # C_i - C_k along d_k = -R_i^T t_ki
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    cosines = np.clip(d[used] @ d[used].T, -1.0, 1.0)
    if np.degrees(np.arccos(cosines.min())) < min_ray_angle_deg:
        return None, "the partners see the image from one direction only: the scale is unknown"
    # least-squares meeting point of the rays C_k + s d_k: sum_k (I - d_k d_k^T)(C - C_k) = 0
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for p in np.flatnonzero(used):
        Q = weights[p] * (np.eye(3) - np.outer(d[p], d[p]))
        A += Q
        b += Q @ C_k[p]
    C = np.linalg.solve(A, b)
    s = np.einsum("pi,pi->p", C - C_k, d)
    used &= s > 0
    if used.sum() < 2:
        return None, "the rays from the partners meet behind them"
    return (R, -R @ C, used), None


def pair_sampson(K: np.ndarray, R_k, t_k, R_i, t_i, x_k: np.ndarray, x_i: np.ndarray) -> np.ndarray:
    """``(N,)`` Sampson distances (pixels) of matches ``x_k``-``x_i`` to the epipolar geometry of two posed cameras.

    The relative pose of camera ``i`` to camera ``k`` gives ``F``
    (:func:`course_lib.sfm.initial_pair.fundamental_from_pose`); the distances are notebook 01's
    (:func:`course_lib.sfm.initial_pair.sampson_pixels`).
    """
    R = R_i @ R_k.T
    return sampson_pixels(fundamental_from_pose(K, R, t_i - R @ t_k), x_k, x_i)


def refine_on_partners(K: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray, partners: list, f_scale: float = 1.0):
    """Rotation and centre of a new image refined on its matches with posed partners.

    Args:
        K: ``(3, 3)``. R_cw, t_cw: the start pose.
        partners: ``[(R_k, t_k, x_k (N, 2), x_i (N, 2)), ...]`` each partner's pose and the matches.
        f_scale: the Huber loss's scale (pixels).

    Returns:
        ``(R_cw, t_cw)`` refined.
    """
    def residuals(p):
        R = Rotation.from_rotvec(p[:3]).as_matrix()
        t = -R @ p[3:]
        return np.concatenate([pair_sampson(K, R_k, t_k, R, t, x_k, x_i) for R_k, t_k, x_k, x_i in partners])

    p0 = np.concatenate([Rotation.from_matrix(R_cw).as_rotvec(), camera_center(R_cw, t_cw)])
    res = least_squares(residuals, p0, loss="huber", f_scale=f_scale, max_nfev=50)
    R = Rotation.from_rotvec(res.x[:3]).as_matrix()
    return R, -R @ res.x[3:]

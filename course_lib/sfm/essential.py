"""The essential matrix and the four relative poses it allows.

With calibrated cameras (intrinsics ``K``), the fundamental matrix becomes the essential matrix

    E = Kᵀ F K,

which relates *normalized* image coordinates ``y = K⁻¹ x``: ``y2ᵀ E y1 = 0``. For camera 1 at the
origin (``R = I, t = 0``) and camera 2 at ``x_cam2 = R X + t``, ``E = [t]ₓ R``: a rank-2 matrix
whose two non-zero singular values are equal. The scale of ``t`` cannot be recovered from images
alone, so ``E`` is normalized to singular values ``(1, 1, 0)`` and the camera centre of
camera 2 to unit length.

Decomposing ``E = U diag(1, 1, 0) Vᵀ`` gives two rotations ``U W Vᵀ`` and ``U Wᵀ Vᵀ`` (with
``W`` the 90° rotation about z) and two signs of the translation ``t = ±U[:, 2]``: four
candidates, of which only one puts the scene in front of both cameras (chosen in
``course_lib.sfm.triangulation.choose_pose``).

Pose convention (:mod:`course_lib.conventions`): ``R`` is ``R_cw`` of camera 2, ``C`` its centre,
``t_cw = -R @ C``; camera 1 is at ``R = I, C = 0``.

Introduced in notebooks/02_essential_matrix_and_pose.ipynb.
"""

from __future__ import annotations

import numpy as np

from course_lib import validate
from course_lib.conventions import fix_sign

__all__ = ["essential_from_fundamental", "pose_candidates", "W"]

#: The 90° rotation about the z axis used to factor E (Hartley & Zisserman, result 9.19).
W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def _check_3x3(M, name: str, what: str) -> np.ndarray:
    return validate.matrix3x3(M, name, what)


def essential_from_fundamental(F: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The essential matrix ``E = Kᵀ F K``, corrected to singular values ``(1, 1, 0)``.

    Both images are taken with the same camera ``K``. A fundamental matrix estimated from noisy
    points gives a ``Kᵀ F K`` whose two largest singular values differ; the closest essential
    matrix (in Frobenius norm, up to scale) is ``U diag(1, 1, 0) Vᵀ`` from its SVD.

    Args:
        F: ``(3, 3)`` fundamental matrix with ``x2hᵀ F x1h = 0`` (pixels, any scale).
        K: ``(3, 3)`` intrinsics shared by both images.

    Returns:
        E: ``(3, 3)`` essential matrix with singular values ``(1, 1, 0)`` and
        ``y2ᵀ E y1 ≈ 0`` for normalized coordinates ``y = K⁻¹ xh``.

    Raises:
        KitInputError: bad shapes, NaN/inf, an all-zero F, or a singular K.

    Introduced in notebooks/02_essential_matrix_and_pose.ipynb.
    """
    F = _check_3x3(F, "F", "fundamental matrix")
    K = validate.intrinsics(K)
    E = K.T @ F @ K
    U, _, Vt = np.linalg.svd(E)
    return U @ np.diag([1.0, 1.0, 0.0]) @ Vt


def pose_candidates(E: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The four relative poses ``(R, C)`` of camera 2 allowed by an essential matrix.

    With ``E = U diag(1, 1, 0) Vᵀ`` (any ``E ≠ 0`` is first projected to that form):

    * ``R ∈ {U W Vᵀ, U Wᵀ Vᵀ}`` and ``t = ±U[:, 2]`` (so that ``E ∝ [t]ₓ R``);
    * the centre ``C = -Rᵀ t`` (the right null vector of E, ``E C = 0``), of unit length;
    * if ``det R = -1`` (the SVD gave ``det U det V = -1``), ``R`` and ``C`` both change sign.

    Candidate order: ``k = 0: (U W Vᵀ, +)``, ``1: (U W Vᵀ, -)``, ``2: (U Wᵀ Vᵀ, +)``,
    ``3: (U Wᵀ Vᵀ, -)``, for the SVD's choice of signs; so that every machine gives the same order
    (:func:`_canonical_order`), the reference takes the signs for which the first rotation is the one
    closer to the identity and the ``+`` centre has its largest-magnitude entry positive.

    Args:
        E: ``(3, 3)`` essential matrix (``y2ᵀ E y1 = 0``), any scale.

    Returns:
        R: ``(4, 3, 3)`` rotations ``R_cw`` of camera 2 (det = +1), camera 1 at ``R = I``.
        C: ``(4, 3)`` unit-length centres of camera 2 in camera 1's frame; ``t_cw = -R[k] @ C[k]``.

    Raises:
        KitInputError: bad shape, NaN/inf, or an all-zero E.

    Introduced in notebooks/02_essential_matrix_and_pose.ipynb.
    """
    E = _check_3x3(E, "E", "essential matrix")
    U, _, Vt = np.linalg.svd(E)
    u3 = U[:, 2]
    Rs, Cs = [], []
    for R0 in (U @ W @ Vt, U @ W.T @ Vt):
        for t in (u3, -u3):
            R, C = R0, -R0.T @ t
            if np.linalg.det(R) < 0:
                R, C = -R, -C
            Rs.append(R)
            Cs.append(C / np.linalg.norm(C))
    return _canonical_order(np.stack(Rs), np.stack(Cs))


def _canonical_order(R: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The documented order with the SVD's choices fixed: the same candidates on every machine.

    Which rotation is ``U W Vᵀ`` and which ``C`` is ``+`` depends on the signs of the singular
    vectors, which LAPACK picks differently on different CPUs. Keeping the documented structure
    (the two centres of one rotation side by side, ``+`` before ``-``), the rotation closer to the
    identity (larger trace) comes first and the ``+`` centre has its largest-magnitude entry positive.
    """
    pairs = [0, 2] if np.trace(R[0]) >= np.trace(R[2]) else [2, 0]
    c = fix_sign(C[0])
    order = [k + (0 if C[k] @ c > 0 else 1) for k in pairs]
    order = [i for k in order for i in (k, k ^ 1)]
    return R[order], C[order]

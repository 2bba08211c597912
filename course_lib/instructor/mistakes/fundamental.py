"""Classic mistakes of notebook 01 (the fundamental matrix), evaluated on a case (instructor side only).

Each function returns ``{key: result}``: what the mistake named by ``key`` gives on the case; the
check module (:mod:`course_lib.checks.fundamental`) maps the keys to its sentences. Built with the
reference library (:mod:`course_lib.sfm.fundamental`) at fixture time, never shipped.
"""

from __future__ import annotations

import numpy as np

from course_lib.conventions import fix_sign, to_homogeneous
from course_lib.sfm import fundamental as ref

__all__ = ["eight_point_variants", "sampson_variants"]


def _solve(a: np.ndarray, b: np.ndarray, rank2: bool = True) -> np.ndarray:
    """The 8-point null vector of ``x_bᵀ F x_a = 0`` (points as given), optionally of rank 2."""
    u1, v1 = a.T
    u2, v2 = b.T
    A = np.stack([u2 * u1, u2 * v1, u2, v2 * u1, v2 * v1, v2, u1, v1, np.ones_like(u1)], axis=1)
    F = np.linalg.svd(A)[2][-1].reshape(3, 3)
    if rank2:
        U, s, Vt = np.linalg.svd(F)
        F = U @ np.diag([s[0], s[1], 0.0]) @ Vt
    return F


def _unit(F: np.ndarray) -> np.ndarray:
    """Unit Frobenius norm, largest-magnitude entry positive (the reference's convention: the SVD's sign
    of a null vector differs between CPUs)."""
    return fix_sign(F / np.linalg.norm(F))


def eight_point_variants(x1: np.ndarray, x2: np.ndarray) -> dict[str, np.ndarray]:
    """F (3, 3) of the classic 8-point mistakes on matches ``x1, x2 (N, 2)``."""
    a, T1 = ref.normalize_points(x1)
    b, T2 = ref.normalize_points(x2)
    Fn = _solve(a, b)
    return {
        "transposed": _unit(T1.T @ _solve(b, a) @ T2),
        "unnormalized": _unit(_solve(x1, x2)),
        "no_rank2": _unit(T2.T @ _solve(a, b, rank2=False) @ T1),
        "not_denormalized": _unit(Fn),
        "denormalized_swapped": _unit(T1.T @ Fn @ T2),
        "denormalized_inverse": _unit(np.linalg.inv(T2).T @ Fn @ np.linalg.inv(T1)),
        "denormalized_no_transpose": _unit(T2 @ Fn @ T1),
    }


def sampson_variants(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> dict[str, np.ndarray]:
    """Distances (N,) of the classic Sampson-distance mistakes for ``F`` and matches ``x1, x2 (N, 2)``."""
    h1, h2 = to_homogeneous(x1), to_homogeneous(x2)
    l2, l1 = h1 @ F.T, h2 @ F  # epipolar lines in image 2 and in image 1
    e = np.sum(h2 * l2, axis=1)
    g2 = l2[:, 0] ** 2 + l2[:, 1] ** 2 + l1[:, 0] ** 2 + l1[:, 1] ** 2
    d = np.abs(e) / np.sqrt(g2)
    d2 = np.abs(e) / np.hypot(l2[:, 0], l2[:, 1])  # x2 to the line F x1
    d1 = np.abs(e) / np.hypot(l1[:, 0], l1[:, 1])  # x1 to the line Fᵀ x2
    wrong_l1 = h2 @ F.T  # F x2 in place of Fᵀ x2
    return {
        "squared": d**2,
        "algebraic": np.abs(e),
        "algebraic_unit": np.abs(e) / np.linalg.norm(F),
        "signed": e / np.sqrt(g2),
        "one_sided_2": d2,
        "one_sided_1": d1,
        "symmetric_sum": d1 + d2,
        "symmetric_mean": (d1 + d2) / 2,
        "symmetric_rms": np.sqrt((d1**2 + d2**2) / 2),
        "symmetric_root": np.sqrt(d1**2 + d2**2),
        "symmetric_squared": d1**2 + d2**2,
        "transposed": ref.sampson_distance(F.T, x1, x2),
        "no_sqrt": np.abs(e) / g2,
        "wrong_gradient": np.abs(e) / np.sqrt(l2[:, 0] ** 2 + l2[:, 1] ** 2 + wrong_l1[:, 0] ** 2 + wrong_l1[:, 1] ** 2),
        "pixels_not_homogeneous_1": np.abs(e) / np.sqrt(g2 + l2[:, 2] ** 2 + l1[:, 2] ** 2),
    }

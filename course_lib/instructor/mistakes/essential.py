"""Classic mistakes of notebook 02 (essential matrix, pose candidates), evaluated on a case (instructor side only).

``essential_variants(F, K)`` returns ``{key: E}``: what ``essential_from_fundamental`` gives with the
mistake ``key``, before and after the correction to singular values (1, 1, 0) (``<key>_corrected``);
the check module (:mod:`course_lib.checks.essential`) maps the keys to its sentences.
"""

from __future__ import annotations

import numpy as np

__all__ = ["essential_variants"]


def _corrected(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, 0.0]) @ Vt


def essential_variants(F: np.ndarray, K: np.ndarray) -> dict[str, np.ndarray]:
    """E (3, 3) of the classic mistakes of E = Kᵀ F K, each also corrected to singular values (1, 1, 0)."""
    Ki = np.linalg.inv(K)
    raw = {"k_f_kt": K @ F @ K.T, "inverse": Ki.T @ F @ Ki, "transposed": K.T @ F.T @ K, "k_f_k": K @ F @ K}
    out = {}
    for key, M in raw.items():
        out[key] = M / np.linalg.norm(M)
        out[f"{key}_corrected"] = _corrected(M)
    E = K.T @ F @ K
    out["uncorrected"] = E / np.linalg.norm(E)
    return out

"""Classic mistakes of notebook 03 (triangulation), evaluated on a case (instructor side only).

Each function returns ``{key: result}``: what the mistake named by ``key`` gives on the case; the
check module (:mod:`course_lib.checks.triangulation`) maps the keys to its sentences.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from course_lib.sfm import triangulation as ref

__all__ = ["linear_variants", "CHEIRALITY_KEYS", "cheirality_counts", "nonlinear_variants"]


def _dlt(P1, P2, x1, x2, rows=(0, 1), smallest: bool = True) -> np.ndarray:
    out = []
    for a, b in zip(np.asarray(x1, float), np.asarray(x2, float)):
        A = np.stack([a[0] * P1[2] - P1[rows[0]], a[1] * P1[2] - P1[rows[1]],
                      b[0] * P2[2] - P2[rows[0]], b[1] * P2[2] - P2[rows[1]]])
        Xh = np.linalg.svd(A)[2][-1 if smallest else 0]
        out.append(Xh[:3] / Xh[3] if Xh[3] != 0 else np.full(3, np.nan))
    return np.array(out).reshape(-1, 3)


def linear_variants(P1, P2, x1, x2) -> dict[str, np.ndarray]:
    """Points (N, 3) of the classic DLT mistakes."""
    with np.errstate(all="ignore"):
        return {"swapped": _dlt(P2, P1, x1, x2), "uv_swapped": _dlt(P1, P2, x1, x2, rows=(1, 0)),
                "largest": _dlt(P1, P2, x1, x2, smallest=False)}


#: The wrong cheirality tests, in the order of the rows of :func:`cheirality_counts`.
CHEIRALITY_KEYS = ("camera2_only", "camera1_only", "no_centre", "t_for_C", "column_of_R", "sign_flipped")


def cheirality_counts(R, C, K, x1, x2) -> np.ndarray:
    """(len(CHEIRALITY_KEYS), 4) int: per wrong test, the points each candidate keeps."""
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    Xc = [ref.triangulate_linear(P1, K @ np.hstack([R[k], (-R[k] @ C[k])[:, None]]), x1, x2) for k in range(4)]
    tests = {
        "camera2_only": lambda k, X: (X - C[k]) @ R[k][2] > 0,
        "camera1_only": lambda k, X: X[:, 2] > 0,
        "no_centre": lambda k, X: (X[:, 2] > 0) & (X @ R[k][2] > 0),
        "t_for_C": lambda k, X: (X[:, 2] > 0) & ((X + R[k] @ C[k]) @ R[k][2] > 0),
        "column_of_R": lambda k, X: (X[:, 2] > 0) & ((X - C[k]) @ R[k][:, 2] > 0),
        "sign_flipped": lambda k, X: (X[:, 2] < 0) & ((X - C[k]) @ R[k][2] < 0),
    }
    with np.errstate(invalid="ignore"):
        return np.array([[int(tests[key](k, Xc[k]).sum()) for k in range(4)] for key in CHEIRALITY_KEYS])


def _refine(K, R_cws, t_cws, uv, X0, residual, dims: int = 3) -> np.ndarray:
    out = X0.copy()
    for j in range(len(X0)):
        seen = [i for i in range(len(R_cws)) if np.isfinite(uv[j, i]).all()]
        if len(seen) < 2:
            continue
        start = X0[j] if dims == 3 else np.append(X0[j], 1.0)
        x = least_squares(lambda p: np.concatenate([residual(p, i, uv[j, i]) for i in seen]), start).x
        out[j] = x[:3]
    return out


def nonlinear_variants(K, R_cws, t_cws, uv, X0) -> dict[str, np.ndarray]:
    """Points (N, 3) of the classic mistakes of the non-linear triangulation."""
    def proj(X, R, t):
        return K @ (R @ X + t)

    def right(X, i, x):
        p = proj(X, R_cws[i], t_cws[i])
        return p[:2] / p[2] - x

    uv0 = np.where(np.isfinite(uv), uv, 0.0)
    return {
        "no_depth_division": _refine(K, R_cws, t_cws, uv, X0, lambda X, i, x: proj(X, R_cws[i], t_cws[i])[:2] - x),
        "cross_multiplied": _refine(K, R_cws, t_cws, uv, X0,
                                    lambda X, i, x: proj(X, R_cws[i], t_cws[i])[:2] - x * proj(X, R_cws[i], t_cws[i])[2]),
        "nan_as_zero": np.array([least_squares(lambda X, j=j: np.concatenate([right(X, i, uv0[j, i])
                                                                               for i in range(len(R_cws))]), X0[j]).x
                                 for j in range(len(X0))]),
        "unseen_not_refined": np.where(np.isfinite(uv).all(axis=(1, 2))[:, None],
                                       ref.triangulate_nonlinear(K, R_cws, t_cws, uv, X0), X0),
    }

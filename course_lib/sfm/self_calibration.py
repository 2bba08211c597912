"""The focal length from the images alone: self-calibration from the verified pairs' fundamental matrices.

Photos without a calibration file and without a focal length in EXIF start from a guess (COLMAP's
``1.2 x`` the longer side, :mod:`course_lib.data.camera`), which can be off by a factor of two or
three. The bundle adjustment refines the focal length, but a model grown with a focal length that
far off is distorted from its first pair on, and the adjustment ends in a wrong model with a wrong
focal length. So before the mapper starts, the focal length is estimated from the pairs:

* For two views of one camera (``K`` shared, principal point at the image centre, square pixels),
  ``E = Kᵀ F K`` is an essential matrix exactly when ``K`` is right: its two non-zero singular
  values are equal (Huang and Faugeras). So every verified pair scores every candidate focal length
  ``f`` by how unequal they are, ``c(f) = (s1 - s2) / (s1 + s2)`` of ``diag(f, f, 1) F' diag(f, f, 1)``
  (``F'``: F for pixels relative to the principal point) -- Mendonça and Cipolla's criterion.
* A pair alone can be blind to ``f`` (views whose optical axes meet at a point as far from both
  centres: a ring aimed at its middle -- Sturm's singular case; or a pair without depth), and
  its curve is then flat; pairs that see it have a sharp minimum. The curves of all pairs are
  summed, weighted by their inliers (capped), over candidates on a log scale from a quarter to four
  times the guess, and the minimum of the sum is refined by a parabola through its neighbours.
  Bougnoux's closed-form focal length of each pair is reported beside it (its median), as a check.
* The estimate is used only where its curve has a clear minimum (:data:`MIN_DEPTH` below the
  curve's level at the ends of the range, not at an end); otherwise the guess stays, and the report
  says why.

The bundle adjustments then refine it together with ``k1``
(:meth:`course_lib.sfm.mapper.IncrementalMapper.adjust_bundle`), from a start close enough that the
model it grows is right.

Introduced in ``notebooks/10_photos_to_nerf.ipynb``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["FocalEstimate", "essential_cost", "focal_from_fundamentals", "bougnoux_focal", "SCAN_RANGE", "MIN_DEPTH"]

#: Candidate focal lengths from ``guess / SCAN_RANGE`` to ``guess * SCAN_RANGE`` (true focal lengths of 0.5x-3x the guess, with room).
SCAN_RANGE = 4.0
#: Candidates on the log scale.
SCAN_STEPS = 161
#: A pair's weight: its inliers, at most this many (a few strong pairs must not outvote the rest).
WEIGHT_CAP = 200
#: The summed curve's minimum must lie this far (relative) below its level at the ends of the range.
MIN_DEPTH = 0.15


@dataclass
class FocalEstimate:
    """What :func:`focal_from_fundamentals` found.

    Attributes:
        focal_px: the estimate (pixels), or None where the pairs do not determine it.
        guess_px: the focal length it started from.
        pairs: pairs used.
        depth: how far the summed curve's minimum lies below its ends (relative; 0: flat).
        bougnoux_median_px: median of the pairs' closed-form (Bougnoux) focal lengths where real, else None.
        note: why the estimate was not used (empty where it was).
        curve: ``(f_px, cost)`` the summed curve on the candidates (for plots).
    """

    focal_px: float | None
    guess_px: float
    pairs: int
    depth: float
    bougnoux_median_px: float | None = None
    note: str = ""
    curve: tuple = field(default=(), repr=False)

    def summary(self) -> dict:
        return {"focal_px": None if self.focal_px is None else round(self.focal_px, 2), "guess_px": round(self.guess_px, 2),
                "pairs": self.pairs, "depth": round(self.depth, 4),
                "bougnoux_median_px": None if self.bougnoux_median_px is None else round(self.bougnoux_median_px, 2),
                "used": self.focal_px is not None, **({"note": self.note} if self.note else {})}


def _centred(F: np.ndarray, principal_point) -> np.ndarray:
    """``(P, 3, 3)`` F for pixels relative to the principal point: ``Tᵀ F T``, ``T = [[1, 0, cx], [0, 1, cy], [0, 0, 1]]``,
    scaled to unit Frobenius norm."""
    cx, cy = principal_point
    T = np.array([[1.0, 0.0, cx], [0.0, 1.0, cy], [0.0, 0.0, 1.0]])
    G = T.T @ np.asarray(F, float) @ T
    return G / np.linalg.norm(G, axis=(1, 2), keepdims=True)


def essential_cost(F: np.ndarray, focal_px: np.ndarray, principal_point) -> np.ndarray:
    """How far ``Kᵀ F K`` is from an essential matrix, for every pair and candidate focal length.

    Args:
        F: ``(P, 3, 3)`` fundamental matrices (pixels). focal_px: ``(G,)`` candidates.
        principal_point: ``(cx, cy)`` pixels.

    Returns:
        ``(P, G)`` ``(s1 - s2) / (s1 + s2)`` of the two largest singular values (0: an essential matrix).
    """
    G = _centred(F, principal_point)
    f = np.asarray(focal_px, float)
    d = np.stack([f, f, np.ones_like(f)], axis=1)  # (G, 3)
    E = d[None, :, :, None] * G[:, None] * d[None, :, None, :]  # (P, G, 3, 3)
    s = np.linalg.svd(E, compute_uv=False)
    return (s[..., 0] - s[..., 1]) / np.maximum(s[..., 0] + s[..., 1], 1e-300)


def bougnoux_focal(F: np.ndarray, principal_point) -> np.ndarray:
    """Bougnoux's closed-form focal length of each pair (one camera, principal point known), NaN where not real.

    ``f² = - p₂ᵀ [e₂]ₓ Ĩ F p₁ p₁ᵀ Fᵀ p₂ / (p₂ᵀ [e₂]ₓ Ĩ F Ĩ Fᵀ p₂)`` with ``Ĩ = diag(1, 1, 0)``, ``p`` the principal
    point (homogeneous) and ``e₂`` the epipole of the second image. Exact for exact F, singular where the optical
    axes meet; used as a check.

    Returns:
        ``(P,)`` pixels.
    """
    cx, cy = principal_point
    p = np.array([cx, cy, 1.0])
    I3 = np.diag([1.0, 1.0, 0.0])
    out = []
    for Fi in np.asarray(F, float):
        _, _, Vt = np.linalg.svd(Fi.T)
        e2 = Vt[-1]
        ex = np.array([[0, -e2[2], e2[1]], [e2[2], 0, -e2[0]], [-e2[1], e2[0], 0]])
        num = -(p @ ex @ I3 @ Fi @ p) * (p @ Fi.T @ p)
        den = p @ ex @ I3 @ Fi @ I3 @ Fi.T @ p
        f2 = num / den if den != 0 else np.nan
        out.append(np.sqrt(f2) if np.isfinite(f2) and f2 > 0 else np.nan)
    return np.array(out)


def focal_from_fundamentals(F: np.ndarray, inliers: np.ndarray, image_size: tuple[int, int], guess_px: float,
                            principal_point=None) -> FocalEstimate:
    """One camera's focal length from the fundamental matrices of its verified pairs (module docstring).

    Args:
        F: ``(P, 3, 3)`` fundamental matrices (pixels; ``x2ᵀ F x1 = 0``). inliers: ``(P,)`` the pairs' inlier counts.
        image_size: ``(W, H)``. guess_px: the focal length to start from (the scan's centre).
        principal_point: ``(cx, cy)``; default the image centre ``((W - 1) / 2, (H - 1) / 2)``.

    Returns:
        :class:`FocalEstimate` (``focal_px`` None where the pairs do not determine it, ``note`` says why).

    Introduced in ``notebooks/10_photos_to_nerf.ipynb``.
    """
    W, H = image_size
    pp = ((W - 1) / 2.0, (H - 1) / 2.0) if principal_point is None else tuple(principal_point)
    F = np.asarray(F, float).reshape(-1, 3, 3)
    guess = float(guess_px)
    if len(F) == 0:
        return FocalEstimate(None, guess, 0, 0.0, note="no verified pair")
    logs = np.linspace(np.log(guess / SCAN_RANGE), np.log(guess * SCAN_RANGE), SCAN_STEPS)
    f = np.exp(logs)
    w = np.minimum(np.asarray(inliers, float), WEIGHT_CAP)
    cost = essential_cost(F, f, pp)
    total = (w[:, None] * cost).sum(axis=0) / w.sum()
    k = int(np.argmin(total))
    ends = min(total[0], total[-1])
    depth = float((ends - total[k]) / max(ends, 1e-12))
    bou = bougnoux_focal(F, pp)
    bou_med = float(np.nanmedian(bou)) if np.isfinite(bou).any() else None
    est = FocalEstimate(None, guess, int(len(F)), depth, bou_med, curve=(f, total))
    if k in (0, SCAN_STEPS - 1):
        est.note = f"the pairs' curve has its minimum at the end of the range ({f[k]:.0f} px): the guess stays"
        return est
    if depth < MIN_DEPTH:
        est.note = (f"the pairs hardly tell the focal length (their curve's minimum is {100 * depth:.0f} % below its ends, "
                    f"need {100 * MIN_DEPTH:.0f} %): the guess stays")
        return est
    a, b, c = total[k - 1], total[k], total[k + 1]  # a parabola in log f through the minimum and its neighbours
    den = a - 2 * b + c
    shift = 0.5 * (a - c) / den if den > 0 else 0.0
    est.focal_px = float(np.exp(logs[k] + np.clip(shift, -1, 1) * (logs[1] - logs[0])))
    return est

"""The fundamental matrix: Hartley normalization, the normalized 8-point algorithm, Sampson distance, RANSAC.

Two images of the same scene are tied by the *epipolar constraint*: a pixel ``x1`` in image 1
and its match ``x2`` in image 2 satisfy, in homogeneous coordinates (rows ``(u, v, 1)``),

    x2ᵀ F x1 = 0,

where ``F`` is the ``(3, 3)`` fundamental matrix of rank 2. ``F @ x1`` is the epipolar line of
``x1`` in image 2 (``a u + b v + c = 0``), ``F.T @ x2`` the epipolar line of ``x2`` in image 1.

Conventions (see :mod:`course_lib.conventions`): points are rows, ``x1, x2`` have shape
``(N, 2)`` and hold pixels ``(u, v)``; row ``k`` of ``x1`` and of ``x2`` is one correspondence.
Every ``F`` returned here has unit Frobenius norm and a deterministic sign (its entry of largest
magnitude is positive), so two estimates can be compared entry by entry.

Introduced in notebooks/01_fundamental_matrix.ipynb.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from course_lib import validate
from course_lib.validate import KitInputError

__all__ = [
    "normalize_points",
    "eight_point",
    "sampson_distance",
    "ransac_fundamental",
    "ransac_iterations",
    "RansacResult",
]

_WHY_8 = "the 8-point algorithm"


# ---------------------------------------------------------------------------------------------
# Normalization
# ---------------------------------------------------------------------------------------------


def normalize_points(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hartley normalization: move the centroid to the origin, scale to mean distance sqrt(2).

    With ``c`` the centroid of the points and ``d`` their mean distance to ``c``, the similarity

        T = [[s, 0, -s c_u], [0, s, -s c_v], [0, 0, 1]],   s = sqrt(2) / d

    maps every point to ``x_n = s (x - c)``. The normalized points are centred at the origin and
    their mean distance to it is ``sqrt(2)``, so all entries of the 8-point system have a similar
    magnitude (about 1) instead of ranging from 1 to 10⁶ for pixels.

    Args:
        x: ``(N, 2)`` pixels ``(u, v)``, N >= 2, not all identical.

    Returns:
        x_n: ``(N, 2)`` normalized points, ``x_n = from_homogeneous(to_homogeneous(x) @ T.T)``.
        T: ``(3, 3)`` the normalizing similarity.

    Raises:
        KitInputError: wrong shape, NaN/inf, fewer than 2 points, or all points identical.

    Introduced in notebooks/01_fundamental_matrix.ipynb.
    """
    x = validate.points(x, "x", 2, min_count=2, why="normalization")
    c = x.mean(axis=0)
    d = np.linalg.norm(x - c, axis=1).mean()
    scale = np.abs(x).max() if x.size else 1.0
    if not d > 1e-12 * max(scale, 1.0):
        raise KitInputError(
            f"x has {len(x)} points that are all identical ({x[0].tolist()}): they cannot be normalized; "
            "check that the correspondences are distinct"
        )
    s = np.sqrt(2.0) / d
    T = np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])
    return (x - c) * s, T


# ---------------------------------------------------------------------------------------------
# The normalized 8-point algorithm
# ---------------------------------------------------------------------------------------------


def _fix_norm_and_sign(F: np.ndarray) -> np.ndarray:
    """Scale to unit Frobenius norm and make the entry of largest magnitude positive."""
    F = F / np.linalg.norm(F)
    k = np.argmax(np.abs(F))
    return F if F.flat[k] >= 0 else -F


def _eight_point_core(x1: np.ndarray, x2: np.ndarray) -> np.ndarray | None:
    """The normalized 8-point algorithm without input checks; None for a degenerate configuration."""
    c1, c2 = x1.mean(0), x2.mean(0)
    d1 = np.linalg.norm(x1 - c1, axis=1).mean()
    d2 = np.linalg.norm(x2 - c2, axis=1).mean()
    if not (d1 > 1e-12 and d2 > 1e-12):
        return None
    s1, s2 = np.sqrt(2.0) / d1, np.sqrt(2.0) / d2
    T1 = np.array([[s1, 0.0, -s1 * c1[0]], [0.0, s1, -s1 * c1[1]], [0.0, 0.0, 1.0]])
    T2 = np.array([[s2, 0.0, -s2 * c2[0]], [0.0, s2, -s2 * c2[1]], [0.0, 0.0, 1.0]])
    u1, v1 = ((x1 - c1) * s1).T
    u2, v2 = ((x2 - c2) * s2).T
    # One row per correspondence: x2ᵀ F x1 = 0 written as A f = 0 with f = F.ravel() (row-major).
    A = np.stack([u2 * u1, u2 * v1, u2, v2 * u1, v2 * v1, v2, u1, v1, np.ones_like(u1)], axis=1)
    # full_matrices only for N = 8, where the null vector is the 9th row of Vt (thin SVD otherwise:
    # the full U of a big A is N x N and slow)
    _, S, Vt = np.linalg.svd(A, full_matrices=len(A) < 9)
    # f is unique (up to scale) only if A has rank 8: its 8th singular value must not vanish.
    if len(S) < 8 or S[7] <= 1e-10 * S[0]:
        return None
    F_n = Vt[-1].reshape(3, 3)
    # Rank 2: zero the smallest singular value (the closest rank-2 matrix in Frobenius norm).
    U, s, Vt = np.linalg.svd(F_n)
    F_n = U @ np.diag([s[0], s[1], 0.0]) @ Vt
    # Undo the normalization: x2nᵀ F_n x1n = x2ᵀ (T2ᵀ F_n T1) x1.
    F = T2.T @ F_n @ T1
    return _fix_norm_and_sign(F)


def eight_point(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """The normalized 8-point algorithm (Hartley 1997) with rank-2 enforcement.

    1. Normalize each image's points (:func:`normalize_points`) to ``x1n, x2n``.
    2. Each correspondence gives one linear equation ``x2nᵀ F_n x1n = 0`` in the 9 entries of
       ``F_n``; stack them into ``A (N, 9)`` and take ``f`` = the right singular vector of the
       smallest singular value (least squares with ``|f| = 1``).
    3. Enforce rank 2: ``F_n = U diag(s1, s2, 0) Vᵀ``.
    4. Denormalize: ``F = T2ᵀ F_n T1``; scale to unit Frobenius norm, largest-magnitude entry positive.

    Args:
        x1: ``(N, 2)`` pixels in image 1, N >= 8.
        x2: ``(N, 2)`` the matching pixels in image 2 (row k matches row k of ``x1``).

    Returns:
        F: ``(3, 3)`` fundamental matrix of rank 2 with ``x2hᵀ F x1h ≈ 0`` (``xh`` = ``(u, v, 1)``),
        unit Frobenius norm, sign fixed so that its largest-magnitude entry is positive.

    Raises:
        KitInputError: fewer than 8 correspondences, mismatched counts, NaN/inf, or a degenerate
            configuration (identical or collinear points, too few distinct correspondences).

    Introduced in notebooks/01_fundamental_matrix.ipynb.
    """
    x1, x2 = validate.matching_points(x1, x2, min_count=8, why=_WHY_8)
    for name, x in (("x1", x1), ("x2", x2)):
        if np.linalg.norm(x - x.mean(0), axis=1).max() <= 1e-12 * max(np.abs(x).max(), 1.0):
            raise KitInputError(f"{name}: all {len(x)} points are identical; the 8-point algorithm needs distinct points")
    F = _eight_point_core(x1, x2)
    if F is None:
        raise KitInputError(
            f"the {len(x1)} correspondences are degenerate for {_WHY_8} (the linear system has rank < 8): "
            "are many points identical, collinear, or duplicated? use at least 8 distinct, well-spread matches"
        )
    return F


# ---------------------------------------------------------------------------------------------
# Sampson distance
# ---------------------------------------------------------------------------------------------


def _check_F(F, name: str = "F") -> np.ndarray:
    try:
        F = np.asarray(F, dtype=float)
    except (TypeError, ValueError):
        raise KitInputError(f"{name} must be a numeric (3, 3) matrix, got {type(F).__name__}") from None
    if F.shape != (3, 3):
        raise KitInputError(f"{name} has shape {F.shape}: expected the (3, 3) fundamental matrix")
    if not np.isfinite(F).all():
        raise KitInputError(f"{name} contains NaN or inf")
    if not np.abs(F).max() > 0:
        raise KitInputError(f"{name} is all zeros: it is not a valid fundamental matrix")
    return F


def _sampson_core(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    x1h = np.column_stack([x1, np.ones(len(x1))])
    x2h = np.column_stack([x2, np.ones(len(x2))])
    Fx1 = x1h @ F.T  # (N, 3) epipolar lines in image 2
    Ftx2 = x2h @ F  # (N, 3) epipolar lines in image 1
    e = np.sum(x2h * Fx1, axis=1)  # algebraic error x2ᵀ F x1
    g2 = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.abs(e) / np.sqrt(g2)
    return np.where(g2 > 0, d, np.where(e == 0, 0.0, np.inf))


def sampson_distance(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Sampson distance of each correspondence to the epipolar geometry ``F``, in pixels.

    The first-order approximation of the geometric (reprojection) error: with the algebraic
    error ``e = x2ᵀ F x1`` and the lines ``l2 = F x1``, ``l1 = Fᵀ x2``,

        d = |e| / sqrt(l2[0]² + l2[1]² + l1[0]² + l1[1]²).

    ``d`` is in pixels, unlike ``e``, whose scale depends on the scale of ``F``. (``d²`` is
    Sampson's error; this returns its square root so that it can be compared with a threshold
    in pixels.)

    Args:
        F: ``(3, 3)`` fundamental matrix (any scale), ``x2hᵀ F x1h = 0``.
        x1: ``(N, 2)`` pixels in image 1.
        x2: ``(N, 2)`` matching pixels in image 2.

    Returns:
        ``(N,)`` distances in pixels (>= 0).

    Raises:
        KitInputError: bad shapes, NaN/inf, or an all-zero ``F``.

    Introduced in notebooks/01_fundamental_matrix.ipynb.
    """
    F = _check_F(F)
    x1, x2 = validate.matching_points(x1, x2)
    return _sampson_core(F, x1, x2)


# ---------------------------------------------------------------------------------------------
# RANSAC
# ---------------------------------------------------------------------------------------------


@dataclass
class RansacResult:
    """The outcome of :func:`ransac_fundamental`.

    Attributes:
        F: ``(3, 3)`` fundamental matrix refit on all inliers (unit Frobenius norm, sign fixed).
        inliers: ``(N,)`` bool, True where the Sampson distance to ``F`` is below the threshold.
        n_iters: number of random samples drawn.
    """

    F: np.ndarray
    inliers: np.ndarray
    n_iters: int

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))

    def __repr__(self) -> str:
        return f"RansacResult(F=<3x3>, inliers={self.n_inliers}/{len(self.inliers)}, n_iters={self.n_iters})"


def ransac_iterations(inlier_ratio: float, confidence: float = 0.999, sample_size: int = 8) -> float:
    """Samples needed to draw at least one all-inlier sample with probability ``confidence``.

        n = log(1 - p) / log(1 - w^s)

    with ``p`` the confidence, ``w`` the inlier ratio and ``s`` the sample size (8 here).

    Args:
        inlier_ratio: ``w`` in [0, 1].
        confidence: ``p`` in (0, 1).
        sample_size: ``s``.

    Returns:
        The number of samples as a float (``inf`` when ``w = 0``, ``0`` when ``w = 1``).

    Introduced in notebooks/01_fundamental_matrix.ipynb.
    """
    w = float(inlier_ratio)
    if not 0.0 <= w <= 1.0:
        raise KitInputError(f"inlier_ratio={w}: expected a fraction in [0, 1]")
    if not 0.0 < confidence < 1.0:
        raise KitInputError(f"confidence={confidence}: expected a probability strictly between 0 and 1")
    p_good = w**sample_size
    if p_good >= 1.0:
        return 0.0
    if p_good <= 0.0:
        return float("inf")
    return float(np.log(1.0 - confidence) / np.log1p(-p_good))


def ransac_fundamental(
    x1: np.ndarray,
    x2: np.ndarray,
    rng: np.random.Generator,
    threshold_px: float = 1.0,
    confidence: float = 0.999,
    max_iters: int = 2000,
) -> RansacResult:
    """Robust F: RANSAC over minimal 8-point samples, inliers by Sampson distance, adaptive stop.

    Each iteration draws 8 distinct correspondences with ``rng``, fits F with the 8-point
    algorithm, and counts the correspondences whose Sampson distance (pixels) is below
    ``threshold_px``. The best count so far gives the inlier ratio ``w`` and the number of
    iterations needed, ``log(1 - confidence) / log(1 - w⁸)`` (:func:`ransac_iterations`); the
    loop stops there or at ``max_iters``. Finally F is refit on all inliers of the best sample
    and the inliers are recomputed with it (repeated while the inlier set grows, at most 5 times).

    Args:
        x1: ``(N, 2)`` pixels in image 1, N >= 8.
        x2: ``(N, 2)`` matching pixels in image 2.
        rng: seeded ``numpy.random.Generator`` (the only source of randomness).
        threshold_px: inlier threshold on the Sampson distance, in pixels.
        confidence: desired probability of drawing at least one outlier-free sample.
        max_iters: the most samples drawn.

    Returns:
        :class:`RansacResult` ``(F (3, 3), inliers (N,) bool, n_iters int)``.

    Raises:
        KitInputError: bad inputs, or no sample gave a non-degenerate F.

    Introduced in notebooks/01_fundamental_matrix.ipynb.
    """
    x1, x2 = validate.matching_points(x1, x2, min_count=8, why=_WHY_8)
    if not isinstance(rng, np.random.Generator):
        raise KitInputError(
            f"rng must be a numpy.random.Generator (e.g. np.random.default_rng(0)), got {type(rng).__name__}"
        )
    if not (np.isfinite(threshold_px) and threshold_px > 0):
        raise KitInputError(f"threshold_px={threshold_px}: expected a positive number of pixels")
    if not 0.0 < confidence < 1.0:
        raise KitInputError(f"confidence={confidence}: expected a probability strictly between 0 and 1")
    if int(max_iters) < 1:
        raise KitInputError(f"max_iters={max_iters}: expected at least 1")
    max_iters = int(max_iters)

    n = len(x1)
    best_F, best_inliers, best_count = None, None, -1
    needed = float(max_iters)
    it = 0
    while it < min(needed, max_iters):
        it += 1
        sample = rng.choice(n, size=8, replace=False)
        F = _eight_point_core(x1[sample], x2[sample])
        if F is None:
            continue  # degenerate sample: draw again (it still counts as an iteration)
        inliers = _sampson_core(F, x1, x2) < threshold_px
        count = int(inliers.sum())
        if count > best_count:
            best_F, best_inliers, best_count = F, inliers, count
            needed = ransac_iterations(count / n, confidence, 8)
    if best_F is None:
        raise KitInputError(
            f"RANSAC found no non-degenerate sample in {it} iterations: the {n} correspondences are degenerate"
        )

    # Refit on all inliers of the best sample, recompute the inliers, and repeat while the set grows.
    F, inliers = best_F, best_inliers
    for round_ in range(5):
        if inliers.sum() < 8:
            break
        F_new = _eight_point_core(x1[inliers], x2[inliers])
        if F_new is None:
            break
        inl_new = _sampson_core(F_new, x1, x2) < threshold_px
        if round_ > 0 and inl_new.sum() < inliers.sum():
            break
        done = np.array_equal(inl_new, inliers)
        F, inliers = F_new, inl_new
        if done:
            break
    return RansacResult(F=F, inliers=inliers, n_iters=it)

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

from dataclasses import dataclass, field

import numpy as np

from course_lib import validate
from course_lib.sfm.refit import refit_on_inliers
from course_lib.validate import KitInputError

__all__ = [
    "normalize_points",
    "normalize_points_batch",
    "eight_point",
    "eight_point_batch",
    "sampson_distance",
    "sampson_distance_batch",
    "ransac",
    "ransac_fundamental",
    "ransac_iterations",
    "RansacResult",
]

_WHY_8 = "the 8-point algorithm"


# ---------------------------------------------------------------------------------------------
# Normalization
# ---------------------------------------------------------------------------------------------


def normalize_points_batch(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hartley normalization of ``B`` point sets at once, without input checks.

    The one implementation behind :func:`normalize_points`, :func:`eight_point_batch` and so
    every 8-point fit of the kit (see :func:`normalize_points` for the formula).

    Args:
        x: ``(B, N, 2)`` pixels.

    Returns:
        x_n: ``(B, N, 2)`` normalized points. T: ``(B, 3, 3)`` the normalizing similarities.
        ok: ``(B,)`` bool, False where the points of a set are all identical (no normalization).
    """
    c = x.mean(axis=1, keepdims=True)
    d = np.linalg.norm(x - c, axis=2).mean(axis=1)
    scale = np.maximum(np.abs(x).max(axis=(1, 2)), 1.0) if x.shape[1] else np.ones(len(x))
    ok = d > 1e-12 * scale
    s = np.sqrt(2.0) / np.where(ok, d, 1.0)
    T = np.zeros((len(x), 3, 3))
    T[:, 0, 0] = T[:, 1, 1] = s
    T[:, :2, 2] = -s[:, None] * c[:, 0]
    T[:, 2, 2] = 1.0
    return (x - c) * s[:, None, None], T, ok


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
    x_n, T, ok = normalize_points_batch(x[None])
    if not ok[0]:
        raise KitInputError(
            f"x has {len(x)} points that are all identical ({x[0].tolist()}): they cannot be normalized; "
            "check that the correspondences are distinct"
        )
    return x_n[0], T[0]


# ---------------------------------------------------------------------------------------------
# The normalized 8-point algorithm
# ---------------------------------------------------------------------------------------------


def _null_vectors(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``f (B, 9)`` minimizing ``|A f|`` with ``|f| = 1``, and ``ok (B,)`` (False where ``A (B, N, 9)`` has rank < 8).

    For minimal samples (N = 8) the null vector is the last column of the complete QR factor of
    ``Aᵀ`` (orthogonal to the 8 rows of A): the SVD's answer at a quarter of the cost, a rank < 8
    shows as a vanishing ``R[7, 7]``. Otherwise the right singular vector of the smallest
    singular value (least squares); rank < 8 shows as a vanishing 8th singular value.
    """
    if A.shape[1] == 8:
        Q, R = np.linalg.qr(np.transpose(A, (0, 2, 1)), mode="complete")
        diag = np.abs(np.diagonal(R, axis1=1, axis2=2))
        return Q[:, :, -1], diag[:, 7] > 1e-10 * diag.max(axis=1)
    _, S, Vt = np.linalg.svd(A, full_matrices=A.shape[1] < 9)
    ok = S[:, 7] > 1e-10 * S[:, 0] if S.shape[1] >= 8 else np.zeros(len(A), bool)
    return Vt[:, -1], ok


def eight_point_batch(x1: np.ndarray, x2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The normalized 8-point algorithm on ``B`` sets of correspondences at once, without input checks.

    The one implementation of the kit (:func:`eight_point` checks its inputs and calls it; the
    RANSAC of :func:`ransac` takes it as its minimal solver): Hartley normalization
    (:func:`normalize_points_batch`), the null vector of ``A``, rank 2, undo the normalization,
    unit Frobenius norm, the entry of largest magnitude positive.

    Args:
        x1, x2: ``(B, N, 2)`` matching pixels, N >= 8.

    Returns:
        F: ``(B, 3, 3)`` with ``x2hᵀ F x1h ≈ 0``. ok: ``(B,)`` bool, False for a degenerate set
        (identical points, or a linear system of rank < 8); its F is not meaningful.
    """
    B = len(x1)
    n1, T1, ok1 = normalize_points_batch(x1)
    n2, T2, ok2 = normalize_points_batch(x2)
    u1, v1 = n1[..., 0], n1[..., 1]
    u2, v2 = n2[..., 0], n2[..., 1]
    # One row per correspondence: x2ᵀ F x1 = 0 written as A f = 0 with f = F.ravel() (row-major).
    A = np.stack([u2 * u1, u2 * v1, u2, v2 * u1, v2 * v1, v2, u1, v1, np.ones_like(u1)], axis=2)  # (B, N, 9)
    f, ok = _null_vectors(A)
    # Rank 2: zero the smallest singular value (the closest rank-2 matrix in Frobenius norm).
    U, s, Vt = np.linalg.svd(f.reshape(B, 3, 3))
    s[:, 2] = 0.0
    # Undo the normalization: x2nᵀ F_n x1n = x2ᵀ (T2ᵀ F_n T1) x1.
    F = np.transpose(T2, (0, 2, 1)) @ ((U * s[:, None, :]) @ Vt) @ T1
    F /= np.linalg.norm(F, axis=(1, 2), keepdims=True)
    k = np.abs(F).reshape(B, 9).argmax(axis=1)
    F *= np.where(F.reshape(B, 9)[np.arange(B), k] < 0, -1.0, 1.0)[:, None, None]
    return F, ok & ok1 & ok2


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
    F, ok = eight_point_batch(x1[None], x2[None])
    if not ok[0]:
        raise KitInputError(
            f"the {len(x1)} correspondences are degenerate for {_WHY_8} (the linear system has rank < 8): "
            "are many points identical, collinear, or duplicated? use at least 8 distinct, well-spread matches"
        )
    return F[0]


# ---------------------------------------------------------------------------------------------
# Sampson distance
# ---------------------------------------------------------------------------------------------


def sampson_distance_batch(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Sampson distances (pixels) of ``N`` matches to ``B`` fundamental matrices, without input checks.

    The one implementation behind :func:`sampson_distance` and the error function of
    :func:`ransac` (see :func:`sampson_distance` for the formula).

    Args:
        F: ``(B, 3, 3)``. x1, x2: ``(N, 2)`` matching pixels.

    Returns:
        ``(B, N)`` distances >= 0 (0 where both the error and the gradient vanish, inf where only
        the gradient does).
    """
    h1 = np.concatenate([x1, np.ones((len(x1), 1))], axis=1).T  # (3, N)
    h2 = np.concatenate([x2, np.ones((len(x2), 1))], axis=1).T
    B, N = len(F), h1.shape[1]
    # one matrix product each for all B models: (3B, 3) @ (3, N)
    Fx1 = (F.reshape(3 * B, 3) @ h1).reshape(B, 3, N)  # epipolar lines in image 2
    Ftx2 = (np.transpose(F, (0, 2, 1)).reshape(3 * B, 3) @ h2).reshape(B, 3, N)  # lines in image 1
    e = Fx1[:, 0] * h2[0] + Fx1[:, 1] * h2[1] + Fx1[:, 2]  # algebraic error x2ᵀ F x1
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
    F = validate.matrix3x3(F, "F", "fundamental matrix")
    x1, x2 = validate.matching_points(x1, x2)
    return sampson_distance_batch(F[None], x1, x2)[0]


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
        distances: ``(N,)`` Sampson distance of every correspondence to ``F`` (pixels).
    """

    F: np.ndarray
    inliers: np.ndarray
    n_iters: int
    distances: np.ndarray | None = field(default=None, repr=False)

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
    validate.probability(confidence, "confidence")
    p_good = w**sample_size
    if p_good >= 1.0:
        return 0.0
    if p_good <= 0.0:
        return float("inf")
    return float(np.log(1.0 - confidence) / np.log1p(-p_good))


def _draw_samples(rng: np.random.Generator, n: int, size: int, count: int) -> np.ndarray:
    """``(count, size)`` indices of ``count`` samples of ``size`` distinct items among ``n``.

    One sample is drawn as ``rng.choice(n, size, replace=False)`` (the textbook loop); many at
    once as the first ``size`` of a random permutation each (``argpartition`` of uniform noise).
    """
    if count == 1:
        return rng.choice(n, size=size, replace=False)[None]
    if n == size:
        return np.tile(np.arange(size), (count, 1))
    return np.argpartition(rng.random((count, n)), size - 1, axis=1)[:, :size]


def _bailout_bar(ratio: float, sub_count: int, m: int) -> float:
    """Inliers among the ``m`` test matches below which a model cannot beat the best (4 sigma).

    A model with at least the best's inlier ratio ``w`` has about ``m w`` inliers among the test
    matches, give or take ``sqrt(m w (1 - w))`` (binomial). ``w`` is the smaller of the best's
    ratio over all matches and over the test matches (``sub_count / m``), in case the test
    matches hold fewer inliers than the rest.
    """
    w = min(ratio, sub_count / m)
    return m * w - 4.0 * np.sqrt(m * w * (1.0 - w))


def ransac(x1: np.ndarray, x2: np.ndarray, rng: np.random.Generator, solver=eight_point_batch,
           error=sampson_distance_batch, sample_size: int = 8, threshold: float = 1.0, confidence: float = 0.999,
           max_iters: int = 2000, batch: int = 1, bailout: int = 0) -> RansacResult | None:
    """RANSAC with its minimal solver and its error function as arguments (as kornia's ``RANSAC``).

    Draws ``batch`` samples of ``sample_size`` correspondences at a time with ``rng``, fits one
    model to each with ``solver``, scores every model by its inlier count (``error < threshold``;
    ties go to the smaller sum of errors truncated at the threshold, as MSAC), and stops after
    ``log(1 - confidence) / log(1 - w^s)`` samples for the best inlier ratio ``w`` so far
    (:func:`ransac_iterations`) or at ``max_iters``. The best model is then refit on all its
    inliers while the inlier set grows. No input checks (the callers check).

    Args:
        x1, x2: ``(N, 2)`` matching pixels, N >= ``sample_size``.
        rng: seeded ``numpy.random.Generator`` (the only source of randomness).
        solver: ``solver(x1 (B, n, 2), x2 (B, n, 2)) -> (models (B, ...), ok (B,) bool)`` for any
            ``n >= sample_size`` (default: :func:`eight_point_batch`).
        error: ``error(models (B, ...), x1 (N, 2), x2 (N, 2)) -> (B, N)`` in the unit of
            ``threshold`` (default: :func:`sampson_distance_batch`, pixels).
        sample_size: correspondences per minimal sample.
        threshold: inlier threshold on ``error``.
        confidence: desired probability of drawing at least one outlier-free sample.
        max_iters: the most samples drawn.
        batch: samples drawn and solved per call of ``solver`` (1: the textbook loop).
        bailout: 0 (the textbook loop) or the size ``m`` of a preemptive test (Capel's bail-out,
            Matas and Chum's T(d,d)): once a best model exists, each new model is first scored on
            ``m`` fixed matches (every ``N / m``-th), and only the models that could beat the best
            are scored on all ``N`` (:func:`_bailout_bar`). The answer is the same unless a better
            model fails the test, which a 4-sigma bar makes rare; on 300 matches with half of them
            outliers it saves about two thirds of the time. Used only where ``N > 2 m``.

    Returns:
        :class:`RansacResult` (its ``F`` is the model; ``distances`` the errors to it), or None
        when every sample was degenerate.
    """
    n = len(x1)
    best_key, best = (-1, 0.0), None
    needed, it = float(max_iters), 0
    sub = np.linspace(0, n - 1, bailout).round().astype(int) if 0 < bailout and 2 * bailout < n else None
    bar = -1.0  # a new model is scored on all matches only if it has at least `bar` inliers among `sub`
    while it < min(needed, max_iters):
        b = int(min(batch, max_iters - it))
        idx = _draw_samples(rng, n, sample_size, b)
        it += b
        models, ok = solver(x1[idx], x2[idx])
        if not ok.any():
            continue  # degenerate samples: draw again (they still count as iterations)
        models = models[ok]
        if sub is not None and best is not None:
            models = models[(error(models, x1[sub], x2[sub]) < threshold).sum(axis=1) >= bar]
            if not len(models):
                continue
        d = error(models, x1, x2)
        count = (d < threshold).sum(axis=1)
        trunc = np.minimum(d, threshold).sum(axis=1)
        k = int(np.lexsort((trunc, -count))[0])
        key = (int(count[k]), -float(trunc[k]))
        if key > best_key:
            best_key, best = key, models[k]
            needed = ransac_iterations(best_key[0] / n, confidence, sample_size)
            if sub is not None:
                bar = _bailout_bar(best_key[0] / n, int((d[k, sub] < threshold).sum()), len(sub))
    if best is None:
        return None
    model, d = refit_on_inliers(solver, error, x1, x2, best, threshold, sample_size)
    return RansacResult(F=model, inliers=d < threshold, n_iters=it, distances=d)


def ransac_fundamental(x1: np.ndarray, x2: np.ndarray, rng: np.random.Generator, threshold_px: float = 1.0,
                       confidence: float = 0.999, max_iters: int = 2000) -> RansacResult:
    """Robust F: RANSAC over minimal 8-point samples, inliers by Sampson distance, adaptive stop.

    Each iteration draws 8 distinct correspondences with ``rng``, fits F with the 8-point
    algorithm, and counts the correspondences whose Sampson distance (pixels) is below
    ``threshold_px``. The best count so far gives the inlier ratio ``w`` and the number of
    iterations needed, ``log(1 - confidence) / log(1 - w⁸)`` (:func:`ransac_iterations`); the
    loop stops there or at ``max_iters``. Finally F is refit on all inliers of the best sample
    and the inliers are recomputed with it (repeated while the inlier set grows, at most 5 times).
    (:func:`ransac` with :func:`eight_point_batch` and :func:`sampson_distance_batch`, one
    sample at a time.)

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
    validate.generator(rng)
    threshold_px = validate.positive(threshold_px, "threshold_px", "a positive number of pixels")
    validate.probability(confidence, "confidence")
    max_iters = validate.count(max_iters, "max_iters", minimum=1)
    res = ransac(x1, x2, rng, threshold=threshold_px, confidence=confidence, max_iters=max_iters)
    if res is None:
        raise KitInputError(
            f"RANSAC found no non-degenerate sample in {max_iters} iterations: the {len(x1)} correspondences are degenerate"
        )
    return res

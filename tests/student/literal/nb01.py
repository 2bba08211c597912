"""Notebook 01, the fundamental matrix: the literal student's exercises."""

import math
from dataclasses import dataclass

import numpy as np


# --- given by the notebook (cell "RansacResult"), not an exercise ------------------------------
@dataclass
class RansacResult:
    F: np.ndarray        # (3, 3) refit on all inliers
    inliers: np.ndarray  # (N,) bool
    n_iters: int         # samples drawn


# --- exercises ---------------------------------------------------------------------------------


def normalize_points(x):
    """Hartley normalization: centroid to the origin, mean distance to it sqrt(2).

    Args:
        x: (N, 2) pixels (u, v), N >= 2, not all identical.

    Returns:
        x_n: (N, 2) normalized points, x_n = s (x - c).
        T: (3, 3) similarity [[s, 0, -s c_u], [0, s, -s c_v], [0, 0, 1]] with x_n = T x in
            homogeneous coordinates (T maps pixels to normalized coordinates).
    """
    c = x.mean(axis=0)
    mean_dist = np.linalg.norm(x - c, axis=1).mean()
    if mean_dist == 0:
        raise ValueError("normalize_points: all points are identical, they cannot be normalized")
    s = np.sqrt(2) / mean_dist
    x_n = s * (x - c)
    T = np.array([[s, 0, -s * c[0]],
                  [0, s, -s * c[1]],
                  [0, 0, 1]])
    return x_n, T


def eight_point(x1, x2):
    """The normalized 8-point algorithm with rank-2 enforcement.

    Args:
        x1: (N, 2) pixels in image 1, N >= 8.
        x2: (N, 2) matching pixels in image 2 (row k matches row k of x1).

    Returns:
        F: (3, 3) fundamental matrix of rank 2 with x2h^T F x1h = 0 (xh = (u, v, 1)), unit
            Frobenius norm, sign fixed so that its entry of largest magnitude is positive.
    """
    if len(x1) < 8:
        raise ValueError(f"eight_point needs at least 8 matches, got {len(x1)}")
    # 1. normalize
    x1n, T1 = normalize_points(x1)
    x2n, T2 = normalize_points(x2)
    u1, v1 = x1n[:, 0], x1n[:, 1]
    u2, v2 = x2n[:, 0], x2n[:, 1]
    # 2. one row (u2u1, u2v1, u2, v2u1, v2v1, v2, u1, v1, 1) per match, f = last row of Vt
    A = np.stack([u2 * u1, u2 * v1, u2, v2 * u1, v2 * v1, v2, u1, v1, np.ones(len(u1))], axis=1)
    _, _, Vt = np.linalg.svd(A)
    F_hat = Vt[-1].reshape(3, 3)
    # 3. rank 2
    U, S, Vt = np.linalg.svd(F_hat)
    S[2] = 0
    F_hat = U @ np.diag(S) @ Vt
    # 4. denormalize
    F = T2.T @ F_hat @ T1
    # 5. unit norm, largest entry positive
    F = F / np.linalg.norm(F)
    if F.flat[np.argmax(np.abs(F))] < 0:
        F = -F
    return F


def sampson_distance(F, x1, x2):
    """Sampson distance of each match to the epipolar geometry F, in pixels.

    Args:
        F: (3, 3) fundamental matrix (any scale), x2h^T F x1h = 0.
        x1: (N, 2) pixels in image 1.
        x2: (N, 2) matching pixels in image 2.

    Returns:
        d: (N,) distances in pixels, d >= 0.
    """
    ones = np.ones((len(x1), 1))
    x1h = np.hstack([x1, ones])
    x2h = np.hstack([x2, ones])
    Fx1 = x1h @ F.T      # row k: F x1h_k
    Ftx2 = x2h @ F       # row k: F^T x2h_k
    e = np.sum(x2h * Fx1, axis=1)
    grad = np.sqrt(Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2)
    return np.abs(e) / grad


def ransac_fundamental(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    """Robust F: RANSAC over 8-point samples, inliers by Sampson distance, adaptive stop, refit.

    Args:
        x1: (N, 2) pixels in image 1, N >= 8.
        x2: (N, 2) matching pixels in image 2.
        rng: seeded numpy.random.Generator; draw every sample from it.
        threshold_px: inlier threshold on the Sampson distance, in pixels.
        confidence: probability p of drawing at least one all-inlier sample.
        max_iters: the most samples drawn.

    Returns:
        RansacResult(F (3, 3) refit on all inliers of the best sample, inliers (N,) bool: the matches
        with Sampson distance < threshold_px to that refit F, n_iters int: the samples drawn).
    """
    N = len(x1)
    if N < 8:
        raise ValueError(f"ransac_fundamental needs at least 8 matches, got {N}")
    best_inliers = None
    best_count = -1
    n_needed = max_iters
    n_iters = 0
    while n_iters < min(n_needed, max_iters):
        sample = rng.choice(N, 8, replace=False)
        n_iters += 1
        F = eight_point(x1[sample], x2[sample])
        inliers = sampson_distance(F, x1, x2) < threshold_px
        count = int(inliers.sum())
        if count > best_count:
            best_count = count
            best_inliers = inliers
            all_inlier = (count / N) ** 8   # probability that a sample of 8 is all inliers
            if all_inlier >= 1.0:
                n_needed = 0
            elif 1 - all_inlier < 1:        # (w ** 8 may be too small to change 1 - w ** 8)
                n_needed = math.ceil(math.log(1 - confidence) / math.log(1 - all_inlier))
    # refit on all inliers of the best sample, then the inliers of the refit F
    F = eight_point(x1[best_inliers], x2[best_inliers])
    inliers = sampson_distance(F, x1, x2) < threshold_px
    return RansacResult(F, inliers, n_iters)

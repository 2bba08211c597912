"""Notebook 01 (the fundamental matrix): classic mistakes, honest solutions and trivial answers, run through its checks."""

from __future__ import annotations

import math

import numpy as np

from course_lib.checks import fundamental as gfu
from course_lib.sfm import fundamental as rfu
from tests.checks.catalogue import Honest, Mistake, _h

# ============================================================================ buggy versions
# Each is written as a student would write it (often the reference with one line changed).

# -- 01: normalize_points -----------------------------------------------------------------------
def normalize_no_centroid(x):
    s = np.sqrt(2) / np.linalg.norm(x - x.mean(0), axis=1).mean()
    T = np.diag([s, s, 1.0])
    return x * s, T


def normalize_mean_one(x):
    c = x.mean(0)
    s = 1.0 / np.linalg.norm(x - c, axis=1).mean()
    T = np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1.0]])
    return (x - c) * s, T


def normalize_two_scales(x):
    c = x.mean(0)
    s = np.sqrt(2) / np.abs(x - c).mean(0) / np.sqrt(2)
    T = np.array([[s[0], 0, -s[0] * c[0]], [0, s[1], -s[1] * c[1]], [0, 0, 1.0]])
    return (x - c) * s, T


def normalize_T_inverted(x):
    xn, T = rfu.normalize_points(x)
    return xn, np.linalg.inv(T)


# -- 01: eight_point ----------------------------------------------------------------------------
def _eight(x1, x2, normalize=True, rank2=True, transpose=False):
    if normalize:
        x1n, T1 = rfu.normalize_points(x1)
        x2n, T2 = rfu.normalize_points(x2)
    else:
        x1n, x2n, T1, T2 = x1, x2, np.eye(3), np.eye(3)
    a, b = (x2n, x1n) if transpose else (x1n, x2n)
    u1, v1 = a.T
    u2, v2 = b.T
    A = np.stack([u2 * u1, u2 * v1, u2, v2 * u1, v2 * v1, v2, u1, v1, np.ones_like(u1)], axis=1)
    F = np.linalg.svd(A)[2][-1].reshape(3, 3)
    if rank2:
        U, s, Vt = np.linalg.svd(F)
        F = U @ np.diag([s[0], s[1], 0.0]) @ Vt
    Ta, Tb = (T2, T1) if transpose else (T1, T2)
    F = Tb.T @ F @ Ta
    return F / np.linalg.norm(F)


def eight_point_no_rank2(x1, x2):
    return _eight(x1, x2, rank2=False)


def eight_point_unnormalized(x1, x2):
    return _eight(x1, x2, normalize=False)


def eight_point_transposed(x1, x2):
    return _eight(x1, x2, transpose=True)


# -- 01: sampson_distance -----------------------------------------------------------------------
def sampson_squared(F, x1, x2):
    return rfu.sampson_distance(F, x1, x2) ** 2


def sampson_algebraic(F, x1, x2):
    return np.abs(np.sum(_h(x2) * (_h(x1) @ F.T), axis=1))


def sampson_one_sided(F, x1, x2):
    l2 = _h(x1) @ F.T
    return np.abs(np.sum(_h(x2) * l2, axis=1)) / np.hypot(l2[:, 0], l2[:, 1])


# -- 01: ransac_fundamental ---------------------------------------------------------------------
def _ransac(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000, error="sampson", refit=True,
            adaptive=True, own_rng=False):
    n = len(x1)
    best, n_iters, need = None, 0, max_iters
    g = np.random.default_rng() if own_rng else rng
    while n_iters < min(need, max_iters):
        n_iters += 1
        idx = g.choice(n, 8, replace=False)
        F = rfu.eight_point(x1[idx], x2[idx])
        if error == "sampson":
            inl = rfu.sampson_distance(F, x1, x2) < threshold_px
        elif error == "algebraic":
            inl = np.abs(np.sum(_h(x2) * (_h(x1) @ F.T), axis=1)) < threshold_px
        else:
            inl = rfu.sampson_distance(F, x1, x2) ** 2 < threshold_px
        if best is None or inl.sum() > best[1].sum():
            best = (F, inl)
            w = inl.mean()
            if adaptive and 0 < w < 1:
                need = math.log(1 - confidence) / math.log(1 - w**8)
            elif adaptive:
                need = 0
    F, inl = best
    if refit and inl.sum() >= 8:
        F = rfu.eight_point(x1[inl], x2[inl])
    return rfu.RansacResult(F, inl, n_iters)


def ransac_algebraic(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    return _ransac(x1, x2, rng, threshold_px, confidence, max_iters, error="algebraic")


def ransac_no_refit(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    return _ransac(x1, x2, rng, threshold_px, confidence, max_iters, refit=False)


def ransac_fixed_iterations(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    return _ransac(x1, x2, rng, threshold_px, confidence, max_iters, adaptive=False)


def ransac_global_rng(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    return _ransac(x1, x2, rng, threshold_px, confidence, max_iters, own_rng=True)

# ============================================================================ honest solutions
# Written from the textbook (Hartley & Zisserman), not from course_lib; calls of other exercises by name.

def normalize_points(x):
    c = x.mean(axis=0)
    s = np.sqrt(2.0) / np.linalg.norm(x - c, axis=1).mean()
    T = np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])
    return (x - c) * s, T


def eight_point(x1, x2):
    a, T1 = normalize_points(x1)
    b, T2 = normalize_points(x2)
    A = np.stack([b[:, 0] * a[:, 0], b[:, 0] * a[:, 1], b[:, 0], b[:, 1] * a[:, 0], b[:, 1] * a[:, 1],
                  b[:, 1], a[:, 0], a[:, 1], np.ones(len(a))], axis=1)
    F = np.linalg.svd(A)[2][-1].reshape(3, 3)
    U, s, Vt = np.linalg.svd(F)
    F = T2.T @ (U @ np.diag([s[0], s[1], 0.0]) @ Vt) @ T1
    return F / np.linalg.norm(F)


def sampson_distance(F, x1, x2):
    x1h = np.column_stack([x1, np.ones(len(x1))])
    x2h = np.column_stack([x2, np.ones(len(x2))])
    Fx1, Ftx2 = x1h @ F.T, x2h @ F
    e = np.sum(x2h * Fx1, axis=1)
    return np.abs(e) / np.sqrt(Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2)


def ransac_fundamental(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    n = len(x1)
    best = np.zeros(n, bool)
    n_iters, needed = 0, max_iters
    while n_iters < min(needed, max_iters):
        idx = rng.choice(n, 8, replace=False)
        inl = sampson_distance(eight_point(x1[idx], x2[idx]), x1, x2) < threshold_px
        n_iters += 1
        if inl.sum() > best.sum():
            best = inl
            w = inl.mean()
            needed = np.log(1 - confidence) / np.log(1 - w**8) if w < 1 else 0
    return eight_point(x1[best], x2[best]), best, n_iters


# ============================================================================ the catalogue

M = Mistake
MISTAKES = [
    M("normalize_points", "centroid not removed", gfu.check_normalize_points, normalize_no_centroid,
      ("subtract the mean",)),
    M("normalize_points", "mean distance 1", gfu.check_normalize_points, normalize_mean_one, ("mean distance is 1",)),
    M("normalize_points", "one scale per axis", gfu.check_normalize_points, normalize_two_scales,
      ("different scales",)),
    M("normalize_points", "T inverted", gfu.check_normalize_points, normalize_T_inverted, ("t is the inverse",)),
    M("eight_point", "no rank-2 step", gfu.check_eight_point, eight_point_no_rank2, ("rank 3", "enforce rank 2"),
      defining="rank 2"),
    M("eight_point", "not normalized", gfu.check_eight_point, eight_point_unnormalized, ("not normalized",)),
    M("eight_point", "F transposed", gfu.check_eight_point, eight_point_transposed, ("transposed f",)),
    M("sampson_distance", "squared error", gfu.check_sampson_distance, sampson_squared, ("squared error",)),
    M("sampson_distance", "algebraic error", gfu.check_sampson_distance, sampson_algebraic, ("algebraic error",)),
    M("sampson_distance", "one-sided distance", gfu.check_sampson_distance, sampson_one_sided,
      ("its epipolar line only",)),
    M("ransac_fundamental", "threshold on the algebraic error", gfu.check_ransac_fundamental, ransac_algebraic,
      ("algebraic error", "sampson_distance(f, x1, x2) < threshold_px")),
    M("ransac_fundamental", "no final refit", gfu.check_ransac_fundamental, ransac_no_refit, ("refit",)),
    M("ransac_fundamental", "fixed iteration count", gfu.check_ransac_fundamental, ransac_fixed_iterations,
      ("n_iters = 2000",)),
    M("ransac_fundamental", "np.random instead of rng", gfu.check_ransac_fundamental, ransac_global_rng,
      ("from the rng argument",)),
]

#: Correct solutions: they must score full marks.
HONEST = [
    Honest("normalize_points", "textbook", gfu.check_normalize_points, normalize_points),
    Honest("eight_point", "textbook", gfu.check_eight_point, eight_point),
    Honest("sampson_distance", "textbook", gfu.check_sampson_distance, sampson_distance),
    Honest("ransac_fundamental", "textbook, returns a tuple", gfu.check_ransac_fundamental, ransac_fundamental),
    Honest("normalize_points", "the reference solution", gfu.check_normalize_points, rfu.normalize_points),
    Honest("eight_point", "the reference solution", gfu.check_eight_point, rfu.eight_point),
    Honest("sampson_distance", "the reference solution", gfu.check_sampson_distance, rfu.sampson_distance),
    Honest("ransac_fundamental", "the reference solution", gfu.check_ransac_fundamental, rfu.ransac_fundamental),
]


def _trivial() -> list:
    z = np.zeros  # noqa: F841
    return [
        (gfu.check_normalize_points, lambda x: (z(x.shape), np.eye(3))),
        (gfu.check_normalize_points, lambda x: (x.copy(), np.eye(3))),
        (gfu.check_eight_point, lambda x1, x2: np.eye(3)),
        (gfu.check_eight_point, lambda x1, x2: np.diag([1.0, 1.0, 0.0]) / np.sqrt(2)),
        (gfu.check_sampson_distance, lambda F, x1, x2: np.ones(len(x1))),
        (gfu.check_ransac_fundamental, lambda x1, x2, rng, threshold_px=1.0, **k: (np.eye(3), np.ones(len(x1), bool), 1)),
    ]


#: Constants of the right shape: they pass the shape gates and trivially satisfied properties, and must earn nothing.
TRIVIAL = _trivial()

"""Notebook 01 (the fundamental matrix): classic mistakes, honest solutions and trivial answers, run through its checks."""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np

from course_lib.checks import fundamental as gfu
from course_lib.sfm import fundamental as rfu
from tests.checks.catalogue import Honest, Mistake, _h

# ============================================================================ buggy versions
# Each is written as a student would write it; calls of earlier exercises use the reference, as the
# grader's hidden checks feed every exercise the reference's earlier steps.

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


def normalize_rms(x):
    c = x.mean(0)
    s = np.sqrt(2) / np.sqrt(np.mean(np.sum((x - c) ** 2, axis=1)))
    T = np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1.0]])
    return (x - c) * s, T


def normalize_uncentred_scale(x):  # near miss: the scale from the distances to the origin of the image
    c = x.mean(0)
    s = np.sqrt(2) / np.linalg.norm(x, axis=1).mean()
    T = np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1.0]])
    return (x - c) * s, T


def normalize_homogeneous(x):
    xn, T = rfu.normalize_points(x)
    return np.column_stack([xn, np.ones(len(xn))]), T


# -- 01: eight_point ----------------------------------------------------------------------------
def _eight(x1, x2, normalize=True, rank2=True, transpose=False, denorm="right"):
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
    if denorm == "right":
        F = Tb.T @ F @ Ta
    elif denorm == "swapped":
        F = Ta.T @ F @ Tb
    elif denorm == "inverse":
        F = np.linalg.inv(Tb).T @ F @ np.linalg.inv(Ta)
    return F / np.linalg.norm(F)


def eight_point_no_rank2(x1, x2):
    return _eight(x1, x2, rank2=False)


def eight_point_unnormalized(x1, x2):
    return _eight(x1, x2, normalize=False)


def eight_point_transposed(x1, x2):
    return _eight(x1, x2, transpose=True)


def eight_point_not_denormalized(x1, x2):
    return _eight(x1, x2, denorm="none")


def eight_point_denormalized_swapped(x1, x2):
    return _eight(x1, x2, denorm="swapped")


def eight_point_denormalized_inverse(x1, x2):
    return _eight(x1, x2, denorm="inverse")


# -- 01: sampson_distance -----------------------------------------------------------------------
def sampson_squared(F, x1, x2):
    return rfu.sampson_distance(F, x1, x2) ** 2


def sampson_algebraic(F, x1, x2):
    return np.abs(np.sum(_h(x2) * (_h(x1) @ F.T), axis=1))


def sampson_one_sided(F, x1, x2):
    l2 = _h(x1) @ F.T
    return np.abs(np.sum(_h(x2) * l2, axis=1)) / np.hypot(l2[:, 0], l2[:, 1])


def sampson_symmetric(F, x1, x2):  # near miss: the symmetric epipolar distance
    l2, l1 = _h(x1) @ F.T, _h(x2) @ F
    e = np.abs(np.sum(_h(x2) * l2, axis=1))
    return e / np.hypot(l2[:, 0], l2[:, 1]) + e / np.hypot(l1[:, 0], l1[:, 1])


def sampson_wrong_gradient(F, x1, x2):  # near miss: F x2 in place of Fᵀ x2
    l2, l1 = _h(x1) @ F.T, _h(x2) @ F.T
    e = np.sum(_h(x2) * l2, axis=1)
    return np.abs(e) / np.sqrt(l2[:, 0] ** 2 + l2[:, 1] ** 2 + l1[:, 0] ** 2 + l1[:, 1] ** 2)


def sampson_signed(F, x1, x2):
    l2, l1 = _h(x1) @ F.T, _h(x2) @ F
    e = np.sum(_h(x2) * l2, axis=1)
    return e / np.sqrt(l2[:, 0] ** 2 + l2[:, 1] ** 2 + l1[:, 0] ** 2 + l1[:, 1] ** 2)


# -- 01: ransac_fundamental ---------------------------------------------------------------------
def _ransac(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000, error="sampson", refit=True,
            adaptive=True, own_rng=False, use_confidence=True, cap=True):
    n = len(x1)
    best, n_iters, need = None, 0, max_iters
    g = np.random.default_rng() if own_rng else rng
    p = confidence if use_confidence else 0.999

    def inliers_of(F):
        if error == "sampson":
            return rfu.sampson_distance(F, x1, x2) < threshold_px
        if error == "algebraic":
            return np.abs(np.sum(_h(x2) * (_h(x1) @ F.T), axis=1)) < threshold_px
        return rfu.sampson_distance(F, x1, x2) ** 2 < threshold_px

    while n_iters < (min(need, max_iters) if cap else need):
        n_iters += 1
        idx = (np.random.choice(n, 8, replace=False) if own_rng == "global" else g.choice(n, 8, replace=False))
        F = rfu.eight_point(x1[idx], x2[idx])
        inl = inliers_of(F)
        if best is None or inl.sum() > best[1].sum():
            best = (F, inl)
            w = inl.mean()
            if adaptive and 0 < w < 1:
                need = math.log(1 - p) / math.log1p(-(w**8))  # log1p: 1 - w**8 rounds to 1 for a tiny w
            elif adaptive:
                need = 0
    F, inl = best
    if refit and inl.sum() >= 8:
        F = rfu.eight_point(x1[inl], x2[inl])
        inl = inliers_of(F)
    return rfu.RansacResult(F, inl, n_iters)


def ransac_algebraic(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    return _ransac(x1, x2, rng, threshold_px, confidence, max_iters, error="algebraic")


def ransac_squared(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    return _ransac(x1, x2, rng, threshold_px, confidence, max_iters, error="squared")


def ransac_no_refit(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    return _ransac(x1, x2, rng, threshold_px, confidence, max_iters, refit=False)


def ransac_fixed_iterations(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    return _ransac(x1, x2, rng, threshold_px, confidence, max_iters, adaptive=False)


def ransac_own_rng(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    return _ransac(x1, x2, rng, threshold_px, confidence, max_iters, own_rng=True)


def ransac_global_np_random(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    return _ransac(x1, x2, rng, threshold_px, confidence, max_iters, own_rng="global")


def ransac_ignores_confidence(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    return _ransac(x1, x2, rng, threshold_px, confidence, max_iters, use_confidence=False)


def ransac_ignores_max_iters(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    return _ransac(x1, x2, rng, threshold_px, confidence, max_iters, cap=False)


# ============================================================================ honest solutions
# Written from the textbook (Hartley & Zisserman), not from course_lib; calls of other exercises by name.

def normalize_points(x):
    c = x.mean(axis=0)
    s = np.sqrt(2.0) / np.linalg.norm(x - c, axis=1).mean()
    T = np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])
    return (x - c) * s, T


def normalize_points__composed_matrices(x):
    """Another style: T as scale @ translation, x_n computed through T in homogeneous coordinates, loops."""
    n = len(x)
    cu = sum(p[0] for p in x) / n
    cv = sum(p[1] for p in x) / n
    mean_dist = sum(math.hypot(p[0] - cu, p[1] - cv) for p in x) / n
    s = math.sqrt(2.0) / mean_dist
    translate = np.array([[1.0, 0.0, -cu], [0.0, 1.0, -cv], [0.0, 0.0, 1.0]])
    scale = np.diag([s, s, 1.0])
    T = scale @ translate
    xh = np.hstack([x, np.ones((n, 1))]) @ T.T
    return xh[:, :2] / xh[:, 2:], T


def eight_point(x1, x2):
    a, T1 = normalize_points(x1)
    b, T2 = normalize_points(x2)
    A = np.stack([b[:, 0] * a[:, 0], b[:, 0] * a[:, 1], b[:, 0], b[:, 1] * a[:, 0], b[:, 1] * a[:, 1],
                  b[:, 1], a[:, 0], a[:, 1], np.ones(len(a))], axis=1)
    F = np.linalg.svd(A)[2][-1].reshape(3, 3)
    U, s, Vt = np.linalg.svd(F)
    F = T2.T @ (U @ np.diag([s[0], s[1], 0.0]) @ Vt) @ T1
    return F / np.linalg.norm(F)


def eight_point__kron_rows_eig(x1, x2):
    """Another style: rows of A as Kronecker products, the null vector from the eigenvectors of AᵀA, sign fixed."""
    a, T1 = normalize_points(x1)
    b, T2 = normalize_points(x2)
    rows = [np.kron(np.append(q, 1.0), np.append(p, 1.0)) for p, q in zip(a, b)]
    A = np.array(rows)
    w, V = np.linalg.eigh(A.T @ A)
    Fn = V[:, np.argmin(w)].reshape(3, 3)
    U, s, Vt = np.linalg.svd(Fn)
    s[2] = 0.0
    F = T2.T @ U @ np.diag(s) @ Vt @ T1
    F = F / np.linalg.norm(F)
    return F if F.flat[np.argmax(np.abs(F))] > 0 else -F


def sampson_distance(F, x1, x2):
    x1h = np.column_stack([x1, np.ones(len(x1))])
    x2h = np.column_stack([x2, np.ones(len(x2))])
    Fx1, Ftx2 = x1h @ F.T, x2h @ F
    e = np.sum(x2h * Fx1, axis=1)
    return np.abs(e) / np.sqrt(Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2)


def sampson_distance__loop_einsum(F, x1, x2):
    """Another style: one match at a time, the error as x2ᵀ F x1 with einsum, Sampson's error then its root."""
    out = np.empty(len(x1))
    for k in range(len(x1)):
        p = np.array([x1[k][0], x1[k][1], 1.0])
        q = np.array([x2[k][0], x2[k][1], 1.0])
        e = np.einsum("i,ij,j->", q, F, p)
        l2, l1 = F @ p, F.T @ q
        out[k] = math.sqrt(e * e / (l2[0] ** 2 + l2[1] ** 2 + l1[0] ** 2 + l1[1] ** 2))
    return out


def sampson_distance__opencv(F, x1, x2):
    """The route notebook 01 offers to skip the exercise: OpenCV's Sampson error, its root, one match at a time."""
    import cv2

    return np.sqrt([cv2.sampsonDistance(np.append(a, 1.0), np.append(b, 1.0), F) for a, b in zip(x1, x2)])


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
    F = eight_point(x1[best], x2[best])
    return F, sampson_distance(F, x1, x2) < threshold_px, n_iters


Result = namedtuple("Result", "F inliers n_iters")


def ransac_fundamental__for_loop(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    """Another style: a for loop with break, permutation samples, ceil of N, a namedtuple."""
    best_inl, best_count, n_iters = None, -1, 0
    limit = max_iters
    for i in range(max_iters):
        if i >= limit:
            break
        sample = rng.permutation(len(x1))[:8]
        F = eight_point(x1[sample], x2[sample])
        inl = sampson_distance(F, x1, x2) < threshold_px
        n_iters = i + 1
        if inl.sum() > best_count:
            best_inl, best_count = inl, int(inl.sum())
            w = best_count / len(x1)
            limit = max_iters if w == 0 else (0 if w == 1 else math.ceil(math.log(1 - confidence) / math.log(1 - w**8)))
    F = eight_point(x1[best_inl], x2[best_inl])
    return Result(F, sampson_distance(F, x1, x2) < threshold_px, n_iters)


def ransac_best_sample_mask(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    """The refit F with the best sample's inlier mask (the docstring asks for the refit F's inliers)."""
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
    M("normalize_points", "mean distance 1", gfu.check_normalize_points, normalize_mean_one, ("mean distance to the centroid is 1",)),
    M("normalize_points", "one scale per axis", gfu.check_normalize_points, normalize_two_scales,
      ("different scales",)),
    M("normalize_points", "T inverted", gfu.check_normalize_points, normalize_T_inverted, ("inverse of t",)),
    M("normalize_points", "RMS distance sqrt(2)", gfu.check_normalize_points, normalize_rms, ("rms distance",)),
    M("normalize_points", "scale from the uncentred points", gfu.check_normalize_points, normalize_uncentred_scale,
      ("uncentred points",)),
    M("normalize_points", "homogeneous points returned", gfu.check_normalize_points, normalize_homogeneous,
      ("drop the homogeneous 1",)),
    M("eight_point", "no rank-2 step", gfu.check_eight_point, eight_point_no_rank2, ("rank 3", "zero the smallest singular value"),
      defining="rank 2"),
    M("eight_point", "not normalized", gfu.check_eight_point, eight_point_unnormalized, ("not normalized",)),
    M("eight_point", "F transposed", gfu.check_eight_point, eight_point_transposed, ("f is transposed",)),
    M("eight_point", "not denormalized", gfu.check_eight_point, eight_point_not_denormalized,
      ("still in normalized coordinates",)),
    M("eight_point", "denormalized T1ᵀ F T2", gfu.check_eight_point, eight_point_denormalized_swapped,
      ("wrong way round",)),
    M("eight_point", "denormalized with the inverses", gfu.check_eight_point, eight_point_denormalized_inverse,
      ("with the inverses",)),
    M("sampson_distance", "squared error", gfu.check_sampson_distance, sampson_squared, ("squared error",)),
    M("sampson_distance", "algebraic error", gfu.check_sampson_distance, sampson_algebraic, ("algebraic error",)),
    M("sampson_distance", "one-sided distance", gfu.check_sampson_distance, sampson_one_sided,
      ("its epipolar line f x1 only",)),
    M("sampson_distance", "symmetric epipolar distance", gfu.check_sampson_distance, sampson_symmetric,
      ("symmetric epipolar distance",)),
    M("sampson_distance", "F x2 for Fᵀ x2", gfu.check_sampson_distance, sampson_wrong_gradient, ("you took f x2",)),
    M("sampson_distance", "signed distance", gfu.check_sampson_distance, sampson_signed, ("absolute value",)),
    M("ransac_fundamental", "threshold on the algebraic error", gfu.check_ransac_fundamental, ransac_algebraic,
      ("algebraic error", "sampson_distance(f, x1, x2) < threshold_px")),
    M("ransac_fundamental", "threshold on the squared distance", gfu.check_ransac_fundamental, ransac_squared,
      ("squared sampson distance",)),
    M("ransac_fundamental", "no final refit", gfu.check_ransac_fundamental, ransac_no_refit, ("refit",)),
    M("ransac_fundamental", "fixed iteration count", gfu.check_ransac_fundamental, ransac_fixed_iterations,
      ("n_iters = 2000",)),
    M("ransac_fundamental", "a generator of its own", gfu.check_ransac_fundamental, ransac_own_rng,
      ("from the rng argument",)),
    M("ransac_fundamental", "np.random instead of rng", gfu.check_ransac_fundamental, ransac_global_np_random,
      ("from the rng argument",)),
    M("ransac_fundamental", "confidence ignored", gfu.check_ransac_fundamental, ransac_ignores_confidence,
      ("must follow the confidence argument",)),
    M("ransac_fundamental", "max_iters ignored", gfu.check_ransac_fundamental, ransac_ignores_max_iters,
      ("at most max_iters",)),
    M("ransac_fundamental", "the best sample's inlier mask", gfu.check_ransac_fundamental, ransac_best_sample_mask,
      ("recompute the inliers with the final f",)),
]

#: Correct solutions: they must score full marks.
HONEST = [
    Honest("normalize_points", "textbook", gfu.check_normalize_points, normalize_points),
    Honest("normalize_points", "composed matrices, loops", gfu.check_normalize_points,
           normalize_points__composed_matrices),
    Honest("eight_point", "textbook", gfu.check_eight_point, eight_point),
    Honest("eight_point", "Kronecker rows, eigh of AᵀA, sign fixed", gfu.check_eight_point, eight_point__kron_rows_eig),
    Honest("sampson_distance", "textbook", gfu.check_sampson_distance, sampson_distance),
    Honest("sampson_distance", "loop, einsum, root of Sampson's error", gfu.check_sampson_distance,
           sampson_distance__loop_einsum),
    Honest("ransac_fundamental", "textbook, returns a tuple", gfu.check_ransac_fundamental, ransac_fundamental),
    Honest("ransac_fundamental", "for loop, permutation samples, namedtuple", gfu.check_ransac_fundamental,
           ransac_fundamental__for_loop),
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


# ============================================================================ issue 29: written as students write them
# Each from the notebook's text and the stub's docstring, with an error students make (not from the checks'
# messages); calls of earlier exercises use the reference, as in grading. Then correct variants in other
# valid forms and conventions (F / F[2, 2], -F, float32, one normalization for both images, ...).

def normalize_points_std(x):  # "mean distance sqrt(2)" read as "standard deviation sqrt(2)"
    c = x.mean(axis=0)
    s = np.sqrt(2) / np.std(x - c)
    T = np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1]])
    return (x - c) * s, T


def normalize_points_inverted_ratio(x):  # s = mean distance / sqrt(2): the ratio upside down
    c = x.mean(axis=0)
    d = np.linalg.norm(x - c, axis=1).mean()
    s = d / np.sqrt(2)
    T = np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1]])
    return (x - c) * s, T


def normalize_points_translation_unscaled(x):  # x_n right, but T translates by -c, not -s c
    c = x.mean(axis=0)
    s = np.sqrt(2) / np.mean(np.sqrt(((x - c) ** 2).sum(axis=1)))
    T = np.array([[s, 0, -c[0]], [0, s, -c[1]], [0, 0, 1]])
    return s * (x - c), T


def normalize_points_scaled_not_centred(x):  # pixels scaled, never centred: both the scale and x_n use raw x
    s = np.sqrt(2) / np.linalg.norm(x, axis=1).mean()
    T = np.diag([s, s, 1.0])
    return x * s, T


def normalize_points_max_distance(x):  # the largest distance becomes sqrt(2)
    c = x.mean(axis=0)
    s = np.sqrt(2) / np.linalg.norm(x - c, axis=1).max()
    T = np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1]])
    return (x - c) * s, T


def _rows(a, b):
    u1, v1 = a[:, 0], a[:, 1]
    u2, v2 = b[:, 0], b[:, 1]
    return np.stack([u2 * u1, u2 * v1, u2, v2 * u1, v2 * v1, v2, u1, v1, np.ones(len(a))], axis=1)


def eight_point_rank2_after_denormalizing(x1, x2):  # the rank-2 step in pixels, after T2ᵀ F T1
    a, T1 = rfu.normalize_points(x1)
    b, T2 = rfu.normalize_points(x2)
    F = np.linalg.svd(_rows(a, b))[2][-1].reshape(3, 3)
    F = T2.T @ F @ T1
    U, S, Vt = np.linalg.svd(F)
    S[2] = 0
    F = U @ np.diag(S) @ Vt
    return F / np.linalg.norm(F)


def eight_point_column_of_vt(x1, x2):  # the null vector read as the last COLUMN of Vt (MATLAB's V(:, end))
    a, T1 = rfu.normalize_points(x1)
    b, T2 = rfu.normalize_points(x2)
    U, S, Vt = np.linalg.svd(_rows(a, b))
    F = Vt[:, -1].reshape(3, 3)
    U, S, Vt = np.linalg.svd(F)
    S[2] = 0
    F = T2.T @ U @ np.diag(S) @ Vt @ T1
    return F / np.linalg.norm(F)


def eight_point_zeroes_largest(x1, x2):  # "zero the smallest singular value" with S assumed ascending
    a, T1 = rfu.normalize_points(x1)
    b, T2 = rfu.normalize_points(x2)
    F = np.linalg.svd(_rows(a, b))[2][-1].reshape(3, 3)
    U, S, Vt = np.linalg.svd(F)
    S[0] = 0
    F = T2.T @ U @ np.diag(S) @ Vt @ T1
    return F / np.linalg.norm(F)


def eight_point_first_eight(x1, x2):  # "8-point": only the first 8 matches go into A
    a, T1 = rfu.normalize_points(x1[:8])
    b, T2 = rfu.normalize_points(x2[:8])
    F = np.linalg.svd(_rows(a, b))[2][-1].reshape(3, 3)
    U, S, Vt = np.linalg.svd(F)
    F = T2.T @ U @ np.diag([S[0], S[1], 0]) @ Vt @ T1
    return F / np.linalg.norm(F)


def sampson_numerator_swapped(F, x1, x2):  # x1ᵀ F x2 on top, the right lines below
    h1, h2 = _h(x1), _h(x2)
    num = np.einsum("ni,ij,nj->n", h1, F, h2)
    Fx1, Ftx2 = h1 @ F.T, h2 @ F
    return np.abs(num) / np.sqrt(Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2)


def sampson_lines_transposed(F, x1, x2):  # the lines as Fᵀ x1 and F x2 (row-vector confusion), numerator right
    h1, h2 = _h(x1), _h(x2)
    num = np.sum(h2 * (h1 @ F.T), axis=1)
    l2, l1 = h1 @ F, h2 @ F.T
    return np.abs(num) / np.sqrt(l2[:, 0] ** 2 + l2[:, 1] ** 2 + l1[:, 0] ** 2 + l1[:, 1] ** 2)


def sampson_mean(F, x1, x2):  # returns the mean distance, one number
    h1, h2 = _h(x1), _h(x2)
    Fx1, Ftx2 = h1 @ F.T, h2 @ F
    e = np.sum(h2 * Fx1, axis=1)
    return float(np.mean(np.abs(e) / np.sqrt(Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2)))


def sampson_in_normalized_coordinates(F, x1, x2):  # normalizes the points first "for stability": no longer pixels
    a, T1 = rfu.normalize_points(x1)
    b, T2 = rfu.normalize_points(x2)
    Fn = np.linalg.inv(T2).T @ F @ np.linalg.inv(T1)
    h1, h2 = _h(a), _h(b)
    l2, l1 = h1 @ Fn.T, h2 @ Fn
    e = np.sum(h2 * l2, axis=1)
    return np.abs(e) / np.sqrt(l2[:, 0] ** 2 + l2[:, 1] ** 2 + l1[:, 0] ** 2 + l1[:, 1] ** 2)


def _ransac29(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000, rule="right", own=None,
              bad_formula=False):
    g = rng
    if own == "seeded":
        g = np.random.default_rng(0)
    elif own == "global":
        np.random.seed(0)
    n = len(x1)
    best_inl, n_iters, N = np.zeros(n, bool), 0, max_iters
    while n_iters < min(N, max_iters):
        idx = np.random.choice(n, 8, replace=False) if own == "global" else g.choice(n, 8, replace=False)
        d = rfu.sampson_distance(rfu.eight_point(x1[idx], x2[idx]), x1, x2)
        inl = d < threshold_px**2 if rule == "squared_threshold" else d < threshold_px
        n_iters += 1
        if inl.sum() > best_inl.sum():
            best_inl = inl
            w = inl.mean()
            if w >= 1:
                N = 0
            elif bad_formula:
                N = math.log(1 - confidence) / math.log(1 - w) ** 8
            else:
                N = math.log(1 - confidence) / math.log(1 - w**8)
    F = rfu.eight_point(x1[best_inl], x2[best_inl])
    d = rfu.sampson_distance(F, x1, x2)
    return rfu.RansacResult(F, d < threshold_px**2 if rule == "squared_threshold" else d < threshold_px, n_iters)


def ransac_threshold_squared(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):  # d < thr²
    return _ransac29(x1, x2, rng, threshold_px, confidence, max_iters, rule="squared_threshold")


def ransac_own_seeded_generator(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    return _ransac29(x1, x2, rng, threshold_px, confidence, max_iters, own="seeded")  # default_rng(0), rng unused


def ransac_seeds_global(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    return _ransac29(x1, x2, rng, threshold_px, confidence, max_iters, own="global")  # np.random.seed(0) inside


def ransac_count_formula_parenthesized(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    return _ransac29(x1, x2, rng, threshold_px, confidence, max_iters, bad_formula=True)  # log(1 - w) ** 8


# -- valid variants (issue 29: every one full marks through the real grader) -------------------------------------
def _unit_f(x1, x2):
    """The normalized 8-point F of unit norm (written inline: no call of the exercise itself)."""
    a, T1 = normalize_points(x1)
    b, T2 = normalize_points(x2)
    F = np.linalg.svd(_rows(a, b))[2][-1].reshape(3, 3)
    U, S, Vt = np.linalg.svd(F)
    return T2.T @ U @ np.diag([S[0], S[1], 0]) @ Vt @ T1


def eight_point__f33_one(x1, x2):
    """F scaled so that F[2, 2] = 1 (the other common normalization of F)."""
    F = _unit_f(x1, x2)
    return F / F[2, 2]


def eight_point__negated(x1, x2):
    """-F of unit norm, the sign not fixed: F is defined up to sign."""
    F = _unit_f(x1, x2)
    F = F / np.linalg.norm(F)
    return -F if F.flat[np.argmax(np.abs(F))] > 0 else F


def eight_point__float32(x1, x2):
    """The whole computation in float32."""
    x1, x2 = x1.astype(np.float32), x2.astype(np.float32)
    a, T1 = normalize_points__float32(x1)
    b, T2 = normalize_points__float32(x2)
    A = _rows(a, b).astype(np.float32)
    F = np.linalg.svd(A)[2][-1].reshape(3, 3)
    U, S, Vt = np.linalg.svd(F)
    F = T2.T @ U @ np.diag(np.array([S[0], S[1], 0], np.float32)) @ Vt @ T1
    return (F / np.linalg.norm(F)).astype(np.float32)


def eight_point__one_normalization(x1, x2):
    """One similarity for both images (from all the points of both): still a valid normalization."""
    a, T = normalize_points(np.vstack([x1, x2]))
    n = len(x1)
    F = np.linalg.svd(_rows(a[:n], a[n:]))[2][-1].reshape(3, 3)
    U, S, Vt = np.linalg.svd(F)
    F = T.T @ U @ np.diag([S[0], S[1], 0]) @ Vt @ T
    return F / np.linalg.norm(F)


def normalize_points__float32(x):
    """float32 throughout."""
    x = np.asarray(x, np.float32)
    c = x.mean(axis=0)
    s = np.float32(np.sqrt(2)) / np.linalg.norm(x - c, axis=1).mean()
    T = np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1]], np.float32)
    return ((x - c) * s).astype(np.float32), T


def sampson_distance__float32(F, x1, x2):
    """float32 throughout, Sampson's error then its root."""
    F = F.astype(np.float32)
    h1 = np.column_stack([x1, np.ones(len(x1))]).astype(np.float32)
    h2 = np.column_stack([x2, np.ones(len(x2))]).astype(np.float32)
    Fx1, Ftx2 = h1 @ F.T, h2 @ F
    e = np.sum(h2 * Fx1, axis=1)
    return np.sqrt(e**2 / (Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2))


def ransac_fundamental__ties_kept(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    """Samples from rng.permutation, a sample as good as the best replaces it (>=), inliers by <=, N rounded up."""
    n, best, n_iters, N = len(x1), None, 0, max_iters
    while n_iters < min(N, max_iters):
        idx = rng.permutation(n)[:8]
        n_iters += 1
        inl = sampson_distance(eight_point(x1[idx], x2[idx]), x1, x2) <= threshold_px
        if best is None or inl.sum() >= best.sum():
            best = inl
            w = inl.mean()
            N = 0 if w == 1 else (max_iters if w == 0 else np.ceil(np.log(1 - confidence) / np.log(1 - w**8)))
    F = eight_point(x1[best], x2[best])
    return F, sampson_distance(F, x1, x2) <= threshold_px, n_iters


MISTAKES += [
    M("normalize_points", "std of the coordinates sqrt(2)", gfu.check_normalize_points, normalize_points_std,
      ("mean distance",), batch="29"),
    M("normalize_points", "scale ratio upside down", gfu.check_normalize_points, normalize_points_inverted_ratio,
      ("mean distance",), batch="29"),
    M("normalize_points", "T translates by -c, not -s c", gfu.check_normalize_points,
      normalize_points_translation_unscaled, ("translates by -c",), batch="29"),
    M("normalize_points", "scaled but not centred", gfu.check_normalize_points, normalize_points_scaled_not_centred,
      ("centroid",), batch="29"),
    M("normalize_points", "largest distance sqrt(2)", gfu.check_normalize_points, normalize_points_max_distance,
      ("mean distance",), batch="29"),
    M("eight_point", "rank 2 enforced after denormalizing", gfu.check_eight_point,
      eight_point_rank2_after_denormalizing, ("epipolar",), batch="29"),
    M("eight_point", "null vector from a column of Vt", gfu.check_eight_point, eight_point_column_of_vt,
      ("epipolar",), batch="29"),
    M("eight_point", "largest singular value zeroed", gfu.check_eight_point, eight_point_zeroes_largest,
      ("epipolar",), batch="29"),
    M("eight_point", "only the first 8 matches", gfu.check_eight_point, eight_point_first_eight, ("epipolar",),
      batch="29"),
    M("sampson_distance", "numerator x1ᵀ F x2", gfu.check_sampson_distance, sampson_numerator_swapped,
      ("sampson",), batch="29"),
    M("sampson_distance", "lines Fᵀ x1 and F x2", gfu.check_sampson_distance, sampson_lines_transposed,
      ("sampson",), batch="29"),
    M("sampson_distance", "the mean, one number", gfu.check_sampson_distance, sampson_mean, ("shape",), batch="29"),
    M("sampson_distance", "in normalized coordinates", gfu.check_sampson_distance,
      sampson_in_normalized_coordinates, ("sampson",), batch="29"),
    M("ransac_fundamental", "d < threshold²", gfu.check_ransac_fundamental, ransac_threshold_squared,
      ("threshold",), batch="29"),
    M("ransac_fundamental", "own default_rng(0)", gfu.check_ransac_fundamental, ransac_own_seeded_generator,
      ("seed",), batch="29"),
    M("ransac_fundamental", "np.random.seed(0) inside", gfu.check_ransac_fundamental, ransac_seeds_global,
      ("global",), batch="29"),
    M("ransac_fundamental", "N = log(1 - p) / log(1 - w) ** 8", gfu.check_ransac_fundamental,
      ransac_count_formula_parenthesized, ("n_iters",), batch="29"),
]

HONEST += [
    Honest("eight_point", "F / F[2, 2]", gfu.check_eight_point, eight_point__f33_one),
    Honest("eight_point", "-F", gfu.check_eight_point, eight_point__negated),
    Honest("eight_point", "float32 throughout", gfu.check_eight_point, eight_point__float32),
    Honest("eight_point", "one normalization for both images", gfu.check_eight_point, eight_point__one_normalization),
    Honest("normalize_points", "float32 throughout", gfu.check_normalize_points, normalize_points__float32),
    Honest("sampson_distance", "float32 throughout", gfu.check_sampson_distance, sampson_distance__float32),
    Honest("sampson_distance", "OpenCV's sampsonDistance, as the notebook offers", gfu.check_sampson_distance,
           sampson_distance__opencv),
    Honest("ransac_fundamental", "permutation samples, ties kept, <=", gfu.check_ransac_fundamental,
           ransac_fundamental__ties_kept),
]

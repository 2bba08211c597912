"""Checks of notebook 01 (the fundamental matrix): normalization, 8-point, Sampson distance, RANSAC.

Each ``check_*`` function runs the student's function on stored cases (fixture ``fundamental``,
built on the instructor's side by :mod:`course_lib.instructor.cases.fundamental`), compares with
the stored reference results and with properties, and names the likely mistake:

* ``normalize_points``: centroid not removed, mean distance 1 instead of sqrt(2), RMS instead of
  mean distance, separate scales for u and v, the scale measured from the uncentred points, T
  inverted, homogeneous points returned;
* ``eight_point``: points not normalized, F transposed (``x1ᵀ F x2 = 0``), rank 3, not
  denormalized or denormalized the wrong way round (``T1ᵀ F T2``, the inverses, no transpose);
* ``sampson_distance``: squared distance, algebraic error, signed distance, one-sided or
  symmetric epipolar (point-to-line) distance, F transposed, F x2 in place of Fᵀ x2, no square
  root in the denominator, three entries of the lines instead of two;
* ``ransac_fundamental``: inliers counted with the algebraic error or the squared distance, no
  final refit, no adaptive iteration count, ``confidence`` or ``max_iters`` ignored, randomness
  not taken from ``rng``; the inliers of the best sample returned instead of the inliers of the
  refit F is correct RANSAC in another form than the docstring's: a detail.

What a mistake gives on a case is stored with the case (made on the instructor's side by
:mod:`course_lib.instructor.mistakes.fundamental`): this module holds no working variant of any
exercise. Where it needs a distance of its own it uses the point-to-line distance (no exercise of
the notebook) or OpenCV (``cv2.sampsonDistance``, ``cv2.findFundamentalMat``).

Defining property (failing it costs at least half of the points): ``eight_point``'s F has rank 2,
checked on all four cases.

The cases: a noiseless synthetic pair, a noisy one (1 px), a pair with outliers, and a random
subset of the embedded scene's pair (1, 2) (``data/synthetic-building``) when it is present; the
grader builds new ones for every grading run.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from course_lib.checks.core import FAILED, Check, declare_defining, load_fixture

__all__ = [
    "check_normalize_points",
    "check_eight_point",
    "check_sampson_distance",
    "check_ransac_fundamental",
]

FIXTURE = "fundamental"
#: RANSAC threshold used by the check on the synthetic pair with outliers (noise 0.7 px).
CHECK_THRESHOLD_PX = 1.5

declare_defining("eight_point", {
    "rank 2": "a fundamental matrix is singular, so that all epipolar lines meet in the epipole",
})


# --------------------------------------------------------------------------- small helpers


def _h(x: np.ndarray) -> np.ndarray:
    return np.column_stack([x, np.ones(len(x))])


def _unit(F: np.ndarray) -> np.ndarray:
    F = np.asarray(F, float)
    n = np.linalg.norm(F)
    return F / n if n > 0 else F


def _same_up_to_scale(A, B, tol: float = 1e-6) -> bool:
    """True if ``A = λ B`` for some λ ≠ 0 (compared after scaling both to unit norm, either sign)."""
    A, B = _unit(A), _unit(B)
    if A.shape != B.shape or not (np.isfinite(A).all() and np.isfinite(B).all()) or np.linalg.norm(A) == 0:
        return False
    return bool(min(np.abs(A - B).max(), np.abs(A + B).max()) < tol)


def _line_distance_px(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """(N,) mean of the distances of x2 to its epipolar line F x1 and of x1 to Fᵀ x2 (the check's yardstick)."""
    F = np.asarray(F, float)
    l2, l1 = _h(x1) @ F.T, _h(x2) @ F
    e = np.abs(np.sum(_h(x2) * l2, axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        return 0.5 * (e / np.hypot(l2[:, 0], l2[:, 1]) + e / np.hypot(l1[:, 0], l1[:, 1]))


def _consensus(F: np.ndarray, x1: np.ndarray, x2: np.ndarray, threshold_px: float) -> np.ndarray:
    """(N,) bool: the matches whose Sampson distance to F is below the threshold (OpenCV's Sampson)."""
    import cv2

    F = np.ascontiguousarray(F, dtype=np.float64)
    d2 = np.array([cv2.sampsonDistance(a, b, F) for a, b in zip(_h(x1), _h(x2))])
    return d2 < threshold_px**2


def _as_array(v, c: Check, what: str):
    if v is FAILED:
        return None
    try:
        return np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        c.fail(f"{what} must be a numeric array, got {type(v).__name__}")
        return None


def _rank(F: np.ndarray, T1: np.ndarray, T2: np.ndarray) -> int:
    """Numerical rank of F, in pixels and in the normalized coordinates of the case (``T1``, ``T2``).

    A pixel-scale F has singular values spread over many orders of magnitude, so a full-rank F (the
    8-point result without the rank-2 step) can look rank 2 in pixels; in normalized coordinates
    that test is reliable. The other way round, a matrix such as np.eye(3), full rank in pixels, can
    look rank 2 in normalized coordinates. So rank 2 must hold in both.
    """
    def rank(M):
        s = np.linalg.svd(M, compute_uv=False)
        return int(np.sum(s > 1e-7 * s[0]))

    F = np.asarray(F, float)
    return max(rank(F), rank(np.linalg.inv(T2).T @ F @ np.linalg.inv(T1)))


# --------------------------------------------------------------------------- normalize_points


def _scale_verdict(c: Check, x: np.ndarray, xn: np.ndarray, T: np.ndarray) -> None:
    """The mean-distance check of normalize_points, with the classic scale mistakes named."""
    centroid = xn.mean(0)
    d = np.linalg.norm(xn - centroid, axis=1)
    mean_d, rms_d = d.mean(), np.sqrt((d**2).mean())
    c_x = x.mean(0)
    uncentred = np.sqrt(2) * np.linalg.norm(x - c_x, axis=1).mean() / np.linalg.norm(x, axis=1).mean()
    if np.isclose(mean_d, np.sqrt(2), rtol=1e-6):
        c.expect(True, "the mean distance to the origin is sqrt(2)", "")
    elif not np.isclose(T[0, 0], T[1, 1], rtol=1e-6):
        c.fail("u and v have different scales: use one scale s for both axes (T[0, 0] == T[1, 1]), "
               "s = sqrt(2) / (mean distance to the centroid)")
    elif np.isclose(rms_d, np.sqrt(2), rtol=1e-6):
        c.fail("the RMS distance is sqrt(2) but the mean distance is not: scale so that the *mean* distance "
               "np.linalg.norm(x - c, axis=1).mean() becomes sqrt(2)")
    elif np.isclose(mean_d, 1.0, rtol=1e-6):
        c.fail("the mean distance is 1: Hartley's normalization scales it to sqrt(2) (s = sqrt(2) / mean distance)")
    elif np.isclose(mean_d, uncentred, rtol=1e-6):
        c.fail("the scale is measured from the uncentred points: s = sqrt(2) / (mean distance to the centroid), "
               "np.linalg.norm(x - c, axis=1).mean() with c the mean of the points", named="uncentred_scale")
    else:
        c.fail(f"the mean distance to the origin is {mean_d:.4g}, expected sqrt(2) = 1.4142")


def check_normalize_points(normalize_points: Callable) -> None:
    """Check ``normalize_points(x (N, 2)) -> (x_n (N, 2), T (3, 3))`` (notebook 01).

    Hartley's normalization: centroid at the origin, mean distance sqrt(2), one scale for both
    axes, ``x_n = T x`` in homogeneous coordinates.
    """
    f = load_fixture(FIXTURE)
    x, T_ref = f["norm_x"], f["norm_T"]
    with Check("normalize_points") as c:
        case = f"{len(x)} pixels of a building facade"
        out = c.call(normalize_points, x, case=case)
        if out is FAILED:
            return
        if not isinstance(out, (tuple, list)) or len(out) != 2:
            c.fail(f"{case}: expected a tuple (x_n, T), got {type(out).__name__}")
            return
        xn, T = _as_array(out[0], c, "x_n"), _as_array(out[1], c, "T")
        if xn is None or T is None:
            return
        if xn.shape == (2, len(x)):
            c.fail(f"x_n has shape {xn.shape}: points are rows, return shape (N, 2)")
            return
        if xn.shape == (len(x), 3) and np.allclose(xn[:, 2], 1.0):
            c.fail(f"x_n has shape {xn.shape}: return the 2-D normalized points (drop the homogeneous 1)")
            return
        if not (c.shape(xn, (len(x), 2), "x_n") & c.shape(T, (3, 3), "T")):
            return
        mapped = _h(x) @ T.T
        with np.errstate(divide="ignore", invalid="ignore"):
            mapped = mapped[:, :2] / mapped[:, 2:]
            back = _h(xn) @ T.T
            back = back[:, :2] / back[:, 2:]
        if np.allclose(mapped, xn, atol=1e-8):
            c.gate(True, "x_n = T x (in homogeneous coordinates)", "")
        elif np.allclose(back, x, atol=1e-6):
            c.fail("T is the inverse: it maps x_n back to the pixels; return the T with x_n = T x (pixels to normalized)",
                   named="T_inverse")
        else:
            c.fail("x_n is not T applied to x: T must be the similarity that maps every pixel x to x_n")
        centroid = xn.mean(0)
        c.gate(np.allclose(centroid, 0.0, atol=1e-8), "the centroid of x_n is at the origin",
               f"the centroid of x_n is {np.round(centroid, 3).tolist()}, not (0, 0): subtract the mean of the points")
        _scale_verdict(c, x, xn, T)
        c.expect(np.allclose(T, T_ref, rtol=1e-6, atol=1e-9), "T matches the reference [[s, 0, -s cu], [0, s, -s cv], [0, 0, 1]]",
                 "T differs from the reference [[s, 0, -s cu], [0, s, -s cv], [0, 0, 1]] with s = sqrt(2) / mean distance")


# --------------------------------------------------------------------------- eight_point


_CASE_TEXT = {
    "noiseless": "noiseless synthetic pair",
    "noisy": "noisy synthetic pair (1 px noise)",
    "outliers": "synthetic pair, inliers only",
    "building": "embedded building pair, reference inliers",
}

#: What each stored 8-point mistake (``ep_<case>_mis_<key>``) means.
_EIGHT_POINT_MISTAKES = {
    "transposed": "transposed F: your F satisfies x1ᵀ F x2 = 0; the kit's constraint is x2ᵀ F x1 = 0, so row k of A "
                  "is [u2 u1, u2 v1, u2, v2 u1, v2 v1, v2, u1, v1, 1]",
    "unnormalized": "not normalized: your F equals the 8-point result on raw pixels; normalize both point sets with "
                    "normalize_points, solve, and denormalize F = T2ᵀ F_n T1",
    "no_rank2": "F has rank 3: enforce rank 2 by zeroing the smallest singular value, F = U diag(s1, s2, 0) Vᵀ",
    "not_denormalized": "F is still in normalized coordinates: denormalize, F = T2ᵀ F_n T1",
    "denormalized_swapped": "denormalized the wrong way round: x2 is normalized by T2 and x1 by T1, so F = T2ᵀ F_n T1 "
                            "(not T1ᵀ F_n T2)",
    "denormalized_inverse": "denormalized with the inverses: x_n = T x, so x2ᵀ (T2ᵀ F_n T1) x1 = 0 and F = T2ᵀ F_n T1 "
                            "(no np.linalg.inv)",
    "denormalized_no_transpose": "denormalized without the transpose: F = T2ᵀ F_n T1 (T2.T, not T2)",
}


def _diagnose_F(F, f, p: str, x1, x2) -> tuple[str, str | None]:
    """The likely mistake when F differs from the reference on case ``p`` (text, key); else what failed, with numbers."""
    for key, hint in _EIGHT_POINT_MISTAKES.items():
        if f"{p}_mis_{key}" in f and _same_up_to_scale(F, f[f"{p}_mis_{key}"], 1e-4):
            return hint, key
    if _rank(F, f[f"{p}_T1"], f[f"{p}_T2"]) == 3:
        return _EIGHT_POINT_MISTAKES["no_rank2"], "no_rank2"
    d = np.median(_line_distance_px(F, x1, x2))
    d_ref = np.median(_line_distance_px(f[f"{p}_F"], x1, x2))
    return (f"F does not fit the matches as well as the reference's 8-point F: median distance of the points to their "
            f"epipolar lines {d:.3g} px, reference {d_ref:.3g} px"), None


def check_eight_point(eight_point: Callable) -> None:
    """Check ``eight_point(x1 (N, 2), x2 (N, 2)) -> F (3, 3)`` (notebook 01).

    On each case F must have rank 2 and unit Frobenius norm; on the noiseless pair it must equal
    the reference up to sign; on the noisy pairs its epipolar residuals must be as small as the
    reference's (the unnormalized algorithm fails this).
    """
    f = load_fixture(FIXTURE)
    with Check("eight_point") as c:
        for name in [str(n) for n in f["cases"]]:
            p = f"ep_{name}"
            x1, x2 = f[f"{p}_x1"], f[f"{p}_x2"]
            case = _CASE_TEXT[name]
            F = _as_array(c.call(eight_point, x1, x2, case=case), c, f"{case}: F")
            if F is None:
                continue
            if F.shape in ((9,), (9, 1)):
                c.fail(f"{case}: F has shape {F.shape}: reshape the null vector to (3, 3) (row-major, F.reshape(3, 3))")
                continue
            if not c.shape(F, (3, 3), f"{case}: F"):
                continue
            F_ref = f[f"{p}_F"]
            if name == "noiseless":
                ok, msg = _same_up_to_scale(F, F_ref, 1e-6), f"{case}: F matches the reference (up to scale and sign)"
            else:
                d, d_ref = np.median(_line_distance_px(F, x1, x2)), np.median(_line_distance_px(F_ref, x1, x2))
                ok, msg = bool(np.isfinite(d) and d <= 1.2 * d_ref + 0.02), f"{case}: epipolar residuals as small as the reference's"
            if ok:
                c.expect(True, msg, "")
            else:
                text, key = _diagnose_F(F, f, p, x1, x2)
                c.fail(f"{case}: {text}", named=key)
            c.gate(_rank(F, f[f"{p}_T1"], f[f"{p}_T2"]) == 2, f"{case}: F has rank 2",
                   f"{case}: F has rank 3: enforce rank 2 by zeroing the smallest singular value, "
                   "F = U diag(s1, s2, 0) Vᵀ", defining="rank 2")
            if name in ("noiseless", "noisy"):
                c.gate(np.isclose(np.linalg.norm(F), 1.0, rtol=1e-6), f"{case}: F has unit Frobenius norm",
                       f"{case}: |F| = {np.linalg.norm(F):.4g}: scale F to unit Frobenius norm, F / np.linalg.norm(F)")
        c.blame_earlier("normalize_points", fn=eight_point)


# --------------------------------------------------------------------------- sampson_distance

_SAMPSON_DEN = "d = |x2ᵀ F x1| / sqrt((F x1)₀² + (F x1)₁² + (Fᵀ x2)₀² + (Fᵀ x2)₁²)"
_SYMMETRIC = ("this is a symmetric epipolar distance (the distances of x1 and x2 to their epipolar lines, combined), "
              "not Sampson's: the four squared line entries go under ONE square root, " + _SAMPSON_DEN)

#: What each stored Sampson mistake (``sd_<case>_mis_<key>``) means.
_SAMPSON_MISTAKES = {
    "squared": "you returned Sampson's squared error: take the square root to get a distance in pixels",
    "algebraic": "this is the algebraic error |x2ᵀ F x1|, whose size depends on the scale of F: divide by "
                 "sqrt((F x1)₀² + (F x1)₁² + (Fᵀ x2)₀² + (Fᵀ x2)₁²)",
    "algebraic_unit": "this is the algebraic error |x2ᵀ F x1| of the unit-norm F, which has no unit: divide by "
                      "sqrt((F x1)₀² + (F x1)₁² + (Fᵀ x2)₀² + (Fᵀ x2)₁²)",
    "signed": "signed distances: take the absolute value",
    "one_sided_2": "distance of x2 to its epipolar line F x1 only: Sampson's denominator uses both lines, " + _SAMPSON_DEN,
    "one_sided_1": "distance of x1 to its epipolar line Fᵀ x2 only: Sampson's denominator uses both lines, " + _SAMPSON_DEN,
    "symmetric_sum": _SYMMETRIC,
    "symmetric_mean": _SYMMETRIC,
    "symmetric_rms": _SYMMETRIC,
    "symmetric_root": _SYMMETRIC,
    "symmetric_squared": _SYMMETRIC,
    "transposed": "transposed F: the algebraic error is x2ᵀ F x1 (F x1 is the line in image 2)",
    "no_sqrt": "the denominator has no square root: " + _SAMPSON_DEN,
    "wrong_gradient": "the line in image 1 is Fᵀ x2 (x2 @ F for rows), not F x2: " + _SAMPSON_DEN,
    "pixels_not_homogeneous_1": "the denominator uses all three entries of each line: only the first two (the "
                                "derivatives with respect to u and v) belong in it, " + _SAMPSON_DEN,
}

_SD_TEXT = {"outliers": "synthetic pair with outliers ({n} points)",
            "scaled": "embedded pair, F of norm {norm:.0f} and negative sign ({n} points)"}


def check_sampson_distance(sampson_distance: Callable) -> None:
    """Check ``sampson_distance(F (3, 3), x1 (N, 2), x2 (N, 2)) -> (N,)`` in pixels (notebook 01)."""
    f = load_fixture(FIXTURE)
    with Check("sampson_distance") as c:
        for k, name in enumerate(str(n) for n in f["sd_cases"]):
            p = f"sd_{name}"
            F, x1, x2, d_ref = f[f"{p}_F"], f[f"{p}_x1"], f[f"{p}_x2"], f[f"{p}_d"]
            case = _SD_TEXT[name].format(n=len(x1), norm=np.linalg.norm(F))
            d = _as_array(c.call(sampson_distance, F, x1, x2, case=case), c, f"{case}: d")
            if d is None:
                continue
            if d.shape in ((len(x1), 1), (1, len(x1))):
                c.fail(f"{case}: d has shape {d.shape}: return a flat array of shape (N,)")
                continue
            if not c.shape(d, (len(x1),), f"{case}: d"):
                continue
            if np.allclose(d, d_ref, rtol=1e-6, atol=1e-9):
                c.expect(True, f"{case}: distances match the reference (pixels)", "")
            else:
                key = next((key for key, h in _SAMPSON_MISTAKES.items() if f"{p}_mis_{key}" in f
                            and np.allclose(d, f[f"{p}_mis_{key}"], rtol=1e-5, atol=1e-9)), None)
                hint = _SAMPSON_MISTAKES.get(key)
                j = int(np.argmax(np.abs(d - d_ref)))
                c.fail(f"{case}: {hint or f'distances differ from the Sampson distance (match {j}: {d[j]:.4g} px, expected {d_ref[j]:.4g} px): ' + _SAMPSON_DEN}",
                       named=key)
            if k == 0:
                d10 = _as_array(c.call(sampson_distance, -10.0 * F, x1, x2, case=case), c, f"{case}: d")
                usable = d10 is not None and d10.shape == d.shape  # an unusable answer fails the gate too
                c.gate(usable and np.allclose(d10, d, rtol=1e-6, atol=1e-9),
                       f"{case}: the distance does not depend on the scale of F",
                       f"{case}: the result changes when F is multiplied by -10: a distance in pixels must not depend on "
                       "the scale (or sign) of F" if usable else
                       f"{case}: called with -10 F, your function returned nothing usable (expected shape {d.shape})")


# --------------------------------------------------------------------------- ransac_fundamental


def _unpack_ransac(out, c: Check, case: str):
    if out is FAILED:
        return None
    if hasattr(out, "F") and hasattr(out, "inliers"):
        F, inl, n = out.F, out.inliers, getattr(out, "n_iters", None)
    elif isinstance(out, (tuple, list)) and len(out) == 3:
        F, inl, n = out
    else:
        c.fail(f"{case}: expected a RansacResult(F, inliers, n_iters), got {type(out).__name__}")
        return None
    try:
        F, inl = np.asarray(F, float), np.asarray(inl)
    except (TypeError, ValueError):
        c.fail(f"{case}: F must be a numeric (3, 3) array and inliers a bool array")
        return None
    if inl.dtype != bool:
        if inl.ndim == 1 and np.issubdtype(inl.dtype, np.integer) and (inl.size == 0 or inl.max() > 1):
            c.fail(f"{case}: inliers holds indices: return a boolean mask of shape (N,) (True for an inlier)")
            return None
        inl = inl.astype(bool)
    try:
        n = None if n is None else int(n)
    except (TypeError, ValueError):
        n = None
    return F, inl, n


def _jaccard(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def _usable(F, inl, n: int) -> bool:
    F = np.asarray(F, float)
    return F.shape == (3, 3) and np.isfinite(F).all() and np.linalg.norm(F) > 0 and inl.shape == (n,)


def _inlier_rule(F, x1, x2, inl, thr: float, stored: dict) -> str | None:
    """The wrong inlier rule that explains the mask ``inl`` best, or None.

    A rule is named when the mask agrees with it (evaluated with the student's final F, and with the
    reference's final F in ``stored``) clearly better than with the right rule, Sampson distance < thr.
    """
    if not _usable(F, inl, len(x1)):
        return None
    e = np.abs(np.sum(_h(x2) * (_h(x1) @ _unit(F).T), axis=1))
    right = max(_jaccard(inl, _consensus(F, x1, x2, thr)), _jaccard(inl, stored["right"]))
    for key, mine in (("algebraic", e < thr), ("squared", _consensus(F, x1, x2, np.sqrt(thr)))):
        j = max(_jaccard(inl, mine), _jaccard(inl, stored[key]))
        if j >= 0.97 and j > right + 0.02:
            return key
    return None


_RULES = {
    "algebraic": "inliers are counted with the algebraic error |x2ᵀ F x1|, which has no unit: compare the Sampson "
                 "distance with the threshold, sampson_distance(F, x1, x2) < threshold_px",
    "squared": "inliers are counted with the squared Sampson distance: compare the distance itself (pixels), "
               "sampson_distance(F, x1, x2) < threshold_px",
}


def _named_rule(F, x1, x2, inl, thr: float, stored: dict) -> tuple[str | None, bool]:
    """``(the wrong inlier rule that explains the mask, whether the mask is F's own consensus set)``."""
    if not _usable(F, inl, len(x1)):
        return None, False
    agree = lambda m: int((m != inl).sum()) <= 1  # noqa: E731
    if agree(_consensus(F, x1, x2, thr)):
        return None, True
    e = np.abs(np.sum(_h(x2) * (_h(x1) @ _unit(F).T), axis=1))
    if agree(_consensus(F, x1, x2, np.sqrt(thr))):
        return "squared", True
    if agree(e < thr):
        return "algebraic", True
    return _inlier_rule(F, x1, x2, inl, thr, stored), False


def _ransac_main_case(c: Check, f: dict, F, inl, case: str) -> None:
    """Inliers, fit and the form of the mask, on the synthetic pair with outliers."""
    x1, x2, thr = f["rs_x1"], f["rs_x2"], CHECK_THRESHOLD_PX
    true_inl = f["rs_true_inliers"].astype(bool)
    stored = {k: f[f"rs_mask_{k}"].astype(bool) for k in ("right", "squared", "algebraic")}
    prec = float(true_inl[inl].mean()) if inl.any() else 0.0
    rec = float(inl[true_inl].mean())
    named, own = _named_rule(F, x1, x2, inl, thr, stored)
    if named is None and prec >= 0.9 and rec >= 0.8:
        c.expect(True, f"{case}: finds the true inliers (precision >= 90 %, recall >= 80 %)", "")
    elif named is not None:
        c.fail(f"{case}: {_RULES[named]}", named=named)
    elif inl.mean() > 0.97:
        c.fail(f"{case}: almost every match is an inlier ({int(inl.sum())}/{len(inl)}): compare "
               "sampson_distance(F, x1, x2) < threshold_px (pixels) for every match")
    else:
        c.fail(f"{case}: the inliers disagree with the true ones (precision {prec:.0%}, recall {rec:.0%})")
    xt1, xt2 = f["rs_x1_true"][true_inl], f["rs_x2_true"][true_inl]
    d = np.median(_line_distance_px(F, xt1, xt2))
    d_ref = np.median(_line_distance_px(f["rs_F"], xt1, xt2))
    c.expect(bool(np.isfinite(d) and d <= 3.0 * d_ref + 0.3), f"{case}: F fits the true geometry as well as the reference",
             f"{case}: F is off (median epipolar distance of the noiseless points {d:.3g} px, reference {d_ref:.3g} px): "
             + _REFIT_HINT, named="no_refit")
    if named is None:
        c.detail(own, f"{case}: the inliers are those of the refit F",
                 f"{case}: correct RANSAC, but the inliers are not those of the returned F (the best sample's?): the "
                 "docstring asks for the inliers recomputed with the refit F, sampson_distance(F, x1, x2) < threshold_px")


_REFIT_HINT = "refit F with eight_point on all inliers of the best sample at the end"


def _ransac_refit_case(c: Check, fn: Callable, f: dict) -> None:
    """No outliers, 1 px noise, a wide threshold: every match is an inlier, and only the refit F is precise."""
    x1, x2, thr = f["rf_x1"], f["rf_x2"], float(f["rf_threshold_px"])
    case = f"synthetic pair without outliers, 1 px noise ({len(x1)} matches, threshold {thr:g} px)"
    out = _unpack_ransac(c.call(fn, x1, x2, np.random.default_rng(3), threshold_px=thr, case=case), c, case)
    if out is None or not c.shape(out[0], (3, 3), f"{case}: F"):
        return
    d = np.median(_line_distance_px(out[0], f["rf_x1_true"], f["rf_x2_true"]))
    d_ref = np.median(_line_distance_px(f["rf_F"], f["rf_x1_true"], f["rf_x2_true"]))
    c.expect(bool(np.isfinite(d) and d <= 2.0 * d_ref + 0.05), f"{case}: F is refit on all inliers",
             f"{case}: F is as imprecise as the fit of a minimal sample (median epipolar distance of the noiseless points "
             f"{d:.3g} px, the fit of all inliers {d_ref:.3g} px): {_REFIT_HINT}", named="no_refit")


def _ransac_randomness(c: Check, fn: Callable, f: dict, out: tuple, case: str) -> None:
    """The same seed gives the same result, whatever numpy's global state; confidence and max_iters are used."""
    x1, x2, thr = f["rs_x1"], f["rs_x2"], CHECK_THRESHOLD_PX
    state = np.random.get_state()
    try:  # another global state: a function that draws from np.random (not from rng) gives another result
        np.random.seed(20261124)
        again = _unpack_ransac(c.call(fn, x1, x2, np.random.default_rng(0), threshold_px=thr, case=case), c, case)
    finally:
        np.random.set_state(state)
    if again is None:
        return
    same = (again[1].shape == out[1].shape and np.array_equal(again[1], out[1]) and again[0].shape == out[0].shape
            and np.allclose(again[0], out[0]) and again[2] == out[2])
    c.gate(same, f"{case}: the same seed gives the same result",
           f"{case}: two runs with the same seeded rng differ: draw every sample from the rng argument "
           "(rng.choice(N, 8, replace=False)), never from np.random or a generator of your own", named="rng_not_used")
    short = _unpack_ransac(c.call(fn, x1, x2, np.random.default_rng(1), threshold_px=thr, max_iters=3, case=case), c, case)
    if short is not None:
        c.gate(short[2] is not None and short[2] <= 3, f"{case}: max_iters bounds the number of samples",
               f"{case}: max_iters=3 gave n_iters = {short[2]}: stop after at most max_iters samples")
    low = _unpack_ransac(c.call(fn, x1, x2, np.random.default_rng(0), threshold_px=thr, confidence=0.01, case=case), c, case)
    if low is not None and low[2] is not None and out[2] is not None:
        c.gate(low[2] < out[2] or out[2] <= 1, f"{case}: a lower confidence stops earlier",
               f"{case}: confidence=0.01 drew {low[2]} samples, confidence=0.999 drew {out[2]}: use the confidence "
               "argument in N = log(1 - confidence) / log(1 - w⁸)")


def check_ransac_fundamental(ransac_fundamental: Callable) -> None:
    """Check ``ransac_fundamental(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000)`` (notebook 01).

    On a synthetic pair with about 20 % outliers (0.7 px noise, threshold 1.5 px) the inliers must
    match the true inliers, F must fit the noiseless points as well as the reference's and be the
    fit of its inliers, the iteration count must adapt (to the inliers and the confidence, within
    max_iters), and the samples must come from ``rng``. On a subset of the embedded pair the
    inlier set must agree with the reference's.
    """
    f = load_fixture(FIXTURE)
    with Check("ransac_fundamental") as c:
        x1, x2 = f["rs_x1"], f["rs_x2"]
        true_inl = f["rs_true_inliers"].astype(bool)
        case = f"synthetic pair with {int((~true_inl).sum())} outliers among {len(x1)} matches"
        out = _unpack_ransac(c.call(ransac_fundamental, x1, x2, np.random.default_rng(0),
                                    threshold_px=CHECK_THRESHOLD_PX, case=case), c, case)
        if out is not None:
            F, inl, n_iters = out
            if c.shape(F, (3, 3), f"{case}: F") & c.shape(inl, (len(x1),), f"{case}: inliers"):
                _ransac_main_case(c, f, F, inl, case)
                if n_iters is None:
                    c.fail(f"{case}: n_iters is missing: return the number of samples drawn")
                else:
                    c.gate(0 < n_iters < 2000, f"{case}: the number of iterations adapts to the inlier ratio",
                           f"{case}: n_iters = {n_iters}: update the number of iterations after each better sample, "
                           "N = log(1 - confidence) / log(1 - w⁸) with w the best inlier ratio so far, and stop there")
                _ransac_randomness(c, ransac_fundamental, f, out, case)
        _ransac_refit_case(c, ransac_fundamental, f)
        if "rb_x1" in f:
            _ransac_embedded(c, ransac_fundamental, f)
        c.blame_earlier("eight_point", "sampson_distance", fn=ransac_fundamental)


def _ransac_embedded(c: Check, fn: Callable, f: dict) -> None:
    x1, x2 = f["rb_x1"], f["rb_x2"]
    ref_inl = f["rb_inliers"].astype(bool)
    thr = float(f["rb_threshold_px"])
    case = f"embedded building pair, {len(x1)} matches (threshold {thr:g} px)"
    out = _unpack_ransac(c.call(fn, x1, x2, np.random.default_rng(7), threshold_px=thr, case=case), c, case)
    if out is None or not c.shape(out[1], (len(x1),), f"{case}: inliers"):
        return
    inl = out[1]
    n, n_ref, common = int(inl.sum()), int(ref_inl.sum()), int((inl & ref_inl).sum())
    # real matches can have two consensus sets of similar size: ask for about as many inliers as the
    # reference found, most of the reference's among them (not for the same set)
    if 0.85 * n_ref <= n <= 1.25 * n_ref and common >= 0.8 * n_ref:
        c.expect(True, f"{case}: finds about as many inliers as the reference, most of them the same", "")
        return
    stored = {"right": ref_inl, "squared": ref_inl, "algebraic": np.zeros_like(ref_inl)}
    named = _inlier_rule(out[0], x1, x2, inl, thr, stored)
    c.fail(f"{case}: {_RULES[named] if named else 'the inliers disagree with the reference'}: {n} inliers, the reference "
           f"has {n_ref} ({common} in common)", named=named)

"""Checks of notebook 01 (the fundamental matrix): normalization, 8-point, Sampson distance, RANSAC.

Cases: fixture ``fundamental`` (:mod:`course_lib.instructor.cases.fundamental`, which also stores what each named
mistake gives on them): synthetic pairs (camera 1 off the origin; noiseless, 1 and 2 px noise, a 6000 x 4000 image,
outliers) and the embedded pair. F is judged against ground truth where there is one (the noiseless points of a noisy
pair), never against the noisy inputs alone, and is defined up to scale and sign
(:func:`course_lib.checks.core.same_up_to_scale`); rank 2 is eight_point's defining property. ``ransac_fundamental``
gets the RANSAC check shared with notebook 04 (:mod:`course_lib.checks.ransac`) at thresholds on both sides of 1 px,
and F's own verdicts (the true geometry, the true inliers, the refit, the count on an exact case, the embedded pair).
Where the check needs a distance of its own it uses the point-to-line distance (no exercise of the notebook) or
OpenCV (``cv2.sampsonDistance``).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from course_lib.checks.core import (EPS32, FAILED, RTOL, Check, Outcome, as_float, close_rel, declare_defining,
                                    load_fixture, report_cases, same_up_to_scale, scale_free_gap)
from course_lib.checks.ransac import (Ransac, Run, call, mask_outcome, minimal_verdicts, samples_needed,
                                      sampling_verdicts, threshold_interval, within)
from course_lib.conventions import to_homogeneous

__all__ = [
    "check_normalize_points",
    "check_eight_point",
    "check_sampson_distance",
    "check_ransac_fundamental",
]

FIXTURE = "fundamental"
#: RANSAC thresholds of the check: on both sides of 1 px (1.5 px on the pair with outliers, 0.7 px noise;
#: 0.8 px on the pair without outliers, 1 px noise, where no sample is so bad that it has almost no inliers),
#: so that d < threshold², d² < threshold and d < threshold differ.
CHECK_THRESHOLD_PX = 1.5
TIGHT_THRESHOLD_PX = 0.8
#: A matrix has rank 2 when its smallest singular value is below this share of its largest (in pixels and in
#: the case's normalized coordinates): far above float32 rounding, far below a 3-rank 8-point F (1e-4 and more).
RANK_RTOL = 10 * EPS32

declare_defining("eight_point", {
    "rank 2": "a fundamental matrix is singular, so that all epipolar lines meet in the epipole",
})


# --------------------------------------------------------------------------- small helpers


def _line_distance_px(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """(N,) mean of the distances of x2 to its epipolar line F x1 and of x1 to Fᵀ x2 (the check's yardstick)."""
    F = np.asarray(F, float)
    l2, l1 = to_homogeneous(x1) @ F.T, to_homogeneous(x2) @ F
    e = np.abs(np.sum(to_homogeneous(x2) * l2, axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        return 0.5 * (e / np.hypot(l2[:, 0], l2[:, 1]) + e / np.hypot(l1[:, 0], l1[:, 1]))


def _median_px(F, x1, x2) -> float:
    d = np.median(_line_distance_px(F, x1, x2))
    return float(d) if np.isfinite(d) else float("inf")


def _sampson_sq(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """(N,) squared Sampson distances in pixels² (OpenCV's Sampson error as it comes; the kit ships no function that
    returns what the exercise sampson_distance returns)."""
    import cv2

    F = np.ascontiguousarray(F, dtype=np.float64)
    return np.array([cv2.sampsonDistance(a, b, F) for a, b in zip(to_homogeneous(x1), to_homogeneous(x2))])


def _rank_verdict(c: Check, case: str, F, p: str, f) -> None:
    """F has rank 2, in pixels and in the normalized coordinates of the case (``T1``, ``T2``).

    A pixel-scale F has singular values spread over many orders of magnitude, so a full-rank F (the 8-point result
    without the rank-2 step) can look rank 2 in pixels; in normalized coordinates that test is reliable. The other
    way round, a matrix such as np.eye(3), full rank in pixels, can look rank 2 in normalized coordinates. So rank 2
    must hold in both (:data:`RANK_RTOL`).
    """
    s_px = np.linalg.svd(F, compute_uv=False)
    s = np.linalg.svd(np.linalg.inv(f[f"{p}_T2"]).T @ F @ np.linalg.inv(f[f"{p}_T1"]), compute_uv=False)
    r = max(int(np.sum(v > RANK_RTOL * v[0])) for v in (s_px, s))
    c.gate(r == 2, f"{case}: F has rank 2",
           f"{case}: F has rank {r} (singular values in normalized coordinates "
           f"{np.array2string(s / s[0], precision=2)}): a fundamental matrix has rank 2; zero the smallest singular "
           "value, F = U diag(s1, s2, 0) Vᵀ",
           defining="rank 2")


# --------------------------------------------------------------------------- normalize_points


_NORM_CASES = (("norm", "{n} pixels of a building facade"), ("norm_large", "{n} pixels of a 6000 x 4000 image"))


def _scale_verdict(c: Check, case: str, x: np.ndarray, xn: np.ndarray, T: np.ndarray) -> None:
    """The mean distance to the origin is sqrt(2), with one scale for both axes; else what it is."""
    d = np.linalg.norm(xn - xn.mean(0), axis=1)
    mean_d, rms_d = d.mean(), np.sqrt((d**2).mean())
    uncentred = np.sqrt(2) * np.linalg.norm(x - x.mean(0), axis=1).mean() / np.linalg.norm(x, axis=1).mean()
    if abs(mean_d - np.sqrt(2)) <= RTOL * np.sqrt(2):
        c.expect(True, f"{case}: the mean distance to the origin is sqrt(2)", "")
    elif abs(T[0, 0] - T[1, 1]) > RTOL * abs(T[1, 1]):
        c.fail(f"{case}: u and v have different scales (T[0, 0] = {T[0, 0]:.4g}, T[1, 1] = {T[1, 1]:.4g}): use one "
               "scale s for both axes, s = sqrt(2) / (mean distance to the centroid)")
    elif abs(rms_d - np.sqrt(2)) <= RTOL * np.sqrt(2):
        c.fail(f"{case}: the RMS distance is sqrt(2) but the mean distance is {mean_d:.4g}: scale so that the *mean* "
               "distance np.linalg.norm(x - c, axis=1).mean() becomes sqrt(2)")
    elif abs(mean_d - uncentred) <= RTOL * uncentred and abs(uncentred - np.sqrt(2)) > 0.01:
        c.fail(f"{case}: the mean distance is {mean_d:.4g}: your scale is measured from the uncentred points "
               "(the distances to the image's origin, not to the centroid): s = sqrt(2) / (mean distance to the "
               "centroid), np.linalg.norm(x - c, axis=1).mean() with c the mean of the points", named="uncentred_scale")
    else:
        c.fail(f"{case}: the mean distance to the centroid is {mean_d:.4g}, expected sqrt(2) = 1.4142 "
               f"(s = sqrt(2) / mean distance; the RMS distance is {rms_d:.4g})")


def _normalize_case(c: Check, fn: Callable, x: np.ndarray, T_ref: np.ndarray, case: str) -> None:
    out = c.call(fn, x, case=case)
    if out is FAILED:
        return
    out = c.fields(out, case, ("x_n", "T"), "the tuple (x_n, T)")
    if out is None or not (c.shape(out[0], (len(x), 2), f"{case}: x_n", {
            (2, len(x)): "points are rows, return shape (N, 2)",
            (len(x), 3): "return the 2-D normalized points (drop the homogeneous 1)"})
            & c.shape(out[1], (3, 3), f"{case}: T")):
        return
    xn, T = as_float(out[0]), as_float(out[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        mapped = to_homogeneous(x) @ T.T
        mapped = mapped[:, :2] / mapped[:, 2:]
        back = to_homogeneous(xn) @ T.T
        back = back[:, :2] / back[:, 2:]
    c_x = x.mean(0)
    s_est = float(np.linalg.norm(xn - xn.mean(0), axis=1).mean() / max(np.linalg.norm(x - c_x, axis=1).mean(), 1e-300))
    if close_rel(mapped, xn):
        c.gate(True, f"{case}: x_n = T x (in homogeneous coordinates)", "")
    elif close_rel(back, x):
        c.fail(f"{case}: T maps x_n back to the pixels: you returned the inverse of T; return the T with x_n = T x "
               "(pixels to normalized)", named="T_inverse")
    elif (np.allclose(T[:2, :2], s_est * np.eye(2), rtol=1e-6) and np.allclose(T[:2, 2], -c_x, rtol=1e-6)
          and close_rel(xn, s_est * (x - c_x))):
        c.fail(f"{case}: x_n is right, but T translates by -c = {np.round(-c_x, 2).tolist()}: in T the translation is "
               "scaled too, T = [[s, 0, -s c_u], [0, s, -s c_v], [0, 0, 1]] (T x = s (x - c))",
               named="T_translation_unscaled")
    else:
        err = float(np.abs(mapped - xn).max())
        c.fail(f"{case}: x_n is not T applied to x (largest difference {err:.3g}): T must be the similarity that maps "
               "every pixel x to x_n")
    centroid = xn.mean(0)
    c.gate(bool(np.abs(centroid).max() <= RTOL * np.sqrt(2)), f"{case}: the centroid of x_n is at the origin",
           f"{case}: the centroid of x_n is {np.round(centroid, 3).tolist()}, not (0, 0): subtract the mean of the points")
    _scale_verdict(c, case, x, xn, T)
    c.expect(close_rel(T, T_ref), f"{case}: T matches the reference [[s, 0, -s cu], [0, s, -s cv], [0, 0, 1]]",
             f"{case}: T differs from the reference [[s, 0, -s cu], [0, s, -s cv], [0, 0, 1]] with s = sqrt(2) / mean "
             "distance")


def check_normalize_points(normalize_points: Callable) -> None:
    """Check ``normalize_points(x (N, 2)) -> (x_n (N, 2), T (3, 3))`` (notebook 01): Hartley's normalization."""
    f = load_fixture(FIXTURE)
    with Check("normalize_points") as c:
        for key, label in _NORM_CASES:
            if f"{key}_x" in f:
                x = f[f"{key}_x"]
                _normalize_case(c, normalize_points, x, f[f"{key}_T"], label.format(n=len(x)))


# --------------------------------------------------------------------------- eight_point


_CASE_TEXT = {
    "noiseless": "noiseless synthetic pair",
    "noisy": "noisy synthetic pair (1 px noise)",
    "few": "few matches, 2 px noise",
    "large": "a 6000 x 4000 image pair, 1 px noise",
    "outliers": "synthetic pair, inliers only",
    "building": "embedded building pair, reference inliers",
}

#: What each stored 8-point mistake (``ep_<case>_mis_<key>``) means, said as what the student did.
_EIGHT_POINT_MISTAKES = {
    "transposed": "your F is transposed: it satisfies x1ᵀ F x2 = 0; the kit's constraint is x2ᵀ F x1 = 0, so row k of "
                  "A is [u2 u1, u2 v1, u2, v2 u1, v2 v1, v2, u1, v1, 1]",
    "unnormalized": "your F is the 8-point result on raw pixels (not normalized): normalize both point sets with "
                    "normalize_points, solve, and denormalize F = T2ᵀ F_n T1",
    "no_rank2": "you skipped the rank-2 step: zero the smallest singular value, F = U diag(s1, s2, 0) Vᵀ",
    "not_denormalized": "your F is still in normalized coordinates: denormalize, F = T2ᵀ F_n T1",
    "denormalized_swapped": "you denormalized the wrong way round: x2 is normalized by T2 and x1 by T1, so "
                            "F = T2ᵀ F_n T1 (not T1ᵀ F_n T2)",
    "denormalized_inverse": "you denormalized with the inverses: x_n = T x, so x2ᵀ (T2ᵀ F_n T1) x1 = 0 and "
                            "F = T2ᵀ F_n T1 (no np.linalg.inv)",
    "denormalized_no_transpose": "you denormalized without the transpose: F = T2ᵀ F_n T1 (T2.T, not T2)",
}

#: Accuracy bounds: F's median epipolar distance of the noiseless points at most this factor of the reference's
#: plus this many pixels (a correct F in float32 or with another valid normalization is within 10 %).
TRUTH_FACTOR, TRUTH_PX = 1.5, 0.1


def _eight_point_fit(F, f, p: str, name: str):
    """``(ok, pass text, numbers)`` of F's fit on case ``p`` (truth where there is one)."""
    F_ref = f[f"{p}_F"]
    if name == "noiseless":
        return same_up_to_scale(F, F_ref), "F equals the true F (up to scale and sign)", (
            "F is not the true F: on noiseless matches the 8-point F is exact (your F differs by "
            f"{scale_free_gap(F, F_ref):.3g} at unit norm)")
    if f"{p}_x1_true" in f:
        xt1, xt2 = f[f"{p}_x1_true"], f[f"{p}_x2_true"]
        d, d_ref = _median_px(F, xt1, xt2), _median_px(F_ref, xt1, xt2)
        return d <= TRUTH_FACTOR * d_ref + TRUTH_PX, "F fits the true geometry as well as the reference's", (
            f"F fits the true geometry worse than the reference's 8-point F: median epipolar distance of the noiseless "
            f"points {d:.3g} px, reference {d_ref:.3g} px")
    x1, x2 = f[f"{p}_x1"], f[f"{p}_x2"]
    d, d_ref = _median_px(F, x1, x2), _median_px(F_ref, x1, x2)
    return d <= 1.2 * d_ref + 0.02, "epipolar residuals as small as the reference's", (
        f"F fits the matches worse than the reference's 8-point F: median distance of the points to their epipolar "
        f"lines {d:.3g} px, reference {d_ref:.3g} px")


def check_eight_point(eight_point: Callable) -> None:
    """Check ``eight_point(x1 (N, 2), x2 (N, 2)) -> F (3, 3)`` (notebook 01)."""
    f = load_fixture(FIXTURE)
    with Check("eight_point") as c:
        results = []
        for name in [str(n) for n in f["cases"]]:
            p = f"ep_{name}"
            x1, x2 = f[f"{p}_x1"], f[f"{p}_x2"]
            case = _CASE_TEXT[name]
            out = c.call(eight_point, x1, x2, case=case)
            reshape = "reshape the null vector to (3, 3) (row-major, F.reshape(3, 3))"
            if not c.shape(out, (3, 3), f"{case}: F", {(9,): reshape, (9, 1): reshape}):
                continue
            F = as_float(out)
            ok, good, bad = _eight_point_fit(F, f, p, name)
            results.append(Outcome(case, ok, good, bad, data=(F, p), keys=() if ok else {
                key for key in _EIGHT_POINT_MISTAKES
                if f"{p}_mis_{key}" in f and same_up_to_scale(F, f[f"{p}_mis_{key}"], 1e-4)}))
        report_cases(c, results, _EIGHT_POINT_MISTAKES, then=lambda o, _: _rank_verdict(c, o.case, *o.data, f))
        c.blame_earlier("normalize_points", fn=eight_point)
        c.causes(eight_point, [
            (r"\beigh\(", "np.linalg.eigh sorts the eigenvalues in ascending order: the solution is the "
                                    "eigenvector of AᵀA with the smallest eigenvalue, V[:, 0], the first column"),
            ((r"\bV[th]?\[:, *-1\]", r"\bsvd\(", r"!\beigh\("), "np.linalg.svd(A) returns Vᵀ: the null vector is its last row, "
                                                "Vt[-1], not its last column"),
            ((r"!\bnormalize_points\b", r"\bdef "), "your code does not call normalize_points: normalize both point sets, solve, "
                                  "denormalize F = T2ᵀ F_n T1"),
            (r"\binv\(", "no inverse in the denormalization: x_n = T x, so F = T2ᵀ F_n T1"),
            (r"\[: *8\b", "the 8-point algorithm solves least squares over all N matches, not the first 8"),
        ])


# --------------------------------------------------------------------------- sampson_distance

_SAMPSON_DEN = "d = |x2ᵀ F x1| / sqrt((F x1)₀² + (F x1)₁² + (Fᵀ x2)₀² + (Fᵀ x2)₁²)"
_SYMMETRIC = ("you computed a symmetric epipolar distance (the distances of x1 and x2 to their epipolar lines, "
              "combined), not Sampson's: the four squared line entries go under ONE square root, " + _SAMPSON_DEN)

#: What each stored Sampson mistake (``sd_<case>_mis_<key>``) means, said as what the student did.
_SAMPSON_MISTAKES = {
    "squared": "you returned Sampson's squared error: take the square root to get a distance in pixels",
    "algebraic": "you returned the algebraic error |x2ᵀ F x1|, whose size depends on the scale of F: divide by "
                 "sqrt((F x1)₀² + (F x1)₁² + (Fᵀ x2)₀² + (Fᵀ x2)₁²)",
    "algebraic_unit": "you returned the algebraic error |x2ᵀ F x1| of the unit-norm F, which has no unit: divide by "
                      "sqrt((F x1)₀² + (F x1)₁² + (Fᵀ x2)₀² + (Fᵀ x2)₁²)",
    "signed": "you returned signed distances: take the absolute value",
    "one_sided_2": "you returned the distance of x2 to its epipolar line F x1 only: Sampson's denominator uses both "
                   "lines, " + _SAMPSON_DEN,
    "one_sided_1": "you returned the distance of x1 to its epipolar line Fᵀ x2 only: Sampson's denominator uses both "
                   "lines, " + _SAMPSON_DEN,
    "symmetric_sum": _SYMMETRIC,
    "symmetric_mean": _SYMMETRIC,
    "symmetric_rms": _SYMMETRIC,
    "symmetric_root": _SYMMETRIC,
    "symmetric_squared": _SYMMETRIC,
    "transposed": "you used the transposed F: the algebraic error is x2ᵀ F x1 (F x1 is the line in image 2)",
    "no_sqrt": "your denominator has no square root: " + _SAMPSON_DEN,
    "wrong_gradient": "you took F x2 for the line in image 1; it is Fᵀ x2 (x2 @ F for rows): " + _SAMPSON_DEN,
    "pixels_not_homogeneous_1": "your denominator uses all three entries of each line: only the first two (the "
                                "derivatives with respect to u and v) belong in it, " + _SAMPSON_DEN,
}

_SD_TEXT = {"outliers": "synthetic pair with outliers ({n} points)",
            "large": "a 6000 x 4000 image pair ({n} points)",
            "scaled": "embedded pair, F of norm {norm:.0f} and negative sign ({n} points)"}
#: Distances agree within this many pixels plus RTOL of their size (float32 rounding of x2ᵀ F x1 is ~1e-4 px).
SAMPSON_ATOL_PX = 1e-3


def _same_distances(d, d_ref) -> bool:
    d, d_ref = np.asarray(d, float), np.asarray(d_ref, float)
    return d.shape == d_ref.shape and bool(np.all(np.abs(d - d_ref) <= SAMPSON_ATOL_PX + RTOL * np.abs(d_ref)))


def check_sampson_distance(sampson_distance: Callable) -> None:
    """Check ``sampson_distance(F (3, 3), x1 (N, 2), x2 (N, 2)) -> (N,)`` in pixels (notebook 01)."""
    f = load_fixture(FIXTURE)
    with Check("sampson_distance") as c:
        results = []
        for k, name in enumerate(str(n) for n in f["sd_cases"]):
            p = f"sd_{name}"
            F, x1, x2, d_ref = f[f"{p}_F"], f[f"{p}_x1"], f[f"{p}_x2"], f[f"{p}_d"]
            case = _SD_TEXT[name].format(n=len(x1), norm=np.linalg.norm(F))
            out = c.call(sampson_distance, F, x1, x2, case=case)
            flat = "return a flat array of shape (N,)"
            if not c.shape(out, (len(x1),), f"{case}: d", {(len(x1), 1): flat, (1, len(x1)): flat}):
                continue
            d = as_float(out)
            ok = _same_distances(d, f[f"{p}_d"])
            j = int(np.argmax(np.abs(d - f[f"{p}_d"])))
            results.append(Outcome(case, ok, "distances match the reference (pixels)",
                                   f"distances differ from the Sampson distance (match {j}: {d[j]:.4g} px, expected "
                                   f"{f[f'{p}_d'][j]:.4g} px)", advice=_SAMPSON_DEN, keys=() if ok else {
                                       key for key in _SAMPSON_MISTAKES
                                       if f"{p}_mis_{key}" in f and _same_distances(d, f[f"{p}_mis_{key}"])}))
            if k == 0:
                d10 = as_float(c.call(sampson_distance, -10.0 * F, x1, x2, case=case))
                usable = d10 is not None and d10.shape == d.shape  # an unusable answer fails the gate too
                c.gate(usable and _same_distances(d10, d), f"{case}: the distance does not depend on the scale of F",
                       f"{case}: the result changes when F is multiplied by -10: a distance in pixels must not depend "
                       "on the scale (or sign) of F" if usable else
                       f"{case}: called with -10 F, your function returned nothing usable (expected shape {d.shape})")
        report_cases(c, results, _SAMPSON_MISTAKES)


# --------------------------------------------------------------------------- ransac_fundamental


def _F_model(c: Check, case: str, parts: list) -> np.ndarray | None:
    F = as_float(parts[0])
    if F is None or F.shape != (3, 3) or not np.isfinite(F).all() or not np.linalg.norm(F) > 0:
        c.fail(f"{case}: F must be a finite, non-zero (3, 3) array, got {'no array' if F is None else F.shape}")
        return None
    return F


def _algebraic_key(run: Run) -> set[str]:
    """``{"algebraic"}`` when the mask is a threshold on the algebraic error |x2ᵀ F x1| of the unit-norm F."""
    x1, x2 = run.args
    F = run.model / np.linalg.norm(run.model)
    e = np.abs(np.sum(to_homogeneous(x2) * (to_homogeneous(x1) @ F.T), axis=1))
    return {"algebraic"} if within(threshold_interval(e, run.inl), run.thr) else set()


RANSAC = Ransac(8, ("match", "matches"), ("F", "inliers", "n_iters"), "a RansacResult(F, inliers, n_iters)", _F_model,
                lambda F, args: np.sqrt(_sampson_sq(F, *args)), "Sampson distance", "F", 1.0, 2000, {
                    "algebraic": "you counted inliers with the algebraic error |x2ᵀ F x1|, which has no unit: compare "
                                 "the Sampson distance with the threshold, sampson_distance(F, x1, x2) < threshold_px"})


def _fit_verdicts(c: Check, f: dict, p: str, run: Run) -> bool:
    """The true inliers found (on the pair with outliers), and F as close to the true geometry as the reference's."""
    true_inl = f["rs_true_inliers"].astype(bool) if p == "rs" else np.ones(len(run.inl), bool)
    case, inl = run.case, run.inl
    if p == "rs":
        prec = float(true_inl[inl].mean()) if inl.any() else 0.0
        rec = float(inl[true_inl].mean())
        c.expect(prec >= 0.9 and rec >= 0.8, f"{case}: finds the true inliers (precision >= 90 %, recall >= 80 %)",
                 f"{case}: the inliers disagree with the true ones (precision {prec:.0%}, recall {rec:.0%}, "
                 f"{int(inl.sum())} of {len(inl)} matches)")
    xt1, xt2 = f[f"{p}_x1_true"][true_inl], f[f"{p}_x2_true"][true_inl]
    F_ref = f["rs_F"] if p == "rs" else f["rf_tight_F"]
    d, d_ref = _median_px(run.model, xt1, xt2), _median_px(F_ref, xt1, xt2)
    return c.expect(d <= 3.0 * d_ref + 0.3, f"{case}: F fits the true geometry as well as the reference",
                    f"{case}: F fits the true geometry worse than the reference's: median epipolar distance of the "
                    f"noiseless points {d:.3g} px, reference {d_ref:.3g} px (check the inlier test, the number of "
                    "samples and the final refit on all inliers of the best sample)")


def _ransac_count_case(c: Check, fn: Callable, f: dict) -> None:
    """An exact case (noiseless inliers, 40 % gross outliers): the best inlier set is found exactly and cannot improve,
    so an adaptive loop draws at least N = log(1 - p) / log(1 - w⁸) samples for the returned ratio w."""
    true_inl = f["rs_true_inliers"].astype(bool)
    xi1, xi2 = f["rs_x1_true"][true_inl], f["rs_x2_true"][true_inl]
    n_in = len(xi1)
    n_out = int(round(n_in * 0.4 / 0.6))
    g = np.random.default_rng(int(abs(float(xi1.sum()))) % (2**31))  # the case's own outliers, fixed by the case
    lo, hi = np.minimum(xi1.min(0), xi2.min(0)), np.maximum(xi1.max(0), xi2.max(0))
    x1 = np.vstack([xi1, g.uniform(lo, hi, (n_out, 2))])
    x2 = np.vstack([xi2, g.uniform(lo, hi, (n_out, 2))])
    order = g.permutation(len(x1))
    x1, x2 = x1[order], x2[order]
    case = f"noiseless inliers with {n_out} gross outliers among {len(x1)} matches (threshold 1 px)"
    run = call(c, RANSAC, fn, (x1, x2), case, 11, threshold_px=1.0)
    if run is None or run.n_iters is None:
        return
    if int((run.inl != (order < n_in)).sum()) > max(2, 0.05 * len(x1)):  # the inlier test is off (said elsewhere)
        return
    w = float(run.inl.mean())
    need = samples_needed(w, 8, 0.999, 2000)
    n = run.n_iters
    c.gate(n >= 0.8 * need - 1, f"{case}: draws as many samples as N = log(1 - confidence) / log(1 - w⁸) asks",
           f"{case}: n_iters = {n}, while the returned inlier ratio {w:.0%} at confidence 0.999 needs N = {need:.0f} "
           f"samples ({n / max(need, 1):.2f} N): N = log(1 - confidence) / log(1 - w⁸) with the same logarithm on "
           "both sides (np.log10 on one side gives N / 2.3), recomputed at each iteration that finds a better sample, and "
           "the loop runs until it has drawn N samples (not until a first good sample); each sample is 8 distinct "
           "matches (rng.choice(N, 8, replace=False))")


def _ransac_refit_case(c: Check, fn: Callable, f: dict) -> None:
    """No outliers, 1 px noise, a wide threshold: every match is an inlier, and only the refit F is precise."""
    x1, x2, thr = f["rf_x1"], f["rf_x2"], float(f["rf_threshold_px"])
    case = f"synthetic pair without outliers, 1 px noise ({len(x1)} matches, threshold {thr:g} px)"
    run = call(c, RANSAC, fn, (x1, x2), case, 3, threshold_px=thr)
    if run is None:
        return
    d = _median_px(run.model, f["rf_x1_true"], f["rf_x2_true"])
    d_ref = _median_px(f["rf_F"], f["rf_x1_true"], f["rf_x2_true"])
    # a refit on all inliers lands near the fit of all matches (honest variants within 1.2x); the 8-match fit of the
    # best sample alone is several times worse (5.5x on this case)
    c.expect(d <= 2.0 * d_ref + 0.05, f"{case}: F is refit on all inliers",
             f"{case}: F fits the noiseless points worse than the fit of all inliers (median epipolar distance {d:.3g} "
             f"px, the fit of all inliers {d_ref:.3g} px; a fit of 8 matches is typically several times worse): refit "
             "F with eight_point on all inliers of the best sample at the end")


def _ransac_embedded(c: Check, fn: Callable, f: dict) -> None:
    x1, x2 = f["rb_x1"], f["rb_x2"]
    ref_inl = f["rb_inliers"].astype(bool)
    thr = float(f["rb_threshold_px"])
    case = f"embedded building pair, {len(x1)} matches (threshold {thr:g} px)"
    run = call(c, RANSAC, fn, (x1, x2), case, 7, threshold_px=thr)
    if run is None:
        return
    n, n_ref, common = int(run.inl.sum()), int(ref_inl.sum()), int((run.inl & ref_inl).sum())
    # real matches can have two consensus sets of similar size: ask for about as many inliers as the
    # reference found, most of the reference's among them (not for the same set)
    c.expect(0.85 * n_ref <= n <= 1.25 * n_ref and common >= 0.8 * n_ref,
             f"{case}: finds about as many inliers as the reference, most of them the same",
             f"{case}: the inliers disagree with the reference: {n} inliers, the reference has {n_ref} ({common} in "
             "common)")


def check_ransac_fundamental(ransac_fundamental: Callable) -> None:
    """Check ``ransac_fundamental(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000)`` (notebook 01).

    The shared RANSAC verdicts (:mod:`course_lib.checks.ransac`) and F's own: the true inliers, F against the true
    geometry, the refit, the count on an exact case, the embedded pair.
    """
    f = load_fixture(FIXTURE)
    with Check("ransac_fundamental") as c:
        n_out = int((~f["rs_true_inliers"].astype(bool)).sum())
        runs, good = [], []
        for p, thr, case in (("rs", CHECK_THRESHOLD_PX, f"synthetic pair with {n_out} outliers among "
                              f"{len(f['rs_x1'])} matches"),
                             ("rf", TIGHT_THRESHOLD_PX, f"synthetic pair without outliers, 1 px noise "
                              f"({len(f['rf_x1'])} matches), threshold_px={TIGHT_THRESHOLD_PX:g}")):
            run = call(c, RANSAC, ransac_fundamental, (f[f"{p}_x1"], f[f"{p}_x2"]), case, threshold_px=thr,
                       judge=lambda k, r, p=p: _fit_verdicts(k, f, p, r))
            if run is not None:
                runs.append(run)
                good.append(_fit_verdicts(c, f, p, run))
        report_cases(c, [mask_outcome(RANSAC, run, _algebraic_key(run)) for run in runs], RANSAC.mistakes)
        if any(good):
            sampling_verdicts(c, RANSAC, ransac_fundamental, runs[0])
            true_inl = f["rs_true_inliers"].astype(bool)
            minimal_verdicts(c, RANSAC, ransac_fundamental, (f["rs_x1_true"][true_inl][:8],
                             f["rs_x2_true"][true_inl][:8]), "exactly 8 noiseless matches (threshold 1 px)",
                             13, threshold_px=1.0)
        elif runs:
            c.fail(f"{runs[0].case}: no case gives F: the number of samples (n_iters), the confidence and the use of "
                   "rng are judged once ransac_fundamental finds F")
        _ransac_refit_case(c, ransac_fundamental, f)
        _ransac_count_case(c, ransac_fundamental, f)
        if "rb_x1" in f:
            _ransac_embedded(c, ransac_fundamental, f)
        c.blame_earlier("eight_point", "sampson_distance", fn=ransac_fundamental)

"""Checks of notebook 04 (PnP) and its step input.

Cases (fixture ``pnp``, :mod:`course_lib.instructor.cases.pnp`): synthetic views with known truth and the embedded
scene (its third image registered against the two-view reconstruction of step 3, in a randomly moved world frame):

* ``pnp_linear``: R_cw a rotation (defining: R Rᵀ = I, det +1), the true pose on a noiseless view,
  the reference's on a noisy and the embedded view; named: R_wc returned (transposed), the centre
  returned as t, t with the wrong sign or scale, the DLT on pixel coordinates.
* ``pnp_ransac``: the pose despite 20 % outliers, the inliers (a mask over all points, in front of
  the camera: mirrored points behind the camera that reproject exactly are outliers), the mask being
  the points within threshold_px of the returned pose at two thresholds (named: the squared error,
  the error against threshold_px², a constant threshold, normalized coordinates), the refit, the
  adaptive count and the confidence, and the randomness: the rng argument only (the same seed gives
  the same result whatever numpy's global state, the rng is drawn from, the global state
  untouched). In a notebook it runs the student's ``pnp_linear``; a failure then ends with a note
  when that one failed its own checks.
* ``pnp_nonlinear``: a rotation, a lower reprojection error, the least-squares optimum (from the
  linear estimate, from a start 3° away, on the embedded view); named: the 9 entries of R projected
  back with an SVD and the residual without the division by the depth (their results stored with
  the cases), only t or only R moved, R_wc returned; a residual of shape (N, 2) that least_squares
  refuses is explained.

Rotation angles are measured with atan2 (float32 rounding reads as 1e-5°, not 0.01°).
"""

from __future__ import annotations

import numpy as np

from course_lib.conventions import nearest_rotation, project, rotation_angle_deg, world_to_camera
from course_lib.checks.core import (FAILED, RTOL, Check, Outcome, call_minimal, declare_defining, load_fixture,
                                    minimal_verdict, refinement_verdicts, report_cases, rng_verdicts, samples_needed,
                                    source_has, threshold_interval, under_global_seed, unique_key, within)

__all__ = [
    "check_pnp_linear",
    "check_pnp_ransac",
    "check_pnp_nonlinear",
]

FIXTURE = "pnp"
RANSAC_SEED = 0
THRESHOLD_PX = 2.0
#: The rng case: the student's rng seed and max_iters (a few samples, so that the result depends on them).
RNG_SEED, RNG_MAX_ITERS = 1, 3


# --------------------------------------------------------------------------- helpers


def _pose(out, c: Check, case: str):
    """``(R (3, 3), t (3,))`` from the student's return value, or None after recording a failure."""
    return c.arrays(out, case, {"R_cw": (3, 3), "t_cw": (3,)}, "the tuple (R_cw, t_cw)")


def _errors(K, R, t, X, x) -> np.ndarray:
    z = world_to_camera(R, t, X)[:, 2]
    with np.errstate(all="ignore"):
        e = np.linalg.norm(project(K, R, t, X) - x, axis=1)
    e[~(z > 0)] = np.inf
    return e


def _rms(e) -> float:
    return float(np.sqrt(np.mean(np.square(e)))) if np.isfinite(e).all() else float("inf")


declare_defining("pnp_linear", {
    "R is a rotation": "R_cw is orthonormal with det +1 (not a reflection, not a scaled matrix)",
})


def _rotation_verdict(c: Check, R, case: str, defining: str | None = None) -> bool:
    """Orthonormal with det +1, or a failure that names the mistake.

    With ``defining`` (pnp_linear) a pass is recorded too, as a check of that defining property.
    """
    gap = float(np.abs(R @ R.T - np.eye(3)).max())
    if gap > 10 * RTOL:
        return c.fail(f"{case}: R_cw is not a rotation: R Rᵀ differs from I by {gap:.3g}; orthogonalize the 3 x 3 block, "
                      "with P[:, :3] = U S Vᵀ take R = U Vᵀ", defining=defining)
    if np.linalg.det(R) < 0:
        return c.fail(f"{case}: det R = -1 (a reflection): P is known only up to sign; when det P[:, :3] < 0 "
                      "flip the sign of P (R and t together)", defining=defining)
    if defining is not None:
        c.gate(True, f"{case}: R_cw is a rotation (orthonormal, det +1)", "", defining=defining)
    return True


_POSE_MISTAKES = {
    "transposed": "you returned R_wc (world from camera), the transpose of R_cw; x_cam = R_cw X + t_cw",
    "C_for_t": "you returned the camera centre C as t_cw (C vs t confusion): t_cw = -R_cw @ C",
    "t_sign": "your t_cw has the wrong sign, so the points end up behind the camera: flip R and t together",
    "t_scale": "your t_cw has the wrong scale: divide P[:, 3] by the same scale as the rotation block, t = P[:, 3] / σ "
               "with σ the singular values of P[:, :3] (or re-estimate t by least squares with R fixed)",
    "reflection": "your R is the reference's times -1 (det -1): flip the sign of P when det P[:, :3] < 0",
    "pixels": "you ran the DLT on pixel coordinates: use normalized coordinates x_n = K⁻¹ [u, v, 1]ᵀ, so that "
              "P = λ [R | t] holds no K",
}


def _pose_keys(R, t, R_ref, t_ref, rot_tol, t_tol, dlt: bool = True) -> tuple[set[str], set[str]]:
    """``(explained, testable)``: the confusions that explain (R, t) against (R_ref, t_ref), and those this case can
    tell apart at all (keys of :data:`_POSE_MISTAKES`; a t of the wrong scale only where t has the right direction)."""
    out = set()
    testable = set(_POSE_MISTAKES) - {"pixels", "t_scale"}
    rot_ok = rotation_angle_deg(R, R_ref) < rot_tol
    near = lambda a, b: np.linalg.norm(a - b) < t_tol * max(1.0, np.linalg.norm(b))  # noqa: E731
    if not rot_ok and rotation_angle_deg(R.T, R_ref) < rot_tol:
        out.add("transposed")
    if rot_ok:
        if near(t, -R_ref.T @ t_ref):
            out.add("C_for_t")
        if near(t, -t_ref):
            out.add("t_sign")
        s = float(t @ t_ref / max(t_ref @ t_ref, 1e-300))
        cos = s * np.linalg.norm(t_ref) / max(np.linalg.norm(t), 1e-300)
        if dlt and cos > np.cos(np.radians(2.0)):
            testable.add("t_scale")
        if dlt and s > 0 and abs(s - 1) > 0.01 and near(t / s, t_ref):
            out.add("t_scale")
    if not rot_ok and rotation_angle_deg(-R, R_ref) < rot_tol:
        out.add("reflection")
    return out, testable


# --------------------------------------------------------------------------- pnp_linear

_DLT_ADVICE = ("check the two equations per point, u_n (p3ᵀX) - p1ᵀX = 0 and v_n (p3ᵀX) - p2ᵀX = 0, with x_n = K⁻¹ x "
               "(normalized coordinates), and the orthogonalization R = U Vᵀ")


def check_pnp_linear(fn, exercise: str = "pnp_linear") -> None:
    """Check ``fn(X, x, K) -> (R_cw, t_cw)`` on noiseless, noisy and embedded 2D-3D matches."""
    f = load_fixture(FIXTURE)
    with Check(exercise) as c:
        results = []
        for key, case in (("lin_noiseless", "noiseless synthetic view"), ("lin_noisy", "noisy synthetic view"),
                          ("lin_embedded", "embedded scene")):
            if f"{key}_X" not in f:
                continue
            K, X, x, R_r, t_r = (f[f"{key}_{s}"] for s in ("K", "X", "x", "R", "t"))
            out = _pose(c.call(fn, X, x, K, case=case), c, case)
            if out is None or not _rotation_verdict(c, out[0], case, defining="R is a rotation"):
                continue
            R, t = out
            if key == "lin_noiseless":
                ok = rotation_angle_deg(R, R_r) < 1e-3 and np.linalg.norm(t - t_r) < RTOL * max(1.0, np.linalg.norm(t_r))
                keys, testable = _pose_keys(R, t, R_r, t_r, 1e-3, 1e-4)
                testable.add("pixels")
                if _pixel_hint(R, K, R_r):
                    keys.add("pixels")
            else:
                e_s, e_r = _rms(_errors(K, R, t, X, x)), _rms(_errors(K, R_r, t_r, X, x))
                t_close = np.linalg.norm(t - t_r) <= 0.05 * np.linalg.norm(t_r)  # t = P[:, 3] / σ is a few % off
                ok = rotation_angle_deg(R, R_r) < 0.5 and (t_close or e_s <= 1.5 * e_r + 0.5)
                keys, testable = _pose_keys(R, t, R_r, t_r, 0.5, 0.05)
                if f"{key}_true_R" in f:  # a DLT on noisy pixels: the orthogonalized K R, within noise
                    testable.add("pixels")
                    if _pixel_hint(R, K, f[f"{key}_true_R"], tol_deg=2.0):
                        keys.add("pixels")
            truth = "truth" if key == "lin_noiseless" else "reference"
            results.append(Outcome(case, ok, "recovers the true pose exactly" if key == "lin_noiseless" else
                                   "close to the reference pose",
                                   f"rotation {rotation_angle_deg(R, R_r):.3g}° from the {truth}, translation off by "
                                   f"{np.linalg.norm(t - t_r):.3g} (|t| = {np.linalg.norm(t_r):.3g}), RMS reprojection "
                                   f"error {_rms(_errors(K, R, t, X, x)):.3g} px", (keys, testable), _DLT_ADVICE))
        report_cases(c, results, _POSE_MISTAKES)
        c.causes(fn, [
            ((source_has(r"\bV[th]?\[:, *-1\]"), source_has(r"\bsvd\(")), "np.linalg.svd(A) returns Vᵀ: the DLT's P is its last row, Vt[-1]"
                                                ".reshape(3, 4), not its last column"),
            ((source_has(r"\bdef "), "!det"), "P is found up to sign: when det(R) < 0 after the orthogonalization, flip the sign of R and t"),
        ])


def _pixel_hint(R, K, R_true, tol_deg: float = 0.05) -> bool:
    """Whether R is the rotation a DLT on pixel coordinates gives (on noiseless data exactly): the orthogonalized K R,
    tens of degrees from any rotation a DLT on normalized coordinates gives."""
    U, _, Vt = np.linalg.svd(K @ R_true)
    return rotation_angle_deg(R, U @ Vt) < tol_deg


# --------------------------------------------------------------------------- pnp_ransac


def _ransac_fields(out, c: Check, case: str, n: int):
    """``(R, t, inliers (n,) bool, n_iters or None)`` from the student's return value, or None after a failure."""
    out = c.fields(out, case, ("R_cw", "t_cw", "inliers", "n_iters"), "a PnPResult(R_cw, t_cw, inliers, n_iters)", 1)
    if out is None:
        return None
    R, t, inl, it = out
    pose = _pose((R, t), c, case)
    if pose is None:
        return None
    inl = np.asarray(inl)
    if inl.shape != (n,) or inl.dtype != bool:
        c.fail(f"{case}: inliers must be a bool array of shape ({n},), got {inl.dtype} {inl.shape} "
               "(a mask over ALL correspondences, not the inlier indices)")
        return None
    try:
        it = None if it is None else int(it)
    except (TypeError, ValueError):
        it = -1
    return pose[0], pose[1], inl, it


#: The inlier rules a mask may follow, as what the student did.
_MASK_RULES = {
    "squared": "you compared the SQUARED reprojection error with threshold_px (e² < threshold_px): compare the error "
               "itself, in pixels",
    "threshold_squared": "you compared the reprojection error with threshold_px² (e < threshold_px²): compare it with "
                         "threshold_px itself",
    "constant": f"you compared with {THRESHOLD_PX:g} px whatever threshold_px was passed: use the threshold_px argument",
    "normalized": "your inliers include points whose reprojection errors are many pixels: measure the reprojection "
                  "error in pixels (project with K), not in normalized coordinates",
    "no_cheirality": "your inliers include points behind the returned camera (depth z <= 0) that reproject within "
                     "threshold_px: an inlier must also be in front of the camera",
}


def _mask_facts(inl, e_px, z, thr: float, behind) -> dict:
    """How the mask relates to the returned pose's reprojection errors ``e_px (N,)`` and depths ``z (N,)``."""
    front = z > 0
    interval = threshold_interval(e_px[front], inl[front])  # the points behind the camera: their own verdict
    keys = set()
    if within(interval, thr**2) and not within(interval, thr):
        keys.add("threshold_squared")
    if within(interval, np.sqrt(thr)) and not within(interval, thr):
        keys.add("squared")
    if thr != THRESHOLD_PX and within(interval, THRESHOLD_PX) and not within(interval, thr):
        keys.add("constant")
    if (inl & front).any() and e_px[inl & front].max() > 10 * thr and inl.mean() > 0.9:
        keys.add("normalized")
    if behind is not None and (inl & behind).any():
        keys.add("no_cheirality")
    tie = np.abs(e_px - thr) <= 1e-6 * thr  # a point at the threshold may go either way
    wrong = (inl != (e_px < thr)) & ~tie & front  # points behind the camera: their own verdict
    return {"keys": keys, "wrong": int(wrong.sum()), "interval": interval}


def _mask_verdict(c: Check, case: str, facts: dict, thr: float, named: str | None) -> None:
    """The returned mask must be the inliers of the returned pose (error below the threshold in pixels, in front)."""
    if facts["wrong"] == 0:
        c.expect(True, f"{case}: the inliers are the points within threshold_px of the returned pose", "")
        return
    if named is not None and named in facts["keys"]:
        why = _MASK_RULES[named]
    else:
        named = None
        iv = facts["interval"]
        why = ("your mask is the points with reprojection error below some τ between "
               f"{iv[0]:.3g} and {iv[1]:.3g} px, threshold_px = {thr:g}" if iv is not None else
               "no threshold on the returned pose's reprojection errors gives your mask") + \
              ": after the refit, recompute the inliers with the final pose (error < threshold_px, in front)"
    c.fail(f"{case}: {facts['wrong']} points are labelled against the returned pose's reprojection errors: {why}",
           named=named)


def _ransac_call(c: Check, fn, f, key: str, case: str, threshold: float | None = None):
    """One call on a stored case: the fields and what the mask says, or None."""
    K, X, x = (f[f"{key}_{s}"] for s in ("K", "X", "x"))
    kw = {} if threshold is None else {"threshold_px": threshold}
    out = _ransac_fields(c.call(fn, X, x, K, np.random.default_rng(RANSAC_SEED), case=case, **kw), c, case, len(X))
    if out is None:
        return None
    R, t, inl, it = out
    thr = THRESHOLD_PX if threshold is None else threshold
    z = world_to_camera(R, t, X)[:, 2]
    with np.errstate(all="ignore"):
        e_px = np.linalg.norm(project(K, R, t, X) - x, axis=1)
    e_px = np.where(np.isfinite(e_px), e_px, np.inf)
    behind = f.get(f"{key}_behind")
    facts = _mask_facts(inl, e_px, z, thr, None if behind is None else behind.astype(bool))
    return {"key": key, "case": case, "R": R, "t": t, "inl": inl, "it": it, "thr": thr, "facts": facts,
            "e": _errors(K, R, t, X, x)}


def _ransac_verdicts(c: Check, f, run: dict, named: str | None, pose_named: str | None = None) -> None:
    """The pose, the inliers, the outliers and points behind rejected, the mask; for one call."""
    key, case, R, t, inl, thr = (run[k] for k in ("key", "case", "R", "t", "inl", "thr"))
    R_r, t_r, inl_r = (f[f"{key}_{s}"] for s in ("R", "t", "inliers"))
    if float((~inl == inl_r).mean()) > 0.9 and float((inl == inl_r).mean()) < 0.5:
        c.fail(f"{case}: your inlier mask is inverted: inliers are the points with reprojection error BELOW the "
               "threshold", named="inverted")
        return
    rot = rotation_angle_deg(nearest_rotation(R), R_r)
    c.expect(rot <= 1.0, f"{case}: finds the pose despite the outliers",
             f"{case}: rotation {rot:.3g}° from the reference ({int(inl.sum())} inliers, reference {int(inl_r.sum())}): "
             + (_POSE_MISTAKES[pose_named] if pose_named else "score each sample by the reprojection error in pixels "
                "of ALL points, keep the best, then refit on its inliers"), named=pose_named)
    if rot > 1.0:
        return
    agree = float((inl == inl_r).mean())
    c.expect(agree > 0.9, f"{case}: the inliers agree with the reference",
             f"{case}: only {agree:.0%} of the inlier labels agree with the reference ({int(inl.sum())} inliers, "
             f"reference {int(inl_r.sum())}): inliers are the points with reprojection error below threshold_px "
             f"= {thr:g} (pixels, in front of the camera)")
    if f"{key}_outlier" in f:
        outl = f[f"{key}_outlier"].astype(bool)
        c.expect((inl & outl).sum() <= 0.02 * len(inl), f"{case}: rejects the outliers",
                 f"{case}: {int((inl & outl).sum())} injected outliers are marked as inliers")
    if f"{key}_behind" in f:
        behind = f[f"{key}_behind"].astype(bool)
        n_b = int((inl & behind).sum())
        c.expect(n_b == 0, f"{case}: points behind the camera are no inliers",
                 f"{case}: {n_b} of the {int(behind.sum())} points behind the camera (they reproject exactly, depth < 0) "
                 "are marked as inliers: " + _MASK_RULES["no_cheirality"],
                 named="no_cheirality" if named == "no_cheirality" else None)
    _mask_verdict(c, case, run["facts"], thr, named if named != "no_cheirality" else None)


def _refit_verdict(c: Check, f, case: str, R, t) -> None:
    """A pose refit on all inliers reprojects the true inliers nearly as well as the reference's."""
    K, X, x, outl = (f[f"ransac_syn_{s}"] for s in ("K", "X", "x", "outlier"))
    outl = outl.astype(bool)
    rms = _rms(_errors(K, R, t, X[~outl], x[~outl]))
    ref = _rms(_errors(K, f["ransac_syn_R"], f["ransac_syn_t"], X[~outl], x[~outl]))
    bound = float(np.sqrt(ref**2 + (0.5 * float(f["ransac_syn_noise"])) ** 2))
    c.expect(rms <= bound, f"{case}: the pose is refit on all inliers",
             f"{case}: RMS reprojection error over the true inliers {rms:.3g} px, the reference's {ref:.3g} px (a pose "
             "from 6 points carries their noise): refit pnp_linear on ALL inliers of the best sample, then recompute "
             "the inliers")


def _iterations_verdict(c: Check, case: str, inl, it, max_iters: int = 1000) -> None:
    """n_iters adapts to the inlier ratio: about log(1 - p) / log(1 - w^6), never more than max_iters."""
    if it is None:
        c.fail(f"{case}: no n_iters returned: return (R_cw, t_cw, inliers, n_iters), the number of samples drawn")
        return
    need = samples_needed(float(inl.mean()), 6, 0.999, max_iters)
    ok = 1 <= it <= min(max_iters, 4 * need + 10) and it >= 0.25 * need - 1
    why = (f"n_iters = {it} > max_iters = {max_iters}" if it > max_iters else
           f"n_iters = {it}, while your inlier ratio {inl.mean():.0%} needs about {need:.0f} samples at confidence "
           "0.999: update the number of iterations N = log(1 - confidence) / log(1 - w^6) with the best inlier ratio "
           "w so far, and stop after N samples" if it >= 1 else f"n_iters = {it}: count the samples drawn")
    c.expect(ok, f"{case}: n_iters adapts to the inlier ratio", f"{case}: {why}")


def _confidence_verdict(c: Check, fn, f, case: str) -> None:
    """The confidence sets the count: at 0.99999 at least about log(1e-5) / log(1 - w^6) samples, more than at 0.9."""
    K, X, x = (f[f"ransac_syn_{s}"] for s in ("K", "X", "x"))
    runs = []
    for p in (0.9, 0.99999):
        # the same case: its verdict ("more samples for a higher confidence") answers both calls
        out = _ransac_fields(c.call(fn, X, x, K, np.random.default_rng(RANSAC_SEED), confidence=p, case=case),
                             c, case, len(X))
        if out is None:
            return
        runs.append(out)
    (_, _, _, lo), (_, _, inl, hi) = runs
    if lo is None or hi is None:
        return  # no n_iters: said above
    need = samples_needed(float(inl.mean()), 6, 0.99999, 1000)
    c.expect(lo <= hi and hi >= 0.7 * need, f"{case}: more samples for a higher confidence",
             f"{case}: n_iters = {lo} at confidence 0.9 and {hi} at 0.99999 ({inl.mean():.0%} inliers need about "
             f"{need:.0f} samples at 0.99999): the confidence argument must set the number of samples, "
             "N = log(1 - confidence) / log(1 - w^6)")


def _same_run(a, b) -> bool:
    return (np.allclose(a[0], b[0], atol=1e-12) and np.allclose(a[1], b[1], atol=1e-12) and a[2].shape == b[2].shape
            and np.array_equal(a[2], b[2]))


def _rng_verdicts(c: Check, fn, f) -> None:
    """A few samples per call (max_iters=3, noise comparable to the threshold): the rng argument is the only randomness.

    The same rng seed under two global np.random states gives the same result, the rng argument is drawn from
    (its state advances), and numpy's global state is left as it was.
    """
    K, X, x = (f[f"ransac_rng_{s}"] for s in ("K", "X", "x"))
    case = f"1 px noise, max_iters={RNG_MAX_ITERS}"
    runs, touched = [], False
    for global_seed in (11, 22):  # the global state must not matter
        out, moved = under_global_seed(global_seed, lambda: _ransac_fields(
            c.call(fn, X, x, K, np.random.default_rng(RNG_SEED), max_iters=RNG_MAX_ITERS, case=case), c, case, len(X)))
        touched = touched or moved
        if out is None:
            return
        runs.append(out)
    its = [r[3] for r in runs]
    # gates: a constant answer satisfies them as well as a right one
    c.gate(all(i is not None and 1 <= i <= RNG_MAX_ITERS for i in its), f"{case}: draws max_iters samples at most",
           f"{case}: n_iters = {its[0]} with max_iters={RNG_MAX_ITERS}: stop after max_iters samples and return "
           "their count")
    rng = np.random.default_rng(RNG_SEED + 1)
    before = rng.bit_generator.state
    ran = _ransac_fields(c.call(fn, X, x, K, rng, max_iters=RNG_MAX_ITERS, case=case), c, case, len(X)) is not None
    c.gate(_same_run(*runs), f"{case}: the same rng seed gives the same result",
           f"{case}: the same rng seed gave different results when np.random's global state changed: draw every "
           "sample from the rng argument (rng.choice(N, 6, replace=False)), not from np.random or a generator of "
           "your own")
    rng_verdicts(c, case, 6, touched, rng.bit_generator.state != before if ran else None)


def _minimal_verdict(c: Check, fn, f) -> None:
    """Exactly 6 noiseless points: the only sample of 6 distinct points is all of them, so the pose is exact and every
    point an inlier. A sample that holds a point twice has 5, which leave the DLT undetermined; the rng records the
    samples (:class:`~course_lib.checks.core.RecordingRng`), so such a sample is named when it is seen."""
    K, X, R, t, outl = (f[f"ransac_syn_{s}"] for s in ("K", "X", "R", "t", "outlier"))
    X = X[~outl.astype(bool)]
    X = X[world_to_camera(R, t, X)[:, 2] > 0][:6]
    x = project(K, R, t, X)
    case = "exactly 6 noiseless points"
    called = call_minimal(c, fn, X, x, K, k=6, item=("point", "points"), seed=RANSAC_SEED, case=case)
    out = None if called is None else _ransac_fields(called[0], c, case, len(X))
    if out is None:
        return
    Rs, ts, inl, it = out
    e = _errors(K, Rs, ts, X, x)
    minimal_verdict(c, called[1], 6, ("point", "points"), case, bool(inl.all()) and float(e.max()) < 0.05, it,
                    f"{case}: the pose reprojects all 6 points exactly",
                    f"{case}: {int(inl.sum())} of 6 inliers, largest reprojection error {float(e.max()):.3g} px; the "
                    "only sample of 6 distinct points is all of them, so the pose must reproject every point exactly")


def check_pnp_ransac(fn, exercise: str = "pnp_ransac") -> None:
    """Check ``fn(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000) -> PnPResult``.

    Cases: synthetic matches with 20 % outliers and a few points behind the camera (pose, inliers,
    outliers and points behind rejected, the mask of the returned pose, the refit, the adaptive count,
    the confidence), a case with 1 px noise called with ``threshold_px=3`` (the threshold in pixels),
    a case with 1 px noise called with ``max_iters=3`` (the rng argument as the only randomness), and
    the embedded scene.
    """
    f = load_fixture(FIXTURE)
    with Check(exercise) as c:
        thr = float(f["ransac_thr_threshold"])
        runs = []
        for key, case, threshold in (("ransac_syn", "synthetic view with 20 % outliers", None),
                                     ("ransac_thr", f"1 px noise, threshold_px={thr:g}", thr),
                                     ("ransac_embedded", "embedded scene", None)):
            if f"{key}_X" in f:
                run = _ransac_call(c, fn, f, key, case, threshold)
                if run is not None:
                    runs.append(run)
        named = unique_key([run["facts"]["keys"] for run in runs if run["facts"]["wrong"] > 0
                            or (run["key"] == "ransac_syn" and "no_cheirality" in run["facts"]["keys"])])
        pose_off = [run for run in runs if rotation_angle_deg(nearest_rotation(run["R"]), f[f"{run['key']}_R"]) > 1.0]
        pose_named = unique_key([_pose_keys(nearest_rotation(run["R"]), run["t"], f[f"{run['key']}_R"],
                                            f[f"{run['key']}_t"], 1.0, 0.05, dlt=False) for run in pose_off])
        # a function that finds no pose in any case (a constant, a stub) is not judged on how it samples: its
        # iteration count and its use of rng say nothing about a RANSAC that does not estimate
        no_pose = bool(runs) and len(pose_off) == len(runs)
        for run in runs:
            _ransac_verdicts(c, f, run, named, pose_named)
            if run["key"] == "ransac_syn" and no_pose:
                c.fail(f"{run['case']}: no case gives the pose (every rotation is more than 1° off): the number of "
                       "samples, the confidence and the use of rng are judged once pnp_ransac finds the pose")
            elif run["key"] == "ransac_syn":
                R, t, inl, it = run["R"], run["t"], run["inl"], run["it"]
                c.gate(np.allclose(R @ R.T, np.eye(3), atol=10 * RTOL) and np.linalg.det(R) > 0,
                       f"{run['case']}: R_cw is a rotation", f"{run['case']}: R_cw is not a rotation (orthonormal, "
                       "det +1): pnp_ransac returns what pnp_linear gives; orthogonalize R there (R = U Vᵀ)")
                _refit_verdict(c, f, run["case"], R, t)
                _iterations_verdict(c, run["case"], inl, it)
                _confidence_verdict(c, fn, f, run["case"])
        if not no_pose:
            _rng_verdicts(c, fn, f)
            _minimal_verdict(c, fn, f)
        c.blame_earlier("pnp_linear", fn=fn)


# --------------------------------------------------------------------------- pnp_nonlinear


_NONLINEAR_MISTAKES = {
    "nine": "you optimized the 9 entries of R (and projected the result back onto a rotation with an SVD): the solver "
            "then minimizes over matrices that are no rotations, and the projection moves it off the optimum; "
            "optimize a rotation vector (3 numbers, Rotation.from_rotvec) and t",
    "nodepth": "your residual is not divided by the depth: the pixel is (K x_cam)[:2] / (K x_cam)[2], minus the "
               "observed pixel",
    "only_t": "only t moved, R is the start's: optimize the rotation too (a rotation vector, 3 numbers, with the 3 of t)",
    "only_R": "only R moved, t is the start's: optimize t too (6 parameters: a rotation vector and t)",
    "transposed": _POSE_MISTAKES["transposed"],
    "C_for_t": _POSE_MISTAKES["C_for_t"],
    "t_sign": _POSE_MISTAKES["t_sign"],
    "early_stop": "not at the least-squares optimum: your optimiser stops before it converges (started again from its "
                  "own result, it moves on to the optimum): let it run to convergence (least_squares without "
                  "max_nfev and with its default tolerances, or enough iterations of your own loop)",
    "euler_mix": "your R is the optimum's rotation with its Euler angles read in one convention and turned back into "
                 "a matrix in another (as_euler('XYZ') then from_euler('xyz'), say: upper and lower case are "
                 "different conventions, intrinsic and extrinsic): use the same convention both ways, or a rotation "
                 "vector (Rotation.from_rotvec / as_rotvec)",
}

#: What to change when the refinement increases the error, and when it stops short of the optimum.
_NONLINEAR_ADVICE = ("the residual must be the projection K (R X + t) / z minus the observed pixels, with "
                     "R = Rotation.from_rotvec(p[:3]).as_matrix()",
                     "not at the least-squares optimum: minimize the sum of squared reprojection errors (pixels) over "
                     "all six parameters, to convergence")
#: The ways a parametrisation reads a rotation into 3 numbers and back: a rotation vector and the 12 Euler sequences,
#: extrinsic (lower case) and intrinsic (upper case).
_READINGS = ("rotvec",) + tuple(a for seq in ("xyz", "xzy", "yxz", "yzx", "zxy", "zyx") for a in (seq, seq.upper()))


def _euler_mix(R, R_r) -> bool:
    """Whether R is R_r read into 3 numbers in one way (:data:`_READINGS`) and turned back into a matrix in another."""
    from scipy.spatial.transform import Rotation

    off = rotation_angle_deg(R, R_r)
    if off < 0.05:
        return False
    tol = min(0.01, off / 5)
    rot = Rotation.from_matrix(R_r)
    for a in _READINGS:
        p = rot.as_rotvec() if a == "rotvec" else rot.as_euler(a)
        for b in _READINGS:
            if b != a and rotation_angle_deg((Rotation.from_rotvec(p) if b == "rotvec" else
                                              Rotation.from_euler(b, p)).as_matrix(), R) < tol:
                return True
    return False


def _wide_start(R, t, deg: float = 25.0, rel: float = 0.3):
    """A start far from the optimum ``(R, t)`` (``deg`` degrees, ``rel`` of |t|; every point stays in front)."""
    from scipy.spatial.transform import Rotation

    axis, d = np.array([1.0, -2.0, 0.5]), np.array([0.3, 1.0, -0.6])
    dR = Rotation.from_rotvec(np.radians(deg) * axis / np.linalg.norm(axis)).as_matrix()
    return dR @ R, t + rel * np.linalg.norm(t) * d / np.linalg.norm(d)


def _converges_when_restarted(fn, X, x, K, R, t, R_r, t_r, e_r: float, restarts: int = 5) -> bool:
    """Whether the student's refinement, started again from its own result (``restarts`` times at most), lowers the
    error at every call and reaches the optimum: the sign of an optimiser stopped before convergence."""
    e_prev = _rms(_errors(K, R, t, X, x))
    for _ in range(restarts):
        try:
            R, t = (np.asarray(v, float) for v in fn(X, x, K, R, t))
        except Exception:  # noqa: BLE001 - a diagnosis only: a call that fails says nothing about convergence
            return False
        if R.shape != (3, 3) or t.size != 3 or not np.isfinite(R).all() or not np.isfinite(t).all():
            return False
        t = t.reshape(3)
        e = _rms(_errors(K, R, t, X, x))
        if not e < e_prev * (1 - 1e-9):
            return False
        if e <= e_r * (1 + 1e-3) + 1e-6 and rotation_angle_deg(R, R_r) < 0.05:
            return True
        e_prev = e
    return False


def _nonlinear_keys(f, key: str, R, t, R0, t0, R_r, t_r) -> set[str]:
    """The classic mistakes of the refinement that explain what it returned (variants stored on the instructor's side)."""
    close = lambda Ra, ta, Rb, tb: rotation_angle_deg(Ra, Rb) < 0.02 and \
        np.linalg.norm(ta - tb) < 2e-3 * max(1.0, np.linalg.norm(tb))  # noqa: E731

    def like(name: str) -> bool:  # R as the stored mistake's, t along its direction where stored (not its length)
        Rm, d = f.get(f"{key}_mis_{name}_R"), f.get(f"{key}_mis_{name}_tdir")
        if Rm is None or not np.isfinite(t).all() or rotation_angle_deg(R, Rm) >= 0.02:
            return False
        return d is None or (np.linalg.norm(t) > 0 and abs(float(t @ d)) / np.linalg.norm(t) > 1 - 1e-4)

    out = set()
    for name in ("nine", "nodepth"):
        if like(name) and not close(R, t, R_r, t_r):
            out.add(name)
    if rotation_angle_deg(R, R0) < 1e-9 and not np.allclose(t, t0, atol=1e-12):
        out.add("only_t")
    if np.allclose(t, t0, atol=1e-12) and rotation_angle_deg(R, R0) > 1e-9:
        out.add("only_R")
    return out | (_pose_keys(R, t, R_r, t_r, 0.5, 0.05, dlt=False)[0] & {"transposed", "C_for_t", "t_sign"})


def _two_d_residual(exc: Exception) -> str | None:
    """least_squares' refusal of a 2-D residual, explained."""
    msg = str(exc).lower()
    if not isinstance(exc, ValueError) or ("dimension" not in msg and "1-d" not in msg and "1d" not in msg):
        return None
    return (f"your function raised ValueError: {str(exc)[:80]}: least_squares needs the residuals as a flat (1-d) "
            "vector of length 2N: return (projected - observed).ravel(), not an (N, 2) array")


def check_pnp_nonlinear(fn, exercise: str = "pnp_nonlinear") -> None:
    """Check ``fn(X, x, K, R_cw, t_cw) -> (R_cw, t_cw)``: from the linear estimate, from a start 3 degrees off, embedded."""
    f = load_fixture(FIXTURE)
    with Check(exercise) as c:
        results = []
        for key, case in (("nl_syn", "noisy synthetic view"), ("nl_far", "start 3° away from the optimum"),
                          ("nl_wide", "start 25° away from the optimum"), ("nl_embedded", "embedded scene")):
            if key == "nl_wide" and "nl_far_X" in f:  # the problem of nl_far, its optimum, started farther away
                K, X, x, R_r, t_r = (f[f"nl_far_{s}"] for s in ("K", "X", "x", "R", "t"))
                R0, t0 = _wide_start(R_r, t_r)
            elif f"{key}_X" not in f:
                continue
            else:
                K, X, x, R0, t0, R_r, t_r = (f[f"{key}_{s}"] for s in ("K", "X", "x", "R0", "t0", "R", "t"))
            out = _pose(c.call_explained(fn, X, x, K, R0, t0, case=case, explain=_two_d_residual), c, case)
            if out is None:
                continue
            R, t = out
            gap = float(np.abs(R @ R.T - np.eye(3)).max())
            if gap > 10 * RTOL or np.linalg.det(R) < 0:
                c.gate(False, "", f"{case}: the refined R_cw is not a rotation (R Rᵀ differs from I by {gap:.3g}, det "
                       f"{np.linalg.det(R):.3g}): optimize a rotation vector (3 numbers, Rotation.from_rotvec) or a "
                       "quaternion, so that R stays a rotation")
                continue
            if np.allclose(R, R0, atol=1e-12) and np.allclose(t, t0, atol=1e-12):
                c.fail(f"{case}: the pose did not move: return the optimized parameters (result.x), not the start")
                continue
            e0, e_r, e_s = (_rms(_errors(K, Rq, tq, X, x)) for Rq, tq in ((R0, t0), (R_r, t_r), (R, t)))
            ok = e_s <= e_r * (1 + 1e-3) + 1e-6 and rotation_angle_deg(R, R_r) < 0.05
            keys = set() if key == "nl_wide" else _nonlinear_keys(f, key, R, t, R0, t0, R_r, t_r)
            if not ok and np.linalg.norm(t - t_r) < 2e-3 * max(1.0, np.linalg.norm(t_r)) and _euler_mix(R, R_r):
                keys.add("euler_mix")
            if not ok and e_s < e0 and _converges_when_restarted(fn, X, x, K, R, t, R_r, t_r, e_r):
                keys.add("early_stop")
            results.append((key, case, R, t, e0, e_r, e_s, ok, R_r, keys))
        named = unique_key([(keys, None if key != "nl_wide" else {"euler_mix", "early_stop"})
                            for key, *_, ok, _, keys in results if not ok])
        for key, case, R, t, e0, e_r, e_s, ok, R_r, keys in results:
            refinement_verdicts(c, case, e0, e_s, ok, f"RMS reprojection error {e_s:.4g} px, "
                                f"{rotation_angle_deg(R, R_r):.2g}° from the optimum ({e_r:.4g} px)",
                                _NONLINEAR_MISTAKES[named] if named else None, _NONLINEAR_ADVICE, named)

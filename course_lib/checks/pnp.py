"""Checks of notebook 04 (PnP) and its step input.

Each ``check_*`` function runs the student's function on stored cases (fixture ``pnp``, built
in the instructor's kit from :mod:`course_lib.sfm.pnp` by ``python -m course_lib fixtures pnp``): a synthetic scene with
known truth and the embedded scene (``data/synthetic-building``: its third image registered
against the two-view reconstruction of step 3). It compares with the stored reference results
and with properties, and names the likely mistake:

* ``pnp_linear``: R not orthogonalized, det R = -1, ``R_cw`` vs ``R_wc`` (transposed), the centre
  ``C`` returned as ``t``, ``t`` not divided by the scale of ``R``, the sign of ``P`` not fixed
  (points behind the camera), the DLT on pixel instead of normalized coordinates.
* ``pnp_ransac``: inverted inlier mask; a mask that is not the inliers of the returned pose (the
  best sample's mask next to a refit pose, a squared error, an error in normalized coordinates,
  a constant instead of ``threshold_px``: each named by the threshold the mask obeys); no refit on
  the inliers (the RMS over the true inliers); a fixed iteration count or an ignored
  ``confidence``; randomness other than the ``rng`` argument (the same seed under two global
  ``np.random`` states must give the same result). In a notebook it runs the student's
  ``pnp_linear``; a failure then ends with a note when that one failed its own checks.
* ``pnp_nonlinear``: points that do not move, a rotation that is no rotation (the 9 entries),
  the 9 entries projected back with an SVD, a residual without the division by the depth (both
  also recognised from their results, computed on the instructor's side and stored with the
  cases), only t optimized, ``R_wc`` returned, stopping early (measured at the optimum, from a
  start 3° away).

Defining property (failing it costs at least half of the points): ``pnp_linear``'s R_cw is a
rotation (orthonormal, det +1), on the noiseless, noisy and embedded views.

The cases and the reference's results on them are stored arrays, made on the instructor's side
by :mod:`course_lib.instructor.cases.pnp`; this module imports no reference solution and ships
to students.
"""

from __future__ import annotations

import numpy as np

from course_lib.conventions import project, rotation_angle_deg, world_to_camera
from course_lib.checks.core import FAILED, Check, declare_defining, load_fixture

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


# --------------------------------------------------------------------------- step input


# --------------------------------------------------------------------------- fixtures


# --------------------------------------------------------------------------- helpers


def _pose(out, c: Check, case: str):
    """``(R (3, 3), t (3,))`` from the student's return value, or None after recording a failure."""
    if out is FAILED:
        return None
    if hasattr(out, "R_cw") and hasattr(out, "t_cw"):
        out = (out.R_cw, out.t_cw)
    if not isinstance(out, (tuple, list)) or len(out) < 2:
        c.fail(f"{case}: return the tuple (R_cw, t_cw), got {type(out).__name__}")
        return None
    try:
        R, t = np.asarray(out[0], float), np.asarray(out[1], float)
    except (TypeError, ValueError):
        c.fail(f"{case}: R_cw and t_cw must be numeric arrays")
        return None
    if R.shape != (3, 3) or t.size != 3:
        c.fail(f"{case}: R_cw must have shape (3, 3) and t_cw shape (3,), got {R.shape} and {t.shape}")
        return None
    if not (np.isfinite(R).all() and np.isfinite(t).all()):
        c.fail(f"{case}: R_cw or t_cw contains NaN or inf")
        return None
    return R, t.reshape(3)


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
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6):
        return c.fail(f"{case}: R_cw is not orthonormal (R Rᵀ ≠ I): you forgot to orthogonalize R; with "
                      "P[:, :3] = U S Vᵀ take R = U Vᵀ", defining=defining)
    if np.linalg.det(R) < 0:
        return c.fail(f"{case}: det R = -1 (a reflection): P is known only up to sign; when det P[:, :3] < 0 "
                      "flip the sign of P (R and t together)", defining=defining)
    if defining is not None:
        c.gate(True, f"{case}: R_cw is a rotation (orthonormal, det +1)", "", defining=defining)
    return True


def _pose_mistake(R, t, R_ref, t_ref, rot_tol, t_tol, dlt: bool = True) -> str | None:
    """Name a typical confusion when (R, t) is not (R_ref, t_ref) (with ``dlt``: also the DLT's scale of t)."""
    rot_ok = rotation_angle_deg(R, R_ref) < rot_tol
    near = lambda a, b: np.linalg.norm(a - b) < t_tol * max(1.0, np.linalg.norm(b))  # noqa: E731
    if not rot_ok and rotation_angle_deg(R.T, R_ref) < rot_tol:
        return "R_cw is transposed: you returned R_wc (world from camera); x_cam = R_cw X + t_cw"
    if rot_ok:
        C = -R_ref.T @ t_ref
        if near(t, C):
            return "t_cw is the camera centre C (C vs t confusion): t_cw = -R_cw @ C"
        if near(t, -t_ref):
            return "t_cw has the wrong sign, so the points end up behind the camera: flip R and t together"
        s = float(t @ t_ref / max(t_ref @ t_ref, 1e-300))
        if dlt and s > 0 and abs(s - 1) > 0.01 and near(t / s, t_ref):
            return (f"t_cw has the wrong scale (x{s:.3g}): divide P[:, 3] by the same scale as the rotation block, "
                    "t = P[:, 3] / σ with σ the singular values of P[:, :3]")
    if not rot_ok and rotation_angle_deg(-R, R_ref) < rot_tol:
        return "det R = -1: flip the sign of P when det P[:, :3] < 0"
    return None


# --------------------------------------------------------------------------- pnp_linear


def check_pnp_linear(fn, exercise: str = "pnp_linear") -> None:
    """Check ``fn(X, x, K) -> (R_cw, t_cw)`` on noiseless, noisy and embedded 2D-3D matches."""
    f = load_fixture(FIXTURE)
    with Check(exercise) as c:
        # noiseless: exact
        K, X, x, R_t, t_t = (f[f"lin_noiseless_{s}"] for s in ("K", "X", "x", "R", "t"))
        out = _pose(c.call(fn, X, x, K, case="noiseless synthetic view"), c, "noiseless synthetic view")
        if out is not None and _rotation_verdict(c, out[0], "noiseless synthetic view", defining="R is a rotation"):
            R, t = out
            ok = rotation_angle_deg(R, R_t) < 1e-4 and np.linalg.norm(t - t_t) < 1e-6 * max(1.0, np.linalg.norm(t_t))
            if ok:
                c.expect(True, "noiseless synthetic view: recovers the true pose exactly", "")
            else:
                why = _pose_mistake(R, t, R_t, t_t, 1e-3, 1e-4) or _pixel_hint(R, K, R_t) or (
                    "check the two equations per point, u_n (p3ᵀX) - p1ᵀX = 0 and v_n (p3ᵀX) - p2ᵀX = 0, "
                    "with x_n = K⁻¹ x (normalized coordinates)")
                c.fail(f"noiseless synthetic view: rotation error {rotation_angle_deg(R, R_t):.3g}°, "
                       f"translation error {np.linalg.norm(t - t_t):.3g}: {why}")
        # noisy and embedded: close to the reference
        for key, case in (("lin_noisy", "noisy synthetic view"), ("lin_embedded", "embedded scene")):
            if f"{key}_X" not in f:
                continue
            K, X, x, R_r, t_r = (f[f"{key}_{s}"] for s in ("K", "X", "x", "R", "t"))
            out = _pose(c.call(fn, X, x, K, case=case), c, case)
            if out is None or not _rotation_verdict(c, out[0], case, defining="R is a rotation"):
                continue
            R, t = out
            e_s, e_r = _rms(_errors(K, R, t, X, x)), _rms(_errors(K, R_r, t_r, X, x))
            t_close = np.linalg.norm(t - t_r) <= 0.05 * np.linalg.norm(t_r)  # t = P[:, 3] / σ is a few % off
            if rotation_angle_deg(R, R_r) < 0.5 and (t_close or e_s <= 1.5 * e_r + 0.5):
                c.expect(True, f"{case}: close to the reference pose", "")
                continue
            why = _pose_mistake(R, t, R_r, t_r, 0.5, 0.05)
            if why is None and key == "lin_noisy" and rotation_angle_deg(R, f["lin_noisy_pixel_R"]) < 0.05:
                why = ("the DLT ran on pixel coordinates: use normalized coordinates x_n = K⁻¹ [u, v, 1]ᵀ, so that "
                       "P = λ [R | t] holds no K")
            if why is None:
                why = "check the equations on normalized coordinates x_n = K⁻¹ x and the orthogonalization R = U Vᵀ"
            c.fail(f"{case}: rotation {rotation_angle_deg(R, R_r):.3g}° from the reference, RMS reprojection error "
                   f"{e_s:.3g} px (reference {e_r:.3g} px): {why}")


def _pixel_hint(R, K, R_true) -> str | None:
    """The rotation a DLT on pixel coordinates gives on noiseless data: the orthogonalized K R."""
    U, _, Vt = np.linalg.svd(K @ R_true)
    if rotation_angle_deg(R, U @ Vt) < 0.05:
        return ("the DLT ran on pixel coordinates: use normalized coordinates x_n = K⁻¹ [u, v, 1]ᵀ, so that "
                "P = λ [R | t] holds no K")
    return None


# --------------------------------------------------------------------------- pnp_ransac


def _ransac_fields(out, c: Check, case: str, n: int):
    """``(R, t, inliers (n,) bool, n_iters or None)`` from the student's return value, or None after a failure."""
    if out is FAILED:
        return None
    if all(hasattr(out, a) for a in ("R_cw", "t_cw", "inliers")):
        R, t, inl, it = out.R_cw, out.t_cw, out.inliers, getattr(out, "n_iters", None)
    elif isinstance(out, (tuple, list)) and len(out) >= 3:
        R, t, inl = out[:3]
        it = out[3] if len(out) > 3 else None
    else:
        c.fail(f"{case}: return a PnPResult(R_cw, t_cw, inliers, n_iters), got {type(out).__name__}")
        return None
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


def _nearest_rotation(R: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(R)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def _iterations_needed(w: float, confidence: float, max_iters: int) -> float:
    """Adaptive RANSAC's count for inlier ratio ``w`` and 6-point samples."""
    if w >= 1.0:
        return 1.0
    if w <= 0.0:
        return float(max_iters)
    return min(float(max_iters), np.log(1.0 - confidence) / np.log(1.0 - w**6))


def _mask_verdict(c: Check, case: str, inl, e, thr: float) -> None:
    """The returned mask must be the inliers of the returned pose (reprojection error below the threshold, in pixels)."""
    tie = np.abs(e - thr) <= 1e-6 * thr  # a point at the threshold may go either way
    bad = (inl != (e < thr)) & ~tie
    if not bad.any():
        c.expect(True, f"{case}: the inliers are the points within threshold_px of the returned pose", "")
        return
    with np.errstate(invalid="ignore"):
        if np.array_equal(inl, e**2 < thr):
            why = (f"the inliers are the points whose SQUARED error is below threshold_px: compare the reprojection "
                   f"error itself (pixels) with threshold_px = {thr:g}")
        elif thr != THRESHOLD_PX and np.array_equal(inl, e < THRESHOLD_PX):
            why = (f"the inliers are the points within {THRESHOLD_PX:g} px, but threshold_px = {thr:g} was passed: use "
                   "the threshold_px argument, not a constant")
        elif inl.sum() > 0.9 * len(inl) and (e[inl] > 10 * thr).any():
            why = ("points with errors of many pixels are marked as inliers: measure the reprojection error in pixels "
                   "(project with K), not in normalized coordinates")
        else:
            why = ("the mask belongs to another pose than the one returned (the best sample's?): after the refit, "
                   "recompute the inliers with the final pose")
    c.fail(f"{case}: {int(bad.sum())} points are labelled against the returned pose's reprojection errors: {why}")


def _ransac_pose(c: Check, case: str, R, t, inl, e, thr, R_r, t_r, n_r: int) -> bool:
    """The pose near the reference's (rotation within 1 degree); a failure names the likely confusion."""
    rot = rotation_angle_deg(_nearest_rotation(R), R_r)
    if rot <= 1.0:
        return c.expect(True, f"{case}: finds the pose despite the outliers", "")
    far = inl.sum() >= n_r + 0.5 * (len(inl) - n_r) and \
        np.median(np.where(np.isfinite(e[inl]), e[inl], 1e9)) > 10 * thr  # (nearly) everything is an inlier
    why = _pose_mistake(_nearest_rotation(R), t, R_r, t_r, 1.0, 0.05)
    why = why or ("the points you mark as inliers reproject far beyond threshold_px from your pose: measure the "
                  "reprojection error in pixels (project with K), not in normalized coordinates" if far else None)
    why = why or (
        "score each sample by the reprojection error in pixels of ALL points and keep the best; then refit on its inliers")
    return c.fail(f"{case}: rotation {rot:.3g}° from the reference ({int(inl.sum())} inliers, reference {n_r}): {why}")


def _ransac_case(c: Check, fn, f, key: str, case: str, threshold: float | None = None):
    """One call on a stored case; the pose, the inliers, the rejected outliers, the mask. Returns the fields or None."""
    K, X, x, R_r, t_r, inl_r = (f[f"{key}_{s}"] for s in ("K", "X", "x", "R", "t", "inliers"))
    kw = {} if threshold is None else {"threshold_px": threshold}
    out = _ransac_fields(c.call(fn, X, x, K, np.random.default_rng(RANSAC_SEED), case=case, **kw), c, case, len(X))
    if out is None:
        return None
    R, t, inl, it = out
    thr = THRESHOLD_PX if threshold is None else threshold
    if float((~inl == inl_r).mean()) > 0.9 and float((inl == inl_r).mean()) < 0.5:
        c.fail(f"{case}: the inlier mask is inverted: inliers are the points with reprojection error BELOW the threshold")
        return None
    e = _errors(K, R, t, X, x)
    if not _ransac_pose(c, case, R, t, inl, e, thr, R_r, t_r, int(inl_r.sum())):
        return None
    agree = float((inl == inl_r).mean())
    c.expect(agree > 0.9, f"{case}: the inliers agree with the reference",
             f"{case}: only {agree:.0%} of the inlier labels agree with the reference ({int(inl.sum())} inliers, "
             f"reference {int(inl_r.sum())}): inliers are the points with reprojection error below threshold_px "
             f"= {thr:g} (pixels, in front of the camera)")
    if f"{key}_outlier" in f:
        outl = f[f"{key}_outlier"]
        c.expect((inl & outl).sum() <= 0.02 * len(X), f"{case}: rejects the outliers",
                 f"{case}: {int((inl & outl).sum())} injected outliers are marked as inliers")
    _mask_verdict(c, case, inl, e, thr)
    return R, t, inl, it, e


def _refit_verdict(c: Check, f, case: str, R, t) -> None:
    """A pose refit on all inliers reprojects the true inliers nearly as well as the reference's."""
    K, X, x, outl = (f[f"ransac_syn_{s}"] for s in ("K", "X", "x", "outlier"))
    rms = _rms(_errors(K, R, t, X[~outl], x[~outl]))
    ref = _rms(_errors(K, f["ransac_syn_R"], f["ransac_syn_t"], X[~outl], x[~outl]))
    bound = float(np.sqrt(ref**2 + (0.5 * float(f["ransac_syn_noise"])) ** 2))
    c.expect(rms <= bound, f"{case}: the pose is refit on all inliers",
             f"{case}: RMS reprojection error over the true inliers {rms:.3g} px, the reference's {ref:.3g} px: refit "
             "pnp_linear on ALL inliers of the best sample (a pose from 6 points carries their noise), then "
             "recompute the inliers")


def _iterations_verdict(c: Check, case: str, inl, it, max_iters: int = 1000) -> None:
    """n_iters adapts to the inlier ratio: about log(1 - p) / log(1 - w^6), never more than max_iters."""
    if it is None:
        c.fail(f"{case}: no n_iters returned: return (R_cw, t_cw, inliers, n_iters), the number of samples drawn")
        return
    need = _iterations_needed(float(inl.mean()), 0.999, max_iters)
    ok = 1 <= it <= min(max_iters, 4 * need + 10)
    why = (f"n_iters = {it} > max_iters = {max_iters}" if it > max_iters else
           f"n_iters = {it} although {inl.mean():.0%} inliers need about {need:.0f} samples at confidence 0.999: "
           "update the number of iterations N = log(1 - confidence) / log(1 - w^6) with the best inlier ratio w "
           "so far, and stop after N samples" if it >= 1 else f"n_iters = {it}: count the samples drawn")
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
    need = _iterations_needed(float(inl.mean()), 0.99999, 1000)
    c.expect(lo <= hi and hi >= 0.7 * need, f"{case}: more samples for a higher confidence",
             f"{case}: n_iters = {lo} at confidence 0.9 and {hi} at 0.99999 ({inl.mean():.0%} inliers need about "
             f"{need:.0f} samples at 0.99999): the confidence argument must set the number of samples, "
             "N = log(1 - confidence) / log(1 - w^6)")


def _rng_verdicts(c: Check, fn, f) -> None:
    """A few samples per call (max_iters=3, noise comparable to the threshold): the same rng seed, the same result."""
    K, X, x = (f[f"ransac_rng_{s}"] for s in ("K", "X", "x"))
    case = f"1 px noise, max_iters={RNG_MAX_ITERS}"
    saved = np.random.get_state()
    runs = []
    try:
        for global_seed in (11, 22):
            np.random.seed(global_seed)  # the global state must not matter
            out = _ransac_fields(c.call(fn, X, x, K, np.random.default_rng(RNG_SEED), max_iters=RNG_MAX_ITERS,
                                        case=case), c, case, len(X))
            if out is None:
                return
            runs.append(out)
    finally:
        np.random.set_state(saved)
    its = [r[3] for r in runs]
    # gates: a constant answer satisfies both as well as a right one
    c.gate(all(i is not None and 1 <= i <= RNG_MAX_ITERS for i in its), f"{case}: draws max_iters samples at most",
             f"{case}: n_iters = {its[0]} with max_iters={RNG_MAX_ITERS}: stop after max_iters samples and return "
             "their count")
    a, b = runs
    same = np.allclose(a[0], b[0], atol=1e-12) and np.allclose(a[1], b[1], atol=1e-12) and np.array_equal(a[2], b[2])
    c.gate(same, f"{case}: the same rng seed gives the same result",
             f"{case}: the same rng seed gave different results when np.random's global state changed: draw every "
             "sample from the rng argument (rng.choice(N, 6, replace=False)), not from np.random or a generator of "
             "your own")


def check_pnp_ransac(fn, exercise: str = "pnp_ransac") -> None:
    """Check ``fn(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000) -> PnPResult``.

    Cases: synthetic matches with 20 % outliers (pose, inliers, outliers rejected, the mask of the
    returned pose, the refit, the adaptive count, the confidence), a case with 1 px noise called
    with ``threshold_px=3`` (the threshold in pixels), a case with 1 px noise called with
    ``max_iters=3`` twice, with the same rng seed and another global ``np.random`` state (the
    ``rng`` argument is the only randomness), and the embedded scene.
    """
    f = load_fixture(FIXTURE)
    with Check(exercise) as c:
        case = "synthetic view with 20 % outliers"
        got = _ransac_case(c, fn, f, "ransac_syn", case)
        if got is not None:
            R, t, inl, it, _ = got
            c.gate(np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0,
                   f"{case}: R_cw is a rotation", f"{case}: R_cw is not a rotation (orthonormal, det +1): pnp_ransac "
                   "returns what pnp_linear gives; orthogonalize R there (R = U Vᵀ)")
            _refit_verdict(c, f, case, R, t)
            _iterations_verdict(c, case, inl, it)
            _confidence_verdict(c, fn, f, case)
        thr = float(f["ransac_thr_threshold"])
        _ransac_case(c, fn, f, "ransac_thr", f"1 px noise, threshold_px={thr:g}", threshold=thr)
        _rng_verdicts(c, fn, f)
        if "ransac_embedded_X" in f:
            _ransac_case(c, fn, f, "ransac_embedded", "embedded scene")
        c.blame_earlier("pnp_linear", fn=fn)


# --------------------------------------------------------------------------- pnp_nonlinear


def _nonlinear_mistake(f, key: str, R, t, R0, t0, R_r, t_r) -> str | None:
    """Name a classic mistake of the refinement from what it returned (variants computed on the instructor's side)."""
    close = lambda Ra, ta, Rb, tb: rotation_angle_deg(Ra, Rb) < 0.02 and \
        np.linalg.norm(ta - tb) < 2e-3 * max(1.0, np.linalg.norm(tb))  # noqa: E731

    def like(name: str) -> bool:  # R as the stored mistake's, t along its direction where stored (not its length)
        Rm, d = f.get(f"{key}_mis_{name}_R"), f.get(f"{key}_mis_{name}_tdir")
        if Rm is None or not np.isfinite(t).all() or rotation_angle_deg(R, Rm) >= 0.02:
            return False
        return d is None or (np.linalg.norm(t) > 0 and abs(float(t @ d)) / np.linalg.norm(t) > 1 - 1e-4)
    scale = float(t @ t_r / max(float(t_r @ t_r), 1e-300))
    scaled = rotation_angle_deg(R, R_r) < 0.5 and scale > 0 and abs(scale - 1) > 0.01 and \
        np.linalg.norm(t / scale - t_r) < 0.05 * np.linalg.norm(t_r)  # R and t drifted together, R then projected
    if scaled or (like("nine") and not close(R, t, R_r, t_r)):
        return ("you optimized the 9 entries of R (and projected the result back onto a rotation with an SVD): the "
                "solver then minimizes over matrices that are no rotations, and the projection moves it off the "
                "optimum; optimize a rotation vector (3 numbers, Rotation.from_rotvec) and t")
    if like("nodepth") and not close(R, t, R_r, t_r):
        return ("the residual is not divided by the depth: the pixel is (K x_cam)[:2] / (K x_cam)[2], minus the "
                "observed pixel")
    if rotation_angle_deg(R, R0) < 1e-9 and not np.allclose(t, t0, atol=1e-12):
        return "only t moved: optimize the rotation too (a rotation vector, 3 numbers, with the 3 of t)"
    return _pose_mistake(R, t, R_r, t_r, 0.5, 0.05, dlt=False)


def check_pnp_nonlinear(fn, exercise: str = "pnp_nonlinear") -> None:
    """Check ``fn(X, x, K, R_cw, t_cw) -> (R_cw, t_cw)``: from the linear estimate, from a start 3 degrees off, embedded."""
    f = load_fixture(FIXTURE)
    with Check(exercise) as c:
        for key, case in (("nl_syn", "noisy synthetic view"), ("nl_far", "start 3° away from the optimum"),
                          ("nl_embedded", "embedded scene")):
            if f"{key}_X" not in f:
                continue
            K, X, x, R0, t0, R_r, t_r = (f[f"{key}_{s}"] for s in ("K", "X", "x", "R0", "t0", "R", "t"))
            out = _pose(c.call(fn, X, x, K, R0, t0, case=case), c, case)
            if out is None:
                continue
            R, t = out
            if not (np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0):
                c.gate(False, "", f"{case}: the refined R_cw is not a rotation: optimize a rotation vector (3 numbers, "
                       "Rotation.from_rotvec) or a quaternion, not the 9 entries of R")
                continue
            if np.allclose(R, R0, atol=1e-12) and np.allclose(t, t0, atol=1e-12):
                c.fail(f"{case}: the pose did not move: return the optimized parameters (result.x), not the start")
                continue
            e0, e_r, e_s = (_rms(_errors(K, Rq, tq, X, x)) for Rq, tq in ((R0, t0), (R_r, t_r), (R, t)))
            why = _nonlinear_mistake(f, key, R, t, R0, t0, R_r, t_r)
            if not c.gate(e_s <= e0 * (1 + 1e-9) + 1e-9, f"{case}: lowers the reprojection error",
                          f"{case}: the refinement increased the RMS reprojection error ({e0:.3g} -> {e_s:.3g} px): "
                          + (why or "the residual must be the projection K (R X + t) / z minus the observed pixels, "
                                    "with R = Rotation.from_rotvec(p[:3]).as_matrix()")):
                continue
            rot = rotation_angle_deg(R, R_r)
            c.expect(e_s <= e_r * (1 + 1e-3) + 1e-6 and rot < 0.05, f"{case}: reaches the least-squares optimum",
                     f"{case}: RMS reprojection error {e_s:.4g} px, {rot:.2g}° from the optimum ({e_r:.4g} px): "
                     + (why or "not at the least-squares optimum: let least_squares run to convergence (its default "
                                "tolerances) over all six parameters"))

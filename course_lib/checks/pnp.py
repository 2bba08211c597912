"""Checks of notebook 04 (PnP) and its step input.

Each ``check_*`` function runs the student's function on stored cases (fixture ``pnp``, built
from :mod:`course_lib.sfm.pnp` by ``python -m course_lib fixtures pnp``): a synthetic scene with
known truth and the embedded scene (``data/synthetic-building``: its third image registered
against the two-view reconstruction of step 3). It compares with the stored reference results
and with properties, and names the likely mistake:

* ``pnp_linear``: R not orthogonalized, det R = -1, ``R_cw`` vs ``R_wc`` (transposed), the centre
  ``C`` returned as ``t``, ``t`` not divided by the scale of ``R``, the sign of ``P`` not fixed
  (points behind the camera), the DLT on pixel instead of normalized coordinates.
* ``pnp_ransac``: inverted inlier mask, squared error compared with the pixel threshold (named
  also when it only shifts a few inlier labels),
  a pose that is not refit on the inliers, too few or too many iterations.
* ``pnp_nonlinear``: a step that increases the error (a residual without the division by the
  depth), points that do not move, a rotation that is no rotation (optimizing the 9 entries),
  stopping early.

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


def _pose_mistake(R, t, R_ref, t_ref, rot_tol, t_tol) -> str | None:
    """Name a typical confusion when (R, t) is not (R_ref, t_ref)."""
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
        if s > 0 and abs(s - 1) > 0.01 and near(t / s, t_ref):
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
    return pose[0], pose[1], inl, it


def check_pnp_ransac(fn, exercise: str = "pnp_ransac") -> None:
    """Check ``fn(X, x, K, rng) -> PnPResult`` on synthetic matches with 20 % outliers and on the embedded scene."""
    f = load_fixture(FIXTURE)
    with Check(exercise) as c:
        for key, case in (("ransac_syn", "synthetic view with 20 % outliers"), ("ransac_embedded", "embedded scene")):
            if f"{key}_X" not in f:
                continue
            K, X, x, R_r, t_r, inl_r = (f[f"{key}_{s}"] for s in ("K", "X", "x", "R", "t", "inliers"))
            out = _ransac_fields(c.call(fn, X, x, K, np.random.default_rng(RANSAC_SEED), case=case), c, case, len(X))
            if out is None:
                continue
            R, t, inl, it = out
            if not _rotation_verdict(c, R, case):
                continue
            agree = float((inl == inl_r).mean())
            if agree < 0.5 and float((~inl == inl_r).mean()) > 0.9:
                c.fail(f"{case}: the inlier mask is inverted: inliers are the points with reprojection error BELOW the threshold")
                continue
            e = _errors(K, R, t, X, x)
            n_r = int(inl_r.sum())
            rot = rotation_angle_deg(R, R_r)
            if rot > 1.0:
                why = _pose_mistake(R, t, R_r, t_r, 1.0, 0.05) or (
                    "score each sample by the reprojection error in pixels of ALL points and keep the best; "
                    "then refit on its inliers")
                c.fail(f"{case}: rotation {rot:.3g}° from the reference ({int(inl.sum())} inliers, reference {n_r}): {why}")
                continue
            c.expect(True, f"{case}: finds the pose despite the outliers", "")
            if inl.sum() < 0.85 * n_r:
                below = int((e < THRESHOLD_PX).sum())
                hint = ("did you compare the squared error with the threshold? compare the distance in pixels"
                        if (e < np.sqrt(THRESHOLD_PX)).sum() >= 0.9 * inl.sum() else
                        "refit the pose on all inliers of the best sample and recompute the inliers with the refit "
                        "pose; in pnp_linear re-estimate t with R fixed (t = P[:, 3] / σ is too noisy)")
                c.fail(f"{case}: {int(inl.sum())} inliers, the reference finds {n_r} ({below} points are within "
                       f"{THRESHOLD_PX:g} px of your pose): {hint}")
            else:
                squared = e**2 < THRESHOLD_PX
                right = e < THRESHOLD_PX
                if agree <= 0.9 and not np.array_equal(squared, right) and float((inl == squared).mean()) > 0.97 \
                        and float((inl == squared).mean()) > float((inl == right).mean()) + 0.02:
                    why = (f"the inliers are the points whose SQUARED error is below threshold_px: compare the "
                           f"reprojection error itself (pixels) with threshold_px = {THRESHOLD_PX:g}")
                else:
                    why = (f"inliers are the points with reprojection error below threshold_px = {THRESHOLD_PX:g} "
                           "(in front of the camera)")
                c.expect(agree > 0.9, f"{case}: the inliers agree with the reference",
                         f"{case}: only {agree:.0%} of the inlier labels agree with the reference: {why}")
            if f"{key}_outlier" in f:
                outl = f[f"{key}_outlier"]
                c.expect((inl & outl).sum() <= 0.02 * len(X), f"{case}: rejects the outliers",
                         f"{case}: {int((inl & outl).sum())} injected outliers are marked as inliers")
            if it is not None:
                try:
                    it = int(it)
                except (TypeError, ValueError):
                    it = -1
                c.expect(1 <= it <= 1000, f"{case}: n_iters is within the limit",
                         f"{case}: n_iters = {it}: count the samples drawn (1 <= n_iters <= max_iters)")


# --------------------------------------------------------------------------- pnp_nonlinear


def check_pnp_nonlinear(fn, exercise: str = "pnp_nonlinear") -> None:
    """Check ``fn(X, x, K, R_cw, t_cw) -> (R_cw, t_cw)`` from the linear estimate, synthetic and embedded."""
    f = load_fixture(FIXTURE)
    with Check(exercise) as c:
        for key, case in (("nl_syn", "noisy synthetic view"), ("nl_embedded", "embedded scene")):
            if f"{key}_X" not in f:
                continue
            K, X, x, R0, t0, R_r, t_r = (f[f"{key}_{s}"] for s in ("K", "X", "x", "R0", "t0", "R", "t"))
            out = _pose(c.call(fn, X, x, K, R0, t0, case=case), c, case)
            if out is None:
                continue
            R, t = out
            if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
                c.fail(f"{case}: the refined R_cw is not a rotation: optimize a rotation vector (3 numbers, "
                       "Rotation.from_rotvec) or a quaternion, not the 9 entries of R")
                continue
            e0, e_r, e_s = (_rms(_errors(K, Rq, tq, X, x)) for Rq, tq in ((R0, t0), (R_r, t_r), (R, t)))
            if np.allclose(R, R0, atol=1e-12) and np.allclose(t, t0, atol=1e-12):
                c.fail(f"{case}: the pose did not move: return the optimized parameters (result.x), not the start")
                continue
            if e_s > e0 * (1 + 1e-9) + 1e-9:
                why = _pose_mistake(R, t, R_r, t_r, 0.5, 0.05) or (
                    "check the residual: the projection K (R X + t) divided by its depth z (the usual slip is a "
                    "residual without that division), minus the observed pixels; and convert the rotation vector "
                    "back with Rotation.from_rotvec(...).as_matrix()")
                c.fail(f"{case}: the non-linear step increased the reprojection error ({e0:.3g} -> {e_s:.3g} px): {why}")
                continue
            c.gate(True, f"{case}: lowers the reprojection error", "")
            c.expect(e_s <= e_r * (1 + 1e-3) + 1e-6 and rotation_angle_deg(R, R_r) < 0.05,
                     f"{case}: reaches the least-squares optimum",
                     f"{case}: RMS reprojection error {e_s:.4g} px, the optimum is {e_r:.4g} px: run the solver to convergence")

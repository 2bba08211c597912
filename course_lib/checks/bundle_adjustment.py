"""Checks of notebook 05 (bundle adjustment) and its step input.

Each ``check_*`` function runs the student's function on stored cases (fixture
``bundle_adjustment``, built from :mod:`course_lib.sfm.visibility` and
:mod:`course_lib.sfm.bundle_adjustment` by ``python -m course_lib fixtures bundle_adjustment``):
small synthetic scenes with known truth and the embedded scene's reconstruction before bundle
adjustment. It compares with the stored reference results and with properties, and names the
likely mistake:

* ``visibility_matrix``: the matrix transposed (cameras as rows, the handout's ``V_ij`` layout),
  True where a point is *not* seen, ints instead of bools.
* ``reprojection_residuals``: a (K, 2) array instead of the flat (2K,) vector, all u's before
  all v's, ``R_wc`` instead of ``R_cw``, no division by the depth, a parameter layout other than
  ``[r_0, t_0, r_1, t_1, ..., X_0, X_1, ...]``, K applied twice or not at all.
* ``jacobian_sparsity``: 9 parameters per camera (the SciPy cookbook's cameras carry f, k1, k2;
  here K is fixed), point columns without the ``6M`` offset (named), rows of u and v not interleaved,
  the matrix transposed.
* ``bundle_adjust``: the cost does not reach the reference minimum, cameras far from the
  reference solution (after a similarity alignment), rotations that are no rotations, NaNs, a
  callback that is never called.

The cases and the reference's results on them are stored arrays, made on the instructor's side
by :mod:`course_lib.instructor.cases.bundle_adjustment`; this module imports no reference solution and ships
to students.
"""

from __future__ import annotations

import numpy as np

from course_lib.conventions import camera_center, rotation_angle_deg
from course_lib.checks.core import FAILED, Check, load_fixture
from course_lib.steps import observation_arrays

__all__ = [
    "check_visibility_matrix",
    "check_reprojection_residuals",
    "check_jacobian_sparsity",
    "check_bundle_adjustment",
]

FIXTURE = "bundle_adjustment"


# --------------------------------------------------------------------------- helpers (no reference needed)


def _rotvec(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


def _pack(R, t, X) -> np.ndarray:
    cams = np.hstack([_rotvec(np.asarray(R, float).reshape(-1, 3, 3)), np.asarray(t, float).reshape(-1, 3)])
    return np.concatenate([cams.ravel(), np.asarray(X, float).ravel()])


def _residuals_np(params, M, N, cam, pt, uv, K, transpose_R=False, divide=True, layout="cams_first"):
    """The reference residual written again for the mistake diagnosis (variants named by the flags)."""
    from scipy.spatial.transform import Rotation

    if layout == "cams_first":
        cams, X = params[: 6 * M].reshape(M, 6), params[6 * M :].reshape(N, 3)
    else:
        X, cams = params[: 3 * N].reshape(N, 3), params[3 * N :].reshape(M, 6)
    R = Rotation.from_rotvec(cams[:, :3]).as_matrix().reshape(M, 3, 3)
    if transpose_R:
        R = np.transpose(R, (0, 2, 1))
    xc = (R[cam] * X[pt][:, None, :]).sum(axis=2) + cams[cam, 3:]
    xh = xc @ np.asarray(K, float).T
    proj = xh[:, :2] / xh[:, 2:3] if divide else xh[:, :2]
    return (proj - uv).ravel()


def _as_array(out, c: Check, case: str):
    if out is FAILED:
        return None
    try:
        import scipy.sparse as sp

        if sp.issparse(out):
            return out
        return np.asarray(out)
    except (TypeError, ValueError):
        c.fail(f"{case}: return a numpy array, got {type(out).__name__}")
        return None


# --------------------------------------------------------------------------- step input


# --------------------------------------------------------------------------- fixtures


# --------------------------------------------------------------------------- visibility_matrix


def check_visibility_matrix(fn, exercise: str = "visibility_matrix") -> None:
    """Check ``fn(track_uv (T, M, 2)) -> (T, M) bool`` on a synthetic case and the embedded tracks."""
    f = load_fixture(FIXTURE)
    cases = [("synthetic tracks", f["vis_track_uv"], f["vis_expected"])]
    if "emb_track_uv" in f:
        cases.append(("embedded scene tracks", f["emb_track_uv"], np.isfinite(f["emb_track_uv"]).all(axis=2)))
    with Check(exercise) as c:
        for case, uv, expected in cases:
            V = _as_array(c.call(fn, uv, case=case), c, case)
            if V is None:
                continue
            T, M = expected.shape
            if V.shape == (M, T) and V.shape != (T, M):
                c.fail(f"{case}: V has shape {V.shape}, expected ({T}, {M}): the kit stores points as rows, "
                       "V[j, i] for point j and image i (the transpose of the handout's V_ij)")
                continue
            if not c.shape(V, (T, M), f"{case}: V"):
                continue
            if V.dtype != bool:
                c.fail(f"{case}: V has dtype {V.dtype}: return a bool array (e.g. ~np.isnan(track_uv[..., 0]))")
                continue
            if np.array_equal(V, ~expected):
                c.fail(f"{case}: V is inverted: it must be True where the point IS seen (the pixel is not NaN)")
                continue
            c.expect(np.array_equal(V, expected), f"{case}: V[j, i] is True exactly where point j is seen in image i",
                     f"{case}: {int((V != expected).sum())} entries differ from the NaN pattern of track_uv")


# --------------------------------------------------------------------------- reprojection_residuals


def check_reprojection_residuals(fn, exercise: str = "reprojection_residuals") -> None:
    """Check ``fn(params, n_cameras, n_points, camera_idx, point_idx, uv, K) -> (2K,)``."""
    f = load_fixture(FIXTURE)
    with Check(exercise) as c:
        p, M, N = f["res_syn_params"], int(f["res_syn_M"]), int(f["res_syn_N"])
        cam, pt, uv, K = f["res_syn_camera_idx"], f["res_syn_point_idx"], f["res_syn_uv"], f["res_syn_K"]
        exp = f["res_syn_expected"]
        case = "perturbed synthetic scene"
        r = _as_array(c.call(fn, p, M, N, cam, pt, uv, K, case=case), c, case)
        if r is not None:
            if r.shape == (len(cam), 2):
                c.fail(f"{case}: r has shape {r.shape}: return the flat vector r.ravel() of shape ({2 * len(cam)},), "
                       "[u_0' - u_0, v_0' - v_0, u_1' - u_1, ...]")
            elif c.shape(r, (2 * len(cam),), f"{case}: r"):
                r = r.astype(float)
                tol = 1e-6 * (1 + np.abs(exp).max())
                if np.abs(r - exp).max() < tol:
                    c.expect(True, f"{case}: equals the reference (projected minus observed, u and v interleaved)", "")
                elif np.abs(r + exp).max() < tol:
                    c.expect(True, f"{case}: equals the reference up to the sign (observed minus projected works too)", "")
                else:
                    c.fail(f"{case}: max difference {np.abs(r - exp).max():.3g} px from the reference: "
                           + _residual_mistake(r, p, M, N, cam, pt, uv, K, exp))
        # zero at the truth
        case = "true cameras and points, noiseless pixels"
        p_t = f["res_true_params"]
        cam_t, pt_t, uv_t = f["res_true_camera_idx"], f["res_true_point_idx"], f["res_true_uv"]
        r = _as_array(c.call(fn, p_t, M, N, cam_t, pt_t, uv_t, K, case=case), c, case)
        if r is not None and np.size(r) == 2 * len(cam_t):
            r = np.asarray(r, float).ravel()
            c.gate(np.isfinite(r).all() and np.abs(r).max() < 1e-6, f"{case}: all residuals are zero",
                     f"{case}: residuals up to {np.nanmax(np.abs(r)):.3g} px where the projection is exact: "
                     "check the projection x = K (R X + t) / z")
        # the embedded reconstruction before BA
        st = {k[4:]: v for k, v in f.items() if k.startswith("emb_")}
        if "track_uv" in st:
            case = "embedded scene before bundle adjustment"
            reg = st["registered"]
            has_X = np.isfinite(st["X"]).all(axis=1)
            uv_e = np.where(st["inlier"][..., None], st["track_uv"], np.nan)[has_X][:, reg]
            cam_e, pt_e, uv_obs = observation_arrays(uv_e)
            p_e = _pack(st["R_cw"][reg], st["t_cw"][reg], st["X"][has_X])
            M_e, N_e = int(reg.sum()), int(has_X.sum())
            exp_e = _residuals_np(p_e, M_e, N_e, cam_e, pt_e, uv_obs, st["K"])
            r = _as_array(c.call(fn, p_e, M_e, N_e, cam_e, pt_e, uv_obs, st["K"], case=case), c, case)
            if r is not None and np.size(r) == exp_e.size:
                r = np.asarray(r, float).ravel()
                c.expect(np.abs(np.abs(r) - np.abs(exp_e)).max() < 1e-6 * (1 + np.abs(exp_e).max()),
                         f"{case}: equals the reference",
                         f"{case}: differs from the reference by up to {np.nanmax(np.abs(np.abs(r) - np.abs(exp_e))):.3g} px")
            elif r is not None:
                c.fail(f"{case}: r has {np.size(r)} entries, expected {exp_e.size} (two per observation)")


def _residual_mistake(r, p, M, N, cam, pt, uv, K, exp) -> str:
    tol = 1e-6 * (1 + np.abs(exp).max())
    variants = [
        (exp.reshape(-1, 2).T.ravel(), "u and v are not interleaved: return (proj - uv).ravel() of the (K, 2) array, "
                                       "not all u's then all v's"),
        (_residuals_np(p, M, N, cam, pt, uv, K, transpose_R=True), "R is transposed (R_wc instead of R_cw): "
                                                                   "x_cam = R_cw X + t_cw with R_cw = Rotation.from_rotvec(r).as_matrix()"),
        (_residuals_np(p, M, N, cam, pt, uv, K, divide=False), "no division by the depth: pixels are "
                                                               "(K x_cam)[:2] / (K x_cam)[2]"),
        (_residuals_np(p, M, N, cam, pt, uv, K, layout="points_first"), "the parameters are read in the wrong "
                                                                        "order: params = [r_0, t_0, ..., r_{M-1}, t_{M-1}, X_0, ..., X_{N-1}] (cameras first, 6 numbers each)"),
        (_residuals_np(p, M, N, cam, pt, uv, np.eye(3)), "K is missing: project with K (pixels), not in normalized coordinates"),
    ]
    r = np.asarray(r, float).ravel()
    for v, msg in variants:
        if v.shape == r.shape and (np.abs(r - v).max() < tol or np.abs(r + v).max() < tol):
            return msg
    return ("check the projection of point point_idx[k] by camera camera_idx[k]: R from the rotation vector "
            "params[6c:6c+3], t = params[6c+3:6c+6], X = params[6M+3j:6M+3j+3]")


# --------------------------------------------------------------------------- jacobian_sparsity


def check_jacobian_sparsity(fn, exercise: str = "jacobian_sparsity") -> None:
    """Check ``fn(n_cameras, n_points, camera_idx, point_idx) -> (2K, 6M + 3N)`` 0/1 pattern (sparse or dense)."""
    f = load_fixture(FIXTURE)
    M, N = int(f["sp_M"]), int(f["sp_N"])
    cam, pt, exp = f["sp_camera_idx"], f["sp_point_idx"], f["sp_expected"]
    case = "synthetic scene (3 cameras, 12 points)"
    with Check(exercise) as c:
        S = _as_array(c.call(fn, M, N, cam, pt, case=case), c, case)
        if S is None:
            return
        import scipy.sparse as sp

        A = (S.toarray() if sp.issparse(S) else np.asarray(S)) != 0
        K2, P = exp.shape
        if A.shape == (P, K2) and A.shape != (K2, P):
            c.fail(f"{case}: shape {A.shape}, expected {(K2, P)}: rows are residuals (2 per observation), columns parameters")
            return
        if A.shape == (K2, 9 * M + 3 * N):
            c.fail(f"{case}: {A.shape[1]} columns = 9 per camera + 3 per point: here K is fixed, so a camera has 6 "
                   "parameters (rotation vector and t), not 9 as in the SciPy cookbook")
            return
        if not c.shape(A, (K2, P), f"{case}: sparsity"):
            return
        if np.array_equal(A, exp):
            c.expect(True, f"{case}: the pattern has a 2x6 camera block and a 2x3 point block per observation", "")
            return
        # diagnose
        cam_part, pt_part = A[:, : 6 * M], A[:, 6 * M :]
        if np.array_equal(cam_part, exp[:, : 6 * M]) and not np.array_equal(pt_part, exp[:, 6 * M :]):
            c.fail(f"{case}: the camera columns are right but not the point columns: point j's columns are "
                   "6M + 3j, 6M + 3j + 1, 6M + 3j + 2 (after all the camera columns)")
            return
        no_offset = np.zeros_like(exp)
        no_offset[:, : 6 * M] = exp[:, : 6 * M]
        rows = np.repeat(np.arange(len(pt)), 2)
        for dj in range(3):
            no_offset[np.arange(K2), 3 * np.asarray(pt)[rows] + dj] = True
        if np.array_equal(A, no_offset):
            c.fail(f"{case}: the point columns start at 0 and overlap the camera columns: point j's columns are "
                   "6M + 3j, 6M + 3j + 1, 6M + 3j + 2 (after all the camera columns; add the offset 6M)")
            return
        inter = np.concatenate([exp[0::2], exp[1::2]])
        if np.array_equal(A, inter):
            c.fail(f"{case}: the rows are not interleaved: rows 2k and 2k+1 are the u and v residuals of observation k")
            return
        c.fail(f"{case}: {int((A != exp).sum())} entries differ from the expected pattern: rows 2k, 2k+1 have ones in "
               "columns 6c..6c+5 (camera c = camera_idx[k]) and 6M+3j..6M+3j+2 (point j = point_idx[k])")


# --------------------------------------------------------------------------- bundle_adjust


def _triple(out, c: Check, case: str, M: int, N: int):
    if out is FAILED:
        return None
    if all(hasattr(out, a) for a in ("R_cw", "t_cw", "X")):
        out = (out.R_cw, out.t_cw, out.X)
    if not isinstance(out, (tuple, list)) or len(out) < 3:
        c.fail(f"{case}: return the tuple (R_cw (M, 3, 3), t_cw (M, 3), X (N, 3)), got {type(out).__name__}")
        return None
    try:
        R, t, X = (np.asarray(a, float) for a in out[:3])
    except (TypeError, ValueError):
        c.fail(f"{case}: R_cw, t_cw and X must be numeric arrays")
        return None
    if R.shape != (M, 3, 3) or t.shape != (M, 3) or X.shape != (N, 3):
        c.fail(f"{case}: shapes {R.shape}, {t.shape}, {X.shape}; expected ({M}, 3, 3), ({M}, 3), ({N}, 3)")
        return None
    if not (np.isfinite(R).all() and np.isfinite(t).all() and np.isfinite(X).all()):
        c.fail(f"{case}: the result contains NaN or inf")
        return None
    return R, t, X


def _rms(K, R, t, X, uv, mask=None) -> float:
    cam, pt, obs = observation_arrays(uv)
    if mask is not None:
        keep = ~mask[pt, cam]
        cam, pt, obs = cam[keep], pt[keep], obs[keep]
    xc = (R[cam] * X[pt][:, None, :]).sum(axis=2) + t[cam]
    xh = xc @ K.T
    with np.errstate(all="ignore"):
        e = np.linalg.norm(xh[:, :2] / xh[:, 2:3] - obs, axis=1)
    return float(np.sqrt(np.mean(e**2))) if np.isfinite(e).all() else float("inf")


def _pose_error(R, t, X, R_true, t_true, X_true):
    """Largest rotation difference (degrees) and centre distance after aligning the points (similarity)."""
    from course_lib.evaluate import align_similarity

    s, Ra, ta = align_similarity(X, X_true)
    rot = max(rotation_angle_deg(R[i] @ Ra.T, R_true[i]) for i in range(len(R)))
    cen = max(np.linalg.norm(s * Ra @ camera_center(R[i], t[i]) + ta - camera_center(R_true[i], t_true[i]))
              for i in range(len(R)))
    return rot, cen


def check_bundle_adjustment(fn, exercise: str = "bundle_adjust") -> None:
    """Check ``fn(K, R_cw, t_cw, X, uv, callback=None) -> (R_cw, t_cw, X)`` on a perturbed synthetic scene."""
    f = load_fixture(FIXTURE)
    with Check(exercise) as c:
        K, R0, t0, X0, uv = (f[f"ba_{s}"] for s in ("K", "R0", "t0", "X0", "uv"))
        M, N = R0.shape[0], X0.shape[0]
        case = "perturbed synthetic scene (0.5 px noise)"
        states = []
        out = _triple(c.call(fn, K, R0, t0, X0, uv, callback=lambda R, t, X: states.append(1), case=case), c, case, M, N)
        if out is not None:
            R, t, X = out
            rms, ref = _rms(K, R, t, X, uv), float(f["ba_final_rms"])
            if rms <= 1.02 * ref + 1e-3:
                c.expect(True, f"{case}: reaches the reference minimum of the reprojection error", "")
            elif rms < 0.9 * float(f["ba_initial_rms"]):
                c.fail(f"{case}: RMS reprojection error {rms:.3f} px, the reference reaches {ref:.3f} px: it stopped "
                       "early (raise max_nfev, lower ftol) or some parameters are not optimized")
            else:
                c.fail(f"{case}: RMS reprojection error {rms:.3f} px, no better than the start "
                       f"({float(f['ba_initial_rms']):.3f} px): are the residuals and the parameter layout consistent?")
            rot, cen = _pose_error(R, t, X, f["ba_R"], f["ba_t"], f["ba_X"])
            size = float(np.linalg.norm(f["ba_X"].max(0) - f["ba_X"].min(0)))
            c.expect(rot < 0.05 and cen < 0.002 * size,
                     f"{case}: the same cameras as the reference (after a similarity alignment: the gauge is free)",
                     f"{case}: cameras differ from the reference by {rot:.3g}° and {cen:.3g} (scene size {size:.3g}) "
                     "after a similarity alignment: not converged, or a different cost")
            c.gate(all(np.allclose(Ri @ Ri.T, np.eye(3), atol=1e-6) and np.linalg.det(Ri) > 0 for Ri in R),
                     f"{case}: every R_cw is a rotation", f"{case}: some R_cw is not a rotation: optimize rotation vectors, "
                     "not the 9 entries of R")
            c.gate(len(states) >= 1, f"{case}: callback is called during the optimization",
                     f"{case}: callback was never called: call callback(R_cw, t_cw, X) after every iteration (the slider needs it)")

"""Checks of notebook 05 (bundle adjustment) and its step input.

Cases (fixture ``bundle_adjustment``, :mod:`course_lib.instructor.cases.bundle_adjustment`): small synthetic
scenes with known truth and the embedded scene's reconstruction before bundle adjustment:

* ``visibility_matrix``: the matrix transposed (cameras as rows, the handout's ``V_ij`` layout),
  True where a point is *not* seen, a comparison with NaN (always True), the last axis not
  reduced; ints instead of bools is correct maths in another form (a detail).
* ``reprojection_residuals``: a (K, 2) array instead of the flat (2K,) vector, all u's before
  all v's, ``R_wc`` instead of ``R_cw``, no division by the depth, a parameter layout other than
  ``[r_0, t_0, r_1, t_1, ..., X_0, X_1, ...]``, K missing, Euler angles for the rotation vector
  (:data:`RESIDUAL_VARIANTS`).
* ``jacobian_sparsity``: 9 parameters per camera (the SciPy cookbook's cameras carry f, k1, k2;
  here K is fixed), point columns without the ``6M`` offset, rows of u and v not interleaved,
  only the u row filled, the matrix transposed; a second case lists the observations in random
  order.
* ``bundle_adjust``: the cost does not reach the *minimum* (computed with tight tolerances, so a
  solve stopped after a few evaluations fails), cameras that did not move, cameras far from those
  of the minimum (after a similarity alignment), rotations that are no rotations, a callback that
  is never called, called once (before or after solving) or at every evaluation of the
  residuals instead of after every iteration.

In a notebook ``bundle_adjust`` runs the student's own residuals and sparsity: when they failed
their checks, the verdict says so (:meth:`~course_lib.checks.core.Check.blame_earlier`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from course_lib.alignment import align_similarity
from course_lib.checks.core import FAILED, RTOL, Check, Outcome, as_float, load_fixture, report_cases
from course_lib.conventions import camera_center, rotation_angle_deg
from course_lib.starting_points import observation_arrays

__all__ = [
    "check_visibility_matrix",
    "check_reprojection_residuals",
    "check_jacobian_sparsity",
    "check_bundle_adjustment",
]

FIXTURE = "bundle_adjustment"
#: Residuals agree within this many pixels (plus RTOL of their size): a correct answer in float32 passes.
RESIDUAL_ATOL_PX = 1e-3


#: The classic mistakes of reprojection_residuals that the check recognises, and what to change. Their
#: residuals on the cases are computed on the instructor's side and stored with the cases
#: (``res_syn_var_<name>``); this module holds no implementation of the residuals.
RESIDUAL_VARIANTS = {
    "not_interleaved": "u and v are not interleaved: return (proj - uv).ravel() of the (K, 2) array, not all u's "
                       "then all v's",
    "R_transposed": "R is transposed (R_wc instead of R_cw): x_cam = R_cw X + t_cw with "
                    "R_cw = Rotation.from_rotvec(r).as_matrix()",
    "no_depth": "no division by the depth: pixels are (K x_cam)[:2] / (K x_cam)[2]",
    "points_first": "the parameters are read in the wrong order: params = [r_0, t_0, ..., r_{M-1}, t_{M-1}, X_0, ..., "
                    "X_{N-1}] (cameras first, 6 numbers each)",
    "no_K": "K is missing: project with K (pixels), not in normalized coordinates",
    "euler": "the first 3 numbers of a camera are a rotation VECTOR (axis times angle): "
             "Rotation.from_rotvec(r), not Euler angles (Rotation.from_euler)",
}


# --------------------------------------------------------------------------- helpers


def _as_array(out, c: Check, case: str):
    if out is FAILED:
        return None
    try:
        if sp.issparse(out):
            return out
        return np.asarray(out)
    except (TypeError, ValueError):
        c.fail(f"{case}: return a numpy array, got {type(out).__name__}")
        return None


# --------------------------------------------------------------------------- visibility_matrix


def _visibility_case(c: Check, fn, case: str, uv, expected) -> None:
    V = _as_array(c.call(fn, uv, case=case), c, case)
    if V is None:
        return
    T, M = expected.shape
    if not c.shape(V, (T, M), f"{case}: V", {
            (M, T): f"the kit stores points as rows, V[j, i] for point j and image i, shape ({T}, {M}) (the "
                    "transpose of the handout's V_ij)",
            (T, M, 2): "one entry per point and image, not per coordinate; reduce the last axis, e.g. "
                       "V = ~np.isnan(track_uv).any(axis=2)"}):
        return
    if V.dtype != bool:
        c.detail(False, "", f"{case}: correct values, but V has dtype {V.dtype}: the docstring asks for a bool array "
                 "(e.g. ~np.isnan(track_uv[..., 0]))")
        V = V != 0
    if np.array_equal(V, ~expected):
        c.fail(f"{case}: V is inverted: it must be True where the point IS seen (the pixel is not NaN)", named="inverted")
    elif V.all() and not expected.all():
        c.fail(f"{case}: V is True everywhere: a comparison with NaN (track_uv != np.nan) is always True, since NaN "
               "equals nothing; test with np.isnan", named="nan_compare")
    else:
        c.expect(np.array_equal(V, expected), f"{case}: V[j, i] is True exactly where point j is seen in image i",
                 f"{case}: {int((V != expected).sum())} entries differ from the NaN pattern of track_uv")


def check_visibility_matrix(fn, exercise: str = "visibility_matrix") -> None:
    """Check ``fn(track_uv (T, M, 2)) -> (T, M) bool`` on a synthetic case and the embedded tracks."""
    f = load_fixture(FIXTURE)
    cases = [("synthetic tracks", f["vis_track_uv"], f["vis_expected"])]
    if "emb_track_uv" in f:
        cases.append(("embedded scene tracks", f["emb_track_uv"], f["emb_visible"]))
    with Check(exercise) as c:
        for case, uv, expected in cases:
            _visibility_case(c, fn, case, uv, expected)


# --------------------------------------------------------------------------- reprojection_residuals


def _residual_outcome(c: Check, fn, f, key: str, case: str) -> Outcome | None:
    """One case of the residuals: equal to the reference's, up to the sign (observed minus projected works too)."""
    p, M, N = f[f"{key}_params"], int(f[f"{key}_M"]), int(f[f"{key}_N"])
    cam, pt, uv, K, exp = (f[f"{key}_{s}"] for s in ("camera_idx", "point_idx", "uv", "K", "expected"))
    out = c.call(fn, p, M, N, cam, pt, uv, K, case=case)
    if not c.shape(out, (2 * len(cam),), f"{case}: r", {(len(cam), 2): f"return the flat vector r.ravel() of shape "
                                                        f"({2 * len(cam)},), [u_0' - u_0, v_0' - v_0, u_1' - u_1, ...]"}):
        return None
    r = as_float(out)
    tol = RESIDUAL_ATOL_PX + RTOL * np.abs(exp).max()  # a float32 answer is good to ~1e-4 px
    same = lambda a: np.abs(r - a).max() < tol or np.abs(r + a).max() < tol  # noqa: E731
    stored = {name for name in RESIDUAL_VARIANTS if f"{key}_var_{name}" in f}  # the mistakes this case can tell
    return Outcome(case, same(exp), "equals the reference (up to the sign, u and v interleaved)",
                   f"max difference {np.abs(r - exp).max():.3g} px from the reference",
                   ({name for name in stored if same(f[f"{key}_var_{name}"])}, stored),
                   "check the projection of point point_idx[k] by camera camera_idx[k]: R from the rotation vector "
                   "params[6c:6c+3], t = params[6c+3:6c+6], X = params[6M+3j:6M+3j+3]")


def check_reprojection_residuals(fn, exercise: str = "reprojection_residuals") -> None:
    """Check ``fn(params, n_cameras, n_points, camera_idx, point_idx, uv, K) -> (2K,)``."""
    f = load_fixture(FIXTURE)
    with Check(exercise) as c:
        cases = (("res_syn", "perturbed synthetic scene"), ("emb", "embedded scene before bundle adjustment"))
        outcomes = [_residual_outcome(c, fn, f, key, case) for key, case in cases if f"{key}_params" in f]
        report_cases(c, [o for o in outcomes if o is not None], RESIDUAL_VARIANTS)
        # zero at the truth
        case = "true cameras and points, noiseless pixels"
        p_t, M, N, K = f["res_true_params"], int(f["res_syn_M"]), int(f["res_syn_N"]), f["res_syn_K"]
        cam_t, pt_t, uv_t = f["res_true_camera_idx"], f["res_true_point_idx"], f["res_true_uv"]
        r = _as_array(c.call(fn, p_t, M, N, cam_t, pt_t, uv_t, K, case=case), c, case)
        if r is not None and np.size(r) == 2 * len(cam_t):
            r = np.asarray(r, float).ravel()
            c.gate(np.isfinite(r).all() and np.abs(r).max() < RESIDUAL_ATOL_PX, f"{case}: all residuals are zero",
                   f"{case}: residuals up to {np.nanmax(np.abs(r)):.3g} px where the projection is exact: "
                   "check the projection x = K (R X + t) / z")
        elif r is not None:
            c.fail(f"{case}: r has {np.size(r)} entries, expected {2 * len(cam_t)} (two per observation)")
        c.causes(fn, [
            (r"\bfrom_euler\(", "a camera's first 3 numbers are a rotation vector: Rotation.from_rotvec, not from_euler"),
            (r"\bnorm\(", "np.linalg.norm makes one distance of each (u, v) difference: return the u and v differences "
                                      "both, (proj - uv).ravel()"),
            (r"\binv\(", "the projection uses K itself: pixels = (K x_cam)[:2] / (K x_cam)[2], no inverse"),
        ])


# --------------------------------------------------------------------------- jacobian_sparsity


def _sparsity_mistake(A, exp, M: int, pt) -> str:
    """Name the mistake when the 0/1 pattern ``A`` is not ``exp``."""
    K2 = exp.shape[0]
    no_offset = np.zeros_like(exp)
    no_offset[:, : 6 * M] = exp[:, : 6 * M]
    rows = np.repeat(np.arange(len(pt)), 2)
    for dj in range(3):
        no_offset[np.arange(K2), 3 * np.asarray(pt)[rows] + dj] = True
    if np.array_equal(A, no_offset):
        return ("the point columns start at 0 and overlap the camera columns: point j's columns are 6M + 3j, "
                "6M + 3j + 1, 6M + 3j + 2 (after all the camera columns; add the offset 6M)")
    if np.array_equal(A[:, : 6 * M], exp[:, : 6 * M]):
        return ("the camera columns are right but not the point columns: point j's columns are 6M + 3j, 6M + 3j + 1, "
                "6M + 3j + 2 (after all the camera columns)")
    if np.array_equal(A, np.concatenate([exp[0::2], exp[1::2]])):
        return "the rows are not interleaved: rows 2k and 2k+1 are the u and v residuals of observation k"
    if np.array_equal(A[0::2], exp[0::2]) and not A[1::2].any():
        return "only row 2k is filled: the v residual of observation k (row 2k + 1) depends on the same 9 parameters"
    return (f"{int((A != exp).sum())} entries differ from the expected pattern: rows 2k, 2k+1 have ones in columns "
            "6c..6c+5 (camera c = camera_idx[k]) and 6M+3j..6M+3j+2 (point j = point_idx[k])")


def _sparsity_case(c: Check, fn, f, key: str, case: str) -> None:
    M, N = int(f[f"{key}_M"]), int(f[f"{key}_N"])
    cam, pt, exp = f[f"{key}_camera_idx"], f[f"{key}_point_idx"], f[f"{key}_expected"]
    S = _as_array(c.call(fn, M, N, cam, pt, case=case), c, case)
    if S is None:
        return
    A = (S.toarray() if sp.issparse(S) else np.asarray(S)) != 0
    K2, P = exp.shape
    if A.shape == (P, K2) and A.shape != (K2, P):
        c.fail(f"{case}: shape {A.shape}, expected {(K2, P)}: rows are residuals (2 per observation), columns parameters")
    elif A.shape == (K2, 9 * M + 3 * N):
        c.fail(f"{case}: {A.shape[1]} columns = 9 per camera + 3 per point: here K is fixed, so a camera has 6 "
               "parameters (rotation vector and t), not 9 as in the SciPy cookbook", named="nine_per_camera")
    elif c.shape(A, (K2, P), f"{case}: sparsity"):
        why = _sparsity_mistake(A, exp, M, pt)
        c.expect(np.array_equal(A, exp), f"{case}: a 2x6 camera block and a 2x3 point block per observation",
                 f"{case}: {why}", named=None if " entries differ" in why else why[:30])


def check_jacobian_sparsity(fn, exercise: str = "jacobian_sparsity") -> None:
    """Check ``fn(n_cameras, n_points, camera_idx, point_idx) -> (2K, 6M + 3N)`` 0/1 pattern (sparse or dense)."""
    f = load_fixture(FIXTURE)
    with Check(exercise) as c:
        _sparsity_case(c, fn, f, "sp", f"synthetic scene ({int(f['sp_M'])} cameras, {int(f['sp_N'])} points)")
        if "sp2_M" in f:
            _sparsity_case(c, fn, f, "sp2", "observations in random order")


# --------------------------------------------------------------------------- bundle_adjust


def _triple(out, c: Check, case: str, M: int, N: int):
    return c.arrays(out, case, {"R_cw": (M, 3, 3), "t_cw": (M, 3), "X": (N, 3)},
                    "the tuple (R_cw (M, 3, 3), t_cw (M, 3), X (N, 3))")


def _cost(K, R, t, X, uv) -> float:
    """``0.5 * sum of squared reprojection errors`` over the observations of ``uv (N, M, 2)`` (inf if one is behind)."""
    cam, pt, obs = observation_arrays(uv)
    xc = (R[cam] * X[pt][:, None, :]).sum(axis=2) + t[cam]
    xh = xc @ K.T
    with np.errstate(all="ignore"):
        r = xh[:, :2] / xh[:, 2:3] - obs
    return 0.5 * float(np.sum(r**2)) if np.isfinite(r).all() and (xc[:, 2] > 0).all() else float("inf")


def _pose_error(R, t, X, R_true, t_true, X_true):
    """Largest rotation difference (degrees) and centre distance after aligning the points (similarity)."""
    s, Ra, ta = align_similarity(X, X_true)
    rot = max(rotation_angle_deg(R[i] @ Ra.T, R_true[i]) for i in range(len(R)))
    cen = max(np.linalg.norm(s * Ra @ camera_center(R[i], t[i]) + ta - camera_center(R_true[i], t_true[i]))
              for i in range(len(R)))
    return rot, cen


#: How close to the minimum of the cost a converged solve must come (relative): least_squares' default
#: tolerances reach 1e-8 here, without x_scale 1e-5; a solve stopped after 3 evaluations 1e-2.
COST_RTOL = 1e-4

#: The robust losses whose minimum is stored with the case (``ba_mis_<loss>_cost``).
ROBUST_LOSSES = ("soft_l1", "huber", "cauchy")


def _minimum_verdict(c: Check, case: str, cost: float, f, moved: dict, progress: float | None) -> None:
    """The cost reaches the minimum (relative :data:`COST_RTOL`); a failure says how far, and what explains it.

    ``moved``: whether the cameras and the points moved; ``progress``: how much the cost of the callback's last
    state was below the one before (None: unknown).
    """
    c0, opt = float(f["ba_initial_cost"]), float(f["ba_final_cost"])
    if cost <= opt * (1 + COST_RTOL) + 1e-9:
        c.expect(True, f"{case}: reaches the minimum of the reprojection error", "")
        return
    facts = f"cost 0.5·Σr² = {cost:.6g}, the minimum is {opt:.6g} ({cost / opt - 1:.1e} above it; the start {c0:.4g})"
    robust = next((loss for loss in ROBUST_LOSSES if f"ba_mis_{loss}_cost" in f
                   and abs(cost - float(f[f"ba_mis_{loss}_cost"])) <= 1e-3 * float(f[f"ba_mis_{loss}_cost"])), None)
    if not moved["cameras"] and moved["points"]:
        c.fail(f"{case}: {facts}: your cameras did not move: optimize the 6 parameters of every camera together with the "
               "points", named="cameras_fixed")
    elif moved["cameras"] and not moved["points"]:
        c.fail(f"{case}: {facts}: your points did not move: optimize the 3 coordinates of every point together with the "
               "cameras (params = [r_0, t_0, ..., X_0, X_1, ...])", named="points_fixed")
    elif robust is not None:
        c.fail(f"{case}: {facts}: your result is the minimum of the robust loss loss='{robust}', not of the sum of "
               "squares: use least_squares' default loss='linear'", named="robust_loss")
    elif progress is not None and progress > 0.01 * max(cost - opt, 0.0):
        c.fail(f"{case}: {facts}: your last iteration still lowered the cost by {progress:.3g}: the solve stopped before "
               "the minimum; let least_squares run to convergence (no small max_nfev, the default tolerances)",
               named="stopped_early")
    elif cost < 0.9 * c0:
        c.fail(f"{case}: {facts}: the result is not the least-squares minimum (check the residuals of every observation, "
               "the plain sum of squares loss='linear', and that every camera and point is a parameter)")
    else:
        c.fail(f"{case}: {facts}: no better than the start: are the residuals and the parameter layout consistent (pack "
               "and unpack the same way)?")


def _callback_verdict(c: Check, case: str, states: list, costs: list[float], c0: float, ends: tuple[float, float]) -> None:
    """The callback sees the iterations: called more than once, each an accepted iterate, the last one the result.

    ``ends``: the cost of the call's result and the minimum of the cost."""
    final, opt = ends
    c.gate(len(costs) >= 1, f"{case}: callback is called during the optimization",
           f"{case}: callback was never called: call callback(R_cw, t_cw, X) after every iteration (the slider needs it)")
    if not costs:
        return
    # a finite-difference evaluation moves a few parameters (one group of columns) by ~1e-8 of their size; an
    # iteration of the solver moves (nearly) all of them, however small its step
    def fd_step(s1, s2) -> bool:
        a = np.concatenate([np.ravel(v) for v in s1])
        b = np.concatenate([np.ravel(v) for v in s2])
        moved = a != b
        return a.shape == b.shape and 0 < moved.mean() < 0.5 and \
            float(np.abs(a - b).max()) < 1e-6 * max(float(np.abs(a).max()), 1.0)

    tiny = sum(1 for s1, s2 in zip(states, states[1:]) if fd_step(s1, s2))
    rising = any(b > a * (1 + 1e-9) + 1e-9 for a, b in zip(costs, costs[1:]))
    at_minimum = final <= opt * (1 + COST_RTOL) + 1e-9
    named = None
    if len(costs) == 1:
        when = ("with the starting state, before solving" if abs(costs[0] - c0) <= 1e-9 * c0 else
                "after solving" if abs(costs[0] - final) <= 1e-6 * max(final, 1e-12) else "")
        why = (f"callback was called once {when}: call it after every iteration, e.g. "
               "least_squares(..., callback=lambda x: callback(*unpack_params(x, M, N)))")
    elif tiny >= 3:
        why = (f"{tiny} of the states passed to callback differ from the one before in a few parameters by less than "
               "1e-6 (finite-difference steps): you called it at every evaluation of the residuals; call it once per "
               "iteration, with the accepted state (least_squares' callback=)")
        named = "every_evaluation"
    elif rising and at_minimum:
        why = ("the cost of the states passed to callback goes up and down: call it once per iteration, with the "
               "accepted state")
    else:
        why = ("the last state passed to callback is not the result: call it after every iteration, the last "
               "one included")
    ok = len(costs) >= 2 and tiny < 3 and not (rising and at_minimum) and costs[-1] <= final * (1 + 1e-6) + 1e-9
    c.expect(ok, f"{case}: callback follows the iterations (the cost never rises, the last state is the result)",
             f"{case}: {why}", named=named)


def check_bundle_adjustment(fn, exercise: str = "bundle_adjust") -> None:
    """Check ``fn(K, R_cw, t_cw, X, uv, callback=None) -> (R_cw, t_cw, X)`` on a synthetic scene a few degrees off.

    Convergence is measured against the minimum of the cost (computed by the reference with tight
    tolerances), not against where the reference stops. The result is judged on a call without a
    callback; the callback in a call of its own (a callback with another signature costs the
    callback's check only): its states must follow the iterations.
    """
    f = load_fixture(FIXTURE)
    with Check(exercise) as c:
        K, R0, t0, X0, uv = (f[f"ba_{s}"] for s in ("K", "R0", "t0", "X0", "uv"))
        M, N = R0.shape[0], X0.shape[0]
        case = "synthetic scene, cameras 3° off (0.5 px noise)"
        cb_case = f"{case}, with a callback"
        out = _triple(c.call(fn, K, R0, t0, X0, uv, case=case), c, case, M, N)
        states: list = []
        cb = lambda R, t, X: states.append((np.array(R, float), np.array(t, float), np.array(X, float)))  # noqa: E731
        cb_out = _triple(c.call(fn, K, R0, t0, X0, uv, callback=cb, case=cb_case), c, cb_case, M, N)
        costs = [_cost(K, *st, uv) if all(np.shape(a) == np.shape(b) for a, b in zip(st, (R0, t0, X0)))
                 else float("inf") for st in states]
        if out is not None:
            R, t, X = out
            c.gate(all(np.allclose(Ri @ Ri.T, np.eye(3), atol=10 * RTOL) and np.linalg.det(Ri) > 0 for Ri in R),
                   f"{case}: every R_cw is a rotation", f"{case}: some R_cw is not a rotation: optimize rotation "
                   "vectors (3 numbers per camera), so that every R stays a rotation")
            cost = _cost(K, R, t, X, uv)
            moved = {"cameras": not (np.allclose(R, R0) and np.allclose(t, t0)), "points": not np.allclose(X, X0)}
            progress = costs[-2] - costs[-1] if len(costs) >= 2 and np.isfinite(costs[-2:]).all() else None
            _minimum_verdict(c, case, cost, f, moved, progress)
            rot, cen = _pose_error(R, t, X, f["ba_R"], f["ba_t"], f["ba_X"])
            size = float(np.linalg.norm(f["ba_X"].max(0) - f["ba_X"].min(0)))
            c.expect(rot < 1.0 and cen < 0.02 * size,  # loose: the minimum is flat along some directions
                     f"{case}: the cameras of the minimum (after a similarity alignment: the gauge is free)",
                     f"{case}: cameras differ from those of the minimum by {rot:.3g}° and {cen:.3g} (scene size "
                     f"{size:.3g}) after a similarity alignment")
        if cb_out is not None:
            final = _cost(K, *cb_out, uv)
            _callback_verdict(c, cb_case, states, costs, float(f["ba_initial_cost"]), (final, float(f["ba_final_cost"])))
        c.blame_earlier("reprojection_residuals", "jacobian_sparsity", fn=fn)

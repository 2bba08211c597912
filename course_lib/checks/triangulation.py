"""Checks of notebook 03 (triangulation): triangulate_linear, choose_pose, triangulate_nonlinear.

Cases (fixture ``triangulation``, :mod:`course_lib.instructor.cases.triangulation`): synthetic scenes with known truth
(camera 1 is never at the world's origin there) and the embedded scene (in a random world frame). A mistake is named
when the result is exactly what it gives on every case (:data:`_LINEAR_MISTAKES`, a wrong cheirality test by the
counts it gives, :data:`_NONLINEAR_MISTAKES`); otherwise the verdict gives the distances and reprojection errors in
pixels. choose_pose's defining property: the candidate with the points in front of BOTH cameras. The non-linear
triangulation runs on a 3-view scene with points unseen in one view (NaN) and on the embedded pair.
"""

from __future__ import annotations

import numpy as np

from course_lib.conventions import project, rotation_angle_deg
from course_lib.checks.core import (FAILED, Check, Outcome, as_float, declare_defining, load_fixture,
                                    refinement_verdicts, report_cases, unique_key)

__all__ = [
    "check_triangulate_linear",
    "check_choose_pose",
    "check_triangulate_nonlinear",
]

FIXTURE = "triangulation"

IN_FRONT = "in front of both cameras"
declare_defining("choose_pose", {
    IN_FRONT: "the right candidate is the one with the points in front of camera 1 AND camera 2",
})


# --------------------------------------------------------------------------- helpers


def _reproj_rms(K, R_cws, t_cws, uv, X) -> float:
    """RMS reprojection error (pixels) over all observed entries of ``uv (N, V, 2)``."""
    sq = []
    for i in range(R_cws.shape[0]):
        seen = np.isfinite(uv[:, i]).all(axis=1)
        with np.errstate(all="ignore"):
            d = project(K, R_cws[i], t_cws[i], X[seen]) - uv[seen, i]
        sq.append((d**2).sum(axis=1))
    sq = np.concatenate(sq)
    return float(np.sqrt(sq.mean())) if sq.size else 0.0


def _scale(X) -> float:
    X = np.asarray(X, float)
    return float(max(np.linalg.norm(X.max(0) - X.min(0)), 1e-9))


#: What each stored mistake of the linear triangulation (``lin_<case>_mis_<key>``) means.
_LINEAR_MISTAKES = {
    "swapped": "you swapped the cameras in the rows of A: the rows of x1 use P2 and those of x2 use P1; build "
               "u1 p3ᵀ - p1ᵀ, v1 p3ᵀ - p2ᵀ from P1 and the same two rows with x2 from P2",
    "uv_swapped": "you swapped u and v in the rows of A: u goes with the first row of P (u p3ᵀ - p1ᵀ) and v with "
                  "the second (v p3ᵀ - p2ᵀ)",
    "largest": "you took the singular vector of the LARGEST singular value: X_h is the last row of Vt (Vt[-1]), "
               "the least-squares null vector of A",
    "not_divided": "you returned X_h[:3] without dividing by the homogeneous coordinate: X = X_h[:3] / X_h[3]",
    "abs_divided": "you divided by |X_h[3]|: the SVD gives X_h with either sign, so divide by X_h[3] itself "
                   "(X = X_h[:3] / X_h[3]); the points whose X_h[3] came out negative are mirrored through the origin",
    "mirrored": "your points are the reference's mirrored through the origin (X -> -X): divide by X_h[3] itself, "
                "keeping its sign",
}


def _linear_keys(A: np.ndarray, ref: np.ndarray, mis: dict, tol: float, cams: tuple) -> set[str]:
    """The mistakes whose result the points ``A (N, 3)`` are, on a case with reference points ``ref``.

    ``cams``: ``(P1, P2, x1, x2)``; points that reproject far better with the cameras swapped than as given
    were triangulated with the cameras swapped, whatever the form of A.
    """
    scale = _scale(ref)
    near = lambda Y: Y.shape == A.shape and np.median(np.linalg.norm(A - Y, axis=1)) <= tol * scale  # noqa: E731
    out = {key for key, Y in mis.items() if near(Y)}
    P1, P2, x1, x2 = cams
    e_right = np.median(np.concatenate([_reprojection_px(P1, A, x1), _reprojection_px(P2, A, x2)]))
    e_swap = np.median(np.concatenate([_reprojection_px(P2, A, x1), _reprojection_px(P1, A, x2)]))
    if e_swap < 0.5 * e_right:
        out.add("swapped")
    unit = ref / np.sqrt(1.0 + np.sum(ref**2, axis=1, keepdims=True))  # X_h[:3] of the unit null vector
    flip = np.sign(np.sum(A * unit, axis=1, keepdims=True))
    if near(flip * unit):
        out.add("not_divided")
    mirror = np.sign(np.sum(A * ref, axis=1, keepdims=True))
    if near(mirror * ref) and (mirror < 0).any():
        out.add("mirrored" if (mirror < 0).all() else "abs_divided")
    return out


def _reprojection_px(P, X, x) -> np.ndarray:
    """(N,) pixel distances between x and the projection of X by P."""
    Xh = np.column_stack([X, np.ones(len(X))]) @ np.asarray(P, float).T
    with np.errstate(all="ignore"):
        return np.linalg.norm(Xh[:, :2] / Xh[:, 2:] - x, axis=1)


def _points_shape(c: Check, X, n: int, case: str, nan: str = "the points contain NaN or inf") -> np.ndarray | None:
    """The student's points as a finite (n, 3) array, or None after a failed check that says what the shape is (or
    ``nan``, what NaN means)."""
    if X is FAILED:
        return None
    A = as_float(X)
    shape = None if A is None else A.shape
    problem = (f"expected an array of shape ({n}, 3), got {type(X).__name__}" if A is None
               else f"returned homogeneous points of shape ({n}, 4): divide by the last coordinate X_h[3] and drop it"
               if shape == (n, 4)
               else f"shape {shape}: points are rows in the kit, return shape ({n}, 3) (transpose)"
               if shape in ((3, n), (4, n)) and n not in (3, 4)
               else f"shape {shape}: keep the points axis for N = 1 (shape (1, 3)); np.squeeze or X[0] drops it"
               if n == 1 and A.size == 3 and shape != (1, 3)
               else f"shape {shape}, expected ({n}, 3)" if shape != (n, 3)
               else nan if not np.isfinite(A).all() else None)
    if problem:
        c.fail(f"{case}: {problem}")
        return None
    return A


def _points_close(A, ref, tol: float) -> bool:
    return bool(np.median(np.linalg.norm(A - ref, axis=1)) <= tol * _scale(ref))


def _points_numbers(A, ref, P1=None, P2=None, x1=None, x2=None) -> str:
    """The distances to the reference and, with the cameras, the reprojection errors (median, pixels)."""
    d = np.median(np.linalg.norm(A - ref, axis=1))
    text = f"median distance to the reference points {d:.3g} (scene size {_scale(ref):.3g})"
    if P1 is not None:
        e = np.median(np.concatenate([_reprojection_px(P1, A, x1), _reprojection_px(P2, A, x2)]))
        e_ref = np.median(np.concatenate([_reprojection_px(P1, ref, x1), _reprojection_px(P2, ref, x2)]))
        text += f", median reprojection error {e:.3g} px (reference {e_ref:.3g} px)"
    return text


# --------------------------------------------------------------------------- triangulate_linear


def check_triangulate_linear(fn, exercise: str = "triangulate_linear") -> None:
    """Check ``fn(P1, P2, x1, x2) -> X (N, 3)`` on a noiseless, a noisy and the embedded pair, and one point."""
    f = load_fixture(FIXTURE)
    with Check(exercise) as c:
        results = []
        for name, case, tol in (("noiseless", "noiseless synthetic pair", 1e-6), ("noisy", "noisy synthetic pair", 5e-3),
                                ("vertical", "noisy pair, camera 2 above camera 1", 5e-3),
                                ("embedded", "embedded scene", 5e-3)):
            k = f"lin_{name}"
            if f"{k}_P1" not in f:
                continue
            cams = P1, P2, x1, x2 = f[f"{k}_P1"], f[f"{k}_P2"], f[f"{k}_x1"], f[f"{k}_x2"]
            ref = f[f"{k}_Xtrue"] if name == "noiseless" else f[f"{k}_X"]
            A = _points_shape(c, c.call(fn, P1, P2, x1, x2, case=case), len(ref), case)
            if A is None:
                continue
            ok = _points_close(A, ref, tol)
            mis = {key: f[f"{k}_mis_{key}"] for key in _LINEAR_MISTAKES if f"{k}_mis_{key}" in f}
            results.append(Outcome(case, ok, "recovers the true points exactly" if name == "noiseless" else
                                   "matches the reference", _points_numbers(A, ref, *cams),
                                   keys=() if ok else _linear_keys(A, ref, mis, max(tol, 1e-6), cams)))
        report_cases(c, results, _LINEAR_MISTAKES)
        failing = any(not o.ok for o in results)
        # one point at a time must work too (N = 1)
        P1, P2 = f["lin_noiseless_P1"], f["lin_noiseless_P2"]
        case = "a single point (N = 1)"
        A = _points_shape(c, c.call(fn, P1, P2, f["lin_noiseless_x1"][:1], f["lin_noiseless_x2"][:1], case=case), 1, case)
        if A is not None:
            want = f["lin_noiseless_Xtrue"][:1]
            c.expect(np.allclose(A, want, rtol=1e-6, atol=1e-6 * _scale(f["lin_noiseless_Xtrue"])), f"{case} works",
                     f"{case}: the right shape (1, 3) but not the true point ({np.round(A[0], 3).tolist()} instead "
                     f"of {np.round(want[0], 3).tolist()})" + (
                         ": the same points as the cases above, one at a time" if failing else
                         ": the N-point cases pass, so look for what depends on N (a loop over range(N - 1), a "
                         "reshape or mean over the points axis, an index [1] that is a second point)"))


# --------------------------------------------------------------------------- choose_pose


#: The wrong cheirality tests, in the order of the rows of the stored ``<case>_mis_counts``, as what the student did.
_CHEIRALITY_MISTAKES = (
    "your test checks only camera 2: require z > 0 in camera 1 as well",
    "your test checks only camera 1: require r3ᵀ (X - C) > 0 for camera 2 as well",
    "your test forgets the centre: use r3ᵀ (X - C) > 0, not r3ᵀ X > 0",
    "your test uses t where the centre C belongs: r3ᵀ (X - C) with C = -Rᵀ t",
    "your test uses the third column of R: r3ᵀ is the third ROW, R[2]",
    "your test keeps the points behind the cameras (the sign is flipped): in front means depth > 0",
)
#: The same, by key (``cheirality_<row>``).
_CHEIRALITY = {f"cheirality_{i}": text for i, text in enumerate(_CHEIRALITY_MISTAKES)}
_ARGMIN = ("you kept the candidate with the FEWEST points in front of both cameras: keep the one with the most "
           "(np.argmax(counts))")
_CONFUSIONS = {
    "transposed": "R_cw is transposed (that is R_wc, world from camera): return the candidate R[k] itself",
    "t_is_C": "t_cw is the camera centre C: the translation is t_cw = -R_cw @ C",
    "c_vs_t": "t_cw is not -R_cw @ C (C vs t confusion): t_cw = -R_cw @ C",
    "other_t": "t_cw does not belong to the chosen rotation's candidate: t_cw = -R[k] @ C[k]",
    "rt_c": "t_cw = -R_cwᵀ @ C (the transposed rotation): t_cw = -R_cw @ C",
}


def _match_candidate(R_s, t_s, R, C, right: int) -> tuple[int | None, str | None]:
    """Index of the candidate the student returned, and a confusion (a key of :data:`_CONFUSIONS`) or None.

    Two candidates share each rotation (``+C`` and ``-C``), so one answer can read as several
    (``(R, -C)`` is candidate k with t = -C, or its partner with t = C): of the readings, in the
    order below, the one of the right candidate ``right`` wins (unless another candidate is returned
    exactly), else the first. (``t = -Rᵀ C`` of the right candidate is also ``Rᵀ C`` of its partner: it reads as
    the right candidate with the transposed rotation in t, since the counts that chose it are the same.)
    """
    tol = 1e-5 * max(1.0, float(np.abs(t_s).max()))
    same = lambda a, b: np.allclose(a, b, atol=tol)  # noqa: E731
    readings = []
    for k in range(4):
        t_k = -R[k] @ C[k]
        if same(R_s, R[k]):
            readings += [(0, k, None)] if same(t_s, t_k) else []
            readings += [(1, k, "t_is_C")] if same(t_s, C[k]) else []
            readings += [(2, k, "c_vs_t")] if same(t_s, -C[k]) or same(t_s, R[k].T @ C[k]) else []
            readings += [(2, k, "rt_c")] if same(t_s, -R[k].T @ C[k]) and not same(t_s, t_k) else []
            readings += [(4, k, "other_t")]
        if same(R_s, R[k].T):
            readings += [(3 if any(same(t_s, t) for t in (t_k, C[k], -C[k], R[k].T @ C[k])) else 5, k, "transposed")]
    if not readings:
        return None, None
    readings.sort(key=lambda r: (r[0], r[1] != right, r[1]))
    best = readings[0][0]
    _, k, why = next((r for r in readings if best > 0 and r[1] == right and r[0] <= max(best, 2)), readings[0])
    return k, why


def _pose_outcome(c: Check, fn, f, key, case) -> Outcome | None:
    """Call choose_pose on one case: the choice as an :class:`Outcome` (named: a wrong cheirality test, by the counts
    it gives, or the candidate with the fewest points), what it returned in ``data``; None after a failed check."""
    R, C, K, x1, x2 = f[f"{key}_R"], f[f"{key}_C"], f[f"{key}_K"], f[f"{key}_x1"], f[f"{key}_x2"]
    fields = c.fields(c.call(fn, R, C, K, x1, x2, case=case), case, ("R_cw", "t_cw", "X", "in_front", "counts"),
                      "a PoseChoice(R_cw, t_cw, X, in_front, counts) (or that 5-tuple)")
    if fields is None:
        return None
    R_s, t_s, X_s, front_s, counts_s = (as_float(v) for v in fields)
    if R_s is None or R_s.shape != (3, 3) or t_s is None or t_s.size != 3:
        c.fail(f"{case}: R_cw must have shape (3, 3) and t_cw shape (3,)")
        return None
    t_s = t_s.reshape(3)
    ref_k, ref_counts = int(f[f"{key}_index"]), f[f"{key}_counts"]
    k, confusion = _match_candidate(R_s, t_s, R, C, ref_k)
    if k is None:
        c.fail(f"{case}: R_cw is none of the four candidates R[k]: return the chosen candidate's rotation unchanged")
        return None
    counts = counts_s.astype(int) if counts_s is not None and counts_s.shape == (4,) else None
    tol = max(2, 0.01 * len(f[f"{key}_in_front"]))
    off = counts is not None and np.abs(counts - ref_counts).max() > tol
    tests = {f"cheirality_{i}" for i, cnt in enumerate(f[f"{key}_mis_counts"])
             if off and np.abs(counts - cnt).max() <= tol and np.abs(cnt - ref_counts).max() > tol}
    argmin = counts is not None and not off and k != ref_k and k == int(np.argmin(counts))
    return Outcome(case, k == ref_k, "picks the candidate with the points in front of both cameras",
                   f"chose candidate {k} ({int(ref_counts[k])} points in front of both cameras) instead of candidate "
                   f"{ref_k} ({int(ref_counts[ref_k])})", tests | ({"argmin"} if argmin else set()),
                   f"your counts are {counts.tolist()}, the reference's {ref_counts.tolist()}; keep the candidate with "
                   "the most points in front of BOTH cameras (z > 0 in camera 1 and r3ᵀ (X - C) > 0 in camera 2)"
                   if counts is not None else "keep the candidate with the most points in front of BOTH cameras",
                   {"key": key, "k": k, "confusion": confusion, "R": R_s, "t": t_s, "X": X_s, "front": front_s,
                    "counts": counts, "tol": tol, "off": off, "tests": tests}, defining=IN_FRONT)


def _pose_verdicts(c: Check, f, o: Outcome, tests: str | None, confusion: str | None) -> None:
    """After the choice: the rest of a right choice (t_cw, X, in_front and counts, the pose); ``tests`` the named
    cheirality test, ``confusion`` the named confusion of t_cw."""
    if not o.ok:
        return
    case, e = o.case, o.data
    key, k = e["key"], e["k"]
    if e["confusion"]:
        c.fail(f"{case}: the right candidate, but {_CONFUSIONS[e['confusion']]}",
               named=confusion if confusion == e["confusion"] else None)
        return
    X_ref, X_all = f[f"{key}_X"], f.get(f"{key}_X_all")
    X_s = e["X"]
    if X_s is None or X_s.shape != X_ref.shape:
        c.fail(f"{case}: X must have shape {X_ref.shape}, got {None if X_s is None else X_s.shape}")
    elif _points_close(X_s, X_ref, 5e-3):
        c.expect(True, f"{case}: X: matches the reference", "")
    else:
        other = [m for m in range(4) if X_all is not None and m != k and _points_close(X_s, X_all[m], 1e-6)]
        c.fail(f"{case}: X: {_points_numbers(X_s, X_ref)}"
               + (f": your X are the points of candidate {other[0]}, not of the chosen candidate {k} (the X of the last "
                  "candidate tried in your loop?): keep the X of the best candidate" if other else ""),
               named="X_of_other" if other else None)
    ref_front, ref_counts, counts = f[f"{key}_in_front"], f[f"{key}_counts"], e["counts"]
    n = len(ref_front)
    mine = tests if tests in e["tests"] else None
    if e["front"] is None or e["front"].shape != (n,):
        c.fail(f"{case}: in_front must be a bool array of shape ({n},)")
    elif counts is None:
        c.fail(f"{case}: counts must have shape (4,): the number of points in front for each candidate")
    else:
        close = not e["off"] and (e["front"].astype(bool) != ref_front).sum() <= max(1, int(0.01 * n))
        why = (_CHEIRALITY[mine] if mine else
               "count, for each candidate, the points with z > 0 in camera 1 AND r3ᵀ (X - C) > 0 in camera 2")
        c.expect(close, f"{case}: in_front and counts agree with the reference",
                 f"{case}: counts {counts.tolist()}, expected about {ref_counts.tolist()}: {why}",
                 defining=IN_FRONT if mine else None, named=mine)
    if f"{key}_true_R" in f:
        ok = np.allclose(e["R"], f[f"{key}_true_R"], atol=1e-5) and np.allclose(e["t"], f[f"{key}_true_t"], atol=1e-5)
        c.gate(ok, f"{case}: equals the true relative pose", f"{case}: differs from the true relative pose")
    if f"{key}_gt_R" in f:  # estimated from real matches: close to the ground truth, not equal
        rot = rotation_angle_deg(e["R"], f[f"{key}_gt_R"])
        cos_t = float(e["t"] @ f[f"{key}_gt_t"] / max(np.linalg.norm(e["t"]), 1e-300))
        c.expect(rot < 1.0 and cos_t > np.cos(np.radians(3.0)), f"{case}: agrees with the ground truth of the scene",
                 f"{case}: {rot:.2g}° and {np.degrees(np.arccos(np.clip(cos_t, -1, 1))):.2g}° (direction of t) from the "
                 "ground truth")


def check_choose_pose(fn, exercise: str = "choose_pose") -> None:
    """Check ``fn(R (4,3,3), C (4,3), K, x1, x2) -> PoseChoice`` on five synthetic pairs and the embedded pair."""
    f = load_fixture(FIXTURE)
    with Check(exercise) as c:
        outcomes = []
        for key, case in (("pose_syn_a", "synthetic pair A"), ("pose_syn_b", "synthetic pair B"),
                          ("pose_syn_wide", "wide-baseline synthetic pair"),
                          ("pose_syn_fwd", "synthetic pair, camera 2 moves forward"),
                          ("pose_syn_back", "synthetic pair, camera 2 moves backward"),
                          ("pose_embedded", "embedded scene")):
            if f"{key}_R" in f:
                o = _pose_outcome(c, fn, f, key, case)
                if o is not None:
                    outcomes.append(o)
        # a test is named by the counts where they are off, a confusion of t_cw where the choice is right
        tests = unique_key([o.data["tests"] for o in outcomes if o.data["off"]])
        confusion = unique_key([{o.data["confusion"]} for o in outcomes if o.ok and o.data["confusion"]])
        report_cases(c, outcomes, {**_CHEIRALITY, "argmin": _ARGMIN},
                     then=lambda o, _: _pose_verdicts(c, f, o, tests, confusion))
        c.blame_earlier("triangulate_linear", fn=fn)


# --------------------------------------------------------------------------- triangulate_nonlinear


#: What each stored mistake of the non-linear triangulation (``nl_<case>_mis_<key>``) means, as what the student did.
_NONLINEAR_MISTAKES = {
    "no_depth_division": "your residual compares K (R X + t) with the pixel without dividing by its depth z: project "
                         "with (K (R X + t))[:2] / (K (R X + t))[2]",
    "cross_multiplied": "your residual is cross-multiplied, (K (R X + t))[:2] - x (K (R X + t))[2]: that is an "
                        "algebraic error, not the reprojection error in pixels; divide by the depth, then subtract x",
    "nan_as_zero": "you turned the unseen observations (NaN in uv) into pixels (0, 0): leave them out of the residuals",
    "unseen_not_refined": "you did not refine the points that some view does not see: use every view in which the "
                          "point is seen (uv[j, i] not NaN), as long as there are two",
    "two_views": "you used only the first two views: sum the residuals over every view in which the point is seen "
                 "(uv[:, i] not NaN)",
    "R_transposed": "you used R transposed: the cameras map x_cam = R_cw X + t_cw, use R_cws[i] itself (not .T)",
    "homogeneous": "each point lies on the line through the origin of the optimum but at another distance: you "
                   "optimized a homogeneous point and did not divide by its last coordinate",
}


def _nonlinear_keys(f: dict, key: str, A: np.ndarray, ref: np.ndarray) -> tuple[set[str], set[str]]:
    """The named mistakes whose result the points ``A`` reproduce on case ``key``.

    Most mistakes are recognised by their stored result. A refinement with ``R`` transposed diverges
    (the points run off to 1e7 and beyond, where the last bits of the CPU decide), so it is recognised
    by what it optimized: the points fit the cameras with ``R_cwsᵀ`` better than the start did, and
    better than they fit the true cameras.
    """
    K, R, t, uv, X0 = (f[f"{key}_{s}"] for s in ("K", "R", "t", "uv", "X0"))
    out = set()
    Rt = np.transpose(R, (0, 2, 1))
    if _reproj_rms(K, Rt, t, uv, A) < min(_reproj_rms(K, Rt, t, uv, X0), _reproj_rms(K, R, t, uv, A)):
        out.add("R_transposed")
    testable = set(_NONLINEAR_MISTAKES)
    if np.median(np.linalg.norm(A - ref, axis=1)) > 100 * _scale(ref):
        testable.discard("R_transposed")  # the points ran off: what they optimized cannot be read any more
    off = np.linalg.norm(A - ref, axis=1).mean()  # how far from the optimum; a mistake must explain that

    def explains(Y) -> bool:
        return Y is not None and Y.shape == A.shape and np.linalg.norm(A - Y, axis=1).mean() <= 0.05 * off

    out |= {name for name in _NONLINEAR_MISTAKES if explains(f.get(f"{key}_mis_{name}"))}
    if explains(f.get(f"{key}_X_2views")):
        out.add("two_views")
    cos = (A * ref).sum(1) / (np.linalg.norm(A, axis=1) * np.linalg.norm(ref, axis=1) + 1e-300)
    if np.median(cos) > 1 - 1e-7 and np.median(np.abs(np.linalg.norm(A, axis=1) / np.linalg.norm(ref, axis=1) - 1)) > 1e-3:
        out.add("homogeneous")
    return out, testable


def check_triangulate_nonlinear(fn, exercise: str = "triangulate_nonlinear") -> None:
    """Check ``fn(K, R_cws, t_cws, uv, X0) -> X`` on a 3-view synthetic scene and the embedded pair."""
    f = load_fixture(FIXTURE)
    with Check(exercise) as c:
        results = []
        for key, case in (("nl_syn", "synthetic scene, 3 views"), ("nl_embedded", "embedded scene, 2 views")):
            if f"{key}_K" not in f:
                continue
            K, R, t, uv, X0, ref = (f[f"{key}_{s}"] for s in ("K", "R", "t", "uv", "X0", "X"))
            X = c.call_explained(fn, K, R, t, uv, X0, case=case, explain=_not_finite if np.isnan(uv).any() else None)
            A = _points_shape(c, X, len(ref), case, "the points contain NaN: uv is NaN where a view does not see the "
                              "point; leave those views out of the residuals (np.isfinite(uv[j, i]).all())")
            if A is None:
                continue
            if np.allclose(A, X0, atol=1e-12):
                c.fail(f"{case}: the points did not move: return the optimized points (result.x), not X0")
                continue
            results.append((key, case, A))
        e_of = {key: tuple(_reproj_rms(*(f[f"{key}_{s}"] for s in ("K", "R", "t", "uv")), Y)
                           for Y in (f[f"{key}_X0"], f[f"{key}_X"], A)) for key, _, A in results}
        failing = [(key, A) for key, _, A in results if e_of[key][2] > e_of[key][1] * (1 + 1e-3) + 1e-6]
        named = unique_key([_nonlinear_keys(f, key, A, f[f"{key}_X"]) for key, A in failing])
        advice = ("minimize the plain sum of squared reprojection errors (pixels) over every view that sees the "
                  "point, to convergence")
        for key, case, A in results:
            e0, e_ref, e_s = e_of[key]
            refinement_verdicts(c, case, e0, e_s, e_s <= e_ref * (1 + 1e-3) + 1e-6,
                                f"RMS reprojection error {e_s:.4g} px, the optimum is {e_ref:.4g} px",
                                _NONLINEAR_MISTAKES[named] if named else None,
                                (f"the optimum is {e_ref:.3g} px: {advice}", advice), named)


def _not_finite(exc: Exception) -> str | None:
    """scipy's "not finite" error on a case whose uv holds NaN, explained."""
    if not isinstance(exc, ValueError) or "finite" not in str(exc).lower():
        return None
    return (f"your function raised ValueError: {str(exc)[:100]}: uv is NaN where a view does not see the point (here "
            "some points are unseen in one view); leave out the views where the point is not seen: residuals only "
            "over the i with np.isfinite(uv[j, i]).all()")

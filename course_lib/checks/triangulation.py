"""Checks of notebook 03 (triangulation) and its step input.

Each ``check_*`` function runs the student's function on stored cases (fixture ``triangulation``,
built in the instructor's kit from :mod:`course_lib.sfm.triangulation` by ``python -m course_lib fixtures triangulation``):
a synthetic scene with known truth (:func:`course_lib.data.synthetic.make_scene`) and the
embedded scene (``data/synthetic-building``, ground truth from
:func:`course_lib.data.building.load_ground_truth`). It compares with the stored reference
results and with properties, and names the likely mistake:

* ``triangulate_linear``: homogeneous points returned (no division by ``X_h[3]``), points as
  columns, the cameras swapped in the rows of A, u and v swapped, the singular vector of the
  largest singular value, a single point (N = 1) that loses its axis.
* ``choose_pose``: a cheirality test that checks only one camera, forgets ``- C``, uses ``t``
  where ``C`` belongs or the third column of ``R`` instead of its third row; ``R_cw`` returned
  transposed (``R_wc``); the centre ``C`` returned as ``t_cw``. Defining property: the points in
  front of BOTH cameras; two pairs (camera 2 moving forward, backward) are built so that a test
  on one camera only picks the wrong candidate, and the counts expose it on every pair.
* ``triangulate_nonlinear``: an optimization that increases the error, does not move the
  points, stops early, or uses only two of the views.

The cases and the reference's results on them are stored arrays, made on the instructor's side
by :mod:`course_lib.instructor.cases.triangulation`; this module imports no reference solution and ships
to students.
"""

from __future__ import annotations

import numpy as np

from course_lib.conventions import project
from course_lib.checks.core import FAILED, Check, declare_defining, load_fixture

__all__ = [
    "check_triangulate_linear",
    "check_choose_pose",
    "check_triangulate_nonlinear",
    "pose_fields",
]

FIXTURE = "triangulation"

declare_defining("choose_pose", {
    "in front of both cameras": "the right candidate is the one with the points in front of camera 1 AND camera 2",
})


# --------------------------------------------------------------------------- step input


# --------------------------------------------------------------------------- fixtures


# --------------------------------------------------------------------------- helpers


def _arr(v) -> np.ndarray | None:
    if v is FAILED or v is None:
        return None
    try:
        return np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        return None


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


def _angle_deg(R_a, R_b) -> float:
    c = np.clip((np.trace(np.asarray(R_a) @ np.asarray(R_b).T) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(c)))


def _scale(X) -> float:
    X = np.asarray(X, float)
    return float(max(np.linalg.norm(X.max(0) - X.min(0)), 1e-9))


#: What each stored mistake of the linear triangulation (``lin_<case>_mis_<key>``) means.
_LINEAR_MISTAKES = {
    "swapped": "the cameras are swapped in the rows of A: the rows of x1 use P2 and those of x2 use P1; build "
               "u1 p3ᵀ - p1ᵀ, v1 p3ᵀ - p2ᵀ from P1 and the same two rows with x2 from P2",
    "uv_swapped": "u and v are swapped in the rows of A: u goes with the first row of P (u p3ᵀ - p1ᵀ) and v with the "
                  "second (v p3ᵀ - p2ᵀ)",
    "largest": "you took the singular vector of the LARGEST singular value: X_h is the last row of Vt (Vt[-1]), "
               "the least-squares null vector of A",
}


def _reprojection_px(P, X, x) -> np.ndarray:
    """(N,) pixel distances between x and the projection of X by P."""
    Xh = np.column_stack([X, np.ones(len(X))]) @ np.asarray(P, float).T
    with np.errstate(all="ignore"):
        return np.linalg.norm(Xh[:, :2] / Xh[:, 2:] - x, axis=1)


def _points_verdict(c: Check, X, ref, case: str, tol: float, P1=None, P2=None, x1=None, x2=None,
                    pass_msg: str = "matches the reference", mis: dict | None = None) -> bool:
    """Shape and closeness of triangulated points, with the typical mistakes named."""
    if X is FAILED:
        return False
    A = _arr(X)
    n = ref.shape[0]
    if A is None:
        return c.fail(f"{case}: expected an array of shape ({n}, 3), got {type(X).__name__}")
    if A.shape == (n, 4):
        return c.fail(f"{case}: returned homogeneous points of shape ({n}, 4): divide by the last coordinate "
                      "X_h[3] and drop it")
    if A.shape in ((3, n), (4, n)) and n not in (3, 4):
        return c.fail(f"{case}: shape {A.shape}: points are rows in the kit, return shape ({n}, 3) (transpose)")
    if A.shape != ref.shape:
        return c.fail(f"{case}: shape {A.shape}, expected {ref.shape}")
    if not np.isfinite(A).all():
        return c.fail(f"{case}: the points contain NaN or inf")
    d = np.linalg.norm(A - ref, axis=1)
    scale = _scale(ref)
    if np.median(d) <= tol * scale:
        return c.expect(True, f"{case}: {pass_msg}", "")
    # not divided by the homogeneous coordinate: each row parallel to the right point, other length
    cos = (A * ref).sum(1) / (np.linalg.norm(A, axis=1) * np.linalg.norm(ref, axis=1) + 1e-300)
    if np.median(np.abs(cos)) > 1 - 1e-6 and np.median(np.abs(np.linalg.norm(A, axis=1) / np.linalg.norm(ref, axis=1) - 1)) > 1e-3:
        return c.fail(f"{case}: each point lies on the right line through the origin but at the wrong distance: "
                      "did you divide by the homogeneous coordinate (X = X_h[:3] / X_h[3])?")
    if np.median(np.linalg.norm(A - (-ref), axis=1)) <= tol * scale:
        return c.fail(f"{case}: the points are mirrored through the origin (X -> -X): divide by X_h[3], keeping its sign")
    hint = ""
    for key, Y in (mis or {}).items():
        if Y.shape == A.shape and np.median(np.linalg.norm(A - Y, axis=1)) <= max(tol, 1e-6) * scale:
            return c.fail(f"{case}: {_LINEAR_MISTAKES[key]}")
    if P1 is not None:
        e_right = np.median(np.concatenate([_reprojection_px(P1, A, x1), _reprojection_px(P2, A, x2)]))
        e_swap = np.median(np.concatenate([_reprojection_px(P2, A, x1), _reprojection_px(P1, A, x2)]))
        if e_swap < 0.5 * e_right:
            return c.fail(f"{case}: your points project well with the cameras swapped ({e_swap:.3g} px, {e_right:.3g} px "
                          f"as given): {_LINEAR_MISTAKES['swapped']}")
        hint = f" (median reprojection error {e_right:.3g} px)"
    return c.fail(f"{case}: median distance to the reference points {np.median(d):.3g} (scene size {scale:.3g}){hint}")


# --------------------------------------------------------------------------- triangulate_linear


def check_triangulate_linear(fn, exercise: str = "triangulate_linear") -> None:
    """Check ``fn(P1, P2, x1, x2) -> X (N, 3)`` on a noiseless, a noisy and the embedded pair."""
    f = load_fixture(FIXTURE)
    with Check(exercise) as c:
        for name, case, tol in (("noiseless", "noiseless synthetic pair", 1e-6), ("noisy", "noisy synthetic pair", 5e-3),
                                ("embedded", "embedded scene", 5e-3)):
            k = f"lin_{name}"
            if f"{k}_P1" not in f:
                continue
            P1, P2, x1, x2 = f[f"{k}_P1"], f[f"{k}_P2"], f[f"{k}_x1"], f[f"{k}_x2"]
            X = c.call(fn, P1, P2, x1, x2, case=case)
            if X is FAILED:
                continue
            mis = {key: f[f"{k}_mis_{key}"] for key in _LINEAR_MISTAKES if f"{k}_mis_{key}" in f}
            if name == "noiseless":
                _points_verdict(c, X, f[f"{k}_Xtrue"], case, tol, P1, P2, x1, x2,
                                pass_msg="recovers the true points exactly", mis=mis)
            else:
                _points_verdict(c, X, f[f"{k}_X"], case, tol, P1, P2, x1, x2, mis=mis)
        # one point at a time must work too (N = 1)
        P1, P2 = f["lin_noiseless_P1"], f["lin_noiseless_P2"]
        X1 = c.call(fn, P1, P2, f["lin_noiseless_x1"][:1], f["lin_noiseless_x2"][:1], case="a single point (N = 1)")
        if X1 is not FAILED:
            A = _arr(X1)
            want = f["lin_noiseless_Xtrue"][:1]
            case = "a single point (N = 1)"
            if A is None or A.size != 3:
                c.fail(f"{case}: expected an array of shape (1, 3), got "
                       f"{type(X1).__name__ if A is None else 'shape ' + str(A.shape)}")
            elif A.shape != (1, 3):
                c.fail(f"{case}: returned shape {A.shape}: keep the points axis for N = 1 (shape (1, 3)); "
                       "np.squeeze or X[0] drops it")
            else:
                c.expect(np.allclose(A, want, rtol=1e-6, atol=1e-6), f"{case} works",
                         f"{case}: the right shape (1, 3) but not the true point ({np.round(A[0], 3).tolist()} instead "
                         f"of {np.round(want[0], 3).tolist()}): build A from this one point as for N points")


# --------------------------------------------------------------------------- choose_pose


def pose_fields(out):
    """``(R_cw, t_cw, X, in_front, counts)`` from a PoseChoice-like object or a tuple, or None."""
    if out is FAILED or out is None:
        return None
    names = ("R_cw", "t_cw", "X", "in_front", "counts")
    if all(hasattr(out, n) for n in names):
        return tuple(getattr(out, n) for n in names)
    if isinstance(out, (tuple, list)) and len(out) >= 5:
        return tuple(out[:5])
    return None


#: The wrong cheirality tests, in the order of the rows of the stored ``<case>_mis_counts``.
_CHEIRALITY_MISTAKES = (
    "the test checks only camera 2: require z > 0 in camera 1 as well",
    "the test checks only camera 1: require r3ᵀ (X - C) > 0 for camera 2 as well",
    "the test forgets the centre: use r3ᵀ (X - C) > 0, not r3ᵀ X > 0",
    "the test uses t where the centre C belongs: r3ᵀ (X - C) with C = -Rᵀ t",
    "the test uses the third column of R: r3ᵀ is the third ROW, R[2]",
    "the sign of the cheirality test is flipped, it keeps the points behind the cameras: in front means depth > 0",
)


def _cheirality_variants(f: dict, key: str) -> list[tuple[str, int, np.ndarray]]:
    """(mistake, index the mistake picks, its counts) for the typical wrong cheirality tests of case ``key``."""
    counts = f[f"{key}_mis_counts"]
    return [(hint, int(np.argmax(cnt)), cnt) for hint, cnt in zip(_CHEIRALITY_MISTAKES, counts)]


def _match_candidate(R_s, t_s, R, C, right: int) -> tuple[int | None, str | None]:
    """Index of the candidate the student returned, or a named confusion.

    Two candidates share each rotation (``+C`` and ``-C``), so one answer can read as several
    (``(R, -C)`` is candidate k with t = -C, or its partner with t = C): of the readings, in the
    order below, the one of the right candidate ``right`` wins (unless another candidate is returned
    exactly), else the first.
    """
    same = lambda a, b: np.allclose(a, b, atol=1e-6)  # noqa: E731
    transposed = "R_cw is transposed (that is R_wc, world from camera): return the candidate R[k] itself"
    c_vs_t = "t_cw is not -R_cw @ C (C vs t confusion): t_cw = -R_cw @ C"
    readings = []
    for k in range(4):
        t_k = -R[k] @ C[k]
        if same(R_s, R[k]):
            readings += [(0, k, None)] if same(t_s, t_k) else []
            readings += [(1, k, "t_cw is the camera centre C: the translation is t_cw = -R_cw @ C")] if same(t_s, C[k]) else []
            readings += [(2, k, c_vs_t)] if same(t_s, -C[k]) or same(t_s, R[k].T @ C[k]) else []
            readings += [(4, k, "t_cw does not belong to the chosen rotation's candidate: t_cw = -R[k] @ C[k]")]
        if same(R_s, R[k].T):
            readings += [(3 if any(same(t_s, t) for t in (t_k, C[k], -C[k], R[k].T @ C[k])) else 5, k, transposed)]
    if not readings:
        return None, None
    readings.sort(key=lambda r: (r[0], r[1] != right, r[1]))
    best = readings[0][0]
    _, k, why = next((r for r in readings if best > 0 and r[1] == right and r[0] <= max(best, 2)), readings[0])
    return k, why


def _pose_case(c: Check, fn, f, key, case) -> None:
    R, C, K, x1, x2 = f[f"{key}_R"], f[f"{key}_C"], f[f"{key}_K"], f[f"{key}_x1"], f[f"{key}_x2"]
    out = c.call(fn, R, C, K, x1, x2, case=case)
    if out is FAILED:
        return
    fields = pose_fields(out)
    if fields is None:
        c.fail(f"{case}: return a PoseChoice(R_cw, t_cw, X, in_front, counts) (or that 5-tuple), got {type(out).__name__}")
        return
    R_s, t_s, X_s, front_s, counts_s = (_arr(v) for v in fields)
    if R_s is None or R_s.shape != (3, 3) or t_s is None or t_s.size != 3:
        c.fail(f"{case}: R_cw must have shape (3, 3) and t_cw shape (3,)")
        return
    t_s = t_s.reshape(3)
    ref_k = int(f[f"{key}_index"])
    k, confusion = _match_candidate(R_s, t_s, R, C, ref_k)
    if k is None:
        c.fail(f"{case}: R_cw is none of the four candidates R[k]: return the chosen candidate's rotation unchanged")
        return
    if k != ref_k:
        variants = _cheirality_variants(f, key)
        named = [hint for hint, idx, _ in variants if idx == k]
        if counts_s is not None and counts_s.shape == (4,):  # prefer the variant that also explains the counts
            named = [hint for hint, idx, cnt in variants if idx == k and np.array_equal(cnt, counts_s)] + named
        why = named[0] if named else ("points behind the camera: keep the candidate with the most points in front "
                                       "of BOTH cameras (z > 0 in camera 1 and r3ᵀ (X - C) > 0 in camera 2)")
        ref_counts = f[f"{key}_counts"]
        c.fail(f"{case}: chose candidate {k} ({int(ref_counts[k])} points in front of both cameras) instead of "
               f"candidate {ref_k} ({int(ref_counts[ref_k])}): {why}", defining="in front of both cameras")
        return
    if confusion:
        c.fail(f"{case}: the right candidate, but {confusion}")
        return
    # a gate: a constant answer (always R[0]) would otherwise earn the cases whose right candidate is 0
    c.gate(True, f"{case}: picks the candidate with the points in front of both cameras", "",
           defining="in front of both cameras")
    if X_s is None or X_s.shape != f[f"{key}_X"].shape:
        c.fail(f"{case}: X must have shape {f[f'{key}_X'].shape}, got {None if X_s is None else X_s.shape}")
    else:
        _points_verdict(c, X_s, f[f"{key}_X"], f"{case}: X", 5e-3)
    ref_front, ref_counts = f[f"{key}_in_front"], f[f"{key}_counts"]
    n = len(ref_front)
    if front_s is None or front_s.shape != (n,):
        c.fail(f"{case}: in_front must be a bool array of shape ({n},)")
    elif counts_s is None or counts_s.shape != (4,):
        c.fail(f"{case}: counts must have shape (4,): the number of points in front for each candidate")
    else:
        tol = max(2, 0.01 * n)
        close = (np.abs(counts_s - ref_counts).max() <= tol
                 and (front_s.astype(bool) != ref_front).sum() <= max(1, int(0.01 * n)))
        named = sorted((np.abs(counts_s - counts).max(), hint) for hint, _, counts in _cheirality_variants(f, key)
                       if np.abs(counts_s - counts).max() <= tol and np.abs(counts - ref_counts).max() > tol)
        named = [hint for _, hint in named]
        why = named[0] if named else ("count, for each candidate, the points with z > 0 in camera 1 AND "
                                      "r3ᵀ (X - C) > 0 in camera 2")
        c.expect(close, f"{case}: in_front and counts agree with the reference",
                 f"{case}: counts {counts_s.astype(int).tolist()}, expected about {ref_counts.tolist()}: {why}",
                 defining="in front of both cameras" if named else None)
    if f"{key}_true_R" in f:
        ok = np.allclose(R_s, f[f"{key}_true_R"], atol=1e-6) and np.allclose(t_s, f[f"{key}_true_t"], atol=1e-6)
        c.gate(ok, f"{case}: equals the true relative pose", f"{case}: differs from the true relative pose")
    if f"{key}_gt_R" in f:  # estimated from real matches: close to the ground truth, not equal
        rot = _angle_deg(R_s, f[f"{key}_gt_R"])
        cos_t = float(t_s @ f[f"{key}_gt_t"] / max(np.linalg.norm(t_s), 1e-300))
        c.expect(rot < 1.0 and cos_t > np.cos(np.radians(3.0)), f"{case}: agrees with the ground truth of the scene",
                 f"{case}: {rot:.2g}° and {np.degrees(np.arccos(np.clip(cos_t, -1, 1))):.2g}° (direction of t) from the "
                 "ground truth")


def check_choose_pose(fn, exercise: str = "choose_pose") -> None:
    """Check ``fn(R (4,3,3), C (4,3), K, x1, x2) -> PoseChoice`` on two synthetic pairs and the embedded pair."""
    f = load_fixture(FIXTURE)
    with Check(exercise) as c:
        for key, case in (("pose_syn_a", "synthetic pair A"), ("pose_syn_b", "synthetic pair B"),
                          ("pose_syn_wide", "wide-baseline synthetic pair"),
                          ("pose_syn_fwd", "synthetic pair, camera 2 moves forward"),
                          ("pose_syn_back", "synthetic pair, camera 2 moves backward"),
                          ("pose_embedded", "embedded scene")):
            if f"{key}_R" in f:
                _pose_case(c, fn, f, key, case)
        c.blame_earlier("triangulate_linear", fn=fn)


# --------------------------------------------------------------------------- triangulate_nonlinear


#: What each stored mistake of the non-linear triangulation (``nl_<case>_mis_<key>``) means.
_NONLINEAR_MISTAKES = {
    "no_depth_division": "the residual compares K (R X + t) with the pixel without dividing by its depth z: project "
                         "with (K (R X + t))[:2] / (K (R X + t))[2]",
    "cross_multiplied": "the residual is cross-multiplied, (K (R X + t))[:2] - x (K (R X + t))[2]: that is an algebraic "
                        "error, not the reprojection error in pixels; divide by the depth, then subtract x",
    "nan_as_zero": "the unseen observations (NaN in uv) became pixels (0, 0): leave them out of the residuals",
    "unseen_not_refined": "the points that some view does not see were not refined: use every view in which the "
                          "point is seen (uv[j, i] not NaN), as long as there are two",
}


def _nonlinear_diagnosis(f: dict, key: str, A: np.ndarray, ref: np.ndarray) -> str | None:
    """The named mistake whose result the points ``A`` reproduce, or None.

    Most mistakes are recognised by their stored result. A refinement with ``R`` transposed diverges
    (the points run off to 1e7 and beyond, where the last bits of the CPU decide), so it is recognised
    by what it optimized: the points fit the cameras with ``R_cwsᵀ`` better than the start did, and
    better than they fit the true cameras.
    """
    K, R, t, uv, X0 = (f[f"{key}_{s}"] for s in ("K", "R", "t", "uv", "X0"))
    Rt = np.transpose(R, (0, 2, 1))
    if _reproj_rms(K, Rt, t, uv, A) < min(_reproj_rms(K, Rt, t, uv, X0), _reproj_rms(K, R, t, uv, A)):
        return "R is transposed: the cameras map x_cam = R_cw X + t_cw, use R_cws[i] itself (not .T)"
    off = np.linalg.norm(A - ref, axis=1).mean()  # how far from the optimum; a mistake must explain that

    def explains(Y) -> bool:
        return Y is not None and Y.shape == A.shape and np.linalg.norm(A - Y, axis=1).mean() <= 0.05 * off

    for name, hint in _NONLINEAR_MISTAKES.items():
        if explains(f.get(f"{key}_mis_{name}")):
            return hint
    if explains(f.get(f"{key}_X_2views")):
        return ("you used only the first two views: sum the residuals over every view in which the point is seen "
                "(uv[:, i] not NaN)")
    cos = (A * ref).sum(1) / (np.linalg.norm(A, axis=1) * np.linalg.norm(ref, axis=1) + 1e-300)
    if np.median(cos) > 1 - 1e-7 and np.median(np.abs(np.linalg.norm(A, axis=1) / np.linalg.norm(ref, axis=1) - 1)) > 1e-3:
        return ("each point lies on the line through the origin of the optimum but at another distance: did you "
                "optimize a homogeneous point and forget to divide by its last coordinate?")
    return None


def check_triangulate_nonlinear(fn, exercise: str = "triangulate_nonlinear") -> None:
    """Check ``fn(K, R_cws, t_cws, uv, X0) -> X`` on a 3-view synthetic scene and the embedded pair."""
    f = load_fixture(FIXTURE)
    with Check(exercise) as c:
        for key, case in (("nl_syn", "synthetic scene, 3 views"), ("nl_embedded", "embedded scene, 2 views")):
            if f"{key}_K" not in f:
                continue
            K, R, t, uv, X0, ref = (f[f"{key}_{s}"] for s in ("K", "R", "t", "uv", "X0", "X"))
            X = c.call(fn, K, R, t, uv, X0, case=case)
            if X is FAILED:
                continue
            A = _arr(X)
            if A is not None and A.shape == (ref.shape[0], 4):
                c.fail(f"{case}: returned homogeneous points of shape {A.shape}: divide by the last coordinate and drop it")
                continue
            if A is None or A.shape != ref.shape:
                c.fail(f"{case}: expected shape {ref.shape}, got {None if A is None else A.shape}")
                continue
            if not np.isfinite(A).all():
                c.fail(f"{case}: the points contain NaN: skip the observations that are NaN in uv (unseen), "
                       "they must not enter the residuals")
                continue
            e0, e_ref, e_s = (_reproj_rms(K, R, t, uv, Y) for Y in (X0, ref, A))
            if np.allclose(A, X0, atol=1e-12):
                c.fail(f"{case}: the points did not move: return the optimized points (result.x), not X0")
                continue
            named = _nonlinear_diagnosis(f, key, A, ref)
            if e_s > e0 * (1 + 1e-9) + 1e-9:
                c.fail(f"{case}: {named or 'the non-linear step increased the RMS reprojection error'} "
                       f"({e0:.3g} px before, {e_s:.3g} px after; the optimum is {e_ref:.3g} px)")
                continue
            c.gate(True, f"{case}: lowers the reprojection error", "")
            ok = e_s <= e_ref * (1 + 1e-3) + 1e-6
            if ok or named is None:
                c.expect(ok, f"{case}: reaches the least-squares optimum",
                         f"{case}: RMS reprojection error {e_s:.4g} px, the optimum is {e_ref:.4g} px: run the solver to "
                         "convergence and use every view that sees the point")
            else:
                c.fail(f"{case}: {named} (RMS reprojection error {e_s:.4g} px, the optimum is {e_ref:.4g} px)")

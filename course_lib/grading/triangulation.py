"""Checks of notebook 03 (triangulation) and its step input.

Each ``check_*`` function runs the student's function on stored cases (fixture ``triangulation``,
built from :mod:`course_lib.sfm.triangulation` by ``python -m course_lib fixtures triangulation``):
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

Step input: :func:`step_input` gives notebook 03 the reference result of step 2 (inlier matches,
F, E and the four pose candidates of the embedded pair) from fixture ``triangulation_step``, so
the notebook runs without the reference solutions of notebooks 01-02.

The reference solutions are imported only inside the fixture builders and :func:`two_view_input`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from course_lib.conventions import project
from course_lib.grading.core import FAILED, Check, declare_defining, fixture_builder, load_fixture
from course_lib.paths import EMBEDDED_SFM

__all__ = [
    "check_triangulate_linear",
    "check_choose_pose",
    "check_triangulate_nonlinear",
    "step_input",
    "two_view_input",
    "pose_fields",
    "EMBEDDED_PAIR",
]

FIXTURE = "triangulation"
STEP_FIXTURE = "triangulation_step"
#: The image pair of the embedded scene that notebooks 03 and 04 start from (0-based).
EMBEDDED_PAIR = (0, 1)
#: Seed of the reference RANSAC on F for the step input.
STEP_SEED = 0
#: The most matches stored per embedded case (keeps the fixture small).
MAX_EMBEDDED = 300

declare_defining("choose_pose", {
    "in front of both cameras": "the right candidate is the one with the points in front of camera 1 AND camera 2",
})


# --------------------------------------------------------------------------- step input


def two_view_input(folder, pair: tuple[int, int] = EMBEDDED_PAIR, seed: int = STEP_SEED) -> dict[str, np.ndarray]:
    """Step 2's reference result for one image pair, computed with the reference library.

    Args:
        folder: a P3 folder (the embedded scene or ``course_data("wpi")``).
        pair: 0-based image indices ``(i, j)``, ``i < j``.
        seed: seed of the RANSAC on F.

    Returns:
        dict with ``K (3, 3)``, ``pair (2,)``, ``F (3, 3)``, ``E (3, 3)``, ``x1, x2 (N, 2)`` (the RANSAC
        inliers), ``track_ids (N,)`` (-1 if not in a track), ``rgb (N, 3)`` uint8, ``R_candidates (4, 3, 3)``,
        ``C_candidates (4, 3)``, ``n_matches`` (before RANSAC).
    """
    try:
        from course_lib.data.p3 import read_p3
        from course_lib.sfm import essential, fundamental
    except ModuleNotFoundError as exc:  # the student release has no reference solutions
        raise RuntimeError(
            f"computing the step input for {folder} needs the reference library ({exc.name}); "
            "use the embedded data (DATA = EMBEDDED_SFM) or your own functions from notebooks 01-02"
        ) from None
    data = read_p3(folder)
    i, j = pair
    m = data.matches[(i, j)]
    try:  # the same RANSAC setting as notebook 01's step result (course_lib.grading.fundamental.two_view_step)
        from course_lib.grading.fundamental import STEP_THRESHOLD_PX as threshold_px
    except ImportError:
        threshold_px = 1.0
    res = fundamental.ransac_fundamental(m.x1, m.x2, np.random.default_rng(seed), threshold_px=threshold_px)
    E = essential.essential_from_fundamental(res.F, data.K)
    R, C = essential.pose_candidates(E)
    inl = res.inliers
    return {
        "K": data.K,
        "pair": np.array(pair),
        "F": res.F,
        "E": E,
        "x1": m.x1[inl],
        "x2": m.x2[inl],
        "track_ids": m.track_ids[inl],
        "rgb": m.rgb[inl],
        "R_candidates": R,
        "C_candidates": C,
        "n_matches": np.array(len(m.x1)),
    }


def _relative_truth(folder, pair) -> tuple[np.ndarray, np.ndarray] | None:
    """True pose of camera j in camera i's frame, translation scaled to unit length (or None)."""
    gt = Path(folder) / "ground_truth.json"
    if not gt.exists():
        return None
    from course_lib.data.building import load_ground_truth

    _, _, R_cw, t_cw = load_ground_truth(folder)
    i, j = pair
    R = R_cw[j] @ R_cw[i].T
    t = t_cw[j] - R @ t_cw[i]
    return R, t / np.linalg.norm(t)


@fixture_builder(STEP_FIXTURE)
def _build_step() -> dict[str, np.ndarray]:
    if not (EMBEDDED_SFM / "ground_truth.json").exists():
        return {}  # the embedded scene is not generated yet (python -m course_lib make-data): nothing to store
    out = two_view_input(EMBEDDED_SFM)
    truth = _relative_truth(EMBEDDED_SFM, EMBEDDED_PAIR)
    if truth is not None:
        out["true_R_cw"], out["true_t_cw"] = truth
    return out


def step_input(folder=None) -> dict[str, np.ndarray]:
    """Notebook 03's starting point: step 2's reference result for the pair :data:`EMBEDDED_PAIR`.

    Args:
        folder: ``None`` or the embedded scene: read the stored fixture (no reference needed);
            another P3 folder (e.g. ``course_data("wpi")``): compute it with :func:`two_view_input`.

    Returns:
        the dict of :func:`two_view_input` (for the embedded scene also ``true_R_cw``,
        ``true_t_cw``: the true relative pose, unit translation).
    """
    if folder is None or Path(folder).resolve() == EMBEDDED_SFM.resolve():
        return load_fixture(STEP_FIXTURE)
    return two_view_input(folder)


# --------------------------------------------------------------------------- fixtures


def _synthetic_two_view(seed: int, n_points: int, noise_px: float):
    from course_lib.data.synthetic import make_scene

    sc = make_scene(np.random.default_rng(seed), n_cameras=3, n_points=n_points, noise_px=noise_px,
                    outlier_fraction=0.0, dropout=0.0)
    return sc


def _relative(sc, i, j):
    R = sc.R_cw[j] @ sc.R_cw[i].T
    t = sc.t_cw[j] - R @ sc.t_cw[i]
    return R, t


@fixture_builder(FIXTURE)
def _build() -> dict[str, np.ndarray]:
    from course_lib.conventions import projection_matrix, skew
    from course_lib.sfm import essential
    from course_lib.sfm import triangulation as tri

    out: dict[str, np.ndarray] = {}
    K = None

    # -- triangulate_linear: noiseless and noisy synthetic pairs with general poses (camera 1 is not I)
    for name, seed, n, noise in (("noiseless", 11, 40, 0.0), ("noisy", 12, 120, 1.0)):
        sc = _synthetic_two_view(seed, n, noise)
        K = sc.K
        P1, P2 = projection_matrix(sc.K, sc.R_cw[0], sc.t_cw[0]), projection_matrix(sc.K, sc.R_cw[1], sc.t_cw[1])
        x1, x2, _, ids = sc.pair(0, 1)
        out.update({f"lin_{name}_P1": P1, f"lin_{name}_P2": P2, f"lin_{name}_x1": x1, f"lin_{name}_x2": x2,
                    f"lin_{name}_X": tri.triangulate_linear(P1, P2, x1, x2), f"lin_{name}_Xtrue": sc.X[ids]})

    # -- choose_pose: candidates from the true E; two scenes whose correct candidate has another index
    for name, seed in (("syn_a", 21), ("syn_b", 24)):
        sc = _synthetic_two_view(seed, 80, 0.5)
        R, t = _relative(sc, 0, 1)
        x1, x2, _, _ = sc.pair(0, 1)
        Rc, Cc = essential.pose_candidates(skew(t) @ R)
        _store_pose_case(out, f"pose_{name}", Rc, Cc, sc.K, x1, x2, tri)
        out[f"pose_{name}_true_R"], out[f"pose_{name}_true_t"] = R, t / np.linalg.norm(t)

    # -- a wide-baseline pair (135 degrees around a small object, close by): here forgetting "- C" or
    #    using the third column of R changes the answer, unlike in the narrow pairs above
    from course_lib.data.synthetic import look_at

    rng = np.random.default_rng(27)
    Xw = rng.uniform(-1.0, 1.0, size=(60, 3))
    R1, t1 = look_at(np.array([0.0, 0.0, -4.0]), np.zeros(3))
    R2, t2 = look_at(np.array([2.8, -0.5, 2.8]), np.zeros(3))
    x1 = project(K, R1, t1, Xw) + rng.normal(0.0, 0.3, (60, 2))
    x2 = project(K, R2, t2, Xw) + rng.normal(0.0, 0.3, (60, 2))
    R = R2 @ R1.T
    t = t2 - R @ t1
    Rc, Cc = essential.pose_candidates(skew(t) @ R)
    _store_pose_case(out, "pose_syn_wide", Rc, Cc, K, x1, x2, tri)
    out["pose_syn_wide_true_R"], out["pose_syn_wide_true_t"] = R, t / np.linalg.norm(t)

    # -- camera 2 moves forward (towards the scene) or backward: here one of the "twisted" candidates
    #    puts every point in front of camera 1 (or of camera 2) and comes first, so a cheirality test on
    #    one camera only picks the wrong pose (in the sideways pairs above it only changes the counts)
    for name, forward in (("fwd", True), ("back", False)):
        Rc, Cc, x1, x2, R, t = _moving_pair(K, forward)
        _store_pose_case(out, f"pose_syn_{name}", Rc, Cc, K, x1, x2, tri)
        out[f"pose_syn_{name}_true_R"], out[f"pose_syn_{name}_true_t"] = R, t / np.linalg.norm(t)

    # -- triangulate_nonlinear: three views, some points unseen in view 2, noisy; X0 from the linear DLT
    sc = make_nl_scene()
    R_cws, t_cws, uv = sc.R_cw, sc.t_cw, sc.uv
    X0 = tri.triangulate_linear(projection_matrix(sc.K, R_cws[0], t_cws[0]), projection_matrix(sc.K, R_cws[1], t_cws[1]),
                                uv[:, 0], uv[:, 1])
    _store_nl_case(out, "nl_syn", sc.K, R_cws, t_cws, uv, X0, tri)
    out["nl_syn_Xtrue"] = sc.X

    # -- the embedded scene: step 2's reference result for the pair
    if (EMBEDDED_SFM / "ground_truth.json").exists():
        st = two_view_input(EMBEDDED_SFM)
        Ke, x1, x2 = st["K"], st["x1"][:MAX_EMBEDDED], st["x2"][:MAX_EMBEDDED]
        ch = tri.choose_pose(st["R_candidates"], st["C_candidates"], Ke, st["x1"], st["x2"])
        P1 = projection_matrix(Ke, np.eye(3), np.zeros(3))
        P2 = projection_matrix(Ke, ch.R_cw, ch.t_cw)
        out.update({"lin_embedded_P1": P1, "lin_embedded_P2": P2, "lin_embedded_x1": x1, "lin_embedded_x2": x2,
                    "lin_embedded_X": tri.triangulate_linear(P1, P2, x1, x2)})
        _store_pose_case(out, "pose_embedded", st["R_candidates"], st["C_candidates"], Ke, x1, x2, tri)
        truth = _relative_truth(EMBEDDED_SFM, EMBEDDED_PAIR)
        if truth is not None:
            out["pose_embedded_gt_R"], out["pose_embedded_gt_t"] = truth
        keep = ch.in_front[:MAX_EMBEDDED]
        R_cws = np.stack([np.eye(3), ch.R_cw])
        t_cws = np.stack([np.zeros(3), ch.t_cw])
        uv = np.stack([x1[keep], x2[keep]], axis=1)
        _store_nl_case(out, "nl_embedded", Ke, R_cws, t_cws, uv, out["lin_embedded_X"][keep], tri)
    return out


def _moving_pair(K, forward: bool, seed: int = 0):
    """Candidates and matches of a pair whose camera 2 moves 1.5 units along the optical axis.

    Returns ``(R (4, 3, 3), C (4, 3), x1, x2, R_true, t_true)``; camera 1 is ``[I | 0]``, the
    60 points lie 5 to 9 units in front of it, 0.3 px noise.
    """
    from scipy.spatial.transform import Rotation

    from course_lib.conventions import skew
    from course_lib.sfm import essential

    rng = np.random.default_rng(seed)
    X = np.column_stack([rng.uniform(-2, 2, 60), rng.uniform(-1.5, 1.5, 60), rng.uniform(5, 9, 60)])
    C2 = np.array([rng.uniform(-0.4, 0.4), rng.uniform(-0.3, 0.3), 1.5 if forward else -1.5])
    R2 = Rotation.from_rotvec(rng.normal(0, 0.05, 3)).as_matrix()
    t2 = -R2 @ C2
    x1 = project(K, np.eye(3), np.zeros(3), X) + rng.normal(0, 0.3, (60, 2))
    x2 = project(K, R2, t2, X) + rng.normal(0, 0.3, (60, 2))
    Rc, Cc = essential.pose_candidates(skew(t2) @ R2)
    return Rc, Cc, x1, x2, R2, t2


def make_nl_scene():
    """The synthetic scene of the non-linear triangulation case: 3 views, 150 points, 1 px noise."""
    from course_lib.data.synthetic import make_scene

    sc = make_scene(np.random.default_rng(31), n_cameras=3, n_points=150, noise_px=1.0, outlier_fraction=0.0, dropout=0.0)
    both = sc.visible[:, 0] & sc.visible[:, 1]  # X0 comes from views 0 and 1
    sc.X, sc.uv, sc.uv_true, sc.outlier = sc.X[both], sc.uv[both], sc.uv_true[both], sc.outlier[both]
    sc.uv[::4, 2] = np.nan  # every 4th point is not seen in view 2
    return sc


def _store_pose_case(out, key, Rc, Cc, K, x1, x2, tri) -> None:
    ch = tri.choose_pose(Rc, Cc, K, x1, x2)
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    Xc = np.stack([tri.triangulate_linear(P1, K @ np.hstack([Rc[k], (-Rc[k] @ Cc[k])[:, None]]), x1, x2) for k in range(4)])
    out.update({f"{key}_R": Rc, f"{key}_C": Cc, f"{key}_K": K, f"{key}_x1": x1, f"{key}_x2": x2,
                f"{key}_R_cw": ch.R_cw, f"{key}_t_cw": ch.t_cw, f"{key}_X": ch.X, f"{key}_in_front": ch.in_front,
                f"{key}_counts": ch.counts, f"{key}_index": np.array(ch.index), f"{key}_Xc": Xc})


def _store_nl_case(out, key, K, R_cws, t_cws, uv, X0, tri) -> None:
    out.update({f"{key}_K": K, f"{key}_R": R_cws, f"{key}_t": t_cws, f"{key}_uv": uv, f"{key}_X0": X0,
                f"{key}_X": tri.triangulate_nonlinear(K, R_cws, t_cws, uv, X0)})
    if R_cws.shape[0] > 2:  # the answer of a function that uses only the first two views
        out[f"{key}_X_2views"] = tri.triangulate_nonlinear(K, R_cws[:2], t_cws[:2], uv[:, :2], X0)


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


def _dlt(P1, P2, x1, x2, rows=(0, 1), smallest: bool = True) -> np.ndarray:
    """The check's own DLT, with switches for the classic mistakes (see :func:`_dlt_variants`)."""
    out = []
    for a, b in zip(np.asarray(x1, float), np.asarray(x2, float)):
        A = np.stack([a[0] * P1[2] - P1[rows[0]], a[1] * P1[2] - P1[rows[1]],
                      b[0] * P2[2] - P2[rows[0]], b[1] * P2[2] - P2[rows[1]]])
        Xh = np.linalg.svd(A)[2][-1 if smallest else 0]
        out.append(Xh[:3] / Xh[3] if Xh[3] != 0 else np.full(3, np.nan))
    return np.array(out).reshape(-1, 3)


def _dlt_variants(P1, P2, x1, x2) -> list[tuple[str, np.ndarray]]:
    """``(mistake, points that mistake gives)`` for the classic mistakes of the linear triangulation."""
    with np.errstate(all="ignore"):
        return [
            ("the cameras are swapped in the rows of A: the rows of x1 use P2 and those of x2 use P1; build "
             "u1 p3ᵀ - p1ᵀ, v1 p3ᵀ - p2ᵀ from P1 and the same two rows with x2 from P2", _dlt(P2, P1, x1, x2)),
            ("u and v are swapped in the rows of A: u goes with the first row of P (u p3ᵀ - p1ᵀ) and v with the "
             "second (v p3ᵀ - p2ᵀ)", _dlt(P1, P2, x1, x2, rows=(1, 0))),
            ("you took the singular vector of the LARGEST singular value: X_h is the last row of Vt (Vt[-1]), "
             "the least-squares null vector of A", _dlt(P1, P2, x1, x2, smallest=False)),
        ]


def _points_verdict(c: Check, X, ref, case: str, tol: float, P1=None, P2=None, x1=None, x2=None,
                    pass_msg: str = "matches the reference") -> bool:
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
    if P1 is not None:
        from course_lib.conventions import from_homogeneous, to_homogeneous

        for why, Y in _dlt_variants(P1, P2, x1, x2):
            if np.median(np.linalg.norm(A - Y, axis=1)) <= max(tol, 1e-6) * scale:
                return c.fail(f"{case}: {why}")
        Xh = to_homogeneous(A)
        e = np.concatenate([np.linalg.norm(from_homogeneous(Xh @ P.T) - x, axis=1) for P, x in ((P1, x1), (P2, x2))])
        hint = f" (median reprojection error {np.median(e):.3g} px)"
    return c.fail(f"{case}: median distance to the reference points {np.median(d):.3g} (scene size {scale:.3g}){hint}: "
                  "check the equations u p3ᵀ - p1ᵀ and v p3ᵀ - p2ᵀ (p_k are the rows of P, u goes with the first row) "
                  "and take the right singular vector of the SMALLEST singular value (Vt[-1])")


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
            if name == "noiseless":
                _points_verdict(c, X, f[f"{k}_Xtrue"], case, tol, P1, P2, x1, x2,
                                pass_msg="recovers the true points exactly")
            else:
                _points_verdict(c, X, f[f"{k}_X"], case, tol, P1, P2, x1, x2)
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


def _cheirality_variants(R, C, Xc) -> list[tuple[str, int]]:
    """(mistake, index the mistake picks) for typical wrong cheirality tests."""
    variants = []
    for hint, test in (
        ("the test checks only camera 2: require z > 0 in camera 1 as well", lambda k, X: (X - C[k]) @ R[k][2] > 0),
        ("the test checks only camera 1: require r3ᵀ (X - C) > 0 for camera 2 as well", lambda k, X: X[:, 2] > 0),
        ("the test forgets the centre: use r3ᵀ (X - C) > 0, not r3ᵀ X > 0", lambda k, X: (X[:, 2] > 0) & (X @ R[k][2] > 0)),
        ("the test uses t where the centre C belongs: r3ᵀ (X - C) with C = -Rᵀ t",
         lambda k, X: (X[:, 2] > 0) & ((X + R[k] @ C[k]) @ R[k][2] > 0)),
        ("the test uses the third column of R: r3ᵀ is the third ROW, R[2]", lambda k, X: (X[:, 2] > 0) & ((X - C[k]) @ R[k][:, 2] > 0)),
        ("the sign of the cheirality test is flipped, it keeps the points behind the cameras: in front means depth > 0",
         lambda k, X: (X[:, 2] < 0) & ((X - C[k]) @ R[k][2] < 0)),
    ):
        with np.errstate(invalid="ignore"):
            counts = np.array([int(test(k, Xc[k]).sum()) for k in range(4)])
        variants.append((hint, int(np.argmax(counts)), counts))
    return variants


def _match_candidate(R_s, t_s, R, C) -> tuple[int | None, str | None]:
    """Index of the candidate the student returned, or a named confusion."""
    for k in range(4):  # exact: the rotation and translation of one candidate
        if np.allclose(R_s, R[k], atol=1e-6) and np.allclose(t_s, -R[k] @ C[k], atol=1e-6):
            return k, None
    for k in range(4):
        if np.allclose(R_s, R[k], atol=1e-6):
            if np.allclose(t_s, C[k], atol=1e-6):
                return k, "t_cw is the camera centre C: the translation is t_cw = -R_cw @ C"
            if np.allclose(t_s, -C[k], atol=1e-6) or np.allclose(t_s, R[k].T @ C[k], atol=1e-6):
                return k, "t_cw is not -R_cw @ C (C vs t confusion): t_cw = -R_cw @ C"
    for k in range(4):
        if np.allclose(R_s, R[k], atol=1e-6):
            return k, "t_cw does not belong to the chosen rotation's candidate: t_cw = -R[k] @ C[k]"
        if np.allclose(R_s, R[k].T, atol=1e-6):
            return k, "R_cw is transposed (that is R_wc, world from camera): return the candidate R[k] itself"
    return None, None


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
    k, confusion = _match_candidate(R_s, t_s, R, C)
    if k is None:
        c.fail(f"{case}: R_cw is none of the four candidates R[k]: return the chosen candidate's rotation unchanged")
        return
    if k != ref_k:
        variants = _cheirality_variants(R, C, f[f"{key}_Xc"])
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
    c.expect(True, f"{case}: picks the candidate with the points in front of both cameras", "",
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
        close = np.abs(counts_s - ref_counts).max() <= tol and (front_s.astype(bool) != ref_front).sum() <= tol
        named = sorted((np.abs(counts_s - counts).max(), hint) for hint, _, counts in _cheirality_variants(R, C, f[f"{key}_Xc"])
                       if np.abs(counts_s - counts).max() <= tol and np.abs(counts - ref_counts).max() > tol)
        named = [hint for _, hint in named]
        why = named[0] if named else ("count, for each candidate, the points with z > 0 in camera 1 AND "
                                      "r3ᵀ (X - C) > 0 in camera 2")
        c.expect(close, f"{case}: in_front and counts agree with the reference",
                 f"{case}: counts {counts_s.astype(int).tolist()}, expected about {ref_counts.tolist()}: {why}",
                 defining="in front of both cameras" if named else None)
    if f"{key}_true_R" in f:
        ok = np.allclose(R_s, f[f"{key}_true_R"], atol=1e-6) and np.allclose(t_s, f[f"{key}_true_t"], atol=1e-6)
        c.expect(ok, f"{case}: equals the true relative pose", f"{case}: differs from the true relative pose")
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


# --------------------------------------------------------------------------- triangulate_nonlinear


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
            if e_s > e0 * (1 + 1e-9) + 1e-9:
                c.fail(f"{case}: the non-linear step increased the reprojection error ({e0:.3g} -> {e_s:.3g} px): "
                       "check the residual: the projection K (R X + t) divided by its depth z (the usual slip is a "
                       "residual without that division), minus the observed pixel; and return the optimum")
                continue
            c.gate(True, f"{case}: lowers the reprojection error", "")
            if f"{key}_X_2views" in f and np.median(np.linalg.norm(A - f[f"{key}_X_2views"], axis=1)) < 1e-4 * _scale(ref):
                c.fail(f"{case}: you used only the first two views: sum the residuals over every view in which "
                       "the point is seen (uv[:, i] not NaN)")
                continue
            c.expect(e_s <= e_ref * (1 + 1e-3) + 1e-6, f"{case}: reaches the least-squares optimum",
                     f"{case}: RMS reprojection error {e_s:.4g} px, the optimum is {e_ref:.4g} px: run the solver to "
                     "convergence and use every view that sees the point")

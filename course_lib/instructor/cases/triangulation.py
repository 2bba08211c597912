"""Cases of notebook 03 (triangulation, cheirality, non-linear triangulation), and notebook 03's step input.

Built from :mod:`course_lib.sfm.triangulation` (fixtures ``triangulation`` and
``triangulation_step``); the checks are in :mod:`course_lib.checks.triangulation`.
"""

from __future__ import annotations

import zlib

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from course_lib.checks.triangulation import FIXTURE
from course_lib.conventions import project, projection_matrix, skew
from course_lib.data.synthetic import WPI_LIKE_K, look_at, make_scene
from course_lib.instructor.cases import builds, store
from course_lib.instructor.cases.fundamental import random_subset
from course_lib.paths import EMBEDDED_SFM
from course_lib.sfm import essential
from course_lib.sfm import triangulation as tri
from course_lib.sfm.fundamental import eight_point
from course_lib.starting_points import STEP_PAIR, relative_truth, two_view_input

#: The most matches stored per embedded case (keeps the fixture small).
MAX_EMBEDDED = 300

@builds("triangulation_step", step=True)
def _build_step() -> dict[str, np.ndarray]:
    out = two_view_input(EMBEDDED_SFM)
    truth = relative_truth(EMBEDDED_SFM, STEP_PAIR)
    if truth is not None:
        out["true_R_cw"], out["true_t_cw"] = truth
    return out


def _synthetic_two_view(seed: int, n_points: int, noise_px: float):
    sc = make_scene(np.random.default_rng(seed), n_cameras=3, n_points=n_points, noise_px=noise_px,
                    outlier_fraction=0.0, dropout=0.0)
    return sc


def _relative(sc, i, j):
    R = sc.R_cw[j] @ sc.R_cw[i].T
    t = sc.t_cw[j] - R @ sc.t_cw[i]
    return R, t


@builds(FIXTURE)
def _build() -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    K = None

    # -- triangulate_linear: noiseless and noisy synthetic pairs with general poses (camera 1 is not I)
    for name, seed, n, noise in (("noiseless", 11, 40, 0.0), ("noisy", 12, 120, 1.0)):
        sc = _synthetic_two_view(seed, n, noise)
        K = sc.K
        P1, P2 = projection_matrix(sc.K, sc.R_cw[0], sc.t_cw[0]), projection_matrix(sc.K, sc.R_cw[1], sc.t_cw[1])
        x1, x2, _, ids = sc.pair(0, 1)
        store(out, f"lin_{name}", P1=P1, P2=P2, x1=x1, x2=x2, X=tri.triangulate_linear(P1, P2, x1, x2), Xtrue=sc.X[ids])
        _store_linear_mistakes(out, f"lin_{name}")
    # a vertical baseline (camera 2 above camera 1, neither at the origin): the depth comes from v, so a system
    # that drops a v row, or mixes up u and v, is far off here even when a horizontal baseline hides it
    g = np.random.default_rng(13)
    target = g.normal(0.0, 1.0, 3) + np.array([0.0, 0.0, 10.0])
    Xv = target + g.uniform([-3.0, -2.0, -1.5], [3.0, 2.0, 1.5], size=(80, 3))
    C1 = target + np.array([g.uniform(-1, 1), 0.0, -9.0])
    C2 = C1 + np.array([g.uniform(-0.1, 0.1), -1.5, g.uniform(-0.2, 0.2)])  # y down: camera 2 is above
    (R1, t1), (R2, t2) = look_at(C1, target), look_at(C2, target)
    P1, P2 = projection_matrix(WPI_LIKE_K, R1, t1), projection_matrix(WPI_LIKE_K, R2, t2)
    x1 = project(WPI_LIKE_K, R1, t1, Xv) + g.normal(0.0, 1.0, (80, 2))
    x2 = project(WPI_LIKE_K, R2, t2, Xv) + g.normal(0.0, 1.0, (80, 2))
    store(out, "lin_vertical", P1=P1, P2=P2, x1=x1, x2=x2, X=tri.triangulate_linear(P1, P2, x1, x2))
    _store_linear_mistakes(out, "lin_vertical")

    # -- choose_pose: candidates from the true E; two scenes whose correct candidate has another index
    for name, seed in (("syn_a", 21), ("syn_b", 24)):
        sc = _synthetic_two_view(seed, 80, 0.5)
        R, t = _relative(sc, 0, 1)
        x1, x2, _, _ = sc.pair(0, 1)
        x1, x2 = _with_behind(x1, x2, sc.K, R, t, seed + 100)
        Rc, Cc = essential.pose_candidates(skew(t) @ R)
        _store_pose_case(out, f"pose_{name}", Rc, Cc, sc.K, x1, x2, tri)
        out[f"pose_{name}_true_R"], out[f"pose_{name}_true_t"] = R, t / np.linalg.norm(t)

    # -- a wide-baseline pair (135 degrees around a small object, close by): here forgetting "- C" or
    #    using the third column of R changes the answer, unlike in the narrow pairs above
    rng = np.random.default_rng(27)
    Xw = rng.uniform(-1.0, 1.0, size=(60, 3))
    a1, a2 = rng.uniform(-0.05, 0.05), rng.uniform(2.3, 2.4)  # camera 2 about 135 degrees around the object
    R1, t1 = look_at(4.0 * np.array([np.sin(a1), 0.0, -np.cos(a1)]), np.zeros(3))
    R2, t2 = look_at(4.0 * np.array([np.sin(a1 + a2), rng.uniform(-0.15, -0.1), -np.cos(a1 + a2)]), np.zeros(3))
    x1 = project(K, R1, t1, Xw) + rng.normal(0.0, 0.3, (60, 2))
    x2 = project(K, R2, t2, Xw) + rng.normal(0.0, 0.3, (60, 2))
    R = R2 @ R1.T
    t = t2 - R @ t1
    x1, x2 = _with_behind(x1, x2, K, R, t, 127)
    Rc, Cc = essential.pose_candidates(skew(t) @ R)
    _store_pose_case(out, "pose_syn_wide", Rc, Cc, K, x1, x2, tri)
    out["pose_syn_wide_true_R"], out["pose_syn_wide_true_t"] = R, t / np.linalg.norm(t)

    # -- camera 2 moves forward (towards the scene) or backward: here one of the "twisted" candidates
    #    puts every point in front of camera 1 (or of camera 2) and comes first, so a cheirality test on
    #    one camera only picks the wrong pose (in the sideways pairs above it only changes the counts)
    for name, forward, seed in (("fwd", True, 28), ("back", False, 29)):
        Rc, Cc, x1, x2, R, t = _moving_pair(K, forward, seed)
        x1, x2 = _with_behind(x1, x2, K, R, t, seed + 100)
        _store_pose_case(out, f"pose_syn_{name}", Rc, Cc, K, x1, x2, tri)
        out[f"pose_syn_{name}_true_R"], out[f"pose_syn_{name}_true_t"] = R, t / np.linalg.norm(t)

    # -- triangulate_nonlinear: three views, some points unseen in view 2, noisy; X0 from the linear DLT
    sc = make_nl_scene()
    R_cws, t_cws, uv = sc.R_cw, sc.t_cw, sc.uv
    X0 = tri.triangulate_linear(projection_matrix(sc.K, R_cws[0], t_cws[0]), projection_matrix(sc.K, R_cws[1], t_cws[1]),
                                uv[:, 0], uv[:, 1])
    _store_nl_case(out, "nl_syn", sc.K, R_cws, t_cws, uv, X0, tri)

    # -- the embedded scene: step 2's reference result for the pair, a random subset of its matches, and
    #    (for the linear and the non-linear case) a random frame of the world, so that camera 1 is not [I | 0]
    if (EMBEDDED_SFM / "ground_truth.json").exists():
        _embedded_cases(out, tri)
    return out


def _embedded_cases(out: dict, tri) -> None:
    st = two_view_input(EMBEDDED_SFM)
    keep = random_subset(len(st["x1"]), 33)[:MAX_EMBEDDED]
    Ke, x1, x2 = st["K"], st["x1"][keep], st["x2"][keep]
    Rc, Cc = essential.pose_candidates(essential.essential_from_fundamental(eight_point(x1, x2), Ke))
    _store_pose_case(out, "pose_embedded", Rc, Cc, Ke, x1, x2, tri)
    ch = tri.choose_pose(Rc, Cc, Ke, x1, x2)
    g = np.random.default_rng(34)  # world = a random rigid motion of camera 1's frame
    R0, t0 = Rotation.from_rotvec(g.normal(0.0, 0.5, 3)).as_matrix(), g.normal(0.0, 1.0, 3)
    R_cws = np.stack([R0, ch.R_cw @ R0])
    t_cws = np.stack([t0, ch.R_cw @ t0 + ch.t_cw])
    P1, P2 = projection_matrix(Ke, R_cws[0], t_cws[0]), projection_matrix(Ke, R_cws[1], t_cws[1])
    X = tri.triangulate_linear(P1, P2, x1, x2)
    store(out, "lin_embedded", P1=P1, P2=P2, x1=x1, x2=x2, X=X)
    _store_linear_mistakes(out, "lin_embedded")
    front = ch.in_front
    _store_nl_case(out, "nl_embedded", Ke, R_cws, t_cws, np.stack([x1[front], x2[front]], axis=1), X[front], tri)


def _with_behind(x1: np.ndarray, x2: np.ndarray, K, R, t, seed: int, n: int = 2):
    """The matches with ``n`` more, of points behind camera 1 (which is [I | 0]), at random rows.

    Their triangulated points are never in front of both cameras, so ``in_front`` is False at rows
    that differ from one build to the next.
    """
    g = np.random.default_rng(seed)
    Xb = np.column_stack([g.uniform(-1.0, 1.0, n), g.uniform(-1.0, 1.0, n), g.uniform(-6.0, -3.0, n)])
    b1, b2 = project(K, np.eye(3), np.zeros(3), Xb), project(K, R, t, Xb)
    rows = np.sort(g.choice(len(x1) + n, n, replace=False))
    y1, y2 = list(x1), list(x2)
    for r, p, q in zip(rows, b1, b2):
        y1.insert(r, p)
        y2.insert(r, q)
    return np.array(y1), np.array(y2)


def _store_linear_mistakes(out: dict, key: str) -> None:
    store(out, f"{key}_mis", **linear_variants(out[f"{key}_P1"], out[f"{key}_P2"], out[f"{key}_x1"], out[f"{key}_x2"]))


def _moving_pair(K, forward: bool, seed: int):
    """Candidates and matches of a pair whose camera 2 moves 1.5 units along the optical axis.

    Returns ``(R (4, 3, 3), C (4, 3), x1, x2, R_true, t_true)``; camera 1 is ``[I | 0]``, the
    50 to 70 points lie 5 to 9 units in front of it, 0.3 px noise.
    """
    rng = np.random.default_rng(seed)
    n = int(rng.integers(50, 71))
    X = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(5, 9, n)])
    C2 = np.array([rng.uniform(-0.4, 0.4), rng.uniform(-0.3, 0.3), 1.5 if forward else -1.5])
    R2 = Rotation.from_rotvec(rng.normal(0, 0.05, 3)).as_matrix()
    t2 = -R2 @ C2
    x1 = project(K, np.eye(3), np.zeros(3), X) + rng.normal(0, 0.3, (n, 2))
    x2 = project(K, R2, t2, X) + rng.normal(0, 0.3, (n, 2))
    Rc, Cc = essential.pose_candidates(skew(t2) @ R2)
    return Rc, Cc, x1, x2, R2, t2


def make_nl_scene():
    """The synthetic scene of the non-linear triangulation case: 3 views, 150 points, 1 px noise."""
    sc = make_scene(np.random.default_rng(31), n_cameras=3, n_points=150, noise_px=1.0, outlier_fraction=0.0, dropout=0.0)
    both = sc.visible[:, 0] & sc.visible[:, 1]  # X0 comes from views 0 and 1
    sc.X, sc.uv, sc.uv_true, sc.outlier = sc.X[both], sc.uv[both], sc.uv_true[both], sc.outlier[both]
    sc.uv[::4, 2] = np.nan  # every 4th point is not seen in view 2
    return sc


def _store_pose_case(out, key, Rc, Cc, K, x1, x2, tri) -> None:
    """Store a choose_pose case; the right candidate is moved to index 1, 2 or 3 (by the case's name).

    The reference orders the candidates the same way on every machine, and the right one is often
    first; choose_pose must pick it by cheirality, never by position, so the cases put it elsewhere.
    """
    right, target = tri.choose_pose(Rc, Cc, K, x1, x2).index, 1 + zlib.crc32(key.encode()) % 3
    order = np.arange(4)
    order[[right, target]] = order[[target, right]]
    Rc, Cc = Rc[order], Cc[order]
    ch = tri.choose_pose(Rc, Cc, K, x1, x2)
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])  # the points of every candidate: an X of another one is named
    out[f"{key}_X_all"] = np.stack([tri.triangulate_linear(P1, K @ np.hstack([Rc[k], (-Rc[k] @ Cc[k])[:, None]]), x1, x2)
                                    for k in range(4)])
    store(out, key, R=Rc, C=Cc, K=K, x1=x1, x2=x2, X=ch.X, in_front=ch.in_front, counts=ch.counts,
          index=np.array(ch.index), mis_counts=cheirality_counts(Rc, Cc, K, x1, x2))


def _store_nl_case(out, key, K, R_cws, t_cws, uv, X0, tri) -> None:
    store(out, key, K=K, R=R_cws, t=t_cws, uv=uv, X0=X0, X=tri.triangulate_nonlinear(K, R_cws, t_cws, uv, X0))
    store(out, f"{key}_mis", **nonlinear_variants(K, R_cws, t_cws, uv, X0))
    if R_cws.shape[0] > 2:  # the answer of a function that uses only the first two views
        out[f"{key}_X_2views"] = tri.triangulate_nonlinear(K, R_cws[:2], t_cws[:2], uv[:, :2], X0)


# --------------------------------------------------------------------------- what the classic mistakes give
# (stored with the cases, keyed as the check module's sentences are: the shipped checks hold no implementation)


def _dlt(P1, P2, x1, x2, rows=(0, 1), smallest: bool = True) -> np.ndarray:
    out = []
    for a, b in zip(np.asarray(x1, float), np.asarray(x2, float)):
        A = np.stack([a[0] * P1[2] - P1[rows[0]], a[1] * P1[2] - P1[rows[1]],
                      b[0] * P2[2] - P2[rows[0]], b[1] * P2[2] - P2[rows[1]]])
        Xh = np.linalg.svd(A)[2][-1 if smallest else 0]
        out.append(Xh[:3] / Xh[3] if Xh[3] != 0 else np.full(3, np.nan))
    return np.array(out).reshape(-1, 3)


def linear_variants(P1, P2, x1, x2) -> dict[str, np.ndarray]:
    """Points (N, 3) of the classic DLT mistakes."""
    with np.errstate(all="ignore"):
        return {"swapped": _dlt(P2, P1, x1, x2), "uv_swapped": _dlt(P1, P2, x1, x2, rows=(1, 0)),
                "largest": _dlt(P1, P2, x1, x2, smallest=False)}


#: The wrong cheirality tests, in the order of the rows of :func:`cheirality_counts`.
CHEIRALITY_KEYS = ("camera2_only", "camera1_only", "no_centre", "t_for_C", "column_of_R", "sign_flipped")


def cheirality_counts(R, C, K, x1, x2) -> np.ndarray:
    """(len(CHEIRALITY_KEYS), 4) int: per wrong test, the points each candidate keeps."""
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    Xc = [tri.triangulate_linear(P1, K @ np.hstack([R[k], (-R[k] @ C[k])[:, None]]), x1, x2) for k in range(4)]
    tests = {
        "camera2_only": lambda k, X: (X - C[k]) @ R[k][2] > 0,
        "camera1_only": lambda k, X: X[:, 2] > 0,
        "no_centre": lambda k, X: (X[:, 2] > 0) & (X @ R[k][2] > 0),
        "t_for_C": lambda k, X: (X[:, 2] > 0) & ((X + R[k] @ C[k]) @ R[k][2] > 0),
        "column_of_R": lambda k, X: (X[:, 2] > 0) & ((X - C[k]) @ R[k][:, 2] > 0),
        "sign_flipped": lambda k, X: (X[:, 2] < 0) & ((X - C[k]) @ R[k][2] < 0),
    }
    with np.errstate(invalid="ignore"):
        return np.array([[int(tests[key](k, Xc[k]).sum()) for k in range(4)] for key in CHEIRALITY_KEYS])


def _refine(K, R_cws, t_cws, uv, X0, residual, dims: int = 3) -> np.ndarray:
    out = X0.copy()
    for j in range(len(X0)):
        seen = [i for i in range(len(R_cws)) if np.isfinite(uv[j, i]).all()]
        if len(seen) < 2:
            continue
        start = X0[j] if dims == 3 else np.append(X0[j], 1.0)
        x = least_squares(lambda p: np.concatenate([residual(p, i, uv[j, i]) for i in seen]), start).x
        out[j] = x[:3]
    return out


def nonlinear_variants(K, R_cws, t_cws, uv, X0) -> dict[str, np.ndarray]:
    """Points (N, 3) of the classic mistakes of the non-linear triangulation."""
    def proj(X, R, t):
        return K @ (R @ X + t)

    def right(X, i, x):
        p = proj(X, R_cws[i], t_cws[i])
        return p[:2] / p[2] - x

    uv0 = np.where(np.isfinite(uv), uv, 0.0)
    return {
        "no_depth_division": _refine(K, R_cws, t_cws, uv, X0, lambda X, i, x: proj(X, R_cws[i], t_cws[i])[:2] - x),
        "cross_multiplied": _refine(K, R_cws, t_cws, uv, X0,
                                    lambda X, i, x: proj(X, R_cws[i], t_cws[i])[:2] - x * proj(X, R_cws[i], t_cws[i])[2]),
        "nan_as_zero": np.array([least_squares(lambda X, j=j: np.concatenate([right(X, i, uv0[j, i])
                                                                               for i in range(len(R_cws))]), X0[j]).x
                                 for j in range(len(X0))]),
        "unseen_not_refined": np.where(np.isfinite(uv).all(axis=(1, 2))[:, None],
                                       tri.triangulate_nonlinear(K, R_cws, t_cws, uv, X0), X0),
    }

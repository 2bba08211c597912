"""Notebook 03 (triangulation): classic mistakes, honest solutions and trivial answers, run through its checks."""

from __future__ import annotations

import numpy as np

from course_lib.checks import triangulation as gtr
from course_lib.sfm import triangulation as rtr
from tests.checks.catalogue import Honest, Mistake

# ============================================================================ buggy versions
# Each is written as a student would write it (often the reference with one line changed).

# -- 03: triangulate_linear -----------------------------------------------------------------------
def _dlt(P1, P2, x1, x2, swap=False, divide=True, largest=False):
    out = []
    for a, b in zip(x1, x2):
        Pa, Pb = (P2, P1) if swap else (P1, P2)
        A = np.stack([a[0] * Pa[2] - Pa[0], a[1] * Pa[2] - Pa[1], b[0] * Pb[2] - Pb[0], b[1] * Pb[2] - Pb[1]])
        Xh = np.linalg.svd(A)[2][0 if largest else -1]
        out.append(Xh[:3] / Xh[3] if divide else Xh)
    return np.array(out)


def triangulate_swapped_cameras(P1, P2, x1, x2):
    return _dlt(P1, P2, x1, x2, swap=True)


def triangulate_homogeneous(P1, P2, x1, x2):
    return _dlt(P1, P2, x1, x2, divide=False)


def triangulate_largest_vector(P1, P2, x1, x2):
    return _dlt(P1, P2, x1, x2, largest=True)


def triangulate_squeezed(P1, P2, x1, x2):
    return np.squeeze(rtr.triangulate_linear(P1, P2, x1, x2))


# -- 03: choose_pose --------------------------------------------------------------------------------
def _choose(R, C, K, x1, x2, test):
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    Xs, fronts = [], []
    for k in range(4):
        t = -R[k] @ C[k]
        X = rtr.triangulate_linear(P1, K @ np.hstack([R[k], t[:, None]]), x1, x2)
        Xs.append(X)
        fronts.append(test(R[k], C[k], X))
    counts = np.array([f.sum() for f in fronts])
    k = int(np.argmax(counts))
    return rtr.PoseChoice(R[k], -R[k] @ C[k], Xs[k], fronts[k], counts, k)


def choose_pose_camera1_only(R, C, K, x1, x2):
    return _choose(R, C, K, x1, x2, lambda Rk, Ck, X: X[:, 2] > 0)


def choose_pose_camera2_only(R, C, K, x1, x2):
    return _choose(R, C, K, x1, x2, lambda Rk, Ck, X: (X - Ck) @ Rk[2] > 0)


def choose_pose_no_centre(R, C, K, x1, x2):
    return _choose(R, C, K, x1, x2, lambda Rk, Ck, X: (X[:, 2] > 0) & (X @ Rk[2] > 0))


# -- 03: triangulate_nonlinear -------------------------------------------------------------------------
def triangulate_nonlinear_unchanged(K, R_cws, t_cws, uv, X0):
    return np.array(X0, copy=True)


def triangulate_nonlinear_two_views(K, R_cws, t_cws, uv, X0):
    return rtr.triangulate_nonlinear(K, R_cws[:2], t_cws[:2], uv[:, :2], X0)


def triangulate_nonlinear_no_depth_division(K, R_cws, t_cws, uv, X0):
    from scipy.optimize import least_squares

    out = []
    for j in range(len(X0)):
        seen = [i for i in range(len(R_cws)) if np.isfinite(uv[j, i]).all()]

        def res(X):  # the projection is not divided by its depth
            return np.concatenate([(K @ (R_cws[i] @ X + t_cws[i]))[:2] - uv[j, i] for i in seen])

        out.append(least_squares(res, X0[j]).x)
    return np.array(out)

def triangulate_uv_swapped(P1, P2, x1, x2):
    out = []
    for a, b in zip(x1, x2):
        A = np.stack([a[0] * P1[2] - P1[1], a[1] * P1[2] - P1[0], b[0] * P2[2] - P2[1], b[1] * P2[2] - P2[0]])
        Xh = np.linalg.svd(A)[2][-1]
        out.append(Xh[:3] / Xh[3])
    return np.array(out)


def triangulate_swapped_cross_product(P1, P2, x1, x2):  # the swap in another formulation: x × P X = 0, 6 rows
    out = []
    for a, b in zip(x1, x2):
        rows = []
        for x, P in ((a, P2), (b, P1)):
            u, v = x
            rows += [v * P[2] - P[1], P[0] - u * P[2], u * P[1] - v * P[0]]
        Xh = np.linalg.svd(np.array(rows))[2][-1]
        out.append(Xh[:3] / Xh[3])
    return np.array(out)


def choose_pose_R_transposed(R, C, K, x1, x2):
    ch = rtr.choose_pose(R, C, K, x1, x2)
    return ch.R_cw.T, ch.t_cw, ch.X, ch.in_front, ch.counts


def choose_pose_C_for_t(R, C, K, x1, x2):
    ch = rtr.choose_pose(R, C, K, x1, x2)
    return ch.R_cw, C[ch.index], ch.X, ch.in_front, ch.counts


def choose_pose_sign_flipped(R, C, K, x1, x2):
    return _choose(R, C, K, x1, x2, lambda Rk, Ck, X: (X[:, 2] < 0) & ((X - Ck) @ Rk[2] < 0))


def _nl(K, R_cws, t_cws, uv, X0, residual, nan_zero=False, skip_partial=False):
    from scipy.optimize import least_squares

    out = np.array(X0, dtype=float, copy=True)
    for j in range(len(X0)):
        seen = [i for i in range(len(R_cws)) if nan_zero or np.isfinite(uv[j, i]).all()]
        if len(seen) < 2 or (skip_partial and len(seen) < len(R_cws)):
            continue
        obs = np.where(np.isfinite(uv[j]), uv[j], 0.0)
        out[j] = least_squares(lambda X: np.concatenate([residual(X, R_cws[i], t_cws[i], obs[i], K) for i in seen]),
                               X0[j]).x
    return out


def _px(X, R, t, x, K):
    p = K @ (R @ X + t)
    return p[:2] / p[2] - x


def triangulate_nonlinear_R_transposed(K, R_cws, t_cws, uv, X0):
    return _nl(K, R_cws, t_cws, uv, X0, lambda X, R, t, x, K: _px(X, R.T, t, x, K))


def triangulate_nonlinear_nan_as_zero(K, R_cws, t_cws, uv, X0):
    return _nl(K, R_cws, t_cws, uv, X0, _px, nan_zero=True)


def triangulate_nonlinear_cross_multiplied(K, R_cws, t_cws, uv, X0):
    def res(X, R, t, x, K):
        p = K @ (R @ X + t)
        return p[:2] - x * p[2]

    return _nl(K, R_cws, t_cws, uv, X0, res)


def triangulate_nonlinear_skips_partly_seen(K, R_cws, t_cws, uv, X0):
    return _nl(K, R_cws, t_cws, uv, X0, _px, skip_partial=True)


def triangulate_nonlinear_homogeneous(K, R_cws, t_cws, uv, X0):  # optimizes (X, w) and forgets to divide by w
    from scipy.optimize import least_squares

    out = np.array(X0, dtype=float, copy=True)
    for j in range(len(X0)):
        seen = [i for i in range(len(R_cws)) if np.isfinite(uv[j, i]).all()]

        def res(Xh):
            return np.concatenate([(lambda p: p[:2] / p[2] - uv[j, i])(K @ (R_cws[i] @ Xh[:3] + t_cws[i] * Xh[3]))
                                   for i in seen] + [[0.1 * (Xh[3] - 1.3)]])

        out[j] = least_squares(res, np.append(X0[j], 1.0)).x[:3]
    return out


# ============================================================================ honest solutions
# Written from the textbook (Hartley & Zisserman 12.2, 9.6.3), not from course_lib.

def triangulate_linear(P1, P2, x1, x2):
    X = np.empty((len(x1), 3))
    for k in range(len(x1)):
        (u1, v1), (u2, v2) = x1[k], x2[k]
        A = np.array([u1 * P1[2] - P1[0], v1 * P1[2] - P1[1], u2 * P2[2] - P2[0], v2 * P2[2] - P2[1]])
        Xh = np.linalg.svd(A)[2][-1]
        X[k] = Xh[:3] / Xh[3]
    return X


def triangulate_linear__cross_product_batched(P1, P2, x1, x2):
    """Another style: the rows of x × P X = 0 (all three per view), all points at once, normalized rows."""
    def rows(P, x):
        u, v = x[:, :1], x[:, 1:]
        return np.stack([v * P[2] - P[1], P[0] - u * P[2], u * P[1] - v * P[0]], axis=1)

    A = np.concatenate([rows(P1, x1), rows(P2, x2)], axis=1)
    A = A / np.linalg.norm(A, axis=2, keepdims=True)
    Xh = np.linalg.svd(A)[2][:, -1]
    return Xh[:, :3] / Xh[:, 3:]


def choose_pose(R, C, K, x1, x2):
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    best = None
    counts = np.zeros(4, int)
    for k in range(4):
        t = -R[k] @ C[k]
        X = triangulate_linear(P1, K @ np.hstack([R[k], t[:, None]]), x1, x2)
        front = (X[:, 2] > 0) & ((X - C[k]) @ R[k][2] > 0)
        counts[k] = front.sum()
        if best is None or counts[k] > counts[best[0]]:
            best = (k, t, X, front)
    k, t, X, front = best
    return R[k], t, X, front, counts


def choose_pose__camera_frame(R, C, K, x1, x2):
    """Another style: the depth in camera 2 as the z of R X + t, a dict of results, argmax at the end."""
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    results = {}
    for k in range(4):
        t = -R[k] @ C[k]
        X = triangulate_linear(P1, K @ np.column_stack([R[k], t]), x1, x2)
        z2 = (X @ R[k].T + t)[:, 2]
        results[k] = (t, X, (X[:, 2] > 0) & (z2 > 0))
    counts = np.array([int(results[k][2].sum()) for k in range(4)])
    k = int(np.argmax(counts))
    return R[k], results[k][0], results[k][1], results[k][2], counts


def triangulate_nonlinear(K, R_cws, t_cws, uv, X0):
    from scipy.optimize import least_squares

    X = np.array(X0, dtype=float, copy=True)
    for j in range(len(X0)):
        views = [i for i in range(len(R_cws)) if not np.isnan(uv[j, i]).any()]
        if len(views) < 2:
            continue

        def residual(p):
            r = []
            for i in views:
                q = K @ (R_cws[i] @ p + t_cws[i])
                r.extend(q[:2] / q[2] - uv[j, i])
            return np.array(r)

        X[j] = least_squares(residual, X0[j], xtol=1e-12, ftol=1e-12).x
    return X


def triangulate_nonlinear__gauss_newton(K, R_cws, t_cws, uv, X0):
    """Another style: a hand-written Gauss-Newton with the analytic Jacobian of the projection, all points at once."""
    X = np.array(X0, dtype=float, copy=True)
    seen = np.isfinite(uv).all(axis=2)
    for _ in range(30):
        H = np.zeros((len(X), 3, 3))
        g = np.zeros((len(X), 3))
        for i in range(len(R_cws)):
            m = seen[:, i]
            Xc = X[m] @ R_cws[i].T + t_cws[i]
            p = Xc @ K.T
            r = p[:, :2] / p[:, 2:] - uv[m, i]
            J = (K[:2, None, :] / p[:, 2][None, :, None] - (p[:, :2].T / p[:, 2] ** 2)[:, :, None] * K[2][None, None, :])
            J = np.transpose(J, (1, 0, 2)) @ R_cws[i]
            H[m] += np.transpose(J, (0, 2, 1)) @ J
            g[m] += np.einsum("nij,ni->nj", J, r)
        ok = seen.sum(axis=1) >= 2
        X[ok] -= np.linalg.solve(H[ok], g[ok][:, :, None])[:, :, 0]
    return X


# ============================================================================ the catalogue

M = Mistake
MISTAKES = [
    M("triangulate_linear", "P1 and P2 swapped in A", gtr.check_triangulate_linear, triangulate_swapped_cameras,
      ("swapped the cameras",)),
    M("triangulate_linear", "no division by X_h[3]", gtr.check_triangulate_linear, triangulate_homogeneous,
      ("divide by the last coordinate",)),
    M("triangulate_linear", "largest singular vector", gtr.check_triangulate_linear, triangulate_largest_vector,
      ("largest singular value",)),
    M("triangulate_linear", "N = 1 squeezed", gtr.check_triangulate_linear, triangulate_squeezed,
      ("keep the points axis",)),
    M("choose_pose", "cheirality on camera 1 only", gtr.check_choose_pose, choose_pose_camera1_only,
      ("checks only camera 1",), defining="in front of both cameras"),
    M("choose_pose", "cheirality on camera 2 only", gtr.check_choose_pose, choose_pose_camera2_only,
      ("checks only camera 2",), defining="in front of both cameras"),
    M("choose_pose", "cheirality forgets the centre", gtr.check_choose_pose, choose_pose_no_centre,
      ("forgets the centre",), defining="in front of both cameras"),
    M("triangulate_nonlinear", "returns X0", gtr.check_triangulate_nonlinear, triangulate_nonlinear_unchanged,
      ("did not move",)),
    M("triangulate_nonlinear", "only two views", gtr.check_triangulate_nonlinear, triangulate_nonlinear_two_views,
      ("only the first two views",)),
    M("triangulate_nonlinear", "projection not divided by z", gtr.check_triangulate_nonlinear,
      triangulate_nonlinear_no_depth_division, ("without dividing by its depth",)),
    M("triangulate_nonlinear", "R transposed", gtr.check_triangulate_nonlinear, triangulate_nonlinear_R_transposed,
      ("r transposed",)),
    M("triangulate_nonlinear", "NaN set to 0", gtr.check_triangulate_nonlinear, triangulate_nonlinear_nan_as_zero,
      ("pixels (0, 0)",)),
    M("triangulate_nonlinear", "cross-multiplied residual", gtr.check_triangulate_nonlinear,
      triangulate_nonlinear_cross_multiplied, ("cross-multiplied",)),
    M("triangulate_nonlinear", "partly seen points not refined", gtr.check_triangulate_nonlinear,
      triangulate_nonlinear_skips_partly_seen, ("did not refine",)),
    M("triangulate_nonlinear", "homogeneous point not divided", gtr.check_triangulate_nonlinear,
      triangulate_nonlinear_homogeneous, ("homogeneous point",)),
    M("triangulate_linear", "u and v swapped", gtr.check_triangulate_linear, triangulate_uv_swapped,
      ("swapped u and v",)),
    M("triangulate_linear", "cameras swapped, cross-product rows", gtr.check_triangulate_linear,
      triangulate_swapped_cross_product, ("reprojection error",)),
    M("choose_pose", "R_cw transposed", gtr.check_choose_pose, choose_pose_R_transposed, ("r_cw is transposed",)),
    M("choose_pose", "C returned as t_cw", gtr.check_choose_pose, choose_pose_C_for_t, ("t_cw is the camera centre",)),
    M("choose_pose", "cheirality sign flipped", gtr.check_choose_pose, choose_pose_sign_flipped,
      ("the sign is flipped",), defining="in front of both cameras"),
]

#: Correct solutions: they must score full marks.
HONEST = [
    Honest("triangulate_linear", "textbook, a loop", gtr.check_triangulate_linear, triangulate_linear),
    Honest("triangulate_linear", "cross-product rows, batched", gtr.check_triangulate_linear,
           triangulate_linear__cross_product_batched),
    Honest("choose_pose", "textbook, a tuple", gtr.check_choose_pose, choose_pose),
    Honest("choose_pose", "depth in the camera frame", gtr.check_choose_pose, choose_pose__camera_frame),
    Honest("triangulate_nonlinear", "least_squares per point", gtr.check_triangulate_nonlinear, triangulate_nonlinear),
    Honest("triangulate_nonlinear", "Gauss-Newton, all points at once", gtr.check_triangulate_nonlinear,
           triangulate_nonlinear__gauss_newton),
    Honest("triangulate_linear", "the reference solution", gtr.check_triangulate_linear, rtr.triangulate_linear),
    Honest("choose_pose", "the reference solution", gtr.check_choose_pose, rtr.choose_pose),
    Honest("triangulate_nonlinear", "the reference solution", gtr.check_triangulate_nonlinear, rtr.triangulate_nonlinear),
]


def _trivial() -> list:
    z = np.zeros  # noqa: F841
    return [
        (gtr.check_triangulate_linear, lambda P1, P2, x1, x2: z((len(x1), 3))),
        (gtr.check_choose_pose, lambda R, C, K, x1, x2: (R[0], -R[0] @ C[0], z((len(x1), 3)), np.ones(len(x1), bool),
                                                         np.array([len(x1), 0, 0, 0]))),
        (gtr.check_triangulate_nonlinear, lambda K, R, t, uv, X0: X0 * 1.0001),
    ]


#: Constants of the right shape: they pass the shape gates and trivially satisfied properties, and must earn nothing.
TRIVIAL = _trivial()


# ============================================================================ issue 29: written as students write them
# From the notebook's text and the stub's docstring, with an error students make; then valid variants.

def triangulate_three_rows(P1, P2, x1, x2):  # the last row of camera 2 forgotten: 3 equations for 4 unknowns
    X = []
    for (u1, v1), (u2, v2) in zip(x1, x2):
        A = np.array([u1 * P1[2] - P1[0], v1 * P1[2] - P1[1], u2 * P2[2] - P2[0]])
        Xh = np.linalg.svd(A)[2][-1]
        X.append(Xh[:3] / Xh[3])
    return np.array(X)


def triangulate_divides_by_abs(P1, P2, x1, x2):  # "divide by the last coordinate" done with its absolute value
    X = []
    for (u1, v1), (u2, v2) in zip(x1, x2):
        A = np.array([u1 * P1[2] - P1[0], v1 * P1[2] - P1[1], u2 * P2[2] - P2[0], v2 * P2[2] - P2[1]])
        Xh = np.linalg.svd(A)[2][-1]
        X.append(Xh[:3] / abs(Xh[3]))
    return np.array(X)


def triangulate_normalized_pixels(P1, P2, x1, x2):  # pixels taken through K⁻¹ although P already holds K
    K = np.array([[700.0, 0, 320], [0, 700.0, 240], [0, 0, 1]])  # K read off the notebook's printout
    Ki = np.linalg.inv(K)
    y1 = (np.column_stack([x1, np.ones(len(x1))]) @ Ki.T)[:, :2]
    y2 = (np.column_stack([x2, np.ones(len(x2))]) @ Ki.T)[:, :2]
    return rtr.triangulate_linear(P1, P2, y1, y2)


def triangulate_columns_of_P(P1, P2, x1, x2):  # P[:, k] (columns) where the rows p_kᵀ belong
    X = []
    for (u1, v1), (u2, v2) in zip(x1, x2):
        A = np.array([u1 * P1[:, 2] - P1[:, 0], v1 * P1[:, 2] - P1[:, 1], u2 * P2[:, 2] - P2[:, 0],
                      v2 * P2[:, 2] - P2[:, 1]])
        A = np.column_stack([A, np.zeros(4)]) if A.shape[1] == 3 else A
        Xh = np.linalg.svd(A)[2][-1]
        X.append(Xh[:3] / Xh[3])
    return np.array(X)


def choose_pose_P2_with_C(R, C, K, x1, x2):  # camera 2 built as K [R | C]: the centre where t belongs
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    counts, keep = np.zeros(4, int), []
    for k in range(4):
        X = rtr.triangulate_linear(P1, K @ np.hstack([R[k], C[k][:, None]]), x1, x2)
        front = (X[:, 2] > 0) & ((X - C[k]) @ R[k][2] > 0)
        counts[k] = front.sum()
        keep.append((X, front))
    k = int(np.argmax(counts))
    return R[k], -R[k] @ C[k], keep[k][0], keep[k][1], counts


def choose_pose_argmin(R, C, K, x1, x2):  # the candidate with the FEWEST points in front
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    counts, keep = np.zeros(4, int), []
    for k in range(4):
        t = -R[k] @ C[k]
        X = rtr.triangulate_linear(P1, K @ np.column_stack([R[k], t]), x1, x2)
        front = (X[:, 2] > 0) & ((X - C[k]) @ R[k][2] > 0)
        counts[k] = front.sum()
        keep.append((t, X, front))
    k = int(np.argmin(counts))
    return R[k], keep[k][0], keep[k][1], keep[k][2], counts


def choose_pose_last_loop_points(R, C, K, x1, x2):  # X and in_front leak out of the loop: candidate 3's
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    counts = np.zeros(4, int)
    for k in range(4):
        t = -R[k] @ C[k]
        X = rtr.triangulate_linear(P1, K @ np.column_stack([R[k], t]), x1, x2)
        in_front = (X[:, 2] > 0) & ((X - C[k]) @ R[k][2] > 0)
        counts[k] = in_front.sum()
    best = int(np.argmax(counts))
    return R[best], -R[best] @ C[best], X, in_front, counts


def _nl29(K, R_cws, t_cws, uv, X0, project, skip_nan=True, **kw):
    from scipy.optimize import least_squares

    X = np.array(X0, float)
    for j in range(len(X0)):
        views = [i for i in range(len(R_cws)) if not skip_nan or np.isfinite(uv[j, i]).all()]
        if len(views) < 2:
            continue
        X[j] = least_squares(lambda p: np.concatenate([project(p, i) - uv[j, i] for i in views]), X0[j], **kw).x
    return X


def triangulate_nonlinear_nan_kept(K, R_cws, t_cws, uv, X0):  # every view used, NaN observations included
    def project(p, i):
        q = K @ (R_cws[i] @ p + t_cws[i])
        return q[:2] / q[2]

    return _nl29(K, R_cws, t_cws, uv, X0, project, skip_nan=False)


def triangulate_nonlinear_huber(K, R_cws, t_cws, uv, X0):  # a robust loss "to be safe": another cost
    def project(p, i):
        q = K @ (R_cws[i] @ p + t_cws[i])
        return q[:2] / q[2]

    return _nl29(K, R_cws, t_cws, uv, X0, project, loss="huber", f_scale=0.5)


def triangulate_nonlinear_t_as_centre(K, R_cws, t_cws, uv, X0):  # x_cam = R (X - t): t taken for the centre
    def project(p, i):
        q = K @ (R_cws[i] @ (p - t_cws[i]))
        return q[:2] / q[2]

    return _nl29(K, R_cws, t_cws, uv, X0, project)


# -- valid variants -----------------------------------------------------------------------------------------------
def triangulate_linear__inhomogeneous_lstsq(P1, P2, x1, x2):
    """X_h[3] = 1 fixed and the 4 x 3 system solved by least squares (the inhomogeneous method)."""
    X = np.empty((len(x1), 3))
    for k, ((u1, v1), (u2, v2)) in enumerate(zip(x1, x2)):
        A = np.array([u1 * P1[2] - P1[0], v1 * P1[2] - P1[1], u2 * P2[2] - P2[0], v2 * P2[2] - P2[1]])
        X[k] = np.linalg.lstsq(A[:, :3], -A[:, 3], rcond=None)[0]
    return X


def triangulate_linear__float32_rows_negated(P1, P2, x1, x2):
    """Rows p1ᵀ - u p3ᵀ (the other sign), computed in float32."""
    P1, P2 = P1.astype(np.float32), P2.astype(np.float32)
    x1, x2 = x1.astype(np.float32), x2.astype(np.float32)
    out = np.empty((len(x1), 3), np.float32)
    for k in range(len(x1)):
        A = np.stack([P1[0] - x1[k, 0] * P1[2], P1[1] - x1[k, 1] * P1[2], P2[0] - x2[k, 0] * P2[2],
                      P2[1] - x2[k, 1] * P2[2]])
        Xh = np.linalg.svd(A)[2][-1]
        out[k] = Xh[:3] / Xh[3]
    return out


def choose_pose__float32(R, C, K, x1, x2):
    """Cheirality with the depths in both camera frames, the chosen pose and points returned in float32."""
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    results = []
    for k in range(4):
        t = -R[k] @ C[k]
        X = triangulate_linear(P1, K @ np.column_stack([R[k], t]), x1, x2)
        front = (X[:, 2] > 0) & ((X @ R[k].T + t)[:, 2] > 0)
        results.append((t, X, front))
    counts = np.array([int(r[2].sum()) for r in results])
    k = int(np.argmax(counts))
    t, X, front = results[k]
    return R[k].astype(np.float32), t.astype(np.float32), X.astype(np.float32), front, counts


def triangulate_nonlinear__per_view_residuals(K, R_cws, t_cws, uv, X0):
    """Slow but correct: one small residual function per view, called in a Python loop, numeric Jacobian."""
    from scipy.optimize import least_squares

    def one_view(i, u):
        def r(p):
            q = K @ (R_cws[i] @ p + t_cws[i])
            return np.array([q[0] / q[2] - u[0], q[1] / q[2] - u[1]])
        return r

    X = np.array(X0, dtype=float)
    for j in range(len(X)):
        fs = [one_view(i, uv[j, i]) for i in range(len(R_cws)) if not np.isnan(uv[j, i, 0])]
        if len(fs) >= 2:
            X[j] = least_squares(lambda p: np.concatenate([f(p) for f in fs]), X0[j], x_scale="jac").x
    return X


MISTAKES += [
    M("triangulate_linear", "three rows in A", gtr.check_triangulate_linear, triangulate_three_rows,
      ("reprojection",), batch="29"),
    M("triangulate_linear", "divided by |w|", gtr.check_triangulate_linear, triangulate_divides_by_abs,
      ("sign",), batch="29"),
    M("triangulate_linear", "pixels through K⁻¹ with P = K[R|t]", gtr.check_triangulate_linear,
      triangulate_normalized_pixels, ("reprojection",), batch="29"),
    M("triangulate_linear", "columns of P for its rows", gtr.check_triangulate_linear, triangulate_columns_of_P,
      ("reprojection",), batch="29"),
    M("choose_pose", "camera 2 as K [R | C]", gtr.check_choose_pose, choose_pose_P2_with_C, ("candidate",),
      batch="29"),
    M("choose_pose", "argmin of the counts", gtr.check_choose_pose, choose_pose_argmin, ("fewest",),
      defining="in front of both cameras", batch="29"),
    M("choose_pose", "X of the last candidate tried", gtr.check_choose_pose, choose_pose_last_loop_points,
      ("x",), batch="29"),
    M("triangulate_nonlinear", "NaN observations kept", gtr.check_triangulate_nonlinear,
      triangulate_nonlinear_nan_kept, ("leave out the views",), batch="29"),
    M("triangulate_nonlinear", "Huber loss", gtr.check_triangulate_nonlinear, triangulate_nonlinear_huber,
      ("optimum",), batch="29"),
    M("triangulate_nonlinear", "x_cam = R (X - t)", gtr.check_triangulate_nonlinear, triangulate_nonlinear_t_as_centre,
      ("reprojection error",), batch="29"),
]

HONEST += [
    Honest("triangulate_linear", "inhomogeneous least squares", gtr.check_triangulate_linear,
           triangulate_linear__inhomogeneous_lstsq),
    Honest("triangulate_linear", "rows negated, float32", gtr.check_triangulate_linear,
           triangulate_linear__float32_rows_negated),
    Honest("choose_pose", "float32 results", gtr.check_choose_pose, choose_pose__float32),
    Honest("triangulate_nonlinear", "one residual function per view (slow)", gtr.check_triangulate_nonlinear,
           triangulate_nonlinear__per_view_residuals),
]

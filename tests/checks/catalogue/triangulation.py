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

# ============================================================================ the catalogue

M = Mistake
MISTAKES = [
    M("triangulate_linear", "P1 and P2 swapped in A", gtr.check_triangulate_linear, triangulate_swapped_cameras,
      ("cameras are swapped",)),
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
      triangulate_nonlinear_no_depth_division, ("divided by its depth",)),
]

#: Correct solutions: they must score full marks.
HONEST = [
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

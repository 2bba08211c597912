"""Notebook 02 (essential matrix, pose candidates): classic mistakes, honest solutions and trivial answers, run through its checks."""

from __future__ import annotations

import numpy as np

from course_lib.checks import essential as ges
from course_lib.sfm import essential as res
from tests.checks.catalogue import Honest, Mistake

# ============================================================================ buggy versions
# Each is written as a student would write it (often the reference with one line changed).

# -- 02: essential_from_fundamental ---------------------------------------------------------------
def essential_uncorrected(F, K):
    E = K.T @ F @ K
    return E / np.linalg.norm(E) * np.sqrt(2)


def essential_wrong_order(F, K):
    U, _, Vt = np.linalg.svd(K @ F @ K.T)
    return U @ np.diag([1.0, 1.0, 0.0]) @ Vt


# -- 02: pose_candidates --------------------------------------------------------------------------
_W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def _candidates(E, fix_det=True, order="documented", centre=True):
    U, _, Vt = np.linalg.svd(E)
    u3 = U[:, 2]
    combos = [(R0, t) for R0 in (U @ _W @ Vt, U @ _W.T @ Vt) for t in (u3, -u3)]
    if order == "sign_first":  # (W, +), (Wᵀ, +), (W, -), (Wᵀ, -)
        combos = [combos[0], combos[2], combos[1], combos[3]]
    Rs, Cs = [], []
    for R, t in combos:
        C = -R.T @ t if centre else t
        if fix_det and np.linalg.det(R) < 0:
            R, C = -R, -C
        Rs.append(R)
        Cs.append(C / np.linalg.norm(C))
    return np.stack(Rs), np.stack(Cs)


def pose_candidates_no_det_fix(E):
    return _candidates(E, fix_det=False)


def pose_candidates_other_order(E):
    return _candidates(E, order="sign_first")


def pose_candidates_t_for_C(E):
    return _candidates(E, centre=False)

# ============================================================================ the catalogue

M = Mistake
MISTAKES = [
    M("essential_from_fundamental", "singular values not corrected", ges.check_essential_from_fundamental,
      essential_uncorrected, ("not corrected", "(1, 1, 0)"), defining="singular values (1, 1, 0)"),
    M("essential_from_fundamental", "K F Kᵀ", ges.check_essential_from_fundamental, essential_wrong_order,
      ("k f kᵀ",)),
    M("pose_candidates", "det R = -1 not fixed", ges.check_pose_candidates, pose_candidates_no_det_fix,
      ("det -1", "flip the sign of both r and c"), defining="det R = +1"),
    M("pose_candidates", "candidates in another order", ges.check_pose_candidates, pose_candidates_other_order,
      ("another order", "the docstring fixes"), defining="documented order"),
    M("pose_candidates", "t returned as C", ges.check_pose_candidates, pose_candidates_t_for_C,
      ("not the camera centre",)),
]

#: Correct solutions: they must score full marks.
HONEST = [
    Honest("essential_from_fundamental", "the reference solution", ges.check_essential_from_fundamental, res.essential_from_fundamental),
    Honest("pose_candidates", "the reference solution", ges.check_pose_candidates, res.pose_candidates),
]


def _trivial() -> list:
    z = np.zeros  # noqa: F841
    return [
        (ges.check_essential_from_fundamental, lambda F, K: np.diag([1.0, 1.0, 0.0])),
        (ges.check_pose_candidates, lambda E: (np.stack([np.eye(3)] * 4), np.tile([1.0, 0.0, 0.0], (4, 1)))),
    ]


#: Constants of the right shape: they pass the shape gates and trivially satisfied properties, and must earn nothing.
TRIVIAL = _trivial()

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


def pose_candidates_C_minus_R_t(E):  # near miss: C = -R t instead of -Rᵀ t
    U, _, Vt = np.linalg.svd(E)
    Rs, Cs = [], []
    for R0 in (U @ _W @ Vt, U @ _W.T @ Vt):
        for t in (U[:, 2], -U[:, 2]):
            R, C = R0, -R0 @ t
            if np.linalg.det(R) < 0:
                R, C = -R, -C
            Rs.append(R)
            Cs.append(C / np.linalg.norm(C))
    return np.stack(Rs), np.stack(Cs)


def pose_candidates_one_rotation(E):
    U, _, Vt = np.linalg.svd(E)
    R = U @ _W @ Vt
    if np.linalg.det(R) < 0:
        R = -R
    C = Vt[2] / np.linalg.norm(Vt[2])
    return np.stack([R, R, R, R]), np.stack([C, -C, C, -C])


def essential_inverse_K(F, K):
    Ki = np.linalg.inv(K)
    U, _, Vt = np.linalg.svd(Ki.T @ F @ Ki)
    return U @ np.diag([1.0, 1.0, 0.0]) @ Vt


def essential_F_transposed(F, K):
    U, _, Vt = np.linalg.svd(K.T @ F.T @ K)
    return U @ np.diag([1.0, 1.0, 0.0]) @ Vt


def essential_kept_singular_values(F, K):  # near miss: rank 2 enforced but the two values not made equal
    U, s, Vt = np.linalg.svd(K.T @ F @ K)
    return U @ np.diag([1.0, s[1] / s[0], 0.0]) @ Vt


# ============================================================================ honest solutions
# Written from the textbook (Hartley & Zisserman 9.6), not from course_lib.

def essential_from_fundamental(F, K):
    U, _, Vt = np.linalg.svd(K.T @ F @ K)
    return U @ np.diag([1.0, 1.0, 0.0]) @ Vt


def essential_from_fundamental__proper_rotations(F, K):
    """Another style: U and V made rotations first (det +1), E then normalized to unit singular values."""
    U, s, Vt = np.linalg.svd(K.T @ F @ K)
    if np.linalg.det(U) < 0:
        U = -U
    if np.linalg.det(Vt) < 0:
        Vt = -Vt
    E = U @ np.diag([(s[0] + s[1]) / 2, (s[0] + s[1]) / 2, 0.0]) @ Vt
    return E / np.linalg.svd(E, compute_uv=False)[0]


def essential_average_singular_value(F, K):
    """Hartley & Zisserman's closest E, diag((s1 + s2) / 2, same, 0): correct up to scale (a detail)."""
    U, s, Vt = np.linalg.svd(K.T @ F @ K)
    m = (s[0] + s[1]) / 2
    return U @ np.diag([m, m, 0.0]) @ Vt


def pose_candidates(E):
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    U, _, Vt = np.linalg.svd(E)
    Rs, Cs = [], []
    for R in (U @ W @ Vt, U @ W.T @ Vt):
        for sign in (1.0, -1.0):
            t = sign * U[:, 2]
            Rk, Ck = R, -R.T @ t
            if np.linalg.det(Rk) < 0:
                Rk, Ck = -Rk, -Ck
            Rs.append(Rk)
            Cs.append(Ck / np.linalg.norm(Ck))
    return np.array(Rs), np.array(Cs)


def pose_candidates__proper_svd(E):
    """Another style: U and V made rotations before building R (no flip afterwards), C = ±V[:, 2]."""
    U, _, Vt = np.linalg.svd(E)
    if np.linalg.det(U) < 0:
        U = U * -1
    if np.linalg.det(Vt) < 0:
        Vt = Vt * -1
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    R1, R2 = U @ W @ Vt, U @ W.T @ Vt
    R = np.empty((4, 3, 3))
    C = np.empty((4, 3))
    R[0], R[1], R[2], R[3] = R1, R1, R2, R2
    for k in range(4):
        t = U[:, 2] if k % 2 == 0 else -U[:, 2]
        C[k] = -R[k].T @ t
    return R, C / np.linalg.norm(C, axis=1, keepdims=True)


# ============================================================================ the catalogue

M = Mistake
MISTAKES = [
    M("essential_from_fundamental", "singular values not corrected", ges.check_essential_from_fundamental,
      essential_uncorrected, ("did not correct", "(1, 1, 0)"), defining="singular values (s, s, 0)"),
    M("essential_from_fundamental", "K F Kᵀ", ges.check_essential_from_fundamental, essential_wrong_order,
      ("k f kᵀ",)),
    M("pose_candidates", "det R = -1 not fixed", ges.check_pose_candidates, pose_candidates_no_det_fix,
      ("det -1", "flip the sign of both r and c"), defining="det R = +1"),
    M("pose_candidates", "t returned as C", ges.check_pose_candidates, pose_candidates_t_for_C,
      ("not the camera centre",)),
    M("pose_candidates", "C = -R t", ges.check_pose_candidates, pose_candidates_C_minus_R_t, ("c = -r t",)),
    M("pose_candidates", "only one rotation", ges.check_pose_candidates, pose_candidates_one_rotation,
      ("one rotation",)),
    M("essential_from_fundamental", "K⁻ᵀ F K⁻¹", ges.check_essential_from_fundamental, essential_inverse_K,
      ("turns an e into an f",)),
    M("essential_from_fundamental", "Fᵀ used", ges.check_essential_from_fundamental, essential_F_transposed,
      ("you used fᵀ",)),
    M("essential_from_fundamental", "singular values (1, s2/s1, 0)", ges.check_essential_from_fundamental,
      essential_kept_singular_values, ("did not correct",), defining="singular values (s, s, 0)"),
]

#: Correct solutions: they must score full marks.
HONEST = [
    Honest("essential_from_fundamental", "textbook", ges.check_essential_from_fundamental, essential_from_fundamental),
    Honest("essential_from_fundamental", "proper rotations, average singular value, rescaled",
           ges.check_essential_from_fundamental, essential_from_fundamental__proper_rotations),
    Honest("pose_candidates", "textbook", ges.check_pose_candidates, pose_candidates),
    Honest("pose_candidates", "U and V made rotations first", ges.check_pose_candidates, pose_candidates__proper_svd),
    Honest("essential_from_fundamental", "the reference solution", ges.check_essential_from_fundamental, res.essential_from_fundamental),
    Honest("pose_candidates", "the reference solution", ges.check_pose_candidates, res.pose_candidates),
    # equivalences (issue 29: one rule, full marks): E up to scale, the candidates in another order
    Honest("essential_from_fundamental", "diag((s1 + s2) / 2, same, 0)", ges.check_essential_from_fundamental,
           essential_average_singular_value),
    Honest("pose_candidates", "grouped by the sign of C (+, +, -, -)", ges.check_pose_candidates,
           pose_candidates_other_order),
]


def _trivial() -> list:
    z = np.zeros  # noqa: F841
    return [
        (ges.check_essential_from_fundamental, lambda F, K: np.diag([1.0, 1.0, 0.0])),
        (ges.check_pose_candidates, lambda E: (np.stack([np.eye(3)] * 4), np.tile([1.0, 0.0, 0.0], (4, 1)))),
    ]


#: Constants of the right shape: they pass the shape gates and trivially satisfied properties, and must earn nothing.
TRIVIAL = _trivial()


# ============================================================================ issue 29: written as students write them
# From the notebook's text and the stub's docstring, with an error students make; then valid variants in other
# documented forms (E up to scale, -E, float32, another candidate order), which must get full marks.

def essential_v_not_transposed(F, K):  # numpy's third output is Vᵀ, used as if it were V (MATLAB's [U, S, V])
    U, S, V = np.linalg.svd(K.T @ F @ K)
    return U @ np.diag([1, 1, 0]) @ V.T


def essential_one_K(F, K):  # E = Kᵀ F: the second K forgotten
    U, S, Vt = np.linalg.svd(K.T @ F)
    return U @ np.diag([1.0, 1.0, 0.0]) @ Vt


def essential_normalized_not_projected(F, K):  # "singular values (1, 1, 0)" read as "divide by the largest"
    E = K.T @ F @ K
    return E / np.linalg.svd(E, compute_uv=False)[0]


def pose_candidates_v_not_transposed(E):  # U W V with numpy's Vᵀ taken for V
    W = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]], float)
    U, S, V = np.linalg.svd(E)
    Rs, Cs = [], []
    for R in (U @ W @ V.T, U @ W.T @ V.T):
        for t in (U[:, 2], -U[:, 2]):
            C = -R.T @ t
            if np.linalg.det(R) < 0:
                R, C = -R, -C
            Rs.append(R)
            Cs.append(C)
    return np.array(Rs), np.array(Cs)


def pose_candidates_det_equals_minus_one(E):  # the flip tested with det(R) == -1: float rounding never equals
    W = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]], float)
    U, S, Vt = np.linalg.svd(E)
    Rs, Cs = [], []
    for R in (U @ W @ Vt, U @ W.T @ Vt):
        for t in (U[:, 2], -U[:, 2]):
            C = -R.T @ t
            if np.linalg.det(R) == -1:
                R, C = -R, -C
            Rs.append(R)
            Cs.append(C)
    return np.array(Rs), np.array(Cs)


# -- valid variants -----------------------------------------------------------------------------------------------
def essential_from_fundamental__up_to_scale(F, K):
    """E = Kᵀ F K projected to (s, s, 0) with s the mean of the two: correct up to scale."""
    U, s, Vt = np.linalg.svd(K.T @ F @ K)
    m = (s[0] + s[1]) / 2
    return U @ np.diag([m, m, 0.0]) @ Vt


def essential_from_fundamental__negated_float32(F, K):
    """-E in float32 (E is defined up to sign)."""
    U, _, Vt = np.linalg.svd((K.T @ F @ K).astype(np.float32))
    return -(U @ np.diag(np.array([1, 1, 0], np.float32)) @ Vt)


def pose_candidates__w_transposed(E):
    """W taken as the rotation by -90° (Wᵀ): the same four candidates, in another order."""
    W = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    U, _, Vt = np.linalg.svd(E)
    Rs, Cs = [], []
    for R in (U @ W @ Vt, U @ W.T @ Vt):
        for sign in (1.0, -1.0):
            C = -R.T @ (sign * U[:, 2])
            if np.linalg.det(R) < 0:
                R, C = -R, -C
            Rs.append(R)
            Cs.append(C)
    return np.array(Rs), np.array(Cs)


def pose_candidates__only_R_flipped(E):
    """det fixed by flipping R alone: C and -C are both in the list, so the four candidates are the same set."""
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    U, _, Vt = np.linalg.svd(E)
    Rs, Cs = [], []
    for R in (U @ W @ Vt, U @ W.T @ Vt):
        R = R if np.linalg.det(R) > 0 else -R
        c = Vt[2] / np.linalg.norm(Vt[2])  # the right null vector of E: the centre's direction
        Rs += [R, R]
        Cs += [c, -c]
    return np.array(Rs), np.array(Cs)


def pose_candidates__float32(E):
    """float32 throughout."""
    E = np.asarray(E, np.float32)
    W = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]], np.float32)
    U, _, Vt = np.linalg.svd(E)
    Rs, Cs = [], []
    for R in (U @ W @ Vt, U @ W.T @ Vt):
        for sign in (1, -1):
            C = -R.T @ (sign * U[:, 2])
            if np.linalg.det(R) < 0:
                R, C = -R, -C
            Rs.append(R)
            Cs.append(C / np.linalg.norm(C))
    return np.array(Rs, np.float32), np.array(Cs, np.float32)


MISTAKES += [
    M("essential_from_fundamental", "Vᵀ used as V", ges.check_essential_from_fundamental, essential_v_not_transposed,
      ("kᵀ f k",), batch="29"),
    M("essential_from_fundamental", "E = Kᵀ F", ges.check_essential_from_fundamental, essential_one_K, ("kᵀ f k",),
      batch="29"),
    M("essential_from_fundamental", "divided by the largest singular value", ges.check_essential_from_fundamental,
      essential_normalized_not_projected, ("singular values",), defining="singular values (s, s, 0)", batch="29"),
    M("pose_candidates", "Vᵀ used as V", ges.check_pose_candidates, pose_candidates_v_not_transposed,
      ("factor e",), batch="29"),
    M("pose_candidates", "det(R) == -1", ges.check_pose_candidates, pose_candidates_det_equals_minus_one,
      ("det -1",), defining="det R = +1", batch="29"),
]

HONEST += [
    Honest("essential_from_fundamental", "up to scale, (s, s, 0)", ges.check_essential_from_fundamental,
           essential_from_fundamental__up_to_scale),
    Honest("essential_from_fundamental", "-E in float32", ges.check_essential_from_fundamental,
           essential_from_fundamental__negated_float32),
    Honest("pose_candidates", "W as the -90° rotation (another order)", ges.check_pose_candidates,
           pose_candidates__w_transposed),
    Honest("pose_candidates", "only R flipped, C = ±V[:, 2]", ges.check_pose_candidates, pose_candidates__only_R_flipped),
    Honest("pose_candidates", "float32 throughout", ges.check_pose_candidates, pose_candidates__float32),
]

"""Checks of notebook 02 (the essential matrix and the four pose candidates).

Cases (fixture ``essential``, :mod:`course_lib.instructor.cases.essential`): E from a noiseless and from a noisy
synthetic pair (with the true relative pose) and from the embedded scene's pair (the reference F of notebook 01):

* ``essential_from_fundamental``: two equal singular values and a zero one (defining), and E equal
  to the reference Kᵀ F K projected to (s, s, 0), up to scale and sign;
* ``pose_candidates``: every R a rotation (defining), every C of unit length, every (R, C) factoring
  E (E ∝ [t]ₓ R with t = -R C), and the four candidates equal to the reference's, in any order.

E is defined up to scale and sign; the four candidates are a set (any order gets full marks: notebook 03 picks
one by cheirality, never by position). det R = +1 is checked on E and on a multiple of E of every pair (for one
of the two the SVD gives det U det V = -1, so a missing flip shows on every pair).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from course_lib.checks.core import (RTOL, Check, Outcome, as_float, declare_defining, load_fixture,
                                    report_cases, same_up_to_scale, scale_free_gap)
from course_lib.conventions import rotation_angle_deg, skew

__all__ = ["check_essential_from_fundamental", "check_pose_candidates", "match_candidates"]

FIXTURE = "essential"

SV = "singular values (s, s, 0)"
declare_defining("essential_from_fundamental", {
    SV: "an essential matrix has two equal singular values and a zero one",
})
declare_defining("pose_candidates", {
    "det R = +1": "a rotation has det +1; det -1 is a reflection, no camera pose",
})

_CASE_TEXT = {
    "noiseless": "noiseless synthetic pair",
    "noisy": "noisy synthetic pair",
    "building": "embedded building pair",
    "noiseless_neg": "noiseless synthetic pair, -E",
    "noisy_neg": "noisy synthetic pair, -E",
    "building_neg": "embedded building pair, -E",
}


# --------------------------------------------------------------------------- helpers


def match_candidates(R, C, R_ref, C_ref, tol: float = 10 * RTOL) -> list[int]:
    """For each reference candidate k, the index of the candidate of ``(R, C)`` equal to it (or -1).

    Equal: the rotations within ``tol`` radians, the unit centres within ``tol`` (float32 answers pass).
    """
    hits = []
    for k in range(len(R_ref)):
        found = -1
        for m in range(len(R)):
            Cn = C[m] / np.linalg.norm(C[m]) if np.linalg.norm(C[m]) > 0 else C[m]
            if (np.radians(rotation_angle_deg(R[m], R_ref[k])) < tol and np.linalg.norm(Cn - C_ref[k]) < tol):
                found = m
                break
        hits.append(found)
    return hits


# --------------------------------------------------------------------------- essential_from_fundamental


#: What each stored mistake of essential_from_fundamental (``<case>_mis_<key>[_corrected]``) means, as what the
#: student did.
_E_MISTAKES = {
    "k_f_kt": "you computed K F Kᵀ: the order is E = Kᵀ F K (F = K⁻ᵀ E K⁻¹)",
    "inverse": "you computed K⁻ᵀ F K⁻¹, which turns an E into an F; the other way round is E = Kᵀ F K",
    "transposed": "you used Fᵀ: E = Kᵀ F K with F as given (x2ᵀ F x1 = 0)",
    "k_f_k": "you computed K F K, a transpose is missing: E = Kᵀ F K",
    "uncorrected": "you did not correct the singular values of Kᵀ F K: set them to (1, 1, 0), E = U diag(1, 1, 0) Vᵀ "
                   "from the SVD of Kᵀ F K",
}


def _e_keys(E, f: dict, name: str) -> set[str]:
    """The stored mistakes (uncorrected or corrected to (1, 1, 0)) that E equals on case ``name``, up to scale."""
    out = set()
    for key in _E_MISTAKES:
        for k in ((key,) if key == "uncorrected" else (key, f"{key}_corrected")):
            if f"{name}_mis_{k}" in f and same_up_to_scale(E, f[f"{name}_mis_{k}"], 1e-5):
                out.add(key)
    return out


def check_essential_from_fundamental(essential_from_fundamental: Callable) -> None:
    """Check ``essential_from_fundamental(F (3, 3), K (3, 3)) -> E (3, 3)`` (notebook 02)."""
    f = load_fixture(FIXTURE)
    with Check("essential_from_fundamental") as c:
        results = []
        for name in [str(n) for n in f["cases"]]:
            F, K = f[f"{name}_F"], f[f"{name}_K"]
            case = _CASE_TEXT[name]
            E = c.call(essential_from_fundamental, F, K, case=case)
            if not c.shape(E, (3, 3), f"{case}: E"):
                continue
            E = as_float(E)
            ok = same_up_to_scale(E, f[f"{name}_E"])
            results.append(Outcome(
                case, ok, "E matches the reference Kᵀ F K corrected to (1, 1, 0), up to scale and sign",
                f"E differs from the reference Kᵀ F K corrected to (1, 1, 0) (by "
                f"{scale_free_gap(E, f[f'{name}_E']):.3g} at unit norm, either sign)",
                keys=() if ok else _e_keys(E, f, name), data=E))
        report_cases(c, results, {k: v for k, v in _E_MISTAKES.items() if k != "uncorrected"},
                     first=lambda o, named: _singular_values_verdict(c, o.case, o.data, named))
        c.causes(essential_from_fundamental, [
            (r"\binv\(", "your code inverts a matrix: E = Kᵀ F K takes K itself (K⁻ᵀ E K⁻¹ = F is the other direction)"),
            (r"\bV[th]?\.T\b|transpose\(\s*V[th]?\b",
             "np.linalg.svd returns Vᵀ already: E = U @ np.diag([1, 1, 0]) @ Vt, without transposing it"),
            ((r"\bK\b", r"!(?s:\bK\b.*\bK\b.*\bK\b)"), "K goes on both sides of F: E = Kᵀ F K"),
        ])


def _singular_values_verdict(c: Check, case: str, E, named: str | None) -> None:
    s = np.linalg.svd(E, compute_uv=False)
    rel = np.round(s / s[0], 4).tolist() if s[0] > 0 else s.tolist()
    c.gate(_equal_singular_values(s), f"{case}: E has two equal singular values and a zero one",
           f"{case}: E's singular values are {rel} relative to the largest, expected (1, 1, 0): "
           + (_E_MISTAKES[named] if named == "uncorrected" else "E = U diag(1, 1, 0) Vᵀ from the SVD of Kᵀ F K"),
           defining=SV, named="uncorrected" if named == "uncorrected" else None)


def _equal_singular_values(s) -> bool:
    return bool(s[0] > 0 and abs(s[0] - s[1]) <= RTOL * s[0] and s[2] <= RTOL * s[0])


# --------------------------------------------------------------------------- pose_candidates


def _c_keys(R, Cn, R_ref, C_ref) -> set[str]:
    """What the student's C holds instead of the centre, read off the reference's candidates: t, or -R t."""
    out = set()
    loose = 100 * RTOL
    if -1 not in match_candidates(R, np.stack([-(R[k].T @ Cn[k]) for k in range(4)]), R_ref, C_ref, loose):
        out.add("t_for_C")
    if -1 not in match_candidates(R, np.stack([R[k].T @ R[k].T @ Cn[k] for k in range(4)]), R_ref, C_ref, loose):
        out.add("C_minus_R_t")
    return out


_C_MISTAKES = {
    "t_for_C": "C holds the translation t = ±U[:, 2], not the camera centre: C = -Rᵀ t (the right null vector of E, "
               "±V[:, 2]); t = -R C",
    "C_minus_R_t": "you computed C = -R t: the centre is C = -Rᵀ t (transpose R), t = ±U[:, 2]",
}


def _candidates_outcome(case: str, E, R, C, R_ref, C_ref) -> Outcome:
    """One case of pose_candidates: the four candidates factor E and are the reference's, in any order; else which
    property fails (the keys of :data:`_C_MISTAKES` that explain it)."""
    norms = np.linalg.norm(C, axis=1)
    Cn = C / np.where(norms > 0, norms, 1.0)[:, None]
    bad = [k for k in range(4) if not same_up_to_scale(skew(-R[k] @ Cn[k]) @ R[k], E, 10 * RTOL)]
    factors = not bad and bool(np.abs(E @ Cn.T).max() <= 10 * RTOL * np.linalg.norm(E))
    hits = match_candidates(R, Cn, R_ref, C_ref)
    ok = factors and -1 not in hits and len(set(hits)) == 4
    if len({tuple(np.round(Rk, 6).ravel()) for Rk in np.abs(R)}) < 2:
        advice = ("the four R are one rotation, where two are expected: U W Vᵀ and U Wᵀ Vᵀ with "
                  "W = [[0, -1, 0], [1, 0, 0], [0, 0, 1]] (W ≠ Wᵀ, so the two differ), each with C and -C; if you use "
                  "both, check W itself and that the second rotation takes its transpose")
    elif not factors:
        advice = (f"candidates {bad} do not factor E (E ∝ [t]ₓ R with t = -R C): R = U W Vᵀ or U Wᵀ Vᵀ, "
                  "t = ±U[:, 2], C = -Rᵀ t")
    else:
        advice = (f"the candidates factor E but {hits.count(-1)} of the reference's four are missing (found at "
                  f"{hits}): R ∈ {{U W Vᵀ, U Wᵀ Vᵀ}}, C = ±(-Rᵀ U[:, 2]), each rotation with both signs")
    return Outcome(case, ok, "the four candidates factor E and match the reference's (in any order)", "",
                   () if ok else _c_keys(R, Cn, R_ref, C_ref), advice, (R, norms))


def _candidate_gates(c: Check, case: str, R, norms) -> None:
    """Every R a rotation (the defining property: det +1), every C of unit length."""
    dets = np.linalg.det(R)
    gap = max(float(np.abs(Rk @ Rk.T - np.eye(3)).max()) for Rk in R)
    det1 = "det R = +1"
    if gap <= RTOL and np.allclose(dets, 1.0, atol=RTOL):
        c.gate(True, f"{case}: every R is a rotation (orthonormal, det +1)", "", defining=det1)
    elif gap <= RTOL:
        bad = [k for k in range(4) if dets[k] < 0]
        c.fail(f"{case}: R[{', '.join(map(str, bad))}] has det -1 (a reflection): when det(R) < 0, flip the sign of "
               "both R and C (test det(R) < 0, never == -1: rounding)", defining=det1)
    else:
        c.fail(f"{case}: R is not orthonormal (R Rᵀ differs from I by {gap:.3g}): R = U W Vᵀ or U Wᵀ Vᵀ with U, Vᵀ "
               "from the SVD of E (numpy returns Vᵀ, not V)", defining=det1)
    c.gate(bool(np.abs(norms - 1.0).max() <= RTOL), f"{case}: every C has unit length",
           f"{case}: C does not have unit length (|C| = {np.round(norms, 3).tolist()}): the scale is unknown, "
           "return C / np.linalg.norm(C)")


def check_pose_candidates(pose_candidates: Callable) -> None:
    """Check ``pose_candidates(E (3, 3)) -> (R (4, 3, 3), C (4, 3))`` (notebook 02)."""
    f = load_fixture(FIXTURE)
    with Check("pose_candidates") as c:
        outcomes = []
        for name in [str(n) for n in f["pose_cases"]]:
            E, R_ref, C_ref = f[f"{name}_E"], f[f"{name}_R"], f[f"{name}_C"]
            case = _CASE_TEXT[name]
            if f"{name}_factor" in f and float(f[f"{name}_factor"]) != -1.0:
                case = case.replace("-E", f"{float(f[f'{name}_factor']):g} E")
            out = c.fields(c.call(pose_candidates, E, case=case), case, ("R", "C"), "the tuple (R (4, 3, 3), C (4, 3))")
            if out is None:
                continue
            R, C = as_float(out[0]), as_float(out[1])
            if C is not None and C.shape == (4, 3, 1):
                C = C[..., 0]
            if c.shape(out[0], (4, 3, 3), f"{case}: R") & c.shape(out[1] if C is None else C, (4, 3), f"{case}: C"):
                outcomes.append(_candidates_outcome(case, E, R, C, R_ref, C_ref))
        report_cases(c, outcomes, _C_MISTAKES, first=lambda o, _: _candidate_gates(c, o.case, *o.data))

"""Checks of notebook 02 (the essential matrix and the four pose candidates).

Each ``check_*`` function runs the student's function on stored cases (fixture ``essential``,
built in the instructor's kit from :mod:`course_lib.sfm.essential` by ``python -m course_lib fixtures essential``),
compares with the stored reference results and with properties, and names the likely mistake:

* ``essential_from_fundamental``: no singular-value correction, ``K F Kᵀ`` instead of
  ``Kᵀ F K``, ``K⁻ᵀ F K⁻¹`` (that maps E to F, not F to E), singular values ``(s, s, 0)`` with s ≠ 1;
* ``pose_candidates``: ``R`` with det -1 (not flipped), ``C`` not of unit length, ``t = ±U[:, 2]``
  returned in place of the centre ``C = -Rᵀ t``, only one rotation (W and Wᵀ), candidates that
  do not factor E, candidates in another order than the docstring's.

Defining properties (failing one costs at least half of the points): E's two equal singular
values and a zero one; every candidate R a rotation (det +1), checked on E and on -E of every pair
(for one of the two the SVD gives det U det V = -1, so a missing flip shows on every pair). Correct
maths in another documented form costs only a detail (at most 1 point of 10): singular values
(s, s, 0) with s ≠ 1 (E is defined up to scale), the four right candidates in another order than
the docstring's (e.g. grouped by the sign of C).

Cases: E from a noiseless and from a noisy synthetic pair (with the true relative pose) and from
the embedded scene's pair (1, 2) (the reference F of notebook 01) when it is present.

The cases and the reference's results on them are stored arrays, made on the instructor's side
by :mod:`course_lib.instructor.cases.essential`; this module imports no reference solution and ships
to students.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from course_lib.checks.core import FAILED, Check, declare_defining, load_fixture

__all__ = ["check_essential_from_fundamental", "check_pose_candidates", "match_candidates"]

FIXTURE = "essential"

declare_defining("essential_from_fundamental", {
    "singular values (1, 1, 0)": "an essential matrix has two equal singular values and a zero one",
})
declare_defining("pose_candidates", {
    "det R = +1": "a rotation has det +1; det -1 is a reflection, no camera pose",
})

#: The documented candidate order, as a sentence for the verdicts.
ORDER_TEXT = "k = 0: (U W Vᵀ, +), 1: (U W Vᵀ, -), 2: (U Wᵀ Vᵀ, +), 3: (U Wᵀ Vᵀ, -)"

_CASE_TEXT = {
    "noiseless": "noiseless synthetic pair",
    "noisy": "noisy synthetic pair",
    "building": "embedded building pair",
    "noiseless_neg": "noiseless synthetic pair, -E",
    "noisy_neg": "noisy synthetic pair, -E",
    "building_neg": "embedded building pair, -E",
}


# --------------------------------------------------------------------------- helpers


def _skew(v):
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _same_up_to_sign(A, B, tol: float) -> bool:
    A, B = np.asarray(A, float), np.asarray(B, float)
    if A.shape != B.shape or not np.isfinite(A).all():
        return False
    return bool(min(np.abs(A - B).max(), np.abs(A + B).max()) < tol)


def _unit(M):
    M = np.asarray(M, float)
    n = np.linalg.norm(M)
    return M / n if n > 0 else M


def _rot_deg(Ra, Rb) -> float:
    c = np.clip((np.trace(Ra @ Rb.T) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(c)))


def match_candidates(R, C, R_ref, C_ref, rot_deg: float = 1e-4, cos_min: float = 1 - 1e-8) -> list[int]:
    """For each reference candidate k, the index of the candidate of ``(R, C)`` equal to it (or -1)."""
    hits = []
    for k in range(len(R_ref)):
        found = -1
        for m in range(len(R)):
            Cn = C[m] / np.linalg.norm(C[m]) if np.linalg.norm(C[m]) > 0 else C[m]
            if _rot_deg(R[m], R_ref[k]) < rot_deg and float(Cn @ C_ref[k]) > cos_min:
                found = m
                break
        hits.append(found)
    return hits


def _documented_order(R, C, tol: float = 1e-6) -> bool:
    """True if ``(R, C)`` has the documented structure (U W Vᵀ, ±), (U Wᵀ Vᵀ, ±).

    Candidates 0 and 1 share one rotation, 2 and 3 the other, and each pair has opposite centres.
    (Which rotation is U W Vᵀ, and which sign is "+", depend on the signs the SVD picks for U and
    V, which are not unique; so only this structure is checked, never the reference's exact order.)
    """
    return bool(np.allclose(R[0], R[1], atol=tol) and np.allclose(R[2], R[3], atol=tol)
                and not np.allclose(R[0], R[2], atol=1e-4)
                and np.allclose(C[1], -C[0], atol=tol) and np.allclose(C[3], -C[2], atol=tol))


# --------------------------------------------------------------------------- fixtures


# --------------------------------------------------------------------------- essential_from_fundamental


def check_essential_from_fundamental(essential_from_fundamental: Callable) -> None:
    """Check ``essential_from_fundamental(F (3, 3), K (3, 3)) -> E (3, 3)`` (notebook 02).

    E must equal the reference ``Kᵀ F K`` projected to singular values ``(1, 1, 0)``, up to sign.
    """
    f = load_fixture(FIXTURE)
    with Check("essential_from_fundamental") as c:
        for name in [str(n) for n in f["cases"]]:
            F, K, E_ref = f[f"{name}_F"], f[f"{name}_K"], f[f"{name}_E"]
            case = _CASE_TEXT[name]
            E = c.call(essential_from_fundamental, F, K, case=case)
            if E is FAILED:
                continue
            E = np.asarray(E, dtype=float)
            if not c.shape(E, (3, 3), f"{case}: E"):
                continue
            s = np.linalg.svd(E, compute_uv=False)
            sv = "singular values (1, 1, 0)"
            if np.allclose(s, [1.0, 1.0, 0.0], atol=1e-6):
                c.gate(True, f"{case}: E has singular values (1, 1, 0)", "", defining=sv)
            elif s[0] > 0 and np.isclose(s[0], s[1], rtol=1e-6) and s[2] < 1e-6 * s[0]:
                c.detail(False, "", f"{case}: E has singular values ({s[0]:.4g}, {s[1]:.4g}, 0): correct maths (E is defined "
                         "up to scale), but the docstring asks for exactly (1, 1, 0): U diag(1, 1, 0) Vᵀ")
            elif _same_up_to_sign(_unit(E), f[f"{name}_mis_uncorrected"], 1e-6):
                c.fail(f"{case}: E = Kᵀ F K is not corrected (singular values {np.round(s / s[0], 3).tolist()} relative): "
                       "set them to (1, 1, 0), E = U diag(1, 1, 0) Vᵀ from the SVD of Kᵀ F K", defining=sv)
            else:
                c.fail(f"{case}: E has singular values {np.round(s, 4).tolist()}, expected two equal ones and a zero, "
                       "(1, 1, 0): E = U diag(1, 1, 0) Vᵀ from the SVD of Kᵀ F K", defining=sv)
            if _same_up_to_sign(_unit(E), _unit(E_ref), 1e-6):
                c.expect(True, f"{case}: E matches the reference Kᵀ F K (up to sign)", "")
                continue
            hint = next((h for key, h in _E_MISTAKES.items() if any(
                f"{name}_mis_{k}" in f and _same_up_to_sign(_unit(E), _unit(f[f"{name}_mis_{k}"]), 1e-5)
                for k in (key, f"{key}_corrected"))), None)
            c.fail(f"{case}: {hint or 'E differs from the reference Kᵀ F K (corrected to singular values (1, 1, 0)), up to sign'}")


#: What each stored mistake of essential_from_fundamental (``<case>_mis_<key>[_corrected]``) means.
_E_MISTAKES = {
    "k_f_kt": "K F Kᵀ: the order is E = Kᵀ F K (F = K⁻ᵀ E K⁻¹)",
    "inverse": "K⁻ᵀ F K⁻¹ turns an E into an F; the other way round is E = Kᵀ F K",
    "transposed": "Fᵀ was used: E = Kᵀ F K with F as given (x2ᵀ F x1 = 0)",
    "k_f_k": "K F K is missing a transpose: E = Kᵀ F K",
}


# --------------------------------------------------------------------------- pose_candidates


def check_pose_candidates(pose_candidates: Callable) -> None:
    """Check ``pose_candidates(E (3, 3)) -> (R (4, 3, 3), C (4, 3))`` (notebook 02).

    Every R must be a rotation (det +1), every C of unit length, every (R, C) must factor E as
    ``E ∝ [t]ₓ R`` with ``t = -R C``, and the four candidates must equal the reference's, in the
    documented order ``(U W Vᵀ, +), (U W Vᵀ, -), (U Wᵀ Vᵀ, +), (U Wᵀ Vᵀ, -)``.
    """
    f = load_fixture(FIXTURE)
    with Check("pose_candidates") as c:
        for name in [str(n) for n in f["pose_cases"]]:
            E, R_ref, C_ref = f[f"{name}_E"], f[f"{name}_R"], f[f"{name}_C"]
            case = _CASE_TEXT[name]
            if f"{name}_factor" in f and float(f[f"{name}_factor"]) != -1.0:
                case = case.replace("-E", f"{float(f[f'{name}_factor']):g} E")
            out = c.call(pose_candidates, E, case=case)
            if out is FAILED:
                continue
            if not isinstance(out, (tuple, list)) or len(out) != 2:
                c.fail(f"{case}: expected a tuple (R (4, 3, 3), C (4, 3)), got {type(out).__name__}")
                continue
            try:
                R, C = np.asarray(out[0], float), np.asarray(out[1], float)
            except (TypeError, ValueError):
                c.fail(f"{case}: R and C must be numeric arrays (np.stack the four candidates)")
                continue
            if C.shape == (4, 3, 1):
                C = C[..., 0]
            if not (c.shape(R, (4, 3, 3), f"{case}: R") & c.shape(C, (4, 3), f"{case}: C")):
                continue
            dets = np.linalg.det(R)
            orth = all(np.allclose(Rk @ Rk.T, np.eye(3), atol=1e-6) for Rk in R)
            det1 = "det R = +1"
            if orth and np.allclose(dets, 1.0, atol=1e-6):
                c.gate(True, f"{case}: every R is a rotation (orthonormal, det +1)", "", defining=det1)
            elif orth:
                bad = [k for k in range(4) if dets[k] < 0]
                c.fail(f"{case}: R[{', '.join(map(str, bad))}] has det -1 (a reflection): when det(R) < 0, "
                       "flip the sign of both R and C", defining=det1)
            else:
                c.fail(f"{case}: R is not orthonormal: R = U W Vᵀ or U Wᵀ Vᵀ with U, V from the SVD of E", defining=det1)
            norms = np.linalg.norm(C, axis=1)
            c.gate(np.allclose(norms, 1.0, atol=1e-6), f"{case}: every C has unit length",
                     f"{case}: C does not have unit length (|C| = {np.round(norms, 3).tolist()}): the scale is unknown, "
                     "return C / np.linalg.norm(C)")
            # factoring E: E ∝ [t]ₓ R with t = -R C, and E C = 0
            Cn = C / np.where(norms > 0, norms, 1.0)[:, None]
            factors = all(
                _same_up_to_sign(_unit(_skew(-R[k] @ Cn[k]) @ R[k]), _unit(E), 1e-5) for k in range(4)
            ) and np.allclose(E @ Cn.T, 0.0, atol=1e-6)
            hits = match_candidates(R, Cn, R_ref, C_ref)
            if factors and -1 not in hits and len(set(hits)) == 4:
                c.expect(True, f"{case}: the four candidates factor E and match the reference", "")
                c.detail(_documented_order(R, Cn), f"{case}: the candidates come in the documented order",
                         f"{case}: correct maths, the right four candidates, but not in the order the docstring asks for "
                         f"(the reference's candidates appear at {hits}): {ORDER_TEXT}, i.e. R[0] = R[1], R[2] = R[3], "
                         "C[1] = -C[0], C[3] = -C[2]")
                continue
            # diagnose: C holds t = ±U[:, 2] instead of the centre -Rᵀ t
            Ct = np.stack([-(R[k].T @ Cn[k]) for k in range(4)])
            if -1 not in match_candidates(R, Ct, R_ref, C_ref, rot_deg=1e-3, cos_min=1 - 1e-6):
                c.fail(f"{case}: C holds the translation t = ±U[:, 2], not the camera centre: C = -Rᵀ t "
                       "(the right null vector of E, ±V[:, 2]); t = -R C")
            elif -1 not in match_candidates(R, np.stack([R[k].T @ R[k].T @ Cn[k] for k in range(4)]), R_ref,
                                            C_ref, rot_deg=1e-3, cos_min=1 - 1e-6):
                c.fail(f"{case}: C = -R t: the centre is C = -Rᵀ t (transpose R), t = ±U[:, 2]")
            elif len({tuple(np.round(Rk, 6).ravel()) for Rk in np.abs(R)}) < 2:
                c.fail(f"{case}: only one rotation: the candidates use both U W Vᵀ and U Wᵀ Vᵀ, each with C and -C")
            elif not factors:
                c.fail(f"{case}: some candidates do not factor E (E ∝ [t]ₓ R with t = -R C): "
                       "R = U W Vᵀ or U Wᵀ Vᵀ, t = ±U[:, 2], C = -Rᵀ t")
            else:
                c.fail(f"{case}: the candidates differ from the reference: R ∈ {{U W Vᵀ, U Wᵀ Vᵀ}}, C = ±(-Rᵀ U[:, 2])")

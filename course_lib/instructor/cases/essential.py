"""Cases of notebook 02 (essential matrix, pose candidates): E from synthetic pairs and the embedded pair, and -E.

Built from :mod:`course_lib.sfm.essential` (fixture ``essential``); the checks are in
:mod:`course_lib.checks.essential`. The embedded case is a random subset of the reference inliers
of notebook 01 (its F refit on that subset), so the hidden cases of a grading run (salted seeds)
repeat nothing that ships. What the classic mistakes give is stored with each case
(:func:`essential_variants`).
"""

from __future__ import annotations

import numpy as np

from course_lib.checks.essential import FIXTURE
from course_lib.data.synthetic import make_scene
from course_lib.instructor.cases import builds, store
from course_lib.instructor.cases.fundamental import embedded_pair, random_subset
from course_lib.sfm import essential as ref
from course_lib.sfm.fundamental import eight_point, ransac_fundamental
from course_lib.starting_points import STEP_SEED, STEP_THRESHOLD_PX


@builds(FIXTURE)
def _build() -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    cases = []
    for name, noise, seed in (("noiseless", 0.0, 21), ("noisy", 0.7, 22)):
        sc = make_scene(np.random.default_rng(seed), n_cameras=2, n_points=150, noise_px=noise, outlier_fraction=0.0)
        x1, x2, _, _ = sc.pair(0, 1)
        store(out, name, F=eight_point(x1, x2), K=sc.K)
        cases.append(name)
    # the embedded pair: the same reference result that two_view_step() serves to notebook 02
    # (recomputed here, so that this fixture does not depend on the order fixtures are built in)
    emb = embedded_pair()
    if emb is not None:
        x1, x2, K = emb
        res = ransac_fundamental(x1, x2, np.random.default_rng(STEP_SEED), threshold_px=STEP_THRESHOLD_PX)
        keep = random_subset(int(res.inliers.sum()), 23)
        x1, x2 = x1[res.inliers][keep], x2[res.inliers][keep]
        store(out, "building", F=eight_point(x1, x2), K=K)
        cases.append("building")
    out["cases"] = np.array(cases)
    for name in cases:
        E = ref.essential_from_fundamental(out[f"{name}_F"], out[f"{name}_K"])
        R, C = ref.pose_candidates(E)
        store(out, name, E=E, R=R, C=C)
        store(out, f"{name}_mis", **essential_variants(out[f"{name}_F"], out[f"{name}_K"]))
    # E and -E are the same essential matrix; for one of the two the SVD gives det(U) det(V) = -1, so
    # a missing det flip shows on every pair (pose_candidates only)
    # (with np.linalg.svd; the multiple of E that exposes it is searched for, -E first)
    for name in cases:
        E0 = out[f"{name}_E"]
        flips = [m for m in (-1.0, 2.0, -2.0, 0.5, -0.5, 3.0, -3.0) if _svd_det_sign(m * E0) != _svd_det_sign(E0)]
        m = flips[0] if flips else -1.0
        R, C = ref.pose_candidates(m * E0)
        store(out, f"{name}_neg", E=m * E0, factor=np.array(m), R=R, C=C)
    out["pose_cases"] = np.array([n for name in cases for n in (name, f"{name}_neg")])
    return out


def _svd_det_sign(E) -> float:
    """det(U) det(V) of ``np.linalg.svd(E)``: -1 means that R = U W Vᵀ comes out as a reflection."""
    U, _, Vt = np.linalg.svd(E)
    return float(np.sign(np.linalg.det(U) * np.linalg.det(Vt)))


# --------------------------------------------------------------------------- what the classic mistakes give
# (stored with the cases, keyed as the check module's sentences are: the shipped checks hold no implementation)


def _corrected(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, 0.0]) @ Vt


def essential_variants(F: np.ndarray, K: np.ndarray) -> dict[str, np.ndarray]:
    """E (3, 3) of the classic mistakes of E = Kᵀ F K, each also corrected to singular values (1, 1, 0)."""
    Ki = np.linalg.inv(K)
    raw = {"k_f_kt": K @ F @ K.T, "inverse": Ki.T @ F @ Ki, "transposed": K.T @ F.T @ K, "k_f_k": K @ F @ K}
    out = {}
    for key, M in raw.items():
        out[key] = M / np.linalg.norm(M)
        out[f"{key}_corrected"] = _corrected(M)
    E = K.T @ F @ K
    out["uncorrected"] = E / np.linalg.norm(E)
    return out

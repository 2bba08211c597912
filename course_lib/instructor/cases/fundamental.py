"""Cases of notebook 01 (fundamental matrix): synthetic pairs, the embedded pair, the unnormalized 8-point.

Built from :mod:`course_lib.sfm.fundamental` (fixture ``fundamental``); the checks are in
:mod:`course_lib.checks.fundamental`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from course_lib.checks.fundamental import CHECK_THRESHOLD_PX, FIXTURE
from course_lib.instructor.cases import builds
from course_lib.paths import EMBEDDED_SFM
from course_lib.steps import STEP_PAIR, STEP_SEED, STEP_THRESHOLD_PX

def _synthetic_cases() -> dict[str, np.ndarray]:
    from course_lib.data.synthetic import make_scene

    out: dict[str, np.ndarray] = {}
    # normalize_points: an anisotropic cloud far from the origin (a strip of a building)
    g = np.random.default_rng(101)
    out["norm_x"] = np.column_stack([g.uniform(150.0, 700.0, 40), g.uniform(380.0, 520.0, 40)])
    # noiseless pair: exact projections
    sc = make_scene(np.random.default_rng(3), n_cameras=2, n_points=120, noise_px=0.0, outlier_fraction=0.0)
    x1, x2, _, _ = sc.pair(0, 1)
    out["noiseless_x1"], out["noiseless_x2"] = x1, x2
    # noisy pair: 1 px noise, no outliers; the unnormalized 8-point is clearly worse here
    sc = make_scene(np.random.default_rng(3), n_cameras=2, n_points=120, noise_px=1.0, outlier_fraction=0.0)
    x1, x2, _, ids = sc.pair(0, 1)
    out["noisy_x1"], out["noisy_x2"] = x1, x2
    # pair with outliers (about 20 % of the correspondences), 0.5 px noise
    sc = make_scene(np.random.default_rng(5), n_cameras=2, n_points=250, noise_px=0.5, outlier_fraction=0.1)
    x1, x2, inl, ids = sc.pair(0, 1)
    out["outliers_x1"], out["outliers_x2"], out["outliers_true_inliers"] = x1, x2, inl
    out["outliers_x1_true"], out["outliers_x2_true"] = sc.uv_true[ids, 0], sc.uv_true[ids, 1]
    return out


def embedded_pair():
    """``(x1, x2, K)`` of the embedded pair, or None when data/synthetic-building is not there."""
    if not (Path(EMBEDDED_SFM) / "matching1.txt").exists():
        return None
    from course_lib.data.p3 import read_p3

    data = read_p3(EMBEDDED_SFM)
    m = data.matches[STEP_PAIR]
    return m.x1, m.x2, data.K


def _unnormalized_eight_point(x1, x2) -> np.ndarray:
    """The typical mistake 'not normalized', kept to recognize it (fixture build time only)."""
    u1, v1 = x1.T
    u2, v2 = x2.T
    A = np.stack([u2 * u1, u2 * v1, u2, v2 * u1, v2 * v1, v2, u1, v1, np.ones_like(u1)], axis=1)
    F = np.linalg.svd(A)[2][-1].reshape(3, 3)
    U, s, Vt = np.linalg.svd(F)
    F = U @ np.diag([s[0], s[1], 0.0]) @ Vt
    return F / np.linalg.norm(F)


@builds(FIXTURE)
def _build() -> dict[str, np.ndarray]:
    from course_lib.sfm import fundamental as ref

    out = _synthetic_cases()
    out["norm_xn"], out["norm_T"] = ref.normalize_points(out["norm_x"])
    cases = ["noiseless", "noisy", "outliers"]
    emb = embedded_pair()
    if emb is not None:
        x1, x2, K = emb
        out["building_x1"], out["building_x2"], out["building_K"] = x1, x2, K
        res = ref.ransac_fundamental(x1, x2, np.random.default_rng(STEP_SEED), threshold_px=STEP_THRESHOLD_PX)
        out["building_F_ransac"], out["building_inliers"] = res.F, res.inliers
        out["building_n_iters"] = np.array(res.n_iters)
        out["building_pair"] = np.array(STEP_PAIR)
        out["building_threshold_px"] = np.array(STEP_THRESHOLD_PX)
        cases.append("building")
    out["cases"] = np.array(cases)
    for name in cases:
        x1, x2 = out[f"{name}_x1"], out[f"{name}_x2"]
        if name == "outliers":
            inl = out["outliers_true_inliers"]
        elif name == "building":
            inl = out["building_inliers"]
        else:
            inl = np.ones(len(x1), bool)
        # eight_point on the inliers of the case; its Sampson distances there
        F = ref.eight_point(x1[inl], x2[inl])
        out[f"{name}_F"] = F
        out[f"{name}_F_unnormalized"] = _unnormalized_eight_point(x1[inl], x2[inl])
        out[f"{name}_sampson"] = ref.sampson_distance(F, x1, x2)
    # RANSAC on the pair with outliers, as the check calls it
    res = ref.ransac_fundamental(
        out["outliers_x1"], out["outliers_x2"], np.random.default_rng(0), threshold_px=CHECK_THRESHOLD_PX
    )
    out["outliers_F_ransac"], out["outliers_inliers"] = res.F, res.inliers
    out["outliers_n_iters"] = np.array(res.n_iters)
    return out

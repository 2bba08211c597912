"""Cases of notebook 05 (visibility, reprojection residuals, Jacobian sparsity, bundle adjustment), and its step input.

Built from :mod:`course_lib.sfm.bundle_adjustment` and :mod:`course_lib.sfm.visibility`
(fixtures ``bundle_adjustment`` and ``bundle_adjustment_step``); the checks are in
:mod:`course_lib.checks.bundle_adjustment`.
"""

from __future__ import annotations

import numpy as np

from course_lib.checks.bundle_adjustment import FIXTURE
from course_lib.instructor.cases import builds
from course_lib.paths import EMBEDDED_SFM
from course_lib.steps import reconstruction_before_ba

@builds("bundle_adjustment_step", step=True)
def _build_step() -> dict[str, np.ndarray]:
    if not (EMBEDDED_SFM / "ground_truth.json").exists():
        return {}
    return reconstruction_before_ba(EMBEDDED_SFM)


def _scene(seed, n_cameras, n_points, noise_px, outlier_fraction):
    from course_lib.data.synthetic import make_scene

    return make_scene(np.random.default_rng(seed), n_cameras=n_cameras, n_points=n_points, noise_px=noise_px,
                      outlier_fraction=outlier_fraction)


def _perturb(sc, seed, rot_deg=1.0, trans=0.2, pts=0.2):
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    R, t = sc.R_cw.copy(), sc.t_cw.copy()
    for i in range(1, sc.n_cameras):
        R[i] = Rotation.from_rotvec(np.radians(rot_deg) * rng.normal(size=3) / np.sqrt(3)).as_matrix() @ R[i]
        t[i] = t[i] + rng.normal(0, trans, 3)
    return R, t, sc.X + rng.normal(0, pts, sc.X.shape)


@builds(FIXTURE)
def _build() -> dict[str, np.ndarray]:
    from course_lib.sfm import bundle_adjustment as ba
    from course_lib.sfm import visibility as vis

    out: dict[str, np.ndarray] = {}
    # visibility: a small synthetic case (more points than cameras, so a transpose shows)
    sc = _scene(51, 4, 30, 0.5, 0.0)
    out["vis_track_uv"] = sc.uv
    out["vis_expected"] = vis.visibility_matrix(sc.uv)

    # residuals: a perturbed synthetic scene (rotation vectors of every size, skew-free K)
    sc = _scene(52, 4, 40, 0.5, 0.0)
    R0, t0, X0 = _perturb(sc, 53, rot_deg=5.0)
    obs = vis.observation_list(sc.uv)
    p = ba.pack_params(R0, t0, X0)
    out.update({"res_syn_params": p, "res_syn_M": np.array(4), "res_syn_N": np.array(40),
                "res_syn_camera_idx": obs.camera_idx, "res_syn_point_idx": obs.point_idx, "res_syn_uv": obs.uv,
                "res_syn_K": sc.K,
                "res_syn_expected": ba.reprojection_residuals(p, 4, 40, obs.camera_idx, obs.point_idx, obs.uv, sc.K)})
    # the true parameters and the noiseless pixels: residuals vanish
    obs_t = vis.observation_list(sc.uv_true)
    out.update({"res_true_params": ba.pack_params(sc.R_cw, sc.t_cw, sc.X), "res_true_camera_idx": obs_t.camera_idx,
                "res_true_point_idx": obs_t.point_idx, "res_true_uv": obs_t.uv})

    # sparsity
    sc = _scene(54, 3, 12, 0.5, 0.0)
    obs = vis.observation_list(sc.uv)
    S = ba.jacobian_sparsity(3, 12, obs.camera_idx, obs.point_idx)
    out.update({"sp_M": np.array(3), "sp_N": np.array(12), "sp_camera_idx": obs.camera_idx,
                "sp_point_idx": obs.point_idx, "sp_expected": S.toarray().astype(bool)})

    # bundle adjustment: a synthetic scene, well conditioned so that any correct solver is quick
    sc = _scene(55, 5, 150, 0.5, 0.0)
    R0, t0, X0 = _perturb(sc, 56, rot_deg=0.5, trans=0.05, pts=0.05)
    res = ba.bundle_adjust(sc.K, R0, t0, X0, sc.uv)
    out.update({"ba_K": sc.K, "ba_R0": R0, "ba_t0": t0, "ba_X0": X0, "ba_uv": sc.uv, "ba_R_true": sc.R_cw,
                "ba_t_true": sc.t_cw, "ba_X_true": sc.X, "ba_R": res.R_cw, "ba_t": res.t_cw, "ba_X": res.X,
                "ba_final_rms": np.array(res.final_rms), "ba_initial_rms": np.array(res.initial_rms)})
    # the embedded reconstruction before BA (notebook 05's starting point) as a case of its own
    if (EMBEDDED_SFM / "ground_truth.json").exists():
        st = reconstruction_before_ba(EMBEDDED_SFM)
        out.update({f"emb_{k}": st[k] for k in ("K", "registered", "R_cw", "t_cw", "X", "track_uv", "inlier")})
    return out

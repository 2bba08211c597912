"""Cases of notebook 04 (PnP), and notebook 04's step input.

Built from :mod:`course_lib.sfm.pnp` (fixtures ``pnp`` and ``pnp_step``); the checks are in
:mod:`course_lib.checks.pnp`.
"""

from __future__ import annotations

import numpy as np

from course_lib.checks.pnp import FIXTURE, RANSAC_SEED, THRESHOLD_PX
from course_lib.instructor.cases import builds
from course_lib.paths import EMBEDDED_SFM
from course_lib.steps import two_view_reconstruction

@builds("pnp_step", step=True)
def _build_step() -> dict[str, np.ndarray]:
    if not (EMBEDDED_SFM / "ground_truth.json").exists():
        return {}  # the embedded scene is not generated yet (python -m course_lib make-data): nothing to store
    out = two_view_reconstruction(EMBEDDED_SFM)
    if (EMBEDDED_SFM / "ground_truth.json").exists():
        from course_lib.data.building import load_ground_truth

        _, _, R_cw, t_cw = load_ground_truth(EMBEDDED_SFM)
        i, j = (int(v) for v in out["pair"])
        k = int(out["new_image"])
        scale = np.linalg.norm(t_cw[j] - R_cw[j] @ R_cw[i].T @ t_cw[i])  # the true baseline of the pair
        R = R_cw[k] @ R_cw[i].T
        out["true_R_cw_new"] = R
        out["true_t_cw_new"] = (t_cw[k] - R @ t_cw[i]) / scale
    return out


def _view(seed, noise_px, outlier_fraction, n_points, image=2):
    from course_lib.data.synthetic import make_scene

    sc = make_scene(np.random.default_rng(seed), n_cameras=4, n_points=n_points, noise_px=noise_px,
                    outlier_fraction=outlier_fraction)
    vis = sc.visible[:, image]
    return sc.K, sc.X[vis], sc.uv[vis, image], sc.outlier[vis, image], sc.R_cw[image], sc.t_cw[image]


def _pixel_dlt(X, x):
    """A typical mistake: the DLT on pixel coordinates, then R = orthogonalized P[:, :3] (kept for its answer)."""
    from course_lib.sfm import pnp

    return pnp.pnp_linear(X, x, np.eye(3))  # K = I: the DLT runs on the pixels themselves


@builds(FIXTURE)
def _build() -> dict[str, np.ndarray]:
    from course_lib.sfm import pnp

    out: dict[str, np.ndarray] = {}
    # pnp_linear: noiseless, noisy
    K, X, x, _, R, t = _view(41, 0.0, 0.0, 80)
    out.update({"lin_noiseless_K": K, "lin_noiseless_X": X[:40], "lin_noiseless_x": x[:40],
                "lin_noiseless_R": R, "lin_noiseless_t": t})
    K, X, x, _, R, t = _view(42, 1.0, 0.0, 200)
    Rr, tr = pnp.pnp_linear(X, x, K)
    Rp, tp = _pixel_dlt(X, x)
    out.update({"lin_noisy_K": K, "lin_noisy_X": X, "lin_noisy_x": x, "lin_noisy_R": Rr, "lin_noisy_t": tr,
                "lin_noisy_true_R": R, "lin_noisy_true_t": t, "lin_noisy_pixel_R": Rp, "lin_noisy_pixel_t": tp})
    # pnp_ransac: outliers
    K, X, x, outl, R, t = _view(43, 0.3, 0.2, 400)
    res = pnp.pnp_ransac(X, x, K, np.random.default_rng(RANSAC_SEED), threshold_px=THRESHOLD_PX)
    out.update({"ransac_syn_K": K, "ransac_syn_X": X, "ransac_syn_x": x, "ransac_syn_outlier": outl,
                "ransac_syn_true_R": R, "ransac_syn_true_t": t, "ransac_syn_R": res.R_cw, "ransac_syn_t": res.t_cw,
                "ransac_syn_inliers": res.inliers})
    # pnp_nonlinear: from the linear estimate on the inliers
    K, X, x, _, R, t = _view(44, 1.0, 0.0, 200)
    R0, t0 = pnp.pnp_linear(X, x, K)
    R1, t1 = pnp.pnp_nonlinear(X, x, K, R0, t0)
    out.update({"nl_syn_K": K, "nl_syn_X": X, "nl_syn_x": x, "nl_syn_R0": R0, "nl_syn_t0": t0, "nl_syn_R": R1, "nl_syn_t": t1,
                "nl_syn_true_R": R, "nl_syn_true_t": t})
    # the embedded scene: register the new image against step 3's reconstruction
    if (EMBEDDED_SFM / "ground_truth.json").exists():
        st = two_view_reconstruction(EMBEDDED_SFM)
        K, X, x = st["K"], st["X_new"], st["x_new"]
        res = pnp.pnp_ransac(X, x, K, np.random.default_rng(RANSAC_SEED), threshold_px=THRESHOLD_PX)
        out.update({"ransac_embedded_K": K, "ransac_embedded_X": X, "ransac_embedded_x": x,
                    "ransac_embedded_R": res.R_cw, "ransac_embedded_t": res.t_cw, "ransac_embedded_inliers": res.inliers})
        Xi, xi = X[res.inliers], x[res.inliers]
        Rl, tl = pnp.pnp_linear(Xi, xi, K)
        out.update({"lin_embedded_K": K, "lin_embedded_X": Xi, "lin_embedded_x": xi, "lin_embedded_R": Rl, "lin_embedded_t": tl})
        R1, t1 = pnp.pnp_nonlinear(Xi, xi, K, Rl, tl)
        out.update({"nl_embedded_K": K, "nl_embedded_X": Xi, "nl_embedded_x": xi, "nl_embedded_R0": Rl, "nl_embedded_t0": tl,
                    "nl_embedded_R": R1, "nl_embedded_t": t1})
    return out

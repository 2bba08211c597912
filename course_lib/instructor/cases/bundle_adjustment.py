"""Cases of notebook 05 (visibility, reprojection residuals, Jacobian sparsity, bundle adjustment), and its step input.

Built from :mod:`course_lib.sfm.bundle_adjustment` and :mod:`course_lib.sfm.visibility`
(fixtures ``bundle_adjustment`` and ``bundle_adjustment_step``); the checks are in
:mod:`course_lib.checks.bundle_adjustment`. Every case is drawn from a seeded generator (salted at
grading time, see :mod:`course_lib.instructor.hidden`), the embedded reconstruction's included: a
random subset of its points, in random order, in a world frame moved by a random similarity. The
residuals of the classic mistakes that the check names (R transposed, no division by the depth,
the points first in the parameter vector, ...) are computed here, on the instructor's side, and
stored with the cases: the shipped checks hold no implementation of the residuals.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from course_lib.checks.bundle_adjustment import FIXTURE, RESIDUAL_VARIANTS
from course_lib.data.synthetic import make_scene
from course_lib.instructor.cases import builds, store
from course_lib.paths import EMBEDDED_SFM
from course_lib.sfm import bundle_adjustment as ba
from course_lib.sfm import visibility as vis
from course_lib.starting_points import reconstruction_before_ba


@builds("bundle_adjustment_step", step=True)
def _build_step() -> dict[str, np.ndarray]:
    return reconstruction_before_ba(EMBEDDED_SFM)


def _scene(seed, n_cameras, n_points, noise_px, outlier_fraction):
    return make_scene(np.random.default_rng(seed), n_cameras=n_cameras, n_points=n_points, noise_px=noise_px,
                      outlier_fraction=outlier_fraction)


def _perturb(sc, seed, rot_deg=1.0, trans=0.2, pts=0.2):
    rng = np.random.default_rng(seed)
    R, t = sc.R_cw.copy(), sc.t_cw.copy()
    for i in range(1, sc.n_cameras):
        R[i] = Rotation.from_rotvec(np.radians(rot_deg) * rng.normal(size=3) / np.sqrt(3)).as_matrix() @ R[i]
        t[i] = t[i] + rng.normal(0, trans, 3)
    return R, t, sc.X + rng.normal(0, pts, sc.X.shape)


def residual_variant(name, params, M, N, cam, pt, uv, K) -> np.ndarray:
    """The residuals of a classic mistake (``name`` in :data:`RESIDUAL_VARIANTS`), for the check to recognise."""
    if name == "points_first":
        X, cams = params[: 3 * N].reshape(N, 3), params[3 * N:].reshape(M, 6)
    else:
        cams, X = params[: 6 * M].reshape(M, 6), params[6 * M:].reshape(N, 3)
    R = Rotation.from_rotvec(cams[:, :3]).as_matrix().reshape(M, 3, 3)
    if name == "euler":
        R = Rotation.from_euler("xyz", cams[:, :3]).as_matrix().reshape(M, 3, 3)
    if name == "R_transposed":
        R = np.transpose(R, (0, 2, 1))
    xc = np.einsum("kij,kj->ki", R[cam], X[pt]) + cams[cam, 3:]
    xh = xc @ (np.eye(3) if name == "no_K" else np.asarray(K, float)).T
    proj = xh[:, :2] if name == "no_depth" else xh[:, :2] / xh[:, 2:3]
    r = proj - uv
    return r.T.ravel() if name == "not_interleaved" else r.ravel()


def _moved_reconstruction(seed: int, keep: float = 0.8) -> dict[str, np.ndarray]:
    """The embedded reconstruction before BA: a random subset of its points in random order, the world moved by a similarity.

    Returns:
        ``K, R_cw (M, 3, 3), t_cw (M, 3), X (N, 3), uv (N, M, 2)`` (the inlier observations, NaN elsewhere).
    """
    st = reconstruction_before_ba(EMBEDDED_SFM)
    reg, has_X = st["registered"], np.isfinite(st["X"]).all(axis=1)
    uv = np.where(st["inlier"][..., None], st["track_uv"], np.nan)[has_X][:, reg]
    X, R, t = st["X"][has_X], st["R_cw"][reg], st["t_cw"][reg]
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(X))[: int(round(keep * len(X)))]
    Rs = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    s, T = float(np.exp(rng.uniform(-0.7, 0.7))), rng.normal(0.0, 2.0, 3)
    R_new = R @ Rs.T  # x_cam' = s x_cam = R Rsᵀ (X' - T) + s t  with X' = s Rs X + T
    t_new = s * t - np.einsum("mij,j->mi", R_new, T)
    return {"K": st["K"], "R_cw": R_new, "t_cw": t_new, "X": s * X[order] @ Rs.T + T, "uv": uv[order],
            "track_uv": st["track_uv"][rng.permutation(len(st["track_uv"]))]}


def _residual_cases(out, ba, vis) -> None:
    # a perturbed synthetic scene (rotation vectors of every size, skew-free K), the mistakes' residuals
    sc = _scene(52, 4, 40, 0.5, 0.0)
    R0, t0, X0 = _perturb(sc, 53, rot_deg=5.0)
    obs = vis.observation_list(sc.uv)
    p = ba.pack_params(R0, t0, X0)
    args = (p, 4, 40, obs.camera_idx, obs.point_idx, obs.uv, sc.K)
    store(out, "res_syn", params=p, M=np.array(4), N=np.array(40), camera_idx=obs.camera_idx,
          point_idx=obs.point_idx, uv=obs.uv, K=sc.K, expected=ba.reprojection_residuals(*args))
    store(out, "res_syn_var", **{name: residual_variant(name, *args) for name in RESIDUAL_VARIANTS})
    # the true parameters and the noiseless pixels: residuals vanish
    obs_t = vis.observation_list(sc.uv_true)
    store(out, "res_true", params=ba.pack_params(sc.R_cw, sc.t_cw, sc.X), camera_idx=obs_t.camera_idx,
          point_idx=obs_t.point_idx, uv=obs_t.uv)


def _sparsity_cases(out, ba, vis) -> None:
    sc = _scene(54, 3, 12, 0.5, 0.0)
    obs = vis.observation_list(sc.uv)
    S = ba.jacobian_sparsity(3, 12, obs.camera_idx, obs.point_idx)
    store(out, "sp", M=np.array(3), N=np.array(12), camera_idx=obs.camera_idx, point_idx=obs.point_idx,
          expected=S.toarray().astype(bool))
    # the observations in random order (not point by point), more cameras than in the first case
    sc = _scene(57, 5, 9, 0.5, 0.0)
    obs = vis.observation_list(sc.uv)
    order = np.random.default_rng(58).permutation(len(obs.camera_idx))
    cam, pt = obs.camera_idx[order], obs.point_idx[order]
    store(out, "sp2", M=np.array(5), N=np.array(9), camera_idx=cam, point_idx=pt,
          expected=ba.jacobian_sparsity(5, 9, cam, pt).toarray().astype(bool))


def _ba_case(out, ba) -> None:
    """A synthetic scene a few degrees off: a solve stopped after 3 evaluations is far from the minimum."""
    sc = _scene(55, 5, 150, 0.5, 0.0)
    R0, t0, X0 = _perturb(sc, 56, rot_deg=3.0, trans=0.3, pts=0.3)
    res = ba.bundle_adjust(sc.K, R0, t0, X0, sc.uv, ftol=1e-14, xtol=1e-14, max_iterations=200)  # the optimum
    store(out, "ba", K=sc.K, R0=R0, t0=t0, X0=X0, uv=sc.uv, R=res.R_cw, t=res.t_cw, X=res.X,
          final_cost=np.array(0.5 * float(np.sum(res.final_errors**2))),
          initial_cost=np.array(0.5 * float(np.sum(res.initial_errors**2))))
    # the minima of the robust losses a student may pick (their plain cost 0.5 Σ r², for the check to name them)
    for loss in ("soft_l1", "huber", "cauchy"):
        rob = ba.bundle_adjust(sc.K, R0, t0, X0, sc.uv, loss=loss, ftol=1e-14, xtol=1e-14, max_iterations=200)
        out[f"ba_mis_{loss}_cost"] = np.array(0.5 * float(np.sum(rob.final_errors**2)))


@builds(FIXTURE)
def _build() -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    # visibility: a small synthetic case (more points than cameras, so a transpose shows)
    sc = _scene(51, 4, 30, 0.5, 0.0)
    uv = sc.uv.copy()
    # observations at the left and top edges: a pixel at u <= 0 or v <= 0 is seen all the same
    seen = np.argwhere(np.isfinite(uv[..., 0]))
    pick = seen[np.random.default_rng(151).choice(len(seen), 4, replace=False)]
    for (j, i), (u, v) in zip(pick, ((0.0, 120.0), (-0.4, 300.5), (210.0, 0.0), (-0.3, -0.2))):
        uv[j, i] = (u, v)
    out["vis_track_uv"] = uv
    out["vis_expected"] = vis.visibility_matrix(uv)
    _residual_cases(out, ba, vis)
    _sparsity_cases(out, ba, vis)
    _ba_case(out, ba)
    # the embedded reconstruction before BA (notebook 05's starting point), moved and subsampled
    if (EMBEDDED_SFM / "ground_truth.json").exists():
        st = _moved_reconstruction(59)
        out["emb_track_uv"] = st["track_uv"]
        out["emb_visible"] = vis.visibility_matrix(st["track_uv"])
        obs = vis.observation_list(st["uv"])
        M, N = len(st["R_cw"]), len(st["X"])
        p = ba.pack_params(st["R_cw"], st["t_cw"], st["X"])
        store(out, "emb", params=p, M=np.array(M), N=np.array(N), camera_idx=obs.camera_idx, point_idx=obs.point_idx,
              uv=obs.uv, K=st["K"],
              expected=ba.reprojection_residuals(p, M, N, obs.camera_idx, obs.point_idx, obs.uv, st["K"]))
    return out

"""Cases of notebook 04 (PnP), and notebook 04's step input.

Built from :mod:`course_lib.sfm.pnp` (fixtures ``pnp`` and ``pnp_step``); the checks are in
:mod:`course_lib.checks.pnp`. Every case is drawn from a seeded generator (salted at grading time,
see :mod:`course_lib.instructor.hidden`), the embedded scene's included: its world frame is moved
by a random similarity and its correspondences are a random subset in random order, so no hidden
input equals a public one. The results of classic mistakes that the checks recognise (a pose
refined over the 9 entries of R and projected back with an SVD, ...) are computed here, on the
instructor's side, and stored with the cases: the shipped checks hold no implementation.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from course_lib.checks.pnp import FIXTURE, RANSAC_SEED, THRESHOLD_PX
from course_lib.conventions import fix_sign
from course_lib.data.building import load_ground_truth
from course_lib.data.synthetic import make_scene
from course_lib.instructor.cases import builds
from course_lib.paths import EMBEDDED_SFM
from course_lib.sfm import pnp
from course_lib.starting_points import two_view_reconstruction

#: The threshold of the threshold case (pixels): its noise (1 px) puts many inliers between sqrt(3) and 3 px.
THRESHOLD_CASE_PX = 3.0


@builds("pnp_step", step=True)
def _build_step() -> dict[str, np.ndarray]:
    out = two_view_reconstruction(EMBEDDED_SFM)
    _, _, R_cw, t_cw = load_ground_truth(EMBEDDED_SFM)
    i, j = (int(v) for v in out["pair"])
    k = int(out["new_image"])
    scale = np.linalg.norm(t_cw[j] - R_cw[j] @ R_cw[i].T @ t_cw[i])  # the true baseline of the pair
    R = R_cw[k] @ R_cw[i].T
    out["true_R_cw_new"] = R
    out["true_t_cw_new"] = (t_cw[k] - R @ t_cw[i]) / scale
    return out


def _view(seed, noise_px, outlier_fraction, n_points, image=2):
    sc = make_scene(np.random.default_rng(seed), n_cameras=4, n_points=n_points, noise_px=noise_px,
                    outlier_fraction=outlier_fraction)
    vis = sc.visible[:, image]
    return sc.K, sc.X[vis], sc.uv[vis, image], sc.outlier[vis, image], sc.R_cw[image], sc.t_cw[image]


def _moved_embedded(seed: int, keep: float = 0.85):
    """The embedded scene's 2D-3D matches, world frame moved by a random similarity, a random subset in random order.

    Returns:
        ``K (3, 3), X (N', 3), x (N', 2)``.
    """
    st = two_view_reconstruction(EMBEDDED_SFM)
    K, X, x = st["K"], st["X_new"], st["x_new"]
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(X))[: int(round(keep * len(X)))]
    Rs = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    s = float(np.exp(rng.uniform(-0.7, 0.7)))
    T = rng.normal(0.0, 2.0, 3)
    return K, s * X[order] @ Rs.T + T, x[order].copy()


def _pixel_dlt(X, x):
    """A typical mistake: the DLT on pixel coordinates, then R = orthogonalized P[:, :3] (kept for its answer)."""
    return pnp.pnp_linear(X, x, np.eye(3))  # K = I: the DLT runs on the pixels themselves


def _nine_entries_then_svd(X, x, K, R0, t0):
    """A classic near miss of pnp_nonlinear: least squares over the 9 entries of R and t, then R = U Vᵀ."""
    def res(p):
        xc = X @ p[:9].reshape(3, 3).T + p[9:]
        xh = xc @ K.T
        return (xh[:, :2] / xh[:, 2:] - x).ravel()

    p = least_squares(res, np.concatenate([R0.ravel(), t0]), method="trf", x_scale="jac").x
    U, _, Vt = np.linalg.svd(p[:9].reshape(3, 3))
    R = U @ Vt
    return R * np.sign(np.linalg.det(R)), p[9:]


def _no_depth_division(X, x, K, R0, t0):
    """A classic mistake of pnp_nonlinear: the residual (K (R X + t))[:2] - x, never divided by the depth."""
    def res(p):
        return ((X @ Rotation.from_rotvec(p[:3]).as_matrix().T + p[3:]) @ K.T)[:, :2].ravel() - x.ravel()

    p = least_squares(res, np.concatenate([Rotation.from_matrix(R0).as_rotvec(), t0])).x
    return Rotation.from_rotvec(p[:3]).as_matrix(), p[3:]


def _nonlinear_case(out, key, K, X, x, R0, t0) -> None:
    R1, t1 = pnp.pnp_nonlinear(X, x, K, R0, t0)
    Rn, tn = _nine_entries_then_svd(X, x, K, R0, t0)
    Rd, td = _no_depth_division(X, x, K, R0, t0)
    # Both mistakes leave t free: the 9 entries and t scale together, so t's length is wherever the
    # solver stopped (only its direction is stored, sign fixed); without the division by depth t runs
    # off and even its direction is where the last bits of the CPU leave it (only R is stored).
    out.update({f"{key}_K": K, f"{key}_X": X, f"{key}_x": x, f"{key}_R0": R0, f"{key}_t0": t0,
                f"{key}_R": R1, f"{key}_t": t1, f"{key}_mis_nine_R": Rn, f"{key}_mis_nine_tdir": _direction(tn),
                f"{key}_mis_nodepth_R": Rd})


def _direction(t: np.ndarray) -> np.ndarray:
    return fix_sign(t / np.linalg.norm(t))


def _perturbed(R, t, seed, deg=3.0, rel=0.05):
    """A start for pnp_nonlinear away from the optimum: R rotated by ``deg`` degrees, t moved by ``rel`` of |t|."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    dR = Rotation.from_rotvec(np.radians(deg) * axis / np.linalg.norm(axis)).as_matrix()
    return dR @ R, t + rel * np.linalg.norm(t) * rng.normal(size=3) / np.sqrt(3)


def _with_behind(X, x, outl, R, t, seed: int, n: int = 8):
    """The matches with ``n`` more: points behind the camera that project exactly onto the pixel of an inlier.

    Such a point (on the ray through the camera centre, on the other side) reprojects with no error, so
    only a cheirality test (depth > 0) rejects it; they are outliers, at random rows. Returns
    ``(X, x, outlier, behind)``.
    """
    g = np.random.default_rng(seed)
    C = -R.T @ t
    src = g.choice(np.flatnonzero(~outl), n, replace=False)
    Xb = C - g.uniform(0.5, 1.5, (n, 1)) * (X[src] - C)
    rows = np.sort(g.choice(len(X) + n, n, replace=False))
    keep = np.setdiff1d(np.arange(len(X) + n), rows)
    X2, x2 = np.empty((len(X) + n, 3)), np.empty((len(X) + n, 2))
    o2, b2 = np.zeros(len(X) + n, bool), np.zeros(len(X) + n, bool)
    X2[keep], x2[keep], o2[keep] = X, x, outl
    X2[rows], x2[rows], o2[rows], b2[rows] = Xb, x[src], True, True
    return X2, x2, o2, b2


def _ransac_cases(out) -> None:
    # outliers: the pose, the inliers, the refit (its RMS over the true inliers)
    K, X, x, outl, R, t = _view(43, 0.3, 0.2, 400)
    X, x, outl, behind = _with_behind(X, x, outl, R, t, 143)
    res = pnp.pnp_ransac(X, x, K, np.random.default_rng(RANSAC_SEED), threshold_px=THRESHOLD_PX)
    out.update({"ransac_syn_K": K, "ransac_syn_X": X, "ransac_syn_x": x, "ransac_syn_outlier": outl,
                "ransac_syn_behind": behind,
                "ransac_syn_true_R": R, "ransac_syn_true_t": t, "ransac_syn_R": res.R_cw, "ransac_syn_t": res.t_cw,
                "ransac_syn_inliers": res.inliers, "ransac_syn_noise": np.array(0.3)})
    # the threshold in pixels: 1 px noise, threshold 3 px
    K, X, x, outl, R, t = _view(45, 1.0, 0.1, 300)
    res = pnp.pnp_ransac(X, x, K, np.random.default_rng(RANSAC_SEED), threshold_px=THRESHOLD_CASE_PX)
    out.update({"ransac_thr_K": K, "ransac_thr_X": X, "ransac_thr_x": x, "ransac_thr_outlier": outl,
                "ransac_thr_R": res.R_cw, "ransac_thr_t": res.t_cw, "ransac_thr_inliers": res.inliers,
                "ransac_thr_threshold": np.array(THRESHOLD_CASE_PX)})
    # the rng: noise comparable to the threshold, a few samples per call (max_iters=3)
    K, X, x, _, _, _ = _view(46, 1.0, 0.0, 200)
    out.update({"ransac_rng_K": K, "ransac_rng_X": X, "ransac_rng_x": x})


@builds(FIXTURE)
def _build() -> dict[str, np.ndarray]:
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
    _ransac_cases(out)
    # pnp_nonlinear: from the linear estimate, and from a start a few degrees away
    K, X, x, _, R, t = _view(44, 1.0, 0.0, 200)
    R0, t0 = pnp.pnp_linear(X, x, K)
    _nonlinear_case(out, "nl_syn", K, X, x, R0, t0)
    out.update({"nl_syn_true_R": R, "nl_syn_true_t": t})
    K, X, x, _, R, t = _view(47, 1.0, 0.0, 150)
    _nonlinear_case(out, "nl_far", K, X, x, *_perturbed(R, t, 48))
    # the embedded scene (world frame moved, a subset): register the new image against step 3's reconstruction
    if (EMBEDDED_SFM / "ground_truth.json").exists():
        K, X, x = _moved_embedded(49)
        res = pnp.pnp_ransac(X, x, K, np.random.default_rng(RANSAC_SEED), threshold_px=THRESHOLD_PX)
        out.update({"ransac_embedded_K": K, "ransac_embedded_X": X, "ransac_embedded_x": x,
                    "ransac_embedded_R": res.R_cw, "ransac_embedded_t": res.t_cw, "ransac_embedded_inliers": res.inliers})
        Xi, xi = X[res.inliers], x[res.inliers]
        Rl, tl = pnp.pnp_linear(Xi, xi, K)
        out.update({"lin_embedded_K": K, "lin_embedded_X": Xi, "lin_embedded_x": xi, "lin_embedded_R": Rl, "lin_embedded_t": tl})
        _nonlinear_case(out, "nl_embedded", K, Xi, xi, Rl, tl)
    return out

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
from course_lib.instructor.cases import builds, store
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
    store(out, key, K=K, X=X, x=x, R0=R0, t0=t0, R=R1, t=t1, mis_nine_R=Rn, mis_nine_tdir=_direction(tn),
          mis_nodepth_R=Rd)


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
    ``(X, x, outlier)``.
    """
    g = np.random.default_rng(seed)
    C = -R.T @ t
    src = g.choice(np.flatnonzero(~outl), n, replace=False)
    Xb = C - g.uniform(0.5, 1.5, (n, 1)) * (X[src] - C)
    rows = np.sort(g.choice(len(X) + n, n, replace=False))
    keep = np.setdiff1d(np.arange(len(X) + n), rows)
    X2, x2 = np.empty((len(X) + n, 3)), np.empty((len(X) + n, 2))
    o2 = np.zeros(len(X) + n, bool)
    X2[keep], x2[keep], o2[keep] = X, x, outl
    X2[rows], x2[rows], o2[rows] = Xb, x[src], True
    return X2, x2, o2


def _ransac_cases(out) -> None:
    # outliers: the pose, the inliers, the refit (its RMS over the true inliers)
    K, X, x, outl, R, t = _view(43, 0.3, 0.2, 400)
    X, x, outl = _with_behind(X, x, outl, R, t, 143)
    res = pnp.pnp_ransac(X, x, K, np.random.default_rng(RANSAC_SEED), threshold_px=THRESHOLD_PX)
    store(out, "ransac_syn", K=K, X=X, x=x, outlier=outl, R=res.R_cw, t=res.t_cw, inliers=res.inliers,
          noise=np.array(0.3))
    # the threshold in pixels: 1 px noise, threshold 3 px
    K, X, x, outl, R, t = _view(45, 1.0, 0.1, 300)
    res = pnp.pnp_ransac(X, x, K, np.random.default_rng(RANSAC_SEED), threshold_px=THRESHOLD_CASE_PX)
    store(out, "ransac_thr", K=K, X=X, x=x, outlier=outl, R=res.R_cw, t=res.t_cw, inliers=res.inliers,
          threshold=np.array(THRESHOLD_CASE_PX))
    # the rng: noise comparable to the threshold, a few samples per call (max_iters=3)
    K, X, x, _, _, _ = _view(46, 1.0, 0.0, 200)
    store(out, "ransac_rng", K=K, X=X, x=x)


@builds(FIXTURE)
def _build() -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    # pnp_linear: noiseless, noisy
    K, X, x, _, R, t = _view(41, 0.0, 0.0, 80)
    store(out, "lin_noiseless", K=K, X=X[:40], x=x[:40], R=R, t=t)
    K, X, x, _, R, t = _view(42, 1.0, 0.0, 200)
    Rr, tr = pnp.pnp_linear(X, x, K)
    store(out, "lin_noisy", K=K, X=X, x=x, R=Rr, t=tr, true_R=R)
    _ransac_cases(out)
    # pnp_nonlinear: from the linear estimate, and from a start a few degrees away
    K, X, x, _, _, _ = _view(44, 1.0, 0.0, 200)
    R0, t0 = pnp.pnp_linear(X, x, K)
    _nonlinear_case(out, "nl_syn", K, X, x, R0, t0)
    K, X, x, _, R, t = _view(47, 1.0, 0.0, 150)
    _nonlinear_case(out, "nl_far", K, X, x, *_perturbed(R, t, 48))
    # the embedded scene (world frame moved, a subset): register the new image against step 3's reconstruction
    if (EMBEDDED_SFM / "ground_truth.json").exists():
        K, X, x = _moved_embedded(49)
        res = pnp.pnp_ransac(X, x, K, np.random.default_rng(RANSAC_SEED), threshold_px=THRESHOLD_PX)
        store(out, "ransac_embedded", K=K, X=X, x=x, R=res.R_cw, t=res.t_cw, inliers=res.inliers)
        Xi, xi = X[res.inliers], x[res.inliers]
        Rl, tl = pnp.pnp_linear(Xi, xi, K)
        store(out, "lin_embedded", K=K, X=Xi, x=xi, R=Rl, t=tl)
        _nonlinear_case(out, "nl_embedded", K, Xi, xi, Rl, tl)
    return out

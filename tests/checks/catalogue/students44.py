"""Mistakes written as students write them, from the released stubs and docstrings only, before reading the checks.

Written for issue 44 (batch ``"44"``): 44 first attempts across every exercise (one of them, the visibility
matrix tested with u or v, judged correct by hand and kept in ``HONEST``), each a plausible slip of a
student who read the notebook's text, not a mistake chosen because a check names it. Earlier exercises
are called through the reference (as the grader's hidden checks feed every exercise the reference's
earlier steps). :mod:`tests.checks.test_mistakes` requires each to be caught and never confidently
misnamed; whether the verdict names it is measured (``python -m tests.checks.test_mistakes``) and
judged by hand, not required.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from course_lib.checks import bundle_adjustment as gba
from course_lib.checks import essential as ges
from course_lib.checks import fundamental as gfu
from course_lib.checks import nerf_data as gnd
from course_lib.checks import nerf_model as gnm
from course_lib.checks import nerf_rendering as gnr
from course_lib.checks import pnp as gpn
from course_lib.checks import triangulation as gtr
from course_lib.nerf import encoding as renc
from course_lib.nerf import rays as rrays
from course_lib.nerf import render as rrender
from course_lib.sfm import bundle_adjustment as rba
from course_lib.sfm import essential as res
from course_lib.sfm import fundamental as rfu
from course_lib.sfm import pnp as rpn
from course_lib.sfm import triangulation as rtr
from tests.checks.catalogue import Honest, Mistake, _h, _torch

# ============================================================================ 01: the fundamental matrix


def normalize_sqrt2_per_point(x):  # every point scaled to distance sqrt(2), not the mean
    c = x.mean(0)
    d = np.linalg.norm(x - c, axis=1, keepdims=True)
    xn = (x - c) * np.sqrt(2) / d
    s = np.sqrt(2) / d.mean()
    T = np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1.0]])
    return xn, T


def normalize_median(x):  # the median distance instead of the mean
    c = x.mean(0)
    s = np.sqrt(2) / np.median(np.linalg.norm(x - c, axis=1))
    T = np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1.0]])
    return (x - c) * s, T


def eight_point_no_transpose_of_T1(x1, x2):  # denormalizes with T2 F T1 (no transpose)
    x1n, T1 = rfu.normalize_points(x1)
    x2n, T2 = rfu.normalize_points(x2)
    A = np.column_stack([x2n[:, 0:1] * _h(x1n), x2n[:, 1:2] * _h(x1n), _h(x1n)])
    F = np.linalg.svd(A)[2][-1].reshape(3, 3)
    U, s, Vt = np.linalg.svd(F)
    F = U @ np.diag([s[0], s[1], 0]) @ Vt
    return T2 @ F @ T1


def eight_point_eigh_largest(x1, x2):  # eigenvector of AᵀA with the LARGEST eigenvalue (eigh sorts ascending)
    x1n, T1 = rfu.normalize_points(x1)
    x2n, T2 = rfu.normalize_points(x2)
    A = np.column_stack([x2n[:, 0:1] * _h(x1n), x2n[:, 1:2] * _h(x1n), _h(x1n)])
    w, V = np.linalg.eigh(A.T @ A)
    F = V[:, -1].reshape(3, 3)
    U, s, Vt = np.linalg.svd(F)
    F = U @ np.diag([s[0], s[1], 0]) @ Vt
    return T2.T @ F @ T1


def sampson_no_sqrt(F, x1, x2):  # the Sampson error (squared pixels) without the square root
    h1, h2 = _h(x1), _h(x2)
    Fx1 = h1 @ F.T
    Ftx2 = h2 @ F
    num = np.sum(h2 * Fx1, axis=1) ** 2
    den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    return num / den


def sampson_third_component(F, x1, x2):  # the denominator sums all three components of each line
    h1, h2 = _h(x1), _h(x2)
    Fx1 = h1 @ F.T
    Ftx2 = h2 @ F
    num = np.abs(np.sum(h2 * Fx1, axis=1))
    den = np.sqrt(np.sum(Fx1 ** 2, axis=1) + np.sum(Ftx2 ** 2, axis=1))
    return num / den


def _ransac(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000, *, log=np.log, replace=False,
            refit_all=False, ge=False, stop_first=False, sample=8):
    n = len(x1)
    best, n_iters, need = None, 0, max_iters
    while n_iters < min(need, max_iters):
        idx = rng.choice(n, sample, replace=replace)
        n_iters += 1
        try:
            F = rfu.eight_point(x1[idx], x2[idx])
        except Exception:  # noqa: BLE001 - a degenerate sample
            continue
        d = rfu.sampson_distance(F, x1, x2)
        inl = d <= threshold_px if ge else d < threshold_px
        if best is None or inl.sum() > best.sum():
            best = inl
            w = inl.mean()
            if w >= 1:
                need = 0
            elif w > 0:
                need = math.ceil(log(1 - confidence) / log(1 - w ** 8))
            if stop_first and w > 0.5:
                break
    use = np.ones(n, bool) if refit_all else best
    F = rfu.eight_point(x1[use], x2[use])
    inl = rfu.sampson_distance(F, x1, x2) < threshold_px
    return rfu.RansacResult(F=F, inliers=inl, n_iters=n_iters, distances=rfu.sampson_distance(F, x1, x2))


def ransac_log10(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):  # log10 on one side only
    return _ransac(x1, x2, rng, threshold_px, confidence, max_iters,
                   log=lambda v: np.log10(v) if v < 1 - confidence + 1e-12 else np.log(v))


def ransac_with_replacement(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    return _ransac(x1, x2, rng, threshold_px, confidence, max_iters, replace=True)


def ransac_refit_on_all(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):  # final fit on all matches
    return _ransac(x1, x2, rng, threshold_px, confidence, max_iters, refit_all=True)


def ransac_stop_at_half(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):  # stops at 50 % inliers
    return _ransac(x1, x2, rng, threshold_px, confidence, max_iters, stop_first=True)


def essential_no_svd(F, K):  # just Kᵀ F K
    return K.T @ F @ K


def essential_K_inverse(F, K):  # K⁻¹ F K⁻ᵀ remembered from "F = K⁻ᵀ E K⁻¹"
    E = np.linalg.inv(K) @ F @ np.linalg.inv(K).T
    U, _, Vt = np.linalg.svd(E)
    return U @ np.diag([1.0, 1.0, 0.0]) @ Vt


def pose_candidates_same_C(E):  # C = U[:, 2] for all four (no sign change)
    R, C = res.pose_candidates(E)
    return R, np.array([C[0], C[0], C[0], C[0]])


def pose_candidates_only_W(E):  # U W Vᵀ twice, forgetting Wᵀ
    U, _, Vt = np.linalg.svd(E)
    W = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    Rs, Cs = [], []
    for R, c in ((U @ W @ Vt, U[:, 2]), (U @ W @ Vt, -U[:, 2]), (U @ W @ Vt, U[:, 2]), (U @ W @ Vt, -U[:, 2])):
        if np.linalg.det(R) < 0:
            R, c = -R, -c
        Rs.append(R)
        Cs.append(c)
    return np.array(Rs), np.array(Cs)


# ============================================================================ 03: triangulation


def triangulate_linear_normalized_rows(P1, P2, x1, x2):  # drops the last column of Vt (takes the first)
    out = []
    for a, b in zip(x1, x2):
        A = np.stack([a[0] * P1[2] - P1[0], a[1] * P1[2] - P1[1], b[0] * P2[2] - P2[0], b[1] * P2[2] - P2[1]])
        Xh = np.linalg.svd(A)[2][0]
        out.append(Xh[:3] / Xh[3])
    return np.array(out)


def choose_pose_t_minus_Rt_C(R, C, K, x1, x2):  # t = -Rᵀ C (choice and counts right)
    ch = rtr.choose_pose(R, C, K, x1, x2)
    k = int(np.argmax(ch.counts))
    return rtr.PoseChoice(R_cw=ch.R_cw, t_cw=-R[k].T @ C[k], X=ch.X, in_front=ch.in_front, counts=ch.counts)


def choose_pose_depth_cam2_by_C(R, C, K, x1, x2):  # cheirality in camera 2 as r3 · X > 0 (forgets the centre)
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    counts, sols = [], []
    for k in range(4):
        t = -R[k] @ C[k]
        X = rtr.triangulate_linear(P1, K @ np.hstack([R[k], t[:, None]]), x1, x2)
        front = (X[:, 2] > 0) & (X @ R[k][2] > 0)
        counts.append(int(front.sum()))
        sols.append((R[k], t, X, front))
    k = int(np.argmax(counts))
    R_, t_, X_, f_ = sols[k]
    return rtr.PoseChoice(R_cw=R_, t_cw=t_, X=X_, in_front=f_, counts=np.array(counts))


def triangulate_nonlinear_no_iterations(K, R_cws, t_cws, uv, X0, max_nfev=50):  # max_nfev=1
    return rtr.triangulate_nonlinear(K, R_cws, t_cws, uv, X0, max_nfev=1)


def triangulate_nonlinear_wrong_sign(K, R_cws, t_cws, uv, X0, max_nfev=50):  # residual observed - projected, squared
    X = np.array(X0, float, copy=True)
    for j in range(len(X)):
        seen = ~np.isnan(uv[j, :, 0])
        if seen.sum() < 2:
            continue

        def r(p, j=j, seen=seen):
            xc = np.einsum("mij,j->mi", R_cws[seen], p) + t_cws[seen]
            pr = xc @ K.T
            return ((uv[j, seen] - pr[:, :2] / pr[:, 2:]) ** 2).ravel()

        X[j] = least_squares(r, X[j], max_nfev=max_nfev).x
    return X


# ============================================================================ 04: PnP


def pnp_linear_no_K(X, x, K):  # DLT on pixels, P taken as [R | t] directly
    A = []
    for Xi, (u, v) in zip(X, x):
        Xh = np.append(Xi, 1.0)
        A.append(np.concatenate([Xh, np.zeros(4), -u * Xh]))
        A.append(np.concatenate([np.zeros(4), Xh, -v * Xh]))
    P = np.linalg.svd(np.array(A))[2][-1].reshape(3, 4)
    U, s, Vt = np.linalg.svd(P[:, :3])
    R = U @ Vt
    t = P[:, 3] / s[0]
    if np.linalg.det(R) < 0:
        R, t = -R, -t
    return R, t


def pnp_linear_scale_by_last(X, x, K):  # scale from P[2, 3] (the depth of the origin) instead of sigma
    R, t = rpn.pnp_linear(X, x, K)
    return R, t / np.abs(t[2]) * np.linalg.norm(t) if abs(t[2]) > 1e-9 else t * 2


def _pnp_ransac(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000, *, inverted=False, replace=False,
                log=np.log, refit_all=False):
    n = len(X)
    best, n_iters, need = np.zeros(n, bool), 0, max_iters
    while n_iters < min(need, max_iters):
        idx = rng.choice(n, 6, replace=replace)
        n_iters += 1
        try:
            R, t = rpn.pnp_linear(X[idx], x[idx], K)
        except Exception:  # noqa: BLE001
            continue
        xc = X @ R.T + t
        pr = xc @ K.T
        err = np.linalg.norm(pr[:, :2] / pr[:, 2:] - x, axis=1)
        inl = (err < threshold_px) & (xc[:, 2] > 0)
        if inverted:
            inl = ~inl
        if inl.sum() > best.sum():
            best = inl
            w = inl.mean()
            need = 0 if w >= 1 else math.ceil(log(1 - confidence) / log(1 - w ** 6))
    use = np.ones(n, bool) if refit_all else best
    R, t = rpn.pnp_linear(X[use], x[use], K)
    return rpn.PnPResult(R_cw=R, t_cw=t, inliers=best, n_iters=n_iters)


def pnp_ransac_refit_all(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    return _pnp_ransac(X, x, K, rng, threshold_px, confidence, max_iters, refit_all=True)


def pnp_ransac_replacement(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    return _pnp_ransac(X, x, K, rng, threshold_px, confidence, max_iters, replace=True)


def pnp_ransac_log10(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):  # log10(1-p) / ln(1-w^6)
    return _pnp_ransac(X, x, K, rng, threshold_px, confidence, max_iters,
                       log=lambda v: np.log10(v) if v < 1 - confidence + 1e-12 else np.log(v))


def pnp_nonlinear_mixed_euler(X, x, K, R_cw, t_cw):  # optimizes intrinsic 'XYZ' angles, returns them read as extrinsic 'xyz'
    def r(p):
        R = Rotation.from_euler("XYZ", p[:3]).as_matrix()
        pr = (X @ R.T + p[3:]) @ K.T
        return (pr[:, :2] / pr[:, 2:] - x).ravel()

    p0 = np.concatenate([Rotation.from_matrix(R_cw).as_euler("XYZ"), t_cw])
    p = least_squares(r, p0).x
    return Rotation.from_euler("xyz", p[:3]).as_matrix(), p[3:]


def pnp_nonlinear_max_nfev_3(X, x, K, R_cw, t_cw):  # stops the optimiser early "to be fast"
    def r(p):
        R = Rotation.from_rotvec(p[:3]).as_matrix()
        pr = (X @ R.T + p[3:]) @ K.T
        return (pr[:, :2] / pr[:, 2:] - x).ravel()

    p0 = np.concatenate([Rotation.from_matrix(R_cw).as_rotvec(), t_cw])
    p = least_squares(r, p0, max_nfev=3).x
    return Rotation.from_rotvec(p[:3]).as_matrix(), p[3:]


# ============================================================================ 05: bundle adjustment


def visibility_isfinite_any(track_uv):  # seen where u OR v is a number
    """Judged by hand: no mistake. The stub's track_uv holds NaN in both u and v where a point is not seen (the kit's
    loaders refuse one NaN coordinate), so "u or v is a number" and "u and v are numbers" are the same test; it is
    graded as a valid variant (HONEST below), not as a mistake."""
    return np.isfinite(track_uv).any(axis=-1)


def residuals_mixed_euler(params, n_cameras, n_points, camera_idx, point_idx, uv, K):  # rotvec read as Euler angles
    cams = params[: 6 * n_cameras].reshape(n_cameras, 6)
    X = params[6 * n_cameras:].reshape(n_points, 3)
    R = Rotation.from_euler("xyz", cams[:, :3]).as_matrix()
    xc = np.einsum("kij,kj->ki", R[camera_idx], X[point_idx]) + cams[camera_idx, 3:]
    pr = xc @ K.T
    return (pr[:, :2] / pr[:, 2:] - uv).ravel()


def residuals_norm_per_observation(params, n_cameras, n_points, camera_idx, point_idx, uv, K):  # (K,) distances
    r = rba.reprojection_residuals(params, n_cameras, n_points, camera_idx, point_idx, uv, K).reshape(-1, 2)
    return np.repeat(np.linalg.norm(r, axis=1), 2)


def sparsity_point_cols_3i(n_cameras, n_points, camera_idx, point_idx):  # point columns at 6M + point_idx (no * 3)
    import scipy.sparse as sp

    k = len(camera_idx)
    A = sp.lil_matrix((2 * k, 6 * n_cameras + 3 * n_points), dtype=int)
    for i, (c, p) in enumerate(zip(camera_idx, point_idx)):
        for row in (2 * i, 2 * i + 1):
            A[row, 6 * c:6 * c + 6] = 1
            A[row, 6 * n_cameras + p:6 * n_cameras + p + 3] = 1
    return A.tocsr()


# ============================================================================ 06: NeRF data and rays


def get_rays_c2w_as_point(H, W, K, c2w):  # the direction pushed through c2w as a point (rotation + translation)
    torch = _torch()
    K = torch.as_tensor(K, dtype=torch.float32)
    c2w = torch.as_tensor(c2w, dtype=torch.float32)
    j, i = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    d = torch.stack([(i + 0.5 - K[0, 2]) / K[0, 0], (j + 0.5 - K[1, 2]) / K[1, 1], torch.ones_like(i)], -1)
    rays_d = d @ c2w[:3, :3].T + c2w[:3, 3]
    rays_o = c2w[:3, 3].expand(rays_d.shape)
    return rays_o, rays_d


def get_rays_no_half_pixel_and_gl(H, W, K, c2w):  # Blender's y-up, z-back camera (the notebook says OpenCV)
    torch = _torch()
    K = torch.as_tensor(K, dtype=torch.float32)
    c2w = torch.as_tensor(c2w, dtype=torch.float32)
    j, i = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    d = torch.stack([(i + 0.5 - K[0, 2]) / K[0, 0], -(j + 0.5 - K[1, 2]) / K[1, 1], -torch.ones_like(i)], -1)
    rays_d = d @ c2w[:3, :3].T
    return c2w[:3, 3].expand(rays_d.shape), rays_d


def stratified_with_replacement(near, far, n_samples, n_rays, perturb, generator=None, device=None,
                                dtype=None):  # uniform depths drawn independently (with replacement), then sorted
    torch = _torch()
    dtype = dtype or torch.float32
    if not perturb:
        return rrays.stratified_samples(near, far, n_samples, n_rays, perturb, generator, device, dtype)
    u = torch.rand(n_rays, n_samples, generator=generator, device=device, dtype=dtype)
    z = near + (far - near) * u
    return torch.sort(z, dim=-1).values


def stratified_linspace_n_plus_1(near, far, n_samples, n_rays, perturb, generator=None, device=None,
                                 dtype=None):  # bins from linspace(near, far, n_samples) -> the last bin past far
    torch = _torch()
    dtype = dtype or torch.float32
    t = torch.linspace(0, 1, n_samples, device=device, dtype=dtype)
    z = (near + (far - near) * t).expand(n_rays, n_samples).clone()
    if perturb:
        z = z + (far - near) / n_samples * torch.rand(n_rays, n_samples, generator=generator, device=device,
                                                      dtype=dtype)
    return z


def encoding_degrees(x, n_freqs, include_input=True):  # 2^k without pi, in "degrees" of a turn
    torch = _torch()
    parts = [x] if include_input else []
    for k in range(n_freqs):
        parts += [torch.sin(2.0 ** k * x * 2), torch.cos(2.0 ** k * x * 2)]
    return torch.cat(parts, -1)


def encoding_interleaved_per_coord(x, n_freqs, include_input=True):  # per coordinate: sin, cos for every frequency
    torch = _torch()
    f = (2.0 ** torch.arange(n_freqs, dtype=x.dtype, device=x.device)) * math.pi
    xf = x[..., :, None] * f  # (..., 3, L)
    enc = torch.stack([torch.sin(xf), torch.cos(xf)], -1).reshape(*x.shape[:-1], -1)
    return torch.cat([x, enc], -1) if include_input else enc


# ============================================================================ 07: the NeRF model


def _nerf_class(**flags):
    torch = _torch()
    nn = torch.nn

    class StudentNeRF(nn.Module):
        def __init__(self, depth=8, width=256, skips=(4,), pos_freqs=10, dir_freqs=4, use_viewdirs=True,
                     view_width=128, density="relu"):
            super().__init__()
            if flags.get("ignore_viewdirs_flag"):
                use_viewdirs = True
            self.pos_freqs, self.dir_freqs, self.skips, self.use_viewdirs = pos_freqs, dir_freqs, tuple(skips), use_viewdirs
            n_pts, n_dirs = 3 + 6 * pos_freqs, 3 + 6 * dir_freqs
            layers, n_in = [], n_pts
            for i in range(depth):
                layers.append(nn.Linear(n_in, width))
                n_in = width + (n_pts if i in self.skips else 0)
            self.trunk = nn.ModuleList(layers)
            self.sigma = nn.Linear(n_in, 1)
            if use_viewdirs:
                self.feature = nn.Linear(n_in, width)
                self.view = nn.Linear(width + n_dirs, view_width)
                self.rgb = nn.Linear(view_width, 3)
            else:
                self.rgb = nn.Linear(n_in, 3)

        def forward(self, pts, viewdirs=None):
            x = renc.positional_encoding(pts, self.pos_freqs)
            h = x
            for i, layer in enumerate(self.trunk):
                h = torch.relu(layer(h))
                if i in self.skips:
                    h = torch.cat([x, h], -1)
            raw = self.sigma(h)[..., 0]
            sigma = torch.abs(raw) if flags.get("abs_density") else torch.relu(raw)
            if self.use_viewdirs:
                d = viewdirs if viewdirs is not None else torch.zeros_like(pts)
                e = renc.positional_encoding(d, self.dir_freqs)
                h = torch.relu(self.view(torch.cat([self.feature(h), e], -1)))
            rgb = self.rgb(h)
            rgb = torch.clamp(rgb, 0, 1) if flags.get("clamp_rgb") else torch.sigmoid(rgb)
            return rgb, sigma

    StudentNeRF.__name__ = "NeRF"
    return StudentNeRF


NeRF_ignores_use_viewdirs = _nerf_class(ignore_viewdirs_flag=True)
NeRF_abs_density = _nerf_class(abs_density=True)
NeRF_clamped_rgb = _nerf_class(clamp_rgb=True)


def psnr_big_epsilon(mse):  # "avoid log(0)": an epsilon as large as a good model's MSE
    torch = _torch()
    return -10.0 * torch.log10(torch.as_tensor(mse) + 1e-3)


def psnr_log_base_e_times_10_over_ln10_wrong(mse):  # -10 * ln(mse) / ln(2)
    torch = _torch()
    return -10.0 * torch.log(torch.as_tensor(mse)) / math.log(2)


# ============================================================================ 08: volume rendering


def render_alpha_from_sigma_only(rgb, sigma, z_vals, rays_d, white_background=True):  # alpha = 1 - exp(-sigma), and |d| ignored
    torch = _torch()
    delta = torch.cat([z_vals[:, 1:] - z_vals[:, :-1], torch.full_like(z_vals[:, :1], 1e10)], -1)
    alpha = 1 - torch.exp(-torch.relu(sigma) * delta.clamp(max=1.0))
    T = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1] + 1e-10], -1), -1)
    w = alpha * T
    rgb_map = (w[..., None] * rgb).sum(1)
    acc = w.sum(1)
    if white_background:
        rgb_map = rgb_map + (1 - acc[:, None])
    return dict(rgb_map=rgb_map, depth_map=(w * z_vals).sum(1), acc_map=acc, weights=w, transmittance=T, alpha=alpha)


def render_background_always_white(rgb, sigma, z_vals, rays_d, white_background=True):  # ignores the flag
    out = rrender.volume_render(rgb, sigma, z_vals, rays_d, white_background=True)
    return out


def render_depth_unweighted_mean(rgb, sigma, z_vals, rays_d, white_background=True):  # depth = mean of z_vals
    out = dict(rrender.volume_render(rgb, sigma, z_vals, rays_d, white_background))
    out["depth_map"] = z_vals.mean(1)
    return out


# ============================================================================ the catalogue

M = Mistake


def _m(exercise, name, check, fn, names, defining=None):
    return M(exercise, name, check, fn, names, defining, batch="44")


MISTAKES = [
    _m("normalize_points", "every point scaled to distance sqrt(2)", gfu.check_normalize_points,
       normalize_sqrt2_per_point, ("each point",)),
    _m("normalize_points", "median distance", gfu.check_normalize_points, normalize_median, ("mean distance",)),
    _m("eight_point", "denormalized T2 F T1 (no transpose)", gfu.check_eight_point, eight_point_no_transpose_of_T1,
       ("transpose",)),
    _m("eight_point", "eigenvector of the largest eigenvalue", gfu.check_eight_point, eight_point_eigh_largest,
       ("smallest",)),
    _m("sampson_distance", "no square root", gfu.check_sampson_distance, sampson_no_sqrt, ("square root",)),
    _m("sampson_distance", "third components in the denominator", gfu.check_sampson_distance, sampson_third_component,
       ("first two",)),
    _m("ransac_fundamental", "log10 for ln in the iteration count", gfu.check_ransac_fundamental, ransac_log10,
       ("log",)),
    _m("ransac_fundamental", "samples drawn with replacement", gfu.check_ransac_fundamental, ransac_with_replacement,
       ("replace",)),
    _m("ransac_fundamental", "final refit on all points", gfu.check_ransac_fundamental, ransac_refit_on_all,
       ("refit",)),
    _m("ransac_fundamental", "stops at the first sample with half inliers", gfu.check_ransac_fundamental,
       ransac_stop_at_half, ("iteration",)),
    _m("essential_from_fundamental", "Kᵀ F K without the SVD step", ges.check_essential_from_fundamental,
       essential_no_svd, ("singular values",)),
    _m("essential_from_fundamental", "K⁻¹ F K⁻ᵀ", ges.check_essential_from_fundamental, essential_K_inverse,
       ("kᵀ f k",)),
    _m("pose_candidates", "the same C for all four", ges.check_pose_candidates, pose_candidates_same_C, ("-c",)),
    _m("pose_candidates", "only U W Vᵀ (no Wᵀ)", ges.check_pose_candidates, pose_candidates_only_W, ("wᵀ",)),
    _m("triangulate_linear", "first row of Vt", gtr.check_triangulate_linear, triangulate_linear_normalized_rows,
       ("largest singular value",)),
    _m("choose_pose", "t = -Rᵀ C", gtr.check_choose_pose, choose_pose_t_minus_Rt_C, ("-r_cwᵀ @ c",)),
    _m("choose_pose", "cheirality r3 · X > 0 in camera 2", gtr.check_choose_pose, choose_pose_depth_cam2_by_C,
       ("centre",)),
    _m("triangulate_nonlinear", "optimiser stopped after one evaluation", gtr.check_triangulate_nonlinear,
       triangulate_nonlinear_no_iterations, ("max_nfev",)),
    _m("triangulate_nonlinear", "squared residuals given to least_squares", gtr.check_triangulate_nonlinear,
       triangulate_nonlinear_wrong_sign, ("squared",)),
    _m("pnp_linear", "DLT without K", gpn.check_pnp_linear, pnp_linear_no_K, ("k⁻¹",)),
    _m("pnp_linear", "t scaled by its depth", gpn.check_pnp_linear, pnp_linear_scale_by_last, ("scale",)),
    _m("pnp_ransac", "final refit on all points", gpn.check_pnp_ransac, pnp_ransac_refit_all, ("refit",)),
    _m("pnp_ransac", "samples drawn with replacement", gpn.check_pnp_ransac, pnp_ransac_replacement, ("replace",)),
    _m("pnp_ransac", "log10 for ln in the iteration count", gpn.check_pnp_ransac, pnp_ransac_log10, ("log",)),
    _m("pnp_nonlinear", "mixed Euler convention", gpn.check_pnp_nonlinear, pnp_nonlinear_mixed_euler, ("euler",)),
    _m("pnp_nonlinear", "optimiser stopped after 3 evaluations", gpn.check_pnp_nonlinear, pnp_nonlinear_max_nfev_3,
       ("max_nfev",)),
    _m("reprojection_residuals", "rotation vector read as Euler angles", gba.check_reprojection_residuals,
       residuals_mixed_euler, ("rotation vector",)),
    _m("reprojection_residuals", "one distance per observation, repeated", gba.check_reprojection_residuals,
       residuals_norm_per_observation, ("u and v",)),
    _m("jacobian_sparsity", "point columns 6M + j (no 3j)", gba.check_jacobian_sparsity, sparsity_point_cols_3i,
       ("3",)),
    _m("get_rays", "direction pushed through c2w as a point", gnd.check_get_rays, get_rays_c2w_as_point,
       ("translation",)),
    _m("get_rays", "Blender camera axes", gnd.check_get_rays, get_rays_no_half_pixel_and_gl, ("opengl",)),
    _m("stratified_samples", "uniform samples with replacement, sorted", gnd.check_stratified_samples,
       stratified_with_replacement, ("bin",)),
    _m("stratified_samples", "linspace of n_samples: last bin past far", gnd.check_stratified_samples,
       stratified_linspace_n_plus_1, ("far",)),
    _m("positional_encoding", "2 instead of pi", gnd.check_positional_encoding, encoding_degrees, ("π",)),
    _m("positional_encoding", "interleaved per coordinate", gnd.check_positional_encoding,
       encoding_interleaved_per_coord, ("order",)),
    _m("NeRF", "use_viewdirs=False ignored", gnm.check_nerf_model, NeRF_ignores_use_viewdirs, ("use_viewdirs",)),
    _m("NeRF", "abs on the density", gnm.check_nerf_model, NeRF_abs_density, ("relu",)),
    _m("NeRF", "rgb clamped instead of sigmoid", gnm.check_nerf_model, NeRF_clamped_rgb, ("sigmoid",)),
    _m("psnr", "epsilon 1e-3 added to the MSE", gnm.check_psnr, psnr_big_epsilon, ("epsilon",)),
    _m("psnr", "log base 2", gnm.check_psnr, psnr_log_base_e_times_10_over_ln10_wrong, ("log10",)),
    _m("volume_render", "Δ clamped to 1 (no 1e10 last interval)", gnr.check_volume_render,
       render_alpha_from_sigma_only, ("δ",)),
    _m("volume_render", "white background ignores the flag", gnr.check_volume_render, render_background_always_white,
       ("white_background",)),
    _m("volume_render", "depth as the mean of z_vals", gnr.check_volume_render, render_depth_unweighted_mean,
       ("weights",)),
]

#: Attempts of this batch that turned out correct when judged by hand: they must score full marks.
HONEST = [
    Honest("visibility_matrix", "seen where u or v is a number (NaN comes in both or neither)",
           gba.check_visibility_matrix, visibility_isfinite_any),
]

"""Notebook 08, volume rendering: the literal student's exercise."""

import torch


def volume_render(rgb, sigma, z_vals, rays_d, white_background=True):
    """Composite the samples along each ray (the NeRF quadrature).

    Args:
        rgb: (R, S, 3) tensor, colours c_i in [0, 1].
        sigma: (R, S) tensor, densities sigma_i >= 0.
        z_vals: (R, S) tensor, sorted sample depths t_i.
        rays_d: (R, 3) tensor, ray directions (not normalized): delta_i = (t_{i+1} - t_i) * |d|,
            the last delta_S = 1e10.
        white_background: add (1 - acc_map) to rgb_map (white behind the scene).

    Returns:
        dict with
            "rgb_map": (R, 3) sum_i w_i c_i (+ 1 - acc_map on white),
            "depth_map": (R,) sum_i w_i t_i,
            "acc_map": (R,) sum_i w_i,
            "weights": (R, S) w_i = T_i alpha_i, alpha_i = 1 - exp(-sigma_i delta_i),
                       T_i = prod_{j<i} (1 - alpha_j) (exclusive: T_1 = 1).
    """
    delta = (z_vals[:, 1:] - z_vals[:, :-1]) * torch.linalg.norm(rays_d, dim=-1, keepdim=True)
    delta = torch.cat([delta, torch.full_like(z_vals[:, :1], 1e10)], dim=1)   # the last interval: 1e10
    alpha = 1 - torch.exp(-sigma * delta)
    T = torch.cumprod(1 - alpha, dim=1)
    T = torch.cat([torch.ones_like(T[:, :1]), T[:, :-1]], dim=1)               # exclusive: T_1 = 1
    weights = T * alpha
    rgb_map = torch.sum(weights[..., None] * rgb, dim=1)
    depth_map = torch.sum(weights * z_vals, dim=1)
    acc_map = torch.sum(weights, dim=1)
    if white_background:
        rgb_map = rgb_map + (1 - acc_map[:, None])
    return {"rgb_map": rgb_map, "depth_map": depth_map, "acc_map": acc_map, "weights": weights}

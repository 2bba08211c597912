"""Notebook 06, NeRF data, rays and positional encoding: the literal student's exercises.

Written to the types the stubs document and nothing more: ``get_rays`` computes in the dtype and on
the device of ``K`` (a float tensor, as its stub says), ``stratified_samples`` takes ``near`` and
``far`` as floats or as ``(R,)`` tensors (the contract of issue 28: the fast preset's per-ray
bounds), draws its jitter from the ``generator`` it is given, and returns float32 for float bounds.
"""

import math

import torch


def get_rays(H, W, K, c2w):
    """One ray per pixel through the pixel centres, in the kit's OpenCV camera axes.

    Args:
        H: image height in pixels (int).
        W: image width in pixels (int).
        K: (3, 3) float tensor, the intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels.
        c2w: (4, 4) float tensor, camera-to-world in OpenCV axes (x right, y down, z forward):
            c2w[:3, :3] rotates camera directions into the world, c2w[:3, 3] is the camera centre.

    Returns:
        rays_o: (H, W, 3) tensor, the camera centre repeated for every pixel.
        rays_d: (H, W, 3) tensor, world directions, NOT normalized:
            rays_d[v, u] = c2w[:3, :3] @ [(u - cx) / fx, (v - cy) / fy, 1] for pixel (u, v) = (column, row).
    """
    u = torch.arange(W, dtype=K.dtype, device=K.device)
    v = torch.arange(H, dtype=K.dtype, device=K.device)
    uu, vv = torch.meshgrid(u, v, indexing="xy")          # (H, W) each: uu[row, col] = col
    d_cam = torch.stack([(uu - K[0, 2]) / K[0, 0],
                         (vv - K[1, 2]) / K[1, 1],
                         torch.ones_like(uu)], dim=-1)     # (H, W, 3)
    rays_d = d_cam @ c2w[:3, :3].T
    rays_o = c2w[:3, 3].expand(rays_d.shape)
    return rays_o, rays_d


def stratified_samples(near, far, n_samples, n_rays, perturb, generator=None):
    """Depths of n_samples points per ray between near and far.

    Args:
        near, far: floats, the depth interval [near, far].
        n_samples: S >= 2 samples per ray.
        n_rays: R, the number of rays.
        perturb: False (evaluation): the evenly spaced depths torch.linspace(near, far, S), the same for
            every ray. True (training): one uniform sample inside each bin; the bins' edges are the
            midpoints between the evenly spaced depths (near and far at the ends); independent for
            every ray and sample.
        generator: torch.Generator for the uniform numbers (None: torch's global one).

    Returns:
        z_vals: (R, S) float32 tensor, sorted along each ray.
    """
    if isinstance(near, torch.Tensor):   # per-ray bounds, (R,) tensors
        t = torch.linspace(0, 1, n_samples, dtype=near.dtype, device=near.device)
        z_vals = near[:, None] + (far - near)[:, None] * t
    else:
        z_vals = torch.linspace(near, far, n_samples).expand(n_rays, n_samples)
    if perturb:
        mids = 0.5 * (z_vals[:, 1:] + z_vals[:, :-1])
        upper = torch.cat([mids, z_vals[:, -1:]], dim=1)
        lower = torch.cat([z_vals[:, :1], mids], dim=1)
        u = torch.rand(z_vals.shape, generator=generator, dtype=z_vals.dtype, device=z_vals.device)
        z_vals = lower + (upper - lower) * u
    return z_vals


def query_points(rays_o, rays_d, z_vals):
    """The sample points pts[r, s] = rays_o[r] + z_vals[r, s] * rays_d[r].

    Args:
        rays_o: (R, 3) tensor of ray origins.
        rays_d: (R, 3) tensor of ray directions (as from get_rays, not normalized).
        z_vals: (R, S) tensor of depths.

    Returns:
        pts: (R, S, 3) tensor of world points.
    """
    return rays_o[:, None, :] + z_vals[:, :, None] * rays_d[:, None, :]


def positional_encoding(x, n_freqs, include_input=True):
    """NeRF's gamma applied to every coordinate, identity term first.

    Args:
        x: (..., D) tensor (positions, D = 3, or unit viewing directions).
        n_freqs: L, the number of frequencies 2^0 pi, 2^1 pi, ..., 2^(L-1) pi.
        include_input: put x itself first (the identity term).

    Returns:
        (..., D * (include_input + 2 L)) tensor:
        [x, sin(2^0 pi x), cos(2^0 pi x), sin(2^1 pi x), cos(2^1 pi x), ..., cos(2^(L-1) pi x)],
        each sin / cos block holding the D coordinates, concatenated along the last axis.
    """
    parts = [x] if include_input else []
    for k in range(n_freqs):
        parts.append(torch.sin(2.0 ** k * math.pi * x))
        parts.append(torch.cos(2.0 ** k * math.pi * x))
    return torch.cat(parts, dim=-1)

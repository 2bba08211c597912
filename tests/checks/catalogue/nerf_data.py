"""Notebook 06 (NeRF data, rays, encoding): classic mistakes, honest solutions and trivial answers, run through its checks."""

from __future__ import annotations

import numpy as np

from course_lib.checks import nerf_data as gnd
from tests.checks.catalogue import Mistake, _torch

# ============================================================================ buggy versions
# Each is written as a student would write it (often the reference with one line changed).

# -- 06: get_rays, stratified_samples, query_points, positional_encoding ----------------------------------
def get_rays_opengl(H, W, K, c2w):
    torch = _torch()
    K = torch.as_tensor(K, dtype=torch.float32)
    c2w = torch.as_tensor(c2w, dtype=torch.float32)
    u, v = torch.meshgrid(torch.arange(W, dtype=torch.float32), torch.arange(H, dtype=torch.float32), indexing="xy")
    d = torch.stack([(u - K[0, 2]) / K[0, 0], -(v - K[1, 2]) / K[1, 1], -torch.ones_like(u)], -1)
    rays_d = d @ c2w[:3, :3].T
    return c2w[:3, 3].expand(rays_d.shape), rays_d


def get_rays_ij(H, W, K, c2w):
    from course_lib.nerf.rays import get_rays

    o, d = get_rays(H, W, K, c2w)  # as with torch.meshgrid(arange(W), arange(H), indexing="ij"): (W, H, 3)
    return o.transpose(0, 1), d.transpose(0, 1)


def stratified_no_jitter(near, far, n_samples, n_rays, perturb, generator=None):
    torch = _torch()
    return torch.linspace(near, far, n_samples).expand(n_rays, n_samples).clone()


def stratified_wide_jitter(near, far, n_samples, n_rays, perturb, generator=None):
    torch = _torch()
    z = torch.linspace(near, far, n_samples).expand(n_rays, n_samples).clone()
    if perturb:
        z = z + (torch.rand(n_rays, n_samples, generator=generator) - 0.5) * (far - near) * 0.3
    return z


def stratified_same_jitter(near, far, n_samples, n_rays, perturb, generator=None):
    from course_lib.nerf.rays import stratified_samples

    torch = _torch()
    z = stratified_samples(near, far, n_samples, 1, perturb, generator=generator)
    return z.expand(n_rays, n_samples).clone() if perturb else torch.linspace(near, far, n_samples).expand(
        n_rays, n_samples).clone()


def query_swapped(rays_o, rays_d, z_vals):
    return rays_d[:, None, :] + z_vals[..., None] * rays_o[:, None, :]


def query_no_origin(rays_o, rays_d, z_vals):
    return z_vals[..., None] * rays_d[:, None, :]


def query_normalized(rays_o, rays_d, z_vals):
    d = rays_d / rays_d.norm(dim=-1, keepdim=True)
    return rays_o[:, None, :] + z_vals[..., None] * d[:, None, :]


def encoding_no_identity(x, n_freqs, include_input=True):
    from course_lib.nerf.encoding import positional_encoding

    return positional_encoding(x, n_freqs, include_input=False)


def encoding_no_pi(x, n_freqs, include_input=True):
    torch = _torch()
    parts = [x] if include_input else []
    for k in range(n_freqs):
        parts += [torch.sin(2.0**k * x), torch.cos(2.0**k * x)]
    return torch.cat(parts, -1)

# ============================================================================ the catalogue

M = Mistake
MISTAKES = [
    M("get_rays", "OpenGL camera axes", gnd.check_get_rays, get_rays_opengl, ("opengl",)),
    M("get_rays", "meshgrid ij", gnd.check_get_rays, get_rays_ij, ("meshgrid",)),
    M("stratified_samples", "no jitter in training", gnd.check_stratified_samples, stratified_no_jitter,
      ("no jitter",)),
    M("stratified_samples", "jitter wider than a bin", gnd.check_stratified_samples, stratified_wide_jitter,
      ("leave their bin",)),
    M("stratified_samples", "one jitter for all rays", gnd.check_stratified_samples, stratified_same_jitter,
      ("the same jitter",)),
    M("query_points", "o and d swapped", gnd.check_query_points, query_swapped, ("swapped",)),
    M("query_points", "origin missing", gnd.check_query_points, query_no_origin, ("rays_o is missing",)),
    M("query_points", "directions normalized", gnd.check_query_points, query_normalized,
      ("directions are normalized",)),
    M("positional_encoding", "no identity term", gnd.check_positional_encoding, encoding_no_identity,
      ("identity term",)),
    M("positional_encoding", "no pi", gnd.check_positional_encoding, encoding_no_pi, ("pi factor",)),
]

#: Correct solutions: they must score full marks.
HONEST = [

]


def _trivial() -> list:
    torch = _torch()
    z = np.zeros  # noqa: F841
    return [
        (gnd.check_get_rays, lambda H, W, K, c2w: (torch.zeros(H, W, 3), torch.zeros(H, W, 3))),
        (gnd.check_stratified_samples, lambda near, far, S, R, perturb, generator=None: torch.zeros(R, S)),
        (gnd.check_query_points, lambda o, d, zv: torch.zeros(*zv.shape, 3)),
        (gnd.check_positional_encoding, lambda x, L, include_input=True: torch.zeros(
            *x.shape[:-1], x.shape[-1] * (int(include_input) + 2 * L))),
    ]


#: Constants of the right shape: they pass the shape gates and trivially satisfied properties, and must earn nothing.
TRIVIAL = _trivial()

"""Notebook 06 (NeRF data, rays, encoding): classic mistakes, honest solutions and trivial answers, run through its checks."""

from __future__ import annotations

import math

import numpy as np
import torch

from course_lib.checks import nerf_data as gnd
from tests.checks.catalogue import Honest, Mistake


# ============================================================================ honest solutions


def get_rays(H, W, K, c2w):
    """Plain code: a pixel grid with meshgrid 'xy', directions (u - cx) / fx, (v - cy) / fy, 1, rotated."""
    u, v = torch.meshgrid(torch.arange(W, dtype=torch.float32), torch.arange(H, dtype=torch.float32), indexing="xy")
    dirs = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], dim=-1)
    rays_d = dirs @ c2w[:3, :3].T
    rays_o = c2w[:3, 3].expand(H, W, 3)
    return rays_o, rays_d


def get_rays__inverse_K(H, W, K, c2w):
    """Homogeneous pixels times K^-1 (meshgrid 'ij' on (v, u)), rotated with einsum."""
    K = torch.as_tensor(K, dtype=torch.float64)
    c2w = torch.as_tensor(c2w, dtype=torch.float64)
    rows, cols = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    pix = torch.stack([cols, rows, torch.ones_like(cols)], dim=-1).double()
    cam = pix @ torch.linalg.inv(K).T
    rays_d = torch.einsum("ij,hwj->hwi", c2w[:3, :3], cam)
    rays_o = torch.broadcast_to(c2w[:3, 3], rays_d.shape).clone()
    return rays_o.float(), rays_d.float()


def stratified_samples(near, far, n_samples, n_rays, perturb, generator=None):
    """Plain code: the kit's bins around the evaluation depths; near and far floats or (R,) tensors (per ray)."""
    near = torch.as_tensor(near, dtype=torch.float32).reshape(-1, 1)
    far = torch.as_tensor(far, dtype=torch.float32).reshape(-1, 1)
    z = (near + (far - near) * torch.linspace(0, 1, n_samples)).expand(n_rays, n_samples)
    if not perturb:
        return z.clone()
    mids = (z[:, 1:] + z[:, :-1]) / 2
    lower = torch.cat([z[:, :1], mids], dim=1)
    upper = torch.cat([mids, z[:, -1:]], dim=1)
    return lower + (upper - lower) * torch.rand(n_rays, n_samples, generator=generator)


def stratified_samples__paper_equal_bins(near, far, n_samples, n_rays, perturb, generator=None):
    """The NeRF paper's equation (2): S equal bins of width (far - near) / S, one uniform sample in each; near and far
    floats or (R,) tensors."""
    near = torch.as_tensor(near, dtype=torch.float32)[..., None]
    far = torch.as_tensor(far, dtype=torch.float32)[..., None]
    if not perturb:
        return (near + (far - near) * torch.linspace(0, 1, n_samples)).expand(n_rays, n_samples).clone()
    width = (far - near) / n_samples
    start = near + width * torch.arange(n_samples, dtype=torch.float32)
    return start + width * torch.rand((n_rays, n_samples), generator=generator)


def query_points(rays_o, rays_d, z_vals):
    return rays_o[:, None, :] + z_vals[:, :, None] * rays_d[:, None, :]


def query_points__einsum_loop(rays_o, rays_d, z_vals):
    """One ray at a time, stacked."""
    return torch.stack([o + torch.einsum("s,c->sc", t, d) for o, d, t in zip(rays_o, rays_d, z_vals)])


def positional_encoding(x, n_freqs, include_input=True):
    """Plain code: a loop over the frequencies."""
    out = [x] if include_input else []
    for k in range(n_freqs):
        out.append(torch.sin(2.0 ** k * math.pi * x))
        out.append(torch.cos(2.0 ** k * math.pi * x))
    return torch.cat(out, dim=-1)


def positional_encoding__vectorised(x, n_freqs, include_input=True):
    """All frequencies at once: (..., L, D) angles, sin and cos stacked per frequency, flattened."""
    freqs = math.pi * 2.0 ** torch.arange(n_freqs, dtype=x.dtype)
    angles = x[..., None, :] * freqs[:, None]
    enc = torch.stack([angles.sin(), angles.cos()], dim=-2).flatten(-3)
    return torch.cat([x, enc], -1) if include_input else enc


# ============================================================================ buggy versions


def _rays(signs=(1, 1, 1), centre=None, offset=0.0, normalize=False, rotate="R", swap_f=False):
    """The plain get_rays above with one thing changed, as a student would get it wrong."""

    def buggy(H, W, K, c2w):
        u, v = torch.meshgrid(torch.arange(W, dtype=torch.float32), torch.arange(H, dtype=torch.float32),
                              indexing="xy")
        cx, cy = (K[0, 2], K[1, 2]) if centre is None else (W / centre, H / centre)
        fx, fy = (K[1, 1], K[0, 0]) if swap_f else (K[0, 0], K[1, 1])
        d = torch.stack([signs[0] * (u + offset - cx) / fx, signs[1] * (v + offset - cy) / fy,
                         signs[2] * torch.ones_like(u)], -1)
        if normalize:
            d = d / d.norm(dim=-1, keepdim=True)
        if rotate == "R":
            d = d @ c2w[:3, :3].T
        elif rotate == "RT":
            d = d @ c2w[:3, :3]
        return c2w[:3, 3].expand(H, W, 3), d

    return buggy


def get_rays_ij(H, W, K, c2w):
    u, v = torch.meshgrid(torch.arange(W, dtype=torch.float32), torch.arange(H, dtype=torch.float32), indexing="ij")
    d = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1) @ c2w[:3, :3].T
    return c2w[:3, 3].expand(d.shape), d


def _strata(jitter="bin", per="all", eval_jitter=False, generator=True, endpoint=True):
    """The plain stratified_samples above with one thing changed."""

    def buggy(near, far, n_samples, n_rays, perturb, generator_=None, **kw):
        gen = kw.get("generator", generator_) if generator else None
        z = (torch.linspace(near, far, n_samples) if endpoint else
             torch.linspace(near, far, n_samples + 1)[:-1]).expand(n_rays, n_samples).clone()
        if not (perturb or eval_jitter) or jitter == "none":
            return z
        shape = (n_rays, n_samples) if per == "all" else (1, n_samples) if per == "sample" else (n_rays, 1)
        u = torch.rand(shape, generator=gen)
        if jitter == "range":
            return z + (u - 0.5) * (far - near) * 0.3
        if jitter == "centred":
            return z + (u - 0.5) * (far - near) / (n_samples - 1)
        mids = (z[:, 1:] + z[:, :-1]) / 2
        lower, upper = torch.cat([z[:, :1], mids], 1), torch.cat([mids, z[:, -1:]], 1)
        return lower + (upper - lower) * (u * 0.5 if jitter == "half" else u)

    def stratified_samples(near, far, n_samples, n_rays, perturb, generator=None):
        return buggy(near, far, n_samples, n_rays, perturb, generator_=generator)

    return stratified_samples


def query_swapped(rays_o, rays_d, z_vals):
    return rays_d[:, None, :] + z_vals[..., None] * rays_o[:, None, :]


def query_no_origin(rays_o, rays_d, z_vals):
    return z_vals[..., None] * rays_d[:, None, :]


def query_normalized(rays_o, rays_d, z_vals):
    d = rays_d / rays_d.norm(dim=-1, keepdim=True)
    return rays_o[:, None, :] + z_vals[..., None] * d[:, None, :]


def query_no_axes(rays_o, rays_d, z_vals):
    return rays_o + z_vals[..., None] * rays_d


def query_wrong_axis(rays_o, rays_d, z_vals):
    return rays_o[None, :, :] + z_vals[..., None] * rays_d[None, :, :]


def _encoding(identity=True, pi=True, order="freq", start=0, linear=False):
    """The plain positional_encoding above with one thing changed."""

    def buggy(x, n_freqs, include_input=True):
        sins, coss, parts = [], [], []
        for k in range(start, start + n_freqs):
            w = (k + 1.0 if linear else 2.0 ** k) * (math.pi if pi else 1.0)
            sins.append(torch.sin(w * x))
            coss.append(torch.cos(w * x))
            parts += [coss[-1], sins[-1]] if order == "cos_first" else [sins[-1], coss[-1]]
        if order == "blocks":
            parts = sins + coss
        if include_input and identity:
            parts = [x] + parts
        return torch.cat(parts, -1)

    return buggy


# ============================================================================ the catalogue

M = Mistake
MISTAKES = [
    M("get_rays", "OpenGL camera axes", gnd.check_get_rays, _rays(signs=(1, -1, -1)), ("opengl",)),
    M("get_rays", "meshgrid ij", gnd.check_get_rays, get_rays_ij, ("meshgrid",)),
    M("get_rays", "rotation transposed", gnd.check_get_rays, _rays(rotate="RT"), ("rotated with the transpose",)),
    M("get_rays", "principal point at W / 2", gnd.check_get_rays, _rays(centre=2.0), ("principal point",)),
    M("get_rays", "half-pixel offset (near miss)", gnd.check_get_rays, _rays(offset=0.5), ("half-pixel",)),
    M("get_rays", "normalized directions (near miss)", gnd.check_get_rays, _rays(normalize=True), ("normalized",)),
    M("get_rays", "fx and fy swapped (near miss)", gnd.check_get_rays, _rays(swap_f=True), ("swapped",)),
    M("stratified_samples", "no jitter in training", gnd.check_stratified_samples, _strata(jitter="none"),
      ("no jitter",)),
    M("stratified_samples", "jitter scaled by far - near", gnd.check_stratified_samples, _strata(jitter="range"),
      ("leave their bin", "far - near"), defining="in their bins"),
    M("stratified_samples", "centred jitter leaves [near, far] (near miss)", gnd.check_stratified_samples,
      _strata(jitter="centred"), ("outside [near, far]",), defining="in their bins"),
    M("stratified_samples", "one jitter for all samples of a ray", gnd.check_stratified_samples, _strata(per="ray"),
      ("the same jitter",)),
    M("stratified_samples", "jitter in evaluation", gnd.check_stratified_samples, _strata(eval_jitter=True),
      ("jitter in evaluation",)),
    M("stratified_samples", "half a bin only (near miss)", gnd.check_stratified_samples, _strata(jitter="half"),
      ("cover only",)),
    M("stratified_samples", "generator ignored", gnd.check_stratified_samples, _strata(generator=False),
      ("generator=generator",)),
    M("stratified_samples", "last depth is not far", gnd.check_stratified_samples, _strata(endpoint=False),
      ("the last depth is not far",)),
    M("query_points", "o and d swapped", gnd.check_query_points, query_swapped, ("swapped",)),
    M("query_points", "origin missing", gnd.check_query_points, query_no_origin, ("rays_o is missing",)),
    M("query_points", "directions normalized", gnd.check_query_points, query_normalized,
      ("directions are normalized",)),
    M("query_points", "no new axes: a broadcasting error", gnd.check_query_points, query_no_axes,
      ("rays_o[:, None, :]",)),
    M("query_points", "rays broadcast along the samples (near miss)", gnd.check_query_points, query_wrong_axis,
      ("broadcast along the samples axis",)),
    M("positional_encoding", "no identity term", gnd.check_positional_encoding, _encoding(identity=False),
      ("identity term",)),
    M("positional_encoding", "no pi", gnd.check_positional_encoding, _encoding(pi=False), ("pi factor",)),
    M("positional_encoding", "cos before sin", gnd.check_positional_encoding, _encoding(order="cos_first"),
      ("cos before sin",)),
    M("positional_encoding", "all sines, then all cosines", gnd.check_positional_encoding, _encoding(order="blocks"),
      ("all sines first",)),
    M("positional_encoding", "frequencies from 2^1 (near miss)", gnd.check_positional_encoding, _encoding(start=1),
      ("wrong frequencies",)),
    M("positional_encoding", "linear frequencies", gnd.check_positional_encoding, _encoding(linear=True),
      ("wrong frequencies (k + 1",)),
]

#: Correct solutions: they must score full marks.
HONEST = [
    Honest("get_rays", "meshgrid xy, plain code", gnd.check_get_rays, get_rays),
    Honest("get_rays", "K^-1 on homogeneous pixels, einsum, float64", gnd.check_get_rays, get_rays__inverse_K),
    Honest("stratified_samples", "the kit's bins", gnd.check_stratified_samples, stratified_samples),
    Honest("stratified_samples", "the paper's equal bins", gnd.check_stratified_samples,
           stratified_samples__paper_equal_bins),
    Honest("query_points", "broadcasting", gnd.check_query_points, query_points),
    Honest("query_points", "one ray at a time, einsum", gnd.check_query_points, query_points__einsum_loop),
    Honest("positional_encoding", "a loop over the frequencies", gnd.check_positional_encoding, positional_encoding),
    Honest("positional_encoding", "vectorised", gnd.check_positional_encoding, positional_encoding__vectorised),
]


def _trivial() -> list:
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


# ============================================================================ issue 29: written as students write them
# From the notebook's text and the stub's docstring, with an error students make; then valid variants in the call
# forms the kit uses later (float32 K and c2w, near/far as floats or (R,) tensors, a generator).

def get_rays_fx_for_both(H, W, K, c2w):  # one focal length for both axes
    f = K[0, 0]
    u, v = torch.meshgrid(torch.arange(W, dtype=torch.float32), torch.arange(H, dtype=torch.float32), indexing="xy")
    d = torch.stack([(u - K[0, 2]) / f, (v - K[1, 2]) / f, torch.ones_like(u)], -1)
    return c2w[:3, 3].expand(H, W, 3), d @ c2w[:3, :3].T


def get_rays_origin_negated(H, W, K, c2w):  # the origin as -t, as for a world-to-camera matrix
    u, v = torch.meshgrid(torch.arange(W, dtype=torch.float32), torch.arange(H, dtype=torch.float32), indexing="xy")
    d = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
    return (-c2w[:3, 3]).expand(H, W, 3), d @ c2w[:3, :3].T


def get_rays_float64(H, W, K, c2w):  # the pixel grid in float64 ("more precise"): float64 rays from float32 inputs
    j, i = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    K, c2w = K.double(), c2w.double()
    d = torch.stack([(i - K[0, 2]) / K[0, 0], (j - K[1, 2]) / K[1, 1], torch.ones_like(i)], -1)
    return c2w[:3, 3].expand(H, W, 3), (d[..., None, :] * c2w[:3, :3]).sum(-1)


def get_rays_numpy(H, W, K, c2w):  # written with numpy: numpy arrays come back, no tensors
    K, c2w = np.asarray(K), np.asarray(c2w)
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, dtype=float)], -1)
    return np.broadcast_to(c2w[:3, 3], (H, W, 3)), d @ c2w[:3, :3].T


def stratified_manual_seed(near, far, n_samples, n_rays, perturb, generator=None):  # seeds torch's global RNG
    z = torch.linspace(near, far, n_samples).expand(n_rays, n_samples)
    if not perturb:
        return z.clone()
    torch.manual_seed(0)
    mids = 0.5 * (z[:, 1:] + z[:, :-1])
    lo, hi = torch.cat([z[:, :1], mids], 1), torch.cat([mids, z[:, -1:]], 1)
    return lo + (hi - lo) * torch.rand(n_rays, n_samples)


def stratified_unstratified(near, far, n_samples, n_rays, perturb, generator=None):  # uniform depths, sorted
    if not perturb:
        return torch.linspace(near, far, n_samples).repeat(n_rays, 1)
    z = near + (far - near) * torch.rand(n_rays, n_samples, generator=generator)
    return torch.sort(z, dim=1).values


def stratified_floats_only(near, far, n_samples, n_rays, perturb, generator=None):  # near, far as Python floats only
    near, far = float(near), float(far)
    z = torch.linspace(near, far, n_samples).expand(n_rays, n_samples)
    if not perturb:
        return z.clone()
    mids = 0.5 * (z[:, 1:] + z[:, :-1])
    lo, hi = torch.cat([z[:, :1], mids], 1), torch.cat([mids, z[:, -1:]], 1)
    return lo + (hi - lo) * torch.rand(n_rays, n_samples, generator=generator)


def stratified_numpy_jitter(near, far, n_samples, n_rays, perturb, generator=None):  # np.random for the jitter
    z = torch.linspace(near, far, n_samples).expand(n_rays, n_samples)
    if not perturb:
        return z.clone()
    mids = 0.5 * (z[:, 1:] + z[:, :-1])
    lo, hi = torch.cat([z[:, :1], mids], 1), torch.cat([mids, z[:, -1:]], 1)
    return lo + (hi - lo) * torch.as_tensor(np.random.uniform(size=(n_rays, n_samples)), dtype=torch.float32)


def stratified_one_jitter_per_sample(near, far, n_samples, n_rays, perturb, generator=None):  # rand(S): all rays alike
    z = torch.linspace(near, far, n_samples).expand(n_rays, n_samples)
    if not perturb:
        return z.clone()
    mids = 0.5 * (z[:, 1:] + z[:, :-1])
    lo, hi = torch.cat([z[:, :1], mids], 1), torch.cat([mids, z[:, -1:]], 1)
    return lo + (hi - lo) * torch.rand(n_samples, generator=generator)


def query_points_samples_first(rays_o, rays_d, z_vals):  # (S, R, 3): the samples axis first
    return rays_o[None] + z_vals.T[..., None] * rays_d[None]


def encoding_include_input_ignored(x, n_freqs, include_input=True):  # x always first
    out = [x]
    for k in range(n_freqs):
        out += [torch.sin(2**k * math.pi * x), torch.cos(2**k * math.pi * x)]
    return torch.cat(out, -1)


def encoding_identity_last(x, n_freqs, include_input=True):  # the identity term appended at the end
    out = []
    for k in range(n_freqs):
        out += [torch.sin(2**k * math.pi * x), torch.cos(2**k * math.pi * x)]
    if include_input:
        out.append(x)
    return torch.cat(out, -1)


def encoding_numpy(x, n_freqs, include_input=True):  # np.sin: a float64 numpy array comes back
    x = np.asarray(x)
    out = [x] if include_input else []
    for k in range(n_freqs):
        out += [np.sin(2**k * np.pi * x), np.cos(2**k * np.pi * x)]
    return np.concatenate(out, axis=-1)


# -- valid variants -----------------------------------------------------------------------------------------------
def get_rays__pixel_grid_matmul(H, W, K, c2w):
    """Homogeneous pixel grid times K⁻¹ᵀ and the rotation's transpose, in K's dtype and device."""
    v, u = torch.meshgrid(torch.arange(H, dtype=K.dtype, device=K.device),
                          torch.arange(W, dtype=K.dtype, device=K.device), indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)], -1)
    d = pix @ torch.linalg.inv(K).T @ c2w[:3, :3].T
    return c2w[:3, 3].expand_as(d), d


def stratified_samples__per_ray_bounds(near, far, n_samples, n_rays, perturb, generator=None):
    """near, far as floats or (R,) tensors: the evenly spaced depths built per ray by broadcasting."""
    near = torch.as_tensor(near, dtype=torch.float32).reshape(-1, 1).expand(n_rays, 1)
    far = torch.as_tensor(far, dtype=torch.float32).reshape(-1, 1).expand(n_rays, 1)
    t = torch.linspace(0.0, 1.0, n_samples)
    z = near + (far - near) * t
    if not perturb:
        return z
    mids = 0.5 * (z[:, 1:] + z[:, :-1])
    lo, hi = torch.cat([z[:, :1], mids], 1), torch.cat([mids, z[:, -1:]], 1)
    return lo + (hi - lo) * torch.rand(z.shape, generator=generator)


def positional_encoding__frequency_table(x, n_freqs, include_input=True):
    """A (L,) table of frequencies, sin and cos interleaved per frequency with stack / reshape."""
    f = (2.0 ** torch.arange(n_freqs, dtype=x.dtype, device=x.device)) * math.pi
    a = x.unsqueeze(-2) * f.unsqueeze(-1)  # (..., L, D)
    sc = torch.stack([torch.sin(a), torch.cos(a)], -2).reshape(*x.shape[:-1], 2 * n_freqs * x.shape[-1])
    return torch.cat([x, sc], -1) if include_input else sc


MISTAKES += [
    M("get_rays", "fx for both axes", gnd.check_get_rays, get_rays_fx_for_both, ("fy",), batch="29"),
    M("get_rays", "origin -t", gnd.check_get_rays, get_rays_origin_negated, ("c2w[:3, 3]",), batch="29"),
    M("get_rays", "float64 rays from float32 K", gnd.check_get_rays, get_rays_float64, ("float32",), batch="29"),
    M("get_rays", "numpy arrays returned", gnd.check_get_rays, get_rays_numpy, ("tensor",), batch="29"),
    M("stratified_samples", "torch.manual_seed(0) inside", gnd.check_stratified_samples, stratified_manual_seed,
      ("generator",), batch="29"),
    M("stratified_samples", "no stratification: sorted uniform depths", gnd.check_stratified_samples,
      stratified_unstratified, ("bin",), defining="in their bins", batch="29"),
    M("stratified_samples", "near, far as floats only", gnd.check_stratified_samples, stratified_floats_only,
      ("(r,)",), batch="29"),
    M("stratified_samples", "np.random for the jitter", gnd.check_stratified_samples, stratified_numpy_jitter,
      ("generator",), batch="29"),
    M("stratified_samples", "one jitter for all rays", gnd.check_stratified_samples, stratified_one_jitter_per_sample,
      ("every ray",), batch="29"),
    M("query_points", "samples axis first", gnd.check_query_points, query_points_samples_first, ("shape",),
      batch="29"),
    M("positional_encoding", "include_input ignored", gnd.check_positional_encoding, encoding_include_input_ignored,
      ("include_input=false",), batch="29"),
    M("positional_encoding", "identity term last", gnd.check_positional_encoding, encoding_identity_last,
      ("identity term x last",), batch="29"),
    M("positional_encoding", "numpy returned", gnd.check_positional_encoding, encoding_numpy, ("tensor",),
      batch="29"),
]

HONEST += [
    Honest("get_rays", "pixel grid @ K⁻¹ᵀ, K's dtype", gnd.check_get_rays, get_rays__pixel_grid_matmul),
    Honest("stratified_samples", "per-ray near/far by broadcasting", gnd.check_stratified_samples,
           stratified_samples__per_ray_bounds),
    Honest("positional_encoding", "frequency table, stack / reshape", gnd.check_positional_encoding,
           positional_encoding__frequency_table),
]

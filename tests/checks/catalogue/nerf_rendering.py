"""Notebook 08 (volume rendering): classic mistakes, honest solutions and trivial answers, run through its checks."""

from __future__ import annotations

import numpy as np
import torch

from course_lib.checks import nerf_rendering as gnr
from tests.checks.catalogue import Honest, Mistake


# ============================================================================ honest solutions


def volume_render(rgb, sigma, z_vals, rays_d, white_background=True):
    """Plain code: the paper's quadrature with an exclusive cumulative product."""
    dists = z_vals[:, 1:] - z_vals[:, :-1]
    dists = torch.cat([dists, torch.full_like(z_vals[:, :1], 1e10)], dim=-1)
    dists = dists * torch.linalg.norm(rays_d, dim=-1, keepdim=True)
    alpha = 1.0 - torch.exp(-sigma * dists)
    trans = torch.cumprod(1.0 - alpha + 1e-10, dim=-1)
    trans = torch.cat([torch.ones_like(trans[:, :1]), trans[:, :-1]], dim=-1)
    weights = alpha * trans
    rgb_map = torch.sum(weights[..., None] * rgb, dim=-2)
    acc_map = torch.sum(weights, dim=-1)
    if white_background:
        rgb_map = rgb_map + (1.0 - acc_map[..., None])
    return {"rgb_map": rgb_map, "depth_map": torch.sum(weights * z_vals, dim=-1), "acc_map": acc_map,
            "weights": weights}


def volume_render__exp_cumsum(rgb, sigma, z_vals, rays_d, white_background=True):
    """T_i = exp(-sum_{j<i} sigma_j delta_j) with an exclusive cumulative sum, no epsilon."""
    norm = rays_d.norm(dim=-1)
    gaps = torch.diff(z_vals, dim=-1) * norm[:, None]
    delta = torch.cat([gaps, 1e10 * torch.ones(z_vals.shape[0], 1, dtype=z_vals.dtype)], dim=1)
    tau = sigma * delta
    before = torch.cat([torch.zeros_like(tau[:, :1]), torch.cumsum(tau[:, :-1], dim=1)], dim=1)
    weights = torch.exp(-before) * (1 - torch.exp(-tau))
    acc = weights.sum(1)
    color = torch.einsum("rs,rsc->rc", weights, rgb)
    if white_background:
        color = color + (1 - acc).unsqueeze(1)
    return dict(weights=weights, acc_map=acc, rgb_map=color, depth_map=torch.einsum("rs,rs->r", weights, z_vals))


def volume_render__loop(rgb, sigma, z_vals, rays_d, white_background=True):
    """A loop over the samples, as the quadrature reads."""
    R, S = sigma.shape
    scale = torch.sqrt((rays_d ** 2).sum(-1))
    T = torch.ones(R)
    weights = torch.zeros(R, S)
    for i in range(S):
        delta = (z_vals[:, i + 1] - z_vals[:, i]) * scale if i < S - 1 else torch.full((R,), 1e10)
        alpha = 1 - torch.exp(-sigma[:, i] * delta)
        weights[:, i] = T * alpha
        T = T * (1 - alpha)
    acc = weights.sum(-1)
    rgb_map = (weights[..., None] * rgb).sum(1) + ((1 - acc)[:, None] if white_background else 0.0)
    return {"rgb_map": rgb_map, "depth_map": (weights * z_vals).sum(-1), "acc_map": acc, "weights": weights}


# ============================================================================ buggy versions


def _render(delta="norm", cumprod="exclusive", form="alpha_T", last=1e10, white=True, depth="sum", shift=False):
    """The plain volume_render above with one thing changed, as a student would get it wrong."""

    def render(rgb, sigma, z_vals, rays_d, white_background=True):
        gaps = z_vals[:, 1:] - z_vals[:, :-1]
        tail = torch.full_like(z_vals[:, :1], last) if last is not None else gaps[:, -1:]
        dists = torch.cat([tail, gaps] if shift else [gaps, tail], dim=-1)
        if delta == "norm":
            dists = dists * torch.linalg.norm(rays_d, dim=-1, keepdim=True)
        alpha = 1.0 - torch.exp(-sigma * (dists if delta != "none" else 1.0))
        trans = torch.cumprod(1.0 - alpha + 1e-10, dim=-1)
        if cumprod == "exclusive":
            trans = torch.cat([torch.ones_like(trans[:, :1]), trans[:, :-1]], dim=-1)
        weights = {"alpha_T": alpha * trans, "T": trans, "alpha": alpha}[form]
        acc = weights.sum(-1)
        rgb_map = (weights[..., None] * rgb).sum(-2)
        if white_background and white:
            rgb_map = rgb_map + (1.0 - acc[..., None])
        dep = (weights * z_vals).sum(-1)
        if depth == "normalized":
            dep = dep / acc.clamp_min(1e-10)
        return {"rgb_map": rgb_map, "depth_map": dep, "acc_map": acc, "weights": weights}

    return render


# ============================================================================ the catalogue

M = Mistake
MISTAKES = [
    M("volume_render", "no Δ in α", gnr.check_volume_render, _render(delta="none"), ("forgot delta",),
      defining="Δ in α"),
    M("volume_render", "weights forget α", gnr.check_volume_render, _render(form="T"), ("weights forget alpha",)),
    M("volume_render", "weights forget T", gnr.check_volume_render, _render(form="alpha"),
      ("forget the transmittance",)),
    M("volume_render", "inclusive cumprod", gnr.check_volume_render, _render(cumprod="inclusive"),
      ("inclusive cumprod",)),
    M("volume_render", "Δ not scaled by |d| (near miss)", gnr.check_volume_render, _render(delta="plain"),
      ("not scaled by |d|",)),
    M("volume_render", "no last interval (near miss)", gnr.check_volume_render, _render(last=0.0),
      ("last interval",)),
    M("volume_render", "last interval repeated (near miss)", gnr.check_volume_render, _render(last=None),
      ("repeats the interval before",)),
    M("volume_render", "intervals shifted by one", gnr.check_volume_render, _render(shift=True),
      ("shifted by one",)),
    M("volume_render", "no white background", gnr.check_volume_render, _render(white=False),
      ("no white background",)),
    M("volume_render", "depth divided by acc (near miss)", gnr.check_volume_render, _render(depth="normalized"),
      ("divided by acc_map",)),
]

#: Correct solutions: they must score full marks.
HONEST = [
    Honest("volume_render", "plain code, exclusive cumprod", gnr.check_volume_render, volume_render),
    Honest("volume_render", "exp of an exclusive cumsum, no epsilon", gnr.check_volume_render,
           volume_render__exp_cumsum),
    Honest("volume_render", "a loop over the samples", gnr.check_volume_render, volume_render__loop),
]


def _trivial() -> list:
    z = np.zeros  # noqa: F841
    return [
        (gnr.check_volume_render, lambda rgb, sigma, zv, d, white_background=True: {
            "rgb_map": torch.zeros(rgb.shape[0], 3), "depth_map": torch.zeros(sigma.shape[0]),
            "acc_map": torch.zeros(sigma.shape[0]), "weights": torch.zeros_like(sigma)}),
    ]


#: Constants of the right shape: they pass the shape gates and trivially satisfied properties, and must earn nothing.
TRIVIAL = _trivial()


# ============================================================================ issue 29: written as students write them
# From the notebook's text and the stub's docstring, with an error students make; then valid variants.

def _vr29(rgb, sigma, z_vals, rays_d, white_background=True, acc="weights", norm="per_ray", bg_axis=True,
          normalize_weights=False):
    d = z_vals[:, 1:] - z_vals[:, :-1]
    d = torch.cat([d, torch.full_like(z_vals[:, :1], 1e10)], -1)
    d = d * (rays_d.norm(dim=-1, keepdim=True) if norm == "per_ray" else rays_d.norm())
    alpha = 1 - torch.exp(-sigma * d)
    T = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], -1), -1)
    w = T * alpha
    if normalize_weights:
        w = w / w.sum(-1, keepdim=True).clamp_min(1e-10)
    acc_map = alpha.sum(-1) if acc == "alphas" else w.sum(-1)
    rgb_map = (w[..., None] * rgb).sum(-2)
    if white_background:
        rgb_map = rgb_map + ((1 - acc_map)[..., None] if bg_axis else (1 - acc_map))
    return {"rgb_map": rgb_map, "depth_map": (w * z_vals).sum(-1), "acc_map": acc_map, "weights": w}


def volume_render_acc_sum_of_alphas(rgb, sigma, z_vals, rays_d, white_background=True):  # acc = Σ α
    return _vr29(rgb, sigma, z_vals, rays_d, white_background, acc="alphas")


def volume_render_one_norm_for_all_rays(rgb, sigma, z_vals, rays_d, white_background=True):  # |d| of the whole tensor
    return _vr29(rgb, sigma, z_vals, rays_d, white_background, norm="global")


def volume_render_background_no_axis(rgb, sigma, z_vals, rays_d, white_background=True):  # (R, 3) + (R,)
    return _vr29(rgb, sigma, z_vals, rays_d, white_background, bg_axis=False)


def volume_render_weights_normalized(rgb, sigma, z_vals, rays_d, white_background=True):  # w / Σ w "so they sum to 1"
    return _vr29(rgb, sigma, z_vals, rays_d, white_background, normalize_weights=True)


# -- valid variants -----------------------------------------------------------------------------------------------
def volume_render__float64_inside(rgb, sigma, z_vals, rays_d, white_background=True):
    """Everything in float64 inside, returned in the input's dtype; alpha through expm1."""
    dt = sigma.dtype
    rgb, sigma, z, d = rgb.double(), sigma.double(), z_vals.double(), rays_d.double()
    delta = torch.diff(z, dim=-1, append=z[:, -1:] + 1e10) * torch.linalg.vector_norm(d, dim=-1)[:, None]
    delta[:, -1] = 1e10 * torch.linalg.vector_norm(d, dim=-1) / torch.linalg.vector_norm(d, dim=-1)
    alpha = -torch.expm1(-sigma * delta)
    T = torch.exp(-torch.cumsum(torch.cat([torch.zeros_like(delta[:, :1]), (sigma * delta)[:, :-1]], 1), 1))
    w = T * alpha
    acc = w.sum(1)
    out = {"rgb_map": (w[..., None] * rgb).sum(1) + (1 - acc[:, None]) * float(white_background),
           "depth_map": (w * z).sum(1), "acc_map": acc, "weights": w}
    return {k: v.to(dt) for k, v in out.items()}


MISTAKES += [
    M("volume_render", "acc = Σ α", gnr.check_volume_render, volume_render_acc_sum_of_alphas, ("acc_map",),
      batch="29"),
    M("volume_render", "one |d| for all rays", gnr.check_volume_render, volume_render_one_norm_for_all_rays,
      ("weights",), batch="29"),
    M("volume_render", "background without a new axis", gnr.check_volume_render, volume_render_background_no_axis,
      ("rgb_map",), batch="29"),
    M("volume_render", "weights normalized to sum 1", gnr.check_volume_render, volume_render_weights_normalized,
      ("weights",), batch="29"),
]

HONEST += [
    Honest("volume_render", "float64 inside, expm1", gnr.check_volume_render, volume_render__float64_inside),
]

"""Classic mistakes of the NeRF exercises, computed on the instructor's side (never shipped).

The checks of notebooks 06-08 name a mistake by comparing the student's result with the results of
known mistakes on the same case. Those results are computed here, by the case builders, and stored
in the fixtures (public and hidden) next to the reference's results: the student kit holds the
arrays, never code that computes an encoding, a rendering or a network.

* :func:`encoding_variant`: ways of writing the positional encoding (the reference is one of them).
* :func:`render_variant`: ways of writing volume rendering (the reference is one of them).
* :func:`nerf_variants`: the reference network with one wire changed (no ReLU in the trunk, a ReLU on
  the feature layer), with the check's probe weights.
"""

from __future__ import annotations

import numpy as np

from course_lib.nerf.encoding import positional_encoding

__all__ = ["ENCODING_VARIANTS", "encoding_variant", "RENDER_VARIANTS", "render_variant", "render_variants_of",
           "nerf_variants"]

#: Encoding mistakes stored per case: label -> keyword arguments of :func:`encoding_variant`.
ENCODING_VARIANTS = {
    "no_identity": {"include_input": False},
    "extra_identity": {"include_input": True},
    "no_pi": {"pi": False},
    "cos_first": {"order": "freq_cos"},
    "blocks": {"order": "blocks"},
    "coord": {"order": "coord"},
    "from1": {"freqs": "pow2_from1"},
    "linear": {"freqs": "linear"},
    "no_pi_blocks": {"pi": False, "order": "blocks"},
    "no_identity_no_pi": {"include_input": False, "pi": False},
    "half_angle": {"freqs": "pow2_half"},
}


def encoding_variant(x: np.ndarray, L: int, include_input: bool = True, pi: bool = True,
                     order: str = "freq", freqs: str = "pow2") -> np.ndarray:
    """One way of writing the positional encoding of ``x (..., D)`` with ``L`` frequencies.

    order: "freq" (the kit's: sin and cos of each frequency side by side), "freq_cos" (cos first),
    "blocks" (all sines, then all cosines), "coord" (grouped by coordinate).
    freqs: "pow2" (2^k, k = 0..L-1), "pow2_from1" (k = 1..L), "linear" (k + 1), "pow2_half" (2^k / 2).
    """
    x = np.asarray(x, float)
    k = np.arange(L, dtype=float)
    fr = {"pow2": 2.0 ** k, "pow2_from1": 2.0 ** (k + 1), "linear": k + 1.0, "pow2_half": 2.0 ** (k - 1)}[freqs]
    xf = x[..., None, :] * (fr * (np.pi if pi else 1.0))[:, None]  # (..., L, D)
    s, co = np.sin(xf), np.cos(xf)
    if order == "freq":
        parts = np.stack([s, co], axis=-2).reshape(*x.shape[:-1], -1)
    elif order == "freq_cos":
        parts = np.stack([co, s], axis=-2).reshape(*x.shape[:-1], -1)
    elif order == "blocks":
        parts = np.concatenate([s.reshape(*x.shape[:-1], -1), co.reshape(*x.shape[:-1], -1)], axis=-1)
    else:  # coord: for each coordinate, its sines and cosines
        parts = np.concatenate([np.swapaxes(s, -1, -2), np.swapaxes(co, -1, -2)], axis=-1).reshape(*x.shape[:-1], -1)
    return np.concatenate([x, parts], axis=-1) if include_input else parts


#: Rendering mistakes stored per case: label -> keyword arguments of :func:`render_variant`.
RENDER_VARIANTS = {
    "no_delta": {"delta": "none"},
    "plain_delta": {"delta": "plain"},
    "inclusive": {"cumprod": "inclusive"},
    "last_zero": {"last": "zero"},
    "last_repeat": {"last": "repeat"},
    "form_T": {"form": "T"},
    "form_alpha": {"form": "alpha"},
    "depth_normalized": {"depth": "normalized"},
    "other_background": {"white": None},
    "dists_first": {"dists": "first"},
}


def render_variant(rgb, sigma, z, d, white: bool | None = True, delta: str = "norm", last: str = "1e10",
                   cumprod: str = "exclusive", depth: str = "sum", form: str = "alpha_T",
                   dists: str = "next", flip_white: bool = False) -> dict[str, np.ndarray]:
    """One way of writing volume rendering (the reference is one of them, the others are mistakes).

    delta: "norm" (dists * |d|), "plain" (dists, no |d|), "none" (alpha = 1 - exp(-sigma)).
    last: the last interval: "1e10" (NeRF's), "zero" (ignored), "repeat" (the previous one).
    cumprod: "exclusive" (T_i = prod_{j<i}), "inclusive" (prod_{j<=i}).
    depth: "sum" (sum w z), "normalized" (sum w z / acc).
    form: the weights: "alpha_T" (alpha_i T_i), "T" (T_i, alpha forgotten), "alpha" (alpha_i, T forgotten).
    dists: "next" (delta_i = t_{i+1} - t_i), "first" (the extra interval put first: delta_1 = 1e10).
    white: the background (None: the other one than ``flip_white`` says; see :func:`render_variants_of`).
    """
    rgb, sigma, z, d = (np.asarray(a, float) for a in (rgb, sigma, z, d))
    gaps = np.diff(z, axis=-1)
    tail = {"1e10": np.full_like(z[:, :1], 1e10), "zero": np.zeros_like(z[:, :1]), "repeat": gaps[:, -1:]}[last]
    dd = np.concatenate([gaps, tail], axis=-1) if dists == "next" else np.concatenate([tail, gaps], axis=-1)
    if delta == "norm":
        dd = dd * np.linalg.norm(d, axis=-1, keepdims=True)
    elif delta == "none":
        dd = np.ones_like(dd)
    alpha = 1.0 - np.exp(-sigma * dd)
    keep = np.cumprod(1.0 - alpha + 1e-10, axis=-1)
    if cumprod == "exclusive":
        keep = np.concatenate([np.ones_like(keep[:, :1]), keep[:, :-1]], axis=-1)
    w = {"alpha_T": alpha * keep, "T": keep, "alpha": alpha}[form]
    acc = w.sum(-1)
    rgb_map = (w[..., None] * rgb).sum(-2)
    if white:
        rgb_map = rgb_map + (1.0 - acc[:, None])
    dep = (w * z).sum(-1)
    if depth == "normalized":
        dep = dep / np.maximum(acc, 1e-10)
    return {"rgb_map": rgb_map, "depth_map": dep, "acc_map": acc, "weights": w}


def render_variants_of(rgb, sigma, z, d, white: bool) -> dict[str, dict[str, np.ndarray]]:
    """Every mistake of :data:`RENDER_VARIANTS` on one case: ``{label: {rgb_map, depth_map, acc_map, weights}}``."""
    out = {}
    for label, kw in RENDER_VARIANTS.items():
        kw = dict(kw)
        kw["white"] = (not white) if kw.get("white", white) is None else white
        out[label] = render_variant(rgb, sigma, z, d, **kw)
    return out


def nerf_variants(model, pts, dirs) -> dict[str, np.ndarray]:
    """Outputs of the reference network ``model`` (weights as they are) with one wire changed.

    Returns ``sigma_no_trunk_relu`` (no ReLU after the trunk layers) and ``rgb_feature_relu`` (a
    ReLU on the feature layer), for the points ``pts (..., 3)`` and directions ``dirs (..., 3)``.
    """
    import torch
    from torch.nn import functional as F

    with torch.no_grad():
        x = positional_encoding(pts, model.pos_freqs)
        e = positional_encoding(dirs, model.dir_freqs)
        out = {}
        for relu_trunk, relu_feature in ((False, False), (True, True)):
            h = x
            for i, layer in enumerate(model.trunk):
                h = F.relu(layer(h)) if relu_trunk else layer(h)
                if i in model.skips:
                    h = torch.cat([x, h], dim=-1)
            sigma = F.relu(model.sigma_head(h)[..., 0])
            feat = model.feature(h)
            feat = F.relu(feat) if relu_feature else feat
            rgb = torch.sigmoid(model.rgb_head(F.relu(model.view_layer(torch.cat([feat, e], dim=-1)))))
            if not relu_trunk:
                out["sigma_no_trunk_relu"] = sigma.numpy()
            else:
                out["rgb_feature_relu"] = rgb.numpy()
        return out

"""Cases of notebook 08 (volume rendering).

Built from :func:`course_lib.nerf.render.volume_render` (fixture ``nerf_rendering``); the checks
are in :mod:`course_lib.checks.nerf_rendering`. The slabs (hand-computable transmittance) and the
random rays are drawn from seeded generators (salted for the hidden cases); the results of the
classic mistakes on them are stored next to the reference's (:func:`render_variant`).
"""

from __future__ import annotations

import numpy as np

from course_lib.checks.nerf_rendering import FIXTURE, KEYS
from course_lib.instructor.cases import builds, store
from course_lib.nerf.render import volume_render


def _random_case(g: np.random.Generator):
    R, S = int(g.integers(5, 8)), int(g.integers(10, 15))
    rgb = g.uniform(0, 1, size=(R, S, 3))
    sigma = g.exponential(2.0, size=(R, S)) * (g.uniform(size=(R, S)) > 0.3)
    sigma[0] = 0.0  # an empty ray: all background
    sigma[1, :-1], sigma[1, -1] = 0.0, 3.0  # density only in the last sample: shows the last interval
    sigma[2] *= 0.05  # a half-transparent ray: acc well below 1 (nothing in the last sample)
    sigma[2, -1] = 0.0
    z = np.sort(g.uniform(2.0, 6.0, size=(R, S)), axis=1)
    d = np.concatenate([g.normal(scale=0.4, size=(R, 2)), np.ones((R, 1))], axis=1)  # z_cam = 1, |d| > 1
    return rgb.astype(np.float32), sigma.astype(np.float32), z.astype(np.float32), d.astype(np.float32)


def _slab_case(g: np.random.Generator):
    """Rays (z_cam = 1, |d| >= 1) through slabs of constant density; empty space elsewhere (red matter).

    Behind a slab of density s over n intervals of depth step h the light left is exp(-s n h |d|).
    """
    S = int(g.integers(36, 48))
    z = np.tile(np.linspace(2.0, 6.0, S), (3, 1))
    step = 4.0 / (S - 1)
    sigma = np.zeros_like(z)
    d = np.concatenate([g.normal(scale=0.3, size=(3, 2)), np.ones((3, 1))], axis=1)
    trans = []
    for r in range(3):
        a, n = int(g.integers(3, S // 2)), int(g.integers(4, S // 3))  # the slab covers samples a .. a + n - 1
        s = float(g.uniform(0.3, 5.0))
        sigma[r, a:a + n] = s
        trans.append(np.exp(-s * n * step * np.linalg.norm(d[r])))
    rgb = np.zeros((3, S, 3))
    rgb[..., 0] = 1.0
    return (rgb.astype(np.float32), sigma.astype(np.float32), z.astype(np.float32), d.astype(np.float32),
            np.array(trans))


def _render(args, white: bool) -> dict[str, np.ndarray]:
    import torch

    res = volume_render(*(torch.as_tensor(a) for a in args), white_background=white)
    return {k: res[k].numpy() for k in KEYS}


@builds(FIXTURE)
def _build() -> dict[str, np.ndarray]:
    g = np.random.default_rng(8)
    out: dict[str, np.ndarray] = {}
    *slab, trans = _slab_case(g)
    store(out, "slab", **dict(zip(("rgb", "sigma", "z_vals", "rays_d"), slab)), trans=trans)
    for label, res in render_variants_of(*slab, white=True).items():
        out[f"slab__{label}_weights"] = res["weights"].astype(np.float32)
    args = _random_case(g)
    out.update(zip(("rgb", "sigma", "z_vals", "rays_d"), args))
    for white in (True, False):  # the check reads the mistakes' weights, and the two that it tells by another map
        bg = "white" if white else "black"
        store(out, bg, **_render(args, white))
        var = render_variants_of(*args, white=white)
        out.update({f"{bg}__{label}_weights": res["weights"].astype(np.float32) for label, res in var.items()})
        out[f"{bg}__other_background_rgb_map"] = var["other_background"]["rgb_map"].astype(np.float32)
        out[f"{bg}__depth_normalized_depth_map"] = var["depth_normalized"]["depth_map"].astype(np.float32)
    return out


# --------------------------------------------------------------------------- what the classic mistakes give
# (stored with the cases, keyed as the check module's sentences are: the shipped checks hold no implementation)


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
    "other_background": {"white": "the other one"},  # the other background than the case asks for
    "dists_first": {"dists": "first"},
}


def render_variant(rgb, sigma, z, d, white: bool = True, delta: str = "norm", last: str = "1e10",
                   cumprod: str = "exclusive", depth: str = "sum", form: str = "alpha_T",
                   dists: str = "next") -> dict[str, np.ndarray]:
    """One way of writing volume rendering (the reference is one of them, the others are mistakes).

    delta: "norm" (dists * |d|), "plain" (dists, no |d|), "none" (alpha = 1 - exp(-sigma)).
    last: the last interval: "1e10" (NeRF's), "zero" (ignored), "repeat" (the previous one).
    cumprod: "exclusive" (T_i = prod_{j<i}), "inclusive" (prod_{j<=i}).
    depth: "sum" (sum w z), "normalized" (sum w z / acc).
    form: the weights: "alpha_T" (alpha_i T_i), "T" (T_i, alpha forgotten), "alpha" (alpha_i, T forgotten).
    dists: "next" (delta_i = t_{i+1} - t_i), "first" (the extra interval put first: delta_1 = 1e10).
    white: whether the background is white.
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
    return {label: render_variant(rgb, sigma, z, d, **dict(kw, white=(not white) if "white" in kw else white))
            for label, kw in RENDER_VARIANTS.items()}

"""Cases of notebook 07 (the NeRF MLP, PSNR).

Built from :class:`course_lib.nerf.model.NeRF` and :func:`course_lib.nerf.encoding.positional_encoding`
(fixture ``nerf_model``); the checks are in :mod:`course_lib.checks.nerf_model`. Everything that a
lookup could key on is drawn from seeded generators, which the hidden cases salt: the points and
directions, the two small configurations, the probe weights' seed, the MSE values of psnr.
"""

from __future__ import annotations

import numpy as np

from course_lib.checks.nerf_model import CONFIG_NAMES, FIXTURE, config_kwargs, copy_probe_weights
from course_lib.instructor.cases import builds, store
from course_lib.nerf.encoding import positional_encoding
from course_lib.nerf.model import NeRF

#: The paper's network: depth, width, skip, pos_freqs, dir_freqs, view_width (the constructor's defaults).
DEFAULT_CONFIG = (8, 256, 4, 10, 4, 128)


def _configs(g: np.random.Generator) -> dict[str, np.ndarray]:
    """The default configuration and two small ones (their skip inside the trunk, no two layer sizes alike)."""
    out = {"default": np.array(DEFAULT_CONFIG)}
    for name, widths in (("small", (24, 32, 40)), ("tiny", (12, 16, 20))):
        depth = int(g.integers(3, 6))
        width = int(g.choice(widths))
        out[name] = np.array([depth, width, int(g.integers(0, depth - 1)), int(g.integers(2, 5)),
                              int(g.integers(1, 3)), width // 2 + 2])
    return out


def _inputs(g: np.random.Generator):
    R, S = int(g.integers(3, 6)), int(g.integers(5, 9))
    pts = g.uniform(-1.5, 1.5, size=(R, S, 3))
    dirs = g.normal(size=(R, S, 3))
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    return pts.astype(np.float32), dirs.astype(np.float32)


@builds(FIXTURE)
def _build() -> dict[str, np.ndarray]:
    import torch

    g = np.random.default_rng(7)
    out: dict[str, np.ndarray] = {"weight_seed": g.integers(1, 2**31, size=1)}
    pts, dirs = _inputs(g)
    out["pts"], out["dirs"] = pts, dirs
    for name, cfg in _configs(g).items():
        out[f"{name}_config"] = cfg
    seed = int(out["weight_seed"][0])
    P, Dv = torch.as_tensor(pts), torch.as_tensor(dirs)
    for name in CONFIG_NAMES:
        _, cfg = config_kwargs(out, name)
        m = NeRF(**cfg)
        copy_probe_weights(m, cfg, seed, -1, False, False)
        with torch.no_grad():  # the density head's bias that makes half of the raw densities positive
            raw = m.sigma_head(m.trunk_features(P))[..., 0]
        bias = float(m.sigma_head.bias.detach()[0]) - float(torch.median(raw))
        out[f"{name}_sigma_bias"] = np.array([bias])
        copy_probe_weights(m, cfg, seed, -1, False, False, bias)
        with torch.no_grad():
            rgb, sigma = m(P, Dv)
            raw = m.sigma_head(m.trunk_features(P))[..., 0]
        store(out, name, rgb=rgb.numpy(), sigma=sigma.numpy(), sigma_raw=raw.numpy(), **nerf_variants(m, P, Dv))
    # the reference encoding of every point and direction the check sends (NeRF is graded on its own)
    rows = np.unique(np.concatenate([pts.reshape(-1, 3), dirs.reshape(-1, 3)]), axis=0)
    out["enc_rows"] = rows
    out["enc_values"] = positional_encoding(torch.as_tensor(rows), DEFAULT_CONFIG[3]).numpy()
    # psnr: MSE values of images in [0, 1]
    mse = np.exp(g.uniform(np.log(1e-4), np.log(0.3), size=4))
    out["psnr_mse"] = mse
    out["psnr_db"] = -10.0 * np.log10(np.asarray(mse, float))  # PSNR of images in [0, 1]
    return out


# --------------------------------------------------------------------------- what the classic mistakes give
# (stored with the cases, keyed as the check module's sentences are: the shipped checks hold no implementation)


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

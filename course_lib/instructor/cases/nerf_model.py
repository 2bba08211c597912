"""Cases of notebook 07 (the NeRF MLP, PSNR).

Built from :class:`course_lib.nerf.model.NeRF` (fixture ``nerf_model``); the checks are in
:mod:`course_lib.checks.nerf_model`.
"""

from __future__ import annotations

import numpy as np

from course_lib.checks.nerf_model import CONFIGS, FIXTURE, layer_table, set_test_weights
from course_lib.instructor.cases import builds

def _inputs():
    g = np.random.default_rng(7)
    pts = g.uniform(-1.5, 1.5, size=(4, 8, 3))
    dirs = g.normal(size=(4, 8, 3))
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    return pts.astype(np.float32), dirs.astype(np.float32)


@builds(FIXTURE)
def _build() -> dict[str, np.ndarray]:
    import torch

    from course_lib.nerf.model import NeRF

    out: dict[str, np.ndarray] = {}
    pts, dirs = _inputs()
    for name, kw in CONFIGS:
        torch.manual_seed(0)
        m = NeRF(**kw)
        out[f"{name}_layers"] = np.array(layer_table(m), dtype=np.int64)
        out[f"{name}_n_params"] = np.array(sum(p.numel() for p in m.parameters()))
        shapes = [tuple(p.shape) for p in m.parameters()]
        out[f"{name}_param_shapes"] = np.array([list(s) + [0] * (2 - len(s)) for s in shapes], dtype=np.int64)
        out[f"{name}_param_ndim"] = np.array([len(s) for s in shapes], dtype=np.int64)
        set_test_weights(m, shapes)
        with torch.no_grad():
            rgb, sigma = m(torch.as_tensor(pts), torch.as_tensor(dirs))
            raw = m.sigma_head(m.trunk_features(torch.as_tensor(pts)))[..., 0]
        out[f"{name}_rgb"], out[f"{name}_sigma"] = rgb.numpy(), sigma.numpy()
        out[f"{name}_sigma_raw"] = raw.numpy()
        out[f"{name}_sigma_skip_hx"] = _sigma_skip_swapped(m, torch.as_tensor(pts)).numpy()
    out["pts"], out["dirs"] = pts, dirs
    return out


def _sigma_skip_swapped(m, pts):
    """The density of the reference model when the skip concatenates [h, γ(x)] (the mistake)."""
    import torch
    from torch.nn import functional as F

    from course_lib.nerf.encoding import positional_encoding

    with torch.no_grad():
        x = positional_encoding(pts, m.pos_freqs)
        h = x
        for i, layer in enumerate(m.trunk):
            h = F.relu(layer(h))
            if i in m.skips:
                h = torch.cat([h, x], dim=-1)
        return F.relu(m.sigma_head(h)[..., 0])

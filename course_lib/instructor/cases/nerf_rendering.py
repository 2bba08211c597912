"""Cases of notebook 08 (volume rendering).

Built from :func:`course_lib.nerf.render.volume_render` (fixture ``nerf_rendering``); the checks
are in :mod:`course_lib.checks.nerf_rendering`.
"""

from __future__ import annotations

import numpy as np

from course_lib.checks.nerf_rendering import FIXTURE, KEYS
from course_lib.instructor.cases import builds

def _random_case():
    g = np.random.default_rng(8)
    R, S = 6, 12
    rgb = g.uniform(0, 1, size=(R, S, 3))
    sigma = g.exponential(2.0, size=(R, S)) * (g.uniform(size=(R, S)) > 0.3)
    sigma[0] = 0.0  # an empty ray: all background
    sigma[1, :-1], sigma[1, -1] = 0.0, 3.0  # density only in the last sample: shows the last interval
    sigma[2] *= 0.05  # a half-transparent ray: acc well below 1 (nothing in the last sample)
    sigma[2, -1] = 0.0
    z = np.sort(g.uniform(2.0, 6.0, size=(R, S)), axis=1)
    d = np.concatenate([g.normal(scale=0.4, size=(R, 2)), np.ones((R, 1))], axis=1)  # z_cam = 1, |d| > 1
    return rgb.astype(np.float32), sigma.astype(np.float32), z.astype(np.float32), d.astype(np.float32)


@builds(FIXTURE)
def _build() -> dict[str, np.ndarray]:
    import torch

    from course_lib.nerf.render import volume_render

    rgb, sigma, z, d = _random_case()
    out = {"rgb": rgb, "sigma": sigma, "z_vals": z, "rays_d": d}
    for bg in (True, False):
        res = volume_render(*(torch.as_tensor(a) for a in (rgb, sigma, z, d)), white_background=bg)
        for k in KEYS:
            out[f"{'white' if bg else 'black'}_{k}"] = res[k].numpy()
    return out

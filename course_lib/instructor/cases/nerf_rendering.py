"""Cases of notebook 08 (volume rendering).

Built from :func:`course_lib.nerf.render.volume_render` (fixture ``nerf_rendering``); the checks
are in :mod:`course_lib.checks.nerf_rendering`. The slabs (hand-computable transmittance) and the
random rays are drawn from seeded generators (salted for the hidden cases); the results of the
classic mistakes on them are stored next to the reference's (:mod:`course_lib.instructor.cases.nerf_variants`).
"""

from __future__ import annotations

import numpy as np

from course_lib.checks.nerf_rendering import FIXTURE, KEYS
from course_lib.instructor.cases import builds
from course_lib.instructor.cases.nerf_variants import render_variants_of
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
    for k, v in zip(("rgb", "sigma", "z_vals", "rays_d"), slab):
        out[f"slab_{k}"] = v
    out["slab_trans"] = trans
    for label, res in render_variants_of(*slab, white=True).items():
        for k in ("weights", "acc_map"):
            out[f"slab__{label}_{k}"] = res[k].astype(np.float32)
    args = _random_case(g)
    out.update(zip(("rgb", "sigma", "z_vals", "rays_d"), args))
    for white in (True, False):
        bg = "white" if white else "black"
        for k, v in _render(args, white).items():
            out[f"{bg}_{k}"] = v
        for label, res in render_variants_of(*args, white=white).items():
            for k in KEYS:
                out[f"{bg}__{label}_{k}"] = res[k].astype(np.float32)
    return out

"""Notebook 08 (volume rendering): classic mistakes, honest solutions and trivial answers, run through its checks."""

from __future__ import annotations

import numpy as np

from course_lib.checks import nerf_rendering as gnr
from tests.checks.catalogue import Honest, Mistake, _torch

# ============================================================================ buggy versions
# Each is written as a student would write it (often the reference with one line changed).

# -- 08: volume_render ------------------------------------------------------------------------------------
def _render(form="alpha_T", delta="norm", cumprod="exclusive"):
    def volume_render(rgb, sigma, z_vals, rays_d, white_background=True):
        torch = _torch()
        out = gnr.render_variant(rgb.numpy(), sigma.numpy(), z_vals.numpy(), rays_d.numpy(), white=white_background,
                                 delta=delta, cumprod=cumprod, form=form)
        return {k: torch.as_tensor(v) for k, v in out.items()}

    return volume_render

# ============================================================================ the catalogue

M = Mistake
MISTAKES = [
    M("volume_render", "no Δ in α", gnr.check_volume_render, _render(delta="none"), ("forgot delta",),
      defining="Δ in α"),
    M("volume_render", "weights forget α", gnr.check_volume_render, _render(form="T"),
      ("weights forget alpha",)),
    M("volume_render", "weights forget T", gnr.check_volume_render, _render(form="alpha"),
      ("forget the transmittance",)),
    M("volume_render", "inclusive cumprod", gnr.check_volume_render, _render(cumprod="inclusive"),
      ("inclusive cumprod",)),
    M("volume_render", "Δ not scaled by |d|", gnr.check_volume_render, _render(delta="plain"),
      ("not scaled by |d|",)),
]

#: Correct solutions: they must score full marks.
HONEST = [
    Honest("volume_render", "the reference solution", gnr.check_volume_render, _render()),
]


def _trivial() -> list:
    torch = _torch()
    z = np.zeros  # noqa: F841
    return [
        (gnr.check_volume_render, lambda rgb, sigma, zv, d, white_background=True: {
            "rgb_map": torch.zeros(rgb.shape[0], 3), "depth_map": torch.zeros(sigma.shape[0]),
            "acc_map": torch.zeros(sigma.shape[0]), "weights": torch.zeros_like(sigma)}),
    ]


#: Constants of the right shape: they pass the shape gates and trivially satisfied properties, and must earn nothing.
TRIVIAL = _trivial()

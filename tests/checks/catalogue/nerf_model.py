"""Notebook 07 (the NeRF model, PSNR): classic mistakes, honest solutions and trivial answers, run through its checks."""

from __future__ import annotations

import numpy as np

from course_lib.checks import nerf_model as gnm
from tests.checks.catalogue import Honest, Mistake, _torch

# ============================================================================ buggy versions
# Each is written as a student would write it (often the reference with one line changed).

# -- 07: NeRF, psnr -------------------------------------------------------------------------------------
def _nerf_classes():
    torch = _torch()
    from torch.nn import functional as F

    from course_lib.nerf.model import NeRF

    class NeRFSigmoidDensity(NeRF):
        def forward(self, pts, viewdirs=None):
            rgb, _ = super().forward(pts, viewdirs)
            return rgb, torch.sigmoid(self.sigma_head(self.trunk_features(pts))[..., 0])

    class NeRFNoSkip(NeRF):
        def __init__(self, *args, **kw):
            kw["skips"] = ()
            super().__init__(*args, **kw)

    class NeRFNoDensityActivation(NeRF):
        def forward(self, pts, viewdirs=None):
            rgb, _ = super().forward(pts, viewdirs)
            return rgb, self.sigma_head(self.trunk_features(pts))[..., 0]

    class NeRFSkipOrder(NeRF):
        def trunk_features(self, pts):
            from course_lib.nerf.encoding import positional_encoding

            x = positional_encoding(pts, self.pos_freqs)
            h = x
            for i, layer in enumerate(self.trunk):
                h = F.relu(layer(h))
                if i in self.skips:
                    h = torch.cat([h, x], dim=-1)
            return h

    return NeRFSigmoidDensity, NeRFNoSkip, NeRFNoDensityActivation, NeRFSkipOrder


def psnr_sign(mse):
    return 10 * _torch().log10(mse)


def psnr_natural_log(mse):
    return -10 * _torch().log(mse)


def psnr_right(mse):
    return -10 * _torch().log10(mse)

def _nerf_reference():
    from course_lib.nerf.model import NeRF

    return NeRF


# ============================================================================ the catalogue

sig, noskip, noact, skiporder = _nerf_classes()

M = Mistake
MISTAKES = [
    M("NeRF", "sigmoid on the density", gnm.check_nerf_model, sig, ("sigmoid", "torch.relu"),
      defining="ReLU density"),
    M("NeRF", "no activation on the density", gnm.check_nerf_model, noact, ("no activation",),
      defining="ReLU density"),
    M("NeRF", "no skip connection", gnm.check_nerf_model, noskip, ("no skip connection",), defining="skip input"),
    M("NeRF", "skip concatenated as [h, γ(x)]", gnm.check_nerf_model, skiporder, ("[h, γ(x)]",),
      defining="skip input"),
    M("psnr", "sign flipped", gnm.check_psnr, psnr_sign, ("sign is flipped",)),
    M("psnr", "natural logarithm", gnm.check_psnr, psnr_natural_log, ("base-10",)),
]

#: Correct solutions: they must score full marks.
HONEST = [
    Honest("psnr", "the reference solution", gnm.check_psnr, psnr_right),
    Honest("NeRF", "the reference solution", gnm.check_nerf_model, _nerf_reference()),
]


def _constant_nerf():
    torch = _torch()

    class ConstantNeRF(torch.nn.Module):
        def __init__(self, **kw):
            super().__init__()
            self.layer = torch.nn.Linear(3, 4)

        def forward(self, pts, viewdirs):
            return torch.full((*pts.shape[:-1], 3), 0.5), torch.zeros(pts.shape[:-1])

    return ConstantNeRF


def _trivial() -> list:
    torch = _torch()
    z = np.zeros  # noqa: F841
    return [
        (gnm.check_nerf_model, _constant_nerf()),
        (gnm.check_psnr, lambda mse: torch.tensor(0.0)),
    ]


#: Constants of the right shape: they pass the shape gates and trivially satisfied properties, and must earn nothing.
TRIVIAL = _trivial()

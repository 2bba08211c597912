"""Notebook 07, the NeRF model: the literal student's exercises.

``positional_encoding`` is pasted from notebook 06, as the notebook asks (its cell has a stub).
"""

import math

import torch
from torch import nn

from tests.student.literal.nb06 import positional_encoding  # pasted into the notebook's own cell


class NeRF(nn.Module):
    """The NeRF MLP: a point and a viewing direction in, a colour and a density out.

    Args:
        depth: number of Linear + ReLU trunk layers (8).
        width: their width (256).
        skips: 0-based indices of trunk layers whose output is concatenated with the encoded input:
            h = torch.cat([γ(x), h], -1) before the next layer ((4,): layer 5 has 63 + 256 inputs).
        pos_freqs: L of the position encoding (10: 3 (1 + 2 L) = 63 inputs).
        dir_freqs: L of the direction encoding (4: 27 inputs).
        use_viewdirs: colour depends on the viewing direction (True).
        view_width: width of the view-dependent layer (128).

    Layers, in order of definition: trunk (depth x nn.Linear), density head nn.Linear(., 1), feature
    nn.Linear(., width), view layer nn.Linear(width + dirs, view_width), RGB head nn.Linear(view_width, 3).
    (With use_viewdirs=False: only the trunk, the density head and nn.Linear(., 3) on the trunk output.)

    forward(pts, viewdirs):
        pts: (..., 3) world points; viewdirs: (..., 3) unit viewing directions.
        Returns rgb (..., 3) in [0, 1] (sigmoid) and sigma (...) >= 0 (ReLU), no trailing axis of 1.
    """

    def __init__(self, depth=8, width=256, skips=(4,), pos_freqs=10, dir_freqs=4, use_viewdirs=True, view_width=128):
        super().__init__()
        self.skips = tuple(skips)
        self.pos_freqs = pos_freqs
        self.dir_freqs = dir_freqs
        self.use_viewdirs = use_viewdirs
        pos_dim = 3 * (1 + 2 * pos_freqs)
        dir_dim = 3 * (1 + 2 * dir_freqs)
        layers = []
        n_in = pos_dim
        for i in range(depth):
            layers.append(nn.Linear(n_in, width))
            n_in = width + pos_dim if i in self.skips else width
        self.trunk = nn.ModuleList(layers)
        self.sigma_head = nn.Linear(n_in, 1)
        if use_viewdirs:
            self.feature = nn.Linear(n_in, width)
            self.view_layer = nn.Linear(width + dir_dim, view_width)
            self.rgb_head = nn.Linear(view_width, 3)
        else:
            self.rgb_head = nn.Linear(n_in, 3)

    def forward(self, pts, viewdirs):
        gamma_x = positional_encoding(pts, self.pos_freqs)
        h = gamma_x
        for i, layer in enumerate(self.trunk):
            h = torch.relu(layer(h))
            if i in self.skips:
                h = torch.cat([gamma_x, h], -1)
        sigma = torch.relu(self.sigma_head(h))[..., 0]
        if self.use_viewdirs:
            feature = self.feature(h)
            gamma_d = positional_encoding(viewdirs, self.dir_freqs)
            h = torch.relu(self.view_layer(torch.cat([feature, gamma_d], -1)))
        rgb = torch.sigmoid(self.rgb_head(h))
        return rgb, sigma


def psnr(mse):
    """Peak signal-to-noise ratio in dB of images in [0, 1].

    Args:
        mse: scalar tensor (or float), the mean squared error.

    Returns:
        -10 log10(mse), a scalar tensor (or float).
    """
    if isinstance(mse, torch.Tensor):
        return -10 * torch.log10(mse)
    return -10 * math.log10(mse)

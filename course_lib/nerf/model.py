"""The NeRF network (notebook 07): a point and a viewing direction in, a colour and a density out.

Architecture (the paper's Fig. 7 and the official code; every size is an argument)::

    gamma(x) (63) -> [Linear(., 256) + ReLU] x 8 ---------------> Linear(256, 1) -> density sigma >= 0
                      the input gamma(x) is concatenated to        |
                      the output of layer 4 (0-based, i.e. the     Linear(256, 256) "feature" (no activation)
                      5th layer; skips=(4,)), so layer 5 sees      |
                      [gamma(x), h] (63 + 256 inputs)              concat gamma(d) (27) -> Linear(., 128) + ReLU
                                                                   -> Linear(128, 3) -> sigmoid -> rgb in [0, 1]

* The density depends on the position only, the colour also on the viewing direction (view-
  dependent effects such as specular highlights); with ``use_viewdirs=False`` the colour comes from
  the trunk directly and ignores the direction.
* Density activation: ``"relu"`` (the paper, sigma = max(raw, 0)) or ``"softplus"``
  (sigma = log(1 + e^raw), smooth, never exactly 0, so it cannot get stuck at a "dead" zero-density
  start where ReLU's gradient vanishes; a common choice in later work).
* Positions are encoded with L = ``pos_freqs`` octaves, directions (unit vectors) with ``dir_freqs``
  (see :mod:`course_lib.nerf.encoding`).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from course_lib.nerf.encoding import encoded_dim, positional_encoding
from course_lib.validate import KitInputError

__all__ = ["NeRF", "density_activation"]


def density_activation(raw: torch.Tensor, kind: str) -> torch.Tensor:
    """Map the network's raw density output to sigma >= 0 (``"relu"`` or ``"softplus"``)."""
    if kind == "relu":
        return F.relu(raw)
    if kind == "softplus":
        return F.softplus(raw)
    raise KitInputError(f"density activation {kind!r}: expected 'relu' or 'softplus'")


class NeRF(nn.Module):
    """The NeRF MLP.

    Args:
        depth: number of Linear+ReLU layers of the trunk (8).
        width: their width (256).
        skips: 0-based indices of trunk layers whose *output* is concatenated with the encoded
            input before the next layer ((4,): the official code).
        pos_freqs: L for positions (10 -> 63 inputs).
        dir_freqs: L for view directions (4 -> 27 inputs).
        use_viewdirs: colour depends on the viewing direction.
        view_width: width of the view-dependent branch (128).
        density: ``"relu"`` (paper) or ``"softplus"``.

    ``forward(pts (..., 3), viewdirs (..., 3)) -> rgb (..., 3) in [0, 1], sigma (...) >= 0``.

    Introduced in ``notebooks/07_nerf_model.ipynb``.
    """

    def __init__(self, depth: int = 8, width: int = 256, skips=(4,), pos_freqs: int = 10, dir_freqs: int = 4,
                 use_viewdirs: bool = True, view_width: int = 128, density: str = "relu"):
        super().__init__()
        if depth < 1 or width < 1:
            raise KitInputError(f"depth = {depth}, width = {width}: both must be >= 1")
        density_activation(torch.zeros(1), density)  # validates the name
        self.depth, self.width, self.skips = int(depth), int(width), tuple(int(s) for s in skips)
        self.pos_freqs, self.dir_freqs, self.use_viewdirs = int(pos_freqs), int(dir_freqs), bool(use_viewdirs)
        self.view_width, self.density = int(view_width), density
        self.in_pts = encoded_dim(3, pos_freqs)
        self.in_dirs = encoded_dim(3, dir_freqs) if use_viewdirs else 0
        layers = []
        n_in = self.in_pts
        for i in range(depth):
            layers.append(nn.Linear(n_in, width))
            n_in = width + (self.in_pts if i in self.skips else 0)
        self.trunk = nn.ModuleList(layers)
        self.sigma_head = nn.Linear(n_in, 1)
        if use_viewdirs:
            self.feature = nn.Linear(n_in, width)
            self.view_layer = nn.Linear(width + self.in_dirs, view_width)
            self.rgb_head = nn.Linear(view_width, 3)
        else:
            self.rgb_head = nn.Linear(n_in, 3)

    def config(self) -> dict:
        """The constructor arguments (to rebuild the model from a checkpoint)."""
        return dict(depth=self.depth, width=self.width, skips=list(self.skips), pos_freqs=self.pos_freqs,
                    dir_freqs=self.dir_freqs, use_viewdirs=self.use_viewdirs, view_width=self.view_width,
                    density=self.density)

    def trunk_features(self, pts: torch.Tensor) -> torch.Tensor:
        x = positional_encoding(pts, self.pos_freqs)
        h = x
        for i, layer in enumerate(self.trunk):
            h = F.relu(layer(h))
            if i in self.skips:
                h = torch.cat([x, h], dim=-1)
        return h

    def forward(self, pts: torch.Tensor, viewdirs: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Colour and density at points seen from directions.

        Args:
            pts: ``(..., 3)`` world points.
            viewdirs: ``(..., 3)`` unit viewing directions (needed when ``use_viewdirs``).

        Returns:
            ``rgb (..., 3)`` in [0, 1] and ``sigma (...)`` >= 0.
        """
        if pts.shape[-1] != 3:
            raise KitInputError(f"pts has shape {tuple(pts.shape)}: expected (..., 3) points")
        h = self.trunk_features(pts)
        sigma = density_activation(self.sigma_head(h)[..., 0], self.density)
        if self.use_viewdirs:
            if viewdirs is None or viewdirs.shape != pts.shape:
                got = None if viewdirs is None else tuple(viewdirs.shape)
                raise KitInputError(f"viewdirs has shape {got}: expected {tuple(pts.shape)}, one unit direction per point")
            e = positional_encoding(viewdirs, self.dir_freqs)
            h = F.relu(self.view_layer(torch.cat([self.feature(h), e], dim=-1)))
        rgb = torch.sigmoid(self.rgb_head(h))
        return rgb, sigma

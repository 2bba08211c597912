"""Notebook 07 (the NeRF model, PSNR): classic mistakes, honest solutions and trivial answers, run through its checks.

The honest networks call ``positional_encoding`` as the notebook's exercise does (here the
reference's, imported below; in a notebook the student's own, which the check replaces by the
reference's values of its points while it runs).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from course_lib.checks import nerf_model as gnm
from course_lib.nerf.encoding import positional_encoding
from tests.checks.catalogue import Honest, Mistake


# ============================================================================ honest solutions


class NeRF(nn.Module):
    """Plain code, as the docstring describes it: trunk, density head, feature, view layer, RGB head."""

    def __init__(self, depth=8, width=256, skips=(4,), pos_freqs=10, dir_freqs=4, use_viewdirs=True, view_width=128):
        super().__init__()
        self.skips, self.pos_freqs, self.dir_freqs, self.use_viewdirs = skips, pos_freqs, dir_freqs, use_viewdirs
        n_pos, n_dir = 3 + 6 * pos_freqs, 3 + 6 * dir_freqs
        trunk, n_in = [], n_pos
        for i in range(depth):
            trunk.append(nn.Linear(n_in, width))
            n_in = width + n_pos if i in skips else width
        self.trunk = nn.ModuleList(trunk)
        self.sigma_head = nn.Linear(n_in, 1)
        if not use_viewdirs:
            self.rgb_head = nn.Linear(n_in, 3)
            return
        self.feature = nn.Linear(n_in, width)
        self.view_layer = nn.Linear(width + n_dir, view_width)
        self.rgb_head = nn.Linear(view_width, 3)

    def forward(self, pts, viewdirs):
        x = positional_encoding(pts, self.pos_freqs)
        h = x
        for i, layer in enumerate(self.trunk):
            h = torch.relu(layer(h))
            if i in self.skips:
                h = torch.cat([x, h], dim=-1)
        sigma = torch.relu(self.sigma_head(h)).squeeze(-1)
        if not self.use_viewdirs:
            return torch.sigmoid(self.rgb_head(h)), sigma
        d = positional_encoding(viewdirs, self.dir_freqs)
        v = torch.relu(self.view_layer(torch.cat([self.feature(h), d], dim=-1)))
        return torch.sigmoid(self.rgb_head(v)), sigma


class NeRF__heads_first_other_orders(nn.Module):
    """The heads defined before the trunk, the skip as cat([h, γ(x)]), the colour input as cat([γ(d), feature])."""

    def __init__(self, depth=8, width=256, skips=(4,), pos_freqs=10, dir_freqs=4, use_viewdirs=True, view_width=128):
        super().__init__()
        self.cfg = dict(skips=set(skips), Lx=pos_freqs, Ld=dir_freqs, views=use_viewdirs)
        enc_x, enc_d = 3 * (1 + 2 * pos_freqs), 3 * (1 + 2 * dir_freqs)
        last_in = width + enc_x if depth - 1 in skips else width
        self.density = nn.Linear(last_in, 1)
        if use_viewdirs:
            self.feat = nn.Linear(last_in, width)
            self.views = nn.Sequential(nn.Linear(enc_d + width, view_width), nn.ReLU())
        self.color = nn.Linear(view_width if use_viewdirs else last_in, 3)
        sizes = [enc_x] + [width + (enc_x if i in skips else 0) for i in range(depth - 1)]
        self.layers = nn.ModuleList(nn.Linear(n, width) for n in sizes)

    def forward(self, pts, viewdirs):
        gx = positional_encoding(pts, self.cfg["Lx"])
        h = gx
        for i, lin in enumerate(self.layers):
            h = F.relu(lin(h))
            h = torch.cat((h, gx), -1) if i in self.cfg["skips"] else h
        sigma = F.relu(self.density(h))[..., 0]
        if not self.cfg["views"]:
            return torch.sigmoid(self.color(h)), sigma
        rgb = torch.sigmoid(self.color(self.views(torch.cat((positional_encoding(viewdirs, self.cfg["Ld"]),
                                                                 self.feat(h)), -1))))
        return rgb, sigma


def psnr(mse):
    return -10.0 * torch.log10(torch.as_tensor(mse))


def psnr__math_float(mse):
    return 10 * math.log10(1.0 / float(mse))


# ============================================================================ buggy versions


def _variant(density="relu", skip="encoded", trunk_relu=True, feature_relu=False, rgb="sigmoid", use_dirs=True,
             sigma_after_view=False):
    """The plain NeRF above with one thing changed, as a student would get it wrong."""

    class Buggy(NeRF):
        def __init__(self, depth=8, width=256, skips=(4,), pos_freqs=10, dir_freqs=4, use_viewdirs=True,
                     view_width=128):
            super().__init__(depth, width, skips, pos_freqs, dir_freqs, use_viewdirs, view_width)
            if skip == "none":
                self.skips = ()
                self.trunk = nn.ModuleList(nn.Linear(3 + 6 * pos_freqs if i == 0 else width, width)
                                           for i in range(depth))
            elif skip == "raw":
                self.trunk = nn.ModuleList(nn.Linear(3 + 6 * pos_freqs if i == 0 else width + (3 if i - 1 in skips
                                                     else 0), width) for i in range(depth))
            if not use_dirs and use_viewdirs:
                self.view_layer = nn.Linear(width, view_width)

        def forward(self, pts, viewdirs):
            x = positional_encoding(pts, self.pos_freqs)
            h = x
            for i, layer in enumerate(self.trunk):
                h = torch.relu(layer(h)) if trunk_relu else layer(h)
                if i in self.skips:
                    h = torch.cat([pts if skip == "raw" else x, h], dim=-1)
            raw = self.sigma_head(h)[..., 0]
            sigma = {"relu": torch.relu, "sigmoid": torch.sigmoid, "none": lambda r: r, "softplus": F.softplus,
                     "exp": torch.exp}[density](raw)
            if not self.use_viewdirs:  # the one documented branch without the view: as the plain NeRF
                return torch.sigmoid(self.rgb_head(h)), torch.relu(raw)
            feat = torch.relu(self.feature(h)) if feature_relu else self.feature(h)
            d = positional_encoding(viewdirs, self.dir_freqs)
            v = torch.relu(self.view_layer(torch.cat([feat, d], dim=-1) if use_dirs else feat))
            out = self.rgb_head(v)
            if sigma_after_view:
                sigma = torch.relu(raw + v.mean(-1))
            return (torch.sigmoid(out) if rgb == "sigmoid" else out), sigma

    return Buggy


def psnr_sign(mse):
    return 10 * torch.log10(torch.as_tensor(mse))


def psnr_natural_log(mse):
    return -10 * torch.log(torch.as_tensor(mse))


def psnr_peak_255(mse):
    return 10 * torch.log10(255.0 ** 2 / torch.as_tensor(mse))


def psnr_factor_20(mse):
    return -20 * torch.log10(torch.as_tensor(mse))


def psnr_no_factor(mse):
    return -torch.log10(torch.as_tensor(mse))


# ============================================================================ the catalogue

M = Mistake
MISTAKES = [
    M("NeRF", "sigmoid on the density", gnm.check_nerf_model, _variant(density="sigmoid"), ("sigmoid", "torch.relu"),
      defining="ReLU density"),
    M("NeRF", "no activation on the density", gnm.check_nerf_model, _variant(density="none"), ("no activation",),
      defining="ReLU density"),
    M("NeRF", "softplus on the density (near miss)", gnm.check_nerf_model, _variant(density="softplus"),
      ("softplus",), defining="ReLU density"),
    M("NeRF", "no skip connection", gnm.check_nerf_model, _variant(skip="none"), ("no skip connection",),
      defining="skip input"),
    M("NeRF", "skip concatenates the raw x", gnm.check_nerf_model, _variant(skip="raw"), ("raw position",),
      defining="skip input"),
    M("NeRF", "no ReLU in the trunk", gnm.check_nerf_model, _variant(trunk_relu=False), ("no relu after the trunk",)),
    M("NeRF", "ReLU on the feature layer (near miss)", gnm.check_nerf_model, _variant(feature_relu=True),
      ("relu on the feature layer",)),
    M("NeRF", "no sigmoid on rgb", gnm.check_nerf_model, _variant(rgb="raw"), ("no sigmoid",)),
    M("NeRF", "view direction not used", gnm.check_nerf_model, _variant(use_dirs=False),
      ("view direction is not used",)),
    M("NeRF", "density depends on the view", gnm.check_nerf_model, _variant(sigma_after_view=True),
      ("sigma changes with the viewing direction",)),
    M("psnr", "sign flipped", gnm.check_psnr, psnr_sign, ("sign is flipped",)),
    M("psnr", "natural logarithm", gnm.check_psnr, psnr_natural_log, ("natural logarithm",)),
    M("psnr", "peak 255", gnm.check_psnr, psnr_peak_255, ("peak of 255",)),
    M("psnr", "factor 20 with the MSE", gnm.check_psnr, psnr_factor_20, ("factor 20",)),
    M("psnr", "factor 10 missing", gnm.check_psnr, psnr_no_factor, ("factor 10 is missing",)),
]

#: Correct solutions: they must score full marks.
HONEST = [
    Honest("NeRF", "plain code, as documented", gnm.check_nerf_model, NeRF),
    Honest("NeRF", "heads first, skip [h, γ(x)], colour input [γ(d), feature]", gnm.check_nerf_model,
           NeRF__heads_first_other_orders),
    Honest("psnr", "torch", gnm.check_psnr, psnr),
    Honest("psnr", "math.log10 of a float", gnm.check_psnr, psnr__math_float),
]


def _constant_nerf():
    class ConstantNeRF(NeRF):
        """The right layers, a forward that returns constants."""

        def forward(self, pts, viewdirs):
            return torch.full((*pts.shape[:-1], 3), 0.5), torch.zeros(pts.shape[:-1])

    return ConstantNeRF


def _trivial() -> list:
    z = np.zeros  # noqa: F841
    return [
        (gnm.check_nerf_model, _constant_nerf()),
        (gnm.check_psnr, lambda mse: torch.tensor(0.0)),
    ]


#: Constants of the right shape: they pass the shape gates and trivially satisfied properties, and must earn nothing.
TRIVIAL = _trivial()


# ============================================================================ issue 29: written as students write them
# From the notebook's text and the stub's docstring, with an error students make; then valid variants.

class NeRF_viewdirs_in_trunk(NeRF):
    """γ(d) concatenated with γ(x) at the input of the trunk (and again at the skip): the density sees the view."""

    def __init__(self, depth=8, width=256, skips=(4,), pos_freqs=10, dir_freqs=4, use_viewdirs=True, view_width=128):
        super().__init__(depth, width, skips, pos_freqs, dir_freqs, use_viewdirs, view_width)
        n_in = 3 + 6 * pos_freqs + 3 + 6 * dir_freqs
        layers = []
        for i in range(depth):
            layers.append(nn.Linear(n_in, width))
            n_in = width + 3 + 6 * pos_freqs + 3 + 6 * dir_freqs if i in skips else width
        self.trunk = nn.ModuleList(layers)
        self.sigma_head = nn.Linear(n_in, 1)
        self.feature = nn.Linear(n_in, width)
        self.view_layer = nn.Linear(width, view_width)
        if not use_viewdirs:
            self.rgb_head = nn.Linear(n_in, 3)

    def forward(self, pts, viewdirs):
        x = torch.cat([positional_encoding(pts, self.pos_freqs), positional_encoding(viewdirs, self.dir_freqs)], -1)
        h = x
        for i, layer in enumerate(self.trunk):
            h = torch.relu(layer(h))
            if i in self.skips:
                h = torch.cat([x, h], -1)
        sigma = torch.relu(self.sigma_head(h)).squeeze(-1)
        if not self.use_viewdirs:
            return torch.sigmoid(self.rgb_head(h)), sigma
        rgb = torch.sigmoid(self.rgb_head(torch.relu(self.view_layer(self.feature(h)))))
        return rgb, sigma


class NeRF_density_after_feature(NeRF):
    """sigma read off the feature layer's output instead of the trunk's."""

    def __init__(self, depth=8, width=256, skips=(4,), pos_freqs=10, dir_freqs=4, use_viewdirs=True, view_width=128):
        super().__init__(depth, width, skips, pos_freqs, dir_freqs, use_viewdirs, view_width)
        self.sigma_head = nn.Linear(width, 1)

    def forward(self, pts, viewdirs):
        if not self.use_viewdirs:  # as documented; the mistake is in the view branch
            return super().forward(pts, viewdirs)
        x = positional_encoding(pts, self.pos_freqs)
        h = x
        for i, layer in enumerate(self.trunk):
            h = torch.relu(layer(h))
            if i in self.skips:
                h = torch.cat([x, h], -1)
        feat = self.feature(h)
        sigma = torch.relu(self.sigma_head(feat)).squeeze(-1)
        d = positional_encoding(viewdirs, self.dir_freqs)
        return torch.sigmoid(self.rgb_head(torch.relu(self.view_layer(torch.cat([feat, d], -1))))), sigma


class NeRF_skip_after_fifth(NeRF):
    """The skip one layer late: "after the 4th layer" counted from 1 (i == 5 in 0-based indices)."""

    def __init__(self, depth=8, width=256, skips=(4,), pos_freqs=10, dir_freqs=4, use_viewdirs=True, view_width=128):
        super().__init__(depth, width, tuple(s + 1 for s in skips), pos_freqs, dir_freqs, use_viewdirs, view_width)


class NeRF_raw_viewdirs(NeRF):
    """The viewing direction fed unencoded into the colour branch (3 inputs, not γ(d))."""

    def __init__(self, depth=8, width=256, skips=(4,), pos_freqs=10, dir_freqs=4, use_viewdirs=True, view_width=128):
        super().__init__(depth, width, skips, pos_freqs, dir_freqs, use_viewdirs, view_width)
        self.view_layer = nn.Linear(width + 3, view_width)

    def forward(self, pts, viewdirs):
        if not self.use_viewdirs:  # as documented; the mistake is in the view branch
            return super().forward(pts, viewdirs)
        x = positional_encoding(pts, self.pos_freqs)
        h = x
        for i, layer in enumerate(self.trunk):
            h = torch.relu(layer(h))
            if i in self.skips:
                h = torch.cat([x, h], -1)
        sigma = torch.relu(self.sigma_head(h)).squeeze(-1)
        v = torch.relu(self.view_layer(torch.cat([self.feature(h), viewdirs], -1)))
        return torch.sigmoid(self.rgb_head(v)), sigma


def psnr__rmse_twenty(mse):
    """20 log10(1 / RMSE): the same number."""
    return 20 * torch.log10(1 / torch.sqrt(torch.as_tensor(mse)))


def psnr__natural_log_ratio(mse):
    """10 ln(1 / mse) / ln 10 with numpy."""
    return 10 * np.log(1 / float(mse)) / np.log(10)


def psnr_mse_in_percent(mse):  # the MSE of 8-bit images expected: mse * 255 ** 2 / 255 ** 2 "to be safe" ... then 255
    return 10 * torch.log10(255.0 / torch.as_tensor(mse))


MISTAKES += [
    M("NeRF", "view direction fed into the trunk", gnm.check_nerf_model, NeRF_viewdirs_in_trunk,
      ("viewing direction",), batch="29"),
    M("NeRF", "density off the feature layer", gnm.check_nerf_model, NeRF_density_after_feature, ("density",),
      batch="29"),
    M("NeRF", "skip one layer late", gnm.check_nerf_model, NeRF_skip_after_fifth, ("layer",),
      batch="29"),
    M("NeRF", "unencoded viewing direction", gnm.check_nerf_model, NeRF_raw_viewdirs, ("γ(d)",), batch="29"),
    M("psnr", "255 / mse", gnm.check_psnr, psnr_mse_in_percent, ("-10 log10(mse)",), batch="29"),
]

HONEST += [
    Honest("psnr", "20 log10(1 / RMSE)", gnm.check_psnr, psnr__rmse_twenty),
    Honest("psnr", "natural logs, numpy", gnm.check_psnr, psnr__natural_log_ratio),
]

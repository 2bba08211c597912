"""The NeRF check cells (notebooks 06-08): the reference passes every check, typical mistakes are named.

Each typical mistake is written as a small function, the way a student would write it; the test
runs the check on it and asserts that the printed verdict names the mistake. The fixtures behind
the checks must be current (rebuilt from the reference and compared).
"""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from course_lib.checks import nerf_data, nerf_model, nerf_rendering
from course_lib.nerf import encoding, rays, render
from course_lib.nerf.model import NeRF


def run_check(capsys, check, fn) -> str:
    capsys.readouterr()
    check(fn)
    return capsys.readouterr().out


def assert_passes(out: str) -> None:
    assert "all " in out and "checks passed" in out and "✘" not in out, out


def assert_names(out: str, *words: str) -> None:
    assert "✘" in out, out
    for w in words:
        assert w.lower() in out.lower(), f"expected {w!r} in:\n{out}"


# --------------------------------------------------------------------------- references pass


REFERENCES = [
    (nerf_data.check_get_rays, rays.get_rays),
    (nerf_data.check_stratified_samples, rays.stratified_samples),
    (nerf_data.check_query_points, rays.query_points),
    (nerf_data.check_positional_encoding, encoding.positional_encoding),
    (nerf_model.check_nerf_model, NeRF),
    (nerf_model.check_psnr, lambda mse: -10.0 * torch.log10(mse)),
    (nerf_rendering.check_volume_render, render.volume_render),
]


@pytest.mark.parametrize("check,fn", REFERENCES)
def test_reference_passes(capsys, check, fn):
    assert_passes(run_check(capsys, check, fn))


def test_pass_lines_have_no_floats(capsys):
    import re

    out = ""
    for check, fn in REFERENCES:
        out += run_check(capsys, check, fn)
    assert not re.search(r"\d\.\d", out), out


def test_not_implemented(capsys):
    def todo(*args, **kwargs):
        raise NotImplementedError

    out = run_check(capsys, nerf_data.check_get_rays, todo)
    assert "not implemented yet" in out


# --------------------------------------------------------------------------- get_rays mistakes


def make_get_rays(indexing="xy", signs=(1, 1, 1), center=None, offset=0.0, normalize=False,
                  rotate="R", expand=True):
    def get_rays(H, W, K, c2w):
        u = torch.arange(W, dtype=torch.float32)
        v = torch.arange(H, dtype=torch.float32)
        uu, vv = torch.meshgrid(u, v, indexing=indexing)
        cx, cy = (K[0, 2], K[1, 2]) if center is None else (W / 2, H / 2)
        d = torch.stack([signs[0] * (uu + offset - cx) / K[0, 0], signs[1] * (vv + offset - cy) / K[1, 1],
                         signs[2] * torch.ones_like(uu)], -1)
        if normalize:
            d = d / d.norm(dim=-1, keepdim=True)
        R = c2w[:3, :3]
        if rotate == "R":
            d = d @ R.T
        elif rotate == "RT":
            d = d @ R
        o = c2w[:3, 3]
        return (o.expand(d.shape) if expand else o), d
    return get_rays


@pytest.mark.parametrize("kwargs,words", [
    ({"indexing": "ij"}, ["meshgrid's ij/xy"]),
    ({"signs": (1, -1, -1)}, ["OpenGL"]),
    ({"signs": (1, 1, -1)}, ["backwards"]),
    ({"signs": (1, -1, 1)}, ["y is flipped"]),
    ({"center": "half"}, ["principal point"]),
    ({"offset": 0.5}, ["half-pixel"]),
    ({"normalize": True}, ["normalized"]),
    ({"rotate": "RT"}, ["transpose"]),
    ({"rotate": None}, ["not rotated"]),
    ({"expand": False}, ["repeat the camera centre"]),
])
def test_get_rays_mistakes(capsys, kwargs, words):
    out = run_check(capsys, nerf_data.check_get_rays, make_get_rays(**kwargs))
    assert_names(out, *words)


# --------------------------------------------------------------------------- stratified sampling mistakes


def make_stratified(always_jitter=False, never_jitter=False, scale="bin", per_sample=True, use_generator=True,
                    endpoint=True):
    def stratified_samples(near, far, n_samples, n_rays, perturb, generator=None):
        if endpoint:
            z = torch.linspace(near, far, n_samples).expand(n_rays, n_samples)
        else:
            z = torch.linspace(near, far, n_samples + 1)[:-1].expand(n_rays, n_samples)
        if (perturb or always_jitter) and not never_jitter:
            g = generator if use_generator else None
            shape = (n_rays, n_samples) if per_sample else (n_rays, 1)
            u = torch.rand(shape, generator=g)
            mids = 0.5 * (z[:, 1:] + z[:, :-1])
            lower = torch.cat([z[:, :1], mids], -1)
            upper = torch.cat([mids, z[:, -1:]], -1)
            if scale == "bin":
                z = lower + (upper - lower) * u
            else:
                z = z + (far - near) * u
        return z
    return stratified_samples


@pytest.mark.parametrize("kwargs,words", [
    ({"always_jitter": True}, ["jitter in evaluation"]),
    ({"never_jitter": True}, ["no jitter"]),
    ({"scale": "range"}, ["leave their bin"]),
    ({"per_sample": False}, ["same jitter for every sample"]),
    ({"use_generator": False}, ["generator=generator"]),
    ({"endpoint": False}, ["the last depth is not far"]),
])
def test_stratified_mistakes(capsys, kwargs, words):
    out = run_check(capsys, nerf_data.check_stratified_samples, make_stratified(**kwargs))
    assert_names(out, *words)


# --------------------------------------------------------------------------- query points mistakes


def query_swapped(rays_o, rays_d, z_vals):
    return rays_d[:, None, :] + z_vals[..., None] * rays_o[:, None, :]


def query_flat(rays_o, rays_d, z_vals):
    return (rays_o[:, None, :] + z_vals[..., None] * rays_d[:, None, :]).reshape(-1, 3)


def test_query_points_mistakes(capsys):
    assert_names(run_check(capsys, nerf_data.check_query_points, query_swapped), "swapped")
    assert_names(run_check(capsys, nerf_data.check_query_points, query_flat), "has shape")


# --------------------------------------------------------------------------- encoding mistakes


def make_encoding(identity=True, pi=True, cos_first=False, blocks=False, start=0):
    def positional_encoding(x, n_freqs, include_input=True):
        sins, coss, parts = [], [], []
        for k in range(start, start + n_freqs):
            w = 2.0 ** k * (math.pi if pi else 1.0)
            sins.append(torch.sin(w * x))
            coss.append(torch.cos(w * x))
            parts += [coss[-1], sins[-1]] if cos_first else [sins[-1], coss[-1]]
        if blocks:
            parts = sins + coss
        if include_input and identity:
            parts = [x] + parts
        return torch.cat(parts, -1)
    return positional_encoding


@pytest.mark.parametrize("kwargs,words", [
    ({"identity": False}, ["missing identity term"]),
    ({"pi": False}, ["missing pi factor"]),
    ({"cos_first": True}, ["sin/cos order", "cos before sin"]),
    ({"blocks": True}, ["sin/cos order", "all sines first"]),
    ({"start": 1}, ["wrong frequencies"]),
])
def test_encoding_mistakes(capsys, kwargs, words):
    out = run_check(capsys, nerf_data.check_positional_encoding, make_encoding(**kwargs))
    assert_names(out, *words)


# --------------------------------------------------------------------------- model mistakes


def make_nerf(skip=True, sigmoid=True, relu_sigma=True, sigma_from_view=False, use_dirs=True, squeeze=True,
              cat_order="xh", no_relu=False):
    enc = encoding.positional_encoding

    class StudentNeRF(nn.Module):
        def __init__(self, depth=8, width=256, skips=(4,), pos_freqs=10, dir_freqs=4, use_viewdirs=True,
                     view_width=128):
            super().__init__()
            self.skips = skips if skip else ()
            self.Lx, self.Ld = pos_freqs, dir_freqs
            nx, nd = 3 * (1 + 2 * pos_freqs), 3 * (1 + 2 * dir_freqs)
            layers, n_in = [], nx
            for i in range(depth):
                layers.append(nn.Linear(n_in, width))
                n_in = width + (nx if i in self.skips else 0)
            self.trunk = nn.ModuleList(layers)
            self.sigma_head = nn.Linear(n_in if not sigma_from_view else view_width, 1)
            self.use_viewdirs = use_viewdirs
            if not use_viewdirs:
                self.trunk_rgb = nn.Linear(n_in, 3)
            self.feature = nn.Linear(n_in, width)
            self.view_layer = nn.Linear(width + (nd if use_dirs else 0), view_width)
            self.rgb_head = nn.Linear(view_width, 3)

        def forward(self, pts, viewdirs):
            x = enc(pts, self.Lx)
            h = x
            for i, layer in enumerate(self.trunk):
                h = layer(h) if no_relu else F.relu(layer(h))
                if i in self.skips:
                    h = torch.cat([x, h] if cat_order == "xh" else [h, x], -1)
            if not self.use_viewdirs:  # as documented: the colour off the trunk
                return torch.sigmoid(self.trunk_rgb(h)), F.relu(self.sigma_head(h))[..., 0]
            sigma = None if sigma_from_view else self.sigma_head(h)
            f = self.feature(h)
            if use_dirs:
                f = torch.cat([f, enc(viewdirs, self.Ld)], -1)
            g = F.relu(self.view_layer(f))
            if sigma_from_view:
                sigma = self.sigma_head(g)
            raw = self.rgb_head(g)
            rgb = torch.sigmoid(raw) if sigmoid else raw
            sigma = F.relu(sigma) if relu_sigma else sigma
            return rgb, (sigma[..., 0] if squeeze else sigma)

    return StudentNeRF


@pytest.mark.parametrize("kwargs,words", [
    ({"skip": False}, ["no skip connection"]),
    ({"sigmoid": False}, ["no sigmoid"]),
    ({"relu_sigma": False}, ["non-negative"]),
    ({"sigma_from_view": True}, ["sigma changes with the viewing direction"]),
    ({"use_dirs": False}, ["view direction is not used"]),
    ({"squeeze": False}, ["drop the last axis"]),
    ({"no_relu": True}, ["with the reference's weights", "no ReLU after the trunk layers"]),
])
def test_model_mistakes(capsys, kwargs, words):
    out = run_check(capsys, nerf_model.check_nerf_model, make_nerf(**kwargs))
    assert_names(out, *words)


def test_student_style_reference_passes(capsys):
    assert_passes(run_check(capsys, nerf_model.check_nerf_model, make_nerf()))


def test_the_skip_order_is_a_convention(capsys):
    """[h, γ(x)] is the same maths as the docstring's [γ(x), h]: accepted (the probe weights are permuted)."""
    assert_passes(run_check(capsys, nerf_model.check_nerf_model, make_nerf(cat_order="hx")))


def test_a_network_with_the_right_layers_and_constant_outputs_earns_nothing():
    from course_lib.checks.core import score
    from tests.checks.catalogue import run_check as run
    from tests.checks.catalogue.nerf_model import TRIVIAL

    result, out = run(*TRIVIAL[0])
    assert score(result) == 0.0, out


def test_nerf_is_fed_the_reference_encoding(capsys):
    """A NeRF whose notebook has no working positional_encoding is graded with the reference's values."""
    import inspect
    import sys
    import types

    from tests.checks.catalogue import nerf_model as cat

    mod = types.ModuleType("student_nb07")
    exec("import torch\nfrom torch import nn\n"  # noqa: S102 - a notebook, in a test
         "def positional_encoding(x, n_freqs, include_input=True):\n    raise NotImplementedError\n\n"
         + inspect.getsource(cat.NeRF), mod.__dict__)
    sys.modules[mod.__name__] = mod
    broken = mod.positional_encoding
    try:
        assert_passes(run_check(capsys, nerf_model.check_nerf_model, mod.NeRF))
        assert mod.positional_encoding is broken  # put back after the check
    finally:
        del sys.modules[mod.__name__]


def test_the_encoding_table_answers_only_for_its_points():
    import numpy as np

    from course_lib.checks.core import load_fixture

    f = load_fixture("nerf_model")
    table = nerf_model.encoding_table(f["enc_rows"], f["enc_values"])
    pts = torch.as_tensor(f["pts"])
    got = table(pts, 3)
    assert got.shape == (*pts.shape[:-1], 21)
    assert torch.allclose(got, encoding.positional_encoding(pts, 3), atol=1e-5)
    assert torch.allclose(table(pts, 2, include_input=False), encoding.positional_encoding(pts, 2, False), atol=1e-5)
    with pytest.raises(LookupError):
        table(pts + 0.5, 3)
    assert np.isfinite(table(pts.double(), 0).numpy()).all()


def test_psnr_mistakes(capsys):
    assert_names(run_check(capsys, nerf_model.check_psnr, lambda m: 10 * torch.log10(m)), "sign")
    assert_names(run_check(capsys, nerf_model.check_psnr, lambda m: -10 * torch.log(m)), "base-10")


# --------------------------------------------------------------------------- volume rendering mistakes


def make_render(delta=True, norm=True, inclusive=False, white=True, last=1e10, depth_norm=False):
    def volume_render(rgb, sigma, z_vals, rays_d, white_background=True):
        d = z_vals[:, 1:] - z_vals[:, :-1]
        d = torch.cat([d, torch.full_like(z_vals[:, :1], last)], -1)
        if norm:
            d = d * rays_d.norm(dim=-1, keepdim=True)
        alpha = 1 - torch.exp(-sigma * d) if delta else 1 - torch.exp(-sigma)
        keep = torch.cumprod(1 - alpha + 1e-10, -1)
        if not inclusive:
            keep = torch.cat([torch.ones_like(keep[:, :1]), keep[:, :-1]], -1)
        w = alpha * keep
        acc = w.sum(-1)
        rgb_map = (w[..., None] * rgb).sum(-2)
        if white_background and white:
            rgb_map = rgb_map + (1 - acc[:, None])
        depth = (w * z_vals).sum(-1)
        if depth_norm:
            depth = depth / acc.clamp_min(1e-10)
        return {"rgb_map": rgb_map, "depth_map": depth, "acc_map": acc, "weights": w}
    return volume_render


@pytest.mark.parametrize("kwargs,words", [
    ({"delta": False}, ["forgot delta"]),
    ({"norm": False}, ["not scaled by |d|"]),
    ({"inclusive": True}, ["inclusive cumprod"]),
    ({"white": False}, ["no white background"]),
    ({"last": 0.0}, ["last interval"]),
    ({"depth_norm": True}, ["divided by acc_map"]),
])
def test_render_mistakes(capsys, kwargs, words):
    out = run_check(capsys, nerf_rendering.check_volume_render, make_render(**kwargs))
    assert_names(out, *words)


def test_render_wrong_return_type(capsys):
    out = run_check(capsys, nerf_rendering.check_volume_render, lambda *a, **k: (a[0].sum(1), None))
    assert_names(out, "return a dict")


def test_check_modules_do_not_import_the_reference():
    """A student release without course_lib.nerf still runs the check cells (fixtures only)."""
    import subprocess
    import sys

    code = ("import sys, course_lib.checks.nerf_data, course_lib.checks.nerf_model, course_lib.checks.nerf_rendering; "
            "bad = [m for m in sys.modules if m.startswith('course_lib.nerf')]; assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True)

"""Volume rendering against hand computations: a slab of constant density, the last interval,
the white background, gradcheck; hierarchical sampling; render_rays/render_image."""

import math

import numpy as np
import pytest
import torch

from course_lib.nerf.render import render_image, render_rays, sample_pdf, volume_render


def _slab(sigma_val=0.7, n=101, a=2.0, b=4.0):
    """One ray along +z from the origin; density sigma_val for z in [a, b), else 0; samples every 0.05."""
    z = torch.linspace(0.0, 5.0, n, dtype=torch.float64)[None]
    sigma = torch.where((z >= a - 1e-9) & (z < b - 1e-9), torch.tensor(sigma_val, dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64))
    return z, sigma


def test_slab_transmittance_and_weights():
    s, a, b = 0.7, 2.0, 4.0
    z, sigma = _slab(s, a=a, b=b)
    rgb = torch.full((*z.shape, 3), 0.25, dtype=torch.float64)
    out = volume_render(rgb, sigma, z, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), white_background=False)
    T = out["transmittance"][0]
    # transmittance behind the slab is exp(-sigma * L) with L = b - a
    behind = int(torch.nonzero(z[0] >= b + 0.5)[0])
    assert T[behind].item() == pytest.approx(math.exp(-s * (b - a)), rel=1e-6)
    # T = 1 in front of the slab (exclusive product: the first sample sees T = 1)
    assert T[0].item() == 1.0 and T[int(torch.nonzero(z[0] >= a - 1e-9)[0])].item() == pytest.approx(1.0)
    # the weights sum to the opacity 1 - exp(-sigma L); the colour is 0.25 of it
    acc = 1 - math.exp(-s * (b - a))
    assert out["acc_map"].item() == pytest.approx(acc, rel=1e-6)
    assert out["weights"].sum().item() == pytest.approx(acc, rel=1e-6)
    np.testing.assert_allclose(out["rgb_map"][0].numpy(), 0.25 * acc, rtol=1e-6)
    # with a white background the light that passes is white
    white = volume_render(rgb, sigma, z, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))
    np.testing.assert_allclose(white["rgb_map"][0].numpy(), 0.25 * acc + (1 - acc), rtol=1e-6)


def test_ray_direction_norm_scales_delta():
    z, sigma = _slab(0.7)
    rgb = torch.zeros((*z.shape, 3), dtype=torch.float64)
    out = volume_render(rgb, sigma, z, torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64), white_background=False)
    # |d| = 2: the slab is 4 world units thick
    assert out["acc_map"].item() == pytest.approx(1 - math.exp(-0.7 * 4.0), rel=1e-6)
    # depth is in units of z_vals: an opaque slab at z = 2 gives depth ~2
    z2, s2 = _slab(1e3)
    o2 = volume_render(rgb, s2, z2, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), white_background=False)
    assert o2["depth_map"].item() == pytest.approx(2.0, abs=1e-6)


def test_last_interval_is_infinite():
    z = torch.tensor([[1.0, 2.0, 3.0]])
    sigma = torch.tensor([[0.0, 0.0, 0.01]])  # a faint density at the last sample only
    rgb = torch.tensor([[[0.0, 0, 0], [0, 0, 0], [0.2, 0.4, 0.6]]])
    out = volume_render(rgb, sigma, z, torch.tensor([[0.0, 0, 1]]))
    assert out["weights"][0, 2].item() == pytest.approx(1.0)  # 1 - exp(-0.01 * 1e10) = 1
    np.testing.assert_allclose(out["rgb_map"][0].numpy(), [0.2, 0.4, 0.6], atol=1e-6)
    # empty ray: nothing stops it, the white background shows
    out0 = volume_render(rgb, torch.zeros_like(sigma), z, torch.tensor([[0.0, 0, 1]]))
    np.testing.assert_allclose(out0["rgb_map"][0].numpy(), [1, 1, 1])
    assert out0["acc_map"].item() == 0.0


def test_gradcheck_float64():
    g = torch.Generator().manual_seed(0)
    R, S = 2, 5
    rgb = torch.rand(R, S, 3, generator=g, dtype=torch.float64, requires_grad=True)
    sigma = (0.2 + torch.rand(R, S, generator=g, dtype=torch.float64)).requires_grad_()
    z = torch.sort(torch.rand(R, S, generator=g, dtype=torch.float64) * 4 + 2, dim=-1)[0]
    d = torch.randn(R, 3, generator=g, dtype=torch.float64)

    def f(rgb, sigma):
        o = volume_render(rgb, sigma, z, d)
        return o["rgb_map"], o["depth_map"], o["acc_map"]

    assert torch.autograd.gradcheck(f, (rgb, sigma), eps=1e-6, atol=1e-5)


def test_sample_pdf_concentrates_on_the_weight():
    bins = torch.linspace(0, 10, 11)[None].expand(3, 11).contiguous()
    w = torch.zeros(3, 10)
    w[:, 6] = 1.0  # all weight in [6, 7)
    z = sample_pdf(bins, w, 64)
    assert z.shape == (3, 64)
    assert ((z >= 6) & (z <= 7)).float().mean() > 0.95
    assert (z[:, 1:] >= z[:, :-1]).all()
    g = torch.Generator().manual_seed(1)
    zp = sample_pdf(bins, w, 64, perturb=True, generator=g)
    assert ((zp >= 6) & (zp <= 7)).float().mean() > 0.95
    # uniform weights -> uniform samples
    zu = sample_pdf(bins, torch.ones(3, 10), 11)
    np.testing.assert_allclose(zu[0].numpy(), np.linspace(0, 10, 11), atol=1e-3)


class _Sphere(torch.nn.Module):
    """A hand-made field: a red sphere of radius 1 at the origin, high density inside."""

    def __init__(self):
        super().__init__()
        self.dummy = torch.nn.Parameter(torch.zeros(1))

    def forward(self, pts, viewdirs=None):
        inside = (pts.norm(dim=-1) < 1.0).to(pts.dtype)
        rgb = torch.zeros_like(pts)
        rgb[..., 0] = 1.0
        return rgb, 50.0 * inside + 0 * self.dummy


def test_render_rays_and_image_sphere():
    m = _Sphere()
    o = torch.tensor([[0.0, 0, -4], [0, 3, -4]])
    d = torch.tensor([[0.0, 0, 1], [0, 0, 1]])
    with torch.no_grad():
        out = render_rays(m, o, d, 2.0, 6.0, 64, n_importance=32, perturb=False)
    assert out["z_vals"].shape == (2, 96) and "rgb_map_coarse" in out
    np.testing.assert_allclose(out["rgb_map"][0].numpy(), [1, 0, 0], atol=1e-3)  # hits the sphere
    np.testing.assert_allclose(out["rgb_map"][1].numpy(), [1, 1, 1], atol=1e-6)  # misses: white
    assert out["depth_map"][0].item() == pytest.approx(3.0, abs=0.05)  # surface at z = -1
    K = np.array([[8.0, 0, 7.5], [0, 8.0, 7.5], [0, 0, 1]])
    c2w = np.eye(4)
    c2w[:3, 3] = [0, 0, -4]
    img = render_image(m, 16, 16, K, c2w, 2.0, 6.0, 32, chunk=100)
    assert img["rgb"].shape == (16, 16, 3) and img["depth"].shape == (16, 16)
    assert img["acc"][8, 8] > 0.99 and img["acc"][0, 0] < 0.01

"""The NeRF MLP: shapes, ranges, configurable sizes, the skip connection."""

import pytest
import torch

from course_lib.nerf.model import NeRF
from course_lib.validate import KitInputError


def test_paper_model_shapes_and_ranges():
    torch.manual_seed(0)
    m = NeRF()
    assert len(m.trunk) == 8 and m.trunk[0].in_features == 63
    assert m.trunk[5].in_features == 256 + 63  # input concatenated after layer 4 (0-based)
    assert m.view_layer.in_features == 256 + 27 and m.view_layer.out_features == 128
    pts = torch.randn(2, 5, 3)
    dirs = torch.nn.functional.normalize(torch.randn(2, 5, 3), dim=-1)
    rgb, sigma = m(pts, dirs)
    assert rgb.shape == (2, 5, 3) and sigma.shape == (2, 5)
    assert (rgb >= 0).all() and (rgb <= 1).all() and (sigma >= 0).all()
    n_params = sum(p.numel() for p in m.parameters())
    assert 590_000 < n_params < 600_000  # the paper's model: about 595k parameters


def test_small_and_softplus():
    m = NeRF(depth=2, width=16, skips=(), pos_freqs=3, dir_freqs=0, use_viewdirs=False, density="softplus")
    rgb, sigma = m(torch.randn(10, 3))
    assert rgb.shape == (10, 3) and (sigma > 0).all()
    # view directions matter only with use_viewdirs
    m2 = NeRF(depth=2, width=16, pos_freqs=2, dir_freqs=2)
    p = torch.randn(4, 3)
    a, _ = m2(p, torch.tensor([[1.0, 0, 0]]).expand(4, 3))
    b, _ = m2(p, torch.tensor([[0.0, 1, 0]]).expand(4, 3))
    assert not torch.allclose(a, b)


def test_errors():
    with pytest.raises(KitInputError, match="viewdirs"):
        NeRF(depth=2, width=8)(torch.zeros(3, 3))
    with pytest.raises(KitInputError):
        NeRF(density="exp")


# ------------------------------------------------------------------ the grid field of the fast preset


@pytest.mark.parametrize("layout", [torch.contiguous_format, torch.channels_last_3d])
@pytest.mark.parametrize("shape", [(1, 1, 7, 5, 3), (1, 3, 10, 12, 9), (1, 12, 4, 6, 5), (1, 2, 1, 4, 4)])
def test_trilinear_written_out_equals_grid_sample(shape, layout):
    """The grid's gather-based trilinear interpolation: grid_sample's values and gradients (corners, faces, inside)."""
    from torch.nn import functional as F

    from course_lib.nerf.grid import Trilinear

    gen = torch.Generator().manual_seed(0)
    grid = torch.randn(*shape, dtype=torch.float64, generator=gen).contiguous(memory_format=layout).requires_grad_()
    xyz = torch.rand(300, 3, dtype=torch.float64, generator=gen) * 2 - 1
    xyz[:6] = torch.tensor([[-1, -1, -1], [1, 1, 1], [1, -1, 1], [0, 0, 0], [-1, 1, -1], [1, 0.3, -0.2]], dtype=torch.float64)
    ref = F.grid_sample(grid, xyz.reshape(1, -1, 1, 1, 3), mode="bilinear", align_corners=True).reshape(shape[1], -1).T
    out = Trilinear.apply(grid, xyz)
    torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-12)
    w = torch.randn(out.shape, dtype=torch.float64, generator=gen)
    g_ref, = torch.autograd.grad((ref * w).sum(), grid)
    g_out, = torch.autograd.grad((out * w).sum(), grid)
    torch.testing.assert_close(g_out, g_ref, rtol=1e-12, atol=1e-12)
    # points outside the grid read 0
    assert Trilinear.apply(grid, torch.tensor([[1.5, 0.0, 0.0], [0.0, -3.0, 0.0]], dtype=torch.float64)).abs().max() == 0


def test_grid_gradients_written_in_place_are_autograd_ones():
    """write_grads_in_place: backward adds into the kept .grad (no new grid-sized tensor), same values, accumulating."""
    from course_lib.nerf.grid import GridField

    gen = torch.Generator().manual_seed(5)
    ref, fast = (GridField([-1, -1, -1], [1, 1.5, 1], resolution=9, sh_degree=1) for _ in range(2))
    with torch.no_grad():
        for g in (ref.density_grid, ref.feature_grid):
            g.normal_(generator=gen)
    fast.load_state_dict(ref.state_dict())
    assert fast.feature_grid.is_contiguous(memory_format=torch.channels_last_3d)
    fast.write_grads_in_place()
    pts = torch.rand(400, 3, generator=gen) * 2 - 1
    dirs = torch.nn.functional.normalize(torch.randn(400, 3, generator=gen), dim=-1)
    for _ in range(2):  # the second backward accumulates, as autograd does
        for f in (ref, fast):
            rgb, sigma = f(pts, dirs)
            (rgb.square().sum() + sigma.sum()).backward()
    kept = fast.feature_grid.grad
    for a, b in ((ref.density_grid, fast.density_grid), (ref.feature_grid, fast.feature_grid)):
        torch.testing.assert_close(b.grad, a.grad, rtol=1e-5, atol=1e-6)
    fast.zero_grad(set_to_none=False)
    rgb, sigma = fast(pts, dirs)
    (rgb.square().sum() + sigma.sum()).backward()
    assert fast.feature_grid.grad is kept  # the same buffer, zeroed and written again
    torch.testing.assert_close(kept, ref.feature_grid.grad / 2, rtol=1e-5, atol=1e-6)


def test_grid_total_variation_gradient_written_out_equals_autograd():
    from course_lib.nerf.grid import GridField

    g = GridField([-1, -1, -1], [1, 2, 1], resolution=9)
    with torch.no_grad():
        g.density_grid.normal_(generator=torch.Generator().manual_seed(0))
    (0.3 * g.total_variation()).backward()
    ref = g.density_grid.grad.clone()
    g.density_grid.grad = None
    tv = g.add_total_variation_grad(0.3)
    torch.testing.assert_close(tv, g.total_variation().detach())
    torch.testing.assert_close(g.density_grid.grad, ref, rtol=1e-5, atol=1e-9)


def test_grid_spherical_harmonics_colour():
    from course_lib.nerf.grid import GridField, sh_basis
    from course_lib.validate import KitInputError

    d = torch.nn.functional.normalize(torch.randn(500, 3, generator=torch.Generator().manual_seed(1)), dim=-1)
    Y = sh_basis(d, 2)
    assert Y.shape == (500, 9) and torch.all(Y[:, 0] == 1)
    # orthogonal on the sphere: the mean of Y_i Y_j over uniform directions is diagonal (Monte Carlo)
    big = torch.nn.functional.normalize(torch.randn(200_000, 3, generator=torch.Generator().manual_seed(2)), dim=-1)
    gram = (sh_basis(big, 2).T @ sh_basis(big, 2)) / big.shape[0]
    off = gram - torch.diag(torch.diag(gram))
    assert off.abs().max() < 0.02
    rgb_grid = GridField([-1, -1, -1], [1, 1, 1], resolution=6)
    sh_grid = GridField([-1, -1, -1], [1, 1, 1], resolution=6, sh_degree=1)
    assert sh_grid.feature_grid.shape[1] == 12
    with torch.no_grad():
        rgb_grid.feature_grid.normal_(generator=torch.Generator().manual_seed(3))
        sh_grid.feature_grid.zero_()
        sh_grid.feature_grid[:, :3] = rgb_grid.feature_grid  # only the view-independent term
    pts = torch.rand(100, 3) * 1.6 - 0.8
    torch.testing.assert_close(sh_grid.color(pts, d[:100]), rgb_grid.color(pts))
    with torch.no_grad():
        sh_grid.feature_grid[:, 3:6] = 1.0  # Y_1 (-y) term: the colour now depends on the direction
    up, down = torch.tensor([[0.0, 1.0, 0.0]]).expand(100, 3), torch.tensor([[0.0, -1.0, 0.0]]).expand(100, 3)
    assert torch.all(sh_grid.color(pts, down)[:, 0] > sh_grid.color(pts, up)[:, 0])
    with pytest.raises(KitInputError, match="pass viewdirs"):
        sh_grid.color(pts)
    with pytest.raises(KitInputError, match="choose spherical harmonics or the colour MLP"):
        GridField([-1, -1, -1], [1, 1, 1], resolution=6, sh_degree=1, mlp_width=16)
    # the resampling keeps all channels
    sh_grid.upsample(8)
    assert sh_grid.feature_grid.shape[1] == 12 and sh_grid.config()["sh_degree"] == 1


def test_grid_enable_sh_keeps_the_colours():
    """RGB grid -> spherical harmonics mid-training (``grid_sh_start``): the same colours, then room for view dependence."""
    from course_lib.nerf.grid import GridField
    from course_lib.validate import KitInputError

    g = GridField([-1, -1, -1], [1, 1, 1], resolution=6)
    with torch.no_grad():
        g.feature_grid.normal_(generator=torch.Generator().manual_seed(4))
    pts = torch.rand(50, 3, generator=torch.Generator().manual_seed(5)) * 1.6 - 0.8
    d = torch.nn.functional.normalize(torch.randn(50, 3, generator=torch.Generator().manual_seed(6)), dim=-1)
    before = g.color(pts)
    g.enable_sh(1)
    assert g.feature_grid.shape[1] == 12 and g.config()["sh_degree"] == 1 and g.config()["feature_dim"] == 12
    torch.testing.assert_close(g.color(pts, d), before)
    with pytest.raises(KitInputError, match="only an RGB colour grid"):
        g.enable_sh(1)
    with pytest.raises(KitInputError, match="expected degree 1 or 2"):
        GridField([-1, -1, -1], [1, 1, 1], resolution=6).enable_sh(3)

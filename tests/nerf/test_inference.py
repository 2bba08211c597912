"""Forward-only rendering: the march through a grid gives what training's renderer gives, faster."""

import numpy as np
import pytest
import torch

from course_lib.data.blender import intrinsics_from_fov
from course_lib.nerf.grid import GridField, Trilinear
from course_lib.nerf.inference import RenderSettings, march_grid, render_view, spread_views, trilinear_rows
from course_lib.nerf.presets import preset
from course_lib.nerf.rays import get_rays
from course_lib.nerf.render import render_rays
from course_lib.nerf.scene import SceneBounds


def blob_field(sh_degree=0):
    """A grid with an opaque ball of colour in the middle, a faint fog around it, empty corners."""
    g = GridField([-1, -1, -1], [1, 1, 1], resolution=24, sh_degree=sh_degree)
    with torch.no_grad():
        D, H, W = g.shape
        z, y, x = torch.meshgrid(*[torch.linspace(-1, 1, n) for n in (D, H, W)], indexing="ij")
        r = (x**2 + y**2 + z**2).sqrt()
        g.density_grid[0, 0] = torch.where(r < 0.5, 6.0, torch.where(r < 0.8, -4.0, -30.0))
        g.feature_grid.normal_(generator=torch.Generator().manual_seed(0))
    g.update_occupancy(1e-3)
    return g


def camera(size=24):
    K = intrinsics_from_fov(size, size, 0.9)
    c2w = np.eye(4)
    c2w[:3, 3] = [0.0, 0.2, -3.0]  # looks along +z at the origin
    return K, c2w


def test_trilinear_rows_is_the_trilinear_interpolation():
    g = torch.randn(1, 5, 6, 7, 8, generator=torch.Generator().manual_seed(1))
    xyz = torch.rand(500, 3, generator=torch.Generator().manual_seed(2)) * 2 - 1
    xyz[:2] = torch.tensor([[1.0, 1.0, 1.0], [-1.0, -1.0, -1.0]])  # the corners of the box
    table = g[0].reshape(5, -1).T.contiguous()
    torch.testing.assert_close(trilinear_rows(table, (6, 7, 8), xyz), Trilinear.apply(g, xyz), atol=1e-6, rtol=0)


@pytest.mark.parametrize("sh_degree", [0, 1])
def test_march_matches_the_training_renderer(sh_degree):
    field = blob_field(sh_degree)
    K, c2w = camera()
    o, d = get_rays(24, 24, K, torch.tensor(c2w, dtype=torch.float32))
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    s = RenderSettings(48, color_threshold=1e-4, near=0.5, far=6.0)
    with torch.no_grad():
        t0, t1 = field.ray_bounds(o, d, near=0.5)
        ref = render_rays(field, o, d, t0, t1, 48, color_threshold=1e-4, last_delta=None)
    out = march_grid(field, o, d, s, segment=8)
    # early termination: what a stopped ray leaves out is below its transmittance (1e-4)
    torch.testing.assert_close(out["rgb_map"], ref["rgb_map"].clamp(0, 1), atol=2e-4, rtol=0)
    torch.testing.assert_close(out["acc_map"], ref["acc_map"], atol=2e-4, rtol=0)
    torch.testing.assert_close(out["depth_map"], ref["depth_map"], atol=2e-3, rtol=0)
    # the opaque ball stops its rays early; rays that miss the box cost nothing
    opaque = out["acc_map"] > 0.9999
    assert out["samples"].min() == 0 and opaque.any() and out["samples"][opaque].max() < 48


def test_march_between_near_and_far_reads_nothing_outside_the_box():
    # box_bounds=False (notebook 09's ablation): samples run from near to far, in and out of the
    # box; a fog that fills the whole box, up to its faces, must end exactly at them
    field = GridField([-1, -1, -1], [1, 1, 1], resolution=16)
    with torch.no_grad():
        field.density_grid.fill_(0.5)
        field.feature_grid.normal_(generator=torch.Generator().manual_seed(0))
    field.update_occupancy(1e-3)
    assert bool(field.occupancy.all())
    K, c2w = camera()
    o, d = get_rays(24, 24, K, torch.tensor(c2w, dtype=torch.float32))
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    s = RenderSettings(64, color_threshold=1e-4, near=0.5, far=6.0, box_bounds=False)
    with torch.no_grad():
        t0, t1 = torch.full_like(o[:, 0], 0.5), torch.full_like(o[:, 0], 6.0)
        ref = render_rays(field, o, d, t0, t1, 64, color_threshold=1e-4, last_delta=None)
    out = march_grid(field, o, d, s, segment=8)
    torch.testing.assert_close(out["rgb_map"], ref["rgb_map"].clamp(0, 1), atol=2e-4, rtol=0)
    torch.testing.assert_close(out["acc_map"], ref["acc_map"], atol=2e-4, rtol=0)
    assert 0.05 < float(out["acc_map"].max()) < 0.9999  # the fog is seen through, not opaque


def test_render_view_of_a_grid_and_of_an_mlp():
    field = blob_field()
    K, c2w = camera(16)
    cfg = preset("fast", n_samples=40, grid_resolution=24)
    bounds = SceneBounds((0.0, 0.0, 0.0), 1.0, (-1.0,) * 3, (1.0,) * 3, near=0.5, far=6.0)
    view = render_view(field, None, cfg, bounds, 16, 16, K, c2w)
    assert view["rgb"].shape == (16, 16, 3) and view["depth"].shape == (16, 16) and field.training
    assert 0.0 <= float(view["rgb"].min()) and float(view["rgb"].max()) <= 1.0
    from course_lib.nerf.model import NeRF
    from course_lib.nerf.render import render_image

    mlp = NeRF(depth=2, width=16, skips=(), pos_freqs=2, dir_freqs=1, view_width=8)
    cfg = preset("paper", n_samples=16)
    a = render_view(mlp, None, cfg, bounds.to_dict(), 8, 8, K, c2w)["rgb"]
    b = render_image(mlp, 8, 8, K, c2w, 0.5, 6.0, 16)["rgb"]
    torch.testing.assert_close(a, b)


def test_spread_views():
    assert spread_views(25, 5) == [0, 6, 12, 18, 24]
    assert spread_views(4, 10) == [0, 1, 2, 3] and spread_views(4, 0) == [0]


def test_views_rendered_together_are_the_views_rendered_alone():
    from course_lib.nerf.inference import render_views

    field = blob_field(sh_degree=1)
    K, c2w = camera(12)
    other = c2w.copy()
    other[:3, 3] = [0.3, -0.2, -2.5]
    cfg = preset("fast", n_samples=40, grid_resolution=24)
    bounds = SceneBounds((0.0, 0.0, 0.0), 1.0, (-1.0,) * 3, (1.0,) * 3, near=0.5, far=6.0)
    together = list(render_views(field, None, cfg, bounds, 12, 12, K, [c2w, other]))
    for img, pose in zip(together, [c2w, other]):
        torch.testing.assert_close(img, render_view(field, None, cfg, bounds, 12, 12, K, pose)["rgb"], atol=0, rtol=0)


def test_preview_camera_keeps_the_view():
    from course_lib.nerf.inference import preview_camera

    K = intrinsics_from_fov(800, 600, 0.7)
    H, W, Kp = preview_camera(600, 800, K, 400)
    assert (H, W) == (300, 400) and preview_camera(300, 400, K, 400)[:2] == (300, 400)
    assert preview_camera(600, 800, K, 0)[:2] == (600, 800)
    # a preview pixel's centre is the centre of the 2 x 2 full-size pixels it covers: the same ray
    full = get_rays(600, 800, torch.as_tensor(K, dtype=torch.float32), torch.eye(4))[1]
    small = get_rays(H, W, torch.as_tensor(Kp, dtype=torch.float32), torch.eye(4))[1]
    for v, u in [(0, 0), (10, 37), (299, 399)]:
        mid = full[2 * v:2 * v + 2, 2 * u:2 * u + 2].mean(dim=(0, 1))
        torch.testing.assert_close(small[v, u], mid, atol=1e-6, rtol=1e-6)

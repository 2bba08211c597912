"""The kit's trainer and renderer run on functions written to the letter of notebook 06-08's stubs.

Issue 28: the training cell of notebook 08 failed for such functions (a float64 K, near/far as
tensors, a ``last_delta`` argument the stub does not have). Here the kit's NeRF code is given
literal implementations of the stubs (keeping the dtype and device of their inputs, taking only
the documented arguments) and trains and renders with them, in both presets.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from course_lib.data.blender import load_blender
from course_lib.nerf import checkpoint, encoding, grid, model, rays, render
from course_lib.nerf.presets import preset
from course_lib.nerf.render import composite
from course_lib.nerf.scene import TrainingRays
from course_lib.nerf.train import train
from course_lib.paths import EMBEDDED_NERF
from course_lib.validate import KitInputError


# --- notebook 06, 07, 08 written from the stubs only ------------------------------------------------------


def get_rays(H, W, K, c2w):
    u = torch.arange(W, dtype=K.dtype, device=K.device)  # keeps K's dtype: float32 as documented
    v = torch.arange(H, dtype=K.dtype, device=K.device)
    uu, vv = torch.meshgrid(u, v, indexing="xy")
    d_cam = torch.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], torch.ones_like(uu)], dim=-1)
    rays_d = d_cam @ c2w[:3, :3].T
    return c2w[:3, 3].expand(rays_d.shape), rays_d


def stratified_samples(near, far, n_samples, n_rays, perturb, generator=None):
    near = torch.as_tensor(near, dtype=torch.float32).reshape(-1, 1)
    far = torch.as_tensor(far, dtype=torch.float32, device=near.device).reshape(-1, 1)
    i = torch.arange(n_samples, dtype=torch.float32, device=near.device)
    z = (near + (far - near) * i / (n_samples - 1)).expand(n_rays, n_samples)
    if not perturb:
        return z
    mids = 0.5 * (z[:, 1:] + z[:, :-1])
    lower = torch.cat([z[:, :1], mids], dim=-1)
    upper = torch.cat([mids, z[:, -1:]], dim=-1)
    return lower + (upper - lower) * torch.rand(z.shape, generator=generator, device=near.device)


def query_points(rays_o, rays_d, z_vals):
    return rays_o[:, None, :] + z_vals[..., None] * rays_d[:, None, :]


def positional_encoding(x, n_freqs, include_input=True):
    parts = [x] if include_input else []
    for k in range(n_freqs):
        parts += [torch.sin(2.0 ** k * torch.pi * x), torch.cos(2.0 ** k * torch.pi * x)]
    return torch.cat(parts, dim=-1)


def volume_render(rgb, sigma, z_vals, rays_d, white_background=True):
    delta = torch.cat([z_vals[:, 1:] - z_vals[:, :-1], torch.full_like(z_vals[:, :1], 1e10)], dim=-1)
    delta = delta * torch.linalg.norm(rays_d, dim=-1, keepdim=True)
    alpha = 1 - torch.exp(-sigma * delta)
    T = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha + 1e-10], dim=-1), dim=-1)[:, :-1]
    weights = T * alpha
    acc = weights.sum(-1)
    rgb_map = (weights[..., None] * rgb).sum(-2) + (1 - acc[:, None] if white_background else 0.0)
    return {"rgb_map": rgb_map, "depth_map": (weights * z_vals).sum(-1), "acc_map": acc, "weights": weights}


class NeRF(nn.Module):
    def __init__(self, depth=8, width=256, skips=(4,), pos_freqs=10, dir_freqs=4, use_viewdirs=True, view_width=128):
        super().__init__()
        self.pos_freqs, self.dir_freqs, self.skips = pos_freqs, dir_freqs, skips
        d_pos, d_dir = 3 * (1 + 2 * pos_freqs), 3 * (1 + 2 * dir_freqs)
        self.trunk = nn.ModuleList([nn.Linear(d_pos if i == 0 else width + (d_pos if i - 1 in skips else 0), width)
                                    for i in range(depth)])
        self.sigma_head = nn.Linear(width, 1)
        self.feature = nn.Linear(width, width)
        self.view_layer = nn.Linear(width + d_dir, view_width)
        self.rgb_head = nn.Linear(view_width, 3)

    def forward(self, pts, viewdirs):
        x = positional_encoding(pts, self.pos_freqs)
        h = x
        for i, layer in enumerate(self.trunk):
            h = torch.relu(layer(h))
            if i in self.skips:
                h = torch.cat([x, h], -1)
        sigma = torch.relu(self.sigma_head(h))[..., 0]
        h = torch.relu(self.view_layer(torch.cat([self.feature(h), positional_encoding(viewdirs, self.dir_freqs)], -1)))
        return torch.sigmoid(self.rgb_head(h)), sigma


@pytest.fixture
def literal(monkeypatch):
    """The kit's NeRF modules with the literal functions in place of the references (what the student kit does)."""
    for mod, names in ((rays, ("get_rays", "stratified_samples", "query_points")),
                       (render, ("stratified_samples", "query_points", "volume_render")),
                       (encoding, ("positional_encoding",)), (grid, ("positional_encoding",)),
                       (model, ("positional_encoding",)), (checkpoint, ("NeRF",))):
        for name in names:
            monkeypatch.setattr(mod, name, globals()[name])


@pytest.fixture(scope="module")
def scene():
    return load_blender(EMBEDDED_NERF, "train", downscale=4), load_blender(EMBEDDED_NERF, "test", downscale=4).subset([0])


@pytest.mark.slow  # a training run: pytest -m "not slow" leaves it out
def test_the_fast_preset_trains_and_renders_with_the_literal_functions(literal, scene):
    train_data, test_data = scene
    cfg = preset("fast", minutes=None, iters=40, batch_rays=512, n_samples=32, grid_resolution=32,
                 grid_schedule=((0, 0.5), (0.3, 1.0)), shrink_box_at=0.2, occupancy_start=0.1, occupancy_every=10,
                 snapshot_every=0, checkpoint_every=0, overhead_budget=0, eval_all=True, seed=0)
    torch.manual_seed(0)
    res = train(train_data, test_data, cfg, progress=False, device=torch.device("cpu"))
    assert np.isfinite(res.metrics["test_psnr"]) and res.metrics["test_psnr"] > 10


def test_the_paper_preset_builds_saves_and_reloads_the_literal_nerf(literal, scene, tmp_path):
    train_data, test_data = scene
    cfg = preset("paper", minutes=None, iters=3, batch_rays=64, n_samples=8, n_importance=0, depth=2, width=32,
                 view_width=16, skips=(0,), snapshot_every=0, checkpoint_every=0, overhead_budget=0, eval_all=True)
    torch.manual_seed(0)
    res = train(train_data, test_data, cfg, out_dir=tmp_path, progress=False, device=torch.device("cpu"))
    assert np.isfinite(res.metrics["test_psnr"])
    ck = checkpoint.load_checkpoint(tmp_path)
    assert isinstance(ck["model"], NeRF)


def test_composite_gives_a_field_that_ends_at_its_last_sample_the_previous_interval():
    torch.manual_seed(0)
    R, S = 5, 7
    rgb, sigma = torch.rand(R, S, 3), 3 * torch.rand(R, S)
    z = torch.sort(2 + 4 * torch.rand(R, S), dim=-1).values
    d = torch.randn(R, 3)
    out = composite(rgb, sigma, z, d, white_background=True, last_delta=None)
    delta = torch.cat([z[:, 1:] - z[:, :-1], z[:, -1:] - z[:, -2:-1]], dim=-1) * d.norm(dim=-1, keepdim=True)
    alpha = 1 - torch.exp(-sigma * delta)
    T = torch.cumprod(torch.cat([torch.ones(R, 1), 1 - alpha + 1e-10], dim=-1), dim=-1)[:, :-1]
    w = T * alpha
    assert out["weights"].shape == (R, S) and torch.allclose(out["weights"], w, atol=1e-6)
    assert torch.allclose(out["rgb_map"], (w[..., None] * rgb).sum(1) + 1 - w.sum(1, keepdim=True), atol=1e-6)
    with pytest.raises(KitInputError, match="last_delta=3"):
        composite(rgb, sigma, z, d, last_delta=3.0)


def test_training_rays_are_get_rays_of_each_view_and_a_get_rays_that_ignores_the_pose_is_named(scene, monkeypatch):
    data = scene[0]
    tr = TrainingRays(data, torch.device("cpu"))
    H, W = data.H, data.W
    for view in (0, 3):
        o, d = rays.camera_rays(H, W, data.K, data.c2w[view])
        idx = torch.arange(view * H * W, (view + 1) * H * W)
        o2, d2 = tr.rays(idx)
        assert torch.allclose(o2, o.reshape(-1, 3)) and torch.allclose(d2, d.reshape(-1, 3), atol=1e-6)

    def unrotated(H, W, K, c2w):  # a classic mistake: the camera-frame directions, not turned into the world
        o, d = get_rays(H, W, K, torch.eye(4))
        return c2w[:3, 3].expand(d.shape), d

    monkeypatch.setattr(rays, "get_rays", unrotated)
    with pytest.raises(KitInputError, match=r"get_rays of training view \d+ is not the camera-frame rays turned by its pose"):
        TrainingRays(data, torch.device("cpu"))


def test_camera_rays_calls_get_rays_with_the_documented_types(monkeypatch):
    seen = {}

    def spy(H, W, K, c2w):
        seen.update(H=type(H), W=type(W), K=(K.dtype, tuple(K.shape)), c2w=(c2w.dtype, tuple(c2w.shape)))
        return get_rays(H, W, K, c2w)

    monkeypatch.setattr(rays, "get_rays", spy)
    o, d = rays.camera_rays(np.int64(3), 4.0, np.diag([2.0, 2.0, 1.0]), np.eye(4)[:3])  # numpy, float64, (3, 4)
    assert seen == {"H": int, "W": int, "K": (torch.float32, (3, 3)), "c2w": (torch.float32, (4, 4))}
    assert d.dtype == torch.float32 and d.shape == (3, 4, 3)
    monkeypatch.setattr(rays, "get_rays", lambda H, W, K, c2w: get_rays(W, H, K, c2w))  # transposed grid
    with pytest.raises(KitInputError, match=r"get_rays returned rays_o of shape \(4, 3, 3\): expected \(H, W, 3\)"):
        rays.camera_rays(3, 4, np.eye(3), np.eye(4))

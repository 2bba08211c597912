"""Adam for voxel grids: the dense update is torch's Adam (fused, over voxel rows); the sparse (lazy) one is
dense Adam where every voxel is touched, frozen voxels elsewhere."""

import copy

import pytest
import torch

from course_lib.nerf.grid import GridField
from course_lib.nerf.optim import GridAdam, touched_voxels


def grids(seed=0):
    gen = torch.Generator().manual_seed(seed)
    return [torch.nn.Parameter(torch.randn(1, c, 4, 5, 6, generator=gen)) for c in (1, 3)]


def run(opt, params, grads, **kw):
    for step, gs in enumerate(grads):
        for g in opt.param_groups:
            g["lr"] = 0.1 * 0.9 ** step  # a schedule, as training has
        for p, g in zip(params, gs):
            p.grad = g.clone()
        opt.step(**kw)


@pytest.mark.parametrize("fused", [False, True])
def test_every_voxel_touched_is_dense_adam(fused):
    gen = torch.Generator().manual_seed(1)
    a, b = grids(), grids()
    grads = [[torch.randn(p.shape, generator=gen) for p in a] for _ in range(5)]
    run(torch.optim.Adam(a, lr=0.1, betas=(0.9, 0.99), fused=fused), a, grads)
    sparse = GridAdam([{"params": b, "sparse": True}], lr=0.1, betas=(0.9, 0.99))
    run(sparse, b, grads)
    for p, q in zip(a, b):
        torch.testing.assert_close(q, p, atol=1e-6, rtol=1e-6)


def test_untouched_voxels_and_their_moments_stay():
    gen = torch.Generator().manual_seed(2)
    p = grids()[1]
    V = p[0, 0].numel()
    half = torch.arange(0, V, 2)
    g_all = torch.randn(p.shape, generator=gen)
    g_half = torch.zeros_like(p).view(3, V)
    g_half[:, half] = torch.randn(3, half.numel(), generator=gen)
    opt = GridAdam([{"params": [p], "sparse": True}], lr=0.1)
    run(opt, [p], [[g_all]])
    before = p.detach().clone().view(3, V)
    m_before = opt.state[p]["exp_avg"].clone().view(3, V)
    run(opt, [p], [[g_half.view(p.shape)]])
    odd = torch.arange(1, V, 2)
    assert torch.equal(p.detach().view(3, V)[:, odd], before[:, odd])  # dense Adam would move them (m != 0)
    assert torch.equal(opt.state[p]["exp_avg"].view(3, V)[:, odd], m_before[:, odd])
    assert not torch.equal(p.detach().view(3, V)[:, half], before[:, half])
    # the same update from the voxels given explicitly as from the scan of the gradient
    q = p.detach().clone().requires_grad_()
    opt2 = GridAdam([{"params": [q], "sparse": True}], lr=0.1)
    opt2.load_state_dict(copy.deepcopy(opt.state_dict()))
    assert opt2.param_groups[0]["sparse"]
    run(opt, [p], [[g_half.view(p.shape)]])
    run(opt2, [q], [[g_half.view(p.shape)]], voxels={q: half})
    torch.testing.assert_close(q, p, atol=0, rtol=0)


def test_reads_of_a_grid_are_its_touched_voxels():
    field = GridField([-1, -1, -1], [1, 1, 1], resolution=8, sh_degree=1)
    field.track_reads()
    pts = torch.rand(50, 3, generator=torch.Generator().manual_seed(3)) * 1.6 - 0.8
    rgb, sigma = field(pts, torch.nn.functional.normalize(pts, dim=-1))
    (rgb.sum() + sigma.sum()).backward()
    reads = field.take_reads()
    for g in (field.density_grid, field.feature_grid):
        assert torch.equal(reads[g], touched_voxels(g.grad))
    assert field.take_reads() == {}


def test_total_variation_gradient_at_every_voxel_is_the_dense_one():
    field = GridField([-1, -1, -1], [1, 2, 1.5], resolution=6)
    with torch.no_grad():
        field.density_grid.normal_(generator=torch.Generator().manual_seed(4))
    field.density_grid.grad = None
    tv_dense = field.add_total_variation_grad(0.3)
    dense = field.density_grid.grad.clone()
    field.density_grid.grad = None
    every = torch.arange(field.density_grid.numel())
    tv_sparse = field.add_total_variation_grad(0.3, voxels=every)
    torch.testing.assert_close(field.density_grid.grad, dense, atol=1e-7, rtol=1e-5)
    torch.testing.assert_close(tv_sparse, tv_dense)
    field.density_grid.grad = None
    some = every[::3]
    field.add_total_variation_grad(0.3, voxels=some)
    g = field.density_grid.grad.view(-1)
    torch.testing.assert_close(g[some], dense.view(-1)[some], atol=1e-7, rtol=1e-5)
    assert (g[every[1::3]] == 0).all()


def channels_last(params):
    return [torch.nn.Parameter(p.detach().clone().contiguous(memory_format=torch.channels_last_3d)) for p in params]


def test_dense_grid_adam_is_torch_adam_on_channels_last_grids():
    # GridField's feature grid is channels-last; fused Adam must see it (and its gradient and moments) as voxel rows
    gen = torch.Generator().manual_seed(6)
    a = grids(3)
    b = channels_last(a)
    grads = [[torch.randn(p.shape, generator=gen) for p in a] for _ in range(4)]
    run(torch.optim.Adam(a, lr=0.1, betas=(0.9, 0.99)), a, grads)
    opt = GridAdam([{"params": b}], lr=0.1, betas=(0.9, 0.99))
    run(opt, b, [[g.contiguous(memory_format=torch.channels_last_3d) for g in gs] for gs in grads])
    for p, q in zip(a, b):
        torch.testing.assert_close(q, p, atol=1e-6, rtol=1e-6)
        assert q.is_contiguous(memory_format=torch.channels_last_3d)
    # a gradient laid out unlike its grid: the unfused update, still the right one
    c = channels_last(grids(3))
    run(GridAdam([{"params": c}], lr=0.1, betas=(0.9, 0.99)), c, grads)
    for p, q in zip(a, c):
        torch.testing.assert_close(q, p, atol=1e-6, rtol=1e-6)


def test_adam_state_of_contiguous_grids_loads_into_channels_last_ones():
    # a checkpoint written before the grids were channels-last: its moments are re-laid out on loading
    gen = torch.Generator().manual_seed(7)
    a = grids(4)
    grads = [[torch.randn(p.shape, generator=gen) for p in a] for _ in range(4)]
    old = torch.optim.Adam(a, lr=0.1, betas=(0.9, 0.99), fused=True)
    run(old, a, grads[:2])
    b = channels_last(a)
    new = GridAdam([{"params": b}], lr=0.1, betas=(0.9, 0.99))
    new.load_state_dict(copy.deepcopy(old.state_dict()))
    assert all(new.state[q]["exp_avg"].stride() == q.stride() for q in b)
    run(old, a, grads[2:])
    run(new, b, [[g.contiguous(memory_format=torch.channels_last_3d) for g in gs] for gs in grads[2:]])
    for p, q in zip(a, b):
        torch.testing.assert_close(q, p, atol=1e-6, rtol=1e-6)

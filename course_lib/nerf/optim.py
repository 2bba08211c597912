"""Sparse Adam for voxel grids (notebook 09): update only the voxels that a step touched.

A training step reads a few hundred thousand voxels (8 corners of every sample that the
occupancy grid lets through), but a grid at 400 or 800 px has millions of voxels times 4-13
channels. Dense Adam reads and writes every value of the parameter and both of its moments at
every step, whatever the gradient; at 150^3-250^3 voxels that pass over memory dominates the step.

:class:`SparseGridAdam` is Adam restricted to the touched voxels ("lazy" Adam: the semantics of
``torch.optim.SparseAdam`` and of DVGO's ``MaskedAdam``), on a grid seen as ``(C, V)`` (channels x
voxels). A voxel is touched when any of its channels has a non-zero gradient. For those
voxels, at global step ``t``::

    m <- beta1 m + (1 - beta1) g            v <- beta2 v + (1 - beta2) g^2
    x <- x - lr / (1 - beta1^t) * m / (sqrt(v / (1 - beta2^t)) + eps)

exactly as ``torch.optim.Adam``; the values and moments of every other voxel stay as they are.

The difference from dense Adam: dense Adam also moves a voxel whose gradient is zero this step
(its moment ``m`` decays but is not zero, so the voxel keeps drifting in the direction it last
went, and ``v`` decays too). Lazy Adam freezes it until a ray touches it again, and its moments
then resume where they were (their decay over the skipped steps is not applied). When every voxel
is touched at every step the two are the same update. Other parameters (a colour MLP) are updated
densely, as ``torch.optim.Adam`` does.

When it pays (``benchmarks/nerf_step_vs_render.py``, a CPU, one thread): the gathers and scatters
of the touched voxels' values, gradients and moments cost several times a streamed pass per
value, so the sparse update wins only where a step reads a small share of the grid. After 300
steps of the fast preset on the building, a step reads 17.7 % of the voxels at 400 px (175^3 x 13
values; the fused dense Adam is about 8 % of the step) and the sparse steps run at 0.83x the
dense ones (0.76x at 200 px). So the fast preset keeps the fused dense Adam and this optimizer is
opt-in (``TrainConfig.grid_sparse_adam``, ``nerf train --sparse-adam``): for grids much larger
than the batch's footprint (tight occupancy, 800 px grids, small batches).
"""

from __future__ import annotations

import torch

__all__ = ["SparseGridAdam", "touched_voxels"]


def touched_voxels(grad: torch.Tensor) -> torch.Tensor:
    """Indices ``(n,)`` of the voxels with a non-zero gradient in any channel.

    Args:
        grad: ``(1, C, D, H, W)``, a grid's gradient.
    """
    flat = grad.reshape(grad.shape[1], -1)
    hit = flat[0] != 0
    for c in range(1, flat.shape[0]):
        hit |= flat[c] != 0
    return torch.nonzero(hit).squeeze(1)


class SparseGridAdam(torch.optim.Optimizer):
    """Adam that updates only the voxels a step touched (lazy Adam; see the module docstring).

    Args:
        params: parameters or parameter groups (dicts, extra keys kept). A group with
            ``sparse=True`` holds voxel grids ``(1, C, D, H, W)``: only their touched voxels are
            updated; any other group is updated densely (same formula).
        lr: learning rate. betas: ``(beta1, beta2)``. eps: added to the denominator.

    The state per parameter is ``step`` (a 0-d tensor), ``exp_avg`` and ``exp_avg_sq`` (its shape),
    the names of ``torch.optim.Adam``, so a state dict of either loads into the other.
    """

    def __init__(self, params, lr: float = 1e-3, betas: tuple = (0.9, 0.999), eps: float = 1e-8):
        super().__init__(params, dict(lr=lr, betas=betas, eps=eps, sparse=False))

    def load_state_dict(self, state_dict: dict) -> None:
        """As ``torch.optim.Optimizer``'s (an Adam state dict loads too); which groups are sparse stays as built."""
        sparse = [g["sparse"] for g in self.param_groups]
        super().load_state_dict(state_dict)
        for g, sp in zip(self.param_groups, sparse):
            g["sparse"] = sp

    def _state(self, p: torch.Tensor) -> dict:
        st = self.state[p]
        if not st:
            st["step"] = torch.zeros((), dtype=torch.float32)
            st["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            st["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
        return st

    @torch.no_grad()
    def step(self, closure=None, voxels: dict | None = None):
        """One update of every parameter that has a gradient (the touched voxels of sparse groups).

        Args:
            closure: as ``torch.optim.Optimizer.step``.
            voxels: optional ``{grid parameter: (n,) flat voxel indices}``, the voxels the step
                read (:meth:`course_lib.nerf.grid.GridField.take_reads`); a sparse grid not in it
                is updated where its gradient is non-zero (:func:`touched_voxels`, a scan of the grid).
        """
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            b1, b2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                st = self._state(p)
                st["step"] += 1
                t = float(st["step"])
                step_size, bc2_sqrt = group["lr"] / (1.0 - b1 ** t), (1.0 - b2 ** t) ** 0.5
                if group["sparse"]:
                    idx = voxels.get(p) if voxels is not None else None
                    idx = touched_voxels(p.grad) if idx is None else idx
                    _sparse_update(p, idx, st["exp_avg"], st["exp_avg_sq"], b1, b2, step_size, bc2_sqrt, group["eps"])
                else:
                    m, v, g = st["exp_avg"], st["exp_avg_sq"], p.grad
                    m.mul_(b1).add_(g, alpha=1.0 - b1)
                    v.mul_(b2).addcmul_(g, g, value=1.0 - b2)
                    p.addcdiv_(m, (v.sqrt() / bc2_sqrt).add_(group["eps"]), value=-step_size)
        return loss


def _sparse_update(p, idx, exp_avg, exp_avg_sq, b1: float, b2: float, step_size: float, bc2_sqrt: float,
                   eps: float) -> None:
    """Adam on the voxels ``idx (n,)`` of one grid: gather, update, scatter back.

    Args:
        p, exp_avg, exp_avg_sq: ``(1, C, D, H, W)`` (contiguous) grid (with its ``.grad``) and moments.
    """
    if idx.numel() == 0:
        return
    C = p.shape[1]
    g = p.grad.reshape(C, -1).index_select(1, idx)  # (C, n)
    m = exp_avg.view(C, -1).index_select(1, idx).mul_(b1).add_(g, alpha=1.0 - b1)
    v = exp_avg_sq.view(C, -1).index_select(1, idx).mul_(b2).addcmul_(g, g, value=1.0 - b2)
    exp_avg.view(C, -1).index_copy_(1, idx, m)
    exp_avg_sq.view(C, -1).index_copy_(1, idx, v)
    step = m.div_(v.sqrt_().div_(bc2_sqrt).add_(eps)).mul_(-step_size)
    p.data.view(C, -1).index_add_(1, idx, step)

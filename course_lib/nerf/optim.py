"""Adam for voxel grids (notebook 09): dense over voxel rows, or only on the voxels a step touched.

A training step reads a few hundred thousand voxels (8 corners of every sample that the
occupancy grid lets through), but a grid at 400 or 800 px has millions of voxels times 4-13
channels. Dense Adam reads and writes every value of the parameter and both of its moments at
every step, whatever the gradient; at 150^3-250^3 voxels that pass over memory dominates the step.

:class:`GridAdam` is Adam restricted to the touched voxels ("lazy" Adam: the semantics of
``torch.optim.SparseAdam`` and of DVGO's ``MaskedAdam``) in its sparse groups, on a grid seen as
``(V, C)`` (a row of channels per voxel: :func:`~course_lib.nerf.grid.voxel_rows`). A voxel is touched when any of its channels has a non-zero gradient. For those
voxels, at global step ``t``::

    m <- beta1 m + (1 - beta1) g            v <- beta2 v + (1 - beta2) g^2
    x <- x - lr / (1 - beta1^t) * m / (sqrt(v / (1 - beta2^t)) + eps)

exactly as ``torch.optim.Adam``; the values and moments of every other voxel stay as they are.

The difference from dense Adam: dense Adam also moves a voxel whose gradient is zero this step
(its moment ``m`` decays but is not zero, so the voxel keeps drifting in the direction it last
went, and ``v`` decays too). Lazy Adam freezes it until a ray touches it again, and its moments
then resume where they were (their decay over the skipped steps is not applied). When every voxel
is touched at every step the two are the same update. Its other groups (the grids by default, a
colour MLP) get ``torch.optim.Adam``'s dense update, fused where it can be: on a grid stored
channels-last (as :class:`~course_lib.nerf.grid.GridField` stores its feature grid) it runs on
the voxel rows, one contiguous block of memory.

When the sparse update pays: the gathers and scatters of the touched voxels' values, gradients
and moments cost several times a streamed pass per value, so it wins only where a step reads a
small share of the grid. With channels-last grids and the fused dense update over voxel rows, the
dense update is the faster one for the fast preset's grids and batches (measured on the building
at 200 and 400 px, 2 CPU threads). So the fast preset keeps the dense update and the sparse one is
opt-in (``TrainConfig.grid_sparse_adam``, ``nerf train --sparse-adam``): for grids much
larger than the batch's footprint (800 px grids, small batches).
"""

from __future__ import annotations

import torch
from torch.optim.adam import adam

from course_lib.nerf.grid import voxel_rows

__all__ = ["GridAdam", "touched_voxels"]


def touched_voxels(grad: torch.Tensor) -> torch.Tensor:
    """Indices ``(n,)`` of the voxels with a non-zero gradient in any channel.

    Args:
        grad: ``(1, C, D, H, W)``, a grid's gradient.
    """
    return torch.nonzero((voxel_rows(grad) != 0).any(dim=1)).squeeze(1)


class GridAdam(torch.optim.Optimizer):
    """Adam for voxel grids stored channels-last: dense and fused, or lazy on the touched voxels.

    Args:
        params: parameters or parameter groups (dicts, extra keys kept). A group with
            ``sparse=True`` holds voxel grids ``(1, C, D, H, W)``: only their touched voxels are
            updated (lazy Adam, see the module docstring); every other group gets the dense update
            (``torch.optim.Adam``'s, fused on a CPU or CUDA GPU).
        lr: learning rate. betas: ``(beta1, beta2)``. eps: added to the denominator.

    The dense update runs on each grid seen as one contiguous block of voxel rows
    (:func:`~course_lib.nerf.grid.voxel_rows`): fused Adam walks its tensors as flat memory, and on
    a channels-last grid seen as ``(1, C, D, H, W)`` it first copies everything into that
    order and back (5x slower at 3 M voxels x 12 channels).

    The state per parameter is ``step`` (a 0-d tensor), ``exp_avg`` and ``exp_avg_sq`` (its shape
    and layout), the names of ``torch.optim.Adam``, so a state dict of either loads into the other.
    """

    def __init__(self, params, lr: float = 1e-3, betas: tuple = (0.9, 0.999), eps: float = 1e-8):
        super().__init__(params, dict(lr=lr, betas=betas, eps=eps, sparse=False))

    def load_state_dict(self, state_dict: dict) -> None:
        """As ``torch.optim.Optimizer``'s (an Adam state dict loads too); which groups are sparse stays as built.

        Each moment is stored with its parameter's layout (a checkpoint of older code holds
        contiguous moments for a channels-last grid).
        """
        sparse = [g["sparse"] for g in self.param_groups]
        super().load_state_dict(state_dict)
        for g, sp in zip(self.param_groups, sparse):
            g["sparse"] = sp
        for p, st in self.state.items():
            for k, v in st.items():
                if k == "step":
                    st[k] = v.to(device=p.device, dtype=torch.float32)
                elif torch.is_tensor(v) and v.shape == p.shape and not _same_layout(v, p):
                    st[k] = torch.empty_like(p).copy_(v)

    def _state(self, p: torch.Tensor) -> dict:
        st = self.state[p]
        if not st:
            st["step"] = torch.zeros((), dtype=torch.float32, device=p.device)
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
            dense = []
            for p in group["params"]:
                if p.grad is None:
                    continue
                st = self._state(p)
                if not group["sparse"]:
                    dense.append((p, st))
                    continue
                st["step"] += 1
                t = float(st["step"])
                idx = voxels.get(p) if voxels is not None else None
                idx = touched_voxels(p.grad) if idx is None else idx
                _sparse_update(p, idx, st["exp_avg"], st["exp_avg_sq"], b1, b2, group["lr"] / (1.0 - b1 ** t),
                               (1.0 - b2 ** t) ** 0.5, group["eps"])
            if dense:
                _dense_update(dense, b1, b2, group["lr"], group["eps"])
        return loss


def _flat(t: torch.Tensor) -> torch.Tensor:
    """``t`` as a contiguous tensor over the same memory: a channels-last grid's voxel rows, else ``t``."""
    if t.dim() == 5 and not t.is_contiguous() and t.is_contiguous(memory_format=torch.channels_last_3d):
        return voxel_rows(t)
    return t


def _same_layout(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Same shape, and the same strides along every axis longer than 1."""
    return a.shape == b.shape and all(sa == sb for sa, sb, n in zip(a.stride(), b.stride(), a.shape) if n > 1)


def _dense_update(params: list, b1: float, b2: float, lr: float, eps: float) -> None:
    """``torch.optim.Adam``'s update of ``[(parameter, its state), ...]``, fused where it can be."""
    ts = [(p.data, p.grad, st["exp_avg"], st["exp_avg_sq"]) for p, st in params]
    # fused Adam reads the four tensors as flat memory: only where they are laid out alike
    fused = all(_same_layout(x, four[0]) and x.device.type in ("cpu", "cuda") for four in ts for x in four)
    if fused:
        ts = [[_flat(x) for x in four] for four in ts]
        fused = all(x.is_contiguous() for four in ts for x in four)
    p, g, m, v = (list(x) for x in zip(*ts))
    adam(p, g, m, v, [], [st["step"] for _, st in params], foreach=False, fused=fused or None,
          amsgrad=False, beta1=b1, beta2=b2, lr=lr, weight_decay=0.0, eps=eps, maximize=False)


def _sparse_update(p, idx, exp_avg, exp_avg_sq, b1: float, b2: float, step_size: float, bc2_sqrt: float,
                   eps: float) -> None:
    """Adam on the voxels ``idx (n,)`` of one grid: gather, update, scatter back.

    Args:
        p, exp_avg, exp_avg_sq: ``(1, C, D, H, W)`` grid (with its ``.grad``) and moments, stored
            channels-last (:func:`~course_lib.nerf.grid.channels_last`): a voxel's values are one row.
    """
    if idx.numel() == 0:
        return
    rows = voxel_rows  # views: the updates below write through them
    g = rows(p.grad).index_select(0, idx)  # (n, C)
    m = rows(exp_avg).index_select(0, idx).mul_(b1).add_(g, alpha=1.0 - b1)
    v = rows(exp_avg_sq).index_select(0, idx).mul_(b2).addcmul_(g, g, value=1.0 - b2)
    rows(exp_avg).index_copy_(0, idx, m)
    rows(exp_avg_sq).index_copy_(0, idx, v)
    step = m.div_(v.sqrt_().div_(bc2_sqrt).add_(eps)).mul_(-step_size)
    rows(p.data).index_add_(0, idx, step)

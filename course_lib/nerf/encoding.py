"""Positional encoding (notebook 07).

An MLP fed raw coordinates ``(x, y, z)`` learns only smooth functions (spectral bias); NeRF feeds it
sines and cosines of the coordinates at octave-spaced frequencies instead. The paper's encoding,
applied to each coordinate ``p`` separately::

    gamma(p) = (sin(2^0 pi p), cos(2^0 pi p), sin(2^1 pi p), cos(2^1 pi p), ..., sin(2^(L-1) pi p), cos(2^(L-1) pi p))

The kit uses exactly this formula (with the factor pi; the paper assumes coordinates roughly in
[-1, 1]; the official code drops the pi, which only rescales the frequencies), and, like the
official code, puts the input itself first. For an input ``x`` of D coordinates the output is::

    [x,                                   D values  (identity, if include_input)
     sin(2^0 pi x), cos(2^0 pi x),        D + D values, frequency k = 0
     sin(2^1 pi x), cos(2^1 pi x),        frequency k = 1
     ...
     sin(2^(L-1) pi x), cos(2^(L-1) pi x)]

i.e. for each frequency the D sines, then the D cosines. Output size ``D (include_input + 2 L)``:
positions (D = 3, L = 10) -> 3 + 3*2*10 = 63; view directions (L = 4) -> 3 + 3*2*4 = 27.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from course_lib.validate import KitInputError

__all__ = ["positional_encoding", "encoded_dim", "PositionalEncoding"]


def encoded_dim(d: int, n_freqs: int, include_input: bool = True) -> int:
    """Output size of :func:`positional_encoding` for ``d`` input coordinates: ``d (include_input + 2 n_freqs)``."""
    return d * (int(include_input) + 2 * n_freqs)


def positional_encoding(x: torch.Tensor, n_freqs: int, include_input: bool = True) -> torch.Tensor:
    """The paper's gamma, applied to every coordinate, identity term first.

    Args:
        x: ``(..., D)`` tensor (positions D = 3, or unit view directions).
        n_freqs: L, the number of octaves (frequencies ``2^0 pi ... 2^(L-1) pi``); 0 gives ``x`` alone.
        include_input: put ``x`` itself first.

    Returns:
        ``(..., D (include_input + 2 L))``: ``[x, sin(2^0 pi x), cos(2^0 pi x), ..., sin(2^(L-1) pi x), cos(2^(L-1) pi x)]``
        where each ``sin(.)`` / ``cos(.)`` block holds the D coordinates.

    Introduced in ``notebooks/07_nerf_model.ipynb``.
    """
    if not isinstance(x, torch.Tensor):
        x = torch.as_tensor(x, dtype=torch.float32)
    if x.ndim < 1:
        raise KitInputError("x must have a last dimension of coordinates, shape (..., D)")
    if n_freqs < 0 or int(n_freqs) != n_freqs:
        raise KitInputError(f"n_freqs = {n_freqs!r}: expected an integer >= 0")
    parts = [x] if include_input else []
    for k in range(int(n_freqs)):
        w = (2.0 ** k) * math.pi
        parts.append(torch.sin(w * x))
        parts.append(torch.cos(w * x))
    if not parts:
        raise KitInputError("include_input=False with n_freqs=0 gives an empty encoding")
    return torch.cat(parts, dim=-1)


class PositionalEncoding(nn.Module):
    """:func:`positional_encoding` as a module (no parameters); ``out_dim`` gives the output size."""

    def __init__(self, d: int = 3, n_freqs: int = 10, include_input: bool = True):
        super().__init__()
        self.d, self.n_freqs, self.include_input = d, n_freqs, include_input
        self.out_dim = encoded_dim(d, n_freqs, include_input)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return positional_encoding(x, self.n_freqs, self.include_input)

    def extra_repr(self) -> str:
        return f"d={self.d}, n_freqs={self.n_freqs}, include_input={self.include_input}, out_dim={self.out_dim}"

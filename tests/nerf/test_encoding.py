"""Positional encoding: sizes, order, values at a known input."""

import math

import numpy as np
import torch

from course_lib.nerf.encoding import PositionalEncoding, encoded_dim, positional_encoding


def test_dims():
    assert positional_encoding(torch.zeros(7, 3), 10).shape == (7, 63)
    assert positional_encoding(torch.zeros(2, 5, 3), 4).shape == (2, 5, 27)
    assert positional_encoding(torch.zeros(4, 3), 10, include_input=False).shape == (4, 60)
    assert encoded_dim(3, 10) == 63 and encoded_dim(3, 4) == 27
    assert PositionalEncoding(3, 4).out_dim == 27


def test_order_and_values():
    x = torch.tensor([[0.25, 0.5, 1.0 / 6.0]], dtype=torch.float64)
    e = positional_encoding(x, 2)[0].numpy()
    np.testing.assert_allclose(e[:3], [0.25, 0.5, 1 / 6])  # identity first
    p = x[0].numpy()
    np.testing.assert_allclose(e[3:6], np.sin(math.pi * p))  # sin(2^0 pi x)
    np.testing.assert_allclose(e[6:9], np.cos(math.pi * p))  # cos(2^0 pi x)
    np.testing.assert_allclose(e[9:12], np.sin(2 * math.pi * p))  # sin(2^1 pi x)
    np.testing.assert_allclose(e[12:15], np.cos(2 * math.pi * p))
    # known values: sin(pi/4) = cos(pi/4), sin(pi/2) = 1, cos(pi) = -1, sin(pi/6) = 1/2
    np.testing.assert_allclose([e[3], e[6], e[4], e[13], e[5]],
                               [math.sqrt(0.5), math.sqrt(0.5), 1.0, -1.0, 0.5], atol=1e-12)


def test_zero_freqs_is_identity():
    x = torch.randn(3, 3)
    assert torch.equal(positional_encoding(x, 0), x)

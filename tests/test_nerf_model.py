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

"""Which pairs to match (course_lib.data.pairing): exhaustive, sequential, retrieval."""

import numpy as np
import pytest

from course_lib.data.features import Features
from course_lib.data.pairing import EXHAUSTIVE_MAX, exhaustive_pairs, retrieval_pairs, select_pairs, sequential_pairs, visual_words
from course_lib.validate import KitInputError


def _grouped_features(n_groups=4, per_group=6, seed=0):
    """Photos in groups: the photos of a group share most descriptors (they see the same things), groups share none."""
    rng = np.random.default_rng(seed)
    feats = []
    for g in range(n_groups):
        scene = rng.uniform(0, 1, (300, 128)).astype(np.float32)
        for _ in range(per_group):
            d = scene[rng.random(300) < 0.6] + rng.normal(0, 0.02, (1, 128)).astype(np.float32)
            feats.append(Features(rng.uniform(0, 100, (len(d), 2)), d))
    return feats


def test_exhaustive_and_sequential():
    assert exhaustive_pairs(4) == [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    assert sequential_pairs(5, 2) == [(0, 1), (0, 2), (1, 2), (1, 3), (2, 3), (2, 4), (3, 4)]
    with pytest.raises(KitInputError, match="at least 1"):
        sequential_pairs(5, 0)


def test_retrieval_finds_the_photos_of_the_same_group():
    feats = _grouped_features()
    H = visual_words(feats, n_words=64, rng=np.random.default_rng(0))
    assert H.shape == (24, 64) and np.allclose(np.linalg.norm(H, axis=1), 1.0, atol=1e-5)
    pairs = retrieval_pairs(feats, k=5, overlap=0, rng=np.random.default_rng(0))
    assert all(i // 6 == j // 6 for i, j in pairs)  # every retrieved pair lies within one group
    assert len(pairs) == 4 * 15  # ... and all pairs within the groups are found
    with_seq = retrieval_pairs(feats, k=5, overlap=1, rng=np.random.default_rng(0))
    assert set(pairs) < set(with_seq) and (5, 6) in with_seq
    assert retrieval_pairs(feats[:5], k=10) == exhaustive_pairs(5)


def test_select_pairs_by_name():
    feats = _grouped_features(2, 3)
    assert select_pairs("auto", feats) == (exhaustive_pairs(6), "exhaustive")
    assert select_pairs("sequential", feats, overlap=1)[0] == sequential_pairs(6, 1)
    assert EXHAUSTIVE_MAX >= 100
    with pytest.raises(KitInputError, match="expected one of"):
        select_pairs("all", feats)

"""Features of photos (course_lib.data.features): RootSIFT, detection, matching, geometric verification."""

import numpy as np
import pytest

from course_lib.data import building
from course_lib.data.features import (
    Features,
    detect_and_match,
    detect_features,
    match_descriptors,
    match_pairs,
    root_sift,
    track_colours,
)


def test_root_sift_is_the_square_root_of_the_l1_normalized_histogram():
    d = np.random.default_rng(0).uniform(0, 200, (5, 128)).astype(np.float32)
    r = root_sift(d)
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), 1.0, rtol=1e-5)
    np.testing.assert_allclose(r**2, d / d.sum(axis=1, keepdims=True), rtol=1e-5)


@pytest.fixture(scope="module")
def two_renders():
    rng = np.random.default_rng(3)
    surfaces = building.build_scene(rng, ground="large", rho=40.0)
    R_cw, t_cw = building.sfm_cameras(np.random.default_rng(1), 2)
    K = building.WPI_LIKE_K * np.array([[0.5], [0.5], [1.0]])
    images = []
    for i in range(2):
        rgb, _ = building.render(surfaces, K, R_cw[i], t_cw[i], (400, 300), supersample=1)
        images.append(np.round(rgb * 255).astype(np.uint8))
    return images, K, R_cw, t_cw


def test_lower_contrast_threshold_finds_more_features_and_matches_hold(two_renders):
    images, K, R_cw, t_cw = two_renders
    few, many = detect_features(images[:1])[0], detect_features(images[:1], contrast_threshold=0.02)[0]
    assert len(many) > len(few) > 100
    capped = detect_features(images[:1], max_features=50)[0]
    assert len(capped) <= 55  # OpenCV keeps ties at the cut
    for kw in ({}, {"rootsift": True, "contrast_threshold": 0.02}):
        x1, x2 = detect_and_match(images, **kw)[(0, 1)]
        e = building.epipolar_errors(K, R_cw[0], t_cw[0], R_cw[1], t_cw[1], x1, x2)
        assert len(x1) > 50 and np.median(e) < 0.5, (kw, len(x1), np.median(e))


def _brute_force_matches(f1, f2, ratio):
    """The rule of match_descriptors, written the slow and obvious way (float64 distances)."""
    d = np.linalg.norm(f1.descriptors[:, None, :].astype(float) - f2.descriptors[None, :, :].astype(float), axis=2)
    out = []
    for q in range(len(f1)):
        t0, t1 = np.argsort(d[q], kind="stable")[:2]
        back = int(np.argmin(d[:, t0]))
        if d[q, t0] < ratio * d[q, t1] and (back == q or np.array_equal(f1.xy[back], f1.xy[q])):
            out.append((q, t0))
    return np.array(out, int).reshape(-1, 2)


@pytest.mark.parametrize("rootsift", [False, True])
def test_match_descriptors_is_the_ratio_test_with_mutual_nearest_neighbours(two_renders, rootsift):
    images = two_renders[0]
    f1, f2 = detect_features(images, rootsift=rootsift, contrast_threshold=0.02)
    for ratio in (0.7, 0.8, 1.0):
        np.testing.assert_array_equal(match_descriptors(f1, f2, ratio), _brute_force_matches(f1, f2, ratio))


def test_match_descriptors_in_chunks_and_constrained(monkeypatch):
    """Large images are matched in row chunks (same result); ``allowed`` restricts the candidates of both directions."""
    import course_lib.data.features as features

    rng = np.random.default_rng(0)
    d1 = rng.uniform(0, 1, (300, 16)).astype(np.float32)
    d2 = np.concatenate([d1[:200] + rng.normal(0, 0.01, (200, 16)).astype(np.float32), rng.uniform(0, 1, (50, 16)).astype(np.float32)])
    f1, f2 = Features(rng.uniform(0, 100, (300, 2)), d1), Features(rng.uniform(0, 100, (250, 2)), d2)
    whole = match_descriptors(f1, f2)
    assert len(whole) > 180 and (whole[:, 0] == whole[:, 1]).all()
    monkeypatch.setattr(features, "_CHUNK_ENTRIES", 1000)
    np.testing.assert_array_equal(match_descriptors(Features(f1.xy, d1), Features(f2.xy, d2)), whole)
    even = lambda rows: ((np.arange(rows.start, rows.stop)[:, None] + np.arange(250)[None, :]) % 2) == 0  # noqa: E731
    m = match_descriptors(f1, f2, allowed=even)
    assert len(m) and ((m[:, 0] + m[:, 1]) % 2 == 0).all()
    assert match_descriptors(f1, Features(f2.xy[:1], d2[:1])).shape == (0, 2)


def test_match_pairs_in_parallel_is_the_same(two_renders):
    feats = detect_features(two_renders[0] * 2, rootsift=True, workers=2)
    pairs = [(0, 1), (0, 3), (1, 2), (2, 3)]
    serial, parallel = match_pairs(feats, pairs, workers=1), match_pairs(feats, pairs, workers=2)
    assert set(serial) == set(pairs)
    for k in pairs:
        np.testing.assert_array_equal(serial[k], parallel[k])


def test_track_colours_at_the_first_observation():
    images = [np.full((4, 5, 3), v, np.uint8) for v in (10, 20)]
    images[1][2, 3] = (1, 2, 3)
    uv = np.array([[[np.nan, np.nan], [3.2, 1.8]], [[0.0, 0.0], [1.0, 1.0]]])
    np.testing.assert_array_equal(track_colours(uv, images), [[1, 2, 3], [10, 10, 10]])
    assert track_colours(np.zeros((0, 2, 2)), images).shape == (0, 3)


def test_matching_ships_without_the_sfm_reference():
    """The student kit leaves the SfM reference (notebooks 01-05) out; ``match`` must still work there."""
    import ast
    from pathlib import Path

    import course_lib.data.features as features
    import course_lib.data.cli_match as match_cli

    for mod in (features, match_cli):
        tree = ast.parse(Path(mod.__file__).read_text())
        names = [n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module]
        names += [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
        assert not [m for m in names if m.startswith("course_lib.sfm")], (mod.__name__, names)

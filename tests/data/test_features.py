"""Features of photos (course_lib.data.features): RootSIFT, detection, matching, geometric verification."""

import numpy as np
import pytest

from course_lib.data import building
from course_lib.data.features import (
    detect_and_match,
    detect_features,
    keep_geometric_inliers,
    root_sift,
    track_colours,
)
from course_lib.data.synthetic import make_scene
from course_lib.validate import KitInputError


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


def test_keep_geometric_inliers_drops_outliers_and_weak_pairs():
    sc = make_scene(np.random.default_rng(2), n_cameras=3, n_points=200, noise_px=0.5, outlier_fraction=0.25)
    x1, x2, inlier, _ = sc.pair(0, 1)
    pairs = {(0, 1): (x1, x2), (0, 2): (x1[:10], x1[:10] + 3.0)}
    kept, counts = keep_geometric_inliers(pairs, np.random.default_rng(0), threshold_px=2.0, min_matches=15)
    assert set(kept) == {(0, 1)} and counts[(0, 2)] == 0
    k1, _ = kept[(0, 1)]
    assert counts[(0, 1)] == len(k1) >= 0.95 * inlier.sum()
    with pytest.raises(KitInputError, match="rng"):
        keep_geometric_inliers(pairs, 0)


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
    import course_lib.data.match_cli as match_cli

    for mod in (features, match_cli):
        tree = ast.parse(Path(mod.__file__).read_text())
        names = [n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module]
        names += [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
        assert not [m for m in names if m.startswith("course_lib.sfm")], (mod.__name__, names)

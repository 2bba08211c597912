"""Geometric verification of matched pairs (course_lib.data.two_view): USAC F, identical photos, guided matching, the P3 file."""

import numpy as np
import pytest

from course_lib.data import building
from course_lib.data.features import Features, detect_features, match_descriptors
from course_lib.data.synthetic import make_scene
from course_lib.data.two_view import (
    GEOMETRY_FILE,
    TwoViewGeometry,
    epipolar_distances,
    guided_matches,
    identical_photos,
    read_two_view_geometries,
    verify_pair,
    verify_pairs,
    write_two_view_geometries,
)
from course_lib.validate import KitInputError


def _verify(x1, x2, seed):
    """:func:`verify_pair` on two point sets matched row by row (features without descriptors)."""
    n = len(x1)
    f1, f2 = (Features(np.asarray(x, float), np.zeros((n, 128), np.float32)) for x in (x1, x2))
    return verify_pair(f1, f2, np.stack([np.arange(n)] * 2, axis=1), seed)


def _pair(outliers=0.3, seed=2):
    sc = make_scene(np.random.default_rng(seed), n_cameras=3, n_points=300, noise_px=0.5, outlier_fraction=outliers)
    x1, x2, inlier, _ = sc.pair(0, 1)
    return sc, x1, x2, inlier


class TestVerifyPair:
    def test_keeps_the_right_matches_and_finds_F(self):
        sc, x1, x2, inlier = _pair()
        F, inl, note = _verify(x1, x2, seed=0)
        assert note == "" and F.shape == (3, 3) and abs(np.linalg.norm(F) - 1) < 1e-9
        assert (inl & inlier).sum() >= 0.95 * inlier.sum() and (inl & ~inlier).sum() <= 0.05 * inl.sum()
        assert (epipolar_distances(F, x1[inl], x2[inl]) <= 4.0).all()

    def test_too_few_and_seeded(self):
        _, x1, x2, _ = _pair()
        F, inl, note = _verify(x1[:10], x2[:10], seed=0)
        assert F is None and not inl.any() and "fewer than 15" in note
        a, b = _verify(x1, x2, seed=3), _verify(x1, x2, seed=3)
        np.testing.assert_array_equal(a[1], b[1])

    def test_identical_photos_are_named(self):
        rng = np.random.default_rng(0)
        x1 = rng.uniform(0, 800, (200, 2))
        assert identical_photos(x1, x1 + rng.normal(0, 0.2, x1.shape))
        assert not identical_photos(x1, x1 + [5.0, 0.0])
        _, _, note = _verify(x1, x1 + rng.normal(0, 0.2, x1.shape), seed=0)
        assert note == "identical"


@pytest.fixture(scope="module")
def four_renders():
    """Four 400x300 renders of the building: photo 4 is the weakest (its best pair has < 100 matches)."""
    from course_lib.data.cli_match import scale_intrinsics

    surfaces = building.build_scene(np.random.default_rng(3), ground="large", rho=40.0)
    R_cw, t_cw = building.sfm_cameras(np.random.default_rng(1), 4)
    K = scale_intrinsics(building.WPI_LIKE_K.copy(), building.SFM_IMAGE_SIZE, (400, 300))
    images = [np.round(building.render(surfaces, K, R_cw[i], t_cw[i], (400, 300), supersample=1)[0] * 255).astype(np.uint8)
              for i in range(4)]
    return detect_features(images, 8192, True, 0.02), K, R_cw, t_cw


def test_guided_matching_adds_right_matches_along_the_epipolar_line(four_renders):
    feats, K, R_cw, t_cw = four_renders
    f1, f2 = feats[0], feats[3]
    m = match_descriptors(f1, f2)
    F, inl, _ = verify_pair(f1, f2, m, seed=0)
    g = guided_matches(f1, f2, F)
    e0 = building.epipolar_errors(K, R_cw[0], t_cw[0], R_cw[3], t_cw[3], f1.xy[m[inl, 0]], f2.xy[m[inl, 1]])
    e = building.epipolar_errors(K, R_cw[0], t_cw[0], R_cw[3], t_cw[3], f1.xy[g[:, 0]], f2.xy[g[:, 1]])
    assert (e < 2).sum() > 1.5 * (e0 < 2).sum()  # many more right matches
    assert np.mean(e < 2) > 0.7
    assert (epipolar_distances(F, f1.xy[g[:, 0]], f2.xy[g[:, 1]]) <= 2.0 + 1e-9).all()


def test_verify_pairs_guides_only_the_weak_photos_and_does_not_depend_on_threads(four_renders):
    feats = four_renders[0]
    matches = {(i, j): match_descriptors(feats[i], feats[j]) for i in range(4) for j in range(i + 1, 4)}
    one = verify_pairs(feats, matches, np.random.default_rng(0), workers=1)
    two = verify_pairs(feats, matches, np.random.default_rng(0), workers=2)
    for k in matches:
        np.testing.assert_array_equal(one[k].inliers, two[k].inliers)
    assert all(g.F is not None for g in one.values())
    best = {i: max(g.n_inliers - g.guided for k, g in one.items() if i in k) for i in range(4)}
    for (i, j), g in one.items():
        assert (g.guided > 0) <= (min(best[i], best[j]) < 50)  # guided only where a photo is weak
    plain = verify_pairs(feats, matches, np.random.default_rng(0), guided=False)
    assert all(g.guided == 0 for g in plain.values())


def test_the_P3_file_round_trip_and_a_broken_one(tmp_path):
    F = np.arange(9.0).reshape(3, 3) / np.linalg.norm(np.arange(9.0))
    geoms = {(0, 2): TwoViewGeometry(F, np.zeros((20, 2), int), np.ones(20, bool)),
             (1, 2): TwoViewGeometry(None, np.zeros((3, 2), int), np.zeros(3, bool), note="3 matches")}
    write_two_view_geometries(tmp_path, geoms, 4.0, 15)
    back = read_two_view_geometries(tmp_path, 3)
    assert set(back) == {(0, 2)}
    np.testing.assert_allclose(back[(0, 2)], F)
    assert read_two_view_geometries(tmp_path / "nowhere", 3) is None
    with pytest.raises(KitInputError, match="not two image numbers"):
        read_two_view_geometries(tmp_path, 2)
    (tmp_path / GEOMETRY_FILE).write_text("{not json")
    with pytest.raises(KitInputError, match="delete it"):
        read_two_view_geometries(tmp_path, 3)


def test_features_without_enough_points_are_not_verified():
    f = Features(np.zeros((1, 2)), np.zeros((1, 128), np.float32))
    out = verify_pairs([f, f], {(0, 1): np.zeros((0, 2), int)}, np.random.default_rng(0))
    assert out[(0, 1)].F is None and "0 matches" in out[(0, 1)].note

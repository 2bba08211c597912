"""The second look at every pose of a finished model (course_lib.sfm.relocalization): another PnP solution of lower
cost after a local BA replaces the model's pose; a right model stays as it is."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from course_lib.alignment import pose_errors
from course_lib.conventions import camera_center, rotation_angle_deg
from course_lib.data.synthetic import make_scene, write_scene_p3
from course_lib.sfm.mapper import IncrementalMapper, MapperOptions
from course_lib.sfm.relocalization import relocalize
from course_lib.sfm.tracks import verified_pairs_and_tracks


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A finished model of a synthetic scene (5 cameras, 300 points, 5 % outliers): ``(scene, mapper)``."""
    sc = make_scene(np.random.default_rng(3), n_cameras=5, n_points=300, outlier_fraction=0.05)
    data, _ = write_scene_p3(sc, tmp_path_factory.mktemp("p3"))
    opts = MapperOptions(relocalize_tries=0)  # built without the second look: the tests call it
    pairs, tracks = verified_pairs_and_tracks(data, np.random.default_rng(0), opts.f_threshold_px, opts.min_pair_matches, {})
    mapper = IncrementalMapper(data, pairs, tracks.uv, data.K, (800, 600), opts, np.random.default_rng(0))
    assert mapper.initialize(next(mapper.find_initial_pair()))
    while ranked := mapper.next_images():
        assert mapper.add_image(ranked[0][0])[0] is not None
    mapper.finish()
    return sc, mapper


def _state(mapper):
    return mapper.R.copy(), mapper.t.copy(), mapper.X.copy(), mapper.candidate.copy()


def _restore(mapper, state):
    mapper.R[:], mapper.t[:], mapper.X[:], mapper.candidate[:] = state


def _turned(R, t, centre, deg):
    """The camera turned ``deg`` about its own y axis through ``centre`` (the points stay in view)."""
    G = Rotation.from_rotvec(np.radians(deg) * R[1]).as_matrix()
    C = centre + G @ (camera_center(R, t) - centre)
    R2 = R @ G.T
    return R2, -R2 @ C


def test_a_pose_in_the_wrong_place_is_replaced_by_the_better_solution(finished):
    sc, mapper = finished
    saved = _state(mapper)
    i = int(np.flatnonzero(mapper.registered)[-1])
    right = mapper.R[i].copy()
    seen = mapper.has_X & mapper.visible[:, i]
    mapper.R[i], mapper.t[i] = _turned(mapper.R[i], mapper.t[i], mapper.X[seen].mean(axis=0), 4.0)
    try:
        out = relocalize(mapper, 2.0, 2, np.random.default_rng(1))
        assert [r["name"] for r in out["replaced"]] == [mapper.names[i]]
        assert out["replaced"][0]["cost_after"] < out["replaced"][0]["cost_before"]
        assert out["replaced"][0]["turn_deg"] == pytest.approx(4.0, abs=0.5)
        assert rotation_angle_deg(mapper.R[i], right) < 0.1
        reg = mapper.registered
        assert pose_errors(mapper.R[reg], mapper.t[reg], sc.R_cw[reg], sc.t_cw[reg]).rotation_deg.max() < 0.2
    finally:
        _restore(mapper, saved)


@pytest.mark.parametrize("tries", [2, 0], ids=["checked", "turned-off"])
def test_a_right_model_stays_as_it_is(finished, tries):
    _, mapper = finished
    saved = _state(mapper)
    out = relocalize(mapper, 2.0, tries, np.random.default_rng(1))
    assert out["replaced"] == [] and out["images"] == (int(mapper.registered.sum()) if tries else 0)
    for before, after in zip(saved, _state(mapper)):
        np.testing.assert_array_equal(before, after)


def test_the_pairs_term_follows_the_pose_and_not_the_points(finished):
    """The pairs' term of the cost (every verified match of the image with the registered images, against the two
    poses' epipolar geometry) tells a turned pose from the right one whatever the model's points say."""
    from course_lib.sfm.relocalization import _pair_cost

    _, mapper = finished
    saved = _state(mapper)
    i = int(np.flatnonzero(mapper.registered)[-1])
    try:
        right = _pair_cost(mapper, i, 2.0)
        mapper.X[:] += 5.0  # points the BA bent elsewhere: the pairs' term reads none of them
        assert _pair_cost(mapper, i, 2.0) == right
        seen = mapper.has_X & mapper.visible[:, i]
        mapper.R[i], mapper.t[i] = _turned(mapper.R[i], mapper.t[i], mapper.X[seen].mean(axis=0), 2.0)
        turned = _pair_cost(mapper, i, 2.0)
        assert turned > 3 * right  # 1287 against 174 on this scene
    finally:
        _restore(mapper, saved)

"""Visibility matrix and observation lists (course_lib.sfm.visibility)."""

import numpy as np
import pytest

from course_lib.data.synthetic import make_scene
from course_lib.sfm.visibility import observation_list, observations_to_uv, track_lengths, visibility_matrix
from course_lib.validate import KitInputError


@pytest.fixture(scope="module")
def scene():
    return make_scene(np.random.default_rng(1), n_cameras=4, n_points=60)


def test_visibility_matrix_matches_nan_pattern(scene):
    vis = visibility_matrix(scene.uv)
    assert vis.shape == (60, 4) and vis.dtype == bool
    np.testing.assert_array_equal(vis, scene.visible)
    np.testing.assert_array_equal(track_lengths(scene.uv), vis.sum(1))


def test_hand_example():
    uv = np.full((3, 2, 2), np.nan)
    uv[0, 0] = [1, 2]
    uv[0, 1] = [3, 4]
    uv[2, 1] = [5, 6]
    vis = visibility_matrix(uv)
    np.testing.assert_array_equal(vis, [[True, True], [False, False], [False, True]])
    obs = observation_list(uv)
    np.testing.assert_array_equal(obs.point_idx, [0, 0, 2])
    np.testing.assert_array_equal(obs.camera_idx, [0, 1, 1])
    np.testing.assert_array_equal(obs.uv, [[1, 2], [3, 4], [5, 6]])
    assert len(obs) == 3


def test_observation_list_round_trip_and_mask(scene):
    obs = observation_list(scene.uv)
    assert len(obs) == scene.visible.sum()
    back = observations_to_uv(obs, 60, 4)
    np.testing.assert_array_equal(np.isnan(back), np.isnan(scene.uv))
    np.testing.assert_allclose(back[scene.visible], scene.uv[scene.visible])
    mask = ~scene.outlier
    obs_in = observation_list(scene.uv, mask)
    assert len(obs_in) == (scene.visible & mask).sum()
    assert not scene.outlier[obs_in.point_idx, obs_in.camera_idx].any()


@pytest.mark.parametrize(
    "bad, msg",
    [
        (np.zeros((5, 2)), "expected (T, M, 2)"),
        (np.zeros((5, 2, 3)), "expected (T, M, 2)"),
        (np.array([[[np.nan, 1.0]]]), "one NaN coordinate"),
        (np.array([[[np.inf, 1.0]]]), "inf"),
    ],
)
def test_bad_inputs(bad, msg):
    with pytest.raises(KitInputError, match=msg.replace("(", r"\(").replace(")", r"\)")):
        visibility_matrix(bad)


def test_bad_mask(scene):
    with pytest.raises(KitInputError, match="mask has shape"):
        observation_list(scene.uv, np.ones((3, 3), bool))

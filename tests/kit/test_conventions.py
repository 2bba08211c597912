"""The conventions page: homogeneous helpers, pose direction, projection, input validation."""

import numpy as np
import pytest

from course_lib import conventions as cv
from course_lib import validate
from course_lib.data.synthetic import look_at, make_scene
from course_lib.alignment import align_similarity, pose_errors


def test_homogeneous_round_trip():
    x = np.array([[1.0, 2.0], [3.0, -4.0]])
    xh = cv.to_homogeneous(x)
    assert xh.shape == (2, 3) and np.all(xh[:, 2] == 1)
    assert np.allclose(cv.from_homogeneous(3.0 * xh), x)


def test_skew_is_cross_product():
    a, b = np.array([1.0, 2.0, 3.0]), np.array([-2.0, 0.5, 4.0])
    assert np.allclose(cv.skew(a) @ b, np.cross(a, b))


def test_pose_direction_and_centre():
    """x_cam = R_cw X + t_cw; the centre maps to the camera origin; +z is in front."""
    R, t = look_at(C=[0.0, 0.0, -5.0], target=[0.0, 0.0, 0.0])
    C = cv.camera_center(R, t)
    assert np.allclose(C, [0, 0, -5])
    assert np.allclose(cv.world_to_camera(R, t, C[None]), 0)
    assert cv.world_to_camera(R, t, np.zeros((1, 3)))[0, 2] == pytest.approx(5.0)
    assert np.allclose(cv.translation_from_center(R, C), t)


def test_look_at_puts_world_up_at_image_top():
    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    R, t = look_at(C=[0.0, 0.0, -5.0], target=[0.0, 0.0, 0.0], up=[0.0, -1.0, 0.0])
    top, bottom = cv.project(K, R, t, np.array([[0.0, -1.0, 0.0], [0.0, 1.0, 0.0]]))
    assert top[1] < 50 < bottom[1]  # v grows downwards: "up" (world -y) appears above the centre


def test_projection_matrix_matches_project():
    sc = make_scene(np.random.default_rng(0), n_cameras=2, n_points=20)
    P = cv.projection_matrix(sc.K, sc.R_cw[1], sc.t_cw[1])
    x = cv.from_homogeneous(cv.to_homogeneous(sc.X) @ P.T)
    assert np.allclose(x, cv.project(sc.K, sc.R_cw[1], sc.t_cw[1], sc.X))


def test_invert_and_compose():
    sc = make_scene(np.random.default_rng(1), n_cameras=2, n_points=5)
    R, t = sc.R_cw[0], sc.t_cw[0]
    Ri, ti = cv.invert_pose(R, t)
    Rc, tc = cv.compose_poses(R, t, Ri, ti)
    assert np.allclose(Rc, np.eye(3)) and np.allclose(tc, 0)


def test_similarity_alignment_recovers_transform():
    rng = np.random.default_rng(2)
    X = rng.normal(size=(30, 3))
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    Y = 2.5 * X @ R.T + [1.0, 2.0, 3.0]
    s, Ra, ta = align_similarity(X, Y)
    assert s == pytest.approx(2.5) and np.allclose(Ra, R) and np.allclose(ta, [1, 2, 3])


def test_pose_errors_are_zero_for_a_similar_reconstruction():
    sc = make_scene(np.random.default_rng(3), n_cameras=4, n_points=10)
    # Scale the world by 3: rotations stay, translations scale.
    e = pose_errors(sc.R_cw, 3.0 * sc.t_cw, sc.R_cw, sc.t_cw)
    assert e.rotation_deg.max() < 1e-4 and e.center.max() < 1e-9 and e.scale == pytest.approx(1 / 3)


@pytest.mark.parametrize(
    "x, message",
    [
        (np.zeros((7, 2)), "needs at least 8 correspondences"),
        (np.zeros((2, 10)), "transpose"),
        (np.array([[1.0, np.nan]] * 9), "NaN"),
        ("abc", "numeric array"),
    ],
)
def test_points_validation_messages(x, message):
    with pytest.raises(validate.KitInputError, match=message):
        validate.points(x, "x1", 2, min_count=8, why="the 8-point algorithm")


def test_intrinsics_validation():
    with pytest.raises(validate.KitInputError, match="not invertible"):
        validate.intrinsics(np.zeros((3, 3)) + np.diag([0, 0, 1.0]))
    with pytest.raises(validate.KitInputError, match=r"\(3, 3\)"):
        validate.intrinsics(np.eye(4))
    with pytest.raises(validate.KitInputError, match="det = -1"):
        validate.rotation(np.diag([1.0, 1.0, -1.0]))


def test_scene_has_ground_truth_noise_and_outliers():
    sc = make_scene(np.random.default_rng(4), n_points=500, noise_px=0.5, outlier_fraction=0.1)
    ok = sc.visible & ~sc.outlier
    err = (sc.uv - sc.uv_true)[ok]
    assert np.std(err) == pytest.approx(0.5, rel=0.1)
    assert 0.05 < sc.outlier[sc.visible].mean() < 0.15
    x1, x2, inl, ids = sc.pair(0, 1)
    assert x1.shape == x2.shape and len(inl) == len(ids) > 100

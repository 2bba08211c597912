"""Registering an image without 3-D points (course_lib.sfm.structureless): its pose from relative poses to posed partners."""

import numpy as np
from scipy.spatial.transform import Rotation

from course_lib.conventions import camera_center, rotation_angle_deg
from course_lib.sfm.structureless import pair_sampson, pose_from_partners, refine_on_partners

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])


def _pose(rng, center):
    R = Rotation.from_rotvec(rng.normal(0, 0.15, 3)).as_matrix()
    return R, -R @ np.asarray(center, float)


def _relative(R_k, t_k, R_i, t_i):
    """``(R_ki, t_ki)`` with ``|t_ki| = 1``: image i's pose in partner k's camera frame."""
    R = R_i @ R_k.T
    t = t_i - R @ t_k
    return R, t / np.linalg.norm(t)


def _scene(rng, centers=((0, 0, 0), (1.0, 0, 0), (0, 0.8, 0.2))):
    partners = [_pose(rng, c) for c in centers]
    new = _pose(rng, (0.5, 0.4, -0.3))
    return partners, new


def _inputs(partners, new):
    R_k = np.stack([p[0] for p in partners])
    t_k = np.stack([p[1] for p in partners])
    rel = [_relative(*p, *new) for p in partners]
    return R_k, t_k, np.stack([r[0] for r in rel]), np.stack([r[1] for r in rel])


def test_the_pose_from_three_partners_is_exact():
    rng = np.random.default_rng(0)
    partners, (R_true, t_true) = _scene(rng)
    found, why = pose_from_partners(*_inputs(partners, (R_true, t_true)), np.array([100.0, 80.0, 60.0]))
    assert why is None
    R, t, used = found
    assert used.all()
    np.testing.assert_allclose(R, R_true, atol=1e-9)
    np.testing.assert_allclose(t, t_true, atol=1e-9)


def test_a_partner_whose_rotation_disagrees_is_left_out():
    """Look-alike texture gives a relative pose tens of degrees off: that partner is not used."""
    rng = np.random.default_rng(1)
    partners, new = _scene(rng, centers=((0, 0, 0), (1.0, 0, 0), (0, 0.8, 0.2), (-0.7, 0.3, 0.1)))
    R_k, t_k, R_ki, t_ki = _inputs(partners, new)
    R_ki[2] = Rotation.from_euler("y", 40, degrees=True).as_matrix() @ R_ki[2]
    found, why = pose_from_partners(R_k, t_k, R_ki, t_ki, np.array([100.0, 90.0, 80.0, 70.0]))
    R, t, used = found
    assert used.tolist() == [True, True, False, True]
    assert rotation_angle_deg(R, new[0]) < 1e-6
    np.testing.assert_allclose(camera_center(R, t), camera_center(*new), atol=1e-9)


def test_one_partner_or_one_direction_cannot_fix_the_scale():
    rng = np.random.default_rng(2)
    partners, new = _scene(rng)
    R_k, t_k, R_ki, t_ki = _inputs(partners, new)
    R_ki[1:] = Rotation.from_euler("x", 30, degrees=True).as_matrix() @ R_ki[1:]
    found, why = pose_from_partners(R_k, t_k, R_ki, t_ki, np.array([100.0, 50.0, 50.0]))
    assert found is None and "two are needed" in why
    # the new camera on the line through two partners' centres: both see it in one direction
    line = [_pose(rng, c) for c in ((0, 0, 0), (1.0, 0, 0))]
    ahead = _pose(rng, (3.0, 0, 0))
    found, why = pose_from_partners(*_inputs(line, ahead), np.array([100.0, 100.0]))
    assert found is None and "one direction only" in why


def test_refinement_brings_a_perturbed_pose_back_on_noisy_matches():
    rng = np.random.default_rng(3)
    partners, (R_true, t_true) = _scene(rng)
    X = rng.uniform([-2, -2, 5], [2, 2, 9], (200, 3))

    def project(R, t):
        x = (X @ R.T + t) @ K.T
        return x[:, :2] / x[:, 2:] + rng.normal(0, 0.3, (len(X), 2))

    x_i = project(R_true, t_true)
    rows = [(R, t, project(R, t), x_i) for R, t in partners]
    R0 = Rotation.from_rotvec([0.01, -0.01, 0.005]).as_matrix() @ R_true
    t0 = t_true + np.array([0.03, -0.02, 0.02])
    R, t = refine_on_partners(K, R0, t0, rows)
    assert rotation_angle_deg(R, R_true) < 0.05
    assert np.linalg.norm(camera_center(R, t) - camera_center(R_true, t_true)) < 0.01
    d = np.concatenate([pair_sampson(K, Rk, tk, R, t, xk, xi) for Rk, tk, xk, xi in rows])
    assert np.sqrt(np.mean(d**2)) < 0.5

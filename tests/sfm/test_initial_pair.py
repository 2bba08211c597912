"""The two-view start (course_lib.sfm.initial_pair): the calibrated five-point pose, its refinement, degenerate pairs."""

import numpy as np
import pytest

from course_lib.conventions import project
from course_lib.data.synthetic import look_at
from course_lib.sfm.essential import essential_from_fundamental, pose_candidates
from course_lib.sfm.fundamental import ransac_fundamental, sampson_distance
from course_lib.sfm.initial_pair import calibrated_pose, fundamental_from_pose, pair_degeneracy, refine_pose
from course_lib.sfm.triangulation import choose_pose
from course_lib.validate import KitInputError

K = np.array([[425.0, 0.0, 319.5], [0.0, 425.0, 239.5], [0.0, 0.0, 1.0]])


def _angle_deg(R1, R2):
    return float(np.degrees(np.arccos(np.clip((np.trace(R1.T @ R2) - 1) / 2, -1, 1))))


def texture_poor_pair(seed=0, n=120, noise_px=0.7):
    """Two views 10 degrees apart of a patch with depth."""
    rng = np.random.default_rng(seed)
    X = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-2, 2, n), 10.0 + rng.uniform(-1, 1, n)])
    R1, t1 = np.eye(3), np.zeros(3)
    C2 = np.array([10.0 * np.sin(np.radians(10)), 0.2, 10.0 - 10.0 * np.cos(np.radians(10))])
    R2, _ = look_at(C2, np.array([0.0, 0.0, 10.0]))
    t2 = -R2 @ C2
    x1 = project(K, R1, t1, X) + rng.normal(0, noise_px, (n, 2))
    x2 = project(K, R2, t2, X) + rng.normal(0, noise_px, (n, 2))
    return x1, x2, R2, t2 / np.linalg.norm(t2)


def test_the_five_point_pose_fits_texture_poor_pairs_where_E_from_the_8_point_F_does_not():
    """The issue's texture-poor ring: pairs of 30-50 matches; the pose from E = KᵀFK missed its own inliers by tens of pixels."""
    from course_lib.data.scenes import texture_poor_ring_scene

    sc = texture_poor_ring_scene(np.random.default_rng(0))
    rows = []
    for i in range(sc.n_cameras):
        j = (i + 1) % sc.n_cameras
        x1, x2, _, _ = sc.pair(i, j)
        res = ransac_fundamental(x1, x2, np.random.default_rng(0), threshold_px=2.0)
        a, b = x1[res.inliers], x2[res.inliers]
        if len(a) < 30:
            continue
        choice, inl = calibrated_pose(a, b, sc.K, 4.0, seed=0)
        old = choose_pose(*pose_candidates(essential_from_fundamental(res.F, sc.K)), sc.K, a, b)
        rows.append((np.median(sampson_distance(fundamental_from_pose(sc.K, choice.R_cw, choice.t_cw), a, b)),
                     choice.in_front[inl].mean(), _angle_deg(choice.R_cw, sc.R_cw[j] @ sc.R_cw[i].T),
                     np.median(sampson_distance(fundamental_from_pose(sc.K, old.R_cw, old.t_cw), a, b))))
    d5, front, rot, d8 = np.array(rows).T
    assert len(rows) >= 10
    assert (d5 < 1.5).all() and np.median(d5) < 0.6 and (front > 0.95).all() and np.median(rot) < 2.0
    assert np.mean(d8 > 5.0) > 0.5  # most poses decomposed from the 8-point F miss their own inliers


def test_refine_pose_recovers_a_perturbed_pose():
    from scipy.spatial.transform import Rotation

    x1, x2, R2, t2 = texture_poor_pair(1, n=300, noise_px=0.3)
    R0 = Rotation.from_rotvec([0.01, -0.01, 0.005]).as_matrix() @ R2
    t0 = t2 + [0.03, -0.02, 0.0]
    R, t = refine_pose(x1, x2, K, R0, t0)
    assert _angle_deg(R0, R2) > 0.8 and _angle_deg(R, R2) < 0.2 and np.degrees(np.arccos(np.clip(t @ t2, -1, 1))) < 1.0
    assert abs(np.linalg.norm(t) - 1) < 1e-12


def test_too_few_matches():
    x1, x2, *_ = texture_poor_pair()
    with pytest.raises(KitInputError, match="at least 5"):
        calibrated_pose(x1[:4], x2[:4], K, 4.0, seed=0)


def test_degenerate_pairs_are_named():
    rng = np.random.default_rng(0)
    x1 = rng.uniform(0, 640, (100, 2))
    assert pair_degeneracy(x1, x1 + rng.normal(0, 0.2, x1.shape), K, 2.0)[0] == "identical or near-identical photos"
    # the camera turned on the spot: x2 = K R K^-1 x1
    from scipy.spatial.transform import Rotation

    H = K @ Rotation.from_rotvec([0.0, 0.2, 0.02]).as_matrix() @ np.linalg.inv(K)
    h = np.column_stack([x1, np.ones(100)]) @ H.T
    assert pair_degeneracy(x1, h[:, :2] / h[:, 2:], K, 2.0)[0] == "pure rotation"
    x1, x2, *_ = texture_poor_pair(n=100, noise_px=0.3)
    assert pair_degeneracy(x1[:7], x2[:7], K, 2.0) == ("", 0.0)

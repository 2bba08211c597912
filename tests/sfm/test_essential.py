"""Tests of course_lib.sfm.essential: E from F, the four pose candidates, OpenCV cross-checks."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from course_lib.conventions import rotation_angle_deg, skew, to_homogeneous
from course_lib.data.p3 import read_p3
from course_lib.data.synthetic import make_scene
from course_lib.paths import course_data
from course_lib.sfm.essential import W, essential_from_fundamental, pose_candidates
from course_lib.sfm.fundamental import eight_point, ransac_fundamental
from course_lib.validate import KitInputError


def relative_pose(scene, i, j):
    """(R, t) of camera j in the frame of camera i: x_j = R x_i + t."""
    R = scene.R_cw[j] @ scene.R_cw[i].T
    return R, scene.t_cw[j] - R @ scene.t_cw[i]


def true_essential(scene, i, j):
    R, t = relative_pose(scene, i, j)
    E = skew(t) @ R
    return E * np.sqrt(2) / np.linalg.norm(E)  # singular values (1, 1, 0)


def same_up_to_sign(A, B, atol):
    return min(np.abs(A - B).max(), np.abs(A + B).max()) < atol


def matching_candidates(R, C, R_true, C_true, rot_deg=1.0, cos_min=0.99):
    C_true = C_true / np.linalg.norm(C_true)
    return [k for k in range(4) if rotation_angle_deg(R[k], R_true) < rot_deg and C[k] @ C_true > cos_min]


@pytest.fixture(scope="module")
def noiseless():
    return make_scene(np.random.default_rng(3), n_cameras=3, n_points=200, noise_px=0.0, outlier_fraction=0.0)


@pytest.fixture(scope="module")
def scene():
    return make_scene(np.random.default_rng(11), n_cameras=4, n_points=400, noise_px=0.5, outlier_fraction=0.15)


def test_essential_from_true_fundamental(noiseless):
    x1, x2, _, _ = noiseless.pair(0, 1)
    F = eight_point(x1, x2)
    E = essential_from_fundamental(F, noiseless.K)
    np.testing.assert_allclose(np.linalg.svd(E, compute_uv=False), [1, 1, 0], atol=1e-12)
    assert same_up_to_sign(E, true_essential(noiseless, 0, 1), 1e-8)
    # y2ᵀ E y1 = 0 in normalized coordinates
    Ki = np.linalg.inv(noiseless.K)
    y1, y2 = to_homogeneous(x1) @ Ki.T, to_homogeneous(x2) @ Ki.T
    np.testing.assert_allclose(np.sum(y2 * (y1 @ E.T), axis=1), 0, atol=1e-10)


def test_essential_noisy_has_corrected_singular_values(scene):
    x1, x2, inl, _ = scene.pair(0, 2)
    E = essential_from_fundamental(eight_point(x1[inl], x2[inl]), scene.K)
    np.testing.assert_allclose(np.linalg.svd(E, compute_uv=False), [1, 1, 0], atol=1e-12)
    assert same_up_to_sign(E, true_essential(scene, 0, 2), 0.02)


def test_pose_candidates_properties(scene):
    x1, x2, inl, _ = scene.pair(0, 1)
    E = essential_from_fundamental(eight_point(x1[inl], x2[inl]), scene.K)
    R, C = pose_candidates(E)
    assert R.shape == (4, 3, 3) and C.shape == (4, 3)
    for k in range(4):
        np.testing.assert_allclose(R[k] @ R[k].T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R[k]) == pytest.approx(1.0)
        assert np.linalg.norm(C[k]) == pytest.approx(1.0)
        t = -R[k] @ C[k]
        assert same_up_to_sign(skew(t) @ R[k], E, 1e-9)  # E ∝ [t]ₓ R
        np.testing.assert_allclose(E @ C[k], 0, atol=1e-9)  # C is the right null vector
    # two rotations, two opposite centres
    np.testing.assert_allclose(R[0], R[1])
    np.testing.assert_allclose(R[2], R[3])
    np.testing.assert_allclose(C[0], -C[1])
    np.testing.assert_allclose(C[2], -C[3])


@pytest.mark.parametrize("pair", [(0, 1), (1, 3), (2, 0)])
def test_exactly_one_candidate_is_the_true_pose(scene, pair):
    x1, x2, inl, _ = scene.pair(*pair)
    E = essential_from_fundamental(eight_point(x1[inl], x2[inl]), scene.K)
    R, C = pose_candidates(E)
    R_true, t_true = relative_pose(scene, *pair)
    assert len(matching_candidates(R, C, R_true, -R_true.T @ t_true)) == 1


def test_det_minus_one_svd_is_flipped():
    # an E whose SVD factors have det U det V = -1: the raw U W Vᵀ would be a reflection
    rng = np.random.default_rng(0)
    for _ in range(20):
        E = skew(rng.normal(size=3)) @ cv2.Rodrigues(rng.normal(size=3))[0]
        R, C = pose_candidates(-E)
        assert np.allclose(np.linalg.det(R), 1.0)
        np.testing.assert_allclose(np.linalg.norm(C, axis=1), 1.0)


def test_W_is_a_rotation():
    np.testing.assert_allclose(W @ W.T, np.eye(3))
    assert np.linalg.det(W) == pytest.approx(1.0)


def test_recover_pose_matches_one_candidate(scene):
    x1, x2, _, _ = scene.pair(0, 3)
    res = ransac_fundamental(x1, x2, np.random.default_rng(0), threshold_px=1.5)
    E = essential_from_fundamental(res.F, scene.K)
    R, C = pose_candidates(E)
    a, b = x1[res.inliers], x2[res.inliers]
    _, R_cv, t_cv, _ = cv2.recoverPose(E, a, b, scene.K)
    C_cv = -R_cv.T @ t_cv.ravel()  # OpenCV's t is t_cw of camera 2
    hits = matching_candidates(R, C, R_cv, C_cv, rot_deg=1e-6, cos_min=1 - 1e-9)
    assert len(hits) == 1
    R_true, t_true = relative_pose(scene, 0, 3)
    assert rotation_angle_deg(R_cv, R_true) < 1.0


def test_opencv_essential_agrees(scene):
    x1, x2, inl, _ = scene.pair(0, 3)
    E = essential_from_fundamental(eight_point(x1[inl], x2[inl]), scene.K)
    E_cv, _ = cv2.findEssentialMat(x1[inl], x2[inl], scene.K, cv2.RANSAC, 0.999, 1.0)
    E_cv = E_cv[:3] * np.sqrt(2) / np.linalg.norm(E_cv[:3])
    # 8-point + correction and OpenCV's 5-point RANSAC: the same E up to noise
    assert same_up_to_sign(E, E_cv, 0.05)
    R, C = pose_candidates(E)
    _, R_cv, t_cv, _ = cv2.recoverPose(E_cv, x1[inl], x2[inl], scene.K)
    assert len(matching_candidates(R, C, R_cv, -R_cv.T @ t_cv.ravel())) == 1


def test_bad_inputs_give_clear_messages():
    F = np.arange(9.0).reshape(3, 3)
    K = np.diag([500.0, 500.0, 1.0])
    with pytest.raises(KitInputError, match="not invertible"):
        essential_from_fundamental(F, np.diag([0.0, 500.0, 1.0]))
    with pytest.raises(KitInputError, match=r"K has shape \(2, 2\)"):
        essential_from_fundamental(F, np.eye(2))
    with pytest.raises(KitInputError, match=r"F has shape \(3, 4\)"):
        essential_from_fundamental(np.zeros((3, 4)), K)
    with pytest.raises(KitInputError, match="all zeros"):
        essential_from_fundamental(np.zeros((3, 3)), K)
    bad = F.copy()
    bad[1, 1] = np.nan
    with pytest.raises(KitInputError, match="NaN"):
        essential_from_fundamental(bad, K)
    with pytest.raises(KitInputError, match="NaN"):
        pose_candidates(bad)
    with pytest.raises(KitInputError, match=r"E has shape \(9,\)"):
        pose_candidates(F.ravel())


def test_wpi_pair_1_2_pose():
    folder = course_data("wpi")
    if folder is None:
        pytest.skip("WPI course data not found (set COURSE_DATA or put it at ../shared/data); skipped the real-data check")
    data = read_p3(folder)
    K, x1, x2 = data.K, data.matches[(0, 1)].x1, data.matches[(0, 1)].x2
    res = ransac_fundamental(x1, x2, np.random.default_rng(0), threshold_px=1.0)
    E = essential_from_fundamental(res.F, K)
    R, C = pose_candidates(E)
    _, R_cv, t_cv, _ = cv2.recoverPose(E, x1[res.inliers], x2[res.inliers], K)
    # Same E on both sides, so the match is exact up to rounding; arccos near 1 resolves angles only
    # to ~1e-6 degrees (sqrt of machine epsilon), so the rotation tolerance sits above that.
    assert len(matching_candidates(R, C, R_cv, -R_cv.T @ t_cv.ravel(), 1e-4, 1 - 1e-9)) == 1

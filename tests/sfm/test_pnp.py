"""Tests of course_lib.sfm.pnp on the synthetic scene (ground truth), OpenCV and pycolmap."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from course_lib.conventions import rotation_angle_deg
from course_lib.data.p3 import read_p3
from course_lib.data.synthetic import make_scene
from course_lib.paths import course_data
from course_lib.sfm.pnp import PnPResult, pnp_linear, pnp_nonlinear, pnp_ransac, pnp_reprojection_errors
from course_lib.validate import KitInputError


def view(noise_px=0.0, outlier_fraction=0.0, seed=1, i=2, n_points=400):
    sc = make_scene(np.random.default_rng(seed), n_cameras=4, n_points=n_points, noise_px=noise_px,
                    outlier_fraction=outlier_fraction)
    vis = sc.visible[:, i]
    return sc, sc.X[vis], sc.uv[vis, i], sc.outlier[vis, i], sc.R_cw[i], sc.t_cw[i]


def rms(e):
    return float(np.sqrt(np.mean(np.square(e))))


def test_linear_exact_on_noiseless_data():
    sc, X, x, _, R, t = view()
    R_e, t_e = pnp_linear(X, x, sc.K)
    assert R_e.shape == (3, 3) and t_e.shape == (3,)
    assert np.linalg.det(R_e) == pytest.approx(1.0)
    np.testing.assert_allclose(R_e, R, atol=1e-8)
    np.testing.assert_allclose(t_e, t, atol=1e-7)
    # minimal case: 6 points
    R6, t6 = pnp_linear(X[:6], x[:6], sc.K)
    np.testing.assert_allclose(R6, R, atol=1e-6)
    np.testing.assert_allclose(t6, t, atol=1e-5)


def test_linear_noisy_is_close():
    sc, X, x, _, R, t = view(noise_px=0.5)
    R_e, t_e = pnp_linear(X, x, sc.K)
    assert rotation_angle_deg(R_e, R) < 0.5
    assert np.linalg.norm(t_e - t) < 0.1
    np.testing.assert_allclose(R_e @ R_e.T, np.eye(3), atol=1e-10)


def test_ransac_with_outliers_recovers_pose_and_matches_opencv():
    sc, X, x, out, R, t = view(noise_px=0.5, outlier_fraction=0.25)
    res = pnp_ransac(X, x, sc.K, np.random.default_rng(0), threshold_px=2.0)
    assert isinstance(res, PnPResult)
    assert res.inliers.shape == (len(X),) and res.inliers.dtype == bool
    assert rotation_angle_deg(res.R_cw, R) < 0.3
    assert np.linalg.norm(res.t_cw - t) < 0.05
    assert (res.inliers == ~out).mean() > 0.97
    assert 1 <= res.n_iters <= 1000
    ok, rvec, tvec, inl_cv = cv2.solvePnPRansac(X, x, sc.K, None, reprojectionError=2.0, confidence=0.999,
                                                  iterationsCount=1000, flags=cv2.SOLVEPNP_EPNP)
    assert ok
    R_cv = cv2.Rodrigues(rvec)[0]
    assert rotation_angle_deg(res.R_cw, R_cv) < 0.3
    assert np.linalg.norm(res.t_cw - tvec.ravel()) < 0.05
    mask_cv = np.zeros(len(X), bool)
    mask_cv[inl_cv.ravel()] = True
    assert (mask_cv == res.inliers).mean() > 0.95


def test_ransac_is_deterministic_and_adaptive():
    sc, X, x, out, R, t = view(noise_px=0.3, outlier_fraction=0.05)
    a = pnp_ransac(X, x, sc.K, np.random.default_rng(5))
    b = pnp_ransac(X, x, sc.K, np.random.default_rng(5))
    np.testing.assert_array_equal(a.inliers, b.inliers)
    assert a.n_iters == b.n_iters
    assert a.n_iters < 100  # 95 % inliers: a handful of samples is enough


def test_nonlinear_improves_and_reaches_noise_floor():
    sigma = 1.0
    sc, X, x, out, R, t = view(noise_px=sigma, outlier_fraction=0.0, n_points=600)
    R0, t0 = pnp_linear(X, x, sc.K)
    R1, t1 = pnp_nonlinear(X, x, sc.K, R0, t0)
    e0 = pnp_reprojection_errors(X, x, sc.K, R0, t0)
    e1 = pnp_reprojection_errors(X, x, sc.K, R1, t1)
    e_true = pnp_reprojection_errors(X, x, sc.K, R, t)
    assert rms(e1) <= rms(e0)
    assert rms(e1) <= rms(e_true) + 1e-9  # the least-squares optimum beats the truth on its own data
    assert rms(e1) == pytest.approx(np.sqrt(2) * sigma, rel=0.1)  # the noise floor
    assert rotation_angle_deg(R1, R) <= rotation_angle_deg(R0, R) + 0.02
    # and it agrees with OpenCV's iterative refinement from the same start
    rvec, tvec = cv2.solvePnPRefineLM(X, x, sc.K, None, cv2.Rodrigues(R0)[0], t0.reshape(3, 1).copy())
    assert rotation_angle_deg(R1, cv2.Rodrigues(rvec)[0]) < 1e-3
    np.testing.assert_allclose(t1, tvec.ravel(), atol=1e-4)


def test_nonlinear_from_perturbed_start():
    sc, X, x, out, R, t = view(noise_px=0.0)
    from scipy.spatial.transform import Rotation

    R0 = Rotation.from_rotvec([0.05, -0.03, 0.02]).as_matrix() @ R
    R1, t1 = pnp_nonlinear(X, x, sc.K, R0, t + 0.3)
    np.testing.assert_allclose(R1, R, atol=1e-8)
    np.testing.assert_allclose(t1, t, atol=1e-6)


def test_pycolmap_cross_check():
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap (environment.txt) is needed for the COLMAP cross-check")
    if not hasattr(pycolmap, "estimate_and_refine_absolute_pose"):
        pytest.skip("this pycolmap has no estimate_and_refine_absolute_pose")
    sc, X, x, out, R, t = view(noise_px=0.5, outlier_fraction=0.2)
    W, H = sc.image_size
    cam = pycolmap.Camera(model="PINHOLE", width=W, height=H,
                          params=[sc.K[0, 0], sc.K[1, 1], sc.K[0, 2], sc.K[1, 2]])
    try:
        ans = pycolmap.estimate_and_refine_absolute_pose(x, X, cam)
    except TypeError as exc:
        pytest.skip(f"pycolmap's absolute pose binding differs: {exc}")
    if ans is None:
        pytest.skip("pycolmap found no pose")
    T = ans["cam_from_world"].matrix()
    res = pnp_ransac(X, x, sc.K, np.random.default_rng(0))
    R1, t1 = pnp_nonlinear(X[res.inliers], x[res.inliers], sc.K, res.R_cw, res.t_cw)
    assert rotation_angle_deg(R1, T[:, :3]) < 0.05
    assert np.linalg.norm(t1 - T[:, 3]) < 0.01


def test_real_data_wpi_registration():
    folder = course_data("wpi")
    if folder is None:
        pytest.skip("the course data (WPI) is not on this machine")
    data = read_p3(folder)
    # 3-D points of image pair (0, 1) from OpenCV's two-view geometry (not the lesson here)
    m = data.matches[(0, 1)]
    E, mask = cv2.findEssentialMat(m.x1, m.x2, data.K, method=cv2.RANSAC, prob=0.999, threshold=1.0)
    _, R2, t2, mask2 = cv2.recoverPose(E, m.x1, m.x2, data.K, mask=mask.copy())
    keep = mask2.ravel() > 0
    P1 = data.K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = data.K @ np.hstack([R2, t2])
    Xh = cv2.triangulatePoints(P1, P2, m.x1[keep].T.copy(), m.x2[keep].T.copy())
    X = (Xh[:3] / Xh[3]).T
    ids = m.track_ids[keep]
    # the same tracks in image 2 (index 2)
    uv = data.track_uv[ids, 2]
    seen = (ids >= 0) & np.isfinite(uv).all(1)
    if seen.sum() < 20:
        pytest.skip(f"only {int(seen.sum())} tracks of pair (1, 2) are seen in image 3")
    X, x = X[seen], uv[seen]
    res = pnp_ransac(X, x, data.K, np.random.default_rng(0), threshold_px=3.0)
    R1, t1 = pnp_nonlinear(X[res.inliers], x[res.inliers], data.K, res.R_cw, res.t_cw)
    e = pnp_reprojection_errors(X[res.inliers], x[res.inliers], data.K, R1, t1)
    assert res.inliers.mean() > 0.5
    assert np.median(e) < 1.5
    ok, rvec, tvec, _ = cv2.solvePnPRansac(X, x, data.K, None, reprojectionError=3.0, flags=cv2.SOLVEPNP_EPNP)
    assert ok and rotation_angle_deg(R1, cv2.Rodrigues(rvec)[0]) < 2.0


@pytest.mark.parametrize(
    "call, words",
    [
        (lambda X, x, K: pnp_linear(X[:5], x[:5], K), "X has 5 rows: linear PnP needs at least 6 2D-3D correspondences"),
        (lambda X, x, K: pnp_linear(X, x[:-1], K), "row k of both must be the same correspondence"),
        (lambda X, x, K: pnp_linear(np.where(np.arange(len(X))[:, None] == 3, np.nan, X), x, K), "NaN"),
        (lambda X, x, K: pnp_linear(X, x, np.zeros((3, 3))), "not invertible"),
        (lambda X, x, K: pnp_linear(X.T, x, K), "transpose"),
        (lambda X, x, K: pnp_ransac(X, x, K, 0), "numpy Generator"),
        (lambda X, x, K: pnp_linear(X * np.array([1.0, 1.0, 0.0]) + np.array([0.0, 0.0, 10.0]), x, K), "one plane"),
        (lambda X, x, K: pnp_ransac(X[:4], x[:4], K, np.random.default_rng(0)), "PnP RANSAC needs at least 6"),
        (lambda X, x, K: pnp_nonlinear(X, x, K, -np.eye(3), np.zeros(3)), "det = -1"),
        (lambda X, x, K: pnp_ransac(X, np.random.default_rng(1).random(x.shape) * 800, K, np.random.default_rng(0),
                                    max_iters=20), "no pose"),
    ],
)
def test_bad_inputs_give_clear_messages(call, words):
    sc, X, x, *_ = view()
    with pytest.raises(KitInputError) as info:
        call(X[:30], x[:30], sc.K)
    assert words in str(info.value)

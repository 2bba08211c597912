"""Tests of course_lib.sfm.fundamental: normalization, 8-point, Sampson distance, RANSAC.

F is compared with the one built from the true poses of the synthetic scene (up to scale and
sign), cross-checked with OpenCV, and run on the real WPI pair (1, 2) where the course data is present.
"""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from course_lib.conventions import skew, to_homogeneous
from course_lib.data.p3 import read_p3
from course_lib.data.synthetic import make_scene
from course_lib.paths import course_data
from course_lib.sfm.fundamental import (
    RansacResult,
    eight_point,
    eight_point_batch,
    normalize_points,
    normalize_points_batch,
    ransac,
    ransac_fundamental,
    ransac_iterations,
    sampson_distance,
    sampson_distance_batch,
)
from course_lib.validate import KitInputError


def true_fundamental(scene, i, j):
    """F of images (i, j) from the true poses: F = K⁻ᵀ [t]ₓ R K⁻¹, unit norm."""
    R = scene.R_cw[j] @ scene.R_cw[i].T
    t = scene.t_cw[j] - R @ scene.t_cw[i]
    Ki = np.linalg.inv(scene.K)
    F = Ki.T @ skew(t) @ R @ Ki
    return F / np.linalg.norm(F)


def close_to_truth(F, scene, i, j, ids, tol_px):
    """F explains the *noiseless* projections of the pair to within tol_px (median Sampson distance).

    Entry-wise comparison of pixel-scale F is ill-conditioned with noise; this compares the geometry.
    """
    xt1, xt2 = scene.uv_true[ids, i], scene.uv_true[ids, j]
    return np.median(sampson_distance(F, xt1, xt2)) < tol_px


def same_up_to_sign(A, B, atol):
    A, B = A / np.linalg.norm(A), B / np.linalg.norm(B)
    return min(np.abs(A - B).max(), np.abs(A + B).max()) < atol


@pytest.fixture(scope="module")
def scene():
    return make_scene(np.random.default_rng(7), n_cameras=4, n_points=400, noise_px=0.5, outlier_fraction=0.2)


@pytest.fixture(scope="module")
def noiseless():
    return make_scene(np.random.default_rng(3), n_cameras=3, n_points=200, noise_px=0.0, outlier_fraction=0.0)


# -- normalize_points ---------------------------------------------------------------------------


def test_normalize_points_centroid_and_mean_distance():
    x = np.random.default_rng(0).uniform([0, 0], [800, 600], (50, 2))
    xn, T = normalize_points(x)
    assert xn.shape == (50, 2) and T.shape == (3, 3)
    np.testing.assert_allclose(xn.mean(0), 0.0, atol=1e-12)
    assert np.linalg.norm(xn, axis=1).mean() == pytest.approx(np.sqrt(2))
    np.testing.assert_allclose((to_homogeneous(x) @ T.T)[:, :2], xn, atol=1e-12)
    np.testing.assert_allclose(T[2], [0, 0, 1])


def test_normalize_points_identical_points_fail_clearly():
    with pytest.raises(KitInputError, match="identical"):
        normalize_points(np.tile([[3.0, 4.0]], (10, 1)))


# -- eight_point --------------------------------------------------------------------------------


def test_eight_point_noiseless_matches_truth(noiseless):
    x1, x2, inl, _ = noiseless.pair(0, 1)
    F = eight_point(x1, x2)
    assert same_up_to_sign(F, true_fundamental(noiseless, 0, 1), 1e-9)
    assert np.linalg.norm(F) == pytest.approx(1.0)
    assert np.abs(F).max() == F.flat[np.argmax(np.abs(F))]  # largest-|entry| positive
    # exactly 8 points suffice
    F8 = eight_point(x1[:8], x2[:8])
    assert same_up_to_sign(F8, true_fundamental(noiseless, 0, 1), 1e-6)


def test_eight_point_rank2_and_residuals(scene):
    x1, x2, inl, ids = scene.pair(0, 1)
    F = eight_point(x1[inl], x2[inl])
    s = np.linalg.svd(F, compute_uv=False)
    assert s[2] < 1e-12 * s[0]
    d = sampson_distance(F, x1[inl], x2[inl])
    assert np.median(d) < 0.5  # noise 0.5 px per coordinate
    assert close_to_truth(F, scene, 0, 1, ids, 0.2)
    # the constraint is x2ᵀ F x1 = 0, not x1ᵀ F x2
    assert np.median(sampson_distance(F.T, x1[inl], x2[inl])) > 10 * np.median(d)


def test_eight_point_matches_opencv_8point(scene):
    x1, x2, inl, _ = scene.pair(1, 2)
    F = eight_point(x1[inl], x2[inl])
    F_cv, _ = cv2.findFundamentalMat(x1[inl], x2[inl], cv2.FM_8POINT)
    assert same_up_to_sign(F, F_cv, 1e-6)


# -- sampson_distance ---------------------------------------------------------------------------


def test_sampson_distance_is_pixels_and_scale_free(noiseless):
    x1, x2, _, _ = noiseless.pair(0, 1)
    F = true_fundamental(noiseless, 0, 1)
    np.testing.assert_allclose(sampson_distance(F, x1, x2), 0.0, atol=1e-8)
    # move x2 by 3 px along the normal of its epipolar line: the distance is about 3 px / sqrt(2)...
    line = to_homogeneous(x1) @ F.T
    n = line[:, :2] / np.linalg.norm(line[:, :2], axis=1, keepdims=True)
    d = sampson_distance(F, x1, x2 + 3.0 * n)
    # ...exactly 3 px if only image 2 carried the error; Sampson splits it between the images.
    assert np.all(d > 1.0) and np.all(d < 3.0 + 1e-9)
    np.testing.assert_allclose(sampson_distance(-1000 * F, x1, x2 + 3.0 * n), d)


def test_sampson_distance_matches_opencv(scene):
    x1, x2, _, _ = scene.pair(0, 1)
    F = true_fundamental(scene, 0, 1)
    d_cv = np.array(
        [cv2.sampsonDistance(np.r_[a, 1.0].reshape(3, 1), np.r_[b, 1.0].reshape(3, 1), F) for a, b in zip(x1, x2)]
    )
    np.testing.assert_allclose(sampson_distance(F, x1, x2) ** 2, d_cv, rtol=1e-8, atol=1e-12)


# -- RANSAC -------------------------------------------------------------------------------------


def test_ransac_iterations_formula():
    assert ransac_iterations(0.5, 0.99, 8) == pytest.approx(np.log(0.01) / np.log(1 - 0.5**8))
    assert ransac_iterations(1.0) == 0.0
    assert ransac_iterations(0.0) == float("inf")


@pytest.mark.parametrize("pair", [(0, 1), (0, 3), (2, 3)])
def test_ransac_recovers_inliers(scene, pair):
    x1, x2, inl, ids = scene.pair(*pair)
    assert 0.1 < 1 - inl.mean() < 0.45  # the scene has 10-45 % outlier correspondences
    res = ransac_fundamental(x1, x2, np.random.default_rng(0), threshold_px=1.5)
    assert isinstance(res, RansacResult)
    precision = inl[res.inliers].mean()
    recall = res.inliers[inl].mean()
    assert precision > 0.97 and recall > 0.9, (precision, recall)
    assert res.n_iters < 2000  # the adaptive count stopped early
    assert close_to_truth(res.F, scene, *pair, ids, 0.5)
    assert np.linalg.norm(res.F) == pytest.approx(1.0)


def test_ransac_is_deterministic_for_a_seed(scene):
    x1, x2, _, _ = scene.pair(0, 1)
    a = ransac_fundamental(x1, x2, np.random.default_rng(5))
    b = ransac_fundamental(x1, x2, np.random.default_rng(5))
    np.testing.assert_array_equal(a.F, b.F)
    np.testing.assert_array_equal(a.inliers, b.inliers)
    assert a.n_iters == b.n_iters


def test_ransac_respects_max_iters(scene):
    x1, x2, _, _ = scene.pair(0, 1)
    assert ransac_fundamental(x1, x2, np.random.default_rng(0), max_iters=3).n_iters == 3


def test_ransac_agrees_with_opencv(scene):
    x1, x2, inl, _ = scene.pair(0, 2)
    res = ransac_fundamental(x1, x2, np.random.default_rng(1), threshold_px=1.5)
    cv2.setRNGSeed(0)
    F_cv, mask = cv2.findFundamentalMat(x1, x2, cv2.FM_RANSAC, 1.5, 0.999, 2000)
    mask = mask.ravel().astype(bool)
    # OpenCV's test is stricter (both point-to-line distances below the threshold), so its
    # inliers are (nearly) a subset of ours; the geometry is as good or better.
    assert res.inliers[mask].mean() > 0.97
    assert res.inliers.sum() >= mask.sum()
    d_ours = sampson_distance(res.F, x1[inl], x2[inl])
    d_cv = sampson_distance(F_cv, x1[inl], x2[inl])
    assert np.median(d_ours) <= np.median(d_cv) + 0.1


# -- bad inputs ---------------------------------------------------------------------------------


def test_bad_inputs_give_clear_messages():
    x = np.random.default_rng(0).uniform(0, 500, (20, 2))
    with pytest.raises(KitInputError, match=r"x1 has shape \(7, 2\): the 8-point algorithm needs at least 8 correspondences"):
        eight_point(x[:7], x[:7] + 1)
    bad = x.copy()
    bad[3, 1] = np.nan
    with pytest.raises(KitInputError, match="NaN"):
        eight_point(x, bad)
    with pytest.raises(KitInputError, match="transpose"):
        eight_point(x.T, x.T)
    with pytest.raises(KitInputError, match="same correspondence"):
        eight_point(x, x[:15])
    with pytest.raises(KitInputError, match="identical"):
        eight_point(np.ones((10, 2)), x[:10])
    with pytest.raises(KitInputError, match="degenerate"):
        line = np.c_[np.arange(10.0), 2 * np.arange(10.0)]  # collinear in both images
        eight_point(line, line)
    with pytest.raises(KitInputError, match="Generator"):
        ransac_fundamental(x, x, rng=0)
    with pytest.raises(KitInputError, match="threshold_px"):
        ransac_fundamental(x, x, np.random.default_rng(0), threshold_px=-1)
    with pytest.raises(KitInputError, match=r"\(3, 3\)"):
        sampson_distance(np.eye(2), x, x)
    with pytest.raises(KitInputError, match=r"x2 has shape \(20, 3\)"):
        sampson_distance(np.eye(3), x, np.c_[x, x[:, :1]])


# -- the batched building blocks and the generic RANSAC ----------------------------------------


def test_batched_parts_equal_the_checked_ones(scene):
    x1, x2, _, _ = scene.pair(0, 1)
    xs1 = np.stack([x1[:40], x1[40:80], x1[80:120]])
    xs2 = np.stack([x2[:40], x2[40:80], x2[80:120]])
    xn, T, ok = normalize_points_batch(xs1)
    F, okF = eight_point_batch(xs1, xs2)
    assert ok.all() and okF.all()
    d = sampson_distance_batch(F, x1, x2)
    assert d.shape == (3, len(x1))
    for b in range(3):
        xn_b, T_b = normalize_points(xs1[b])
        np.testing.assert_array_equal(xn[b], xn_b)
        np.testing.assert_array_equal(T[b], T_b)
        np.testing.assert_allclose(F[b], eight_point(xs1[b], xs2[b]), atol=1e-12)
        np.testing.assert_allclose(d[b], sampson_distance(F[b], x1, x2), rtol=1e-12)
    assert not normalize_points_batch(np.ones((1, 5, 2)))[2][0]


def test_ransac_takes_its_solver_and_error():
    """The generic RANSAC fits a 2-D line (minimal sample: 2 points) as well as F (kornia-style)."""
    rng = np.random.default_rng(3)
    t = rng.uniform(-10, 10, 100)
    pts = np.c_[t, 2 * t + 1] + rng.normal(0, 0.05, (100, 2))
    pts[:30] = rng.uniform(-20, 20, (30, 2))  # outliers

    def line_solver(a, b):  # a: (B, n, 2) points; fit v = m u + c by least squares
        A = np.stack([a[..., 0], np.ones_like(a[..., 0])], axis=2)
        sol = np.stack([np.linalg.lstsq(Ai, ai[:, 1], rcond=None)[0] for Ai, ai in zip(A, a)])
        return sol, np.ptp(a[..., 0], axis=1) > 1e-9

    def line_error(models, a, b):
        return np.abs(a[:, 1][None] - (models[:, :1] * a[:, 0][None] + models[:, 1:]))

    res = ransac(pts, pts, rng, line_solver, line_error, sample_size=2, threshold=0.3, batch=16)
    np.testing.assert_allclose(res.F, [2.0, 1.0], atol=0.05)
    assert res.inliers[30:].all() and res.inliers[:30].sum() <= 3
    np.testing.assert_allclose(res.distances, line_error(res.F[None], pts, pts)[0])


def test_ransac_fundamental_is_the_generic_ransac_one_sample_at_a_time(scene):
    x1, x2, _, _ = scene.pair(0, 2)
    a = ransac_fundamental(x1, x2, np.random.default_rng(5), threshold_px=1.0)
    b = ransac(x1, x2, np.random.default_rng(5), threshold=1.0)
    np.testing.assert_array_equal(a.F, b.F)
    np.testing.assert_array_equal(a.inliers, b.inliers)
    assert a.n_iters == b.n_iters


# -- the real course data -----------------------------------------------------------------------


def wpi_pair(folder, i=0, j=1):
    """Unique correspondences ``x1, x2`` of images (i, j) (0-based) of a P3 folder."""
    m = read_p3(folder).matches[(i, j)]
    return m.x1, m.x2


def test_ransac_on_wpi_pair_1_2():
    folder = course_data("wpi")
    if folder is None:
        pytest.skip("WPI course data not found (set COURSE_DATA or put it at ../shared/data); skipped the real-data check")
    x1, x2 = wpi_pair(folder, 0, 1)
    assert len(x1) >= 600
    t0 = time.perf_counter()
    res = ransac_fundamental(x1, x2, np.random.default_rng(0), threshold_px=1.0)
    elapsed = time.perf_counter() - t0
    frac = res.inliers.mean()
    d = sampson_distance(res.F, x1[res.inliers], x2[res.inliers])
    print(f"WPI (1,2): {res.n_inliers}/{len(x1)} inliers ({frac:.0%}), {res.n_iters} iterations, {elapsed:.2f} s")
    assert frac >= 0.6
    assert np.median(d) < 0.5

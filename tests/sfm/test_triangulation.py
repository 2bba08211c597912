"""Tests of course_lib.sfm.triangulation on the synthetic scene (ground truth), OpenCV and pycolmap."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from course_lib.conventions import projection_matrix, skew
from course_lib.data.p3 import read_p3
from course_lib.paths import course_data
from course_lib.sfm.essential import pose_candidates
from course_lib.sfm.triangulation import (
    choose_pose,
    reprojection_errors,
    triangulate_linear,
    triangulate_nonlinear,
)
from course_lib.validate import KitInputError
from tests.scenes import relative_scene


def candidates_from_E(E):
    """The four (R, C) of an essential matrix (Hartley & Zisserman 9.6), built here independently."""
    U, _, Vt = np.linalg.svd(E)
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    Rs, Cs = [], []
    for Wk in (W, W.T):
        R = U @ Wk @ Vt
        if np.linalg.det(R) < 0:
            R = -R
        for sign in (1.0, -1.0):
            t = sign * U[:, 2]
            Rs.append(R)
            Cs.append(-R.T @ t)
    return np.stack(Rs), np.stack(Cs)


def test_linear_noiseless_exact_and_matches_opencv():
    sc, R, t, X = relative_scene()
    x1, x2 = sc.uv[:, 0], sc.uv[:, 1]
    P1, P2 = projection_matrix(sc.K, R[0], t[0]), projection_matrix(sc.K, R[1], t[1])
    Xe = triangulate_linear(P1, P2, x1, x2)
    assert Xe.shape == X.shape
    np.testing.assert_allclose(Xe, X, atol=1e-6)
    Xcv = cv2.triangulatePoints(P1, P2, x1.T.copy(), x2.T.copy())
    np.testing.assert_allclose(Xe, (Xcv[:3] / Xcv[3]).T, atol=1e-6)


def test_linear_noisy_error_consistent_with_noise_and_close_to_opencv():
    sc, R, t, X = relative_scene(noise_px=0.5, n_points=500)
    x1, x2 = sc.uv[:, 0], sc.uv[:, 1]
    P1, P2 = projection_matrix(sc.K, R[0], t[0]), projection_matrix(sc.K, R[1], t[1])
    Xe = triangulate_linear(P1, P2, x1, x2)
    rmse = np.sqrt(((Xe - X) ** 2).sum(1).mean())
    # depth error ~ Z^2 / (f b) * sigma: Z ~ 10, f ~ 530, baseline ~ 2.6 -> ~0.04 per 0.5 px
    assert 0.005 < rmse < 0.2
    Xcv = cv2.triangulatePoints(P1, P2, x1.T.copy(), x2.T.copy())
    Xcv = (Xcv[:3] / Xcv[3]).T
    assert np.median(np.linalg.norm(Xe - Xcv, axis=1)) < 0.2 * rmse + 1e-3
    e = reprojection_errors(sc.K, R[1], t[1], Xe, x2)
    assert e.shape == (len(X),) and 0.1 < np.sqrt((e**2).mean()) < 1.0


def test_choose_pose_picks_true_candidate_and_agrees_with_recoverpose():
    sc, R, t, X = relative_scene(noise_px=0.3)
    x1, x2 = sc.uv[:, 0], sc.uv[:, 1]
    E = skew(t[1]) @ R[1]
    E /= np.linalg.norm(E)
    Rc, Cc = candidates_from_E(E)
    choice = choose_pose(Rc, Cc, sc.K, x1, x2)
    t_true = t[1] / np.linalg.norm(t[1])
    np.testing.assert_allclose(choice.R_cw, R[1], atol=1e-8)
    np.testing.assert_allclose(choice.t_cw, t_true, atol=1e-8)
    assert choice.counts.shape == (4,) and choice.counts[choice.index] == choice.counts.max()
    assert choice.in_front.mean() > 0.99
    assert sorted(choice.counts)[-2] < 0.5 * len(x1)  # the three wrong candidates lose clearly
    # OpenCV's recoverPose from the same E
    _, R_cv, t_cv, _ = cv2.recoverPose(E, x1, x2, sc.K)
    np.testing.assert_allclose(choice.R_cw, R_cv, atol=1e-6)
    np.testing.assert_allclose(choice.t_cw, t_cv.ravel(), atol=1e-6)
    # the scale of X is that of the unit baseline
    s = np.linalg.norm(t[1])
    np.testing.assert_allclose(choice.X[choice.in_front] * s, X[choice.in_front], atol=0.5)


def test_choose_pose_with_the_essential_candidates():
    sc, R, t, X = relative_scene(noise_px=0.3)
    E = skew(t[1]) @ R[1]
    Rc, Cc = pose_candidates(E / np.linalg.norm(E))
    choice = choose_pose(Rc, Cc, sc.K, sc.uv[:, 0], sc.uv[:, 1])
    np.testing.assert_allclose(choice.R_cw, R[1], atol=1e-6)
    np.testing.assert_allclose(choice.t_cw, t[1] / np.linalg.norm(t[1]), atol=1e-6)


def test_nonlinear_lowers_reprojection_error_and_rmse_matches_noise():
    sc, R, t, X = relative_scene(noise_px=1.0, n_points=500)
    uv = sc.uv
    P1, P2 = projection_matrix(sc.K, R[0], t[0]), projection_matrix(sc.K, R[1], t[1])
    X0 = triangulate_linear(P1, P2, uv[:, 0], uv[:, 1])
    Xn = triangulate_nonlinear(sc.K, R, t, uv, X0)  # all three views

    def rms(Xs):
        e = np.concatenate([reprojection_errors(sc.K, R[i], t[i], Xs, uv[:, i]) for i in range(3)])
        return np.sqrt((e**2).mean())

    assert rms(Xn) < rms(X0)
    # with the true points the residual is the injected noise: sqrt(2) * sigma per observation;
    # the optimum has 3 fewer dof per point out of 6 -> sqrt(2 * (6 - 3) / 6) * sigma
    assert rms(Xn) == pytest.approx(np.sqrt(2 * 3 / 6) * 1.0, rel=0.15)
    assert rms(Xn) < rms(X)
    # and the points are closer to the truth than the two-view linear ones
    err0 = np.sqrt(((X0 - X) ** 2).sum(1).mean())
    errn = np.sqrt(((Xn - X) ** 2).sum(1).mean())
    assert errn < err0


def test_nonlinear_handles_unseen_and_many_points():
    sc, R, t, X = relative_scene(noise_px=1.0, n_points=3000)
    uv = sc.uv[:, :2].copy()
    P1, P2 = projection_matrix(sc.K, R[0], t[0]), projection_matrix(sc.K, R[1], t[1])
    X0 = triangulate_linear(P1, P2, uv[:, 0], uv[:, 1])
    uv[:10, 1] = np.nan  # seen once only: must come back unchanged
    Xn = triangulate_nonlinear(sc.K, R[:2], t[:2], uv, X0)  # timing: see the report (< 0.1 s here, unloaded)
    np.testing.assert_array_equal(Xn[:10], X0[:10])
    assert np.isfinite(Xn).all()


def test_pycolmap_cross_check():
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap (environment.txt) is needed for the COLMAP cross-check")
    fn = getattr(pycolmap, "triangulate_point", None) or getattr(pycolmap, "TriangulatePoint", None)
    if fn is None:
        pytest.skip("this pycolmap has no triangulate_point")
    sc, R, t, X = relative_scene(noise_px=0.0, n_points=20)
    P1 = np.hstack([R[0], t[0][:, None]])
    P2 = np.hstack([R[1], t[1][:, None]])
    Kinv = np.linalg.inv(sc.K)
    x1 = (np.c_[sc.uv[:, 0], np.ones(20)] @ Kinv.T)[:, :2]
    x2 = (np.c_[sc.uv[:, 1], np.ones(20)] @ Kinv.T)[:, :2]
    Xe = triangulate_linear(P1, P2, x1, x2)
    for k in range(20):
        try:
            Xc = fn(P1, P2, x1[k], x2[k])
        except TypeError as exc:  # the binding's signature changed between versions
            pytest.skip(f"pycolmap.triangulate_point signature differs: {exc}")
        np.testing.assert_allclose(np.asarray(Xc).ravel()[:3], Xe[k], atol=1e-6)


def test_real_data_wpi_pair():
    folder = course_data("wpi")
    if folder is None:
        pytest.skip("the course data (WPI) is not on this machine")
    data = read_p3(folder)
    m = data.matches[(0, 1)]
    # two-view geometry from OpenCV (not the lesson here): essential matrix + recoverPose
    E, mask = cv2.findEssentialMat(m.x1, m.x2, data.K, method=cv2.RANSAC, prob=0.999, threshold=1.0)
    inl = mask.ravel() > 0
    x1, x2 = m.x1[inl], m.x2[inl]
    Rc, Cc = candidates_from_E(E)
    choice = choose_pose(Rc, Cc, data.K, x1, x2)
    _, R_cv, t_cv, _ = cv2.recoverPose(E, x1, x2, data.K)
    np.testing.assert_allclose(choice.R_cw, R_cv, atol=1e-6)
    assert choice.in_front.mean() > 0.9
    X0 = choice.X
    uv = np.stack([x1, x2], axis=1)
    Rs = np.stack([np.eye(3), choice.R_cw])
    ts = np.stack([np.zeros(3), choice.t_cw])
    Xn = triangulate_nonlinear(data.K, Rs, ts, uv, X0)
    e0 = np.concatenate([reprojection_errors(data.K, Rs[i], ts[i], X0, uv[:, i]) for i in range(2)])
    en = np.concatenate([reprojection_errors(data.K, Rs[i], ts[i], Xn, uv[:, i]) for i in range(2)])
    assert np.sqrt((en**2).mean()) <= np.sqrt((e0**2).mean()) + 1e-9
    assert np.median(en) < 1.0


@pytest.mark.parametrize(
    "call, words",
    [
        (lambda P, x: triangulate_linear(P[:, :3], P, x, x), "(3, 4) projection matrix"),
        (lambda P, x: triangulate_linear(P, P, x, x[:-1]), "rows"),
        (lambda P, x: triangulate_linear(P, P, x.T, x.T), "transpose"),
        (lambda P, x: triangulate_linear(P, P, np.where(np.arange(len(x))[:, None] == 2, np.nan, x), x), "NaN"),
        (lambda P, x: choose_pose(np.zeros((3, 3, 3)), np.zeros((4, 3)), np.eye(3), x, x), "four pose candidates"),
        (lambda P, x: reprojection_errors(np.zeros((3, 3)), np.eye(3), np.zeros(3), np.zeros((len(x), 3)), x), "not invertible"),
        (lambda P, x: triangulate_nonlinear(np.eye(3), np.eye(3)[None].repeat(2, 0), np.zeros((2, 3)),
                                            np.zeros((len(x), 3, 2)), np.zeros((len(x), 3))), "(N, V, 2)"),
    ],
)
def test_bad_inputs_give_clear_messages(call, words):
    P = np.hstack([np.eye(3), np.zeros((3, 1))])
    x = np.random.default_rng(0).random((5, 2))
    with pytest.raises(KitInputError, match=None) as info:
        call(P, x)
    assert words in str(info.value)

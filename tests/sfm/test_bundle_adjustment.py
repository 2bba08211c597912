"""Bundle adjustment (course_lib.sfm.bundle_adjustment): Jacobian, convergence, gauge, robust loss, inputs."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from course_lib.conventions import camera_center, rotation_angle_deg
from course_lib.data.synthetic import make_scene
from course_lib.sfm import bundle_adjustment as ba
from course_lib.alignment import align_similarity
from course_lib.sfm.visibility import observation_list
from course_lib.validate import KitInputError

NOISE = 0.5


@pytest.fixture(scope="module")
def scene():
    return make_scene(np.random.default_rng(7), n_cameras=5, n_points=250, noise_px=NOISE, outlier_fraction=0.0)


def perturbed(scene, rng, rot_deg=1.0, trans=0.2, pts=0.2):
    """Start values: truth with camera 0 kept, the others and the points perturbed."""
    R = scene.R_cw.copy()
    t = scene.t_cw.copy()
    for i in range(1, scene.n_cameras):
        R[i] = Rotation.from_rotvec(np.radians(rot_deg) * rng.normal(size=3) / np.sqrt(3)).as_matrix() @ R[i]
        t[i] = t[i] + rng.normal(0, trans, 3)
    X = scene.X + rng.normal(0, pts, scene.X.shape)
    return R, t, X


def numeric_jacobian(fun, p, cols, h=1e-6):
    J = np.zeros((fun(p).size, len(cols)))
    for c, k in enumerate(cols):
        e = np.zeros_like(p)
        e[k] = h
        J[:, c] = (fun(p + e) - fun(p - e)) / (2 * h)
    return J


@pytest.mark.parametrize("angle", [0.0, 1e-6, 0.3, 2.5])  # rotation vectors of camera 0: zero, tiny, moderate, large
def test_jacobian_matches_finite_differences(scene, angle):
    """The analytic Jacobian equals central finite differences, at every size of rotation vector."""
    # Rotate the whole world by G so that camera 0's rotation vector has length `angle`
    # (projections do not change: X' = G X, R' = R G^T).
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    G = Rotation.from_rotvec(angle * axis).as_matrix() @ scene.R_cw[0]
    R = scene.R_cw @ G.T
    X = scene.X @ G.T
    obs = observation_list(scene.uv)
    M, N = scene.n_cameras, len(scene.X)
    K = scene.K.copy()
    K[0, 1] = 2.0  # a skew term, so that entry of the derivative is tested too
    p = ba.pack_params(R, scene.t_cw, X)
    assert abs(np.linalg.norm(p[:3]) - angle) < 1e-9
    fun = lambda q: ba.reprojection_residuals(q, M, N, obs.camera_idx, obs.point_idx, obs.uv, K)  # noqa: E731
    J = ba.reprojection_jacobian(p, M, N, obs.camera_idx, obs.point_idx, K)
    cols = list(range(6 * M)) + list(range(6 * M, p.size, 37))
    Jn = numeric_jacobian(fun, p, cols)
    Ja = J.toarray()[:, cols]
    assert np.abs(Ja - Jn).max() < 1e-5 * np.abs(Ja).max()


def test_sparsity_pattern(scene):
    obs = observation_list(scene.uv)
    M, N = scene.n_cameras, len(scene.X)
    S = ba.jacobian_sparsity(M, N, obs.camera_idx, obs.point_idx)
    assert S.shape == (2 * len(obs), 6 * M + 3 * N)
    assert S.nnz == 2 * len(obs) * 9
    J = ba.reprojection_jacobian(ba.pack_params(scene.R_cw, scene.t_cw, scene.X), M, N, obs.camera_idx, obs.point_idx, scene.K)
    nz = J.toarray() != 0
    assert not (nz & (S.toarray() == 0)).any()  # the Jacobian is zero outside the pattern
    k = 5
    row = S.getrow(2 * k).indices
    assert set(row) == set(range(6 * obs.camera_idx[k], 6 * obs.camera_idx[k] + 6)) | set(
        range(6 * M + 3 * obs.point_idx[k], 6 * M + 3 * obs.point_idx[k] + 3)
    )


def test_pack_unpack_round_trip(scene):
    p = ba.pack_params(scene.R_cw, scene.t_cw, scene.X)
    assert p.shape == (6 * 5 + 3 * 250,)
    R, t, X = ba.unpack_params(p, 5, 250)
    np.testing.assert_allclose(R, scene.R_cw, atol=1e-12)
    np.testing.assert_allclose(t, scene.t_cw)
    np.testing.assert_allclose(X, scene.X)
    with pytest.raises(KitInputError, match="params has shape"):
        ba.unpack_params(p[:-1], 5, 250)


def test_residuals_vanish_at_truth_without_noise(scene):
    obs = observation_list(scene.uv_true)
    p = ba.pack_params(scene.R_cw, scene.t_cw, scene.X)
    r = ba.reprojection_residuals(p, 5, 250, obs.camera_idx, obs.point_idx, obs.uv, scene.K)
    assert r.shape == (2 * len(obs),)
    assert np.abs(r).max() < 1e-9


def test_converges_to_the_noise_level_and_the_truth(scene):
    rng = np.random.default_rng(11)
    R0, t0, X0 = perturbed(scene, rng)
    res = ba.bundle_adjust(scene.K, R0, t0, X0, scene.uv, keep_iterates=True)
    assert res.success
    assert res.initial_rms > 10 * res.final_rms
    # Expected RMS of the 2-D residual at the optimum: sigma * sqrt(2) * sqrt(1 - n_params / n_residuals)
    n_res = 2 * len(res.point_idx)
    n_par = 6 * 4 - 1 + 3 * 250
    expected = NOISE * np.sqrt(2) * np.sqrt(1 - n_par / n_res)
    assert abs(res.final_rms - expected) < 0.1 * expected, (res.final_rms, expected)
    # gauge: camera 0 untouched
    np.testing.assert_allclose(res.R_cw[0], scene.R_cw[0], atol=1e-12)
    np.testing.assert_allclose(res.t_cw[0], scene.t_cw[0], atol=1e-12)
    assert "camera 0 fixed" in res.gauge and "scale" in res.gauge
    # poses and points close to the truth after a similarity alignment (on the points)
    s, Ra, ta = align_similarity(res.X, scene.X)
    X_al = s * res.X @ Ra.T + ta
    size = scene.scene_size
    assert np.median(np.linalg.norm(X_al - scene.X, axis=1)) < 0.005 * size
    for i in range(5):
        assert rotation_angle_deg(res.R_cw[i] @ Ra.T, scene.R_cw[i]) < 0.25  # 0.5 px noise, 250 points
        C = s * Ra @ camera_center(res.R_cw[i], res.t_cw[i]) + ta
        assert np.linalg.norm(C - camera_center(scene.R_cw[i], scene.t_cw[i])) < 0.01 * size
    # history: one cost per iterate, non-increasing overall
    assert len(res.cost_history) == len(res.iterates) >= 2
    assert res.cost_history[-1] < res.cost_history[0]
    assert abs(res.cost_history[-1] - 0.5 * (res.final_errors**2).sum()) < 1e-6 * res.cost_history[-1]
    assert "observations" in res.summary()


def test_lm_and_trf_reach_the_same_minimum(scene):
    rng = np.random.default_rng(14)
    R0, t0, X0 = perturbed(scene, rng)
    lm = ba.bundle_adjust(scene.K, R0, t0, X0, scene.uv, method="lm")
    trf = ba.bundle_adjust(scene.K, R0, t0, X0, scene.uv, method="trf")
    assert lm.method == "lm" and trf.method == "trf"
    assert abs(lm.cost_history[-1] - trf.cost_history[-1]) < 1e-4 * trf.cost_history[-1]
    np.testing.assert_allclose(lm.X, trf.X, atol=1e-3)
    assert lm.n_iterations <= 15


def test_scale_fixed_by_one_translation_coordinate(scene):
    rng = np.random.default_rng(12)
    R0, t0, X0 = perturbed(scene, rng)
    res = ba.bundle_adjust(scene.K, R0, t0, X0, scene.uv, scale_camera=3)
    k = int(res.gauge.split("t_cw[3][")[1][0])
    assert res.t_cw[3][k] == t0[3][k]
    free = ba.bundle_adjust(scene.K, R0, t0, X0, scene.uv, fix_scale=False)
    assert "scale free" in free.gauge
    assert abs(free.final_rms - res.final_rms) < 1e-3  # the same optimum up to the gauge


def test_callback_sees_every_iteration(scene):
    rng = np.random.default_rng(13)
    R0, t0, X0 = perturbed(scene, rng)
    seen = []
    res = ba.bundle_adjust(scene.K, R0, t0, X0, scene.uv, callback=lambda it, R, t, X, cost: seen.append((it, cost)))
    assert [s[0] for s in seen] == list(range(len(seen)))
    assert np.allclose([s[1] for s in seen], res.cost_history)


def test_huber_loss_resists_outliers():
    sc = make_scene(np.random.default_rng(21), n_cameras=5, n_points=250, noise_px=0.5, outlier_fraction=0.05)
    rng = np.random.default_rng(22)
    R0, t0, X0 = perturbed(sc, rng, rot_deg=0.5, trans=0.1, pts=0.1)
    plain = ba.bundle_adjust(sc.K, R0, t0, X0, sc.uv, max_iterations=20)
    robust = ba.bundle_adjust(sc.K, R0, t0, X0, sc.uv, loss="huber", f_scale=1.0, ftol=1e-6)

    clean = ~(sc.outlier & sc.visible).any(axis=1)  # points without an outlier observation

    def err(res):
        s, Ra, ta = align_similarity(res.X[clean], sc.X[clean])
        return np.median(np.linalg.norm(s * res.X[clean] @ Ra.T + ta - sc.X[clean], axis=1))

    assert err(robust) < 0.5 * err(plain)
    inl = ~sc.outlier[robust.point_idx, robust.camera_idx]
    assert np.median(robust.final_errors[inl]) < 1.0


def test_points_without_observations_are_kept(scene):
    uv = scene.uv.copy()
    uv[0] = np.nan
    X = scene.X.copy()
    X[0] = np.nan
    res = ba.bundle_adjust(scene.K, scene.R_cw, scene.t_cw, X, uv, max_iterations=5)
    assert np.isnan(res.X[0]).all() and np.isfinite(res.X[1:]).all()


def test_bad_inputs(scene):
    K, R, t, X, uv = scene.K, scene.R_cw, scene.t_cw, scene.X, scene.uv
    with pytest.raises(KitInputError, match="R_cw has shape"):
        ba.bundle_adjust(K, R[0], t, X, uv)
    with pytest.raises(KitInputError, match="t_cw has shape"):
        ba.bundle_adjust(K, R, t[:3], X, uv)
    with pytest.raises(KitInputError, match="uv has shape"):
        ba.bundle_adjust(K, R, t, X, uv[:, :3])
    with pytest.raises(KitInputError, match="det = -1"):
        ba.bundle_adjust(K, np.concatenate([-R[:1], R[1:]]), t, X, uv)
    X2 = X.copy()
    X2[3] = np.nan
    with pytest.raises(KitInputError, match=r"X\[3\] is NaN"):
        ba.bundle_adjust(K, R, t, X2, uv)
    uv1 = uv.copy()
    uv1[:, 1:] = np.nan
    with pytest.raises(KitInputError, match="at least two"):
        ba.bundle_adjust(K, R, t, X, uv1)
    with pytest.raises(KitInputError, match="not invertible"):
        ba.bundle_adjust(np.zeros((3, 3)) + np.diag([0, 0, 1.0]), R, t, X, uv)
    with pytest.raises(KitInputError, match="method="):
        ba.bundle_adjust(K, R, t, X, uv, method="gauss")
    with pytest.raises(KitInputError, match="loss="):
        ba.bundle_adjust(K, R, t, X, uv, loss="l1")
    with pytest.raises(KitInputError, match="camera_idx and point_idx must be integer"):
        ba.jacobian_sparsity(5, 250, np.zeros(3), np.zeros(3))

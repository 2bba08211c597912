"""Sparse Levenberg-Marquardt with the Schur complement (course_lib.sfm.lm).

Analytic Jacobians against finite differences (both camera models), the Schur-complement step
against a dense solve of the normal equations, convergence on synthetic problems with a known
answer, the robust loss, input errors, the ``ba`` command, and the real Ladybug problem when the
course data is present.
"""

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from course_lib.__main__ import main as cli_main
from course_lib.data.bal import FLIP_YZ, BALProblem, load_bal, write_bal
from course_lib.data.synthetic import make_scene
from course_lib.paths import course_data
from course_lib.sfm import lm
from course_lib.alignment import align_similarity
from course_lib.validate import KitInputError

LADYBUG_COOKBOOK_COST = 1.3409e4  # SciPy cookbook's final cost on Ladybug 49-7776 (all observations)


def synthetic_bal(rng, n_cameras=6, n_points=120, noise_px=0.0, k=(-0.02, 0.004), f=530.0):
    """A BAL problem made from the kit's synthetic scene (known answer), and its true parameters."""
    scene = make_scene(rng, n_cameras=n_cameras, n_points=n_points, noise_px=0.0, outlier_fraction=0.0)
    pt, cam = np.nonzero(scene.visible)
    R_bal = FLIP_YZ @ scene.R_cw  # OpenCV axes -> BAL axes (y up, looking down -z)
    t_bal = scene.t_cw @ FLIP_YZ
    cams = np.hstack([Rotation.from_matrix(R_bal).as_rotvec(), t_bal, np.tile([f, *k], (n_cameras, 1))])
    obs = lm.BALCamera().project(cams, scene.X[pt], cam) + rng.normal(0.0, noise_px, (len(pt), 2))
    return BALProblem(cams, scene.X.copy(), cam.astype(np.int64), pt.astype(np.int64), obs, "synthetic")


def perturb(rng, cams, X, rot=0.01, trans=0.05, pts=0.05, intr=True):
    cams = cams.copy()
    cams[:, :3] += rng.normal(0, rot, cams[:, :3].shape)
    cams[:, 3:6] += rng.normal(0, trans, cams[:, 3:6].shape)
    if intr and cams.shape[1] == 9:
        cams[:, 6] *= 1 + rng.normal(0, 0.01, len(cams))
    return cams, X + rng.normal(0, pts, X.shape)


def cost(model, cams, X, p):
    r = lm.residuals(model, cams, X, p.cam_idx, p.pt_idx, p.obs)
    return 0.5 * float((r**2).sum())


# ---------------------------------------------------------------------------------------------
# Jacobians
# ---------------------------------------------------------------------------------------------


def numeric_jacobian(model, cams, X, cam_idx, pt_idx):
    obs = np.zeros((len(cam_idx), 2))
    x0 = np.concatenate([cams.ravel(), X.ravel()])
    nc = cams.size

    def fun(x):
        return lm.residuals(model, x[:nc].reshape(cams.shape), x[nc:].reshape(X.shape), cam_idx, pt_idx, obs).ravel()

    J = np.zeros((2 * len(cam_idx), x0.size))
    for c in range(x0.size):
        h = 1e-6 * max(1.0, abs(x0[c]))
        e = np.zeros_like(x0)
        e[c] = h
        J[:, c] = (fun(x0 + e) - fun(x0 - e)) / (2 * h)
    return J


def random_cameras(rng, model, n_cameras):
    rvec = rng.normal(0, 0.8, (n_cameras, 3))
    rvec[0] = [1e-7, -2e-8, 5e-8]  # a tiny rotation (Taylor branch of J_r)
    rvec[1] = [0.0, 0.0, 0.0]
    rvec[2] = np.array([0.2, -0.9, 0.4]) / np.linalg.norm([0.2, -0.9, 0.4]) * 3.0  # near pi
    t = rng.normal(0, 0.5, (n_cameras, 3))
    if isinstance(model, lm.BALCamera):
        t[:, 2] -= 12.0  # BAL: points in front have P.z < 0
        return np.hstack([rvec, t, np.tile([480.0, -0.03, 0.006], (n_cameras, 1)) + rng.normal(0, [5, 0.01, 0.002], (n_cameras, 3))])
    t[:, 2] += 12.0
    return np.hstack([rvec, t])


@pytest.mark.parametrize(
    "model",
    [lm.BALCamera(), lm.PinholeCamera(np.array([[520.0, 1.5, 320.0], [0.0, 515.0, 240.0], [0.0, 0.0, 1.0]]))],
    ids=["bal-9", "pinhole-6"],
)
def test_jacobian_matches_finite_differences(model, rng=np.random.default_rng(3)):
    M, N = 4, 7
    cams = random_cameras(rng, model, M)
    X = rng.normal(0, 1.0, (N, 3))
    cam_idx = np.repeat(np.arange(M), N)
    pt_idx = np.tile(np.arange(N), M)
    J = lm.jacobian(model, cams, X, cam_idx, pt_idx).toarray()
    Jn = numeric_jacobian(model, cams, X, cam_idx, pt_idx)
    assert J.shape == (2 * M * N, model.n_params * M + 3 * N)
    scale = np.abs(Jn).max(axis=0, keepdims=True) + 1e-9
    np.testing.assert_allclose(J / scale, Jn / scale, atol=2e-6)
    # the pattern: each observation touches its camera's n columns and its point's 3 columns only
    assert (J != 0).sum(axis=1).max() <= model.n_params + 3


# ---------------------------------------------------------------------------------------------
# The Schur-complement step
# ---------------------------------------------------------------------------------------------


def dense_lm_step(model, cams, X, cam_idx, pt_idx, obs, lam, free):
    J = lm.jacobian(model, cams, X, cam_idx, pt_idx).toarray()
    r = lm.residuals(model, cams, X, cam_idx, pt_idx, obs).ravel()
    H = J.T @ J
    g = J.T @ r
    D = np.clip(np.diag(H), 1e-6, 1e32)
    A = H + lam * np.diag(D)
    f = np.concatenate([free.ravel(), np.ones(X.size, bool)])
    delta = np.zeros(J.shape[1])
    delta[f] = np.linalg.solve(A[np.ix_(f, f)], -g[f])
    return delta[: cams.size].reshape(cams.shape), delta[cams.size :].reshape(X.shape)


@pytest.mark.parametrize("dense_limit", [4000, 0], ids=["dense-cholesky", "sparse-spsolve"])
@pytest.mark.parametrize("lam", [1e-4, 1.0])
def test_schur_step_equals_dense_normal_equations(dense_limit, lam):
    rng = np.random.default_rng(1)
    p = synthetic_bal(rng, n_cameras=4, n_points=25, noise_px=1.0)
    model = lm.BALCamera()
    cams, X = perturb(rng, p.camera_params, p.points)
    free = np.ones(cams.shape, bool)
    free[0] = False  # a fixed camera (gauge) and one fixed coordinate
    free[2, 4] = False
    dc_ref, dp_ref = dense_lm_step(model, cams, X, p.cam_idx, p.pt_idx, p.obs, lam, free)

    order = np.argsort(p.cam_idx, kind="stable")
    ci, pi, obs = p.cam_idx[order], p.pt_idx[order], p.obs[order]
    st = lm.BlockStructure(4, len(X), 9, ci, pi)
    proj, A, B = model.project_jacobian(cams, X[pi], ci)
    A = A * free[ci][:, None, :]
    ne = lm.normal_equations(st, proj - obs, A, B, np.ones(len(ci)))
    dc, dp, _, pred = lm.schur_solve(st, ne, lam, free, dense_limit=dense_limit)
    np.testing.assert_allclose(dc, dc_ref, rtol=1e-6, atol=1e-9 * np.abs(dc_ref).max())
    np.testing.assert_allclose(dp, dp_ref, rtol=1e-6, atol=1e-9 * np.abs(dp_ref).max())
    assert (dc[0] == 0).all() and dc[2, 4] == 0
    # predicted decrease of the model = cost - 0.5 |r + J delta|^2
    J = lm.jacobian(model, cams, X, p.cam_idx, p.pt_idx).toarray() * np.concatenate([free.ravel(), np.ones(X.size)])
    r = lm.residuals(model, cams, X, p.cam_idx, p.pt_idx, p.obs).ravel()
    lin = 0.5 * r @ r - 0.5 * np.sum((r + J @ np.concatenate([dc.ravel(), dp.ravel()])) ** 2)
    assert pred >= lin * (1 - 1e-6)  # plus the damping term lam * delta^T D delta / 2 >= 0


def test_reduced_camera_sparsity():
    rng = np.random.default_rng(2)
    p = synthetic_bal(rng, n_cameras=5, n_points=30)
    keep = ~((p.cam_idx == 0) & np.isin(p.pt_idx, np.flatnonzero(np.isin(np.arange(30), p.pt_idx[p.cam_idx == 4]))))
    ci, pi = p.cam_idx[keep], p.pt_idx[keep]  # cameras 0 and 4 share no point
    S = lm.reduced_camera_sparsity(5, 9, ci, pi).toarray()
    J = lm.jacobian(lm.BALCamera(), p.camera_params, p.points, ci, pi).toarray()
    Jc, Jp = J[:, :45] != 0, J[:, 45:] != 0
    ref = (Jc.T.astype(int) @ Jp.astype(int) @ Jp.T.astype(int) @ Jc.astype(int)) > 0
    assert ((S != 0) == ref).all()
    assert not S[:9, 36:].any()


# ---------------------------------------------------------------------------------------------
# Convergence
# ---------------------------------------------------------------------------------------------


def test_converges_to_the_known_answer_without_noise():
    """Noise-free BAL problem, perturbed start, free gauge: reprojections exact, points up to a similarity."""
    rng = np.random.default_rng(4)
    p = synthetic_bal(rng, n_cameras=6, n_points=150)
    cams, X = perturb(rng, p.camera_params, p.points)
    model = lm.BALCamera()
    res = lm.solve(model, cams, X, p.cam_idx, p.pt_idx, p.obs, ftol=1e-14, max_iterations=60)
    assert res.initial_cost > 1e3
    assert res.final_cost < 1e-12 * res.initial_cost
    assert res.final_cost == pytest.approx(cost(model, res.cameras, res.points, p), rel=1e-9, abs=1e-12)
    assert res.cost_history[0] == res.initial_cost and res.cost_history[-1] == res.final_cost
    assert np.all(np.diff(res.cost_history) < 0)
    s, R, t = align_similarity(res.points, p.points)
    aligned = s * res.points @ R.T + t
    assert np.abs(aligned - p.points).max() < 1e-5
    np.testing.assert_allclose(res.cameras[:, 6:], p.camera_params[:, 6:], rtol=1e-5, atol=1e-7)


def test_with_noise_reaches_the_least_squares_minimum():
    """With 0.5 px noise the minimum costs less than the truth, by about the degrees of freedom."""
    rng = np.random.default_rng(5)
    p = synthetic_bal(rng, n_cameras=6, n_points=150, noise_px=0.5)
    model = lm.BALCamera()
    c_true = cost(model, p.camera_params, p.points, p)
    cams, X = perturb(rng, p.camera_params, p.points)
    res = lm.solve(model, cams, X, p.cam_idx, p.pt_idx, p.obs, ftol=1e-12)
    assert res.success
    assert res.final_cost < c_true
    dof = 9 * 6 + 3 * 150 - 7
    expected = 0.25 * dof  # E[c_true - c_min] = sigma^2 / 2 * dof
    assert 0.5 * expected < c_true - res.final_cost < 1.6 * expected


def test_pinhole_with_fixed_gauge_recovers_the_truth():
    """The lesson's model (K fixed, 6 params): gauge fixed from the truth, so the answer is unique."""
    rng = np.random.default_rng(6)
    scene = make_scene(rng, n_cameras=5, n_points=200, noise_px=0.0, outlier_fraction=0.0)
    pt, cam = np.nonzero(scene.visible)
    model = lm.PinholeCamera(scene.K)
    truth = np.hstack([Rotation.from_matrix(scene.R_cw).as_rotvec(), scene.t_cw])
    fixed = np.zeros(truth.shape, bool)
    fixed[0] = True
    fixed[4, 3] = True  # one translation coordinate of another camera: the scale
    cams, X = perturb(rng, truth, scene.X, rot=0.01, trans=0.1, pts=0.1)
    cams[fixed] = truth[fixed]
    res = lm.solve(model, cams, X, cam, pt, scene.uv[pt, cam], fixed_cameras=fixed, ftol=1e-14)
    np.testing.assert_allclose(res.cameras, truth, atol=1e-7)
    two_views = scene.visible.sum(axis=1) >= 2  # a point seen once is free along its ray
    np.testing.assert_allclose(res.points[two_views], scene.X[two_views], atol=1e-6)
    assert (res.cameras[fixed] == truth[fixed]).all()


def test_huber_resists_outliers():
    rng = np.random.default_rng(8)
    p = synthetic_bal(rng, n_cameras=6, n_points=150, noise_px=0.5)
    bad = rng.random(p.n_obs) < 0.05
    obs = p.obs.copy()
    obs[bad] += rng.uniform(-60, 60, (int(bad.sum()), 2))
    model = lm.BALCamera()
    cams, X = perturb(rng, p.camera_params, p.points, intr=False)

    def point_error(res):
        s, R, t = align_similarity(res.points, p.points)
        return np.sqrt(np.mean(np.sum((s * res.points @ R.T + t - p.points) ** 2, axis=1)))

    plain = lm.solve(model, cams, X, p.cam_idx, p.pt_idx, obs, ftol=1e-10)
    huber = lm.solve(model, cams, X, p.cam_idx, p.pt_idx, obs, loss="huber", f_scale=2.0, ftol=1e-10)
    assert point_error(huber) < 0.5 * point_error(plain)
    # the reported costs are plain squared errors in both cases
    assert huber.final_cost == pytest.approx(cost(model, huber.cameras, huber.points, BALProblem(
        p.camera_params, p.points, p.cam_idx, p.pt_idx, obs)), rel=1e-9)


def test_unobserved_points_are_left_alone():
    rng = np.random.default_rng(9)
    p = synthetic_bal(rng, n_cameras=4, n_points=40, noise_px=0.3)
    X = np.vstack([p.points, [[np.nan, np.nan, np.nan], [1.0, 2.0, 3.0]]])
    res = lm.solve(lm.BALCamera(), p.camera_params, X, p.cam_idx, p.pt_idx, p.obs, max_iterations=3)
    assert np.isnan(res.points[-2]).all() and (res.points[-1] == [1.0, 2.0, 3.0]).all()


# ---------------------------------------------------------------------------------------------
# Inputs
# ---------------------------------------------------------------------------------------------


def test_bad_inputs_fail_clearly():
    rng = np.random.default_rng(10)
    p = synthetic_bal(rng, n_cameras=3, n_points=20)
    m = lm.BALCamera()
    args = (p.camera_params, p.points, p.cam_idx, p.pt_idx, p.obs)
    with pytest.raises(KitInputError, match=r"expected \(M, 9\)"):
        lm.solve(m, p.camera_params[:, :6], *args[1:])
    with pytest.raises(KitInputError, match=r"expected \(M, 6\)"):
        lm.solve(lm.PinholeCamera(np.eye(3)), *args)
    with pytest.raises(KitInputError, match="points as rows"):
        lm.solve(m, p.camera_params, p.points.T, *args[2:])
    with pytest.raises(KitInputError, match="outside"):
        lm.solve(m, p.camera_params, p.points, p.cam_idx + 5, p.pt_idx, p.obs)
    with pytest.raises(KitInputError, match="same length"):
        lm.solve(m, p.camera_params, p.points, p.cam_idx[:-1], p.pt_idx, p.obs)
    obs = p.obs.copy()
    obs[3] = np.nan
    with pytest.raises(KitInputError, match="NaN"):
        lm.solve(m, *args[:4], obs)
    with pytest.raises(KitInputError, match="fixed_cameras"):
        lm.solve(m, *args, fixed_cameras=np.zeros((3, 6), bool))
    with pytest.raises(KitInputError, match="loss"):
        lm.solve(m, *args, loss="tukey")


# ---------------------------------------------------------------------------------------------
# The command line
# ---------------------------------------------------------------------------------------------


def test_cli_ba_prints_and_writes_json(tmp_path, capsys):
    rng = np.random.default_rng(11)
    p = synthetic_bal(rng, n_cameras=5, n_points=80, noise_px=0.5)
    cams, X = perturb(rng, p.camera_params, p.points)
    path = write_bal(tmp_path / "small.txt.bz2", BALProblem(cams, X, p.cam_idx, p.pt_idx, p.obs))
    out = tmp_path / "out" / "ba.json"
    assert cli_main(["ba", str(path), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "initial_cost" in text and "final_cost" in text and "iterations" in text and "seconds" in text
    res = json.loads(out.read_text())
    assert {"initial_cost", "final_cost", "iterations", "seconds"} <= set(res)
    assert res["final_cost"] < 1e-2 * res["initial_cost"]
    assert cli_main(["ba", str(tmp_path / "missing.txt")]) == 2
    assert "not found" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# The real thing
# ---------------------------------------------------------------------------------------------


def test_ladybug_reaches_the_cookbook_cost():
    """BAL Ladybug 49-7776: at least as low as the SciPy cookbook's 1.3409e4 (speed: benchmarks/ba_speed.py)."""
    path = course_data("bal-ladybug")
    if path is None:
        pytest.skip("course data 'bal-ladybug' is not on this machine (set COURSE_DATA)")
    p = load_bal(path)
    res = lm.solve(lm.BALCamera(), p.camera_params, p.points, p.cam_idx, p.pt_idx, p.obs, ftol=1e-4)
    assert res.initial_cost == pytest.approx(8.5091e5, rel=1e-4)
    assert res.final_cost <= LADYBUG_COOKBOOK_COST
    assert res.iterations <= 20


def test_sparse_and_dense_reduced_systems_agree():
    rng = np.random.default_rng(12)
    p = synthetic_bal(rng, n_cameras=5, n_points=60, noise_px=0.5)
    cams, X = perturb(rng, p.camera_params, p.points)
    a = lm.solve(lm.BALCamera(), cams, X, p.cam_idx, p.pt_idx, p.obs, ftol=1e-10)
    b = lm.solve(lm.BALCamera(), cams, X, p.cam_idx, p.pt_idx, p.obs, ftol=1e-10, dense_limit=0)
    assert a.iterations == b.iterations
    assert b.final_cost == pytest.approx(a.final_cost, rel=1e-9)


# ---------------------------------------------------------------------------------------------
# Intrinsics shared by all cameras (SIMPLE_RADIAL)
# ---------------------------------------------------------------------------------------------


def _simple_radial_problem(rng, f_scale=1.0, k1=-0.08, noise_px=0.0):
    sc = make_scene(rng, n_cameras=8, n_points=300, noise_px=0.0, outlier_fraction=0.0)
    model = lm.SimpleRadialCamera(sc.K[:2, 2])
    cams = np.hstack([Rotation.from_matrix(sc.R_cw).as_rotvec(), sc.t_cw])
    pt, cam = np.nonzero(sc.visible)
    truth = np.array([sc.K[0, 0], k1])
    obs = model.project(cams, sc.X[pt], cam, truth) + rng.normal(0, noise_px, (len(pt), 2))
    return sc, model, cams, pt, cam, obs, truth


def test_simple_radial_jacobian_matches_finite_differences():
    sc, model, cams, pt, cam, _, truth = _simple_radial_problem(np.random.default_rng(5))
    sh = truth * [1.1, 0.5]
    _, A, B, C = model.project_jacobian(cams, sc.X[pt], cam, sh)
    eps = 1e-6
    for k in range(2):
        d = np.zeros(2)
        d[k] = eps
        num = (model.project(cams, sc.X[pt], cam, sh + d) - model.project(cams, sc.X[pt], cam, sh - d)) / (2 * eps)
        np.testing.assert_allclose(C[:, :, k], num, atol=1e-5 * np.abs(num).max())
    for k in range(6):
        d = np.zeros_like(cams)
        d[:, k] = eps
        num = (model.project(cams + d, sc.X[pt], cam, sh) - model.project(cams - d, sc.X[pt], cam, sh)) / (2 * eps)
        np.testing.assert_allclose(A[:, :, k], num, atol=1e-5 * np.abs(num).max())
    X = sc.X[pt].copy()
    for k in range(3):
        d = np.zeros_like(X)
        d[:, k] = eps
        num = (model.project(cams, X + d, cam, sh) - model.project(cams, X - d, cam, sh)) / (2 * eps)
        np.testing.assert_allclose(B[:, :, k], num, atol=1e-5 * np.abs(num).max())


@pytest.mark.parametrize("dense_limit", [4000, 0], ids=["dense-cholesky", "sparse-spsolve"])
def test_schur_step_with_shared_parameters_equals_the_dense_solve(dense_limit):
    rng = np.random.default_rng(6)
    sc, model, cams, pt, cam, obs, truth = _simple_radial_problem(rng, noise_px=0.5)
    sh = truth * [1.05, 0.0] + [0.0, -0.01]
    X = sc.X + rng.normal(0, 0.02, sc.X.shape)
    free = np.ones(cams.shape, bool)
    free[0] = False
    free[1, 3] = False
    lam = 1e-3
    order = np.argsort(cam, kind="stable")
    ci, pi, ob = cam[order], pt[order], obs[order]
    st = lm.BlockStructure(len(cams), len(X), 6, ci, pi)
    proj, A, B, C = model.project_jacobian(cams, X[pi], ci, sh)
    A = A * free[ci][:, None, :]
    ne = lm.normal_equations(st, proj - ob, A, B, np.ones(len(ci)), C)
    dc, dp, ds, _ = lm.schur_solve(st, ne, lam, free, dense_limit=dense_limit, free_shared=np.ones(2, bool))
    # the dense reference: J = [A | B | C] over all parameters, (J^T J + lam D) delta = -J^T r
    nc, npt = cams.size, X.size
    J = np.zeros((2 * len(ci), nc + npt + 2))
    for k, (c, p) in enumerate(zip(ci, pi)):
        J[2 * k:2 * k + 2, 6 * c:6 * c + 6] = A[k]
        J[2 * k:2 * k + 2, nc + 3 * p:nc + 3 * p + 3] = B[k]
        J[2 * k:2 * k + 2, nc + npt:] = C[k]
    f = np.concatenate([free.ravel(), np.ones(npt + 2, bool)])
    H = J.T @ J
    H = H + lam * np.diag(np.clip(np.diag(H), 1e-6, 1e32))
    g = J.T @ (proj - ob).ravel()
    delta = np.zeros(len(f))
    delta[f] = np.linalg.solve(H[np.ix_(f, f)], -g[f])
    np.testing.assert_allclose(dc.ravel(), delta[:nc], atol=1e-8 * np.abs(delta).max())
    np.testing.assert_allclose(ds, delta[nc + npt:], rtol=1e-6)
    np.testing.assert_allclose(dp.ravel(), delta[nc:nc + npt], atol=1e-8 * np.abs(delta).max())


def test_focal_length_and_k1_are_recovered():
    rng = np.random.default_rng(7)
    sc, model, cams, pt, cam, obs, truth = _simple_radial_problem(rng, noise_px=0.3)
    fixed = np.zeros(cams.shape, bool)
    fixed[0] = True
    fixed[1, 3] = True
    start = cams + rng.normal(0, 0.002, cams.shape) * ~fixed
    res = lm.solve(model, start, sc.X + rng.normal(0, 0.02, sc.X.shape), cam, pt, obs, fixed_cameras=fixed,
                   shared=truth * [1.1, 0.0], max_iterations=50)
    assert abs(res.shared[0] / truth[0] - 1) < 0.01 and abs(res.shared[1] - truth[1]) < 0.01
    assert np.sqrt(2 * res.final_cost / len(pt)) < 0.5
    held = lm.solve(model, start, sc.X, cam, pt, obs, fixed_cameras=fixed, shared=truth * [1.1, 0.0],
                    fixed_shared=np.array([True, False]), max_iterations=5)
    assert held.shared[0] == truth[0] * 1.1
    with pytest.raises(KitInputError, match="shared parameters"):
        lm.solve(model, start, sc.X, cam, pt, obs, max_iterations=1)

"""Tests of course_lib.sfm.triangulation on the synthetic scene (ground truth), OpenCV and pycolmap."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from course_lib.conventions import compose_poses, invert_pose, projection_matrix, skew, world_to_camera
from course_lib.data.synthetic import make_scene
from course_lib.sfm.triangulation import (
    choose_pose,
    reprojection_errors,
    triangulate_linear,
    triangulate_nonlinear,
)
from course_lib.validate import KitInputError


def relative_scene(noise_px=0.0, n_points=300, seed=0, outlier_fraction=0.0):
    """The synthetic scene re-expressed with camera 0 at R = I, t = 0 (the two-view frame)."""
    sc = make_scene(np.random.default_rng(seed), n_cameras=3, n_points=n_points, noise_px=noise_px,
                    outlier_fraction=outlier_fraction, dropout=0.0)
    R0w, t0w = sc.R_cw[0], sc.t_cw[0]
    R_w0, t_w0 = invert_pose(R0w, t0w)
    R_cw = np.stack([compose_poses(R, t, R_w0, t_w0)[0] for R, t in zip(sc.R_cw, sc.t_cw)])
    t_cw = np.stack([compose_poses(R, t, R_w0, t_w0)[1] for R, t in zip(sc.R_cw, sc.t_cw)])
    X = world_to_camera(R0w, t0w, sc.X)
    return sc, R_cw, t_cw, X


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


def test_choose_pose_with_h1_candidates_if_available():
    essential = pytest.importorskip("course_lib.sfm.essential", reason="H1's essential.py not there yet")
    sc, R, t, X = relative_scene(noise_px=0.3)
    E = skew(t[1]) @ R[1]
    Rc, Cc = essential.pose_candidates(E / np.linalg.norm(E))
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
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap is optional (not installed in CI)")
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
    from course_lib.paths import course_data

    folder = course_data("wpi")
    if folder is None:
        pytest.skip("the course data (WPI) is not on this machine")
    p3 = pytest.importorskip("course_lib.data.p3", reason="H4's P3 loader not there yet")
    data = p3.read_p3(folder)
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


# ------------------------------------------------------------------------------------------------
# The check cells of notebook 03: the reference passes, typical mistakes are named.
# ------------------------------------------------------------------------------------------------

from course_lib.grading import triangulation as gtri  # noqa: E402
from course_lib.grading.core import RESULTS  # noqa: E402
from course_lib.sfm import triangulation as tri  # noqa: E402


def run_check(check, fn, capsys):
    check(fn)
    text = capsys.readouterr().out
    return text, RESULTS[text.splitlines()[0]]


@pytest.mark.parametrize("check, fn", [
    (gtri.check_triangulate_linear, tri.triangulate_linear),
    (gtri.check_choose_pose, tri.choose_pose),
    (gtri.check_triangulate_nonlinear, tri.triangulate_nonlinear),
])
def test_checks_pass_with_the_reference(check, fn, capsys):
    text, result = run_check(check, fn, capsys)
    assert result.ok, text
    assert "✘" not in text


def textbook_triangulate_linear(P1, P2, x1, x2):
    """The DLT as a student writes it: a loop over points, no row scaling."""
    X = []
    for (u1, v1), (u2, v2) in zip(x1, x2):
        A = np.array([u1 * P1[2] - P1[0], v1 * P1[2] - P1[1], u2 * P2[2] - P2[0], v2 * P2[2] - P2[1]])
        Xh = np.linalg.svd(A)[2][-1]
        X.append(Xh[:3] / Xh[3])
    return np.array(X)


def textbook_triangulate_nonlinear(K, R_cws, t_cws, uv, X0):
    """One least_squares per point, default settings."""
    from scipy.optimize import least_squares

    from course_lib.conventions import project

    X = X0.copy()
    for j in range(len(X0)):
        views = [i for i in range(len(R_cws)) if np.isfinite(uv[j, i]).all()]

        def res(p, j=j, views=views):
            return np.concatenate([project(K, R_cws[i], t_cws[i], p[None])[0] - uv[j, i] for i in views])

        X[j] = least_squares(res, X0[j]).x
    return X


@pytest.mark.parametrize("check, fn", [
    (gtri.check_triangulate_linear, textbook_triangulate_linear),
    (gtri.check_triangulate_nonlinear, textbook_triangulate_nonlinear),
])
def test_checks_pass_a_textbook_implementation(check, fn, capsys):
    text, result = run_check(check, fn, capsys)
    assert result.ok, text


def _dlt_homogeneous(P1, P2, x1, x2):
    A = np.stack([x1[:, :1] * P1[2] - P1[0], x1[:, 1:] * P1[2] - P1[1],
                  x2[:, :1] * P2[2] - P2[0], x2[:, 1:] * P2[2] - P2[1]], axis=1)
    return np.linalg.svd(A)[2][:, -1]


def _choose_with(test):
    """choose_pose with another cheirality test(R_k, C_k, X) -> mask."""
    def choose(R, C, K, x1, x2):
        P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
        best, counts = None, []
        for k in range(4):
            t = -R[k] @ C[k]
            X = tri.triangulate_linear(P1, K @ np.hstack([R[k], t[:, None]]), x1, x2)
            m = test(R[k], C[k], X)
            counts.append(m.sum())
            if best is None or m.sum() > best[0]:
                best = (m.sum(), R[k], t, X, m)
        return tri.PoseChoice(best[1], best[2], best[3], best[4], np.array(counts))
    return choose


def _choose_returning(transform):
    def choose(R, C, K, x1, x2):
        ch = tri.choose_pose(R, C, K, x1, x2)
        ch.R_cw, ch.t_cw = transform(ch.R_cw, ch.t_cw, R[ch.index], C[ch.index])
        return ch
    return choose


@pytest.mark.parametrize("check, fn, words", [
    (gtri.check_triangulate_linear, lambda *a: _dlt_homogeneous(*a)[:, :3], "divide by the homogeneous coordinate"),
    (gtri.check_triangulate_linear, lambda *a: _dlt_homogeneous(*a), "homogeneous points"),
    (gtri.check_triangulate_linear, lambda *a: tri.triangulate_linear(*a).T, "transpose"),
    (gtri.check_triangulate_linear, lambda P1, P2, x1, x2: tri.triangulate_linear(P1, P2, x1[:, ::-1], x2[:, ::-1]),
     "u goes with the first row"),
    (gtri.check_choose_pose, _choose_with(lambda R, C, X: (X[:, 2] < 0) & ((X - C) @ R[2] < 0)), "points behind"),
    (gtri.check_choose_pose, _choose_with(lambda R, C, X: (X - C) @ R[2] > 0), "checks only camera 2"),
    (gtri.check_choose_pose, _choose_with(lambda R, C, X: X[:, 2] > 0), "checks only camera 1"),
    (gtri.check_choose_pose, _choose_with(lambda R, C, X: (X[:, 2] > 0) & (X @ R[2] > 0)), "forgets the centre"),
    (gtri.check_choose_pose, _choose_with(lambda R, C, X: (X[:, 2] > 0) & ((X - C) @ R[:, 2] > 0)), "third ROW"),
    (gtri.check_choose_pose, _choose_returning(lambda R, t, Rk, Ck: (R.T, t)), "R_wc"),
    (gtri.check_choose_pose, _choose_returning(lambda R, t, Rk, Ck: (R, Ck)), "camera centre C"),
    (gtri.check_choose_pose, _choose_returning(lambda R, t, Rk, Ck: (R, -Ck)), "C vs t"),
    (gtri.check_triangulate_nonlinear, lambda K, R, t, uv, X0: X0 + 0.05, "increased the reprojection error"),
    (gtri.check_triangulate_nonlinear, lambda K, R, t, uv, X0: X0.copy(), "did not move"),
    (gtri.check_triangulate_nonlinear, lambda K, R, t, uv, X0: tri.triangulate_nonlinear(K, R[:2], t[:2], uv[:, :2], X0),
     "only the first two views"),
    (gtri.check_triangulate_nonlinear, lambda K, R, t, uv, X0: 0.5 * (X0 + tri.triangulate_nonlinear(K, R, t, uv, X0)),
     "run the solver to convergence"),
    (gtri.check_triangulate_nonlinear, lambda K, R, t, uv, X0: np.full_like(X0, np.nan), "NaN"),
])
def test_checks_name_the_mistake(check, fn, words, capsys):
    text, result = run_check(check, fn, capsys)
    assert not result.ok
    assert words in text, text


def test_single_point_message_is_not_self_contradictory(capsys):
    """A (1, 3) answer with the wrong value is told so, never 'expected shape (1, 3) ..., got shape (1, 3)'."""
    def wrong_for_one_point(P1, P2, x1, x2):
        X = tri.triangulate_linear(P1, P2, x1, x2)
        return X + 1.0 if len(X) == 1 else X

    text, result = run_check(gtri.check_triangulate_linear, wrong_for_one_point, capsys)
    assert not result.ok
    assert "the right shape (1, 3) but not the true point" in text, text
    assert "expected shape (1, 3)" not in text, text


def test_check_reports_not_implemented(capsys):
    def todo(*args):
        raise NotImplementedError

    text, result = run_check(gtri.check_triangulate_linear, todo, capsys)
    assert "not implemented yet" in text and not result.ok


def test_fixtures_are_current():
    from course_lib.grading.core import build_fixtures

    diffs = build_fixtures(["triangulation", "triangulation_step"], write=False)
    assert not any(diffs.values()), diffs


def test_checks_and_step_input_run_without_the_reference_solutions():
    """A student release has no course_lib.sfm solutions: checks and step input read fixtures only."""
    import subprocess
    import sys

    code = '''
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.startswith("course_lib.sfm.") and name != "course_lib.sfm.evaluate":
            raise ModuleNotFoundError(name, name=name)
sys.meta_path.insert(0, Block())
from course_lib.grading import triangulation as g
def todo(*a, **k):
    raise NotImplementedError
for name in dir(g):
    if name.startswith("check_"):
        getattr(g, name)(todo)
print(sorted(g.step_input()))
'''
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "not implemented yet" in out.stdout and "Traceback" not in out.stdout
    assert "'K'" in out.stdout


def test_nonlinear_point_error_matches_first_order_prediction():
    """RMSE to the true points equals the one predicted from the noise: sigma^2 (J^T J)^-1 per point."""
    sigma = 1.0
    sc, R, t, X = relative_scene(noise_px=sigma, n_points=1500, seed=3)
    uv = sc.uv
    P1, P2 = projection_matrix(sc.K, R[0], t[0]), projection_matrix(sc.K, R[1], t[1])
    Xn = triangulate_nonlinear(sc.K, R, t, uv, triangulate_linear(P1, P2, uv[:, 0], uv[:, 1]))
    predicted = []
    fx, fy = sc.K[0, 0], sc.K[1, 1]
    for j in range(len(X)):
        J = []
        for i in range(3):
            Xc = R[i] @ X[j] + t[i]
            d = np.array([[fx / Xc[2], 0, -fx * Xc[0] / Xc[2] ** 2], [0, fy / Xc[2], -fy * Xc[1] / Xc[2] ** 2]])
            J.append(d @ R[i])
        J = np.vstack(J)
        predicted.append(np.trace(np.linalg.inv(J.T @ J)) * sigma**2)
    rmse_pred = np.sqrt(np.mean(predicted))
    rmse = np.sqrt(((Xn - X) ** 2).sum(1).mean())
    assert rmse == pytest.approx(rmse_pred, rel=0.1)

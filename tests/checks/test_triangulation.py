"""Tests of notebook 03's checks (course_lib.checks.triangulation) and its step input: the reference passes, classic mistakes are named."""

from __future__ import annotations

import numpy as np
import pytest

from course_lib.conventions import projection_matrix
from course_lib.sfm.triangulation import triangulate_linear, triangulate_nonlinear
from tests.scenes import relative_scene
from course_lib.checks import triangulation as gtri
from course_lib.checks.core import RESULTS
from course_lib.sfm import triangulation as tri


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
    (gtri.check_triangulate_linear, lambda *a: _dlt_homogeneous(*a)[:, :3], "without dividing by the homogeneous"),
    (gtri.check_triangulate_linear, lambda *a: _dlt_homogeneous(*a), "homogeneous points"),
    (gtri.check_triangulate_linear, lambda *a: tri.triangulate_linear(*a).T, "transpose"),
    (gtri.check_triangulate_linear, lambda P1, P2, x1, x2: tri.triangulate_linear(P1, P2, x1[:, ::-1], x2[:, ::-1]),
     "median reprojection error"),  # the reference's DLT with u and v swapped: not the stored mistake exactly
    (gtri.check_choose_pose, _choose_with(lambda R, C, X: (X[:, 2] < 0) & ((X - C) @ R[2] < 0)), "points behind"),
    (gtri.check_choose_pose, _choose_with(lambda R, C, X: (X - C) @ R[2] > 0), "checks only camera 2"),
    (gtri.check_choose_pose, _choose_with(lambda R, C, X: X[:, 2] > 0), "checks only camera 1"),
    (gtri.check_choose_pose, _choose_with(lambda R, C, X: (X[:, 2] > 0) & (X @ R[2] > 0)), "forgets the centre"),
    (gtri.check_choose_pose, _choose_with(lambda R, C, X: (X[:, 2] > 0) & ((X - C) @ R[:, 2] > 0)), "third ROW"),
    (gtri.check_choose_pose, _choose_returning(lambda R, t, Rk, Ck: (R.T, t)), "R_wc"),
    (gtri.check_choose_pose, _choose_returning(lambda R, t, Rk, Ck: (R, Ck)), "camera centre C"),
    (gtri.check_choose_pose, _choose_returning(lambda R, t, Rk, Ck: (R, -Ck)), "C vs t"),
    (gtri.check_triangulate_nonlinear, lambda K, R, t, uv, X0: X0 + 0.05, "increased the RMS reprojection error"),
    (gtri.check_triangulate_nonlinear, lambda K, R, t, uv, X0: X0.copy(), "did not move"),
    (gtri.check_triangulate_nonlinear, lambda K, R, t, uv, X0: tri.triangulate_nonlinear(K, R[:2], t[:2], uv[:, :2], X0),
     "only the first two views"),
    (gtri.check_triangulate_nonlinear, lambda K, R, t, uv, X0: 0.5 * (X0 + tri.triangulate_nonlinear(K, R, t, uv, X0)),
     "to convergence"),
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

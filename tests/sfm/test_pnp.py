"""Tests of course_lib.sfm.pnp on the synthetic scene (ground truth), OpenCV and pycolmap."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from course_lib.conventions import rotation_angle_deg, skew
from course_lib.data.synthetic import make_scene
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
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap is optional (not installed in CI)")
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
    from course_lib.paths import course_data

    folder = course_data("wpi")
    if folder is None:
        pytest.skip("the course data (WPI) is not on this machine")
    p3 = pytest.importorskip("course_lib.data.p3", reason="H4's P3 loader not there yet")
    data = p3.read_p3(folder)
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


# ------------------------------------------------------------------------------------------------
# The check cells of notebook 04: the reference passes, typical mistakes are named.
# ------------------------------------------------------------------------------------------------

from course_lib.conventions import to_homogeneous  # noqa: E402
from course_lib.grading import pnp as gpnp  # noqa: E402
from course_lib.grading.core import RESULTS  # noqa: E402
from course_lib.sfm import pnp as ref  # noqa: E402


def run_check(check, fn, capsys):
    check(fn)
    text = capsys.readouterr().out
    return text, RESULTS[text.splitlines()[0]]


@pytest.mark.parametrize("check, fn", [
    (gpnp.check_pnp_linear, ref.pnp_linear),
    (gpnp.check_pnp_ransac, ref.pnp_ransac),
    (gpnp.check_pnp_nonlinear, ref.pnp_nonlinear),
])
def test_checks_pass_with_the_reference(check, fn, capsys):
    text, result = run_check(check, fn, capsys)
    assert result.ok, text
    assert "✘" not in text


def _raw_P(X, x, K, pixels=False):
    """The DLT's P (no conditioning, no sign fix): what a student computes first."""
    xn = x if pixels else (to_homogeneous(x) @ np.linalg.inv(K).T)[:, :2]
    Xh = to_homogeneous(X)
    A = np.zeros((2 * len(X), 12))
    A[0::2, 0:4], A[0::2, 8:12] = -Xh, xn[:, :1] * Xh
    A[1::2, 4:8], A[1::2, 8:12] = -Xh, xn[:, 1:] * Xh
    return np.linalg.svd(A, full_matrices=False)[2][-1].reshape(3, 4)


def _no_orthogonalization(X, x, K):
    P = _raw_P(X, x, K)
    P = P if np.linalg.det(P[:, :3]) > 0 else -P
    s = np.cbrt(np.linalg.det(P[:, :3]))
    return P[:, :3] / s, P[:, 3] / s


def _no_sign_fix(X, x, K):
    P = _raw_P(X, x, K)
    P = -P if np.linalg.det(P[:, :3]) > 0 else P  # the unlucky sign
    U, S, Vt = np.linalg.svd(P[:, :3])
    return U @ Vt, P[:, 3] / S.mean()


def _pixels(X, x, K):
    P = _raw_P(X, x, K, pixels=True)
    P = P if np.linalg.det(P[:, :3]) > 0 else -P
    U, S, Vt = np.linalg.svd(P[:, :3])
    return U @ Vt, P[:, 3] / S.mean()


def _with(transform):
    def fn(X, x, K):
        R, t = ref.pnp_linear(X, x, K)
        return transform(R, t)
    return fn


def _nl_gd(X, x, K, R, t):
    R1, t1 = ref.pnp_nonlinear(X, x, K, R, t)
    return R1, t + 3.0 * (t1 - t)  # an overshooting step


def _nl_halfway(X, x, K, R, t):
    """Stops halfway between the start and the optimum (on the rotation manifold)."""
    from scipy.spatial.transform import Rotation

    R1, t1 = ref.pnp_nonlinear(X, x, K, R, t)
    w = Rotation.from_matrix(R1 @ R.T).as_rotvec()
    return Rotation.from_rotvec(0.5 * w).as_matrix() @ R, 0.5 * (t + t1)


def _nl_nine(X, x, K, R, t):
    R1, t1 = ref.pnp_nonlinear(X, x, K, R, t)
    return R1 * 1.01, t1


def textbook_pnp_linear(X, x, K):
    """The DLT as the notebook teaches it, written plainly: no conditioning of the 3-D points."""
    P = _raw_P(X, x, K)
    P = P if np.linalg.det(P[:, :3]) > 0 else -P
    U, S, Vt = np.linalg.svd(P[:, :3])
    R = U @ Vt
    xn = to_homogeneous(x) @ np.linalg.inv(K).T
    A = np.concatenate([skew(v) for v in xn])
    b = -np.concatenate([skew(v) @ (R @ Xj) for v, Xj in zip(xn, X)])
    return R, np.linalg.lstsq(A, b, rcond=None)[0]


def sigma_scaled_pnp_linear(X, x, K):
    """The DLT with t = P[:, 3] / sigma_1 (no re-estimation of t)."""
    P = _raw_P(X, x, K)
    P = P if np.linalg.det(P[:, :3]) > 0 else -P
    U, S, Vt = np.linalg.svd(P[:, :3])
    return U @ Vt, P[:, 3] / S[0]


def textbook_pnp_ransac(X, x, K, rng, threshold_px=2.0, confidence=0.999, max_iters=1000):
    """Plain RANSAC: best 6-point sample by inlier count, adaptive stop, one refit on its inliers."""
    n, best, need, it = len(X), None, max_iters, 0
    while it < min(need, max_iters):
        it += 1
        s = rng.choice(n, 6, replace=False)
        R, t = textbook_pnp_linear(X[s], x[s], K)
        inl = ref.pnp_reprojection_errors(X, x, K, R, t) < threshold_px
        if best is None or inl.sum() > best.sum():
            best = inl
            w = inl.mean()
            need = int(np.ceil(np.log(1 - confidence) / np.log(1 - w**6))) if 0 < w < 1 else max_iters
    R, t = textbook_pnp_linear(X[best], x[best], K)
    return ref.PnPResult(R, t, ref.pnp_reprojection_errors(X, x, K, R, t) < threshold_px, it)


def textbook_pnp_nonlinear(X, x, K, R, t):
    """Quaternion parametrization, default least_squares settings."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    from course_lib.conventions import project

    def res(p):
        return (project(K, Rotation.from_quat(p[:4]).as_matrix(), p[4:], X) - x).ravel()

    p = least_squares(res, np.r_[Rotation.from_matrix(R).as_quat(), t]).x
    return Rotation.from_quat(p[:4]).as_matrix(), p[4:]


@pytest.mark.parametrize("check, fn", [
    (gpnp.check_pnp_linear, textbook_pnp_linear),
    (gpnp.check_pnp_linear, sigma_scaled_pnp_linear),
    (gpnp.check_pnp_ransac, textbook_pnp_ransac),
    (gpnp.check_pnp_nonlinear, textbook_pnp_nonlinear),
])
def test_checks_pass_a_textbook_implementation(check, fn, capsys):
    text, result = run_check(check, fn, capsys)
    assert result.ok, text


@pytest.mark.parametrize("check, fn, words", [
    (gpnp.check_pnp_linear, _no_orthogonalization, "forgot to orthogonalize"),
    (gpnp.check_pnp_linear, _no_sign_fix, "det R = -1"),
    (gpnp.check_pnp_linear, _with(lambda R, t: (-R, t)), "det R = -1"),
    (gpnp.check_pnp_linear, _with(lambda R, t: (R.T, t)), "R_wc"),
    (gpnp.check_pnp_linear, _with(lambda R, t: (R, -R.T @ t)), "C vs t"),
    (gpnp.check_pnp_linear, _with(lambda R, t: (R, -t)), "behind the camera"),
    (gpnp.check_pnp_linear, _with(lambda R, t: (R, 2.5 * t)), "wrong scale"),
    (gpnp.check_pnp_linear, _pixels, "pixel coordinates"),
    (gpnp.check_pnp_ransac, lambda X, x, K, rng: ref.PnPResult(*(lambda r: (r.R_cw, r.t_cw, ~r.inliers, r.n_iters))(
        ref.pnp_ransac(X, x, K, rng))), "inverted"),
    (gpnp.check_pnp_ransac, lambda X, x, K, rng: (lambda r: (r.R_cw, r.t_cw, np.flatnonzero(r.inliers), r.n_iters))(
        ref.pnp_ransac(X, x, K, rng)), "not the inlier indices"),
    (gpnp.check_pnp_ransac, lambda X, x, K, rng: (lambda r: (r.R_cw.T, r.t_cw, r.inliers, r.n_iters))(
        ref.pnp_ransac(X, x, K, rng)), "R_wc"),
    (gpnp.check_pnp_nonlinear, _nl_gd, "increased the reprojection error"),
    (gpnp.check_pnp_nonlinear, lambda X, x, K, R, t: (R.copy(), t.copy()), "did not move"),
    (gpnp.check_pnp_nonlinear, _nl_nine, "not a rotation"),
    (gpnp.check_pnp_nonlinear, _nl_halfway, "run the solver to convergence"),
])
def test_checks_name_the_mistake(check, fn, words, capsys):
    text, result = run_check(check, fn, capsys)
    assert not result.ok
    assert words in text, text


def test_fixtures_are_current():
    from course_lib.grading.core import build_fixtures

    diffs = build_fixtures(["pnp", "pnp_step"], write=False)
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
from course_lib.grading import pnp as g
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

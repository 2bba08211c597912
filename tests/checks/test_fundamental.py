"""Tests of notebook 01's checks (course_lib.checks.fundamental): the reference passes, classic mistakes are named."""

from __future__ import annotations

import numpy as np
import pytest

from course_lib.conventions import to_homogeneous
from course_lib.sfm.fundamental import RansacResult
from course_lib.checks import core as grading_core
from course_lib.checks import fundamental as checks
from course_lib import starting_points
from course_lib.sfm import fundamental as reference


def verdict(check, fn, capsys):
    """Run a check, return (all passed, the printed text)."""
    check(fn)
    out = capsys.readouterr().out
    return grading_core.RESULTS[out.splitlines()[0]].ok, out


def test_checks_pass_the_reference(capsys):
    for check, fn in [
        (checks.check_normalize_points, reference.normalize_points),
        (checks.check_eight_point, reference.eight_point),
        (checks.check_sampson_distance, reference.sampson_distance),
        (checks.check_ransac_fundamental, reference.ransac_fundamental),
    ]:
        ok, out = verdict(check, fn, capsys)
        assert ok, out
        assert "✘" not in out


def _norm_variant(center=True, target=np.sqrt(2), rms=False, per_axis=False, inverse=False):
    def fn(x):
        c = x.mean(0) if center else np.zeros(2)
        if per_axis:
            s = target / np.abs(x - c).mean(0)
        else:
            d = np.linalg.norm(x - c, axis=1)
            s = target / (np.sqrt((d**2).mean()) if rms else d.mean())
            s = np.array([s, s])
        T = np.array([[s[0], 0, -s[0] * c[0]], [0, s[1], -s[1] * c[1]], [0, 0, 1.0]])
        return (x - c) * s, (np.linalg.inv(T) if inverse else T)

    return fn


@pytest.mark.parametrize(
    "fn, phrase",
    [
        (_norm_variant(center=False), "subtract the mean"),
        (_norm_variant(target=1.0), "the mean distance to the centroid is 1,"),
        (_norm_variant(rms=True), "RMS distance"),
        (_norm_variant(per_axis=True), "one scale s for both axes"),
        (_norm_variant(inverse=True), "you returned the inverse of T"),
        (lambda x: (_ for _ in ()).throw(NotImplementedError), "not implemented yet"),
    ],
)
def test_check_normalize_points_names_mistakes(fn, phrase, capsys):
    ok, out = verdict(checks.check_normalize_points, fn, capsys)
    assert not ok and phrase in out, out


def _eight_variant(normalize=True, transpose=False, rank2=True, unit=True, denormalize=True):
    def fn(x1, x2):
        if normalize:
            a, T1 = reference.normalize_points(x1)
            b, T2 = reference.normalize_points(x2)
        else:
            a, b, T1, T2 = x1, x2, np.eye(3), np.eye(3)
        if transpose:
            a, b = b, a
        A = np.stack([b[:, 0] * a[:, 0], b[:, 0] * a[:, 1], b[:, 0], b[:, 1] * a[:, 0], b[:, 1] * a[:, 1], b[:, 1],
                      a[:, 0], a[:, 1], np.ones(len(a))], axis=1)
        F = np.linalg.svd(A)[2][-1].reshape(3, 3)
        if rank2:
            U, s, Vt = np.linalg.svd(F)
            F = U @ np.diag([s[0], s[1], 0]) @ Vt
        if denormalize:
            F = (T1.T @ F @ T2) if transpose else (T2.T @ F @ T1)
        return F / np.linalg.norm(F) * (1.0 if unit else 7.0)

    return fn


@pytest.mark.parametrize(
    "fn, phrase",
    [
        (_eight_variant(normalize=False), "on raw pixels (not normalized)"),
        (_eight_variant(transpose=True), "your F is transposed"),
        (_eight_variant(rank2=False), "rank 3"),
        (_eight_variant(denormalize=False), "still in normalized coordinates"),
    ],
)
def test_check_eight_point_names_mistakes(fn, phrase, capsys):
    ok, out = verdict(checks.check_eight_point, fn, capsys)
    assert not ok and phrase in out, out


def test_check_eight_point_accepts_any_scale_and_sign(capsys):
    """F is defined up to scale and sign: 7 F and -F pass every check (one rule for equivalences)."""
    for fn in (_eight_variant(unit=False), lambda x1, x2: -reference.eight_point(x1, x2)):
        ok, out = verdict(checks.check_eight_point, fn, capsys)
        assert ok, out


def _sampson_parts(F, x1, x2):
    x1h, x2h = to_homogeneous(x1), to_homogeneous(x2)
    l2, l1 = x1h @ F.T, x2h @ F
    e = np.sum(x2h * l2, axis=1)
    return e, l1, l2


@pytest.mark.parametrize(
    "fn, phrase",
    [
        (lambda F, x1, x2: reference.sampson_distance(F, x1, x2) ** 2, "square root"),
        (lambda F, x1, x2: np.abs(_sampson_parts(F, x1, x2)[0]), "algebraic error"),
        (lambda F, x1, x2: np.abs(_sampson_parts(F, x1, x2)[0]) / np.hypot(*_sampson_parts(F, x1, x2)[2][:, :2].T),
         "its epipolar line F x1 only"),
        (lambda F, x1, x2: reference.sampson_distance(F.T, x1, x2), "you used the transposed F"),
    ],
)
def test_check_sampson_distance_names_mistakes(fn, phrase, capsys):
    ok, out = verdict(checks.check_sampson_distance, fn, capsys)
    assert not ok and phrase in out, out


def _ransac_algebraic(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    """The classic mistake: the threshold is compared with |x2ᵀ F x1|."""
    best = None
    for _ in range(200):
        s = rng.choice(len(x1), 8, replace=False)
        F = reference.eight_point(x1[s], x2[s])
        e = np.abs(np.sum(to_homogeneous(x2) * (to_homogeneous(x1) @ F.T), axis=1))
        inl = e < threshold_px
        if best is None or inl.sum() > best[1].sum():
            best = (F, inl)
    return RansacResult(best[0], best[1], 200)


def _ransac_fixed_iters(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    """No adaptive stop: always max_iters samples."""
    res = reference.ransac_fundamental(x1, x2, rng, threshold_px, confidence=1 - 1e-15, max_iters=max_iters)
    return RansacResult(res.F, res.inliers, max_iters)


_calls = iter(range(10**6))


def _ransac_global_rng(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    """Ignores the rng argument: each call draws from another stream (like np.random without a seed),
    made deterministic here so that the test is."""
    return reference.ransac_fundamental(x1, x2, np.random.default_rng(1000 + next(_calls)), threshold_px, confidence,
                                        max_iters)


def _ransac_no_refit(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):
    """Keeps the F of the best minimal sample (no refit on the inliers), with a strict threshold."""
    best = None
    for _ in range(300):
        s = rng.choice(len(x1), 8, replace=False)
        F = reference.eight_point(x1[s], x2[s])
        inl = reference.sampson_distance(F, x1, x2) ** 2 < threshold_px
        if best is None or inl.sum() > best[1].sum():
            best = (F, inl)
    return RansacResult(best[0], best[1], 300)


@pytest.mark.parametrize(
    "fn, phrase",
    [
        (_ransac_algebraic, "algebraic error"),
        (_ransac_fixed_iters, "log(1 - confidence)"),
        (_ransac_global_rng, "the same rng seed gave different results"),
        (_ransac_no_refit, "refit"),
    ],
)
def test_check_ransac_names_mistakes(fn, phrase, capsys):
    ok, out = verdict(checks.check_ransac_fundamental, fn, capsys)
    assert not ok and phrase in out, out


def test_two_view_step_is_the_reference_result():
    step = starting_points.two_view_step()
    res = reference.ransac_fundamental(step.x1, step.x2, np.random.default_rng(starting_points.STEP_SEED),
                                       threshold_px=starting_points.STEP_THRESHOLD_PX)
    np.testing.assert_allclose(step.F, res.F, atol=1e-9)
    np.testing.assert_array_equal(step.inliers, res.inliers)

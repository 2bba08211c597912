"""Tests of notebook 02's checks (course_lib.checks.essential): the reference passes, classic mistakes are named."""

from __future__ import annotations

import numpy as np
import pytest

from course_lib.sfm.essential import W
from course_lib.checks import core as grading_core
from course_lib.checks import essential as checks
from course_lib.sfm import essential as reference


def verdict(check, fn, capsys):
    check(fn)
    out = capsys.readouterr().out
    return grading_core.RESULTS[out.splitlines()[0]].ok, out


def test_checks_pass_the_reference(capsys):
    for check, fn in [
        (checks.check_essential_from_fundamental, reference.essential_from_fundamental),
        (checks.check_pose_candidates, reference.pose_candidates),
    ]:
        ok, out = verdict(check, fn, capsys)
        assert ok and "✘" not in out, out


def _correct(E):
    U, _, Vt = np.linalg.svd(E)
    return U @ np.diag([1.0, 1.0, 0.0]) @ Vt


@pytest.mark.parametrize(
    "fn, phrase",
    [
        (lambda F, K: K.T @ F @ K, "you did not correct the singular values"),
        (lambda F, K: _correct(K @ F @ K.T), "K F Kᵀ"),
        (lambda F, K: _correct(np.linalg.inv(K).T @ F @ np.linalg.inv(K)), "turns an E into an F"),
    ],
)
def test_check_essential_names_mistakes(fn, phrase, capsys):
    ok, out = verdict(checks.check_essential_from_fundamental, fn, capsys)
    assert not ok and phrase in out, out


def _candidates_variant(flip_det=True, unit=True, center_is_t=False, one_rotation=False):
    def fn(E):
        U, _, Vt = np.linalg.svd(E)
        Rs, Cs = [], []
        rots = (U @ W @ Vt, U @ W @ Vt) if one_rotation else (U @ W @ Vt, U @ W.T @ Vt)
        for R0 in rots:
            for t in (U[:, 2], -U[:, 2]):
                R, C = R0, (t if center_is_t else -R0.T @ t)
                if flip_det and np.linalg.det(R) < 0:
                    R, C = -R, -C
                Rs.append(R)
                Cs.append(C * (1.0 if unit else 2.5))
        return np.stack(Rs), np.stack(Cs)

    return fn


def _reflection_E():
    """True if the check's stored E values make the 'no det flip' mistake visible (det U det V = -1)."""
    f = grading_core.load_fixture("essential")
    return any(np.linalg.det(np.linalg.svd(f[f"{n}_E"])[0]) * np.linalg.det(np.linalg.svd(f[f"{n}_E"])[2]) < 0
               for n in f["pose_cases"])


@pytest.mark.parametrize(
    "fn, phrase",
    [
        (_candidates_variant(unit=False), "unit length"),
        (_candidates_variant(center_is_t=True), "C holds the translation t"),
        (_candidates_variant(one_rotation=True), "the four R are one rotation"),
    ],
)
def test_check_pose_candidates_names_mistakes(fn, phrase, capsys):
    ok, out = verdict(checks.check_pose_candidates, fn, capsys)
    assert not ok and phrase in out, out


def test_check_pose_candidates_names_det_minus_one(capsys):
    assert _reflection_E(), "the essential fixture should hold an E whose SVD has det U det V = -1"
    ok, out = verdict(checks.check_pose_candidates, _candidates_variant(flip_det=False), capsys)
    assert not ok and "det -1" in out, out


def test_equivalent_forms_get_full_marks_and_the_reference_verdict(capsys):
    """E of another scale and sign, the candidates in another order, float32: full marks, and the printed verdict is
    the reference's (so the notebook's check cell passes under nbval too)."""
    from tests.checks.catalogue import essential as cat

    for check, ref_fn, fns in ((checks.check_essential_from_fundamental, reference.essential_from_fundamental,
                                (cat.essential_average_singular_value, cat.essential_from_fundamental__negated_float32)),
                               (checks.check_pose_candidates, reference.pose_candidates,
                                (cat.pose_candidates_other_order, cat.pose_candidates__w_transposed,
                                 cat.pose_candidates__float32))):
        check(ref_fn)
        want = capsys.readouterr().out
        for fn in fns:
            check(fn)
            out = capsys.readouterr().out
            result = grading_core.RESULTS[out.splitlines()[0]]
            assert grading_core.score(result) == 1.0 and not result.details_failed and out == want, out

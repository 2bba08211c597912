"""course_lib.exercises: the table of exercises matches the notebooks; the kit reads every form a stub allows."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from course_lib import exercises
from course_lib.exercises import EXERCISES, Fields, call, implementation
from course_lib.instructor.notebooks import kit_specs
from course_lib.validate import KitInputError


def test_the_table_lists_every_exercise_of_the_notebooks_with_its_notebook_and_reference():
    specs = {e.name: e for s in kit_specs() for e in s.exercises}
    assert list(EXERCISES) == list(specs)  # the same exercises, in notebook order
    for name, ex in EXERCISES.items():
        assert ex.notebook == specs[name].notebook, name
        ref = specs[name].reference
        assert ex.module == (ref.split(":")[0] if ref else None), name


def test_in_the_instructors_kit_the_implementation_is_the_reference():
    from course_lib.sfm import pnp

    assert implementation("pnp_ransac") is pnp.pnp_ransac
    assert getattr(implementation("psnr"), "__kit_stand_in__", False)  # no library function: never called by the kit
    with pytest.raises(KitInputError, match="'ransac' is not an exercise of the kit; the exercises are: normalize_points"):
        implementation("ransac")


@dataclass
class Choice:
    R_cw: np.ndarray
    t_cw: np.ndarray
    X: np.ndarray
    in_front: np.ndarray
    counts: np.ndarray


@pytest.mark.parametrize("form", ["tuple", "dataclass"])
def test_a_result_as_a_tuple_or_as_a_dataclass_reads_the_same(monkeypatch, form):
    parts = (np.eye(3), [0.0, 0.0, 1.0], np.zeros((2, 3)), [1, 0], [2, 0, 0, 0])

    def choose_pose(R, C, K, x1, x2):
        return parts if form == "tuple" else Choice(*parts)

    monkeypatch.setitem(exercises._IMPLEMENTATIONS, "choose_pose", choose_pose)
    res = call("choose_pose", None, None, None, None, None)
    assert isinstance(res, Fields)
    assert res.in_front.dtype == bool and res.in_front.tolist() == [True, False]
    assert res.counts.dtype.kind == "i" and res.t_cw.dtype == float and res.t_cw.shape == (3,)
    R, t, X, in_front, counts = res  # unpacks like the documented tuple
    assert np.array_equal(R, np.eye(3))


def test_a_result_that_does_not_fit_its_docstring_says_what_is_documented(monkeypatch):
    monkeypatch.setitem(exercises._IMPLEMENTATIONS, "pnp_ransac", lambda *a, **k: (np.eye(3), np.zeros(3)))
    with pytest.raises(KitInputError, match=r"pnp_ransac returned 2 values; its docstring documents 4: "
                                            r"\(R_cw, t_cw, inliers, n_iters\)"):
        call("pnp_ransac", None, None, None, None)
    monkeypatch.setitem(exercises._IMPLEMENTATIONS, "pnp_ransac", lambda *a, **k: None)
    with pytest.raises(KitInputError, match="pnp_ransac returned None"):
        call("pnp_ransac", None, None, None, None)

    @dataclass
    class Half:
        R_cw: np.ndarray

    monkeypatch.setitem(exercises._IMPLEMENTATIONS, "pnp_ransac", lambda *a, **k: Half(np.eye(3)))
    with pytest.raises(KitInputError, match="a Half without t_cw, inliers, n_iters"):
        call("pnp_ransac", None, None, None, None)


def test_single_sfm_results_come_back_as_float_arrays(monkeypatch):
    monkeypatch.setitem(exercises._IMPLEMENTATIONS, "eight_point", lambda x1, x2: [[1, 0, 0], [0, 1, 0], [0, 0, 0]])
    F = call("eight_point", None, None)
    assert isinstance(F, np.ndarray) and F.dtype == float

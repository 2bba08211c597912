"""Through the real grader: each mistake charged once, and the randomness checks see what a notebook would (issue 29).

* A mistake in ``normalize_points`` (no centring), which ``eight_point`` and ``ransac_fundamental`` call, costs
  ``normalize_points`` only: the later exercises keep full marks, their nbval share included (the grader's check
  on the notebook's cases answers the earlier steps by their references, as the hidden checks do).
* A RANSAC that draws from a generator of its own, or seeds numpy's global generator, is told so by the
  hidden checks: the grader returns the states of the generator arguments and the global states that the
  student's call left, as a notebook's kernel would show them.
"""

from __future__ import annotations

import pytest

from course_lib.instructor.grade import grade_submission, prepare_hidden
from course_lib.instructor.notebooks import kit_specs
from tests.checks.catalogue import collect
from tests.instructor.severity import _submission

#: Minutes, not seconds: left out of the quick subset (pytest -m "not slow").
pytestmark = pytest.mark.slow

SEED = 2033


def _mistake(exercise: str, name: str):
    return next(m for m in collect("MISTAKES") if m.exercise == exercise and m.name == name)


@pytest.fixture(scope="module")
def hidden(tmp_path_factory):
    return prepare_hidden([s for s in kit_specs() if s.name.startswith("01")], SEED, tmp_path_factory.mktemp("hidden"))


def test_a_mistake_costs_its_own_exercise_only(hidden, tmp_path):
    m = _mistake("normalize_points", "centroid not removed")
    report = grade_submission(_submission(tmp_path / "sub", m, "01"), notebooks=["01"], hidden=hidden,
                              run_nbval=True, allow_reference=True)
    g = {e["name"]: e for e in report["exercises"]}
    assert g["normalize_points"]["points"] < 10
    for later in ("eight_point", "ransac_fundamental"):
        assert g[later]["points"] == 10, (later, g[later])
    assert g["eight_point"]["nbval"] == "pass", g["eight_point"]


@pytest.mark.parametrize("name, words", [
    ("own default_rng(0)", "the rng argument is untouched after the call"),
    ("np.random.seed(0) inside", "changed numpy's global random state"),
])
def test_the_randomness_checks_see_what_a_notebook_shows(hidden, tmp_path, name, words):
    m = _mistake("ransac_fundamental", name)
    report = grade_submission(_submission(tmp_path / "sub", m, "01"), notebooks=["01"],
                              exercises=["ransac_fundamental"], hidden=hidden, run_nbval=False, allow_reference=True)
    g = report["exercises"][0]
    assert g["points"] < 9 and any(words in line for line in g["feedback"]), g

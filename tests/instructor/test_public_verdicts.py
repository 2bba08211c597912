"""The check cells' stored verdicts are what the grader's own check prints for the instructor's solutions.

The nbval share of an exercise comes from the grader: the exercise's check on the notebook's own cases, run with
the student's function, must print the verdict stored in the instructor notebook
(:func:`course_lib.instructor.grade_run.add_nbval`). So for every exercise the instructor's solution (cut out of its
notebook, as the hidden checks' calibration does) checked on the public fixtures must print exactly that verdict; a
check changed without its notebook's verdict refreshed would cost every student that share.
"""

from __future__ import annotations

import types

import nbformat
import pytest

from course_lib.instructor.extract import extract_exercise
from course_lib.instructor.hidden import run_check
from course_lib.instructor.notebooks import NOTEBOOKS_DIR, kit_specs
from course_lib.paths import FIXTURES_DIR

EXERCISES = [e for s in kit_specs() for e in s.exercises]


@pytest.mark.parametrize("e", EXERCISES, ids=lambda e: f"{e.notebook[:2]}-{e.name}")
def test_the_instructors_solution_prints_the_stored_verdict(e, monkeypatch):
    monkeypatch.setenv("COURSE_LIB_QUICK", "1")
    ex = extract_exercise(nbformat.read(NOTEBOOKS_DIR / e.notebook, as_version=4), e.name, e.check_cell)
    module = types.ModuleType("__instructor__")
    exec(compile(ex.code, f"<{e.notebook}>", "exec"), module.__dict__)  # noqa: S102 - the instructor's own code
    _, printed = run_check(e.check_module, e.check_function, str(FIXTURES_DIR), module.__dict__[e.name])
    assert printed.rstrip() == e.verdict.rstrip(), (
        f"{e.notebook}: the check of {e.name} prints another verdict than the one stored in the notebook; store the "
        f"new one: python -m course_lib refresh-checks notebooks/{e.notebook}\n--- printed\n{printed}\n--- stored\n"
        f"{e.verdict}")

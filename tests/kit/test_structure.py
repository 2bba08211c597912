"""The house rules of ``course_lib``, read from its source (:mod:`tests.kit.structure`; ``python -m tests.kit.structure`` prints the figures)."""

import pytest

from tests.kit import structure

#: Longest function anywhere in ``course_lib`` (the grader included, since its split into plan / run / report).
MAX_FUNCTION_LINES = 80
#: A module longer than this has one job, which the first line of its docstring names.
LARGE_MODULE_LINES = 500


@pytest.fixture(scope="module")
def mods():
    return structure.load()


def test_the_reader_sees_every_module_and_its_imports(mods):
    assert {"course_lib", "course_lib.sfm.mapper", "course_lib.sfm.lm", "course_lib.sfm.lm.solver"} <= set(mods)
    assert mods["course_lib.sfm.mapper"].imports["course_lib.sfm.triangulator"] == "top"
    assert mods["course_lib.sfm.lm.cameras"].imports["course_lib.exercises"] == "deferred"


def test_no_import_circle_not_even_through_a_deferred_import(mods):
    circles = [structure.describe_circle(mods, c) for c in structure.cycles(mods)]
    assert circles == [], "import circles (move the shared part into a module both can import):\n" + "\n".join(circles)


def test_the_circle_finder_finds_a_deferred_circle(mods, monkeypatch):
    a, b = mods["course_lib.exercises"], mods["course_lib.saved_solutions"]
    monkeypatch.setitem(b.imports, "course_lib.exercises", "deferred")
    (circle,) = structure.cycles(mods)
    assert set(circle) == {a.name, b.name} and "(deferred)" in structure.describe_circle(mods, circle)


def test_no_private_name_is_used_outside_its_module(mods):
    uses = list(structure.private_uses(mods))
    assert uses == [], "private names taken from another module (make them public, or move them where they belong):\n" \
        + "\n".join(uses)


def test_no_function_longer_than_80_lines(mods):
    long = [f"{n} lines: {where}" for n, where in structure.functions(mods) if n > MAX_FUNCTION_LINES]
    assert long == [], f"functions over {MAX_FUNCTION_LINES} lines (split them into named steps):\n" + "\n".join(long)


def test_every_large_module_names_its_one_job_in_its_first_line(mods):
    unnamed = [m.name for m in mods.values() if m.lines > LARGE_MODULE_LINES and not m.doc_first_line.endswith(".")]
    assert unnamed == [], f"modules over {LARGE_MODULE_LINES} lines whose docstring does not open with a sentence naming their job: {unnamed}"


def test_the_report_states_every_figure(mods):
    text = structure.report(mods=mods)
    for part in ("import circles: 0", "private names used across modules:", "functions over 80 lines:",
                 "modules over 500 lines:", "lines per folder:"):
        assert part in text

"""The student's path: a fresh release, filled by the literal student, runs notebooks 01-10 and gets full marks.

The literal-student catalogue (:mod:`tests.student.literal`: every exercise written from the
released notebook's text and stub only, keeping the dtypes it is given) fills a fresh student
release (:func:`course_lib.instructor.release.write_release`, filled by :mod:`tests.student.fill`
the way a student fills it). Then, as a student who works through the course:

1. every notebook 01-10 runs in order, each in a fresh kernel whose ``course_lib`` is the
   release's (:func:`course_lib.instructor.release.verify_release` with no error allowed: it
   checks ``course_lib.__file__`` inside the kernel), in quick mode (``COURSE_LIB_QUICK=1``);
   no cell may end in an error, and every check cell prints its verdict;
2. the kit's grader (:func:`course_lib.instructor.grade.grade_submission`) gives every exercise
   of the filled release full marks.

Full marks are the whole hidden share (every hidden check passes) and the nbval share: the grader gives it when the notebook runs top to bottom
through the check cell and the check on the notebook's own cases, run by the grader with the student's
function in its sandbox, prints the reference verdict. The grading here is the grader's own, with one
stand-in: the notebooks' top-to-bottom runs are the in-order run of 1 (in the student's own chain of
saved solutions), not nbval's runs of notebooks 01-08 a second time in sandboxed kernels (some 90 s of
CPU; the grader's nbval runner itself is tested on the honest catalogue,
``tests/instructor/test_honest_grading.py``, and on attacks, ``tests/instructor/test_attacks.py``). So
2 asserts full marks on every exercise: the whole hidden share, and the nbval share from the grader's
own verdict of each check cell.

The catalogue is also held to each check function on its own (fast, no notebook), so a
failure of the notebook run is the kit's, not the catalogue's.
"""

from __future__ import annotations

import importlib

import pytest

from course_lib.instructor.notebooks import kit_specs
from course_lib.instructor.release import verify_release, write_release
from tests.student.fill import catalogue, fill_release
from tests.student.literal import MODULES

#: Minutes, not seconds: left out of the quick subset (pytest -m "not slow").
pytestmark = pytest.mark.slow

#: Every notebook of the course, in the order a student works through them.
COURSE = ("01", "02", "03", "04", "05", "06", "07", "08", "09", "10")
GRADE_SEED = 2026


@pytest.fixture(scope="module")
def filled_release(tmp_path_factory):
    kit = tmp_path_factory.mktemp("literal") / "kit"
    write_release(kit)
    filled = fill_release(kit)
    unfilled = {s.name: [e.name for e in s.exercises if e.name not in {f.split(".")[0] for f in filled.get(s.name, [])}]
                for s in kit_specs()}
    assert not any(unfilled.values()), f"exercises the filler found no stub of in the release: {unfilled}"
    return kit, filled


def test_the_catalogue_holds_every_exercise_of_the_kit():
    exercises = {e.name for s in kit_specs() for e in s.exercises}
    have = {name.split(".")[0] for name in catalogue()}
    assert exercises <= have, f"no literal solution for {sorted(exercises - have)} in tests/student/literal"


SPECS = {e.name: e for s in kit_specs() for e in s.exercises}  # exercise -> its spec (check, reference verdict)


def lines(text: str) -> list[str]:
    """A printed verdict as the grader compares it: line by line, trailing spaces left out."""
    return [line.rstrip() for line in text.rstrip().splitlines()]


@pytest.mark.parametrize("exercise", sorted(SPECS))
def test_each_literal_solution_passes_its_check(exercise, capsys):
    """Each literal solution on its own, through the check its notebook's check cell calls: no ✘, and the verdict
    the instructor's notebook stores for the reference (what the grader's nbval share asks of the check cell)."""
    spec = SPECS[exercise]
    check = getattr(importlib.import_module(spec.check_module), spec.check_function)
    solution = next(getattr(m, exercise) for m in (importlib.import_module(f"tests.student.literal.{n}")
                                                   for n in MODULES) if hasattr(m, exercise))
    check(solution)
    out = capsys.readouterr().out
    assert "✘" not in out, out
    assert lines(out) == lines(spec.verdict), f"printed:\n{out}\nthe reference's verdict:\n{spec.verdict}"


@pytest.fixture(scope="module")
def in_order(filled_release):
    """The in-order run of 1: ``{notebook: [problems]}``."""
    kit, _ = filled_release
    return verify_release(kit, only=list(COURSE), allowed_errors=())


def test_the_filled_release_runs_notebooks_01_to_10_in_order_without_an_error(filled_release, in_order):
    kit, _ = filled_release
    released = sorted(p.name for p in (kit / "notebooks").glob("*.ipynb"))
    missing = [n for n in COURSE if not any(name.startswith(n) for name in released)]
    errors = {name: found for name, found in in_order.items() if found}
    assert not missing and not errors, "\n".join(
        [f"notebooks/{n}*: not in the release" for n in missing]
        + [f"{name}: {'; '.join(p[:400] for p in found)}" for name, found in errors.items()])


class InOrderRun:
    """The grader's nbval runner (:class:`~course_lib.instructor.nbval_run.NbvalRun`) answered by the in-order run:
    every code cell of a notebook ran top to bottom when the student's in-order run of it ended without a problem."""

    sandbox: dict = {}

    def __init__(self, problems: dict[str, list[str]]):
        self.problems, self.notebooks = problems, {}

    def submit(self, name: str, nb) -> None:
        self.notebooks[name] = nb

    restart = submit

    def stop(self) -> None:
        pass

    def results(self) -> tuple[dict[tuple[str, int], str], dict[str, str]]:
        out = {}
        for name, nb in self.notebooks.items():
            found = self.problems.get(name, ["not in the in-order run"])
            verdict = "pass" if not found else "; ".join(found)[:300]
            out.update({(name, k): verdict for k in range(sum(c.cell_type == "code" for c in nb.cells))})
        return out, {}


def test_the_filled_release_gets_full_marks(filled_release, in_order, monkeypatch):
    from course_lib.instructor import grade
    from course_lib.instructor.grade import grade_submission

    def start_nbval(run, cell_timeout, jobs):  # the notebooks' runs: the in-order run (the module's docstring)
        runner = InOrderRun(in_order)
        for name, nb in run.to_nbval.items():
            runner.submit(name, nb)
        return runner

    monkeypatch.setattr(grade, "start_nbval", start_nbval)
    kit, _ = filled_release
    try:
        report = grade_submission(kit, salt=GRADE_SEED)
    except Exception as exc:  # noqa: BLE001 - a grader that refuses to run without its isolation
        if any(w in str(exc).lower() for w in ("isolation", "namespace", "sandbox")):
            pytest.skip(f"the grader refuses to grade here: {exc}")
        raise
    short = {f"{g['notebook'][:2]} {g['name']}": (g["points"], g["status"], g["nbval"], g["feedback"][:3])
             for g in report["exercises"] if g["status"] != "full" or g["points"] < g["max_points"]}
    assert not short, f"{report['total']} / {report['max']}: {short}"
    assert report["max"] == sum(e.points for s in kit_specs() for e in s.exercises)
    assert sorted(g["name"] for g in report["exercises"]) == sorted(SPECS)

"""Grading a class (``grade-class``): the gradebook, the CSV, one submission's crash or timeout costing only itself.

The first tests put a stand-in for the single-submission grader in place (a short script that writes the report a
submission's ``behaviour`` file asks for, or crashes, or hangs), so they take seconds; the last one grades a small
class of real submissions made from the student release (notebook 01, hidden checks only).
"""

from __future__ import annotations

import csv
import json
import os
import sqlite3
import sys
import textwrap
import time
from pathlib import Path

import pytest

from course_lib.__main__ import main
from course_lib.instructor import classroom
from course_lib.instructor.gradebook import Gradebook

FAKE_GRADER = textwrap.dedent("""
    import json, os, sys, time
    from pathlib import Path
    sub, report, feedback = Path(sys.argv[1]), Path(sys.argv[3]), Path(sys.argv[5])
    what = (sub / "behaviour").read_text().split()
    if what[0] == "crash":
        print("Traceback: something broke"); sys.stdout.flush(); os.abort()
    if what[0] == "hang":
        time.sleep(600)
    if what[0] == "refuse-once" and not (sub / "refused").exists():
        (sub / "refused").write_text("")
        print("error: refusing to run the students' code: bubblewrap could not make the sandbox (bwrap: Creating "
              "new namespace failed: Resource temporarily unavailable)")
        sys.exit(2)
    pts = [float(p) for p in what[1:]]
    exercises = [{"notebook": "01_f.ipynb", "name": f"ex{i}", "points": p, "max_points": 10.0, "status": "graded"}
                 for i, p in enumerate(pts)]
    report.write_text(json.dumps({"total": sum(pts), "max": 10.0 * len(pts), "hidden_seed": 7, "seconds": 0.1,
                                  "notebooks": [], "exercises": exercises, "options": sys.argv[6:],
                                  "uid": os.environ.get("COURSE_GRADER_STUDENT_UID")}))
    feedback.write_text(f"# Grading feedback of {sub.name}\\n")
""")


@pytest.fixture
def fake_grader(tmp_path, monkeypatch):
    script = tmp_path / "fake_grader.py"
    script.write_text(FAKE_GRADER)
    monkeypatch.setattr(classroom, "GRADER", [sys.executable, str(script)])
    monkeypatch.setattr(classroom, "START_SECONDS", 0.0)


def make_class(root: Path, behaviours: dict[str, str]) -> Path:
    for student, what in behaviours.items():
        (root / student).mkdir(parents=True, exist_ok=True)
        (root / student / "behaviour").write_text(what)
    return root


def grade_class(root: Path, *extra: str) -> int:
    return main(["grade-class", str(root / "class"), "--gradebook", str(root / "grades.sqlite"),
                 "--csv", str(root / "grades.csv"), "--insecure", "--submission-timeout", "5", *extra])


def rows(db: Path, sql: str) -> list:
    with sqlite3.connect(db) as c:
        return c.execute(sql).fetchall()


@pytest.mark.fails_closed  # no sandbox needed: a stand-in grader
def test_a_crash_and_a_timeout_cost_only_their_own_submission(tmp_path, fake_grader, capsys):
    make_class(tmp_path / "class", {"ada": "ok 10 7", "bob": "crash", "cy": "hang", "dee": "ok 3 0"})
    t0 = time.monotonic()
    assert grade_class(tmp_path, "--jobs", "4") == 0
    assert time.monotonic() - t0 < 60  # the hanging one is stopped at its limit (5 s here), in parallel
    reports = {s: json.loads((tmp_path / "reports" / s / "report.json").read_text())
               for s in ("ada", "bob", "cy", "dee")}
    assert reports["ada"]["total"] == 17 and reports["dee"]["total"] == 3
    assert reports["bob"]["status"] == "crashed" and "signal" in reports["bob"]["error"]
    assert reports["cy"]["status"] == "timed out" and "ran past its time" in reports["cy"]["error"]
    for s in ("bob", "cy"):
        assert "could not be graded" in (tmp_path / "reports" / s / "feedback.md").read_text()
    assert "Traceback: something broke" in (tmp_path / "reports" / "bob" / "grader.log").read_text()
    assert reports["ada"]["options"] == ["--submission-timeout", "5.0", "--insecure"]  # grade's options passed on
    assert sorted(rows(tmp_path / "grades.sqlite", "SELECT student, status, total FROM gradings")) == [
        ("ada", "graded", 17.0), ("bob", "crashed", 0.0), ("cy", "timed out", 0.0), ("dee", "graded", 3.0)]
    assert "not finished: bob, cy" in capsys.readouterr().out


@pytest.mark.fails_closed  # no sandbox needed: a stand-in grader
def test_a_grading_refused_while_others_ran_is_graded_again_alone(tmp_path, fake_grader):
    make_class(tmp_path / "class", {"ada": "refuse-once 5", "bob": "ok 6", "cy": "ok 7"})
    assert grade_class(tmp_path, "--jobs", "2") == 0
    assert sorted(rows(tmp_path / "grades.sqlite", "SELECT student, status, total FROM gradings")) == [
        ("ada", "graded", 5.0), ("bob", "graded", 6.0), ("cy", "graded", 7.0)]  # ada's refusal is not recorded
    uids = {json.loads((tmp_path / "reports" / s / "report.json").read_text())["uid"] for s in ("ada", "bob", "cy")}
    if os.getuid() == 0:  # as root, each job's students' processes get a uid of their own
        assert uids <= {str(classroom.STUDENT_UID), str(classroom.STUDENT_UID - 1)}
    else:
        assert uids == {None}


@pytest.mark.fails_closed  # no sandbox needed: a stand-in grader
def test_graded_commits_are_skipped_and_regrade_keeps_the_history(tmp_path, fake_grader):
    make_class(tmp_path / "class", {"ada": "ok 10", "bob": "crash"})
    (tmp_path / "class" / "ada.commit").write_text("ada/kit\nabc123\n")  # what the CI template's plan job writes
    assert grade_class(tmp_path, "--jobs", "2") == 0
    (tmp_path / "class" / "bob" / "behaviour").write_text("ok 4")  # bob's new commit
    assert grade_class(tmp_path) == 0  # ada's commit is graded already; bob's is new
    assert rows(tmp_path / "grades.sqlite", "SELECT student, status, total FROM gradings ORDER BY student, id") == [
        ("ada", "graded", 10.0), ("bob", "crashed", 0.0), ("bob", "graded", 4.0)]
    assert rows(tmp_path / "grades.sqlite", "SELECT commit_id FROM gradings WHERE student = 'ada'") == [("abc123",)]
    (tmp_path / "class" / "ada" / "behaviour").write_text("ok 9")
    assert grade_class(tmp_path, "--regrade") == 0  # same commit, graded again: both gradings kept
    assert rows(tmp_path / "grades.sqlite", "SELECT total FROM gradings WHERE student = 'ada' ORDER BY id") == [
        (10.0,), (9.0,)]
    export = list(csv.reader(open(tmp_path / "grades.csv")))
    assert export[0] == ["student", "commit", "graded_at", "status", "total", "max", "01_f.ipynb", "01_f.ipynb: ex0"]
    assert [r[0] for r in export[1:]] == ["ada", "bob"] and export[1][4] == "9" and export[2][4] == "4"


@pytest.mark.fails_closed  # no sandbox needed: a stand-in grader
def test_the_csv_has_one_row_per_student_with_notebooks_and_exercises(tmp_path):
    book = Gradebook(tmp_path / "g.sqlite")

    def ex(nb, name, p):
        return {"notebook": nb, "name": name, "points": p, "max_points": 10, "status": "graded"}

    book.record("b", "c1", "v", "graded", {"total": 15, "max": 30, "exercises": [
        ex("01", "eight_point", 10), ex("01", "normalize", 5), ex("02", "pose", 0)]}, "fb")
    book.record("a", "c2", "v", "crashed", {"total": 0, "max": None}, "fb")
    assert book.export_csv(tmp_path / "g.csv") == 2
    head, a, b = list(csv.reader(open(tmp_path / "g.csv")))
    assert head[4:] == ["total", "max", "01", "02", "01: eight_point", "01: normalize", "02: pose"]
    assert b[4:] == ["15", "30", "15", "0", "10", "5", "0"] and a[4:] == ["0", "", "0", "0", "0", "0", "0"]


@pytest.mark.fails_closed
def test_no_sandbox_no_class_grading(tmp_path, monkeypatch, capsys):
    from course_lib.instructor import grade
    from course_lib.instructor.sandbox.jail import IsolationError  # noqa: F401

    def refuse(*a, **k):
        raise IsolationError("bubblewrap is not installed: apt-get install bubblewrap")

    monkeypatch.setattr(grade, "preflight", refuse)
    make_class(tmp_path / "class", {"ada": "ok 1"})
    assert main(["grade-class", str(tmp_path / "class"), "--gradebook", str(tmp_path / "g.sqlite")]) == 2
    assert "bubblewrap is not installed" in capsys.readouterr().err
    assert not (tmp_path / "g.sqlite").exists()


@pytest.mark.slow  # the grader on a class: pytest -m "not slow" leaves it out
def test_a_class_of_real_submissions(tmp_path, capsys):
    """A complete notebook 01, the untouched release, and a complete one with a link to another student's folder
    (left out, and named in its report), graded two at once with real sandboxes."""
    from tests.instructor.test_grade import NB01, released, solved, write_submission

    write_submission(tmp_path / "class" / "ada", {NB01: solved()[NB01]})
    write_submission(tmp_path / "class" / "bob", {NB01: released(NB01)})
    write_submission(tmp_path / "class" / "cy", {NB01: solved()[NB01]})
    os.symlink(tmp_path / "class" / "ada" / "notebooks", tmp_path / "class" / "cy" / "notebooks" / "ada")
    rc = main(["grade-class", str(tmp_path / "class"), "--gradebook", str(tmp_path / "grades.sqlite"), "--csv",
               str(tmp_path / "grades.csv"), "--jobs", "2", "--notebooks", "01", "--no-nbval", "--timeout", "20",
               "--hidden-seed", "11"])
    assert rc == 0, capsys.readouterr()
    reports = {s: json.loads((tmp_path / "reports" / s / "report.json").read_text()) for s in ("ada", "bob", "cy")}
    assert reports["ada"]["total"] == reports["cy"]["total"] == 0.9 * reports["ada"]["max"]  # nbval's share not run
    assert reports["bob"]["total"] == 0
    assert any(r.startswith("notebooks/ada: a symbolic link") for r in reports["cy"]["submission"]["left out"])
    assert "notebooks/ada" in (tmp_path / "reports" / "cy" / "feedback.md").read_text()
    assert rows(tmp_path / "grades.sqlite", "SELECT student, hidden_seed FROM gradings ORDER BY student") == [
        ("ada", 11), ("bob", 11), ("cy", 11)]
    head, *students = list(csv.reader(open(tmp_path / "grades.csv")))
    assert [s[0] for s in students] == ["ada", "bob", "cy"] and len(head) == 6 + 1 + len(reports["ada"]["exercises"])

"""Grading, measured on submissions that this file builds itself (notebooks 01 and 02 only, to stay fast).

Submissions: the instructor notebooks (full marks in the instructor's self-test, zero as a student's
work because they call the reference), the untouched release (zero), a self-written full solution,
a partly solved one (exact partial score), one with a typical mistake in every exercise (marked
down, feedback naming the mistake), one that raises, one that loops forever, one that prints the
expected verdict by hand, one that monkeypatches the checks, one that imports the reference in a
helper cell, and ones with deleted or reordered cells. The hidden cases (seed 11) are built once.
The full 8-notebook grading is timed by benchmarks/grade_speed.py, not here.
"""

from __future__ import annotations

import json
import os
import re
import textwrap
from pathlib import Path

import nbformat
import pytest

from course_lib.instructor.grade import grade_submission, prepare_hidden, to_markdown
from course_lib.instructor.notebooks import NOTEBOOKS_DIR, kit_specs
from course_lib.instructor.release import stub_notebook

NOTEBOOKS = ["01", "02"]
NB01, NB02 = "01_fundamental_matrix.ipynb", "02_essential_matrix_and_pose.ipynb"
SEED = 11

# ------------------------------------------------------------------ a student's own solutions

SOLUTIONS = {
    "normalize_points": """
        c = x.mean(axis=0)
        s = np.sqrt(2.0) / np.linalg.norm(x - c, axis=1).mean()
        T = np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])
        return (x - c) * s, T
    """,
    "eight_point": """
        a, T1 = normalize_points(x1)
        b, T2 = normalize_points(x2)
        A = np.stack([b[:, 0] * a[:, 0], b[:, 0] * a[:, 1], b[:, 0], b[:, 1] * a[:, 0], b[:, 1] * a[:, 1],
                      b[:, 1], a[:, 0], a[:, 1], np.ones(len(a))], axis=1)
        F = np.linalg.svd(A)[2][-1].reshape(3, 3)
        U, s, Vt = np.linalg.svd(F)
        F = T2.T @ (U @ np.diag([s[0], s[1], 0.0]) @ Vt) @ T1
        F = F / np.linalg.norm(F)
        return F if F.flat[np.argmax(np.abs(F))] > 0 else -F
    """,
    "sampson_distance": """
        x1h = np.column_stack([x1, np.ones(len(x1))])
        x2h = np.column_stack([x2, np.ones(len(x2))])
        Fx1, Ftx2 = x1h @ F.T, x2h @ F
        e = np.sum(x2h * Fx1, axis=1)
        return np.abs(e) / np.sqrt(Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2)
    """,
    "ransac_fundamental": """
        n = len(x1)
        best = np.zeros(n, bool)
        n_iters, needed = 0, max_iters
        while n_iters < min(needed, max_iters):
            idx = rng.choice(n, 8, replace=False)
            inl = sampson_distance(eight_point(x1[idx], x2[idx]), x1, x2) < threshold_px
            n_iters += 1
            if inl.sum() > best.sum():
                best = inl
                w = inl.mean()
                needed = np.log(1 - confidence) / np.log(1 - w**8) if w < 1 else 0
        F = eight_point(x1[best], x2[best])
        return RansacResult(F, sampson_distance(F, x1, x2) < threshold_px, n_iters)  # refit, inliers recomputed
    """,
    "essential_from_fundamental": """
        U, _, Vt = np.linalg.svd(K.T @ F @ K)
        return U @ np.diag([1.0, 1.0, 0.0]) @ Vt
    """,
    "pose_candidates": """
        U, _, Vt = np.linalg.svd(E)
        W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
        Rs, Cs = [], []
        for R0 in (U @ W @ Vt, U @ W.T @ Vt):
            for t in (U[:, 2], -U[:, 2]):
                R, C = R0, -R0.T @ t
                if np.linalg.det(R) < 0:
                    R, C = -R, -C
                Rs.append(R)
                Cs.append(C / np.linalg.norm(C))
        return np.stack(Rs), np.stack(Cs)
    """,
}

#: One typical mistake per exercise, and a phrase the feedback must contain.
MISTAKES = {
    "normalize_points": (SOLUTIONS["normalize_points"].replace("np.sqrt(2.0)", "1.0"), "the mean distance to the centroid is 1"),
    "eight_point": ("""
        A = np.stack([x2[:, 0] * x1[:, 0], x2[:, 0] * x1[:, 1], x2[:, 0], x2[:, 1] * x1[:, 0], x2[:, 1] * x1[:, 1],
                      x2[:, 1], x1[:, 0], x1[:, 1], np.ones(len(x1))], axis=1)
        F = np.linalg.svd(A)[2][-1].reshape(3, 3)
        U, s, Vt = np.linalg.svd(F)
        F = U @ np.diag([s[0], s[1], 0.0]) @ Vt
        return F / np.linalg.norm(F)
    """, "not normalized"),
    "sampson_distance": (SOLUTIONS["sampson_distance"].replace("return np.abs(e) / np.sqrt(", "return e**2 / ("),
                         "squared error"),
    "ransac_fundamental": (SOLUTIONS["ransac_fundamental"].replace("n_iters < min(needed, max_iters)",
                                                                   "n_iters < max_iters"),
                           "updated with the best inlier ratio so far"),
    "essential_from_fundamental": ("""
        return K.T @ F @ K
    """, "did not correct the singular values"),
    "pose_candidates": (SOLUTIONS["pose_candidates"].replace("if np.linalg.det(R) < 0:", "if False:"), "det -1"),
}


# ------------------------------------------------------------------ building submissions


def released(name: str):
    return stub_notebook(nbformat.read(NOTEBOOKS_DIR / name, as_version=4), name)


def fill(nb, name: str, body: str):
    """Put ``body`` in place of the stub of exercise ``name`` (the student's edit)."""
    for cell in nb.cells:
        if cell.cell_type == "code" and re.search(rf"^def {name}\(", cell.source, re.M) and "YOUR CODE HERE" in cell.source:
            lines = cell.source.splitlines()
            k = next(i for i, ln in enumerate(lines) if ln.strip() == "# YOUR CODE HERE")
            indent = lines[k][: len(lines[k]) - len(lines[k].lstrip())]
            code = textwrap.indent(textwrap.dedent(body).strip("\n"), indent).splitlines()
            cell.source = "\n".join(lines[:k] + code + lines[k + 2:])
            return nb
    raise AssertionError(f"no stub of {name}")


def check_cell_index(nb, name: str) -> int:
    return next(i for i, c in enumerate(nb.cells) if c.cell_type == "code" and c.source.startswith("# NBVAL_CHECK_OUTPUT")
                and f"({name})" in c.source)


def write_submission(root: Path, notebooks: dict) -> Path:
    (root / "notebooks").mkdir(parents=True, exist_ok=True)
    for name, nb in notebooks.items():
        nbformat.write(nb, root / "notebooks" / name)
    return root


def solved(names=tuple(SOLUTIONS), bodies=None) -> dict:
    bodies = {**SOLUTIONS, **(bodies or {})}
    nbs = {NB01: released(NB01), NB02: released(NB02)}
    for nbname, nb in nbs.items():
        for cell in nb.cells:
            for ex in names:
                if cell.cell_type == "code" and re.search(rf"^def {ex}\(", cell.source, re.M):
                    fill(nb, ex, bodies[ex])
    return nbs


def by_name(report: dict) -> dict:
    return {g["name"]: g for g in report["exercises"]}


@pytest.fixture(scope="module")
def hidden(tmp_path_factory):
    specs = kit_specs(NOTEBOOKS_DIR, only=NOTEBOOKS)
    return prepare_hidden(specs, SEED, tmp_path_factory.mktemp("hidden"))


def grade(path, hidden, **kw):
    kw.setdefault("run_nbval", False)
    return grade_submission(path, notebooks=NOTEBOOKS, hidden=hidden, timeout=kw.pop("timeout", 20.0), **kw)


# ------------------------------------------------------------------ the tests


def test_hidden_cases_are_new_and_the_reference_passes_them(hidden):
    import numpy as np

    from course_lib.paths import FIXTURES_DIR

    with np.load(hidden.fixtures_dir / "fundamental.npz") as h, np.load(FIXTURES_DIR / "fundamental.npz") as p:
        # (tests/instructor/test_hidden_cases.py proves that no hidden array equals any shipped one)
        keys = [k for k in h.files if k in p.files and h[k].dtype.kind == "f" and h[k].size >= 16]
        assert keys and any(h[k].shape != p[k].shape or not np.allclose(h[k], p[k]) for k in keys), \
            "the hidden scene must differ from the public one"
    assert all(hidden.reference_passing.values()) and not hidden.reference_notes, hidden.reference_notes


@pytest.mark.slow  # the grader with nbval: pytest -m "not slow" leaves it out
def test_self_written_solutions_get_full_marks_with_nbval(tmp_path, hidden):
    report = grade(write_submission(tmp_path, solved()), hidden, run_nbval=True, cell_timeout=120)
    assert report["total"] == report["max"] == 60, json.dumps(report, indent=1, ensure_ascii=False)
    assert all(g["nbval"] == "pass" and g["status"] == "full" for g in report["exercises"])
    md = to_markdown(report)
    assert "**Total: 60 / 60 points**" in md and "full marks" in md


def test_instructor_notebooks_full_marks_in_self_test_and_zero_as_student_work(tmp_path, hidden):
    sub = tmp_path / "instructor"
    write_submission(sub, {n: nbformat.read(NOTEBOOKS_DIR / n, as_version=4) for n in (NB01, NB02)})
    self_test = grade(sub, hidden, allow_reference=True)
    assert self_test["total"] == 54 and all(g["status"] == "full" for g in self_test["exercises"])  # 90 % without nbval
    student = grade(sub, hidden)  # the reference solutions are not in the student's sandbox
    assert student["total"] == 0
    for g in student["exercises"]:
        assert any(re.search(r"(ImportError|ModuleNotFoundError).*course_lib\.sfm", f) for f in g["feedback"]), g


def test_untouched_release_gets_zero_and_one_line_per_exercise(tmp_path, hidden):
    report = grade(write_submission(tmp_path, {NB01: released(NB01), NB02: released(NB02)}), hidden)
    assert report["total"] == 0 and report["max"] == 60
    for g in report["exercises"]:
        assert g["status"] == "not attempted" and g["feedback"] == [
            f"not attempted: your {g['name']} still raises NotImplementedError (the released stub)"], g


def test_partly_solved_gets_the_exact_partial_score(tmp_path, hidden):
    nbs = solved(names=("normalize_points", "eight_point", "sampson_distance", "essential_from_fundamental"))
    report = grade(write_submission(tmp_path, nbs), hidden)
    g = by_name(report)
    assert report["total"] == 4 * 9.0  # 90 % of 10 points for each solved exercise (nbval not run here)
    assert [g[n]["points"] for n in ("ransac_fundamental", "pose_candidates")] == [0, 0]
    assert g["eight_point"]["hidden"]["passed"] == g["eight_point"]["hidden"]["total"] > 0


@pytest.mark.slow  # the grader on many mistakes: pytest -m "not slow" leaves it out
def test_typical_mistakes_are_marked_down_and_named(tmp_path, hidden):
    nbs = solved(bodies={k: v[0] for k, v in MISTAKES.items()})
    report = grade(write_submission(tmp_path, nbs), hidden)
    for name, (_, phrase) in MISTAKES.items():
        g = by_name(report)[name]
        assert 0 <= g["points"] < 9, g
        assert any(phrase in f for f in g["feedback"]), (name, phrase, g["feedback"])


@pytest.mark.slow  # the grader up to its limits: pytest -m "not slow" leaves it out
def test_raising_and_looping_exercises_do_not_stop_the_others(tmp_path, hidden):
    nbs = solved(bodies={"eight_point": "raise ValueError('my bug')", "essential_from_fundamental": "while True:\n    pass"})
    report = grade(write_submission(tmp_path, nbs), hidden, timeout=8.0)
    g = by_name(report)
    assert g["eight_point"]["points"] == 0 and any("raised ValueError: my bug" in f for f in g["eight_point"]["feedback"])
    assert g["essential_from_fundamental"]["status"] == "timeout" and g["essential_from_fundamental"]["points"] == 0
    assert g["normalize_points"]["points"] == g["sampson_distance"]["points"] == g["pose_candidates"]["points"] == 9


def test_verdict_printed_by_hand_gets_nothing(tmp_path, hidden):
    nbs = solved(names=("normalize_points", "sampson_distance", "essential_from_fundamental", "pose_candidates"))
    nb = nbs[NB01]
    spec = kit_specs(NOTEBOOKS_DIR, only=["01"])[0]
    k = check_cell_index(nb, "eight_point")
    nb.cells[k].source = "# NBVAL_CHECK_OUTPUT\nprint(" + repr(spec.exercise("eight_point").verdict) + ", end='')"
    report = grade(write_submission(tmp_path, nbs), hidden)
    g = by_name(report)
    assert g["eight_point"]["points"] == 0 and g["eight_point"]["status"] == "check-edited"
    assert "the check cell of eight_point was edited" in g["eight_point"]["feedback"][0], g["eight_point"]
    assert g["normalize_points"]["points"] == 9  # only the edited check loses its credit


def test_checks_patched_in_the_notebook_change_nothing(tmp_path, hidden):
    """A cell that makes every check pass in the notebook's kernel: the hidden checks run in the grader, so a wrong
    eight_point still fails them (the nbval share's verdict is the grader's too: tests/instructor/test_attacks.py)."""
    nbs = solved(bodies={"eight_point": "return np.eye(3)"})
    patch = nbformat.v4.new_code_cell(
        "import course_lib.checks.core as core\n"
        "_expect = core.Check.expect\n"
        "core.Check.expect = lambda self, condition, ok, bad: _expect(self, True, ok, bad)\n")
    nbs[NB01].cells.insert(2, patch)
    report = grade(write_submission(tmp_path, nbs), hidden)
    for g in report["exercises"]:
        assert g["points"] == (0 if g["name"] == "eight_point" else 9), g
    # a patch inside the exercise function itself changes only the student's own process
    body = ("import course_lib.checks.core as c\nc.Check.expect = lambda *a, **k: None\nc.RESULTS.clear()\n"
            "return np.eye(3)")
    report = grade(write_submission(tmp_path / "inner", solved(bodies={"eight_point": body})), hidden)
    assert by_name(report)["eight_point"]["points"] == 0, by_name(report)["eight_point"]


def test_a_harmless_checkmark_of_the_student_is_not_tampering(tmp_path, hidden):
    nbs = solved()
    nbs[NB01].cells.insert(3, nbformat.v4.new_code_cell('print("✔ data loaded, 2 images")'))
    report = grade(write_submission(tmp_path, nbs), hidden)
    assert report["total"] == 54, [(g["name"], g["status"], g["feedback"][:1]) for g in report["exercises"]]


def test_reference_imported_in_a_helper_cell_gets_nothing(tmp_path, hidden):
    nbs = solved(bodies={"eight_point": "return ref_eight_point(x1, x2)"})
    nbs[NB01].cells.insert(2, nbformat.v4.new_code_cell("from course_lib.sfm.fundamental import eight_point as ref_eight_point"))
    report = grade(write_submission(tmp_path, nbs), hidden)
    g = by_name(report)
    assert g["eight_point"]["points"] == 0  # the reference is not in the student's sandbox
    assert any("ModuleNotFoundError" in f for f in g["eight_point"]["feedback"]), g["eight_point"]
    assert g["normalize_points"]["points"] == 9


def test_deleted_and_reordered_cells_are_reported(tmp_path, hidden):
    nbs = solved()
    nb = nbs[NB01]
    k = check_cell_index(nb, "sampson_distance")
    del nb.cells[k - 1]  # the exercise cell of sampson_distance
    nb2 = nbs[NB02]
    a = check_cell_index(nb2, "essential_from_fundamental")
    moved = nb2.cells[a - 1:a + 1]  # essential_from_fundamental's exercise and check cells, moved to the end
    del nb2.cells[a - 1:a + 1]
    nb2.cells += moved
    report = grade(write_submission(tmp_path, nbs), hidden)
    g = by_name(report)
    assert g["sampson_distance"]["status"] == "deleted" and g["sampson_distance"]["points"] == 0
    assert g["essential_from_fundamental"]["status"] == "reordered" and g["essential_from_fundamental"]["points"] == 0
    assert "reordered" in g["essential_from_fundamental"]["feedback"][0]
    assert g["normalize_points"]["points"] == 9 and g["pose_candidates"]["points"] == 9


def test_missing_notebook_and_cli_reports(tmp_path, hidden, monkeypatch):
    from course_lib.__main__ import main
    from course_lib.instructor import grade_plan

    write_submission(tmp_path / "sub", {NB01: released(NB01)})
    monkeypatch.setattr(grade_plan, "prepare_hidden", lambda *a, **k: hidden)
    rc = main(["grade", str(tmp_path / "sub"), "--notebooks", "01", "02", "--no-nbval", "--json",
               str(tmp_path / "r.json"), "--markdown", str(tmp_path / "f.md")])
    assert rc == 0
    report = json.loads((tmp_path / "r.json").read_text())
    assert set(report) >= {"total", "max", "exercises", "notebooks", "hidden_seed"}
    for g in report["exercises"]:
        assert set(g) >= {"notebook", "name", "points", "max_points", "feedback"}
    assert all(g["status"] == "missing" for g in report["exercises"] if g["notebook"] == NB02)
    assert "# Grading feedback" in (tmp_path / "f.md").read_text()


def test_ci_template_grades_from_the_instructors_repository_and_no_token_reaches_student_code():
    """Issue 18, item 9: the job that runs the grader (the students' code) holds no secret and can only read; the
    jobs that hold tokens run nothing of a submission; nothing is triggered by a push to a student's repository."""
    yaml = pytest.importorskip("yaml")  # installed with jupyterlab (jupyter_events)

    from course_lib.paths import REPO_ROOT

    text = (REPO_ROOT / "templates" / "github-actions-grade.yml").read_text()
    wf = yaml.safe_load(text)
    on = wf[True] if True in wf else wf["on"]  # YAML 1.1 reads the key `on` as True
    assert "push" not in on and "pull_request" not in on and "pull_request_target" not in on
    assert {"schedule", "workflow_dispatch", "repository_dispatch"} <= set(on)
    assert wf["permissions"] == {}
    jobs = wf["jobs"]
    grade = jobs["grade"]
    run = "\n".join(s.get("run", "") for s in grade["steps"])
    assert "python -m course_lib grade-class" in run and "--reports" in run  # run: tests/instructor/test_template.py
    assert "secrets." not in yaml.safe_dump(grade), "the job that runs the students' code must reference no secret"
    assert grade["permissions"] == {"contents": "read"}
    assert all(s["with"].get("persist-credentials") is False for s in grade["steps"]
               if s.get("uses", "").startswith("actions/checkout"))
    for name, job in jobs.items():
        if "secrets." in yaml.safe_dump(job):
            steps = "\n".join(s.get("run", "") for s in job["steps"])
            assert "course_lib" not in steps and "pip install" not in steps and "python" not in steps, name
    assert any(s.get("uses", "").startswith("actions/upload-artifact") for s in grade["steps"])


def test_hidden_cases_on_disk_cannot_be_rewritten_by_a_notebook(tmp_path, hidden):
    """The hidden runs read the cases from the grader's memory: a notebook that rewrites the files gains nothing."""
    path = hidden.fixtures_dir / "fundamental.npz"
    saved = path.read_bytes()
    try:
        path.write_bytes(b"rewritten by a notebook")
        report = grade(write_submission(tmp_path, solved()), hidden)
        assert report["total"] == 54, [(g["name"], g["feedback"]) for g in report["exercises"]]
    finally:
        path.write_bytes(saved)


@pytest.mark.skipif(not os.environ.get("GRADE_SLOW_TESTS"), reason="about a minute; set GRADE_SLOW_TESTS=1")
def test_a_looping_exercise_under_nbval_does_not_cost_the_cells_after_it(tmp_path, hidden):
    nbs = solved(bodies={"essential_from_fundamental": "while True:\n    pass"})
    report = grade_submission(write_submission(tmp_path, nbs), notebooks=["02"], hidden=hidden, timeout=8.0,
                              run_nbval=True, cell_timeout=10)
    g = by_name(report)
    assert g["essential_from_fundamental"]["status"] == "timeout" and g["essential_from_fundamental"]["nbval"] == "fail"
    assert g["pose_candidates"]["points"] == 10 and g["pose_candidates"]["nbval"] == "pass", g["pose_candidates"]


#: Every kind of invisible or reordering character a student's text may carry (issue 40, item 6).
HIDDEN_CHARS = ("\x00\x07\x1b\x7f\x85\x9f\u00ad\u061c\u180e\u200b\u200d\u200e\u202a\u202e\u2028\u2029\u2060\u2066"
                "\u2069\u206a\u206f\ufeff\ufe0f\ufff9\ufffb\ue000\U000f0000\U000e0000\U000e0001\U000e0041\U000e007f"
                "\U000e0100\U0010ffff\ud800")


def test_feedback_and_report_are_plain_data():
    """Controls, format characters (bidi, zero-width, soft hyphen, U+061C, U+206A-F, U+FFF9-B, tag characters),
    private use, surrogates and variation selectors are escaped in the report and the feedback, wherever they are."""
    import json
    import unicodedata

    from course_lib.instructor.grade import plain_data, plain_text

    text = "x" + "y".join(HIDDEN_CHARS) + "\x1b[31mred"
    report = {"total": 0, "max": 10, "hidden_seed": 1, "seconds": 1.0, "notebooks": [{"notebook": "n" + text,
              "points": 0, "max_points": 10}], "submission": {"left out": [text]},
              "exercises": [{"notebook": "n" + text, "name": "f" + text, "points": 0, "max_points": 10,
                             "status": "zero" + text, "feedback": [text] * 3, "nbval": text, "hidden": {}}]}
    for out in (json.dumps(plain_data(report), ensure_ascii=False), to_markdown(report)):
        shown = {c for c in out if unicodedata.category(c) in ("Cc", "Cf", "Cs", "Co", "Cn", "Zl", "Zp")
                 or 0xfe00 <= ord(c) <= 0xfe0f or ord(c) >= 0xe0000} - {"\n"}
        assert not shown, sorted(map(hex, map(ord, shown)))
        assert "[31m" not in out and "\\u202e" in out and "\\U000e0041" in out
    assert plain_text("plain ✓ é 日本 text\n\t") == "plain ✓ é 日本 text\n\t"


def test_package_installs_are_left_out_with_a_neutral_note():
    """An honest ``!pip install numpy`` is no offence: the notebook nbval runs has ``pass`` in its place (still valid
    Python where it was indented), and the note says it costs nothing; other shell lines stay."""
    import ast

    from IPython.core.inputtransformer2 import TransformerManager

    from course_lib.instructor.placement import without_installs

    cells = ["!pip install numpy\nx = 1", "if True:\n    %pip install -q scipy", "!python -m pip install torch", "!ls"]
    nb, notes = without_installs(nbformat.v4.new_notebook(cells=[nbformat.v4.new_code_cell(c) for c in cells]))
    assert nb.cells[0].source == "pass  # left out by the grader: !pip install numpy\nx = 1"
    assert nb.cells[1].source.startswith("if True:\n    pass  # left out by the grader")
    assert nb.cells[3].source == "!ls"
    assert [c for c, _ in notes] == [0, 1, 2] and all("this costs nothing" in t for _, t in notes), notes
    for cell in nb.cells:
        ast.parse(TransformerManager().transform_cell(cell.source))

"""Issue 14: an adversarial student's submissions, built here, and the points each must get.

Every attack targets ``eight_point`` of notebook 01 (the issue's own run) and is graded with the
hidden checks only (nbval is covered by tests/instructor/test_grade.py). The attacks that reach the
interpreter through an allowed module (``numpy.testing._private.utils.sys``) pass the static scans
on purpose: what stops them is the separation (the student's code runs in a process that holds
only the student release of ``course_lib``, sees neither the instructor's kit nor the hidden
cases, and can write only its own temporary folder). For the stealth route the test first shows
that the same code earns full marks when it runs with the instructor's library, so the attack is
real. ``test_attack_table`` prints the table (``pytest -s``).
"""

from __future__ import annotations

import ast
import json
import textwrap
from pathlib import Path

import nbformat
import pytest

from course_lib.instructor.grade import grade_submission, prepare_hidden
from course_lib.instructor.notebooks import NOTEBOOKS_DIR, kit_specs
from course_lib.instructor.release import stub_notebook
from course_lib.paths import REPO_ROOT

NB01 = "01_fundamental_matrix.ipynb"
SEED = 14
SYS = 'np.testing._private.utils.sys.modules'  # the route to the interpreter through an allowed module

HONEST = """
    a, T1 = normalize_points(x1)
    b, T2 = normalize_points(x2)
    A = np.stack([b[:, 0] * a[:, 0], b[:, 0] * a[:, 1], b[:, 0], b[:, 1] * a[:, 0], b[:, 1] * a[:, 1],
                  b[:, 1], a[:, 0], a[:, 1], np.ones(len(a))], axis=1)
    F = np.linalg.svd(A)[2][-1].reshape(3, 3)
    U, s, Vt = np.linalg.svd(F)
    F = T2.T @ (U @ np.diag([s[0], s[1], 0.0]) @ Vt) @ T1
    F = F / np.linalg.norm(F)
    return F if F.flat[np.argmax(np.abs(F))] > 0 else -F
"""
NORMALIZE = """
    c = x.mean(axis=0)
    s = np.sqrt(2.0) / np.linalg.norm(x - c, axis=1).mean()
    T = np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])
    return (x - c) * s, T
"""

STEALTH = f"""
    imp = {SYS}["importlib"]
    ref = imp.import_module("course_lib.sfm." + "fundamen" + "tal")
    F = ref._eight_point_core(x1, x2)
    F = F / np.linalg.norm(F)
    return F if F.flat[np.argmax(np.abs(F))] > 0 else -F
"""
OS_EXIT = f"""
    {SYS}["os"]._exit(0)
"""
READ_REFERENCE = f"""
    src = {SYS}["builtins"].open({str(REPO_ROOT / "course_lib" / "sfm" / "fundamental.py")!r}).read()
    ns = {{"__name__": "stolen"}}
    {SYS}["builtins"].exec(src, ns)
    return ns["eight_point"](x1, x2)
"""
LOOP = """
    while True:
        pass
"""
EYE = """
    return np.eye(3)
"""


def write_outside(target: Path) -> str:
    return f"""
    with {SYS}["builtins"].open({str(target)!r}, "w") as f:
        f.write("overwritten by a student")
""" + HONEST


def released():
    return stub_notebook(nbformat.read(NOTEBOOKS_DIR / NB01, as_version=4), NB01)


def fill(nb, name: str, body: str):
    for cell in nb.cells:
        if cell.cell_type == "code" and f"def {name}(" in cell.source and "YOUR CODE HERE" in cell.source:
            lines = cell.source.splitlines()
            k = next(i for i, ln in enumerate(lines) if ln.strip() == "# YOUR CODE HERE")
            indent = lines[k][: len(lines[k]) - len(lines[k].lstrip())]
            code = textwrap.indent(textwrap.dedent(body).strip("\n"), indent).splitlines()
            cell.source = "\n".join(lines[:k] + code + lines[k + 2:])
            return nb
    raise AssertionError(f"no stub of {name}")


def submission(root: Path, eight_point: str | None, extra_cell: str | None = None) -> Path:
    nb = fill(released(), "normalize_points", NORMALIZE)
    if eight_point is not None:
        fill(nb, "eight_point", eight_point)
    if extra_cell:
        nb.cells.insert(3, nbformat.v4.new_code_cell(extra_cell))
    (root / "notebooks").mkdir(parents=True, exist_ok=True)
    nbformat.write(nb, root / "notebooks" / NB01)
    return root


@pytest.fixture(scope="module")
def hidden(tmp_path_factory):
    return prepare_hidden(kit_specs(NOTEBOOKS_DIR, only=["01"]), SEED, tmp_path_factory.mktemp("hidden14"))


def grade_eight_point(path: Path, hidden, timeout: float = 20.0) -> dict:
    report = grade_submission(path, notebooks=["01"], exercises=["eight_point"], hidden=hidden, timeout=timeout,
                              run_nbval=False)
    (g,) = report["exercises"]
    return dict(g, seconds_total=report["seconds"], isolation=report.get("isolation", {}))


def test_the_stealth_route_would_work_without_the_separation(hidden):
    """Run as the grader used to (student code in a process with the instructor's library): full marks."""
    from course_lib.checks import core
    from course_lib.instructor.hidden import run_check

    import numpy as np

    code = "import numpy as np\n\ndef eight_point(x1, x2):\n" + textwrap.indent(textwrap.dedent(STEALTH), "    ")
    ns: dict = {}
    exec(compile(code, "<attack>", "exec"), ns)  # noqa: S102 - the attack, in the test's own process
    result, _ = run_check("course_lib.checks.fundamental", "check_eight_point", str(hidden.fixtures_dir),
                          ns["eight_point"])
    assert result is not None and core.score(result) == 1.0 and np is not None
    from course_lib.instructor.scan import scan_exercise

    assert scan_exercise(ast.parse(code), "course_lib.sfm.fundamental:eight_point",
                         {"course_lib.sfm.fundamental"}) == [], "the stealth route passes the static scans"


def test_stealth_route_gets_nothing(tmp_path, hidden):
    g = grade_eight_point(submission(tmp_path, STEALTH), hidden)
    assert g["points"] == 0 and g["status"] == "zero", g
    assert any("ModuleNotFoundError" in f and "course_lib.sfm.fundamental" in f for f in g["feedback"]), g["feedback"]


def test_os_exit_is_named_and_costs_only_itself(tmp_path, hidden):
    g = grade_eight_point(submission(tmp_path, OS_EXIT), hidden)
    assert g["points"] == 0 and g["status"] == "exit", g
    assert any("your function ended the process with os._exit(0)" in f for f in g["feedback"]), g["feedback"]
    assert g["hidden"]["seconds"] < 10


def test_reading_the_reference_source_finds_nothing(tmp_path, hidden):
    assert (REPO_ROOT / "course_lib" / "sfm" / "fundamental.py").exists()
    g = grade_eight_point(submission(tmp_path, READ_REFERENCE), hidden)
    assert g["points"] == 0, g
    if g["isolation"].get("hidden checks", {}).get("namespaces"):
        assert any("FileNotFoundError" in f for f in g["feedback"]), g["feedback"]


def test_writing_outside_the_temporary_folder_fails(tmp_path, hidden):
    targets = [tmp_path / "outside.txt", REPO_ROOT / "data" / "fixtures" / "fundamental.npz"]
    before = [t.read_bytes() if t.exists() else None for t in targets]
    (tmp_path / "outside.txt").write_text("original")
    before[0] = b"original"
    for k, target in enumerate(targets):
        g = grade_eight_point(submission(tmp_path / f"sub{k}", write_outside(target)), hidden)
        assert target.read_bytes() == before[k], f"{target} was changed by the student's code"
        assert g["points"] == 0, g
        if g["isolation"].get("hidden checks", {}).get("read_only"):
            assert any("Read-only file system" in f or "No such file" in f for f in g["feedback"]), g["feedback"]


def test_looping_exercise_is_stopped_at_its_own_limit(tmp_path, hidden):
    g = grade_eight_point(submission(tmp_path, LOOP), hidden, timeout=6.0)
    assert g["points"] == 0 and g["status"] == "timeout", g
    assert any("stopped after 6 s" in f for f in g["feedback"]), g["feedback"]
    assert g["hidden"]["seconds"] < 6.0 + 5


def test_shape_alone_earns_nothing(tmp_path, hidden):
    g = grade_eight_point(submission(tmp_path, EYE), hidden)
    assert g["points"] == 0, g


def test_rebinding_a_check_by_import_alias_is_flagged_like_an_assignment(tmp_path, hidden):
    for k, cell in enumerate(["from pprint import pprint as check_eight_point",
                              "check_eight_point = print",
                              "import pprint as check_eight_point",
                              "for check_eight_point in [print]:\n    pass",
                              "with open('x', 'w') as check_eight_point:\n    pass"]):
        report = grade_submission(submission(tmp_path / f"s{k}", HONEST, extra_cell=cell), notebooks=["01"],
                                  exercises=["eight_point"], hidden=hidden, run_nbval=False)
        (g,) = report["exercises"]
        assert g["points"] == 0 and g["status"] == "tampered", (cell, g)
        assert "rebinds check_eight_point" in g["feedback"][0], (cell, g["feedback"])


def test_honest_gets_full_hidden_marks_and_the_untouched_release_zero(tmp_path, hidden):
    g = grade_eight_point(submission(tmp_path / "honest", HONEST), hidden)
    assert g["status"] == "full" and g["points"] == 9, g  # 90 %: nbval is not run here
    iso = g["isolation"]["hidden checks"]
    assert "namespaces" in iso
    g0 = grade_eight_point(submission(tmp_path / "release", None), hidden)
    assert g0["points"] == 0 and any("not implemented yet" in f for f in g0["feedback"]), g0


def test_attack_table(tmp_path, hidden, capsys):
    """Every attack with its points and the first lines of its feedback (printed with ``pytest -s``)."""
    (tmp_path / "outside.txt").write_text("original")
    attacks = [
        ("honest eight_point", HONEST, None),
        ("untouched release", None, None),
        ("stealth route: importlib via numpy.testing..sys -> _eight_point_core", STEALTH, None),
        ("os._exit via the same route", OS_EXIT, None),
        ("sys.exit() via the same route", f"\n    {SYS}['sys'].exit(0)\n", None),
        ("builtins.open + exec of the reference source", READ_REFERENCE, None),
        ("write outside the temporary folder", write_outside(tmp_path / "outside.txt"), None),
        ("looping exercise (limit 6 s)", LOOP, None),
        ("return np.eye(3)", EYE, None),
        ("import alias rebinding a check", HONEST, "from pprint import pprint as check_eight_point"),
        ("assignment rebinding a check", HONEST, "check_eight_point = print"),
    ]
    rows = []
    for k, (what, body, cell) in enumerate(attacks):
        sub = submission(tmp_path / f"a{k}", body, extra_cell=cell)
        report = grade_submission(sub, notebooks=["01"], exercises=["eight_point"], hidden=hidden,
                                  timeout=6.0 if "loop" in what else 20.0, run_nbval=False)
        (g,) = report["exercises"]
        rows.append((what, g["points"], g["max_points"], g["status"], " / ".join(g["feedback"][:2])[:230],
                     report["seconds"]))
    with capsys.disabled():
        print("\n| attack | points | status | feedback | s |\n|---|---:|---|---|---:|")
        for what, pts, mx, status, fb, sec in rows:
            print(f"| {what} | {pts:g} / {mx:g} | {status} | {fb} | {sec:g} |")
    assert rows[0][1] == 9 and all(r[1] == 0 for r in rows[1:]), json.dumps(rows, indent=1, ensure_ascii=False)

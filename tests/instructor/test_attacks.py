"""Issue 14: an adversarial student's submissions, built here, and the points each must get.

Every attack targets ``eight_point`` of notebook 01 (the issue's own run) and is graded with the
hidden checks only (nbval is covered by tests/instructor/test_grade.py). Many reach the interpreter
through an allowed module (``numpy.testing._private.utils.sys``): what stops them is the separation
(the student's code runs in a process that holds only the student release of ``course_lib``, sees
neither the instructor's kit nor the hidden cases, and can write only its own temporary folder). For the stealth route the test first shows
that the same code earns full marks when it runs with the instructor's library, so the attack is
real. ``test_attack_table`` prints the table (``pytest -s`` or ``ATTACK_TABLE=1``).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import resource
import textwrap
import time
from pathlib import Path

import nbformat
import pytest

from course_lib.instructor.grade import grade_submission, prepare_hidden, to_markdown
from course_lib.instructor.notebooks import NOTEBOOKS_DIR, kit_specs
from course_lib.instructor.release import stub_notebook
from course_lib.instructor.settings import Limits
from course_lib.paths import REPO_ROOT

#: Minutes, not seconds: left out of the quick subset (pytest -m "not slow").
pytestmark = pytest.mark.slow

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
    F, ok = ref.eight_point_batch(x1[None], x2[None])
    return F[0]
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


#: Every test of this file: its wall time, the grader's peak RSS after it (this process: the grader runs here) and
#: the largest peak of a process it waited for (workers, sandboxes); printed by the last test (``ATTACK_TABLE=1``).
MEASURED: list[tuple] = []


@pytest.fixture(autouse=True)
def measured(request):
    t0, before = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    yield
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    MEASURED.append((request.node.name, f"{time.perf_counter() - t0:.1f}", f"{peak:.0f} (+{peak - before:.0f})",
                     f"{children:.0f}"))


#: What :func:`grade_eight_point` gave each notebook 01 (its bytes) with each budget: the attack table reuses the
#: gradings of the tests before it (the same notebook, the same hidden cases) and grades only what they did not.
GRADED: dict[tuple[bytes, float], dict] = {}


def grade_eight_point(path: Path, hidden, timeout: float = 20.0) -> dict:
    key = ((path / "notebooks" / NB01).read_bytes(), timeout)
    if key not in GRADED:
        report = grade_submission(path, notebooks=["01"], exercises=["eight_point"], hidden=hidden, timeout=timeout,
                                  run_nbval=False)
        (g,) = report["exercises"]
        GRADED[key] = dict(g, seconds_total=report["seconds"], isolation=report.get("isolation", {}))
    return GRADED[key]


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


def test_stealth_route_gets_nothing(tmp_path, hidden):
    g = grade_eight_point(submission(tmp_path, STEALTH), hidden)
    assert g["points"] == 0 and g["status"] == "zero", g
    assert any("ModuleNotFoundError" in f and "course_lib.sfm.fundamental" in f for f in g["feedback"]), g["feedback"]


def test_os_exit_is_named_and_costs_only_itself(tmp_path, hidden):
    g = grade_eight_point(submission(tmp_path, OS_EXIT), hidden)
    assert g["points"] == 0 and g["status"] == "exit", g
    assert any("your function ended the process with os._exit(0)" in f for f in g["feedback"]), g["feedback"]


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
    assert any("stopped after" in f for f in g["feedback"]), g["feedback"]  # at its budget (6 s, or 10x the reference's + 5 s)


def test_shape_alone_earns_nothing(tmp_path, hidden):
    g = grade_eight_point(submission(tmp_path, EYE), hidden)
    assert g["points"] == 0, g


def test_rebinding_a_check_in_the_notebook_is_no_offence_and_changes_nothing(tmp_path, hidden):
    """The hidden checks run in the grader on the exercise's code alone: checks rebound in other cells (by assignment,
    import alias, loop or ``with`` target) neither cost nor earn anything (the nbval share: test_40 below)."""
    cells = ["from pprint import pprint as check_eight_point", "check_eight_point = print",
             "import pprint as check_eight_point", "for check_eight_point in [print]:\n    pass",
             "with open('x', 'w') as check_eight_point:\n    pass"]
    for body, points in ((HONEST, 9), (EYE, 0)):
        report = grade_submission(with_cells(tmp_path / f"s{points}", body, cells), notebooks=["01"],
                                  exercises=["eight_point"], hidden=hidden, run_nbval=False)
        (g,) = report["exercises"]
        assert g["points"] == points and g["status"] in ("full", "zero"), g


def test_honest_gets_full_hidden_marks_and_the_untouched_release_zero(tmp_path, hidden):
    g = grade_eight_point(submission(tmp_path / "honest", HONEST), hidden)
    assert g["status"] == "full" and g["points"] == 9, g  # 90 %: nbval is not run here
    iso = g["isolation"]["hidden checks"]
    assert "namespaces" in iso
    g0 = grade_eight_point(submission(tmp_path / "release", None), hidden)
    assert g0["points"] == 0 and g0["status"] == "not attempted" and len(g0["feedback"]) == 1, g0


def test_attack_table(tmp_path, hidden, capsys, request):
    """Every attack with its points and the first lines of its feedback (printed with ``pytest -s`` or
    ``ATTACK_TABLE=1``); the attacks that the tests above graded are not graded again (:data:`GRADED`)."""
    (tmp_path / "outside.txt").write_text("original")
    attacks = [
        ("honest eight_point", HONEST, None),
        ("untouched release", None, None),
        ("stealth route: importlib via numpy.testing..sys -> eight_point_batch", STEALTH, None),
        ("os._exit via the same route", OS_EXIT, None),
        ("sys.exit() via the same route", f"\n    {SYS}['sys'].exit(0)\n", None),
        ("builtins.open + exec of the reference source", READ_REFERENCE, None),
        ("write outside the temporary folder", write_outside(tmp_path / "outside.txt"), None),
        ("looping exercise (limit 6 s)", LOOP, None),
        ("return np.eye(3)", EYE, None),
    ]
    rows = []
    for k, (what, body, cell) in enumerate(attacks):
        g = grade_eight_point(submission(tmp_path / f"a{k}", body, extra_cell=cell), hidden,
                              timeout=6.0 if "loop" in what else 20.0)
        rows.append((what, g["points"], g["max_points"], g["status"], " / ".join(g["feedback"][:2])[:230],
                     g["seconds_total"]))
    with capsys.disabled():
        show_table(request, "Issue 14", ["attack", "points", "status", "feedback", "s"],
                   [(what, f"{pts:g} / {mx:g}", status, fb, f"{sec:g}") for what, pts, mx, status, fb, sec in rows])
    assert rows[0][1] == 9 and all(r[1] == 0 for r in rows[1:]), json.dumps(rows, indent=1, ensure_ascii=False)


# =============================================================================================
# Issue 18 (items 1, 2, 7): the submission is data, the student's process sees an allow-list, the grader cannot be hurt
# =============================================================================================
#
# Each attack is graded next to folders that are not the submission: another student's submission
# (with a solved notebook 01 that would earn marks), a home folder with a secret, and the kit's
# notebooks. Every test asserts the attack's points, and that nothing outside the submission was
# written or deleted (a snapshot of those folders) or read (the secret and the other student's code
# appear nowhere in the report, and reading them fails).

SECRET = "secret-of-another-folder-7f3a"


def snapshot(*folders: Path) -> dict:
    """Every file under ``folders``: its content's hash and modification time (links: their target)."""
    out = {}
    for folder in folders:
        for dirpath, dirnames, filenames in os.walk(folder, followlinks=False):
            for name in dirnames + filenames:
                p = Path(dirpath) / name
                if p.is_symlink():
                    out[str(p)] = ("link", os.readlink(p))
                elif p.is_file():
                    out[str(p)] = (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
                else:
                    out[str(p)] = ("dir",)
    return out


@pytest.fixture()
def outside(tmp_path):
    """Folders beside the submission: another student's solved submission, a home folder with a secret."""
    other = submission(tmp_path / "other-student", HONEST)
    (other / "notebooks" / "solution_notes.txt").write_text(SECRET)
    home = tmp_path / "home"
    home.mkdir()
    (home / "secret.txt").write_text(SECRET)
    folders = [other, home, NOTEBOOKS_DIR]
    before = snapshot(*folders)
    yield {"other": other, "home": home, "secret": home / "secret.txt", "folders": folders}
    assert snapshot(*folders) == before, "a folder outside the submission was written or deleted"


def unharmed(report: dict) -> None:
    """The secret and the other student's notes appear nowhere in what the grader wrote."""
    text = json.dumps(report, ensure_ascii=False) + to_markdown(report)
    assert SECRET not in text, "a file outside the submission reached the report"


def grade01(path: Path, hidden, **kw) -> dict:
    kw.setdefault("run_nbval", False)
    return grade_submission(path, notebooks=["01"], exercises=kw.pop("exercises", ["eight_point"]), hidden=hidden,
                            timeout=kw.pop("timeout", 20.0), **kw)


def test_symlinked_notebooks_folder_is_not_followed_out_of_the_submission(tmp_path, hidden, outside):
    """Class 1: ``notebooks`` (or one notebook) links to another student's work: not graded, and nbval's preparation
    deletes nothing there (it used to unlink every notebook of the linked folder)."""
    folder_link = tmp_path / "sub-folder-link"  # its own (untouched) notebook at the top, ``notebooks`` a link
    folder_link.mkdir()
    nbformat.write(released(), folder_link / NB01)
    (folder_link / "notebooks").symlink_to(outside["other"] / "notebooks")
    file_link = tmp_path / "sub-file-link"
    (file_link / "notebooks").mkdir(parents=True)
    (file_link / "notebooks" / NB01).symlink_to(outside["other"] / "notebooks" / NB01)
    for sub, nbval in ((folder_link, True), (file_link, False)):
        report = grade01(sub, hidden, run_nbval=nbval, exercises=["normalize_points", "eight_point"])
        unharmed(report)
        assert report["total"] == 0, report["exercises"]
        assert any("outside the submission" in r for r in report["submission"]["left out"]), report["submission"]
    assert all(g["status"] == "missing" and "outside the submission" in g["feedback"][0]
               for g in report["exercises"]), report["exercises"]


def test_a_link_inside_the_submission_is_copied_as_a_file(tmp_path, hidden):
    """An honest layout with links that stay inside the submission is graded as if the files were there."""
    sub = submission(tmp_path / "honest", HONEST)
    (sub / "work").mkdir()
    (sub / "notebooks" / NB01).rename(sub / "work" / NB01)
    (sub / "notebooks" / NB01).symlink_to(Path("..") / "work" / NB01)
    os.mkfifo(sub / "notebooks" / "pipe.ipynb")  # a FIFO would block a grader that reads it
    report = grade01(sub, hidden)
    (g,) = report["exercises"]
    assert g["points"] == 9 and g["status"] == "full", g
    assert any("pipe.ipynb" in r and "not a regular file" in r for r in report["submission"]["left out"])


def read_attack(path_expr: str) -> str:
    """Exercise code that reads a file outside the submission and earns full marks if it can."""
    return f"""
    stolen = {SYS}["builtins"].open({path_expr}).read()
    assert stolen
""" + HONEST


def test_the_student_process_cannot_read_other_submissions_or_home_folders(tmp_path, hidden, outside):
    """Class 2: another submission's notebook, a home folder, the grader's own home and /proc of the grader."""
    targets = [repr(str(outside["other"] / "notebooks" / NB01)), repr(str(outside["secret"])),
               repr(str(Path.home() / ".bashrc")) if (Path.home() / ".bashrc").exists() else repr("/etc/shadow"),
               f"'/proc/{os.getpid()}/environ'"]
    for k, target in enumerate(targets):
        report = grade01(submission(tmp_path / f"s{k}", read_attack(target)), hidden)
        unharmed(report)
        (g,) = report["exercises"]
        assert g["points"] == 0, (target, g)
        box = report["isolation"]["hidden checks"]
        if box.get("read_only"):
            assert any("FileNotFoundError" in f or "PermissionError" in f for f in g["feedback"]), (target, g)


def test_exception_text_carries_no_file_from_outside(tmp_path, hidden, outside):
    """Class 2: a file's content in an exception message would reach the feedback; the file is not in view."""
    body = f"""
    raise ValueError({SYS}["builtins"].open({str(outside['secret'])!r}).read())
"""
    report = grade01(submission(tmp_path / "s", body), hidden)
    unharmed(report)
    (g,) = report["exercises"]
    assert g["points"] == 0 and any("FileNotFoundError" in f for f in g["feedback"]), g


def write_frames(payload: str) -> str:
    """Exercise code that writes ``payload`` (bytes) straight into every pipe it holds (the reply pipe among them)."""
    return f"""
    os = {SYS}["os"]
    st = {SYS}["stat"]
    data = {payload}
    for name in os.listdir("/proc/self/fd"):
        fd = int(name)
        try:
            if st.S_ISFIFO(os.fstat(fd).st_mode):
                for k in range(0, len(data), 1 << 16):
                    os.write(fd, data[k:k + (1 << 16)])
        except OSError:
            pass
    return np.eye(3)
"""


def test_forged_and_giant_reply_frames_cost_only_that_exercise(tmp_path, hidden, outside):
    """Class 7: a frame that claims 2 GiB (written in pieces), one just under the reply limit full of garbage, a
    forged frame whose array is a zip archive, and deep JSON: each ends that exercise; the grader's memory stays
    flat and the other exercise (normalize_points) is still graded."""
    from course_lib.instructor.sandbox.wire import MAX_REPLY

    zip_frame = ("b'\\x50\\x4b\\x03\\x04' + b'\\x00' * 64")
    payloads = {
        "claims 2 GiB": "(2**31 - 9).to_bytes(8, 'little') + b'x' * (1 << 20)",
        "just under the limit": f"({MAX_REPLY - 8}).to_bytes(8, 'little') + b'\\x00' * {MAX_REPLY - 8}",
        "zip archive": ("(lambda h: (8 + len(h) + 8 + 68).to_bytes(8, 'little') + len(h).to_bytes(4, 'little') + "
                        "(1).to_bytes(4, 'little') + h + (68).to_bytes(8, 'little') + " + zip_frame + ")"
                        "(b'{\"ok\": true, \"value\": {\"$\": \"nd\", \"a\": 0}, \"callbacks\": null}')"),
        "deep JSON": ("(lambda h: (8 + len(h)).to_bytes(8, 'little') + len(h).to_bytes(4, 'little') + "
                      "(0).to_bytes(4, 'little') + h)(b'[' * 100000 + b']' * 100000)"),
    }
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    for k, (what, payload) in enumerate(payloads.items()):
        report = grade01(submission(tmp_path / f"s{k}", write_frames(payload)), hidden,
                         exercises=["normalize_points", "eight_point"])
        unharmed(report)
        g = {x["name"]: x for x in report["exercises"]}
        assert g["eight_point"]["points"] == 0, (what, g["eight_point"])
        assert g["normalize_points"]["points"] == 9, (what, g["normalize_points"])
    grown = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak) << 10
    assert grown < 400 << 20, f"the grader grew by {grown >> 20} MiB"


def test_deep_attribute_chains_and_nesting_do_not_end_the_grading(tmp_path, hidden, outside):
    """Class 7: a cell with a 100 000-deep attribute chain, and an exercise nested too deeply to parse."""
    sub = submission(tmp_path / "chain", HONEST, extra_cell="x = np" + ".T" * 100_000)
    report = grade01(sub, hidden)
    unharmed(report)
    (g,) = report["exercises"]
    assert g["points"] == 9, g  # the chain is in a cell of its own: the exercise is graded
    deep = HONEST.replace("    return F if", "    y = x1" + ".T" * 100_000 + "\n    return F if")
    report = grade01(submission(tmp_path / "deep", deep), hidden, exercises=["normalize_points", "eight_point"])
    unharmed(report)
    g = {x["name"]: x for x in report["exercises"]}
    assert g["eight_point"]["points"] == 0 and g["normalize_points"]["points"] == 9, g


SMALL = Limits(processes=64, processes_total=64, memory_total_bytes=768 << 20, disk_bytes=64 << 20)


def test_fork_bombs_memory_and_disk_are_bounded_for_the_whole_tree(tmp_path, hidden, outside):
    """Class 7: totals for the process tree (processes, memory of four processes, disk of many files), not per
    process; the grader survives each, nothing outside is written, and nothing of the student is left running."""
    fork_bomb = f"""
    os = {SYS}["os"]
    kids = 0
    try:
        while kids < 3000:
            if os.fork() == 0:
                {SYS}["time"].sleep(60)
                os._exit(0)
            kids += 1
    except OSError:
        pass
    raise RuntimeError(f"started {{kids}} processes")
"""
    memory = f"""
    os = {SYS}["os"]
    kids = [pid for pid in (os.fork() for _ in range(3)) if pid]
    block = np.ones(300 << 17)  # 300 MiB in each of the four processes
    {SYS}["time"].sleep(3)
    if len(kids) < 3:
        os._exit(0)
    codes = [os.waitstatus_to_exitcode(os.waitpid(k, 0)[1]) for k in kids]
    raise RuntimeError(f"exit codes of the three others: {{codes}} ({{block[0]}})")
"""
    disk = f"""
    written = 0
    try:
        for k in range(100):
            with {SYS}["builtins"].open(f"fill{{k}}.bin", "wb") as f:
                f.write(b"x" * (16 << 20))
            written += 16 << 20
    except OSError as exc:
        raise RuntimeError(f"wrote {{written >> 20}} MiB, then {{exc}}")
    raise RuntimeError(f"wrote {{written >> 20}} MiB")
"""
    for what, body in (("fork bomb", fork_bomb), ("memory", memory), ("disk", disk)):
        report = grade01(submission(tmp_path / what.replace(" ", "-"), body), hidden, limits=SMALL)
        unharmed(report)
        (g,) = report["exercises"]
        assert g["points"] == 0, (what, g)
        box = report["isolation"]["hidden checks"]
        text = " ".join(g["feedback"])
        if what == "fork bomb" and "cgroup" in box.get("processes", ""):
            started = int(text.split("started ")[1].split()[0])
            assert started < SMALL.processes_total, text
        if what == "memory" and "cgroup" in box.get("memory", ""):
            assert "more memory than the limit" in text or "-9" in text, text
        if what == "disk" and box.get("read_only"):
            wrote = int(text.split("wrote ")[1].split()[0])
            assert wrote <= SMALL.disk_bytes >> 20 and "No space left" in text, text
    assert not orphans(), f"processes of the student still running: {orphans()}"


def orphans() -> list[str]:
    """Processes of a student's sandbox whose grader has finished (their temporary folder is gone)."""
    left = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            args = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        cfg = [a.decode() for a in args if b"course-student-" in a and a.endswith(b"config.json")]
        if cfg and not Path(cfg[0]).exists():
            left.append(pid)
    return left


def test_system_v_shared_memory_ends_with_the_sandbox(tmp_path, hidden, outside):
    """Class 7: a segment made by the student's code does not outlive grading, and the host's segments are not seen."""
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    host_key, student_key = 0x5EC0DE18, 0x5EC0DE19
    host_id = libc.shmget(host_key, 4096, 0o1600)  # IPC_CREAT | 0600
    assert host_id >= 0
    body = f"""
    ct = {SYS}["ctypes"]
    libc = ct.CDLL(None)
    made = libc.shmget({student_key}, 1 << 20, 0o1666)
    seen = libc.shmget({host_key}, 0, 0)
    raise RuntimeError(f"made {{made}}, host segment {{'seen' if seen >= 0 else 'not seen'}}")
"""
    try:
        sub = submission(tmp_path / "shm", body)
        report = grade01(sub, hidden)
        unharmed(report)
        (g,) = report["exercises"]
        assert g["points"] == 0, g
        keys = {int(line.split()[0]) for line in Path("/proc/sysvipc/shm").read_text().splitlines()[1:]}
        if report["isolation"]["hidden checks"].get("namespaces"):
            assert student_key not in keys and any("not seen" in f for f in g["feedback"]), g["feedback"]
    finally:
        libc.shmctl(host_id, 0, None)  # IPC_RMID


FORGE = """
import pytest


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    report.outcome = "passed"
    report.longrepr = None
"""


def test_conftest_pytest_ini_and_shadowing_modules_are_not_loaded_by_nbval(tmp_path, hidden, outside):
    """Class 7: a conftest.py that makes every cell pass, a pytest.ini that loads the same as a plugin, and a
    ``pytest.py`` next to the notebooks that would replace pytest: none is loaded, and the untouched release earns
    nothing."""
    sub = submission(tmp_path / "forge", None)
    nb_dir = sub / "notebooks"
    (nb_dir / "conftest.py").write_text(FORGE)
    (nb_dir / "forge.py").write_text(FORGE)
    for name in ("pytest.ini", "tox.ini"):
        (nb_dir / name).write_text("[pytest]\naddopts = -p forge\n")
    (nb_dir / "pytest.py").write_text(f"open({str(outside['home'] / 'pwned.txt')!r}, 'w').write('x')\n")
    report = grade01(sub, hidden, run_nbval=True, exercises=["normalize_points", "eight_point"])
    unharmed(report)
    assert not (outside["home"] / "pwned.txt").exists()
    g = {x["name"]: x for x in report["exercises"]}
    assert g["eight_point"]["points"] == 0 and g["eight_point"]["nbval"] != "pass", g["eight_point"]
    assert g["normalize_points"]["points"] == 10 and g["normalize_points"]["nbval"] == "pass", g["normalize_points"]


# =============================================================================================
# Issue 33: a grader that fails closed and stays bounded (the third red-team table)
# =============================================================================================
#
# Each attack is a submission built here (none copies the issue's), graded next to the folders of
# ``outside`` (snapshotted: nothing outside the submission may change). Every row asserts its points
# (0), the grader's peak memory (this process's, and the exercise worker's growth) and time.
# ``ATTACK_TABLE=1`` or ``pytest -s`` prints the table.

ROWS33: list[tuple] = []
NB05 = "05_bundle_adjustment.ipynb"


def show_table(request, title: str, head: list[str], rows: list[tuple]) -> None:
    """Print a Markdown table, only when asked (``pytest -s`` or ``ATTACK_TABLE=1``): ``pytest -q`` stays quiet."""
    if not (os.environ.get("ATTACK_TABLE") or request.config.getoption("capture") == "no"):
        return
    print(f"\n{title}\n\n| " + " | ".join(head) + " |\n|" + "---|" * len(head))
    for row in rows:
        print("| " + " | ".join(str(x) for x in row) + " |")


def filled(root: Path, nb_name: str, bodies: dict[str, str], extra_cells: list[str] = ()) -> Path:
    """A submission: the release of ``nb_name`` with ``bodies`` pasted into their stubs, and ``extra_cells`` after
    the first cell."""
    nb = stub_notebook(nbformat.read(NOTEBOOKS_DIR / nb_name, as_version=4), nb_name)
    for name, body in bodies.items():
        fill(nb, name, body)
    for k, cell in enumerate(extra_cells):
        nb.cells.insert(1 + k, nbformat.v4.new_code_cell(cell))
    (root / "notebooks").mkdir(parents=True, exist_ok=True)
    nbformat.write(nb, root / "notebooks" / nb_name)
    return root


def rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def graded_row(what: str, report: dict, name: str, rss_before: float, klass: str, rows: list | None = None) -> dict:
    """The row of one attack (and its checks: points 0, the grader's memory), in ``rows`` (default: issue 33's)."""
    g = next(x for x in report["exercises"] if x["name"] == name)
    mem = g.get("hidden", {}).get("memory", {}) or {}
    worker = (mem.get("worker peak growth bytes") or 0) / 2**20
    cgroup = (mem.get("cgroup peak bytes") or 0) / 2**20
    grown = rss_mib() - rss_before
    (ROWS33 if rows is None else rows).append((klass, what, f"{g['points']:g} / {g['max_points']:g}", g["status"], f"{report['seconds']:.1f}",
                   f"{g.get('hidden', {}).get('seconds', 0):g}", f"{rss_mib():.0f} (+{grown:.0f})", f"{worker:.0f}",
                   f"{cgroup:.0f}", _short_cell(g["feedback"][0] if g["feedback"] else "")))
    assert g["points"] == 0, (what, g)
    assert grown < 100, f"{what}: the grader grew by {grown:.0f} MiB"
    assert worker < 512, f"{what}: the exercise's worker grew by {worker:.0f} MiB"
    return g


def _short_cell(text: str) -> str:
    text = " ".join(text.split()).replace("|", "/")
    return text if len(text) < 150 else text[:147] + "..."


PROC_WALK = f"""
    os = {SYS}["os"]
    re = {SYS}["re"]
    opener = {SYS}["builtins"].open
    seen = []
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        for what in ("cwd", "root", "exe"):
            try:
                seen.append(os.readlink(f"/proc/{{pid}}/{{what}}"))
            except OSError:
                pass
        for what in ("environ", "cmdline", "mountinfo"):
            try:
                seen.append(opener(f"/proc/{{pid}}/{{what}}", "rb").read().decode(errors="replace"))
            except OSError:
                pass
    tried = set()
    for path in set(re.findall(r"/[A-Za-z0-9_.@+-][A-Za-z0-9_./@+-]*", " ".join(seen))):
        parts = path.rstrip("/").split("/")
        for k in range(len(parts), 1, -1):
            folder = "/".join(parts[:k])
            if folder in tried:
                continue
            tried.add(folder)
            try:
                src = opener(folder + "/course_lib/sfm/fundamental.py").read()
            except OSError:
                continue
            ns = {{"__name__": "stolen"}}
            {SYS}["builtins"].exec(src, ns)
            return ns["eight_point"](x1, x2)
    raise RuntimeError(f"uid {{os.getuid()}}: no reference in {{len(tried)}} folders named in /proc")
"""


def outliving(target: Path) -> str:
    """A daemon that leaves the process group and keeps rewriting ``target`` (the grader's report) for 20 s."""
    return f"""
    os = {SYS}["os"]
    if os.fork() == 0:
        os.setsid()
        if os.fork() == 0:
            for _ in range(200):
                try:
                    with {SYS}["builtins"].open({str(target)!r}, "w") as f:
                        f.write('{{"total": 10, "max": 10}}')
                except OSError:
                    pass
                {SYS}["time"].sleep(0.1)
        os._exit(0)
    {SYS}["time"].sleep(0.5)
    raise RuntimeError("a daemon was left behind")
"""


PLANT_BYTECODE = f"""
    sys = {SYS}["sys"]
    os = {SYS}["os"]
    {SYS}["builtins"].setattr(sys, "dont_write_bytecode", False)
    planted = []
    for folder in list(sys.path) + [sys.prefix, sys.base_prefix, "/"]:
        try:
            os.makedirs(folder + "/course_lib/__pycache__", exist_ok=True)
            with {SYS}["builtins"].open(folder + "/course_lib/__pycache__/core.cpython-311.pyc", "wb") as f:
                f.write(b"planted")
            planted.append(folder)
        except OSError:
            pass
    {SYS}["importlib"].import_module("course_lib.checks.core")
    raise RuntimeError(f"planted bytecode in {{planted}}")
"""

HUGE_SPARSE = """
    import scipy.sparse as sp
    return sp.coo_matrix(([1.0], ([0], [0])), shape=(2 ** 17, 2 ** 17))
"""

#: Frames written straight into the reply pipe: a module that declares 40 000 layers it sends no weights for; a
#: header of 3 MiB of nested lists; 70 000 tiny arrays in one reply.
FORGED_MODULE = ("(lambda h: (8 + len(h)).to_bytes(8, 'little') + len(h).to_bytes(4, 'little') + "
                 "(0).to_bytes(4, 'little') + h)(b'{\"ok\": true, \"value\": {\"$\": \"module\", \"h\": 1, \"n\": \"M\", "
                 "\"params\": [], \"linear\": [' + b','.join([b'[4096, 4096, true]'] * 40000) + b']}, "
                 "\"callbacks\": null}')")
FLOOD_HEADER = ("(lambda h: (8 + len(h)).to_bytes(8, 'little') + len(h).to_bytes(4, 'little') + "
                "(0).to_bytes(4, 'little') + h)(b'{\"ok\": true, \"value\": ' + b'[' + b'[0,0,0,0],' * 300000 + "
                "b'0], \"callbacks\": null}')")


def many_arrays() -> str:
    """70 000 one-byte ``.npy`` records in one reply (more than the array count a reply may hold)."""
    return ("(lambda rec, n, h: (8 + len(h) + n * (8 + len(rec))).to_bytes(8, 'little') + len(h).to_bytes(4, 'little')"
            " + n.to_bytes(4, 'little') + h + (len(rec).to_bytes(8, 'little') + rec) * n)"
            "((lambda b: (b.seek(0), b.read())[1])((lambda b: (np.save(b, np.zeros(1, np.uint8)), b)[1])"
            f"({SYS}['io'].BytesIO())), 70000, b'{{\"ok\": true, \"value\": {{\"$\": \"nd\", \"a\": 0}}, "
            "\"callbacks\": null}')")


STALL_ORACLE = """
    a, b = np.random.default_rng(0).normal(size=(2, 1_500_000, 2))
    for _ in range(10 ** 6):  # the reference answers eight_point for it, on this exercise's clock
        eight_point(a, b)
    return None
"""

FAKE_TOTAL = ("\\n\\n**Total: 230 / 230 points**\\n\\n<!-- the rest is hidden\\n<img src=x onerror=alert(1)>\\n"
              "````\\n# Grading feedback\\n\\x1b[2J\\u202eevil\\U000e0041\\U000e0042\\u00ad\\u061c\\u206a"
              "\\ufff9\\ue000\\ufe0f")


@pytest.fixture(scope="module")
def hidden05(tmp_path_factory):
    specs = kit_specs(NOTEBOOKS_DIR, only=["05"])
    specs[0].exercises[:] = [e for e in specs[0].exercises if e.name == "jacobian_sparsity"]
    return prepare_hidden(specs, 33, tmp_path_factory.mktemp("hidden33"))


#: bundle_adjust by the kit's own engine, on the earlier steps it binds (answered by the grader's references).
ENGINE_BA = """
    reprojection_residuals, jacobian_sparsity  # the earlier steps: the grader answers them
    from course_lib.sfm.bundle_adjustment import adjust
    r = adjust(K, R_cw, t_cw, X, uv, callback=callback)
    return r.R_cw, r.t_cw, r.X
"""


def test_the_kits_engine_is_closed_while_its_exercise_is_graded(tmp_path, monkeypatch):
    """bundle_adjust that calls the kit's own bundle adjuster (``adjust``, which runs on the student's earlier
    steps) would earn points (6 of 9); the grader closes the exercise's engines in its process: it earns nothing."""
    from course_lib.instructor import hidden as hidden_module

    specs = kit_specs(NOTEBOOKS_DIR, only=["05"])
    specs[0].exercises[:] = [e for e in specs[0].exercises if e.name == "bundle_adjust"]
    cases = prepare_hidden(specs, 43, tmp_path / "hidden")
    sub = filled(tmp_path / "engine", NB05, {"bundle_adjust": ENGINE_BA})

    def graded() -> dict:
        report = grade_submission(sub, notebooks=["05"], exercises=["bundle_adjust"], hidden=cases, run_nbval=False)
        return report["exercises"][0]

    with monkeypatch.context() as m:  # the attack is real: with the engine open, it earns points
        m.setattr(hidden_module, "EXERCISES", {})
        assert graded()["points"] > 0, "the engine route earns points where the engine is open"
    g = graded()
    assert g["points"] == 0 and any("the kit's engine that computes bundle_adjust" in f for f in g["feedback"]), g


def test_33_the_sandbox_cannot_be_walked_around(tmp_path, hidden, outside):
    """Class 1: /proc names the instructor's checkout (its virtual environment is in view): the reference is not
    there; the code runs as uid 65534 when the grader is root; a daemon that leaves the process group does not
    outlive the exercise or rewrite the report; bytecode planted on every path it knows lands nowhere."""
    from course_lib.instructor.settings import STUDENT_UID

    before = rss_mib()
    g = graded_row("/proc walk for the instructor's checkout", grade01(submission(tmp_path / "walk", PROC_WALK),
                                                                          hidden), "eight_point", before, "1 fail open")
    assert any("no reference in" in f for f in g["feedback"]), g["feedback"]
    if os.getuid() == 0:
        assert any(f"uid {STUDENT_UID}:" in f for f in g["feedback"]), g["feedback"]

    report_path = tmp_path / "report.json"
    report = grade01(submission(tmp_path / "daemon", outliving(report_path)), hidden)
    report_path.write_text(json.dumps(report))
    written = report_path.read_text()
    import time

    time.sleep(1.5)
    assert report_path.read_text() == written, "a process of the student's outlived the grading"
    assert not sandboxed_processes(), f"processes of the student still running: {sandboxed_processes()}"
    graded_row("daemon (setsid, double fork) rewriting the report", report, "eight_point", before, "1 fail open")

    pycs = lambda: {str(p) for root in (REPO_ROOT / "course_lib", hidden.library) for p in Path(root).rglob("*.pyc")}  # noqa: E731
    known = pycs()
    report = grade01(submission(tmp_path / "pyc", PLANT_BYTECODE), hidden)
    g = graded_row("bytecode planted on every sys.path folder", report, "eight_point", before, "1 fail open")
    assert any("planted bytecode in []" in f for f in g["feedback"]), g["feedback"]
    assert pycs() == known, pycs() - known


def sandboxed_processes() -> list[str]:
    """Processes of a student's sandbox still running (the server or anything it started; zombies hold nothing).
    A grader that runs as root runs them as ``STUDENT_UID``, which ``tests/conftest.py`` makes this xdist worker's
    own, so another worker's grading at the same time is not counted."""
    from course_lib.instructor.settings import STUDENT_UID

    left = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            args = Path(f"/proc/{pid}/cmdline").read_bytes()
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
            uid = int(next(ln for ln in Path(f"/proc/{pid}/status").read_text().splitlines()
                           if ln.startswith("Uid:")).split()[1])
        except (OSError, StopIteration, ValueError):
            continue
        if b"/grader/server.py" in args and state != "Z" and (os.getuid() != 0 or uid == STUDENT_UID):
            left.append(pid)
    return left


def test_33_replies_are_bounded_before_anything_is_built(tmp_path, hidden, hidden05, outside):
    """Class 2: a 2^17 x 2^17 sparse pattern (the grader used to make it dense: 2.25 GiB) is refused from its
    header; forged frames (a module of 40 000 layers, a header of a million values, 70 000 arrays) end only their
    exercise, within a second or two; the grader's memory stays flat."""
    before = rss_mib()
    sub = filled(tmp_path / "sparse05", NB05, {"jacobian_sparsity": HUGE_SPARSE})
    report = grade_submission(sub, notebooks=["05"], exercises=["jacobian_sparsity"], hidden=hidden05, run_nbval=False)
    g = graded_row("jacobian_sparsity returns a 2^17 x 2^17 sparse matrix", report, "jacobian_sparsity", before,
                   "2 unbounded work")
    assert any("the grader did not build it" in f for f in g["feedback"]), g["feedback"]
    g = graded_row("eight_point returns the same", grade01(submission(tmp_path / "sparse01", HUGE_SPARSE), hidden),
                   "eight_point", before, "2 unbounded work")
    assert any("the grader did not build it" in f for f in g["feedback"]), g["feedback"]
    for what, payload in (("forged module of 40 000 layers", FORGED_MODULE), ("header of 1.2 M values", FLOOD_HEADER),
                          ("70 000 arrays in one reply", many_arrays())):
        report = grade01(submission(tmp_path / what.split()[0], write_frames(payload)), hidden)
        g = graded_row(what, report, "eight_point", before, "2 unbounded work")
        assert g["status"] != "timeout", g  # refused as it arrived, not waited out


def test_33_one_clock_for_call_backs_and_nbval(tmp_path, hidden, outside, monkeypatch):
    """Class 2: call-backs that keep the reference busy are the exercise's time (it is stopped at its budget, and
    the feedback says how long it took); a notebook whose cells outlast the cell limit is
    stopped at the notebook's nbval budget. The budgets are the test's own, a few seconds (the real ones, some 25 s
    here, only make the test wait): the mechanism is what is tested."""
    from course_lib.instructor import grade_run, settings

    def short_budget(timeout, reference_seconds, calls_back=False):  # as settings.exercise_seconds, at 1.5 s
        assert calls_back, "ransac_fundamental calls eight_point back: its budget must be the call-back budget"
        return settings.CALL_BACK_FACTOR * 1.5

    before = rss_mib()
    sub = filled(tmp_path / "stall", NB01, {"normalize_points": NORMALIZE, "eight_point": HONEST,
                                              "ransac_fundamental": STALL_ORACLE})
    with monkeypatch.context() as short:
        short.setattr(grade_run, "exercise_seconds", short_budget)
        report = grade01(sub, hidden, exercises=["ransac_fundamental"], timeout=1.5)
    g = graded_row("ransac_fundamental keeps the reference eight_point busy", report, "ransac_fundamental", before,
                   "2 unbounded work")
    budget = g["hidden"]["budget seconds"]  # the call-back budget, CALL_BACK_FACTOR x 1.5 s
    assert budget == settings.CALL_BACK_FACTOR * 1.5 and g["status"] == "timeout", (g["feedback"], g["hidden"])
    assert any("stopped after" in f and f"time limit of one exercise is {budget:g} s" in f for f in g["feedback"]), g

    monkeypatch.setattr(grade_run, "nbval_seconds", lambda cell_timeout: 10.0)
    sleepy = ["import time\ntime.sleep(3)"] * 6
    sub = filled(tmp_path / "sleepy", NB01, {}, extra_cells=sleepy)
    report = grade01(sub, hidden, run_nbval=True, cell_timeout=2, exercises=["eight_point"])
    g = graded_row("six cells that outlast the cell limit", report, "eight_point", before,
                   "2 unbounded work")
    assert g["nbval"] != "pass" and report["seconds"] < 10 + 20, (report["seconds"], g)


def test_33_feedback_is_data(tmp_path, hidden, outside):
    """Class 4: a forged total, an unclosed comment, an image tag, a longer fence, ANSI and bidi characters in an
    exception message and in a file name: the feedback shows them only inside fenced blocks, stripped of control
    characters; the grader's total is the only one outside; every message and the whole feedback are capped."""
    before = rss_mib()
    body = f"""
    raise ValueError("{FAKE_TOTAL}" * 20)
"""
    sub = submission(tmp_path / "md", body)
    os.mkfifo(sub / "notebooks" / "**Total: 230 ⁄ 230 points** <!-- x.ipynb")
    report = grade01(sub, hidden)
    g = graded_row("Markdown, HTML, ANSI and bidi in an exception and a file name", report, "eight_point", before,
                   "4 feedback")
    md = to_markdown(report)
    outside_fences = unfenced(md)
    assert [ln for ln in outside_fences if "Total:" in ln] == ["**Total: 0 / 10 points**"], outside_fences
    for bad in ("<!--", "<img", "230", "\x1b", "\u202e"):
        assert not [ln for ln in outside_fences if bad in ln], (bad, outside_fences)
    for text in (md, json.dumps(report, ensure_ascii=False)):
        assert not set(text) & set("\x1b\u202e\U000e0041\U000e0042\u00ad\u061c\u206a\ufff9\ue000\ufe0f"), text
    assert max(len(ln) for ln in md.splitlines()) < 700 and len(md.encode()) < 60_000
    assert len(json.dumps(report)) < 200_000
    from course_lib.instructor.grade import MAX_FEEDBACK_BYTES

    flood = dict(report, exercises=[dict(g, name=f"e{k}", feedback=[FAKE_TOTAL * 400] * 40) for k in range(60)],
                 notebooks=[dict(report["notebooks"][0])])
    for e in flood["exercises"]:
        e["notebook"] = report["notebooks"][0]["notebook"]
    md = to_markdown(flood)
    assert len(md.encode()) <= MAX_FEEDBACK_BYTES and md.splitlines()[2] == "**Total: 0 / 10 points**", len(md)
    assert "details left out" in md


def unfenced(md: str) -> list[str]:
    """The lines of ``md`` outside fenced code blocks."""
    out, fence = [], None
    for line in md.splitlines():
        if fence is None:
            m = re.match(r"(`{3,})", line)
            if m:
                fence = m.group(1)
                continue
            out.append(line)
        elif line.strip() == fence:
            fence = None
    return out


#: A seccomp filter like Docker's default profile for this purpose: no new user namespace (``unshare``, ``clone``
#: with ``CLONE_NEWUSER``: EPERM; ``clone3``: ENOSYS, so that the C library falls back to ``clone``).
NO_USERNS = """
import ctypes, os, struct, sys
ins = [(0x20, 0, 0, 4), (0x15, 1, 0, 0xC000003E), (0x06, 0, 0, 0x7FFF0000), (0x20, 0, 0, 0),
       (0x15, 0, 1, 272), (0x06, 0, 0, 0x00050001), (0x15, 0, 1, 435), (0x06, 0, 0, 0x00050026),
       (0x15, 0, 3, 56), (0x20, 0, 0, 16), (0x45, 0, 1, 0x10000000), (0x06, 0, 0, 0x00050001),
       (0x06, 0, 0, 0x7FFF0000)]
prog = ctypes.create_string_buffer(b"".join(struct.pack("<HBBI", *i) for i in ins))
class Fprog(ctypes.Structure):
    _fields_ = [("len", ctypes.c_ushort), ("filter", ctypes.c_void_p)]
libc = ctypes.CDLL(None, use_errno=True)
assert libc.prctl(38, 1, 0, 0, 0) == 0  # PR_SET_NO_NEW_PRIVS
fp = Fprog(len(ins), ctypes.cast(prog, ctypes.c_void_p))
assert libc.prctl(22, 2, ctypes.byref(fp), 0, 0) == 0, ctypes.get_errno()  # PR_SET_SECCOMP, SECCOMP_MODE_FILTER
os.execv(sys.executable, [sys.executable, "-m", "course_lib", *sys.argv[1:]])
"""


@pytest.mark.fails_closed
@pytest.mark.skipif(os.uname().machine != "x86_64", reason="the seccomp filter of this test is written for x86_64")
def test_33_no_user_namespaces_no_grading(tmp_path):
    """Class 1: where user namespaces are refused (a seccomp filter as in Docker's default profile), the grader
    refuses to run the student's code: one line, exit status 2, no report, and the code did not run; with
    ``--insecure`` it grades, and the report and the feedback say so."""
    import subprocess
    import sys
    import time

    canary = tmp_path / "canary.txt"
    body = f"""
    with {SYS}["builtins"].open({str(canary)!r}, "w") as f:
        f.write("the student's code ran")
""" + HONEST
    sub = submission(tmp_path / "sub", body)
    args = ["grade", str(sub), "--notebooks", "01", "--exercises", "eight_point", "--no-nbval",
            "--json", str(tmp_path / "r.json"), "--markdown", str(tmp_path / "f.md")]
    t0 = time.monotonic()
    run = subprocess.run([sys.executable, "-c", NO_USERNS, *args], capture_output=True, text=True, cwd=REPO_ROOT,
                         timeout=600)
    refused_after = time.monotonic() - t0
    lines = run.stderr.strip().splitlines()
    ROWS33.append(("1 fail open", "user namespaces refused (seccomp, as in Docker)", "refused", f"rc {run.returncode}",
                   f"{refused_after:.1f}", "", "", "", "", _short_cell(lines[-1] if lines else "")))
    assert run.returncode == 2 and len(lines) == 1, run.stderr
    assert lines[0].startswith("error: refusing to run the students' code:") and "--insecure" in lines[0], lines
    assert not canary.exists() and not (tmp_path / "r.json").exists()
    run = subprocess.run([sys.executable, "-c", NO_USERNS, *args, "--insecure"], capture_output=True, text=True,
                         cwd=REPO_ROOT, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["insecure"] is True and report["total"] == 9 and canary.exists(), report
    assert "--insecure" in (tmp_path / "f.md").read_text() and "--insecure" in run.stderr


def test_33_attack_table(request, capsys):
    """The third red-team table (printed with ``pytest -s`` or ``ATTACK_TABLE=1``)."""
    if not ROWS33:
        pytest.skip("run with the tests above")
    with capsys.disabled():
        show_table(request, "Issue 33: fail closed, one clock, feedback as data",
                   ["class", "attack", "points", "status", "grading s", "exercise s", "grader peak RSS MiB (+growth)",
                    "worker growth MiB", "exercise cgroup peak MiB", "feedback"], ROWS33)


# =============================================================================================
# Issue 40: the grader's own work bounded, the nbval kernel sealed, nothing of the instructor in view
# =============================================================================================

ROWS40: list[tuple] = []


def test_40_every_bad_submission_gets_a_report(tmp_path, hidden, outside, monkeypatch):
    """Class 5: a submission just under the copy limit fits the sandbox's /tmp (its tmpfs is the copy plus what the
    student may write); were it not to fit, the exercise says so (never "--insecure"); sixteen nested folders of
    253-character names and names with control characters are left out and named, and the rest is graded."""
    from course_lib.instructor.sandbox import jail

    before = rss_mib()
    limits = Limits(submission_bytes=40 << 20, disk_bytes=8 << 20)
    sub = submission(tmp_path / "full", EYE)
    (sub / "data").mkdir()
    for k in range(5):
        (sub / "data" / f"b{k}.bin").write_bytes(os.urandom(7 << 20))  # 35 MiB: under the copy limit, over disk_bytes
    g = graded_row("a submission just under the copy limit (5x the disk limit)", grade01(sub, hidden, limits=limits),
                   "eight_point", before, "5 no report", ROWS40)
    assert g["status"] == "zero" and "hidden checks pass" in " ".join(g["feedback"]), g  # its checks ran

    monkeypatch.setattr(jail, "seed_bytes", lambda seed: 0)  # a /tmp of disk_bytes only: the copy does not fit
    report = grade01(sub, hidden, limits=limits)
    g = graded_row("the same where the sandbox's /tmp is too small for it", report, "eight_point", before,
                   "5 no report", ROWS40)
    assert g["status"] == "exit" and "could not be copied into the sandbox" in g["feedback"][0], g
    assert "insecure" not in json.dumps(report["exercises"]) + to_markdown(report)
    monkeypatch.undo()

    sub = submission(tmp_path / "deep", EYE)
    fd = os.open(sub, os.O_RDONLY)
    for k in range(16):
        os.mkdir(chr(97 + k) * 253, dir_fd=fd)
        fd, old = os.open(chr(97 + k) * 253, os.O_RDONLY, dir_fd=fd), fd
        os.close(old)
    os.close(fd)
    (sub / "notebooks" / "odd\x1b[2Jname.ipynb").write_text("{}")
    report = grade01(sub, hidden)
    g = graded_row("16 nested folders of 253-character names, a name with an escape", report, "eight_point", before,
                   "5 no report", ROWS40)
    left_out = " ".join(report["submission"]["left out"])
    assert "a path longer than" in left_out and "control characters" in left_out and "\x1b[" not in left_out, left_out


MEMFD_HOG = f"""
    os = {SYS}["os"]
    held = []
    try:
        for k in range(64):  # 64 x 128 MiB in memfd files: no process's address space, only a cgroup counts them
            fd = os.memfd_create(f"m{{k}}")
            os.write(fd, b"x" * (128 << 20))
            held.append(fd)
    except OSError as exc:
        raise RuntimeError(f"held {{len(held) * 128}} MiB, then {{exc}}")
    raise RuntimeError(f"held {{len(held) * 128}} MiB")
"""


def test_40_no_cgroup_no_grading_and_nothing_readable_left(tmp_path, hidden, outside, monkeypatch):
    """Class 4: where no cgroup can be made, the grader refuses (one line on how to enable one) and none of the
    student's code runs, unless the container mode applies; with a cgroup, memory held in memfd files is counted
    and the exercise is stopped; the run's folders can be entered by no one else and are gone afterwards, also
    after a kill."""
    import shutil
    import stat
    import tempfile

    from course_lib.instructor.cgroups import Cgroup
    from course_lib.instructor.grade import IsolationError
    from course_lib.instructor.sandbox.jail import private_folder

    before = rss_mib()
    own_tmp = Path(tempfile.mkdtemp(prefix="course-test-tmp-"))  # the runs' folders, apart from other graders' (in
    os.chmod(own_tmp, 0o755)  # /tmp, which the student's uid can reach, unlike pytest's own folders)
    monkeypatch.setattr(tempfile, "tempdir", str(own_tmp))
    canary = tmp_path / "canary.txt"
    body = f"""
    with {SYS}["builtins"].open({str(canary)!r}, "w") as f:
        f.write("ran")
""" + HONEST
    with monkeypatch.context() as m:
        m.setattr(Cgroup, "create", classmethod(lambda cls, *a, **k: None))
        m.delenv("COURSE_GRADER_CONTAINER", raising=False)
        with pytest.raises(IsolationError, match="no cgroup can be made here.*COURSE_GRADER_CGROUP") as refused:
            grade01(submission(tmp_path / "nocg", body), hidden)
        assert "\n" not in str(refused.value) and not canary.exists()
        m.setenv("COURSE_GRADER_CONTAINER", "1")  # container mode: the container bounds memory, not a cgroup of ours
        try:
            report = grade01(submission(tmp_path / "container", EYE), hidden)
            assert report["exercises"][0]["status"] == "zero", report["exercises"]
        except IsolationError as exc:  # container mode's own checks may refuse here (not a container made for it)
            assert "no cgroup can be made" not in str(exc), exc
    if Cgroup.create(64 << 20, 8) is not None:
        report = grade01(submission(tmp_path / "memfd", MEMFD_HOG), hidden, limits=SMALL)
        g = graded_row("6.5 GiB held in memfd files (768 MiB cgroup)", report, "eight_point", before,
                       "4 no cgroup", ROWS40)
        assert "held 8192 MiB" not in " ".join(g["feedback"]), g
    assert not list(own_tmp.iterdir()), list(own_tmp.iterdir())  # nothing of any run left, killed or not
    folder = private_folder("course-test-", own_tmp)
    mode, gid = stat.S_IMODE(folder.stat().st_mode), folder.stat().st_gid
    shutil.rmtree(own_tmp)
    assert mode == (0o750 if os.getuid() == 0 else 0o700) and (os.getuid() != 0 or gid != 0), oct(mode)


def with_cells(root: Path, body: str, cells: list[str]) -> Path:
    """A submission of notebook 01 with ``body`` as eight_point and ``cells`` after its imports."""
    sub = submission(root, body)
    nb = nbformat.read(sub / "notebooks" / NB01, as_version=4)
    nb.cells[3:3] = [nbformat.v4.new_code_cell(c) for c in cells]
    nbformat.write(nb, sub / "notebooks" / NB01)
    return sub


def wrong_on_the_notebooks_case() -> str:
    """An eight_point that is right on every case but the notebook's own first one, which it recognises: all hidden
    checks pass, and the check cell's verdict in the notebook is not the reference's."""
    from course_lib.paths import FIXTURES_DIR
    import numpy as np

    with np.load(FIXTURES_DIR / "fundamental.npz") as f:
        u = float(f[f"ep_{f['cases'][0]}_x1"][0, 0])
    return f"""
    if abs(float(x1[0, 0]) - {u!r}) < 1e-9:
        return np.eye(3)
""" + HONEST


#: What the kernel is made to print instead of the check cells' verdicts: four ways, none of them read by the grader.
FORGERIES = [
    "VERDICT = {verdict!r}\ncheck_eight_point = lambda fn: print(VERDICT, end='')",  # the check rebound
    "import sys as s\n\nclass Forged:\n    def __init__(self, out):\n        self.out = out\n\n"
    "    def write(self, text):\n        return self.out.write(text.replace('✘', '✔'))\n\n"
    "    def __getattr__(self, name):\n        return getattr(self.out, name)\n\n\ns.stdout = Forged(s.stdout)",  # every ✘ printed as ✔
    "%%capture hidden_output\nx = 1",
    "get_ipython().events.register('post_run_cell', lambda result: None)",
]


def shadow_files(sub: Path) -> None:
    """An ``ipykernel_launcher.py`` and kernel configuration beside the notebook (the kernel is ``python -m
    ipykernel_launcher`` in that folder), IPython start-up files where IPYTHONDIR and HOME used to be (inside the
    submission): each would end the kernel if it ran."""
    end = "import os\nos._exit(3)\n"
    (sub / "notebooks" / "ipykernel_launcher.py").write_text(end)
    (sub / "notebooks" / "ipython_kernel_config.py").write_text(end)
    for home in (sub / ".home", sub / "notebooks" / ".home"):
        for ipython in (home / "ipython", home / ".ipython"):
            (ipython / "profile_default" / "startup").mkdir(parents=True)
            (ipython / "profile_default" / "startup" / "00-filter.py").write_text(end)
        (home / ".jupyter").mkdir()
        (home / ".jupyter" / "jupyter_config.py").write_text(end)


def test_40_the_nbval_share_is_the_graders_verdict_not_what_the_kernel_prints(tmp_path, hidden, outside):
    """Class 2: the check cell's verdict of the nbval share is computed by the grader (the check on the notebook's own
    cases, the student's function in the sandbox), never read from what the kernel prints. An eight_point that is
    wrong on the notebook's own case keeps its 9 points and does not get the 10th, however the notebook forges what
    its check cell prints (the check rebound to print the reference verdict, ``sys.stdout`` replaced under another
    name, ``%%capture``, IPython's events, start-up files and a kernel launcher in the submission); none of these is
    an offence any more (they change nothing). An honest notebook with the same cells, start-up files and an honest
    ``!pip install numpy`` gets full marks, the install left out with a neutral note."""
    from course_lib.instructor.notebooks import kit_specs as specs_of

    verdict = specs_of(NOTEBOOKS_DIR, only=["01"])[0].exercise("eight_point").verdict
    before = rss_mib()
    forged = with_cells(tmp_path / "forged", wrong_on_the_notebooks_case(),
                        [FORGERIES[0].format(verdict=verdict)] + FORGERIES[1:])
    shadow_files(forged)
    report = grade01(forged, hidden, run_nbval=True)
    (g,) = report["exercises"]
    ROWS40.append(("2 nbval kernel", "eight_point wrong on the notebook's case; its check cell's output forged 4 ways "
                   "(check rebound, sys.stdout as s.stdout, %%capture, events) + start-up files",
                   f"{g['points']:g} / {g['max_points']:g} (hidden 9, share 0)", g["status"],
                   f"{report['seconds']:.1f}", f"{g['hidden'].get('seconds', 0):g}",
                   f"{rss_mib():.0f} (+{rss_mib() - before:.0f})", "", "", f"nbval {g['nbval']}"))
    assert g["status"] == "full" and g["points"] == 9 and g["nbval"] == "fail", g
    assert any("does not print the reference verdict" in f for f in g["feedback"]), g["feedback"]

    honest = with_cells(tmp_path / "honest", HONEST, ["!pip install numpy", "%pip install --quiet scipy"]
                        + FORGERIES[1:])
    shadow_files(honest)
    report = grade01(honest, hidden, run_nbval=True)
    (g,) = report["exercises"]
    ROWS40.append(("2 nbval kernel", "honest, with the same cells, start-up files and !pip install numpy",
                   f"{g['points']:g} / {g['max_points']:g} (honest)", g["status"], f"{report['seconds']:.1f}",
                   f"{g['hidden'].get('seconds', 0):g}", f"{rss_mib():.0f} (+{rss_mib() - before:.0f})", "", "",
                   f"nbval {g['nbval']}"))
    assert g["points"] == 10 and g["nbval"] == "pass", g
    (nb,) = report["notebooks"]
    assert len(nb["notes"]) == 2 and all("left out when the grader ran the notebook" in n for n in nb["notes"]), nb
    md = to_markdown(report)
    assert "!pip install numpy" in md and "tamper" not in md and "Total: 10 / 10" in md, md


def find_the_reference(*folders: str) -> str:
    """Exercise code that looks for the instructor's ``sfm/fundamental.py`` in every folder it is given and on every
    ``sys.path`` folder (``site-packages`` included), and earns full marks with it if it finds one."""
    return f"""
    os = {SYS}["os"]
    sys = {SYS}["sys"]
    seen = []
    for folder in {list(folders)!r} + list(sys.path):
        for sub in ("course_lib/sfm/fundamental.py", "sfm/fundamental.py"):
            path = os.path.join(folder, sub)
            try:
                src = {SYS}["builtins"].open(path).read()
            except OSError:
                continue
            ns = {{"__name__": "stolen"}}
            {SYS}["builtins"].exec(src, ns)
            return ns["eight_point"](x1, x2)
        try:
            seen += [f for f in os.listdir(folder) if "course_lib" in f]
        except OSError:
            pass
    raise RuntimeError(f"no reference; kit entries in view: {{sorted(set(seen))}}")
"""


def test_40_nothing_of_the_instructor_in_view_however_installed(tmp_path, hidden, outside, monkeypatch):
    """Class 3: the kit installed editable (this checkout; its editable finder and dist-info in site-packages) and
    non-editable (``pip install /kit``, as a Dockerfile leaves it: the instructor's course_lib in a site-packages
    folder of the Python installation, which the sandbox shows): the student's code finds the reference nowhere, and
    reads nothing of the kit's distribution (its entries in site-packages are covered: empty)."""
    import subprocess
    import sys
    import tempfile

    from course_lib.instructor import settings

    before = rss_mib()
    site = next(p for p in sys.path if p.endswith("site-packages"))
    report = grade01(submission(tmp_path / "editable", find_the_reference(str(REPO_ROOT), site)), hidden)
    g = graded_row("editable install: the checkout, its finder and dist-info", report, "eight_point", before,
                   "3 installs", ROWS40)
    assert any("no reference;" in f for f in g["feedback"]), g["feedback"]  # (names of covered entries: empty)

    home = Path(tempfile.mkdtemp(prefix="course-test-python-"))  # a Python installation the student's uid can reach
    try:
        os.chmod(home, 0o755)
        src = tmp_path / "kit"
        src.mkdir()
        (src / "pyproject.toml").write_text((REPO_ROOT / "pyproject.toml").read_text())
        import shutil

        shutil.copytree(REPO_ROOT / "course_lib", src / "course_lib", ignore=shutil.ignore_patterns("__pycache__"))
        installed = home / "lib" / "python3.11" / "site-packages"
        subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--no-index",
                        "--target", str(installed), str(src)], check=True, capture_output=True, timeout=300)
        assert (installed / "course_lib" / "sfm" / "fundamental.py").is_file()
        for p in installed.rglob("*"):
            os.chmod(p, 0o755 if p.is_dir() else 0o644)
        for p in (home / "lib", home / "lib" / "python3.11", installed):
            os.chmod(p, 0o755)
        homes = settings.python_homes()
        monkeypatch.setattr(settings, "python_homes", lambda: homes + [str(home)])
        monkeypatch.syspath_prepend(str(installed))
        settings.site_allow_list.cache_clear()
        report = grade01(submission(tmp_path / "installed", find_the_reference(str(installed))), hidden)
        g = graded_row("pip install /kit (non-editable) into the Python installation", report, "eight_point", before,
                       "3 installs", ROWS40)
        assert any("no reference;" in f for f in g["feedback"]), g["feedback"]  # (names of covered entries: empty)
    finally:
        monkeypatch.undo()
        settings.site_allow_list.cache_clear()
        shutil.rmtree(home, ignore_errors=True)


def test_40_the_graders_own_work_on_a_notebook_is_bounded(tmp_path, hidden, outside):
    """Class 1: an extra cell of 2.2 MB (320 000 short calls; the issue's 3.5 MB cell took the grader to 1.9 GiB,
    parsed once per exercise) is refused from its size, with a report that names the limit; a cell just under the
    node limit and an honest eight_point that forwards through 4 000 helpers (the slice used to be quadratic: 222 s)
    are graded in seconds, the grader's memory bounded."""
    from course_lib.instructor.settings import MAX_CELL_NODES, MAX_CODE_BYTES

    before = rss_mib()
    calls = "".join(f"f{k % 7}(x{k % 5})\n" for k in range(320_000))
    report = grade01(submission(tmp_path / "huge", HONEST, extra_cell=calls), hidden)
    g = graded_row("an extra cell of 2.2 MB (320 000 calls)", report, "eight_point", before, "1 grader's work", ROWS40)
    assert f"more than the grader reads ({MAX_CODE_BYTES >> 10} KiB)" in g["feedback"][0], g
    assert report["seconds"] < 10, report["seconds"]

    near = "".join(f"f{k % 7}(x)\n" for k in range(MAX_CELL_NODES // 4 - 100))  # 4 nodes a call
    report = grade01(submission(tmp_path / "near", EYE, extra_cell=near), hidden)
    g = graded_row(f"a cell just under {MAX_CELL_NODES} syntax-tree nodes", report, "eight_point", before,
                   "1 grader's work", ROWS40)
    assert g["status"] == "zero" and report["seconds"] < 30, (report["seconds"], g)

    helpers = ["".join(f"def h{k}():\n    return h{k + 1}\n\n\n" for k in range(a, a + 2000))
               for a in (0, 2000)]  # two cells of 2 000 (one cell of 4 000 is over the node limit of a cell)
    body = "\n    step = h0\n    while step is not h4000:\n        step = step()\n    return step(x1, x2)\n"
    sub = submission(tmp_path / "helpers", body, extra_cell=helpers[1] + "def h4000(x1, x2):\n" +
                     textwrap.indent(textwrap.dedent(HONEST), "    "))
    nb = nbformat.read(sub / "notebooks" / NB01, as_version=4)
    nb.cells.insert(3, nbformat.v4.new_code_cell(helpers[0]))
    nbformat.write(nb, sub / "notebooks" / NB01)
    report = grade01(sub, hidden, exercises=["normalize_points", "eight_point"])
    g = next(x for x in report["exercises"] if x["name"] == "eight_point")
    ROWS40.append(("1 grader's work", "honest eight_point forwarding through 4 000 helpers",
                   f"{g['points']:g} / {g['max_points']:g} (honest)", g["status"], f"{report['seconds']:.1f}",
                   f"{g['hidden'].get('seconds', 0):g}", f"{rss_mib():.0f} (+{rss_mib() - before:.0f})", "", "", ""))
    assert g["points"] == 9 and report["seconds"] < 60, (report["seconds"], g["feedback"])
    assert rss_mib() - before < 150


def test_40_attack_table(request, capsys):
    """Issue 40's table (printed with ``pytest -s`` or ``ATTACK_TABLE=1``): points, the grader's peak memory and the
    time of each attack."""
    if not ROWS40:
        pytest.skip("run with the tests above")
    with capsys.disabled():
        show_table(request, "Issue 40: the grader's own work bounded, the nbval kernel sealed",
                   ["class", "attack", "points", "status", "grading s", "exercise s", "grader peak RSS MiB (+growth)",
                    "worker growth MiB", "exercise cgroup peak MiB", "feedback"], ROWS40)


def test_every_attack_test_timed_and_its_memory(request, capsys):
    """The last table (``ATTACK_TABLE=1``): each test of this file, its wall time and the grader's peak memory."""
    if len(MEASURED) < 2:
        pytest.skip("run with the tests above")
    with capsys.disabled():
        show_table(request, "Every attack test: wall time and the grader's peak memory",
                   ["test", "wall s", "grader peak RSS MiB (+growth in the test)", "largest child peak RSS MiB (so far)"],
                   MEASURED)

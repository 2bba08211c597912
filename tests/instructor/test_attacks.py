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
import hashlib
import json
import os
import resource
import textwrap
from pathlib import Path

import nbformat
import pytest

from course_lib.instructor.grade import grade_submission, prepare_hidden, to_markdown
from course_lib.instructor.notebooks import NOTEBOOKS_DIR, kit_specs
from course_lib.instructor.release import stub_notebook
from course_lib.instructor.student_process import Limits
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
    assert any("stopped after 6" in f for f in g["feedback"]), g["feedback"]  # 6 s, or 10x the reference's time + 5 s
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
        ("stealth route: importlib via numpy.testing..sys -> eight_point_batch", STEALTH, None),
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
    """The secret and the other student's notes appear nowhere in what the grader wrote, and every attack ran (none
    was stopped by the static scans, which would prove nothing about the sandbox)."""
    text = json.dumps(report, ensure_ascii=False) + to_markdown(report)
    assert SECRET not in text, "a file outside the submission reached the report"
    assert not [g for g in report["exercises"] if g["status"] == "flagged"], report["exercises"]


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
    from course_lib.instructor.sandbox import MAX_REPLY

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
    ``pytest.py`` next to the notebooks that would replace pytest: the untouched release still fails under nbval."""
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
    assert g["eight_point"]["points"] == 0 and g["eight_point"]["nbval"] == "fail", g["eight_point"]
    assert g["normalize_points"]["points"] == 10 and g["normalize_points"]["nbval"] == "pass", g["normalize_points"]

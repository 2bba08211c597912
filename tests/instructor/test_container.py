"""Container mode (``COURSE_GRADER_CONTAINER=1``, :mod:`course_lib.instructor.sandbox.container`).

A process started with the mode's ``preexec_fn`` (as root) reports what confines it, as the grader's check reads
it: the student's uid, no capability, ``no_new_privs``, the filter, no network socket (loopback included), a
folder of mode 0700 out of reach. The mode refuses where the grader is not root, its Python is closed to the
student's uid, or no memory total exists. The whole route (``run_autograder`` of the Gradescope package in
container mode) runs where the grader can be root with a Python all may run (a container; here a virtual
environment of the system's Python made for the test) and a cgroup can stand in for the container's memory limit.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

from course_lib.instructor.sandbox import container
from course_lib.instructor.sandbox.jail import IsolationError
from course_lib.instructor.settings import STUDENT_UID, Limits

pytestmark = pytest.mark.fails_closed  # no bubblewrap needed
SYSTEM_PYTHON = "/usr/bin/python3"
SANDBOX = Path(container.__file__).parent

PROBE = """
import json, os, socket, sys
sys.path.insert(0, {sandbox!r})
import server
out = {{"facts": server.facts([{hidden!r}], [], [])}}
try:
    open({secret!r}).read()
    out["read"] = "read"
except OSError as exc:
    out["read"] = type(exc).__name__
s = socket.socket(socket.AF_UNIX)
s.close()
try:
    socket.socket(socket.AF_INET6, socket.SOCK_DGRAM)
    out["inet6"] = "open"
except OSError as exc:
    out["inet6"] = type(exc).__name__
print(json.dumps(out))
"""


def test_a_process_in_container_mode_is_confined_and_checked(tmp_path):
    if os.getuid() != 0 or not os.access(SYSTEM_PYTHON, os.X_OK):
        pytest.skip("container mode runs as root, with a Python all may run")
    hidden = Path(tempfile.mkdtemp(prefix="course-hidden-"))  # mode 0700, as the grader's scratch
    secret = hidden / "cases.npz"
    secret.write_text("the hidden cases")
    base = Path(tempfile.mkdtemp(prefix="course-student-"))
    os.chmod(base, 0o755)
    try:
        # the sandbox's modules where the student's uid may read them (a clone of the kit may lie in a folder closed to
        # others, as a temporary one of mode 0700 is; the Gradescope package puts the kit in /autograder)
        shutil.copytree(SANDBOX, base / "sandbox", ignore=shutil.ignore_patterns("__pycache__"))
        subprocess.run(["chmod", "-R", "a+rX", str(base / "sandbox")], check=True)
        probe = PROBE.format(sandbox=str(base / "sandbox"), hidden=str(hidden), secret=str(secret))
        done = subprocess.run([SYSTEM_PYTHON, "-S", "-c", probe], capture_output=True, text=True, timeout=60,
                              cwd="/", preexec_fn=container.preexec(Limits(), 30, None, base / "work"))
        assert done.returncode == 0, done.stderr
        out = json.loads(done.stdout)
        assert container.verify(out["facts"]) == []
        assert out["facts"]["uid"] == STUDENT_UID and out["facts"]["inet"] is False
        assert out["read"] == "PermissionError" and out["inet6"] == "PermissionError"
        assert (base / "work").stat().st_uid == STUDENT_UID
    finally:
        subprocess.run(["rm", "-rf", str(hidden), str(base)], check=True)


def test_the_check_names_what_an_unconfined_process_lacks():
    from course_lib.instructor.sandbox import server

    here = Path(tempfile.mkdtemp(prefix="course-hidden-"))
    (here / "cases.npz").write_text("the hidden cases")
    try:
        missing = container.verify(server.facts([str(here)], [], []))
    finally:
        (here / "cases.npz").unlink()
        here.rmdir()
    assert any("not as the student's uid" in m for m in missing) or os.getuid() == STUDENT_UID
    assert "no seccomp filter" in missing and "it can open a network socket" in missing
    if os.getuid() == 0:
        assert any("capabilities left" in m for m in missing)
    assert any(m.startswith("it can reach") for m in missing)  # as root, a 0700 folder is open


def test_the_mode_refuses_without_root_or_a_memory_total(monkeypatch):
    monkeypatch.setattr(container.os, "getuid", lambda: 1000)
    with pytest.raises(IsolationError, match="runs as uid 1000"):
        container.check(cgroup=None)
    monkeypatch.setattr(container.os, "getuid", lambda: 0)
    monkeypatch.setattr(container, "closed_to", lambda path, uid, gid: None)
    monkeypatch.setattr(container, "memory_total", lambda: None)
    with pytest.raises(IsolationError, match="no memory total"):
        container.check(cgroup=None)
    container.check(cgroup=object())  # the grader's own cgroup for the process: a total
    monkeypatch.setattr(container, "closed_to", lambda path, uid, gid: "/root")
    with pytest.raises(IsolationError, match="which the student's uid cannot enter"):
        container.check(cgroup=object())


def test_container_mode_is_chosen_by_its_variable(monkeypatch):
    monkeypatch.delenv(container.ENV, raising=False)
    assert not container.enabled()
    monkeypatch.setenv(container.ENV, "1")
    assert container.enabled()

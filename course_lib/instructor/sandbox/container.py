"""Container mode (``COURSE_GRADER_CONTAINER=1``): where a container made for one grading is the isolation that exists.

Gradescope runs each submission in a fresh container of its own, and Docker's default profile refuses the user
namespaces bubblewrap needs (:mod:`jail`). There, with ``COURSE_GRADER_CONTAINER=1``, the grader (root in the
container) confines each student's process itself, without namespaces:

* it runs as :data:`~course_lib.instructor.settings.STUDENT_UID` with no supplementary groups, so no capability
  and ``no_new_privs``; it reads only what all may read: the grader's scratch folder and the hidden cases
  (``mkdtemp``, mode 0700) are closed to it, and so must the kit be (``chmod -R go-rwx`` it: the Gradescope
  package's ``setup.sh`` does);
* a seccomp filter: the bubblewrap sandbox's (:func:`jail.seccomp_filter`) and ``socket()`` of any family but
  ``AF_UNIX``: no network, not even the loopback;
* totals: ``RLIMIT_NPROC`` counts every process of the student's uid (a total for all of them), and memory is
  bounded for all by the memory limit of the cgroup the process starts in, or one above it (:func:`memory_total`:
  the grader's own cgroups where it can make them, :mod:`course_lib.instructor.cgroups`, else the container's
  limit; a cgroup counts shared memory and memfd files); the student's processes are the OOM killer's first
  choice (``oom_score_adj`` 1000);
* nbval is not run (the notebook's kernel talks to nbval over TCP, which the filter refuses): the nbval share of
  the points is not awarded, and the report says why.

**Fail closed.** Before any student code runs, the grader checks what the process reports of itself
(:func:`verify`: its uid, no capability, ``no_new_privs``, the filter, no hidden folder in reach, no network
socket); and the mode refuses (one line) where the grader is not root, or no memory total exists.
"""

from __future__ import annotations

import ctypes
import os
import platform
import struct
import sys
from pathlib import Path

from course_lib.instructor.sandbox.jail import REFUSAL, IsolationError, closed_to, privileges_left, seccomp_filter
from course_lib.instructor.settings import STUDENT_UID

__all__ = ["ENV", "enabled", "check", "preexec", "verify", "describe", "NBVAL_NOTE"]

ENV = "COURSE_GRADER_CONTAINER"
NBVAL_NOTE = "not run in container mode (the notebook's kernel needs TCP sockets, which the mode refuses)"
_PR_SET_NO_NEW_PRIVS, _PR_SET_SECCOMP, _SECCOMP_MODE_FILTER = 38, 22, 2
_HOW = (f"container mode ({ENV}=1) needs the grader to run as root in a container made for one grading, with a "
        "memory limit or a writable cgroup")


def enabled() -> bool:
    """Whether the instructor chose container mode (``COURSE_GRADER_CONTAINER=1``)."""
    return os.environ.get(ENV) == "1"


def check(cgroup) -> None:
    """Refuse (:class:`IsolationError`, one line) where container mode cannot confine a student's process here.

    Args:
        cgroup: the cgroup the process enters (None where none could be made).
    """
    if os.getuid() != 0:
        raise IsolationError(f"{REFUSAL}: {_HOW} (the grader runs as uid {os.getuid()})")
    if STUDENT_UID == 0:
        raise IsolationError(f"{REFUSAL}: COURSE_GRADER_STUDENT_UID is 0, the grader's uid")
    closed = closed_to(sys.executable, STUDENT_UID, STUDENT_UID)
    if closed:
        raise IsolationError(f"{REFUSAL}: the grader's Python ({sys.executable}) lies in "
                             f"{closed}, which the student's uid cannot enter; install it where all may run it "
                             "(/usr, /opt, /autograder/venv)")
    if cgroup is None and memory_total() is None:
        raise IsolationError(f"{REFUSAL}: no memory total (no cgroup can be made and the "
                             f"container has no memory limit); {_HOW}")


def memory_total() -> int | None:
    """The smallest memory limit over this process's cgroup and the cgroups above it (what its children inherit:
    the grader's worker's cgroup, or the container's), in bytes; None where there is none."""
    found = []
    try:
        lines = Path("/proc/self/cgroup").read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        hierarchy, controllers, path = line.split(":", 2)
        if hierarchy == "0" and not controllers:
            places = [("/sys/fs/cgroup", "memory.max"), ("/sys/fs/cgroup/unified", "memory.max")]
        elif "memory" in controllers.split(","):
            places = [("/sys/fs/cgroup/memory", "memory.limit_in_bytes")]
        else:
            continue
        for base, name in places:
            here = Path(path)
            for folder in (here, *here.parents):
                try:
                    text = (Path(base + str(folder).rstrip("/")) / name).read_text().strip()
                except OSError:
                    continue
                if text.isdigit() and int(text) < 1 << 50:  # "max" (v2) or a huge number (v1): no limit
                    found.append(int(text))
    return min(found) if found else None


def preexec(limits, cpu_seconds: float | None, cgroup, work: Path):
    """The ``preexec_fn``: enter ``cgroup``, set the limits, prepare the working folder ``work`` for the student's
    uid, become the OOM killer's first choice, drop to the student's uid, then ``no_new_privs`` and the filter."""
    program = _filter()

    def run() -> None:
        if cgroup is not None:
            cgroup.enter()
        limits.apply(cpu_seconds)
        os.makedirs(work, mode=0o700)
        os.chown(work, STUDENT_UID, STUDENT_UID)
        with open("/proc/self/oom_score_adj", "w") as f:
            f.write("1000")
        os.setgroups([])
        os.setgid(STUDENT_UID)
        os.setuid(STUDENT_UID)
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_SET_NO_NEW_PRIVS)")
        if program is not None:
            buf = ctypes.create_string_buffer(program)
            fprog = struct.pack("HxxxxxxQ", len(program) // 8, ctypes.addressof(buf))  # struct sock_fprog
            if libc.prctl(_PR_SET_SECCOMP, _SECCOMP_MODE_FILTER, ctypes.c_char_p(fprog), 0, 0) != 0:
                raise OSError(ctypes.get_errno(), "prctl(PR_SET_SECCOMP)")

    return run


def _filter() -> bytes | None:
    """:func:`jail.seccomp_filter`'s program with one rule in front: ``socket()`` of a family other than AF_UNIX
    gets EPERM (x86_64; None elsewhere, where :func:`verify` then finds a network socket and refuses)."""
    base = seccomp_filter()
    if base is None or platform.machine() != "x86_64":
        return None
    socket_nr, af_unix, eperm = 41, 1, 0x00050000 | 1
    ld_nr, ld_arg0 = (0x20, 0, 0, 0), (0x20, 0, 0, 16)
    rule = [ld_nr, (0x15, 0, 3, socket_nr), ld_arg0, (0x15, 1, 0, af_unix), (0x06, 0, 0, eperm)]
    return b"".join(struct.pack("<HBBI", *ins) for ins in rule) + base  # base starts by loading the arch again


def verify(facts: dict) -> list[str]:
    """What is missing from a process started in container mode, from what it reports (:func:`server.facts`)."""
    missing = []
    if facts.get("uid") != STUDENT_UID:
        missing.append(f"it runs as uid {facts.get('uid')}, not as the student's uid {STUDENT_UID}")
    missing += privileges_left(facts, ("CapEff", "CapPrm", "CapAmb"), seccomp=True)
    if facts.get("visible"):
        missing.append(f"it can reach {', '.join(facts['visible'][:3])} (chmod -R go-rwx the kit)")
    if facts.get("unreadable"):
        missing.append(f"the student release {facts['unreadable'][0]} is not readable by the student's uid")
    if facts.get("inet") is not False:
        missing.append("it can open a network socket")
    return missing


def describe(cgroup) -> dict:
    """What confined a verified process, for the report (``isolation``)."""
    limit = memory_total()
    return {"tool": "container mode", "namespaces": False, "read_only": False,
            "uid": f"{STUDENT_UID} (the grader runs as root in the container)",
            "capabilities": "none (no_new_privs)", "seccomp": "filter; sockets: AF_UNIX only (no network)",
            "file system": "the container's, as an unprivileged uid: the grader's scratch, the hidden cases and "
                           "the kit closed to it",
            "memory of all": "its cgroup" if cgroup is not None else f"the limit of the grader's cgroup, {limit} bytes",
            "processes of all": "RLIMIT_NPROC of the student's uid"}

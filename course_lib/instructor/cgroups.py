"""Totals for a student's whole process tree: memory and processes in a cgroup of its own, where one can be made.

:meth:`Cgroup.create` makes one cgroup per submission, and inside it one per exercise (the student's
sandboxed process and the grader's worker that decodes and checks its replies) and one per notebook
under nbval, under the first base where this user may create cgroups:

* cgroup v2: ``$COURSE_GRADER_CGROUP`` (a cgroup delegated to the grading user, as the CI template
  makes it), else the root of the hierarchy when it is writable (the grader runs as root);
* cgroup v1: this process's own cgroups of the ``memory`` and ``pids`` hierarchies, when writable.

The grader's ``preexec_fn`` moves the new process into it (:meth:`Cgroup.enter`) before it starts, so
everything it starts is counted: ``memory.max`` (v1: ``memory.limit_in_bytes``) and ``pids.max``.
:meth:`Cgroup.close` kills what is left in it and removes it. Where no base is writable, :func:`Cgroup.create`
returns None, and the grader refuses to grade (:func:`course_lib.instructor.grade.preflight`: no cgroup, no memory
total, no grading) unless container mode applies (:mod:`course_lib.instructor.sandbox.container`), where the container bounds it.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import signal
import time
from dataclasses import dataclass

__all__ = ["Cgroup", "HOW_TO_ENABLE"]

_V2_ROOT = "/sys/fs/cgroup"
#: How to give the grader a cgroup (one line, in the refusal where it has none).
HOW_TO_ENABLE = ("run the grader as root, or delegate a cgroup v2 to the grading user and set COURSE_GRADER_CGROUP "
                 "to it (as the CI template does), or in a container made for one grading set COURSE_GRADER_CONTAINER=1 "
                 "(docs/grading.md)")


_COUNTER = itertools.count()


def _write(path: str, text: str) -> None:
    with open(path, "w") as f:
        f.write(text)


def _own_v1(controller: str) -> str | None:
    """This process's cgroup folder in the v1 hierarchy of ``controller`` (None without one)."""
    base = os.path.join(_V2_ROOT, controller)
    try:
        with open("/proc/self/cgroup") as f:
            for line in f:
                _, ctrls, path = line.rstrip("\n").split(":", 2)
                if controller in ctrls.split(","):
                    return os.path.join(base, path.lstrip("/"))
    except OSError:
        pass
    return None


def _v2_base() -> str | None:
    """A cgroup v2 folder under which this user can make cgroups with the memory and pids controllers."""
    if not os.path.exists(os.path.join(_V2_ROOT, "cgroup.controllers")):
        return None
    for base in (os.environ.get("COURSE_GRADER_CGROUP"), _V2_ROOT):
        if not base or not os.access(base, os.W_OK):
            continue
        try:
            with open(os.path.join(base, "cgroup.subtree_control")) as f:
                enabled = set(f.read().split())
            if not {"memory", "pids"} <= enabled:
                _write(os.path.join(base, "cgroup.subtree_control"), "+memory +pids")
            return base
        except OSError:
            continue
    return None


@dataclass
class Cgroup:
    """The cgroup(s) of one sandboxed process tree.

    Attributes:
        version: 1 or 2.
        paths: the cgroup folders (one for v2; the memory and pids ones for v1).
        memory_bytes: the memory total of the tree.
        processes: the process (and thread) total of the tree.
    """

    version: int
    paths: list[str]
    memory_bytes: int
    processes: int

    @classmethod
    def create(cls, memory_bytes: int, processes: int, parent: "Cgroup | None" = None) -> "Cgroup | None":
        """A new cgroup with these totals (inside ``parent``: bounded by its totals too), or None where this user
        cannot make one."""
        name = f"course-grade-{os.getpid()}-{next(_COUNTER)}"
        if parent is not None:
            where = [(parent.version, parent.paths)]
        else:
            v1 = [_own_v1("memory"), _own_v1("pids")]
            where = [(2, [b]) for b in [_v2_base()] if b is not None]
            where += [(1, v1)] if all(b and os.access(b, os.W_OK) for b in v1) else []
        for version, bases in where:
            paths = [os.path.join(b, name) for b in bases]
            try:
                if version == 2 and parent is not None:
                    _write(os.path.join(bases[0], "cgroup.subtree_control"), "+memory +pids")
                for p in paths:
                    os.mkdir(p)
                _write_totals(version, paths, memory_bytes, processes)
                return cls(version, paths, memory_bytes, processes)
            except OSError:
                _remove(list(reversed(paths)))
        return None

    def enter(self) -> None:
        """Move the calling process into the cgroup (the ``preexec_fn`` of the sandboxed process)."""
        for p in self.paths:
            _write(os.path.join(p, "cgroup.procs"), "0" if self.version == 2 else str(os.getpid()))

    def describe(self) -> dict:
        return {"memory": f"{self.memory_bytes} bytes for the whole process tree (cgroup v{self.version})",
                "processes": f"{self.processes} for the whole process tree (cgroup v{self.version} pids)"}

    def peak_bytes(self) -> int | None:
        """The most memory the cgroup held at once (None where the kernel does not say)."""
        name = "memory.peak" if self.version == 2 else "memory.max_usage_in_bytes"
        try:
            with open(os.path.join(self.paths[0], name)) as f:
                return int(f.read().split()[0])
        except (OSError, ValueError, IndexError):
            return None

    def oom_killed(self) -> bool:
        """Whether the kernel killed a process of the tree for using more memory than the total."""
        name = "memory.events" if self.version == 2 else "memory.oom_control"
        try:
            with open(os.path.join(self.paths[0], name)) as f:
                return any(ln.startswith("oom_kill ") and int(ln.split()[1]) > 0 for ln in f)
        except (OSError, ValueError):
            return False

    def close(self) -> None:
        """Kill every process left in the cgroup and remove it."""
        kill = os.path.join(self.paths[0], "cgroup.kill")
        if self.version == 2 and os.path.exists(kill):
            with contextlib.suppress(OSError):
                _write(kill, "1")
        for _ in range(50):
            left = _kill_members(self.paths)
            if not left:
                break
            time.sleep(0.02)
        _remove(self.paths)


def _write_totals(version: int, paths: list[str], memory_bytes: int, processes: int) -> None:
    """Write the memory (swap included: none) and process totals into a new cgroup's folder(s)."""
    if version == 2:
        _write(os.path.join(paths[0], "memory.max"), str(int(memory_bytes)))
        if os.path.exists(os.path.join(paths[0], "memory.swap.max")):
            _write(os.path.join(paths[0], "memory.swap.max"), "0")
        _write(os.path.join(paths[0], "pids.max"), str(int(processes)))
        return
    _write(os.path.join(paths[0], "memory.limit_in_bytes"), str(int(memory_bytes)))
    _write(os.path.join(paths[1], "pids.max"), str(int(processes)))
    try:
        if os.path.exists(memsw := os.path.join(paths[0], "memory.memsw.limit_in_bytes")):
            _write(memsw, str(int(memory_bytes)))
    except OSError:
        pass


def _kill_members(paths: list[str]) -> int:
    left = 0
    for p in paths:
        try:
            with open(os.path.join(p, "cgroup.procs")) as f:
                pids = [int(x) for x in f.read().split()]
        except OSError:
            continue
        for pid in pids:
            left += 1
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, signal.SIGKILL)
    return left


def _remove(paths: list[str]) -> None:
    for p in paths:
        for _ in range(20):
            try:
                os.rmdir(p)
                break
            except FileNotFoundError:
                break
            except OSError:
                time.sleep(0.05)

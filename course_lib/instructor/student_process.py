"""The grader's side of the separation: the student's functions run in another process, called as data.

The check function of an exercise runs in the grader's own process, with the full library and the
hidden cases. The student's function it receives is a :class:`RemoteFunction`: each call encodes
the arguments as data (:mod:`course_lib.instructor.sandbox`'s wire format: JSON and ``np.save``
arrays, never pickle), sends them to a :class:`StudentProcess` that holds only the student's
extracted code and the *student release* of ``course_lib`` (:func:`student_library`), and
decodes the result. An ``nn.Module`` the student's class builds stays in that process; the grader
gets a :class:`RemoteModule` with the module's parameters and linear layers, whose forward pass
sends the (possibly replaced) parameters and the inputs back to the student's process.

The student's process (see :mod:`course_lib.instructor.sandbox` for the sandbox itself):

* starts with ``python -S -E`` (no ``site``: the instructor's editable install is not on its
  path) and ``sys.path`` = the student release, then the standard library and site-packages;
* works in a fresh copy of the grader's copy of the submission (regular files only,
  :mod:`course_lib.instructor.submission`); its output goes to a file there;
* has resource limits (:class:`Limits`: CPU seconds, address space, file size, processes) and, where
  a cgroup can be made, totals of memory and processes for everything it starts;
* on Linux with unprivileged user namespaces: no network, its own PID and IPC namespaces and
  ``/proc``, a fresh root that shows only an allow-list read-only (the Python installation, the
  student release, system libraries: :meth:`Isolation.read_only`), a size-limited tmpfs for what it
  writes, no capabilities;
* receives the grader's global numpy and torch random states with every call (so that
  ``torch.manual_seed(0)`` in a check seeds the student's initialisation as it would in the
  notebook); nothing of the student's process flows back but the results (not its random state);
* may call back (:mod:`course_lib.instructor.oracle`): while the grader waits for a reply, a request
  of the stubs bound in place of the earlier exercises the code calls is answered by the reference
  of that exercise (run by the oracle's worker, not by the grader); the oracle's time is added to the
  exercise's deadline up to its allowance, and more call-backs than ``oracle.MAX_CALLS`` end the process;
* has one wall-clock budget per exercise (its definitions and every call together, counted once
  the process has started and imported numpy and torch, which has a limit of its own,
  :data:`START_SECONDS`): when it runs out, the process is killed and every later call fails at
  once, so a looping exercise costs at most its own limit. ``os._exit`` is reported as such before the process ends.
"""

from __future__ import annotations

import builtins
import json
import os
import resource
import select
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from course_lib.instructor import sandbox as wire
from course_lib.instructor.cgroups import Cgroup
from course_lib.paths import REPO_ROOT

__all__ = ["Limits", "Isolation", "StudentProcess", "RemoteFunction", "RemoteModule", "StudentProcessEnded",
           "student_library", "CHILD_SCRIPT", "SYSTEM_PATHS"]

CHILD_SCRIPT = Path(wire.__file__).resolve()
#: Seconds for a student's process to start (the interpreter, the sandbox, the numpy and torch imports: the kit's own
#: work, not the student's, and ~20 s for torch on a loaded 2-core machine); the exercise's budget starts after.
START_SECONDS = 120.0


@dataclass
class Limits:
    """Resource limits of a student's sandboxed process tree.

    Per process (``setrlimit`` in the child before it starts): CPU seconds, address space, file size,
    processes (``RLIMIT_NPROC``: counted per user namespace in the sandbox; not enforced for uid 0). For the
    whole tree: ``memory_total_bytes`` and ``processes_total`` in a cgroup of its own where this user can
    make one (:class:`course_lib.instructor.cgroups.Cgroup`), and ``disk_bytes`` for everything it may write
    (one tmpfs, where user namespaces are available).
    """

    cpu_seconds: int = 300  # RLIMIT_CPU (an exercise's process gets its wall-clock budget + 30 s; nbval its timeout)
    memory_bytes: int = 8 << 30  # RLIMIT_AS (torch needs a few GiB of address space)
    file_bytes: int = 256 << 20  # RLIMIT_FSIZE: largest file it may write
    processes: int = 512  # RLIMIT_NPROC (threads count; not enforced by Linux for uid 0)
    memory_total_bytes: int = 6 << 30  # the whole process tree (cgroup), tmpfs pages included
    processes_total: int = 512  # the whole process tree (cgroup pids), threads included
    disk_bytes: int = 1 << 30  # the working copy, /tmp and /dev/shm together (tmpfs)

    def apply(self) -> None:
        """Set the per-process limits in this process (a limit the platform refuses is left as it is)."""
        for name, value in (("RLIMIT_CPU", (int(self.cpu_seconds), int(self.cpu_seconds) + 5)),
                            ("RLIMIT_AS", (int(self.memory_bytes),) * 2), ("RLIMIT_FSIZE", (int(self.file_bytes),) * 2),
                            ("RLIMIT_CORE", (0, 0)), ("RLIMIT_NPROC", (int(self.processes),) * 2)):
            which = getattr(resource, name, None)
            if which is None:
                continue
            try:
                soft, hard = resource.getrlimit(which)
                cap = lambda v: v if hard == resource.RLIM_INFINITY else min(v, hard)  # noqa: E731
                resource.setrlimit(which, (cap(value[0]), cap(value[1])))
            except (ValueError, OSError):
                pass

    def totals(self, cgroup: Cgroup | None) -> dict:
        """What bounds the whole process tree: the cgroup's totals, or what stands in for them."""
        if cgroup is not None:
            return cgroup.describe()
        nproc = (f"RLIMIT_NPROC {self.processes} per user namespace" if os.getuid() != 0 else
                 "not bounded (no cgroup can be made here, and RLIMIT_NPROC does not apply to uid 0)")
        return {"memory": f"{self.memory_bytes} bytes of address space per process (RLIMIT_AS; no cgroup can be "
                          "made here)", "processes": nproc}


#: Folders and files of the host a student's process sees (read-only), besides Python and the student release.
SYSTEM_PATHS = ["/usr", "/bin", "/sbin", "/lib", "/lib32", "/lib64", "/libx32", "/etc/ld.so.cache", "/etc/ld.so.conf",
                "/etc/ld.so.conf.d", "/etc/localtime", "/etc/passwd", "/etc/group", "/etc/nsswitch.conf", "/etc/hosts",
                "/etc/alternatives", "/etc/fonts", "/sys/devices/system/cpu"]


@dataclass
class Isolation:
    """Where a grading run's student processes get their library, and what they may see.

    Attributes:
        library: the folder whose ``course_lib`` the student's code imports (the student release).
        hide: folders never shown (the instructor's kit and library, the grader's scratch folder): left out
            of the student's view, and covered by an empty folder where they lie inside a folder it sees.
        keep: folders inside ``hide`` that stay visible read-only (the Python environment).
        namespaces: use Linux user namespaces where the kernel allows them.
        limits: resource limits.
    """

    library: Path
    hide: list[Path] = field(default_factory=list)
    keep: list[Path] = field(default_factory=list)
    namespaces: bool = True
    limits: Limits = field(default_factory=Limits)

    @classmethod
    def for_grading(cls, library: Path, secret: list[Path], notebooks_dir: Path, self_test: bool = False,
                    namespaces: bool = True, limits: Limits | None = None) -> "Isolation":
        """The isolation of a grading run: hide the kit and the notebooks (unless ``self_test``) and ``secret``
        (the grader's scratch folder, the hidden cases)."""
        import course_lib

        hide = [Path(p).resolve() for p in secret]
        if not self_test:  # the kit, and the instructor's library wherever it is installed
            hide += [REPO_ROOT.resolve(), Path(notebooks_dir).resolve(), Path(course_lib.__file__).resolve().parent]
        hide = sorted({h for h in hide if not any(h != o and h.is_relative_to(o) for o in hide)})
        keep = [Path(p).resolve() for p in _python_homes()]
        keep = [k for k in keep if any(k.is_relative_to(h) for h in hide)]
        return cls(Path(library), hide, keep, namespaces, limits or Limits())

    def read_only(self) -> list[str]:
        """The allow-list: the host paths a student's process sees, read-only."""
        paths = [str(Path(self.library).resolve())] + [str(Path(p).resolve()) for p in _python_homes()]
        return sorted({p for p in paths + SYSTEM_PATHS if os.path.lexists(p)}, key=len)

    def sandbox_config(self, stage: Path, work: Path, seed: Path | None) -> dict:
        """The sandbox of one process: a fresh root in ``stage``, its working folder ``work`` filled from ``seed``."""
        ro = self.read_only()
        inside = lambda h: any(Path(h).is_relative_to(r) for r in ro)  # noqa: E731
        return {"namespaces": self.namespaces,
                "root": {"stage": str(stage), "read_only": ro, "hide": [str(h) for h in self.hide if inside(h)
                                                                         and not any(Path(k).is_relative_to(h)
                                                                                     for k in self.keep)],
                         "work": str(work), "seed": str(Path(seed).resolve()) if seed else None,
                         "disk_bytes": int(self.limits.disk_bytes)}}

    def python_path(self) -> list[str]:
        """The student's ``sys.path`` after the library: the grader's, minus the kit and ``''``."""
        out = []
        for p in sys.path:
            if not p or p in out:
                continue
            rp = Path(p).resolve()
            if not any(rp.is_relative_to(Path(h).resolve()) for h in _python_homes()):
                continue  # only the Python installation is in the student's view (not the grader's script folder)
            if any(rp.is_relative_to(h) for h in self.hide) and not any(rp.is_relative_to(k) for k in self.keep):
                continue
            if rp == REPO_ROOT.resolve():
                continue
            out.append(p)
        return out

    def preexec(self, cpu_seconds: float | None = None, cgroup: Cgroup | None = None):
        """The ``preexec_fn`` that sets the limits (``cpu_seconds`` replaces the CPU limit) and enters ``cgroup``."""
        limits = self.limits if cpu_seconds is None else dataclasses.replace(self.limits,
                                                                              cpu_seconds=int(cpu_seconds) + 1)

        def run() -> None:
            if cgroup is not None:
                cgroup.enter()
            limits.apply()

        return run

    def cgroup(self) -> Cgroup | None:
        """A cgroup with this isolation's totals for one process tree (None where none can be made)."""
        if not self.namespaces:
            return None
        return Cgroup.create(self.limits.memory_total_bytes, self.limits.processes_total)


def _python_homes() -> list[str]:
    """The folders of the Python installation (the environment and the interpreter it was made from)."""
    homes = {sys.prefix, sys.base_prefix, sys.exec_prefix, sys.base_exec_prefix,
             os.path.dirname(os.path.dirname(os.path.realpath(sys.executable)))}
    return sorted(h for h in homes if h and h != "/")


def student_library(out_dir: Path, notebooks_dir: Path | None = None) -> Path:
    """Write the student release's ``course_lib`` and ``data`` into ``out_dir`` (what a student's code may import)."""
    from course_lib.instructor.notebooks import NOTEBOOKS_DIR
    from course_lib.instructor.release import release_files

    files = release_files(Path(notebooks_dir or NOTEBOOKS_DIR))
    out_dir = Path(out_dir)
    for rel, data in sorted(files.items()):
        if rel.startswith(("course_lib/", "data/")):
            dst = out_dir / rel
            dst.parent.mkdir(parents=True, exist_ok=True)
            dst.write_bytes(data)
    return out_dir


class StudentProcessEnded(Exception):
    """Raised by a remote call once the student's process has ended (time limit, exit, crash)."""


class StudentError(Exception):
    """An exception of a type the grader does not import, raised by the student's code."""


_EXC_TYPES: dict[str, type] = {}


def _student_exception(reply: dict) -> BaseException:
    name = wire._ident(reply.get("type", "Exception"), "Exception")
    msg = str(reply.get("message", "")) + str(reply.get("where", ""))
    cls = getattr(builtins, name, None) if reply.get("builtin") else None
    if not (isinstance(cls, type) and issubclass(cls, Exception)) or cls is StopIteration:
        cls = _EXC_TYPES.setdefault(name, type(name, (StudentError,), {}))
    try:
        return cls(msg)
    except Exception:  # noqa: BLE001 - exception types with other constructors (UnicodeDecodeError)
        return _EXC_TYPES.setdefault(name, type(name, (StudentError,), {}))(msg)


def _signal_name(num: int) -> str:
    try:
        return signal.Signals(num).name
    except ValueError:
        return f"signal {num}"


class StudentProcess:
    """One student's exercise code in its own sandboxed process, called by the grader with data.

    Args:
        iso: the grading run's :class:`Isolation`.
        code: the extracted exercise code (imports, helpers and the def).
        name: the exercise (the name the code defines).
        submission: the student's folder (copied; the copy is the process's working directory).
        budget: wall-clock seconds for everything this process does for the grader.
        torch: import torch at start (the NeRF exercises).
        oracle: answers the call-backs of the earlier exercises the code calls (:mod:`course_lib.instructor.oracle`);
            their names are bound to stubs in the process after the code is loaded.
    """

    def __init__(self, iso: Isolation, code: str, name: str, submission: Path | None, budget: float,
                 torch: bool = False, oracle=None):
        self.iso, self.name, self.budget, self.oracle = iso, name, float(budget), oracle
        self.t0 = time.monotonic()
        self.deadline = self.t0 + max(self.budget, START_SECONDS)  # the start: Python, numpy and torch imports
        self.ended: str | None = None  # why the process is gone (feedback for the student)
        self.event: str | None = None  # "timeout", "exit", "crash", "protocol", "limit"
        self.hello: dict = {}
        self.tmp = Path(tempfile.mkdtemp(prefix="course-student-"))
        os.chmod(self.tmp, 0o755)
        self.cwd = self.tmp / "work"  # filled from the submission's copy inside the sandbox
        self.cwd.mkdir()
        stage = self.tmp / "stage"
        stage.mkdir()
        seed = Path(submission) if submission is not None and Path(submission).is_dir() else None
        req_r, self.req_w = os.pipe()
        self.rep_r, rep_w = os.pipe()
        cfg = {"sandbox": iso.sandbox_config(stage, self.cwd, seed), "cwd": str(self.cwd), "path": str(iso.library),
               "sys_path": iso.python_path(), "code": code, "name": name, "torch": bool(torch),
               "req_fd": req_r, "rep_fd": rep_w, "oracle": oracle.names if oracle is not None else []}
        (self.tmp / "config.json").write_text(json.dumps(cfg))
        env = {k: v for k, v in os.environ.items() if k in ("PATH", "LANG", "LC_ALL", "TZ")}
        env.update(HOME=str(self.cwd), TMPDIR="/tmp", OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
                   MKL_NUM_THREADS="1", PYTHONDONTWRITEBYTECODE="1", MPLBACKEND="Agg", COURSE_LIB_QUICK="1")
        self.cgroup = iso.cgroup()
        self.largest_reply = 0
        self.unpacked_at = time.monotonic()
        self.proc = subprocess.Popen(
            [sys.executable, "-S", "-E", str(CHILD_SCRIPT), "serve", str(self.tmp / "config.json")],
            cwd=self.cwd, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            pass_fds=(req_r, rep_w), start_new_session=True,
            preexec_fn=iso.preexec(self.budget + 30, self.cgroup))
        os.close(req_r)
        os.close(rep_w)
        self.sandbox = self._sandbox_report(iso)
        reply = self._receive() if not self.ended else None
        if reply is not None:
            self.hello = reply[0]
        self.hello["sandbox"] = self.sandbox  # the grader's record, never the student's

    def _sandbox_report(self, iso: Isolation) -> dict:
        """What confines the process: its first frame (written before any code of the student's ran) and the totals."""
        first = self._receive()
        self.t0 = time.monotonic()  # the exercise's budget counts from here: its definitions and every call
        self.deadline = self.t0 + self.budget
        box = first[0].get("sandbox") if first is not None and first[0].get("event") == "sandbox" else None
        if not isinstance(box, dict):
            box = {"note": "the process did not report its sandbox"}
        box = {str(k): v if isinstance(v, (str, bool)) else str(v) for k, v in box.items()}
        box.update(iso.limits.totals(self.cgroup))
        return box

    # -- the connection ------------------------------------------------------------------------
    def _remaining(self) -> float:
        return self.deadline - time.monotonic()

    def _read_exact(self, n: int) -> bytearray:
        """``n`` bytes of the reply pipe, read as they come (the buffer grows with what arrived, never ahead of it)."""
        buf = bytearray()
        while len(buf) < n:
            wait = self._remaining()
            if wait <= 0 or not select.select([self.rep_r], [], [], wait)[0]:
                raise TimeoutError
            b = os.read(self.rep_r, min(n - len(buf), 1 << 20))
            if not b:
                raise EOFError
            buf += b
        return buf

    def _receive(self) -> tuple[dict, list] | None:
        """The next reply; None (and :attr:`ended` set) when the process ended, ran out of time or sent no reply."""
        try:
            (n,) = struct.unpack("<Q", self._read_exact(8))
            if n > wire.MAX_REPLY:
                raise wire.WireError(f"a reply of {n} bytes, more than any exercise returns "
                                     f"(the limit is {wire.MAX_REPLY >> 20} MiB)")
            self.largest_reply = max(self.largest_reply, n)
            data = self._read_exact(n)
            self.unpacked_at = time.monotonic()  # a call-back's time counts from here (see _answer_oracle)
            head, arrays = wire.unpack(data)
        except TimeoutError:
            self._end("timeout", f"stopped after {self.budget:g} s: an endless loop, or far too slow "
                                 f"(the time limit of one exercise is {self.budget:g} s)")
            return None
        except EOFError:
            self._end_from_exit()
            return None
        except Exception as exc:  # noqa: BLE001 - whatever arrives, the grader goes on
            self._end("protocol", "the process running your function sent something that is not a reply "
                                  f"({type(exc).__name__}: {str(exc)[:200]})")
            return None
        if head.get("event") == "exit":
            code = head.get("code")
            self._end("exit", f"your function ended the process with os._exit({code if isinstance(code, int) else 1})")
            return None
        return head, arrays

    def _end_from_exit(self) -> None:
        try:
            rc = self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            rc = None
        if self.cgroup is not None and self.cgroup.oom_killed():
            why = ("the process running your function (with the processes it started) used more memory than the "
                   f"limit ({self.iso.limits.memory_total_bytes >> 20} MiB in all) and was stopped")
        elif rc is not None and rc > 128 and rc - 128 in (signal.SIGXCPU, signal.SIGKILL):
            why = f"the process running your function used up its CPU time limit ({int(self.budget) + 31} s)"
        elif rc is not None and (rc < 0 or rc > 128):
            why = f"the process running your function was stopped by {_signal_name(abs(rc) if rc < 0 else rc - 128)}"
        else:
            why = f"the process running your function ended (exit code {rc}) before it replied: sys.exit, os._exit " \
                  "or a crash"
        self._end("exit", why)

    def _end(self, event: str, why: str) -> None:
        if self.ended is None:
            self.event, self.ended = event, why
        self.kill()

    def _send(self, head: dict, arrays: list) -> bool:
        data = wire.pack(head, arrays)
        view = memoryview(struct.pack("<Q", len(data)) + data)
        try:
            while view:
                wait = self._remaining()
                if wait <= 0 or not select.select([], [self.req_w], [], wait)[1]:
                    raise TimeoutError
                view = view[os.write(self.req_w, view[: 1 << 16]):]
        except TimeoutError:
            self._end("timeout", f"stopped after {self.budget:g} s: an endless loop, or far too slow")
            return False
        except (BrokenPipeError, OSError):
            self._end_from_exit()
            return False
        return True

    # -- calls ------------------------------------------------------------------------------------
    def call(self, args: tuple, kwargs: dict, handle: int | None = None, params: list | None = None):
        """Call the student's object (or handle) with data; the result as data, or the student's exception raised."""
        import numpy as np

        if self.ended:
            raise StudentProcessEnded(self.ended)
        arrays: list = []
        callbacks: list = []
        head = {"op": "call", "h": handle, "args": wire.encode(tuple(args), arrays, callbacks),
                "kwargs": wire.encode(dict(kwargs), arrays, callbacks), "rng": self._rng_out(arrays),
                "grad": _grad_enabled()}
        if params:
            head["params"] = []
            for name, value in params:
                arrays.append(np.asarray(value))
                head["params"].append([name, len(arrays) - 1])
        if not self._send(head, arrays):
            raise StudentProcessEnded(self.ended)
        got = self._receive()
        while got is not None and got[0].get("event") == "oracle":
            got = self._answer_oracle(*got)
        if got is None:
            raise StudentProcessEnded(self.ended)
        reply, out = got
        if not reply.get("ok"):
            if reply.get("wire"):
                raise TypeError(reply.get("message", "the result cannot be sent to the grader"))
            raise _student_exception(reply)
        try:
            value = wire.decode(reply["value"], out, module_proxy=lambda tree, arrs: RemoteModule.make(self, tree, arrs))
            replay = wire.decode(reply.get("callbacks"), out) or []
            replay = [(callbacks[int(i)], tuple(a), dict(k)) for i, a, k in replay]
        except Exception as exc:  # noqa: BLE001 - a forged reply ends this exercise, not the grading
            self._end("protocol", f"the process running your function sent a malformed reply ({type(exc).__name__}: "
                                  f"{str(exc)[:200]})")
            raise StudentProcessEnded(self.ended) from None
        for cb, a, k in replay:
            cb(*a, **k)  # the grader's callbacks, replayed in order after the call
        self._rng_in(reply.get("rng"), out)
        self._generators_in(reply.get("gens"), out, args, kwargs)
        return value

    def _answer_oracle(self, head: dict, arrays: list) -> tuple[dict, list] | None:
        """Answer a call-back of the student's code (an earlier exercise, by its reference); then the next frame.

        The grader's time on it (from the request's arrival to the reply's departure, plus
        :data:`~course_lib.instructor.oracle.ROUND_TRIP_SECONDS` for the transport on the student's side) is added
        to the exercise's deadline, up to the oracle's allowance; more call-backs than
        :data:`~course_lib.instructor.oracle.MAX_CALLS` end the process.
        """
        from course_lib.instructor.oracle import MAX_CALLS, ROUND_TRIP_SECONDS

        if self.oracle is None or self.oracle.calls >= MAX_CALLS:
            why = (f"your {self.name} called the earlier exercises ({', '.join(self.oracle.names)}) more than "
                   f"{MAX_CALLS} times; the grader answers at most that many calls per exercise"
                   if self.oracle is not None else "the process asked the grader for an earlier step it does not need")
            self._end("limit", why)
            return None
        t0 = self.unpacked_at
        reply, out = self.oracle.answer(head, arrays, self._remaining())
        sent = self._send(reply, out)
        self.deadline += self.oracle.credit(time.monotonic() - t0 + ROUND_TRIP_SECONDS)
        return self._receive() if sent else None

    @staticmethod
    def _rng_in(state, arrays: list) -> None:
        """The global random states the student's call left, set here: as in a notebook, a function that seeds or
        draws from np.random (or torch's global generator) changes its caller's state (the checks test that it does
        not). A state that cannot be set is ignored."""
        if not isinstance(state, dict):
            return
        import numpy as np

        try:
            if state.get("np") is not None:
                np.random.set_state(tuple(wire.decode(state["np"], arrays)))
            torch = sys.modules.get("torch")
            if torch is not None and state.get("torch") is not None:
                torch.set_rng_state(wire.decode(state["torch"], arrays))
        except Exception:  # noqa: BLE001 - a malformed state changes nothing
            pass

    @staticmethod
    def _generators_in(gens, arrays: list, args: tuple, kwargs: dict) -> None:
        """The states of the generator arguments after the student's call, set in the caller's generators: as in a
        notebook, an rng the function drew from has advanced (the checks test that the function draws from it)."""
        import numpy as np

        torch = sys.modules.get("torch")
        for entry in gens if isinstance(gens, list) else []:
            try:
                (kind, at), tree = entry
                mine = args[int(at)] if kind == "a" else kwargs[str(at)]
                theirs = wire.decode(tree, arrays)
                if isinstance(mine, np.random.Generator) and isinstance(theirs, np.random.Generator):
                    mine.bit_generator.state = theirs.bit_generator.state
                elif torch is not None and isinstance(mine, torch.Generator) and isinstance(theirs, torch.Generator):
                    mine.set_state(theirs.get_state())
            except Exception:  # noqa: BLE001 - a malformed entry changes nothing
                continue

    @staticmethod
    def _rng_out(arrays: list) -> dict:
        import numpy as np

        out = {"np": wire.encode(list(np.random.get_state()), arrays)}
        torch = sys.modules.get("torch")
        if torch is not None:
            out["torch"] = wire.encode(torch.get_rng_state(), arrays)
        return out

    # -- the end ------------------------------------------------------------------------------------
    def kill(self) -> None:
        if self.proc.poll() is None:
            kill_tree(self.proc.pid)
        if self.cgroup is not None:
            self.cgroup.close()
        try:
            self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:  # pragma: no cover
            pass

    def close(self) -> None:
        if self.oracle is not None:
            self.oracle.close()
        if self.proc.poll() is None and not self.ended:
            try:
                os.set_blocking(self.req_w, False)
                os.write(self.req_w, struct.pack("<Q", len(b := wire.pack({"op": "bye"}, []))) + b)
            except OSError:
                pass
            try:
                self.proc.wait(timeout=2)
            except subprocess.TimeoutExpired:
                pass
        self.kill()
        if self.cgroup is not None:
            self.cgroup.close()
        for fd in (self.req_w, self.rep_r):
            try:
                os.close(fd)
            except OSError:
                pass
        shutil.rmtree(self.tmp, ignore_errors=True)

    def __enter__(self) -> "StudentProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def seconds(self) -> float:
        return time.monotonic() - self.t0


def kill_tree(pid: int) -> None:
    """SIGKILL a sandbox launcher, its process group and its direct children.

    The launcher's child is process 1 of the sandbox's PID namespace: when it dies, Linux kills
    every process in that namespace, including those that left the process group (``setsid``).
    """
    try:
        kids = [int(k) for t in os.listdir(f"/proc/{pid}/task")
                for k in open(f"/proc/{pid}/task/{t}/children").read().split()]
    except OSError:
        kids = []
    for k in kids:
        try:
            os.kill(k, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
    for kill, target in ((os.killpg, pid), (os.kill, pid)):
        try:
            kill(target, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass


def _grad_enabled() -> bool:
    torch = sys.modules.get("torch")
    return bool(torch.is_grad_enabled()) if torch is not None else True


class RemoteFunction:
    """The student's function (or class) as the check sees it: each call goes to the student's process."""

    def __init__(self, proc: StudentProcess, name: str):
        self._proc = proc
        self.__name__ = self.__qualname__ = name

    def __call__(self, *args, **kwargs):
        return self._proc.call(args, kwargs)

    def __repr__(self) -> str:
        return f"<your {self.__name__}, running in its own process>"


class RemoteModule:
    """Placeholder; :meth:`make` builds the ``torch.nn.Module`` subclass (torch is imported lazily)."""

    _cls = None

    @classmethod
    def make(cls, proc: StudentProcess, tree: dict, arrays: list):
        if RemoteModule._cls is None:
            RemoteModule._cls = _remote_module_class()
        name = wire._ident(tree.get("n", "Module"), "Module")
        sub = type(name, (RemoteModule._cls,), {})
        return sub(proc, tree, arrays)


def _remote_module_class():
    import torch

    class _Remote(torch.nn.Module):
        """A student's ``nn.Module`` living in the student's process: its parameters and linear layers are mirrored here;
        ``forward`` sends the current parameters and the inputs there and returns the result."""

        def __init__(self, proc: StudentProcess, tree: dict, arrays: list):
            super().__init__()
            names, mirror = [], []
            for name, k in tree["params"]:
                names.append(str(name))
                mirror.append(torch.nn.Parameter(torch.from_numpy(arrays[int(k)].copy())))
            linear = [torch.nn.Linear(int(i), int(o), bias=bool(b), device="meta") for i, o, b in tree["linear"]]
            object.__setattr__(self, "_r", {"proc": proc, "h": int(tree["h"]), "names": names, "mirror": mirror,
                                            "linear": linear})

        def parameters(self, recurse: bool = True):
            yield from self._r["mirror"]

        def named_parameters(self, prefix: str = "", recurse: bool = True, remove_duplicate: bool = True):
            for n, p in zip(self._r["names"], self._r["mirror"]):
                yield (f"{prefix}.{n}" if prefix else n), p

        def modules(self):
            yield self
            yield from self._r["linear"]

        def named_modules(self, memo=None, prefix: str = "", remove_duplicate: bool = True):
            yield prefix, self
            for i, m in enumerate(self._r["linear"]):
                yield f"{prefix}.linear{i}" if prefix else f"linear{i}", m

        def forward(self, *args, **kwargs):
            r = self._r
            params = [(n, p.detach().cpu().numpy()) for n, p in zip(r["names"], r["mirror"])]
            return r["proc"].call(args, kwargs, handle=r["h"], params=params)

        def extra_repr(self) -> str:
            return "running in the student's process"

    return _Remote

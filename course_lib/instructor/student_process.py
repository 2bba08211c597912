"""The grader's side of the separation: the student's code runs in a sandboxed process, called as data.

The check function of an exercise runs in the grader's exercise worker (:func:`course_lib.instructor.hidden.run_hidden`)
with the full library and the hidden cases; the student's function it receives is a proxy
(:mod:`course_lib.instructor.remote`) whose calls go to a :class:`StudentProcess`: the arguments are sent as data
(:mod:`course_lib.instructor.sandbox.wire`: JSON and ``np.save`` arrays, never pickle) to a process that holds only
the student's extracted code and the student release of ``course_lib``, and the result is decoded here.

The process is started in the run's isolation mode and checked before any of the student's code runs
(:mod:`course_lib.instructor.sandbox.launch`: fail closed); it works in a fresh copy of the grader's copy of the
submission, under the limits of :class:`~course_lib.instructor.settings.Limits` and the totals of its exercise's
cgroup. With every call it receives the grader's global numpy and torch random states (so that
``torch.manual_seed(0)`` in a check seeds the student's initialisation as in the notebook); its call-backs to the
earlier exercises are answered by their references (:mod:`course_lib.instructor.oracle`). **One clock**: its
definitions, every call, the decoding of its replies and the call-backs share the exercise's budget, counted once the
process has started (:data:`~course_lib.instructor.settings.START_SECONDS`); when it runs out, the process is killed
and every later call fails at once.

A reply is checked before anything is built from it: at most ``wire.MAX_REPLY`` bytes, read as they arrive, bounded
as :func:`wire.unpack` says; a sparse matrix whose declared shape is within :data:`SPARSE_SLACK` times the size of
the expected answer's (:meth:`StudentProcess.call`'s ``expect``); a module whose layers match the weights it sent.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from course_lib.instructor import oracle as oracle_module
from course_lib.instructor.remote import remote_module
from course_lib.instructor.sandbox import jail, launch, wire
from course_lib.instructor.settings import START_SECONDS, Isolation

__all__ = ["StudentProcess", "StudentProcessEnded"]


class StudentProcessEnded(Exception):
    """Raised by a remote call once the student's process has ended (time limit, exit, crash)."""


class StudentError(Exception):
    """An exception of a type the grader does not import, raised by the student's code."""


_EXC_TYPES: dict[str, type] = {}


def _student_exception(reply: dict) -> BaseException:
    name = wire.ident(reply.get("type", "Exception"), "Exception")
    msg = str(reply.get("message", ""))[:2000] + str(reply.get("where", ""))[:100]
    cls = wire.builtin_exception(reply) or _EXC_TYPES.setdefault(name, type(name, (StudentError,), {}))
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
        iso: the grading run's :class:`~course_lib.instructor.settings.Isolation`.
        code: the extracted exercise code (imports, helpers and the def).
        name: the exercise (the name the code defines).
        submission: the grader's copy of the student's folder (copied again into the process's working folder).
        budget: wall-clock seconds for everything this process does for the grader.
        torch: import torch at start (the NeRF exercises).
        oracle: answers the call-backs of the earlier exercises the code calls (:mod:`course_lib.instructor.oracle`);
            their names are bound to stubs in the process after the code is loaded.
        cgroup: the cgroup the process enters (None: the caller's own, e.g. the exercise worker's).
        engines: the kit's engines that compute this exercise (``module.attr``), closed in the process before the
            student's code runs (:attr:`course_lib.exercise_table.Exercise.engines`).

    Raises:
        IsolationError: the sandbox cannot be made or verified (and the run is not ``insecure``).
    """

    def __init__(self, iso: Isolation, code: str, name: str, submission: Path | None, budget: float,
                 torch: bool = False, oracle=None, cgroup=None, engines: tuple[str, ...] = ()):
        self.iso, self.name, self.budget, self.oracle, self.cgroup = iso, name, float(budget), oracle, cgroup
        self.engines = engines
        self.t0 = time.monotonic()
        self.deadline = self.t0 + START_SECONDS  # the start: Python, numpy and torch imports
        self.ended: str | None = None  # why the process is gone (feedback for the student)
        self.event: str | None = None  # "timeout", "exit", "crash", "protocol", "limit"
        self.hello: dict = {}
        self.largest_reply = 0
        self.req_w = self.rep_r = -1
        self.proc = None
        self.sandbox: dict = {}  # what confines the process (the grader's record, never the student's)
        self.tmp = jail.private_folder("course-student-", iso.scratch)
        try:
            self._start(code, submission, torch)
        except BaseException:
            self.close()
            raise

    def _start(self, code: str, submission: Path | None, torch: bool) -> None:
        iso = self.iso
        seed = Path(submission).resolve() if submission is not None and Path(submission).is_dir() else None
        cwd, seed_at = launch.paths(iso, self.tmp, seed)
        req_r, self.req_w = os.pipe()
        self.rep_r, rep_w = os.pipe()
        cfg = {"cwd": cwd, "seed": seed_at, "path": str(iso.library), "sys_path": iso.python_path(), "code": code,
               "name": self.name, "torch": bool(torch), "req_fd": req_r, "rep_fd": rep_w,
               "oracle": self.oracle.names if self.oracle is not None else [],
               "engines": list(self.engines)}
        with open(self.tmp / "stderr.txt", "wb") as stderr:
            self.started = launch.start(iso, "serve", cfg, self.tmp, seed, self.cgroup, self.budget + 30,
                                        launch.env(cwd), [req_r, rep_w], stderr)
        self.proc = self.started.proc
        first = self._receive()
        secure = self.started.mode != launch.INSECURE
        if secure and ((not self.started.info and self.started.mode == launch.BUBBLEWRAP)
                       or (first is None and self.event != "timeout")):
            said = ""
            with contextlib.suppress(OSError):  # unreadable: the refusal still comes, without the launcher's words
                said = (self.tmp / "stderr.txt").read_text(errors="replace")[:2000]  # the launcher's, bwrap's words
            raise launch.refuse_start(self.started, said or self.ended or "")
        if first is None:  # the process did not start in time: none of the student's code ran
            self.ended = (f"the process for your {self.name} did not start within {START_SECONDS:g} s (the machine is "
                          "overloaded); none of your code ran")
            self.sandbox = {"note": "the process did not start"}
            return
        facts = first[0].get("facts") if first[0].get("event") == "sandbox" else None
        self.sandbox = launch.check(self.started, iso, facts if isinstance(facts, dict) else {}, self.cgroup)
        if first[0].get("seed_failed"):  # the submission's problem, reported as this exercise's; nothing of it ran
            self._end("exit", "your submission could not be copied into the sandbox's working folder "
                              f"({str(first[0]['seed_failed'])[:200]}); none of your code ran")
            self.sandbox = {"note": "the submission could not be copied into the sandbox"}
            return
        self._send({"op": "go"}, [])
        self.t0 = time.monotonic()  # the exercise's budget counts from here: its definitions and every call
        self.deadline = self.t0 + self.budget
        reply = self._receive() if not self.ended else None
        self.hello = reply[0] if reply is not None else {}

    # -- the connection ------------------------------------------------------------------------
    def _remaining(self) -> float:
        return self.deadline - time.monotonic()

    def _timeout_text(self) -> str:
        return (f"stopped after {self.seconds:.1f} s: an endless loop, or far too slow (the time limit of one "
                f"exercise is {self.budget:g} s, for your code, the grader's checks of its results and the earlier "
                "steps it calls)")

    def _receive(self) -> tuple[dict, list] | None:
        """The next reply; None (and :attr:`ended` set) when the process ended, ran out of time or sent no reply."""
        try:
            (n,) = struct.unpack("<Q", wire.read_exact(self.rep_r, 8, self.deadline))
            if n > wire.MAX_REPLY:
                raise wire.WireError(f"a reply of {n} bytes, more than any exercise returns "
                                     f"(the limit is {wire.MAX_REPLY >> 20} MiB)")
            self.largest_reply = max(self.largest_reply, n)
            data = wire.read_exact(self.rep_r, n, self.deadline)
            head, arrays = wire.unpack(data)
        except TimeoutError:
            self._end("timeout", self._timeout_text())
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
            why = ("the process running your function (with the processes it started and the grader's work on its "
                   f"results) used more memory than the limit ({self.cgroup.memory_bytes >> 20} MiB in all) and "
                   "was stopped")
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
        try:
            wire.write_frame(self.req_w, head, arrays, self.deadline)
        except TimeoutError:
            self._end("timeout", self._timeout_text())
            return False
        except OSError:  # the process ended (a broken pipe)
            self._end_from_exit()
            return False
        return True

    # -- calls ------------------------------------------------------------------------------------
    def call(self, args: tuple, kwargs: dict, handle: int | None = None, params: list | None = None, expect=None):
        """Call the student's object (or handle) with data; the result as data, or the student's exception raised.

        ``expect``: a function of no arguments that returns the expected answer of this call (the reference's
        result); it is called only when the reply declares something it does not send (a sparse matrix's shape),
        which is then checked against the expected answer's before anything is built.
        """
        if self.ended:
            raise StudentProcessEnded(self.ended)
        arrays: list = []
        callbacks: list = []
        head = {"op": "call", "h": handle, "args": wire.encode(tuple(args), arrays, callbacks),
                "kwargs": wire.encode(dict(kwargs), arrays, callbacks), "rng": wire.global_rng(arrays),
                "grad": torch.is_grad_enabled() if (torch := sys.modules.get("torch")) is not None else True}
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
                raise TypeError(str(reply.get("message", "the result cannot be sent to the grader"))[:2000])
            raise _student_exception(reply)
        try:
            sizes = wire.declared(reply.get("value"))
            wire.declared(reply.get("callbacks"))
        except Exception as exc:  # noqa: BLE001 - a forged reply ends this exercise, not the grading
            raise self._malformed(exc) from None
        _check_sparse(self.name, [s for s in sizes if s[0] == "sparse"], expect)
        try:
            value = wire.decode(reply["value"], out, module_proxy=lambda tree, arrs: remote_module(self, tree, arrs))
            replay = wire.decode(reply.get("callbacks"), out) or []
            replay = [(callbacks[int(i)], tuple(a), dict(k)) for i, a, k in replay]
        except Exception as exc:  # noqa: BLE001 - a forged reply ends this exercise, not the grading
            raise self._malformed(exc) from None
        for cb, a, k in replay:
            cb(*a, **k)  # the grader's callbacks, replayed in order after the call
        try:  # the global random states the student's call left, set here, as in a notebook (the checks test it)
            wire.set_global_rng(reply.get("rng"), out)
        except Exception:  # noqa: BLE001 - a malformed state changes nothing
            pass
        self._generators_in(reply.get("gens"), out, args, kwargs)
        return value

    def _malformed(self, exc: Exception) -> StudentProcessEnded:
        """End the exercise on a reply that cannot be read (forged, or broken): the exception for the check."""
        self._end("protocol", f"the process running your function sent a malformed reply ({type(exc).__name__}: "
                              f"{str(exc)[:200]})")
        return StudentProcessEnded(self.ended)

    def _answer_oracle(self, head: dict, arrays: list) -> tuple[dict, list] | None:
        """Answer a call-back of the student's code (an earlier exercise, by its reference); then the next frame.

        Its time is the exercise's (one clock): the reference is stopped when the exercise's time is up. More
        call-backs than :data:`~course_lib.instructor.oracle.MAX_CALLS` end the process.
        """
        if self.oracle is None or self.oracle.calls >= oracle_module.MAX_CALLS:  # read at the call (a test lowers it)
            why = (f"your {self.name} called the earlier exercises ({', '.join(self.oracle.names)}) more than "
                   f"{oracle_module.MAX_CALLS} times; the grader answers at most that many calls per exercise"
                   if self.oracle is not None else "the process asked the grader for an earlier step it does not need")
            self._end("limit", why)
            return None
        reply, out = self.oracle.answer(head, arrays, self._remaining())
        if self._remaining() <= 0 or reply.get("deadline"):  # the exercise's time ran out in the call-back
            self._end("timeout", self._timeout_text())
            return None
        sent = self._send(reply, out)
        return self._receive() if sent else None

    @staticmethod
    def _generators_in(gens, arrays: list, args: tuple, kwargs: dict) -> None:
        """The states of the generator arguments after the student's call, set in the caller's generators: as in a
        notebook, an rng the function drew from has advanced (the checks test that the function draws from it)."""
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

    # -- the end ------------------------------------------------------------------------------------
    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            jail.kill_tree(self.proc.pid)
        if self.proc is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):  # pragma: no cover
                self.proc.wait(timeout=5)

    def close(self) -> None:
        if self.oracle is not None:
            self.oracle.close()
        if self.proc is not None and self.proc.poll() is None and not self.ended:
            try:
                os.set_blocking(self.req_w, False)
                wire.write_frame(self.req_w, {"op": "bye"})
            except OSError:
                pass
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(timeout=2)
        self.kill()
        wire.close_fds((self.req_w, self.rep_r))
        self.req_w = self.rep_r = -1
        shutil.rmtree(self.tmp, ignore_errors=True)

    def __enter__(self) -> "StudentProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def seconds(self) -> float:
        return time.monotonic() - self.t0


def _shapes_of(value, out: set, depth: int = 0) -> set:
    """The shapes of every array, tensor and sparse matrix in an expected answer (tuples, lists, dicts, records)."""
    if hasattr(value, "shape") and hasattr(value, "dtype"):
        out.add(tuple(int(n) for n in value.shape))
    elif depth < 20:
        parts = (value.values() if isinstance(value, dict) else value if isinstance(value, (tuple, list)) else
                 vars(value).values() if hasattr(value, "__dict__") and not isinstance(value, type) else ())
        for v in list(parts)[:1000]:
            _shapes_of(v, out, depth + 1)
    return out


#: A declared sparse matrix is built when it has at most this many times the cells of the expected answer's largest
#: matrix (a transposed or miscounted pattern still reaches the check, which names the mistake), plus a few.
SPARSE_SLACK, SPARSE_EXTRA_CELLS = 4, 4096


def _check_sparse(name: str, sparse: list[tuple], expect) -> None:
    """Refuse (``ValueError``, as the student's function would raise it), before it is built, a declared sparse
    matrix much larger than the expected answer (the reference's result on the same arguments): more than
    :data:`SPARSE_SLACK` times the cells of its largest matrix; without an expected answer, more than
    ``wire.MAX_SPARSE_CELLS`` cells."""
    if not sparse:
        return
    shapes = None
    if expect is not None:
        try:
            shapes = _shapes_of(expect(), set())
        except Exception:  # noqa: BLE001 - the reference cannot answer this call: the plain bound applies
            shapes = None
    cells = lambda shape: int(np.prod(shape, dtype=object)) if shape else 1  # noqa: E731
    limit = (SPARSE_SLACK * max(map(cells, shapes), default=0) + SPARSE_EXTRA_CELLS if shapes is not None
             else wire.MAX_SPARSE_CELLS)
    for _, path, shape in sparse:
        if cells(shape) > limit:
            want = (f"the expected answer has shape {' or '.join(str(s) for s in sorted(shapes)[:3])}"
                    if shapes else f"no exercise returns more than {limit} cells")
            raise ValueError(f"your {name} returned a sparse matrix of shape {shape} (at {path}); {want}, so the "
                             "grader did not build it")

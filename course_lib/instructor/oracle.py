"""Each exercise graded on its own: the earlier exercises it calls answer with the reference's results.

An exercise often calls the student's own earlier exercises (``eight_point`` calls
``normalize_points``, ``ransac_fundamental`` calls ``eight_point`` and ``sampson_distance``,
``pnp_ransac`` calls ``pnp_linear``, ``choose_pose`` calls ``triangulate_linear``, ``bundle_adjust``
calls ``reprojection_residuals`` and ``jacobian_sparsity``, the ``NeRF`` of notebook 07 calls
``positional_encoding``). Graded with the student's own earlier functions, one mistake would cost
points in every exercise after it. So, while the grader checks exercise X, the earlier exercises
that X's extracted code binds (:func:`earlier_steps`) are answered by their **reference**, through
a synchronous call-back:

* in X's sandboxed process, after the student's code is loaded, each such name of ``__main__`` is
  rebound to a neutral wire stub (``sandbox.server.oracle_stub``: it holds no reference code, it sends its
  arguments as data and returns the answer; the kit's stand-ins of the same name find it there);
* the grader, while it waits for X's reply, receives the stub's request and passes its arguments on,
  undecoded, to an :class:`Oracle`: a worker process forked from the grader (it has the full
  library) that decodes the arguments, runs the reference, and sends the result back as data; the grader forwards it to
  X's process, and X goes on. An exception of the reference (junk arguments) is raised in X's
  process with the reference's message, as the reference would raise it. A call that the
  reference cannot answer (arguments that do not fit its signature: the student's function has
  another interface; values that cannot be sent as data) is answered by the student's own function.

Bounds (per exercise): at most :data:`MAX_CALLS` call-backs (then X's process is stopped), each
request and each result at most ``wire.MAX_REPLY`` bytes (the stub refuses a larger argument
with a ``ValueError``), and **one clock**: the call-backs' time is X's time, on X's budget
(:func:`course_lib.instructor.settings.exercise_seconds`), and a reference that runs longer than
what is left of it is stopped (its worker is killed, and the stub raises ``TimeoutError``). The
worker, not the grader, decodes the student's data and runs the reference, under an address-space
limit and in the exercise's cgroup, so nothing the student sends can stop or exhaust the grader.

Only the exercises that come *before* X in the kit (notebook order, then cell order) and that X's
code binds are answered, never X itself, and only while X is graded; an earlier exercise that is a
class (``NeRF``) stays the student's (a module cannot travel as data). If X's code does not call Y
(it wrote the step inline, or captured its own function elsewhere), nothing changes.

**Why this cannot change Y's own grade.** Every exercise is graded in its own process
(:class:`~course_lib.instructor.student_process.StudentProcess`), made for it and ended after it.
The stubs exist only in X's process, and Y's grade comes from Y's own process, where Y is the
student's function (no stub of Y is bound there: an exercise is never its own earlier step). Y's
hidden checks call Y directly; nothing that happens in X's process reaches them.

The NeRF model (a :func:`~course_lib.instructor.remote.remote_module`) is no exception:
its forward pass runs in the student's process, where ``positional_encoding`` is the stub, so the
network is fed the reference's encoding of whatever it encodes. Gradients do not flow through a call-back
(the encoding of input points needs none). A numpy ``Generator`` argument travels as its state: the
student's generator is not advanced by the reference's draws.
"""

from __future__ import annotations

import importlib
import inspect
import os
import resource
import signal
import symtable
import time

from course_lib.instructor.sandbox import wire
from course_lib.threads import single_thread_math

__all__ = ["MAX_CALLS", "Oracle", "earlier_steps", "bound_address_space", "status_kib"]

#: Call-backs the grader answers while it grades one exercise; one more stops the exercise's process. An honest
#: ransac_fundamental makes ~800 on the hidden cases (eight_point and sampson_distance per sample); one without the
#: adaptive stop (a mistake the checks name) ~20 000: the cap lets that one be graded (docs/benchmarks.md).
MAX_CALLS = 50_000
#: Address space a worker may add to what it inherited from the grader.
WORKER_EXTRA_BYTES = 4 << 30


def earlier_steps(code: str, exercise: str, kit: list[tuple[str, str | None]]) -> dict[str, str]:
    """The earlier exercises that an exercise's extracted code binds, with their references.

    Args:
        code: the exercise's extracted code (:func:`course_lib.instructor.extract.extract_exercise`: a backward
            slice, so a name it binds is one the exercise needs: its own earlier function, or the kit's stand-in).
        exercise: the exercise's name.
        kit: every exercise of the kit in order, ``[(name, "module:attr" of its reference or None)]``.

    Returns:
        ``{name: reference}`` of the exercises before ``exercise`` that have a reference and that the code binds.
    """
    try:
        table = symtable.symtable(code, "<exercise>", "exec")
    except SyntaxError:
        return {}
    bound = {s.get_name() for s in table.get_symbols() if s.is_assigned() or s.is_imported()}
    names = [n for n, _ in kit]
    if exercise not in names:
        return {}
    before = kit[: names.index(exercise)]
    return {n: ref for n, ref in before if ref and n in bound and n != exercise}


class Oracle:
    """The grader's answers to the call-backs of one exercise's process: the references of its earlier steps.

    Args:
        exercise: the exercise being graded.
        steps: ``{name: "module:attr"}`` of the earlier exercises it may call (:func:`earlier_steps`).
    """

    def __init__(self, exercise: str, steps: dict[str, str]):
        self.exercise, self.steps = exercise, dict(steps)
        self.calls = 0
        self.pid: int | None = None
        self.fds: tuple[int, int] | None = None

    @property
    def names(self) -> list[str]:
        return sorted(self.steps)

    def answer(self, head: dict, arrays: list, seconds_left: float) -> tuple[dict, list]:
        """The reply to one call-back request (``head``: its name, args and kwargs as wire trees), within
        ``seconds_left`` (what is left of the exercise's budget)."""
        self.calls += 1
        name = head.get("name")
        if name not in self.steps:
            return _error("LookupError", f"the grader answers no call of {str(name)[:80]!r} while it grades "
                                         f"{self.exercise}"), []
        wait = max(0.0, seconds_left)
        t0 = time.monotonic()
        try:
            self._start()
            wire.write_frame(self.fds[1], {"name": name, "args": head.get("args"), "kwargs": head.get("kwargs")},
                             arrays)
            reply = wire.read_frame(self.fds[0], wire.MAX_REPLY + (1 << 20), t0 + wait)
        except TimeoutError:
            self.close()
            reply = (dict(_error("TimeoutError", f"the grader's {name} did not finish on these arguments in the "
                                                 f"{wait:.1f} s left of {self.exercise}'s time"), deadline=True), [])
        except (OSError, EOFError, ValueError, wire.WireError) as exc:
            self.close()
            reply = (_error("RuntimeError", f"the grader's {name} could not answer ({type(exc).__name__}: "
                                            f"{str(exc)[:200]})"), [])
        return reply

    def _start(self) -> None:
        if self.pid is not None:
            return
        req_r, req_w = os.pipe()
        rep_r, rep_w = os.pipe()
        pid = os.fork()
        if pid == 0:  # the worker: the grader's library, none of the grader's other files
            try:
                _worker(req_r, rep_w, self.steps)
            finally:
                os._exit(0)
        os.close(req_r)
        os.close(rep_w)
        self.pid, self.fds = pid, (rep_r, req_w)

    def close(self) -> None:
        """End the worker (at the end of the exercise, or when it cannot answer; a later call starts a new one)."""
        if self.pid is not None:
            try:
                os.kill(self.pid, signal.SIGKILL)
                os.waitpid(self.pid, 0)
            except (ProcessLookupError, ChildProcessError):
                pass
        wire.close_fds(self.fds or ())
        self.pid, self.fds = None, None


def status_kib(key: str) -> int:
    """A ``/proc/self/status`` figure in KiB (0 where there is none)."""
    try:
        with open("/proc/self/status") as f:
            return next(int(ln.split()[1]) for ln in f if ln.startswith(key + ":"))
    except (OSError, StopIteration, ValueError, IndexError):
        return 0


def bound_address_space(extra_bytes: int) -> None:
    """Let this process (a worker forked from the grader) add at most ``extra_bytes`` to the address space it has."""
    vm = status_kib("VmSize") << 10
    try:
        if vm:
            resource.setrlimit(resource.RLIMIT_AS, (vm + extra_bytes, vm + extra_bytes))
    except (ValueError, OSError):
        pass


def _error(kind: str, message: str) -> dict:
    return {"ok": False, "type": kind, "builtin": True, "message": message}


def _worker(req: int, rep: int, steps: dict[str, str]) -> None:
    """The worker's loop: decode a request, run the reference, send the result (or its exception) as data."""
    wire.close_inherited(req, rep)
    single_thread_math()
    bound_address_space(WORKER_EXTRA_BYTES)
    while True:
        try:
            head, arrays = wire.read_frame(req, trusted=True)
        except (EOFError, OSError):
            return
        reply, out = _run_reference(head, arrays, steps)
        wire.write_frame(rep, reply, out)


def _run_reference(head: dict, arrays: list, steps: dict[str, str]) -> tuple[dict, list]:
    """Decode the arguments, call the reference of ``head["name"]``, encode its result."""
    name = head.get("name")
    try:
        args = wire.decode(head.get("args"), arrays)
        kwargs = wire.decode(head.get("kwargs"), arrays)
        if not isinstance(args, tuple) or not isinstance(kwargs, dict) or not all(isinstance(k, str) for k in kwargs):
            raise wire.WireError("malformed call")
        module, attr = steps[name].split(":")
        fn = getattr(importlib.import_module(module), attr)
        try:
            inspect.signature(fn).bind(*args, **kwargs)
        except TypeError as exc:  # not the exercise's interface: the student's own function answers
            return {"ok": False, "unbound": True, "message": str(exc)[:500]}, []
        value = fn(*args, **kwargs)
        out: list = []
        tree = wire.encode(value, out)
    except wire.WireError as exc:
        return _error("TypeError", str(exc)), []
    except MemoryError:
        return _error("MemoryError", f"the grader's {name} ran out of memory on these arguments"), []
    except Exception as exc:  # noqa: BLE001 - the reference's own error, raised in the student's process
        base = next(c for c in type(exc).__mro__ if c.__module__ == "builtins")  # KitInputError -> ValueError
        name = type(exc).__name__[:80]
        return {"ok": False, "type": base.__name__, "builtin": True,
                "message": str(exc)[:2000] if base is type(exc) else f"{name}: {str(exc)[:2000]}"}, []
    size = sum(a.nbytes for a in out)
    if size > wire.MAX_REPLY:
        return _error("ValueError", f"the grader's {name} would return {size >> 20} MiB, more than the limit "
                                    f"({wire.MAX_REPLY >> 20} MiB)"), []
    return {"ok": True, "value": tree}, out

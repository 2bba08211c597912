"""Hidden checks: each exercise checked here, on new cases, while the student's code runs elsewhere.

* :func:`build_hidden_fixtures` makes the hidden cases of a grading run: the case builders of
  :mod:`course_lib.instructor.cases` (the instructor's full library) run again with every seeded
  ``numpy.random.default_rng`` salted by a grading-time seed, so the synthetic scenes are new; seed
  0, which the checks reuse for the student's own RANSAC calls, is kept. They stay in this
  process.
* :func:`run_hidden` runs the check function of the exercise on those cases
  (:func:`course_lib.fixtures.using_cases`) in a worker forked from the grader, with the student's function in a
  sandboxed process (:class:`course_lib.instructor.student_process.StudentProcess`); the grader itself only waits for
  the worker's verdict (data). :func:`run_reference` runs the instructor's solution here, for the expected verdicts.
* **The check cell's verdict, computed here.** When the hidden checks all pass, the same worker runs the check
  again on the notebook's own cases (the stored fixtures the check cell reads), with the same proxy, and sends
  what that check prints: the verdict of the nbval share comes from the grader, never from what the notebook's
  kernel prints (code in the notebook can filter or forge that, not this).
"""

from __future__ import annotations

import contextlib
import importlib
import io
import math
import os
import time
import types
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from course_lib.checks import core
from course_lib.exercise_table import EXERCISES
from course_lib.instructor.cases import builders
from course_lib.instructor.oracle import Oracle, bound_address_space, status_kib
from course_lib.instructor.remote import RemoteFunction
from course_lib.instructor.sandbox import jail, wire
from course_lib.instructor.settings import GRACE_SECONDS, START_SECONDS
from course_lib.instructor.student_process import StudentProcess
from course_lib.threads import single_thread_math

__all__ = ["build_hidden_fixtures", "build_in_process", "HiddenJob", "HiddenOutcome", "run_hidden", "run_check",
           "run_reference", "all_pass", "hold_in_memory"]


# ---------------------------------------------------------------------------------------------
# Hidden fixtures
# ---------------------------------------------------------------------------------------------

#: Seeds the check functions reuse when they call the student's function (kept unsalted).
KEPT_SEEDS = {0}


def build_in_process(name: str, salt: int) -> dict[str, np.ndarray]:
    """The hidden cases of fixture ``name`` for a grading ``salt``, built in this process."""
    original = np.random.default_rng

    def salted(seed=None):
        if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool) and int(seed) not in KEPT_SEEDS:
            return original(np.random.SeedSequence([int(salt) % 2**63, int(seed)]))
        return original(seed)

    np.random.default_rng = salted
    try:
        return builders()[name]()
    finally:
        np.random.default_rng = original


#: Hidden fixtures held in the grader's memory (folder -> name -> arrays); forked runs read them from here.
_MEMORY: dict[str, dict[str, dict[str, np.ndarray]]] = {}


def hold_in_memory(fixtures_dir: Path) -> None:
    """Load every fixture of ``fixtures_dir`` into this process, for the forked runs to use."""
    held = {}
    for p in sorted(Path(fixtures_dir).glob("*.npz")):
        with np.load(p, allow_pickle=False) as z:
            held[p.stem] = {k: z[k] for k in z.files}
    _MEMORY[str(fixtures_dir)] = held


def build_hidden_fixtures(out_dir: Path, check_modules: list[str], salt: int) -> dict[str, list[str]]:
    """Write the hidden cases of ``check_modules`` into ``out_dir`` (no step fixture: they are no cases), and hold
    them in this process's memory; ``{fixture: its keys}``. The reference library builds them, in this process
    (the grader has imported it and torch before, :func:`course_lib.instructor.grade_plan.prepare_hidden`)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    built = {}
    for name in builders(sorted(set(check_modules)), steps=False):
        arrays = build_in_process(name, salt)
        np.savez_compressed(out_dir / f"{name}.npz", **{k: np.asarray(v) for k, v in arrays.items()})
        built[name] = sorted(arrays)
    hold_in_memory(out_dir)
    return built


# ---------------------------------------------------------------------------------------------
# Running one exercise
# ---------------------------------------------------------------------------------------------


@dataclass
class HiddenJob:
    name: str  # the exercise
    code: str  # the extracted code
    check_module: str
    check_function: str
    fixtures_dir: str
    reference: str | None = None  # "module:attr" of the graded exercise's reference
    allow_reference: bool = False  # the instructor's self-test
    submission: str | None = None  # the student's folder (its copy is the working directory)
    steps: dict = field(default_factory=dict)  # earlier exercises it calls -> their references (oracle.earlier_steps)
    public_dir: str | None = None  # the notebook's own cases: the check runs on them too when the hidden ones pass
    reference_result: object = None  # the reference's CheckResult on the hidden cases (what "all pass" is)


@dataclass
class HiddenOutcome:
    status: str  # "ok", "timeout", "exit", "error"
    message: str = ""
    seconds: float = 0.0
    result: object = None  # the CheckResult of the hidden checks (computed in the exercise's worker)
    sandbox: dict = field(default_factory=dict)  # what the student's process was confined by
    attempted: bool = True  # False: every call of the student's function raised NotImplementedError (the stub)
    memory: dict = field(default_factory=dict)  # worker peak growth, exercise cgroup peak, largest reply (bytes)
    public: str | None = None  # what the check printed on the notebook's own cases (None: not run)
    public_note: str = ""  # why it was not run or did not finish

    @property
    def lines(self) -> list[str]:
        """The verdict lines ("  ✔ ..." / "  ✘ ...") of the hidden checks."""
        return list(self.result.lines) if self.result is not None else []

    @property
    def passing(self) -> list[str]:
        return [ln.strip()[2:] for ln in self.lines if ln.strip().startswith("✔")]

    @property
    def failing(self) -> list[str]:
        return [ln.strip()[2:] for ln in self.lines if ln.strip().startswith("✘")]


def run_check(check_module: str, check_function: str, fixtures_dir: str, obj) -> tuple[object, str]:
    """Run a check function in this process on the hidden cases; ``(CheckResult or None, printed text)``."""
    if fixtures_dir not in _MEMORY:
        hold_in_memory(Path(fixtures_dir))
    check_fn = getattr(importlib.import_module(check_module), check_function)
    saved = dict(core.RESULTS)
    core.RESULTS.clear()
    out = io.StringIO()
    try:
        with core.using_cases(_MEMORY[fixtures_dir]), contextlib.redirect_stdout(out):
            check_fn(obj)
        results = list(core.RESULTS.values())
    finally:
        core.RESULTS.clear()
        core.RESULTS.update(saved)
    return (results[-1] if results else None), out.getvalue()


def run_reference(job: HiddenJob) -> HiddenOutcome:
    """The instructor's solution on the hidden cases, in the grader's own process (the calibration)."""
    t0 = time.perf_counter()
    module = types.ModuleType("__reference__")
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            exec(compile(job.code, "<instructor notebook>", "exec"), module.__dict__)  # noqa: S102 - the instructor's
        result, _ = run_check(job.check_module, job.check_function, job.fixtures_dir, module.__dict__.get(job.name))
    except Exception as exc:  # noqa: BLE001
        return HiddenOutcome("error", message=f"the reference run failed: {type(exc).__name__}: {exc}",
                             seconds=time.perf_counter() - t0)
    return HiddenOutcome("ok" if result is not None else "error", result=result,
                         message="" if result is not None else "the check recorded no verdict",
                         seconds=time.perf_counter() - t0)


def run_hidden(job: HiddenJob, timeout: float = 60.0, isolation=None, cgroup_parent=None,
               deadline: float = math.inf) -> HiddenOutcome:
    """Run the hidden checks of one exercise: the check in a worker of the grader, the student's function in its
    own sandboxed process.

    **One clock, one memory cap.** The worker is forked from the grader (it has the hidden cases and the full
    library) into the exercise's cgroup (``cgroup_parent``'s child), where the student's process and the oracle's
    worker run too. The grader waits for the worker's verdict until ``timeout`` seconds after the student's process
    started (plus :data:`~course_lib.instructor.settings.GRACE_SECONDS`, and never past ``deadline``, the
    submission's), then stops the worker and everything in its cgroup. The outcome's ``seconds`` is the real time spent on the hidden
    checks. With ``job.public_dir``, the verdict on the notebook's own cases follows on the same clock; a run out of
    time there leaves the hidden checks' outcome as it was.

    Args:
        job: the exercise, its extracted code and its check.
        timeout: the exercise's budget in seconds (:func:`course_lib.instructor.settings.exercise_seconds`).
        isolation: the grading run's :class:`course_lib.instructor.settings.Isolation`.
        cgroup_parent: the submission's cgroup (None: none could be made).
        deadline: the submission's deadline (``time.monotonic()``).

    Raises:
        IsolationError: the student's sandbox could not be made or verified (nothing of the student's ran).
    """
    t0 = time.monotonic()
    cgroup = isolation.cgroup(parent=cgroup_parent) if isolation is not None else None
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the worker
        try:
            os.close(r)
            _worker(job, timeout, isolation, cgroup, w)
        finally:
            os._exit(0)
    os.close(w)
    frames: dict = {}
    why = "ended"
    try:
        why = _await_frames(r, frames, t0, timeout, deadline)
    finally:
        os.close(r)
        try:
            os.kill(pid, 9) if why else None  # a worker that sent all it had to cleans up its sandbox and ends
            os.waitpid(pid, 0)
        except (ChildProcessError, ProcessLookupError):
            pass
        peak = cgroup.peak_bytes() if cgroup is not None else None
        oom = cgroup.oom_killed() if cgroup is not None else False
        if cgroup is not None:
            cgroup.close()
    dt = frames.get("outcome seconds", time.monotonic() - t0)
    if "outcome" not in frames:
        return _no_outcome(why, dt, timeout, deadline, oom, isolation, peak)
    out = _outcome_from(frames["outcome"], dt)
    out.memory["cgroup peak bytes"] = peak
    if "public" in frames:
        out.public = str(frames["public"].get("printed", ""))
    elif frames["outcome"].get("public_follows"):
        out.public_note = ("the check on the notebook's own cases did not finish within the exercise's time "
                           f"({timeout:g} s)" if why == "timeout" else "the check on the notebook's own cases ended "
                           "unexpectedly")
    return out


def _await_frames(r: int, frames: dict, t0: float, timeout: float, deadline: float) -> str:
    """Read the worker's frames into ``frames`` (``"outcome"``, then ``"public"`` when one follows) until the
    exercise's time is up; ``""`` when all came, else why not (``"timeout"``, ``"ended"``)."""
    budget_end = min(t0 + START_SECONDS + timeout + GRACE_SECONDS, deadline)
    while True:
        try:
            head, _ = wire.read_frame(r, 64 << 20, budget_end)
        except TimeoutError:
            return "timeout"
        except (EOFError, OSError, wire.WireError):
            return "ended"
        event = head.get("event")
        if event == "started":
            budget_end = min(time.monotonic() + timeout + GRACE_SECONDS, deadline)
        elif event == "isolation":
            raise jail.IsolationError(str(head.get("message", "the sandbox could not be verified")))
        elif event == "outcome" and "outcome" not in frames:
            frames["outcome"], frames["outcome seconds"] = head, time.monotonic() - t0
            if not head.get("public_follows"):
                return ""
        elif event == "public" and "outcome" in frames:
            frames["public"] = head
            return ""


def _no_outcome(why: str, dt: float, timeout: float, deadline: float, oom: bool, isolation,
                peak: int | None) -> HiddenOutcome:
    """The outcome of an exercise whose worker sent no verdict: out of time, out of memory, or ended."""
    memory = {"cgroup peak bytes": peak}
    if why == "timeout":
        past = time.monotonic() >= deadline - 0.5
        msg = (f"stopped after {dt:.1f} s: " + ("the submission's time for grading ran out" if past else
               f"your code, the grader's checks of its results and the earlier steps it called took longer "
               f"than the exercise's time limit ({timeout:g} s)"))
        return HiddenOutcome("timeout", message=msg, seconds=dt, memory=memory)
    if oom:
        return HiddenOutcome("exit", message=f"stopped after {dt:.1f} s: your code and the grader's work on its "
                                             f"results used more memory than the exercise's limit "
                                             f"({isolation.limits.memory_total_bytes >> 20} MiB in all)",
                             seconds=dt, memory=memory)
    return HiddenOutcome("error", message=f"the grader's worker for this exercise ended unexpectedly after "
                                          f"{dt:.1f} s", seconds=dt, memory=memory)


def _worker(job: HiddenJob, timeout: float, isolation, cgroup, w: int) -> None:
    """The exercise's worker: the student's process, the check, the verdict sent to the grader as JSON."""
    wire.close_inherited(w)
    rss0 = status_kib("VmRSS")
    if cgroup is not None:
        cgroup.enter()
    else:  # no cgroup: the worker's own address space is bounded
        bound_address_space(isolation.limits.memory_total_bytes if isolation is not None else 4 << 30)
    single_thread_math()
    t0 = time.perf_counter()

    def send(head: dict) -> None:
        head["memory"] = {"worker peak growth bytes": max(0, status_kib("VmHWM") - rss0) << 10}
        wire.write_frame(w, head)

    try:
        torch = job.check_module.startswith("course_lib.checks.nerf")
        oracle = Oracle(job.name, job.steps)  # earlier steps answered by the reference, on this exercise's clock
        engines = () if job.allow_reference or job.name not in EXERCISES else EXERCISES[job.name].engines
        with StudentProcess(isolation, job.code, job.name, job.submission, timeout, torch=torch, oracle=oracle,
                            cgroup=cgroup, engines=engines) as proc:
            wire.write_frame(w, {"event": "started"})
            _check_student(job, proc, send, t0)
    except jail.IsolationError as exc:
        wire.write_frame(w, {"event": "isolation", "message": str(exc)})
    except BaseException as exc:  # noqa: BLE001 - reported to the grader, never raised there
        send(_outcome_dict("error", message=f"the grader failed: {type(exc).__name__}: {str(exc)[:500]}",
                           seconds=time.perf_counter() - t0))


def _check_student(job: HiddenJob, proc: StudentProcess, send, t0: float) -> None:
    """The check on the hidden cases with the student's function ``proc`` serves; its outcome sent; then, when they
    all pass and ``job.public_dir`` is set, the check on the notebook's own cases, and what it prints."""
    hello, box = proc.hello, proc.sandbox
    seconds = lambda: time.perf_counter() - t0  # noqa: E731
    failed = lambda status, why: send(_outcome_dict(status, message=why, seconds=seconds(), sandbox=box))  # noqa: E731
    if proc.ended:
        return failed("timeout" if proc.event == "timeout" else "exit", proc.ended)
    if not hello.get("ok"):
        return failed("error", f"defining {job.name} failed: {hello.get('type')}: {str(hello.get('message'))[:2000]}"
                               f"{hello.get('where', '')}")
    if not hello.get("found"):
        return failed("error", f"the exercise code does not define {job.name}")
    fn = RemoteFunction(proc, job.name, _reference(job.reference) if job.reference else None)
    try:
        result, _ = run_check(job.check_module, job.check_function, job.fixtures_dir, fn)
    except Exception as exc:  # noqa: BLE001 - a check that cannot finish is the grader's problem, reported
        return failed("error", f"the grader failed: {type(exc).__name__}: {str(exc)[:500]}")
    attempted = not (fn.calls and fn.not_implemented == fn.calls)
    status = ("timeout" if proc.event == "timeout" else "exit") if proc.ended else "ok"
    if status == "ok" and result is None:
        status = "error"
    public = status == "ok" and job.public_dir is not None and all_pass(result, job.reference_result)
    send(_outcome_dict(status, result=result, message=proc.ended or ("" if result is not None else
                       "the check recorded no verdict"), seconds=seconds(), sandbox=box, attempted=attempted,
                       largest_reply=proc.largest_reply, public_follows=public))
    if public:
        try:
            _, printed = run_check(job.check_module, job.check_function, job.public_dir, fn)
        except Exception as exc:  # noqa: BLE001 - the verdict then differs from the reference's, and says why
            printed = f"the grader's check on the notebook's cases failed: {type(exc).__name__}: {str(exc)[:500]}"
        send({"event": "public", "printed": printed[:PRINTED_CHARS]})


def all_pass(result, reference) -> bool:
    """Whether ``result`` passes every hidden check the reference passes, in the documented form (full marks)."""
    if result is None or reference is None:
        return False
    return core.score_against(result, reference) >= 1 and not result.details_failed


def _reference(spec: str):
    """The reference function ``"module:attr"`` (the expected answers of the student's calls), or None."""
    try:
        module, attr = spec.split(":")
        return getattr(importlib.import_module(module), attr)
    except Exception:  # noqa: BLE001 - without it, declared sizes are bounded by the plain limits
        return None


#: Characters of one verdict line and lines of one check sent from the worker (student text can be in them), and
#: characters of a check's printed verdict on the notebook's cases.
LINE_CHARS, MAX_LINES, PRINTED_CHARS = 2000, 400, 20_000


def _outcome_dict(status: str, result=None, message: str = "", seconds: float = 0.0, sandbox: dict | None = None,
                  attempted: bool = True, largest_reply: int = 0, public_follows: bool = False) -> dict:
    res = None
    if result is not None:
        res = {"exercise": str(result.exercise), "passed": int(result.passed), "total": int(result.total),
               "lines": [str(ln)[:LINE_CHARS] for ln in result.lines[:MAX_LINES]],
               "verdicts": [{"ok": bool(v.ok), "text": str(v.text)[:LINE_CHARS], "kind": str(v.kind),
                             "defining": v.defining} for v in result.verdicts[:MAX_LINES]]}
    return {"event": "outcome", "status": status, "message": str(message)[:LINE_CHARS], "seconds": float(seconds),
            "result": res, "sandbox": {str(k): str(v)[:300] if not isinstance(v, bool) else v
                                       for k, v in (sandbox or {}).items()}, "attempted": bool(attempted),
            "largest_reply": int(largest_reply), "public_follows": bool(public_follows)}


def _outcome_from(head: dict, seconds: float) -> HiddenOutcome:
    """The worker's verdict as a :class:`HiddenOutcome` (``seconds``: the real time the grader measured)."""
    res = head.get("result")
    result = None
    if isinstance(res, dict):
        result = core.CheckResult(res["exercise"], res["passed"], res["total"], list(res["lines"]),
                                  [core.Verdict(v["ok"], v["text"], v["kind"], v["defining"]) for v in res["verdicts"]])
    return HiddenOutcome(head.get("status", "error"), message=head.get("message", ""), seconds=seconds, result=result,
                         sandbox=head.get("sandbox") or {}, attempted=bool(head.get("attempted", True)),
                         memory=dict(head.get("memory") or {},
                                     **{"largest reply bytes": int(head.get("largest_reply", 0))}))

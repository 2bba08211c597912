"""Hidden checks: each exercise checked here, on new cases, while the student's code runs elsewhere.

* :func:`build_hidden_fixtures` makes the hidden cases of a grading run: the case builders of
  :mod:`course_lib.instructor.cases` (the instructor's full library) run again with every seeded
  ``numpy.random.default_rng`` salted by a grading-time seed, so the synthetic scenes are new; seed
  0, which the checks reuse for the student's own RANSAC calls, is kept. They stay in this
  process.
* :func:`run_hidden` runs the check function of the exercise *in this process* on those cases
  (:func:`course_lib.checks.core.using_cases`); the student's function it receives is a proxy for
  the same function in a sandboxed process (:class:`course_lib.instructor.student_process.StudentProcess`)
  that holds only the student's code and the student release of ``course_lib``.
  :func:`run_reference` runs the instructor's solution here, for the expected verdicts.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import multiprocessing as mp
import os
import sys
import traceback
import types
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from course_lib.checks import core

__all__ = [
    "build_hidden_fixtures",
    "build_in_process",
    "HiddenJob",
    "HiddenOutcome",
    "run_hidden",
    "run_check",
    "run_reference",
]


# ---------------------------------------------------------------------------------------------
# Hidden fixtures
# ---------------------------------------------------------------------------------------------

#: Seeds the check functions reuse when they call the student's function (kept unsalted).
KEPT_SEEDS = {0}


def _salted_rng_factory(salt: int):
    original = np.random.default_rng

    def default_rng(seed=None):
        if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool) and int(seed) not in KEPT_SEEDS:
            return original(np.random.SeedSequence([int(salt) % 2**63, int(seed)]))
        return original(seed)

    return original, default_rng


def build_in_process(name: str, salt: int) -> dict[str, np.ndarray]:
    """The hidden cases of fixture ``name`` for a grading ``salt``, built in this process."""
    from course_lib.instructor.cases import builders

    original, salted = _salted_rng_factory(salt)
    np.random.default_rng = salted
    try:
        return builders()[name]()
    finally:
        np.random.default_rng = original


def _build_hidden(out_dir: str, check_modules: list[str], salt: int) -> dict:
    from course_lib.instructor.cases import builders

    single_thread_math()
    built = {}
    for name in builders(check_modules, steps=False):
        arrays = build_in_process(name, salt)
        np.savez_compressed(Path(out_dir) / f"{name}.npz", **{k: np.asarray(v) for k, v in arrays.items()})
        built[name] = sorted(arrays)
    return built


#: Hidden fixtures held in the grader's memory (folder -> name -> arrays); forked runs read them from here.
_MEMORY: dict[str, dict[str, dict[str, np.ndarray]]] = {}


def hold_in_memory(fixtures_dir: Path) -> None:
    """Load every fixture of ``fixtures_dir`` into this process, for the forked runs to use."""
    held = {}
    for p in sorted(Path(fixtures_dir).glob("*.npz")):
        with np.load(p, allow_pickle=False) as z:
            held[p.stem] = {k: z[k] for k in z.files}
    _MEMORY[str(fixtures_dir)] = held


def build_hidden_fixtures(out_dir: Path, check_modules: list[str], salt: int, timeout: float = 600) -> dict:
    """Write the hidden cases of ``check_modules`` into ``out_dir`` (no step fixture: they are no cases).

    Runs in a forked process (the reference library builds them; torch stays out of this process).
    """

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    res = _in_child(_build_hidden, (str(out_dir), sorted(set(check_modules)), int(salt)), timeout)
    if "error" in res or "value" not in res:
        raise RuntimeError(f"building the hidden cases failed: {res.get('error', res)}")
    hold_in_memory(out_dir)
    return res["value"]


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


@dataclass
class HiddenOutcome:
    status: str  # "ok", "timeout", "exit", "error"
    lines: list[str] = field(default_factory=list)  # the verdict lines ("  ✔ ..." / "  ✘ ...")
    message: str = ""
    seconds: float = 0.0
    result: object = None  # the CheckResult of the hidden checks (computed in the grader's process)
    sandbox: dict = field(default_factory=dict)  # what the student's process was confined by

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
    import time

    t0 = time.perf_counter()
    module = types.ModuleType("__reference__")
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            exec(compile(job.code, "<instructor notebook>", "exec"), module.__dict__)  # noqa: S102 - the instructor's
        result, _ = run_check(job.check_module, job.check_function, job.fixtures_dir, module.__dict__.get(job.name))
    except Exception as exc:  # noqa: BLE001
        return HiddenOutcome("error", message=f"the reference run failed: {type(exc).__name__}: {exc}",
                             seconds=time.perf_counter() - t0)
    lines = list(result.lines) if result is not None else []
    return HiddenOutcome("ok" if result is not None else "error", lines=lines, result=result,
                         message="" if result is not None else "the check recorded no verdict",
                         seconds=time.perf_counter() - t0)


def run_hidden(job: HiddenJob, timeout: float = 60.0, isolation=None) -> HiddenOutcome:
    """Run the hidden checks of one exercise: the check here, the student's function in its own process.

    Args:
        job: the exercise, its extracted code and its check.
        timeout: wall-clock seconds for everything the student's process does for this exercise.
        isolation: the grading run's :class:`course_lib.instructor.student_process.Isolation`.
    """
    import time

    from course_lib.instructor.oracle import ALLOWANCE, Oracle
    from course_lib.instructor.student_process import RemoteFunction, StudentProcess

    t0 = time.perf_counter()
    torch = job.check_module.startswith("course_lib.checks.nerf")
    oracle = Oracle(job.name, job.steps, ALLOWANCE * timeout)  # earlier steps answered by the reference
    with StudentProcess(isolation, job.code, job.name, job.submission, timeout, torch=torch, oracle=oracle) as proc:
        hello = proc.hello
        if proc.ended:
            return HiddenOutcome("timeout" if proc.event == "timeout" else "exit", message=proc.ended,
                                 seconds=time.perf_counter() - t0)
        if not hello.get("ok"):
            return HiddenOutcome("error", message=f"defining {job.name} failed: {hello.get('type')}: "
                                 f"{hello.get('message')}{hello.get('where', '')}", seconds=time.perf_counter() - t0,
                                 sandbox=hello.get("sandbox", {}))
        if not hello.get("found"):
            return HiddenOutcome("error", message=f"the exercise code does not define {job.name}",
                                 seconds=time.perf_counter() - t0, sandbox=hello.get("sandbox", {}))
        try:
            result, _ = run_check(job.check_module, job.check_function, job.fixtures_dir, RemoteFunction(proc, job.name))
        except Exception as exc:  # noqa: BLE001 - a check that cannot finish is the grader's problem, reported
            return HiddenOutcome("error", message=f"the grader failed: {type(exc).__name__}: {exc}",
                                 seconds=time.perf_counter() - t0, sandbox=hello.get("sandbox", {}))
        dt = time.perf_counter() - t0
        if proc.ended:
            status = "timeout" if proc.event == "timeout" else "exit"
            return HiddenOutcome(status, lines=list(result.lines) if result else [], message=proc.ended, seconds=dt,
                                 result=result, sandbox=hello.get("sandbox", {}))
    if result is None:
        return HiddenOutcome("error", message="the check recorded no verdict", seconds=dt)
    return HiddenOutcome("ok", lines=list(result.lines), result=result, seconds=dt, sandbox=hello.get("sandbox", {}))


def single_thread_math() -> None:
    """One thread for OpenBLAS (numpy, scipy) and torch in this process: the same numbers on every run."""
    from course_lib.threads import set_blas_threads

    set_blas_threads(1)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)


def _child_main(conn, fn, args):
    try:
        value = fn(*args)
        conn.send({"value": value})
    except BaseException as exc:  # noqa: BLE001
        try:
            conn.send({"error": f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=3)}"})
        except Exception:  # noqa: BLE001
            pass
    finally:
        conn.close()
        os._exit(0)


def _in_child(fn, args, timeout: float) -> dict:
    """Run ``fn(*args)`` in a forked process; ``{"value": ...}``, ``{"error": ...}`` or ``{"timeout": True}``."""
    ctx = mp.get_context("fork")
    parent, child = ctx.Pipe(duplex=False)
    p = ctx.Process(target=_child_main, args=(child, fn, args), daemon=True)
    p.start()
    child.close()
    try:
        if parent.poll(timeout):
            try:
                return parent.recv()
            except EOFError:
                return {"crashed": True}
        return {"timeout": True}
    finally:
        if p.is_alive():
            p.kill()
        p.join(5)
        parent.close()

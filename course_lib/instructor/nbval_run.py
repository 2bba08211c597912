"""nbval over a submission's notebooks, each in its own sandboxed pytest process, on the submission's clock.

Each notebook runs in a fresh copy of the grader's copy of the submission (its working directory),
with the student release's ``course_lib`` first on ``PYTHONPATH``, in the sandbox of
:mod:`course_lib.instructor.sandbox.jail` (checked before the notebook runs, like every student's
process), in a cgroup of its own inside the submission's. pytest reads no configuration and no
``conftest.py`` of the submission (``-c /dev/null --noconftest``), no module of the notebooks' folder
can stand in for pytest's own or the kernel's (both ``python -P``: the kernel imports nothing from the
submission), HOME, IPYTHONDIR and Jupyter's folders lie outside the submission's copy (no start-up file or
configuration of the student's is read), and its junit report goes through a pipe that only the
(undumpable) pytest and the launcher hold (:func:`course_lib.instructor.sandbox.server.launch`).

The report says which cells ran without an error; no check cell's output is compared (the grader restores the
check cells without nbval's output marker, :func:`~course_lib.instructor.placement.restored`, and computes their
verdicts itself, :func:`~course_lib.instructor.hidden.run_hidden`): the kernel is the student's process.

**One clock.** A notebook gets :func:`course_lib.instructor.settings.nbval_seconds` for all its runs
together (a restart included), and never more than what is left of the submission's time; a run that does
not finish by then counts as not run.
"""

from __future__ import annotations

import math
import os
import re
import shutil
import subprocess
import sys
import threading
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import nbformat

from course_lib.instructor.sandbox import jail, launch, wire
from course_lib.instructor.settings import START_SECONDS, Isolation

__all__ = ["NbvalRun"]


class NbvalRun:
    """pytest --nbval over notebooks, one sandboxed pytest process per notebook, ``jobs`` at a time, in the background.

    Args:
        submission: the grader's copy of the submission.
        isolation: the run's :class:`~course_lib.instructor.settings.Isolation`.
        cell_timeout: seconds for one cell.
        jobs: notebooks at the same time.
        timeout: seconds for one notebook, a restart included.
        deadline: the submission's deadline (``time.monotonic()``).
        cgroup: the submission's cgroup (each notebook gets one inside it), or None.
    """

    def __init__(self, submission: Path, isolation: Isolation, cell_timeout: float, jobs: int = 2,
                 timeout: float = 1800.0, deadline: float = math.inf, cgroup=None):
        from concurrent.futures import ThreadPoolExecutor

        self.submission, self.iso = Path(submission), isolation
        self.cell_timeout, self.timeout = cell_timeout, timeout
        self.deadline, self.cgroup = deadline, cgroup
        self.pool = ThreadPoolExecutor(max_workers=max(1, jobs))
        self.futures: dict[str, object] = {}
        self.sandbox: dict = {}
        self._lock = threading.Lock()
        self._procs: dict[str, subprocess.Popen] = {}
        self._replace: dict[str, object] = {}
        self._stopped = False

    def submit(self, name: str, nb) -> None:
        self.futures[name] = self.pool.submit(self._run, name, nb)

    def restart(self, name: str, nb) -> None:
        """Run notebook ``name`` again from the start with ``nb`` (stopping the run in progress, if any)."""
        with self._lock:
            fut = self.futures.get(name)
            if fut is None or fut.done():
                self.futures[name] = self.pool.submit(self._run, name, nb)
                return
            self._replace[name] = nb
            proc = self._procs.get(name)
        if proc is not None:
            jail.kill_tree(proc.pid)

    def stop(self) -> None:
        """Stop every notebook still running (the grading ended, or was refused); idempotent."""
        with self._lock:
            self._stopped = True
            procs = list(self._procs.values())
        for proc in procs:
            jail.kill_tree(proc.pid)
        self.pool.shutdown(wait=True, cancel_futures=True)

    def _run(self, name: str, nb) -> tuple[dict[tuple[str, int], str], str]:
        end = min(time.monotonic() + self.timeout, self.deadline)
        while True:  # again from the start while a restart replaced the notebook
            with self._lock:
                nb = self._replace.pop(name, nb)
            out = self._one(name, nb, end)
            with self._lock:
                if name not in self._replace:
                    return out

    def _one(self, name: str, nb, end: float) -> tuple[dict[tuple[str, int], str], str]:
        """Run one notebook until ``end`` at the latest (after a cell that timed out, nbval skips the rest: a notebook
        whose exercise looped in its hidden checks is run again with that exercise cut short, :meth:`restart`)."""
        tmp = jail.private_folder("course-nbval-", self.iso.scratch)
        try:
            seed = tmp / "seed"  # the submission's copy with only the notebook under test, restored by the grader
            shutil.copytree(self.submission, seed, ignore=_other_notebooks(self.submission), symlinks=False)
            (seed / "notebooks").mkdir(exist_ok=True)
            nbformat.write(nb, seed / "notebooks" / name)
            return self._pytest(tmp, seed, name, end)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    def _pytest(self, tmp: Path, seed: Path, name: str, end: float):
        """One sandboxed pytest run, until ``end`` at the latest; its junit report comes out through the launcher."""
        stage = tmp / "run"
        stage.mkdir()
        work, seed_at = launch.paths(self.iso, stage, seed)
        nb_dir = os.path.join(work, "notebooks")
        report_r, report_w = os.pipe()
        go_r, go_w = os.pipe()
        collect_r, collect_w = os.pipe()
        cfg = {"cwd": work, "nb_dir": nb_dir, "seed": seed_at, "python": sys.executable,
               "argv": self.pytest_command(name, "{junit}", nb_dir), "report_fd": report_w, "go_fd": go_r,
               "collect_fd": collect_w}
        fds = [report_w, go_r, collect_w]
        cgroup = self.iso.cgroup(parent=self.cgroup)
        started = None
        try:
            with self._lock:  # its own session, so that whatever the notebook started is stopped with it
                if name in self._replace or self._stopped:
                    return {}, "replaced"
                given, fds = fds, []  # closed by launch.start, whatever happens
                started = launch.start(self.iso, "exec", cfg, stage, seed, cgroup, max(1.0, end - time.monotonic()),
                                       self._env(work), given)
                self._procs[name] = started.proc
            box = self._checked(name, started, report_r, cgroup)
            if isinstance(box, str):
                return {}, box
            wire.write_frame(go_w, {"op": "go"})
            junit, complete = wire.read_until_closed(collect_r, wire.MAX_REPORT, end)
            if not complete:
                return {}, f"nbval did not finish {name} within its time"
            try:
                started.proc.wait(timeout=max(1.0, end - time.monotonic()))
            except subprocess.TimeoutExpired:
                return {}, f"nbval did not finish {name} within its time"
        finally:
            wire.close_fds(fds + [report_r, go_w, collect_r])
            if started is not None:
                jail.kill_tree(started.proc.pid)
                started.proc.wait()
                with self._lock:
                    self._procs.pop(name, None)
            if cgroup is not None:
                cgroup.close()
        if not self.sandbox:
            self.sandbox = box
        return _read_junit(junit, name)

    def _checked(self, name: str, started: launch.Started, report_r: int, cgroup) -> dict | str:
        """What the sandbox of a run enforces, checked before the notebook runs; a note when it did not start.

        Raises:
            IsolationError: bubblewrap could not make the sandbox, or it is not isolated.
        """
        try:
            head, _ = wire.read_frame(report_r, 1 << 20, time.monotonic() + START_SECONDS)
            facts = head.get("facts") if isinstance(head.get("facts"), dict) else {}
        except (TimeoutError, EOFError, OSError, wire.WireError):
            head, facts = {}, None
        no_info = started.mode == launch.BUBBLEWRAP and not started.info
        if started.mode != launch.INSECURE and (no_info or facts is None):
            if started.proc.poll() is not None and no_info:
                raise launch.refuse_start(started, what="the sandbox of nbval")
            return f"nbval of {name} did not start"
        box = launch.check(started, self.iso, facts or {}, cgroup, what="the sandbox of nbval")
        if head.get("seed_failed"):  # the submission's problem: its notebook does not run
            why = str(head["seed_failed"])[:200]
            return f"nbval of {name}: the submission could not be copied into the sandbox ({why})"
        return box

    def pytest_command(self, name: str, junit: str, rootdir: str) -> list[str]:
        """pytest's arguments for nbval of notebook ``name``: no conftest.py and no pytest configuration of the
        submission is read (the launcher runs them with ``python -B -P``: no module of the notebooks' folder
        shadows pytest's)."""
        return ["-q", "-p", "no:cacheprovider", "--noconftest", "-c", os.devnull, "--rootdir", rootdir, "--nbval-lax",
                "--nbval-current-env", f"--nbval-cell-timeout={int(self.cell_timeout)}", f"--junitxml={junit}", name]

    def _env(self, work: str) -> dict:
        """The notebook's environment: HOME, IPYTHONDIR and Jupyter's folders outside the working copy of the
        submission (in the sandbox: fresh folders of its tmpfs), so that no start-up file or configuration of the
        submission is read by the kernel."""
        home = Path(work).parent / "home"
        more = {"COURSE_DATA": os.environ["COURSE_DATA"]} if os.environ.get("COURSE_DATA") else {}
        return launch.env(home, PYTHONPATH=str(self.iso.library), JUPYTER_RUNTIME_DIR=str(home / "runtime"),
                          JUPYTER_DATA_DIR=str(home / "data"), IPYTHONDIR=str(home / "ipython"),
                          MPLCONFIGDIR=str(home / "mpl"), JUPYTER_CONFIG_DIR=str(home / "jupyter"),
                          JUPYTER_CONFIG_PATH="", JUPYTER_PATH="", PYTHONNOUSERSITE="1", **more)

    def results(self) -> tuple[dict[tuple[str, int], str], dict[str, str]]:
        """``{(notebook, code cell index): "pass" or a failure text}`` and ``{notebook: note}`` for runs that failed."""
        out, notes = {}, {}
        for name in list(self.futures):
            while True:  # a restart may replace the future while we wait for it
                fut = self.futures[name]
                try:
                    res, note = fut.result()
                except jail.IsolationError:
                    raise  # no sandbox, no grading
                except Exception as exc:  # noqa: BLE001 - the grader never dies on a submission
                    res, note = {}, f"nbval could not run {name} ({type(exc).__name__}: {str(exc)[:200]})"
                if self.futures[name] is fut:
                    break
            out.update(res)
            if note:
                notes[name] = note
        return out, notes


def _other_notebooks(submission: Path):
    """``copytree``'s ignore: the submission's notebooks (the one under test is written by the grader)."""
    skip = {".ipynb_checkpoints"}

    def ignore(folder: str, names: list[str]) -> list[str]:
        in_nb_dir = Path(folder) == submission / "notebooks" or Path(folder) == submission
        return [n for n in names if n in skip or (in_nb_dir and n.endswith(".ipynb"))]

    return ignore


def _read_junit(junit: bytes, name: str) -> tuple[dict[tuple[str, int], str], str]:
    if not junit:
        return {}, f"nbval did not run {name}"
    results = {}
    try:
        cases = list(ET.fromstring(junit).iter("testcase"))
    except Exception as exc:  # noqa: BLE001 - a broken report is that notebook's note
        return {}, f"nbval's report of {name} cannot be read ({type(exc).__name__})"
    for tc in cases:
        cell = tc.attrib.get("name", "")
        if not cell.startswith("Cell ") or not cell.split()[1].isdigit():
            continue
        bad = [c for c in tc if c.tag in ("failure", "error", "skipped")]
        text = "pass"
        if bad:  # nbval skips the cells after one that timed out
            text = (bad[0].attrib.get("message") or bad[0].text or "failed").strip()
            text = ("not run: " if bad[0].tag == "skipped" else "") + re.sub(r"\x1b\[[0-9;]*m", "", text)
        results[(name, int(cell.split()[1]))] = text
    return results, ""

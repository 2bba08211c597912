"""nbval over a submission's notebooks, each in its own sandboxed pytest process.

Each notebook runs in a fresh copy of the grader's copy of the submission (its working directory),
with the student release's ``course_lib`` first on ``PYTHONPATH``, resource limits and (where Linux
allows it) the sandbox of :mod:`course_lib.instructor.sandbox`. pytest reads no configuration and
no ``conftest.py`` of the submission (``-c /dev/null --noconftest``), and no module of the notebooks'
folder can stand in for pytest's own (``python -P``).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import xml.etree.ElementTree as ET
from pathlib import Path

import nbformat

from course_lib.instructor.student_process import CHILD_SCRIPT, Isolation, kill_tree

__all__ = ["NbvalRun", "MAX_NBVAL_RERUNS"]

MAX_NBVAL_RERUNS = 3  # reruns of a notebook after cells that timed out


class NbvalRun:
    """pytest --nbval over notebooks, one sandboxed pytest process per notebook, ``jobs`` at a time, in the background.

    Each notebook runs in a fresh copy of the submission (its working directory), with the student
    release's ``course_lib`` first on ``PYTHONPATH``, resource limits, and (where Linux allows it)
    the sandbox of :mod:`course_lib.instructor.sandbox`: no network, an allow-listed read-only file
    system, a size-limited tmpfs for what it writes, totals for the process tree.
    """

    def __init__(self, submission: Path, isolation: Isolation, cell_timeout: float, jobs: int = 2,
                 timeout: float = 1800.0):
        from concurrent.futures import ThreadPoolExecutor

        self.submission, self.iso = Path(submission), isolation
        self.cell_timeout, self.timeout = cell_timeout, timeout
        self.pool = ThreadPoolExecutor(max_workers=max(1, jobs))
        self.futures: dict[str, object] = {}
        self.sandbox: dict = {}
        self._lock = threading.Lock()
        self._procs: dict[str, subprocess.Popen] = {}
        self._replace: dict[str, object] = {}

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
            kill_tree(proc.pid)

    def _run(self, name: str, nb) -> tuple[dict[tuple[str, int], str], str]:
        while True:
            with self._lock:
                nb = self._replace.pop(name, nb)
            out = self._one(name, nb)
            with self._lock:
                if name not in self._replace:
                    return out

    def _one(self, name: str, nb) -> tuple[dict[tuple[str, int], str], str]:
        """Run one notebook; after a cell that timed out (nbval skips the rest), run the rest again."""
        tmp = Path(tempfile.mkdtemp(prefix="course-nbval-"))
        try:
            os.chmod(tmp, 0o755)
            seed = tmp / "seed"  # the submission's copy with only the notebook under test, restored by the grader
            shutil.copytree(self.submission, seed, ignore=_other_notebooks(self.submission), symlinks=False)
            (seed / "notebooks").mkdir(exist_ok=True)
            results: dict[tuple[str, int], str] = {}
            done_upto = -1
            for attempt in range(MAX_NBVAL_RERUNS + 1):
                with self._lock:
                    if name in self._replace:
                        return results, "replaced"
                nbformat.write(nb, seed / "notebooks" / name)
                res, note = self._pytest(tmp, seed, name, attempt)
                if note:
                    return results, note
                results.update({k: v for k, v in res.items() if k[1] > done_upto})
                timed_out = sorted(k[1] for k, v in res.items() if k[1] > done_upto and "timeout" in v.lower()
                                   and not v.startswith("not run"))
                if not timed_out or not any(v.startswith("not run") for k, v in res.items() if k[1] > timed_out[0]):
                    break
                done_upto = timed_out[0]
                # the rerun: the cell that timed out raises at once, the cells after it run again
                code = [c for c in nb.cells if c.cell_type == "code"]
                code[done_upto].source = f"raise TimeoutError('this cell did not finish within {self.cell_timeout:g} s')"
                code[done_upto].outputs = []
            return results, ""
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    def _pytest(self, tmp: Path, seed: Path, name: str, attempt: int):
        """One sandboxed pytest run; its junit report comes out through a file the sandbox never holds."""
        work = tmp / f"work{attempt}"  # the sandbox's working copy (in its own tmpfs; on this disk without namespaces)
        stage = tmp / f"stage{attempt}"
        for d in (work, stage):
            d.mkdir()
        nb_dir = work / "notebooks"
        junit_in = nb_dir / ".nbval.junit.xml"
        junit_out, report_out = tmp / f"junit{attempt}.xml", tmp / f"sandbox{attempt}.json"
        fds = [os.open(p, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600) for p in (junit_out, report_out)]
        cfg = {"sandbox": self.iso.sandbox_config(stage, work, seed), "cwd": str(nb_dir),
               "collect": str(junit_in), "collect_fd": fds[0], "report_fd": fds[1]}
        (tmp / f"sandbox{attempt}.cfg.json").write_text(json.dumps(cfg))
        cmd = [sys.executable, "-S", "-E", str(CHILD_SCRIPT), "exec", str(tmp / f"sandbox{attempt}.cfg.json"), "--",
               *self.pytest_command(name, junit_in)]
        cgroup = self.iso.cgroup()
        try:
            with self._lock:  # its own session, so that whatever the notebook started is stopped with it
                if name in self._replace:
                    return {}, "replaced"
                proc = subprocess.Popen(cmd, cwd=work, env=self._env(work), stdout=subprocess.DEVNULL,
                                        stderr=subprocess.DEVNULL, pass_fds=fds, start_new_session=True,
                                        preexec_fn=self.iso.preexec(self.timeout, cgroup))
                self._procs[name] = proc
            for fd in fds:
                os.close(fd)
            fds = []
            try:
                proc.wait(timeout=self.timeout)
            except subprocess.TimeoutExpired:
                return {}, f"nbval did not finish {name} within {self.timeout:g} s"
            finally:
                kill_tree(proc.pid)
                proc.wait()
                with self._lock:
                    self._procs.pop(name, None)
        finally:
            for fd in fds:
                os.close(fd)
            if cgroup is not None:
                cgroup.close()
        self._read_report(report_out, cgroup)
        junit = junit_out if junit_out.stat().st_size else junit_in  # without namespaces: on this disk
        return _read_junit(junit, name)

    def pytest_command(self, name: str, junit: Path) -> list[str]:
        """nbval of notebook ``name``: no conftest.py and no pytest configuration of the submission is read."""
        safe_path = ["-P"] if sys.version_info >= (3, 11) else []  # no module of the notebooks' folder shadows pytest's
        return [sys.executable, *safe_path, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--noconftest", "-c", os.devnull,
                "--rootdir", str(junit.parent), "--nbval-lax", "--nbval-current-env",
                f"--nbval-cell-timeout={int(self.cell_timeout)}", f"--junitxml={junit}", name]

    def _env(self, work: Path) -> dict:
        home = work / ".home"
        env = {k: v for k, v in os.environ.items() if k in ("PATH", "LANG", "LC_ALL", "TZ")}
        env.update(COURSE_LIB_QUICK="1", PYTHONDONTWRITEBYTECODE="1", PYTHONPATH=str(self.iso.library),
                   HOME=str(home), JUPYTER_RUNTIME_DIR=str(home / "runtime"), JUPYTER_DATA_DIR=str(home / "data"),
                   IPYTHONDIR=str(home / "ipython"), MPLCONFIGDIR=str(home / "mpl"), MPLBACKEND="Agg", TMPDIR="/tmp",
                   OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONNOUSERSITE="1")
        if os.environ.get("COURSE_DATA"):
            env["COURSE_DATA"] = os.environ["COURSE_DATA"]
        return env

    def _read_report(self, path: Path, cgroup) -> None:
        """What the sandbox enforced (written by the launcher before the notebook ran), with the totals."""
        if self.sandbox:
            return
        try:
            box = json.loads(path.read_text() or "{}")
        except ValueError:
            box = {}
        if isinstance(box, dict) and box:
            box.update(self.iso.limits.totals(cgroup))
            self.sandbox = box

    def results(self) -> tuple[dict[tuple[str, int], str], dict[str, str]]:
        """``{(notebook, code cell index): "pass" or a failure text}`` and ``{notebook: note}`` for runs that failed."""
        out, notes = {}, {}
        for name in list(self.futures):
            while True:  # a restart may replace the future while we wait for it
                fut = self.futures[name]
                try:
                    res, note = fut.result()
                except Exception as exc:  # noqa: BLE001 - the grader never dies on a submission
                    res, note = {}, f"nbval could not run {name} ({type(exc).__name__}: {str(exc)[:200]})"
                if self.futures[name] is fut:
                    break
            out.update(res)
            if note:
                notes[name] = note
        self.pool.shutdown()
        return out, notes


def _other_notebooks(submission: Path):
    """``copytree``'s ignore: the submission's notebooks (the one under test is written by the grader)."""
    skip = {".ipynb_checkpoints"}

    def ignore(folder: str, names: list[str]) -> list[str]:
        in_nb_dir = Path(folder) == submission / "notebooks" or Path(folder) == submission
        return [n for n in names if n in skip or (in_nb_dir and n.endswith(".ipynb"))]

    return ignore


def _read_junit(junit: Path, name: str) -> tuple[dict[tuple[str, int], str], str]:
    if not junit.exists():
        return {}, f"nbval did not run {name}"
    results = {}
    try:
        cases = list(ET.parse(junit).iter("testcase"))
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

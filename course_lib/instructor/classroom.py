"""Grading a class: every submission of a folder graded on its own, several at once, into the gradebook.

``python -m course_lib grade-class SUBMISSIONS_DIR --gradebook grades.sqlite [--csv grades.csv]``

Each sub-folder of ``SUBMISSIONS_DIR`` is one student's submission (the folder's name is the student). Each is
graded by the single-submission grader, ``python -m course_lib grade`` (:mod:`course_lib.instructor.grade`), in a
process of its own with its own sandboxes, clock and memory cap; ``jobs`` of them run at once
(:func:`default_jobs`: as many as the cores and the memory allow). A grader that crashes or runs past its
submission's time gives that one submission a report saying what happened (status ``crashed`` or ``timed out``,
0 points), never stops the others; one refused by the grader while others ran (its sandbox could not be made,
e.g. for lack of a resource another submission held) is graded again alone after them. As root, each job's
students' processes run as a uid of their own. Reports and feedback go to ``REPORTS/<student>/`` (``report.json``,
``feedback.md``, and ``grader.log``, the grader's own output, for the instructor); every grading goes into the
:class:`~course_lib.instructor.gradebook.Gradebook`.

The commit of a submission is the second line of ``<student>.commit`` beside its folder (what the CI template's
``plan`` job writes: the repository, then the commit), else a digest of its files. A commit already graded is
skipped unless ``regrade``.
"""

from __future__ import annotations

import hashlib
import json
import os
import queue
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

from course_lib.instructor.gradebook import Gradebook
from course_lib.instructor.sandbox.jail import REFUSAL
from course_lib.instructor.settings import STUDENT_UID
from course_lib.paths import REPO_ROOT

__all__ = ["Submission", "find_submissions", "default_jobs", "grade_class", "grade_one", "grader_version"]

#: Memory one grading takes at its peak (the grader, an exercise's student process and two notebooks under nbval,
#: each with torch loaded; measured: benchmarks/grade_class.py), for :func:`default_jobs`.
GRADING_BYTES = 3 << 30
#: The single-submission grader, run once per submission (the tests put a stand-in here).
GRADER = [sys.executable, "-m", "course_lib", "grade"]
#: Seconds a grading may take past ``--submission-timeout`` before it is stopped: the hidden cases are made (and the
#: reference run on them) before the submission's clock starts.
START_SECONDS = 600.0


@dataclass(frozen=True)
class Submission:
    student: str
    path: Path
    commit: str


def find_submissions(folder: Path) -> list[Submission]:
    """The submissions in ``folder``: its sub-folders (links are not followed), sorted by name."""
    subs = []
    for entry in sorted(os.scandir(folder), key=lambda e: e.name):
        if entry.is_dir(follow_symlinks=False) and not entry.name.startswith("."):
            recorded = Path(folder) / f"{entry.name}.commit"
            lines = recorded.read_text().splitlines() if recorded.is_file() else []
            commit = lines[1].strip() if len(lines) > 1 else _digest(Path(entry.path))
            subs.append(Submission(entry.name, Path(entry.path), commit))
    return subs


def _digest(folder: Path) -> str:
    """A digest of a folder's regular files (names and contents; links not followed): a commit's stand-in."""
    h = hashlib.sha256()
    for root, dirs, files in os.walk(folder):  # os.walk does not follow links to folders
        dirs.sort()
        for name in sorted(files):
            path = Path(root, name)
            if path.is_file() and not path.is_symlink():
                h.update(str(path.relative_to(folder)).encode("utf-8", "surrogateescape") + b"\0")
                with open(path, "rb") as f:
                    while chunk := f.read(1 << 20):
                        h.update(chunk)
    return "sha256:" + h.hexdigest()[:16]


def default_jobs() -> int:
    """Gradings at once: one per core, as far as the available memory holds :data:`GRADING_BYTES` for each."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    try:
        meminfo = dict(ln.split(":", 1) for ln in Path("/proc/meminfo").read_text().splitlines())
        available = int(meminfo["MemAvailable"].split()[0]) * 1024
    except (OSError, KeyError, ValueError):
        available = cores * GRADING_BYTES
    return max(1, min(cores, available // GRADING_BYTES))


def grader_version() -> str:
    """The kit's version and the instructor's commit (where the kit is a git checkout)."""
    import course_lib

    try:
        rev = subprocess.run(["git", "-C", str(REPO_ROOT), "describe", "--always", "--dirty"], capture_output=True,
                             text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        rev = ""
    return f"{course_lib.__version__}+{rev}" if rev else course_lib.__version__


@dataclass
class Outcome:
    sub: Submission
    status: str
    report: dict
    feedback: str


def grade_class(submissions: list[Submission], gradebook: Gradebook, reports: Path, grade_options: list[str],
                *, jobs: int, submission_timeout: float, regrade: bool = False,
                progress: bool = True) -> list[Outcome]:
    """Grade ``submissions`` (those not graded yet, or all with ``regrade``), ``jobs`` at once, into ``gradebook``.

    Args:
        grade_options: options of ``python -m course_lib grade`` for every submission (``--timeout 60`` ...).
        submission_timeout: the graders' ``--submission-timeout``; a grader still running :data:`START_SECONDS`
            past it is stopped (SIGTERM: it cleans up; SIGKILL 10 s later), and its submission gets a report that
            says so.
    """
    from tqdm.auto import tqdm

    todo = [s for s in submissions if regrade or not gradebook.graded(s.student, s.commit)]
    version, out, limit = grader_version(), [], submission_timeout + START_SECONDS
    # as root, each job's students' processes run as a uid of their own (STUDENT_UID, STUDENT_UID - 1, ...), so that
    # one submission's processes (a fork bomb) never count against another's process limit (RLIMIT_NPROC is per uid)
    uids: queue.Queue = queue.Queue()
    for k in range(max(1, jobs)):
        uids.put(STUDENT_UID - k)

    def one(sub: Submission) -> Outcome:
        uid = uids.get()
        try:
            env = {"COURSE_GRADER_STUDENT_UID": str(uid)} if os.getuid() == 0 else {}
            return grade_one(sub, reports / sub.student, grade_options, limit, env)
        finally:
            uids.put(uid)

    def done(o: Outcome) -> None:
        gradebook.record(o.sub.student, o.sub.commit, version, o.status, o.report, o.feedback)
        bar.set_postfix_str(f"{o.sub.student}: {o.report.get('total', 0):g} ({o.status})", refresh=False)
        bar.update()
        out.append(o)

    again = []
    with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool, \
            tqdm(total=len(todo), desc="grading", unit="submission", disable=not progress) as bar:
        for fut in as_completed([pool.submit(one, s) for s in todo]):
            o = fut.result()
            if o.status == "crashed" and REFUSAL in o.report["error"] and jobs > 1:  # a grading refused while others
                # ran (a sandbox not made for lack of a resource another held) is graded again alone, after them
                again.append(o.sub)  # nothing of it ran
            else:
                done(o)
        for sub in again:  # alone, after the others: a refusal now is the grader's last word
            done(one(sub))
    return out


def grade_one(sub: Submission, out: Path, options: list[str], limit: float, env: dict | None = None) -> Outcome:
    """Run the single-submission grader on ``sub`` in a process group of its own (``env`` added to its
    environment); its outcome, whatever happens."""
    out.mkdir(parents=True, exist_ok=True)
    report_path, feedback_path = out / "report.json", out / "feedback.md"
    for p in (report_path, feedback_path):
        p.unlink(missing_ok=True)
    argv = [*GRADER, os.path.abspath(sub.path), "--json", str(report_path),
            "--markdown", str(feedback_path), *options]
    t0 = time.monotonic()
    with open(out / "grader.log", "wb") as log:
        proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                start_new_session=True, env={**os.environ, **(env or {})})
        try:
            rc, what, status = proc.wait(timeout=limit), None, "crashed"
        except subprocess.TimeoutExpired:
            _stop(proc)
            rc, what, status = proc.returncode, f"it ran past its time ({limit:g} s) and was stopped", "timed out"
    seconds = round(time.monotonic() - t0, 1)
    if what is None and rc == 0:
        try:
            return Outcome(sub, "graded", json.loads(report_path.read_text()), feedback_path.read_text())
        except (OSError, ValueError) as exc:
            what = f"its report could not be read ({exc.__class__.__name__})"
    if what is None:
        what = (f"the grader was killed by signal {-rc}" if rc < 0 else f"the grader stopped with exit status {rc}")
        tail = (out / "grader.log").read_text(errors="replace").strip().splitlines()[-1:]
        what += f" ({tail[0][:300]})" if tail else ""
    report = {"total": 0.0, "max": None, "hidden_seed": None, "seconds": seconds, "status": status,
              "error": what, "notebooks": [], "exercises": []}
    feedback = (f"# Grading feedback\n\n**Total: 0 points: your submission could not be graded.**\n\n"
                f"The grading of this submission did not finish: {status}. Your instructor has the details.\n")
    report_path.write_text(json.dumps(report, indent=1) + "\n")
    feedback_path.write_text(feedback)
    return Outcome(sub, status, report, feedback)


def _stop(proc: subprocess.Popen) -> None:
    """End a grader and everything it started (its process group): SIGTERM, then SIGKILL after 10 s."""
    for sig, wait in ((signal.SIGTERM, 10), (signal.SIGKILL, 30)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(timeout=wait)
            return
        except subprocess.TimeoutExpired:
            continue

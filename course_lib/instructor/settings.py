"""What confines a grading run: the students' processes' limits and view, and every time budget, in one place.

* :class:`Limits`: resource limits of one sandboxed process tree (per process, and the totals of
  its cgroup where the grader can make one).
* :class:`Isolation`: where the students' processes get their library, what they may see, and
  whether the run is ``insecure`` (no sandbox: a trusted local run, written into the report).
* The budgets (:func:`exercise_seconds`, :func:`nbval_seconds`, :data:`DEFAULT_SUBMISSION_SECONDS`,
  :class:`Clock`): **one clock** per exercise and one per submission for everything a submission
  causes: the student's process, the decoding of its replies, the grader's checks of them, the
  earlier steps it calls back (:mod:`course_lib.instructor.oracle`), and nbval.
"""

from __future__ import annotations

import functools
import os
import re
import resource
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import course_lib
from course_lib.instructor.cgroups import Cgroup
from course_lib.instructor.notebooks import NOTEBOOKS_DIR
from course_lib.instructor.release import release_files, write_files
from course_lib.paths import REPO_ROOT

__all__ = ["Limits", "Isolation", "Clock", "student_library", "exercise_seconds", "nbval_seconds", "SYSTEM_PATHS",
           "CALL_BACK_FACTOR", "site_allow_list", "site_folders", "START_SECONDS", "GRACE_SECONDS",
           "DEFAULT_EXERCISE_SECONDS", "DEFAULT_CELL_SECONDS", "DEFAULT_SUBMISSION_SECONDS", "STUDENT_UID",
           "MAX_NOTEBOOK_BYTES", "MAX_CODE_BYTES", "MAX_CODE_NODES", "MAX_CELL_NODES"]

# ---------------------------------------------------------------------------------------------
# Budgets: the one place where the grader's clocks are set
# ---------------------------------------------------------------------------------------------

#: Seconds for the hidden checks of one exercise by default (``--timeout``). Correct but slow code is graded (a dense
#: finite-difference Jacobian in bundle_adjust, one residual function per view in triangulate_nonlinear); an endless
#: loop costs this once, and the submission's clock bounds all. The measurements behind it: docs/benchmarks.md.
DEFAULT_EXERCISE_SECONDS = 120.0
#: Seconds for one notebook cell under nbval by default (``--cell-timeout``; :func:`nbval_seconds` gives a notebook's).
DEFAULT_CELL_SECONDS = 120.0
#: Seconds for a student's process to start (the interpreter, the sandbox, the numpy and torch imports: the kit's own
#: work, not the student's; torch's import is the slow part, docs/benchmarks.md); the exercise's budget starts after.
START_SECONDS = 120.0
#: Seconds the grader may take past an exercise's budget to finish what it was doing (decoding the last reply,
#: the check's last comparison) before it stops the exercise's worker outright.
GRACE_SECONDS = 5.0
#: Seconds for grading one submission, everything included (``--submission-timeout``); the CI template's job
#: timeout must stay above it.
DEFAULT_SUBMISSION_SECONDS = 1800.0


#: An exercise that calls earlier exercises (answered by their references, one call-back each) gets this many times
#: the budget of one that does not: each call-back costs transport, and a RANSAC without the adaptive stop (a mistake
#: the checks name) makes some 25 times the call-backs of an honest one (docs/benchmarks.md).
CALL_BACK_FACTOR = 3.0


def exercise_seconds(timeout: float, reference_seconds: float, calls_back: bool = False) -> float:
    """The wall-clock budget of one exercise's hidden checks (everything it causes, from the moment its sandboxed
    process has started): the only place it is computed.

    At least ``timeout`` (``--timeout``) and ten times the reference's time on the same hidden cases
    (:func:`course_lib.instructor.hidden.run_reference`) plus 5 s; :data:`CALL_BACK_FACTOR` times that when its code
    calls earlier exercises (their call-backs are on this clock too).

    Args:
        timeout: the run's per-exercise floor, in seconds.
        reference_seconds: the reference solution's time on the hidden cases, in seconds.
        calls_back: the exercise's code calls earlier exercises (:func:`course_lib.instructor.oracle.earlier_steps`).
    """
    base = max(float(timeout), 10.0 * float(reference_seconds) + 5.0)
    return round(base * (CALL_BACK_FACTOR if calls_back else 1.0), 1)


def nbval_seconds(cell_timeout: float) -> float:
    """Seconds for nbval of one notebook, its restart with a looping exercise cut short included.

    Three times the time limit of one cell (an honest notebook runs every cell well within it) plus 60 s for the
    kernel to start and the notebook's set-up cells.
    """
    return 3.0 * float(cell_timeout) + 60.0


class Clock:
    """A wall-clock budget of ``seconds`` (``None``: no deadline) from now: its ``deadline`` (``time.monotonic()``)."""

    def __init__(self, seconds: float | None):
        self.seconds = None if seconds is None else float(seconds)
        self.deadline = float("inf") if seconds is None else time.monotonic() + float(seconds)

    def expired(self) -> bool:
        return time.monotonic() >= self.deadline


#: Bytes of a submitted notebook the grader reads (an honest one, outputs included, is under 2 MB), and bytes of
#: source in its code cells (the kit's largest solved notebook holds 16 kB): everything the grader does with a notebook
#: (parse, place, extract, slice) is linear in its code, so these bound the grader's time and memory on it.
MAX_NOTEBOOK_BYTES = 32 << 20
MAX_CODE_BYTES = 256 << 10
#: Syntax-tree nodes in a notebook's code cells (the kit's largest solved notebook: 3 100; the grader's work on a
#: notebook is about 0.1 ms per node: this keeps it near 10 s and 200 MiB).
MAX_CODE_NODES = 80_000
#: Syntax-tree nodes in one code cell: a larger cell counts as a syntax error (its exercise alone gets no credit).
MAX_CELL_NODES = 40_000


# ---------------------------------------------------------------------------------------------
# Limits and the view of a student's process
# ---------------------------------------------------------------------------------------------

#: The uid a student's code runs as when the grader runs as root (a container, a VM): never the grading user.
STUDENT_UID = int(os.environ.get("COURSE_GRADER_STUDENT_UID", "65534"))


@dataclass
class Limits:
    """Resource limits of a student's sandboxed process tree: per process (``setrlimit`` before it starts, the
    ``RLIMIT_*`` fields), and for the whole tree in a cgroup of its own (:class:`course_lib.instructor.cgroups.Cgroup`,
    where the grader's own work on the exercise, decoding and checking its replies, runs too)."""

    cpu_seconds: int = 300  # RLIMIT_CPU (an exercise's process gets its wall-clock budget + 30 s; nbval its budget)
    memory_bytes: int = 8 << 30  # RLIMIT_AS (torch needs a few GiB of address space)
    file_bytes: int = 256 << 20  # RLIMIT_FSIZE: largest file it may write
    processes: int = 512  # RLIMIT_NPROC (threads count)
    memory_total_bytes: int = 6 << 30  # the whole process tree (cgroup), tmpfs pages and the grader's worker included
    processes_total: int = 512  # the whole process tree (cgroup pids), threads included
    disk_bytes: int = 1 << 30  # what it may write in its /tmp (a tmpfs: this plus its working copy of the submission)
    submission_bytes: int = 1 << 30  # the grader's copy of a submission (copy_submission's limit; the rest is left out)
    submission_memory_bytes: int = 12 << 30  # everything of one submission at the same time (cgroup)

    def apply(self, cpu_seconds: float | None = None) -> None:
        """Set the per-process limits in this process (a limit the platform refuses is left as it is)."""
        cpu = int(self.cpu_seconds if cpu_seconds is None else cpu_seconds)
        for which, value in ((resource.RLIMIT_CPU, (cpu, cpu + 5)), (resource.RLIMIT_AS, (int(self.memory_bytes),) * 2),
                             (resource.RLIMIT_FSIZE, (int(self.file_bytes),) * 2), (resource.RLIMIT_CORE, (0, 0)),
                             (resource.RLIMIT_NPROC, (int(self.processes),) * 2)):
            try:
                _, hard = resource.getrlimit(which)
                cap = lambda v: v if hard == resource.RLIM_INFINITY else min(v, hard)  # noqa: E731
                resource.setrlimit(which, (cap(value[0]), cap(value[1])))
            except (ValueError, OSError):
                pass

    def totals(self, cgroup: Cgroup | None) -> dict:
        """What bounds the whole process tree: the cgroup's totals, or what stands in for them."""
        if cgroup is not None:
            return cgroup.describe()
        return {"memory": f"{self.memory_bytes} bytes of address space per process (RLIMIT_AS; no cgroup can be "
                          "made here)", "processes": f"RLIMIT_NPROC {self.processes} (no cgroup can be made here)"}


#: Folders and files of the host a student's process sees (read-only), besides Python and the student release.
SYSTEM_PATHS = ["/usr", "/bin", "/sbin", "/lib", "/lib32", "/lib64", "/libx32", "/etc/ld.so.cache", "/etc/ld.so.conf",
                "/etc/ld.so.conf.d", "/etc/localtime", "/etc/passwd", "/etc/group", "/etc/nsswitch.conf", "/etc/hosts",
                "/etc/alternatives", "/etc/fonts", "/sys/devices/system/cpu"]


@dataclass
class Isolation:
    """Where a grading run's student processes get their library, and what they may see.

    Attributes:
        library: the folder whose ``course_lib`` the student's code imports (the student release).
        hide: folders never shown (the instructor's kit and library, the grader's scratch folder, the hidden
            cases): left out of the student's view, covered by an empty folder where they lie inside a folder it
            sees, and checked to be absent from its view before any of its code runs.
        keep: folders inside ``hide`` that stay visible read-only (the Python environment).
        insecure: no sandbox at all (``--insecure``: a trusted local run; the report says so).
        limits: resource limits.
        scratch: the run's folder, where each student's process gets its own private folder (removed with the run's
            folder however that process ended); None: the system's temporary folder.
    """

    library: Path
    hide: list[Path] = field(default_factory=list)
    keep: list[Path] = field(default_factory=list)
    insecure: bool = False
    limits: Limits = field(default_factory=Limits)
    scratch: Path | None = None

    @classmethod
    def for_grading(cls, library: Path, secret: list[Path], notebooks_dir: Path, self_test: bool = False,
                    insecure: bool = False, limits: Limits | None = None, scratch: Path | None = None) -> "Isolation":
        """The isolation of a grading run: hide the kit and the notebooks (unless ``self_test``) and ``secret``
        (the grader's scratch folder, the hidden cases); ``scratch``: the run's folder."""
        hide = [Path(p).resolve() for p in secret]
        if not self_test:  # the kit, and the instructor's library wherever it is installed
            hide += [REPO_ROOT.resolve(), Path(notebooks_dir).resolve(), Path(course_lib.__file__).resolve().parent]
        hide = sorted({h for h in hide if not any(h != o and h.is_relative_to(o) for o in hide)})
        keep = [Path(p).resolve() for p in python_homes()]
        keep = [k for k in keep if any(k.is_relative_to(h) for h in hide)]
        return cls(Path(library), hide, keep, insecure, limits or Limits(), scratch)

    def read_only(self) -> list[str]:
        """The allow-list: the host paths a student's process sees, read-only (each site-packages folder inside them
        shows only :func:`site_allow_list`'s entries)."""
        paths = [str(Path(self.library).resolve())] + [str(Path(p).resolve()) for p in python_homes()]
        return sorted({p for p in paths + SYSTEM_PATHS if os.path.lexists(p)}, key=len)

    def covered(self) -> list[str]:
        """The hidden folders that lie inside a folder of the allow-list (covered by an empty folder there)."""
        ro = self.read_only()
        return [str(h) for h in self.hide if any(Path(h).is_relative_to(r) for r in ro)
                and not any(Path(k).is_relative_to(h) for k in self.keep)]

    def python_path(self) -> list[str]:
        """The student's ``sys.path`` after the library: the grader's, minus the kit and ``''``."""
        out = []
        for p in sys.path:
            if not p or p in out:
                continue
            rp = Path(p).resolve()
            if not any(rp.is_relative_to(Path(h).resolve()) for h in python_homes()):
                continue  # only the Python installation is in the student's view (not the grader's script folder)
            if any(rp.is_relative_to(h) for h in self.hide) and not any(rp.is_relative_to(k) for k in self.keep):
                continue
            if rp == REPO_ROOT.resolve():
                continue
            out.append(p)
        return out

    def cgroup(self, parent: Cgroup | None = None) -> Cgroup | None:
        """A cgroup with this isolation's totals for one process tree, inside ``parent`` (None where none can be
        made)."""
        if self.insecure and parent is None:
            return None
        return Cgroup.create(self.limits.memory_total_bytes, self.limits.processes_total, parent=parent)


#: Distributions never shown to a student's process, wherever installed: the kit itself (the instructor's library,
#: installed editable, from a checkout, or from a wheel).
KIT_DISTRIBUTIONS = {"course-lib"}


def site_folders() -> list[str]:
    """Every site-packages (or dist-packages) folder of the Python installation and of the system, on the grader's
    ``sys.path`` or not: each is shown to a student's process with only :func:`site_allow_list`'s entries."""
    import glob

    found = {p for p in sys.path if p.rstrip("/").endswith(("site-packages", "dist-packages"))}
    for home in python_homes() + ["/usr", "/usr/local"]:
        for pattern in ("lib/python3*/site-packages", "lib/python3*/dist-packages", "lib/python3/dist-packages",
                        "local/lib/python3*/dist-packages", "lib64/python3*/site-packages"):
            found.update(glob.glob(os.path.join(home, pattern)))
    return sorted({os.path.realpath(p) for p in found if os.path.isdir(p)})


@functools.lru_cache(maxsize=1)
def site_allow_list() -> dict[str, list[str]]:
    """``{site folder: its entries a student's process sees}``: the top-level files and folders (and metadata) of the
    distributions installed there, the kit's own (:data:`KIT_DISTRIBUTIONS`) excepted; a folder that is not on the
    grader's ``sys.path`` shows nothing. An entry no distribution installed (a copy of ``course_lib`` put there by
    hand) is not shown either."""
    import importlib.metadata as md

    on_path = {os.path.realpath(p) for p in sys.path if p}
    out: dict[str, set[str]] = {d: set() for d in site_folders()}
    for dist in md.distributions():
        name = re.sub(r"[-_.]+", "-", (dist.metadata.get("Name") or "").lower())
        base = os.path.realpath(str(dist.locate_file("")))
        if name in KIT_DISTRIBUTIONS or base not in out or base not in on_path:
            continue
        meta = getattr(dist, "_path", None)
        tops = {Path(str(meta)).name} if meta is not None else set()
        for f in dist.files or []:
            parts = Path(str(f)).parts
            if parts and parts[0] not in ("..", "/") and not parts[0].startswith("__editable__"):
                tops.add(parts[0])
        out[base] |= tops
    return {d: sorted(e for e in es if e and "course_lib" not in e and os.path.lexists(os.path.join(d, e)))
            for d, es in out.items()}


def python_homes() -> list[str]:
    """The folders of the Python installation (the environment and the interpreter it was made from)."""
    homes = {sys.prefix, sys.base_prefix, sys.exec_prefix, sys.base_exec_prefix,
             os.path.dirname(os.path.dirname(os.path.realpath(sys.executable)))}
    return sorted(h for h in homes if h and h != "/")


def student_library(out_dir: Path, notebooks_dir: Path | None = None) -> Path:
    """Write the student release's ``course_lib`` and ``data`` into ``out_dir`` (what a student's code may import)."""
    files = release_files(Path(notebooks_dir or NOTEBOOKS_DIR))
    return write_files({rel: data for rel, data in files.items() if rel.startswith(("course_lib/", "data/"))}, out_dir)

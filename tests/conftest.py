"""The suite in parallel (pytest-xdist, ``-n auto --dist loadfile``, set in ``pyproject.toml``).

Each file runs whole on one worker (a notebook's cells share one kernel; a module's fixtures are built once).
What the workers would otherwise share is split here, before any test module imports ``course_lib``:

* the students' uid of the grader's sandbox (``COURSE_GRADER_STUDENT_UID``): ``RLIMIT_NPROC`` counts every
  process of a uid, so a fork bomb graded on one worker would starve an honest grading on the other; each worker
  gets its own block of :data:`UIDS_PER_WORKER` uids below the base (the class runs use ``uid - k`` per job);
* threads: one per worker for BLAS, OpenMP and torch (two workers with two threads each on two cores spend their
  time waiting for one another), and for the kernels and processes the tests start.

The notebooks that write into the repository's ``outputs/`` folder (``REPO_ROOT / "outputs"``: the same folder from
nbval's kernel and from the browser test's) run on one worker with the browser test, one after the other
(:func:`pytest_xdist_make_scheduler`). The files go to the workers longest first, so that no long file starts last
and the workers end together: that unit first (the longest, in the whole suite and in ``pytest -m "not slow"``, where
notebooks 08-10 alone are the longest), then :data:`FIRST`, then every other file with a slow test, then the rest in
collection order.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

UIDS_PER_WORKER = 16

#: The longest files after the browser test's unit, longest first (measured with a per-worker timeline of the whole
#: suite, README "Test"); the last ones are the longest of the quick subset too.
FIRST = (
    "tests/student/test_literal_student.py",
    "tests/instructor/test_honest_grading.py",
    "tests/instructor/test_release_behaviour.py",
    "tests/instructor/test_kit_holds_no_solution.py",
    "tests/instructor/test_attacks.py",
    "tests/instructor/test_grade.py",
    "tests/instructor/test_valid_variants.py",
    "tests/instructor/test_release.py",
    "tests/instructor/test_gradescope.py",
    "tests/instructor/test_template.py",
    "tests/checks/test_mistakes.py",
    "tests/nerf/test_train.py",
    "tests/instructor/test_classroom.py",
)

#: The files whose notebooks write into the repository's outputs/ folder: one work unit, on one worker.
REPO = Path(__file__).resolve().parent.parent
OUTPUTS_WRITERS = frozenset(["tests/browser/test_browser.py"] + [
    f"notebooks/{p.name}" for p in sorted((REPO / "notebooks").glob("*.ipynb"))
    if 'REPO_ROOT / \\"outputs\\"' in p.read_text(encoding="utf-8")])

WORKER = os.environ.get("PYTEST_XDIST_WORKER", "")  # "gw0", "gw1", ... in a worker; "" without xdist
if WORKER.startswith("gw"):
    _base = int(os.environ.get("COURSE_GRADER_STUDENT_UID", "65534"))
    os.environ["COURSE_GRADER_STUDENT_UID"] = str(_base - UIDS_PER_WORKER * int(WORKER[2:]))
    for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(_var, "1")


def pytest_collection_modifyitems(config, items) -> None:
    if not WORKER:  # the workers' collection order is the order in which the files are handed out
        return
    slow = {it.nodeid.split("::", 1)[0] for it in items if it.get_closest_marker("slow")}

    def rank(item) -> tuple[int, int]:
        path = item.nodeid.split("::", 1)[0]
        if path in OUTPUTS_WRITERS:
            return (0, 0)
        return (1, FIRST.index(path)) if path in FIRST else ((2, 0) if path in slow else (3, 0))

    items.sort(key=rank)  # stable: a file's tests keep their order


@pytest.hookimpl(tryfirst=True)
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile``, but the files of :data:`OUTPUTS_WRITERS` are one unit (one worker, one at a time)."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class OutputsOnOneWorker(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            path = nodeid.split("::", 1)[0]
            return "repository outputs/" if path in OUTPUTS_WRITERS else path

    return OutputsOnOneWorker(config, log)

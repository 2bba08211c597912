"""The grader fails closed: where it cannot make and verify a sandbox, it refuses to run students' code.

The tests that grade (or run a student's process) need that sandbox (bubblewrap, installed by ``.ci/run``).
Where it cannot be made here, they are skipped, all with the one line of the grader's refusal as the reason;
the tests of the refusal itself (``fails_closed``) always run.
"""

from __future__ import annotations

import functools

import pytest

NEEDS_SANDBOX = {"test_attacks.py", "test_classroom.py", "test_grade.py", "test_honest_grading.py", "test_oracle.py",
                 "test_sandbox.py", "test_template.py", "test_gradescope.py"}


@functools.lru_cache(maxsize=1)
def sandbox_refusal() -> str | None:
    """None where a student's process can be sandboxed and verified here, else the grader's one-line refusal."""
    import os
    import tempfile
    from pathlib import Path

    from course_lib.instructor.notebooks import NOTEBOOKS_DIR
    from course_lib.instructor.sandbox.jail import IsolationError
    from course_lib.instructor.settings import Isolation
    from course_lib.instructor.student_process import StudentProcess

    with tempfile.TemporaryDirectory() as lib:
        os.chmod(lib, 0o755)
        iso = Isolation.for_grading(Path(lib), [], NOTEBOOKS_DIR)
        try:
            with StudentProcess(iso, "", "probe", None, 30.0):
                return None
        except IsolationError as exc:
            return str(exc)


def pytest_configure(config) -> None:
    config.addinivalue_line("markers", "fails_closed: runs where the sandbox cannot be made, too")


def pytest_collection_modifyitems(config, items) -> None:
    needing = [it for it in items if it.path.name in NEEDS_SANDBOX and it.path.parent.name == "instructor"
               and "fails_closed" not in it.keywords]
    if not needing:
        return
    why = sandbox_refusal()
    if why is not None:
        skip = pytest.mark.skip(reason=f"the grader cannot sandbox students' code here: {why}")
        for it in needing:
            it.add_marker(skip)

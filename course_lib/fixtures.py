"""The stored cases of the check cells and the notebooks' starting points: ``data/fixtures/<name>.npz``.

:func:`load_fixture` reads a fixture; inside :func:`using_cases` (the grader's hidden checks, in the
grader's own process) it serves the cases given there instead. The fixtures are built in the
instructor's kit by ``python -m course_lib fixtures``.
"""

from __future__ import annotations

import contextlib

import numpy as np

from course_lib.paths import FIXTURES_DIR

__all__ = ["load_fixture", "using_cases"]

#: The cases that :func:`load_fixture` serves instead of the stored files (see :func:`using_cases`).
_CASES: dict[str, dict[str, np.ndarray]] | None = None


def load_fixture(name: str) -> dict[str, np.ndarray]:
    """The cases of fixture ``name``: ``data/fixtures/<name>.npz`` as a dict of arrays.

    Inside :func:`using_cases` (the grader's hidden checks), the cases given there instead.
    """
    if _CASES is not None:
        if name not in _CASES:
            raise FileNotFoundError(f"fixture {name!r} is not among the cases of this run")
        return {k: v.copy() for k, v in _CASES[name].items()}
    path = FIXTURES_DIR / f"{name}.npz"
    if not path.exists():
        raise FileNotFoundError(
            f"fixture {name!r} is missing ({path}); instructors rebuild fixtures with: python -m course_lib fixtures"
        )
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


@contextlib.contextmanager
def using_cases(cases: dict[str, dict[str, np.ndarray]]):
    """Within the block, the checks of this process read ``cases`` (``{fixture name: arrays}``), not the stored files.

    The grader runs the check functions on the hidden cases of a grading run this way; the
    student's code never runs in the process that holds them.
    """
    global _CASES
    saved, _CASES = _CASES, cases
    try:
        yield
    finally:
        _CASES = saved

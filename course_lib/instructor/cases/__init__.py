"""The cases behind the checks, built from the reference solutions (instructor side only).

One module per check module of :mod:`course_lib.checks`, with the same name. Each registers the
builder of its fixture with :func:`builds`: ``build() -> {key: array}`` makes the inputs of the
cases, the reference's results on them, and the results of the classic mistakes that the checks
recognise. The same builders make

* the **public fixtures** in ``data/fixtures/`` (``python -m course_lib fixtures``), which ship
  with the student kit and feed the check cells of the notebooks, and
* the **hidden cases** of a grading run (:mod:`course_lib.instructor.hidden`), with every seeded
  random generator salted by a grading-time seed, which never leave the grader's process.

The student kit holds none of this: the checks it ships compare with stored arrays only.
"""

from __future__ import annotations

import functools
import importlib
from typing import Callable

import numpy as np

from course_lib.paths import EMBEDDED_SFM

__all__ = ["builds", "builders", "store", "CASE_MODULES", "STEP_FIXTURES"]

#: The case modules, in build order (a later fixture may read an earlier one).
CASE_MODULES = (
    "fundamental",
    "essential",
    "triangulation",
    "pnp",
    "bundle_adjustment",
    "nerf_data",
    "nerf_model",
    "nerf_rendering",
)

_BUILDERS: dict[str, Callable[[], dict[str, np.ndarray]]] = {}
#: Fixtures that are a notebook's starting point (:mod:`course_lib.starting_points`), not cases of a check:
#: public by design, and never built for (or read by) the hidden checks.
STEP_FIXTURES: set[str] = set()
#: fixture name -> the check module it feeds (``course_lib.checks.<module>``)
CHECK_MODULE: dict[str, str] = {}


def builds(name: str, step: bool = False):
    """Register ``fn() -> dict[str, np.ndarray]`` as the builder of fixture ``name``.

    Args:
        name: the fixture (``data/fixtures/<name>.npz``).
        step: the fixture is a notebook's starting point (:data:`STEP_FIXTURES`), not check cases. It is
            made from the embedded scene: before that is generated (``python -m course_lib make-data``)
            the builder stores nothing (``{}``).
    """

    def register(fn):
        if step:
            STEP_FIXTURES.add(name)
            built = fn

            @functools.wraps(built)
            def fn() -> dict[str, np.ndarray]:
                return built() if (EMBEDDED_SFM / "ground_truth.json").exists() else {}

        _BUILDERS[name] = fn
        CHECK_MODULE[name] = "course_lib.checks." + fn.__module__.rsplit(".", 1)[-1]
        return fn

    return register


def builders(modules: list[str] | None = None, steps: bool = True) -> dict[str, Callable[[], dict[str, np.ndarray]]]:
    """``{fixture name: builder}`` of the case modules.

    Args:
        modules: only those feeding these check modules (``course_lib.checks.<name>``); default all.
        steps: include the step fixtures (:data:`STEP_FIXTURES`); the hidden checks leave them out.
    """
    for mod in CASE_MODULES:
        importlib.import_module(f"{__name__}.{mod}")
    wanted = None if modules is None else {m.rsplit(".", 1)[-1] for m in modules}
    return {k: fn for k, fn in _BUILDERS.items() if (steps or k not in STEP_FIXTURES)
            and (wanted is None or CHECK_MODULE[k].rsplit(".", 1)[-1] in wanted)}


def store(out: dict[str, np.ndarray], prefix: str, **arrays) -> None:
    """Store one case's arrays in a fixture under its prefix: ``out[f"{prefix}_{name}"] = array`` for each keyword."""
    out.update({f"{prefix}_{k}": v for k, v in arrays.items()})

"""Stand-ins for reference solutions that the student release leaves out.

The student kit (``python -m course_lib release``) ships some library modules that other code of
the kit builds on (for example :mod:`course_lib.nerf.render`, which the NeRF trainer uses) with
the *exercise* functions taken out. In their place sits a stand-in made by :func:`stand_in`: it
calls the student's own function of the same name, defined in the running notebook, so that the
kit's trainer and renderer use the student's ``volume_render``, ``get_rays``, ... once they are
written. Until then it raises :class:`NotImplementedError` with a message that says which
notebook the exercise belongs to.

This module is part of the student kit; the instructor's library never calls it.
"""

from __future__ import annotations

import sys
from typing import Any, Callable

__all__ = ["stand_in", "find_student_solution"]


def find_student_solution(name: str) -> Any:
    """The object called ``name`` in the running notebook (the ``__main__`` namespace), or None."""
    main = sys.modules.get("__main__")
    return getattr(main, name, None) if main is not None else None


def stand_in(name: str, notebook: str) -> Callable:
    """A function that forwards to the student's ``name`` from the running notebook.

    Args:
        name: the exercise's name (a function or class of the notebook).
        notebook: the notebook that teaches it, e.g. ``"08_nerf_rendering_and_training.ipynb"``.

    Returns:
        A callable with the exercise's name; calling it calls the student's object.
    """

    def forward(*args, **kwargs):
        mine = find_student_solution(name)
        if mine is None or getattr(mine, "__kit_stand_in__", False) or not callable(mine):
            raise NotImplementedError(
                f"{name} is an exercise of notebooks/{notebook}: the student kit leaves its reference solution "
                f"out. Define your {name} in this notebook (run its cell, or paste your solution from {notebook}) "
                "and the kit will use it here."
            )
        return mine(*args, **kwargs)

    forward.__name__ = forward.__qualname__ = name
    forward.__kit_stand_in__ = True
    forward.__doc__ = f"Stand-in for the exercise {name} of notebooks/{notebook}: calls your own {name}."
    return forward

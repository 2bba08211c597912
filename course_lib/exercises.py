"""The exercises of the notebooks, and how the kit's own code calls them.

Parts of the kit build on exercises: the SfM pipeline (:mod:`course_lib.sfm.pipeline`, notebooks 05
and 10) chains RANSAC on F (and the 8-point refit of a carried F), the pose candidates and the
cheirality choice of the initial pair (whose E is OpenCV's five-point estimate, not the lesson's
route), triangulation, PnP and the bundle adjuster's residuals; the NeRF trainer and renderer (notebooks 08-10) make rays, samples and encodings and
composite with ``volume_render``. In the instructor's kit those calls reach the reference solutions;
in the student kit (``python -m course_lib release``) they reach **the student's own functions**
(:mod:`course_lib.saved_solutions`: the function defined in the running notebook, or the one saved when the
student ran the exercise's cell in its own notebook).

Either way the kit calls an exercise exactly as its stub documents (the contract the check cells
test): SfM exercises get numpy float64 arrays, points as rows, poses ``R_cw, t_cw``; NeRF exercises
get float32 torch tensors on the run's device (:func:`course_lib.nerf.rays.camera_rays` converts
for ``get_rays``). A result that the stub allows in several forms (a tuple or a dataclass with the
same fields) is read by :func:`call` into one :class:`Fields` object.

* :data:`EXERCISES` -- every exercise: the notebook that teaches it, the module of its reference
  solution, and the fields of its result where the stub names them (a test keeps it equal to the
  notebooks); it lives in :mod:`course_lib.exercise_table`, which :mod:`course_lib.saved_solutions`
  reads too.
* :func:`implementation` -- the function the kit calls for an exercise.
* :func:`call` -- call it as the stub documents and read its result.

Introduced in ``notebooks/05_bundle_adjustment.ipynb`` (the kit's pipeline runs on your functions).
"""

from __future__ import annotations

import functools
import importlib
from typing import Any, Callable

import numpy as np

from course_lib.exercise_table import EXERCISES, Exercise, exercise_of
from course_lib.saved_solutions import stand_in
from course_lib.validate import KitInputError

__all__ = ["Exercise", "EXERCISES", "Fields", "implementation", "call", "caller", "exercise_of"]


_IMPLEMENTATIONS: dict[str, Callable] = {}


def implementation(name: str) -> Callable:
    """The function (or class) the kit calls for exercise ``name``.

    In the instructor's kit: the reference solution, ``getattr(module, name)``. In the student kit
    the reference module is left out or ships a stand-in in the exercise's place; either way the
    result is a stand-in (:func:`course_lib.saved_solutions.stand_in`) that calls the student's own
    function and says which notebook to finish where there is none yet.
    """
    ex = exercise_of(name)
    if name not in _IMPLEMENTATIONS:
        try:
            if ex.module is None:
                raise ImportError(name)
            found = getattr(importlib.import_module(ex.module), name)
        except ImportError:  # the student kit: the reference module is left out
            found = stand_in(name, ex.notebook, ex.module)
        _IMPLEMENTATIONS[name] = found
    return _IMPLEMENTATIONS[name]


class Fields:
    """The parts of an exercise's result by name (``res.R_cw``), whatever form the stub allowed for it.

    Also unpacks like the tuple the stub documents: ``R_cw, t_cw = call("pnp_linear", ...)``.
    """

    def __init__(self, names: tuple[str, ...], values: tuple):
        self._names = names
        for n, v in zip(names, values):
            setattr(self, n, v)

    def __iter__(self):
        return iter(getattr(self, n) for n in self._names)

    def __len__(self) -> int:
        return len(self._names)

    def __repr__(self) -> str:
        return f"Fields({', '.join(self._names)})"


def _fields(name: str, names: tuple[str, ...], value: Any) -> Fields:
    """Read a result that the stub allows as a tuple (in the order of ``names``) or as an object with those attributes."""
    if isinstance(value, (tuple, list)) and not hasattr(value, "_fields"):
        if len(value) != len(names):
            raise KitInputError(f"{name} returned {len(value)} values; its docstring documents {len(names)}: "
                                f"({', '.join(names)})")
        return Fields(names, tuple(value))
    if value is None:
        raise KitInputError(f"{name} returned None: its docstring documents ({', '.join(names)}) (a return missing?)")
    missing = [n for n in names if not hasattr(value, n)]
    if missing:
        raise KitInputError(f"{name} returned a {type(value).__name__} without {', '.join(missing)}: its docstring "
                            f"documents ({', '.join(names)}), as a tuple in this order or as an object with these attributes")
    return Fields(names, tuple(getattr(value, n) for n in names))


#: dtypes of the SfM results' fields that are not float64 arrays
_SFM_DTYPES = {"inliers": bool, "in_front": bool, "counts": int}


def call(name: str, *args, **kwargs) -> Any:
    """Call exercise ``name`` with the arguments its stub documents, and read its result.

    Args:
        name: the exercise.
        *args, **kwargs: exactly what the stub documents (the callers convert first).

    Returns:
        A result with several parts (:attr:`Exercise.fields`) as a :class:`Fields`; a single numpy
        result as a float64 array; anything else as returned.
    """
    ex = exercise_of(name)
    out = implementation(name)(*args, **kwargs)
    if ex.fields:
        res = _fields(name, ex.fields, out)
        if (ex.module or "").startswith("course_lib.sfm"):
            for f in ex.fields:  # numpy, in the types the stubs document
                v = getattr(res, f)
                setattr(res, f, int(v) if f == "n_iters" else np.asarray(v, dtype=_SFM_DTYPES.get(f, float)))
        return res
    if (ex.module or "").startswith("course_lib.sfm") and isinstance(out, (np.ndarray, list, tuple)):
        return np.asarray(out, dtype=float)
    return out


def caller(name: str) -> Callable:
    """``functools.partial(call, name)``: the exercise as a function the kit can pass around."""
    exercise_of(name)
    return functools.partial(call, name)

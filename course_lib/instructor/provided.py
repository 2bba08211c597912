"""What the grader puts next to an exercise in the student's process: earlier steps, as reference values.

Each exercise is graded on its own (issue 19): an exercise whose code calls an earlier exercise
(the ``NeRF`` of notebook 07 calls ``positional_encoding``, the exercise of notebook 06) is fed the
*reference's* results of that earlier step, so a mistake there costs points once, in its own exercise.
The student's process holds no reference code, so the earlier step is bound as a **table** of the
reference's values on this run's hidden inputs (:func:`course_lib.checks.nerf_model.encoding_table`):
it answers for the check's points and computes nothing.

:func:`provided_code` returns the lines that the grader appends to the exercise's extracted code;
they rebind the earlier exercise's name in the student's ``__main__`` after the student's own code
(a pasted copy of their earlier function included), where the student's code, and the kit's stand-in
of the same name, look it up at call time.
"""

from __future__ import annotations

import numpy as np

__all__ = ["PROVIDED", "provided_code"]

#: exercise -> (name it calls, fixture with the table, rows key, values key, check-module function)
PROVIDED = {
    "NeRF": ("positional_encoding", "nerf_model", "enc_rows", "enc_values", "course_lib.checks.nerf_model"),
}


def provided_code(exercise: str, fixtures: dict[str, dict[str, np.ndarray]]) -> str:
    """The code that binds the earlier steps of ``exercise`` to the reference's values (empty if none).

    Args:
        exercise: the exercise's name.
        fixtures: the cases of this run, ``{fixture name: arrays}`` (the hidden ones when grading).
    """
    if exercise not in PROVIDED:
        return ""
    from course_lib.checks.nerf_model import pack_table

    name, fixture, rows, values, module = PROVIDED[exercise]
    arrays = fixtures.get(fixture, {})
    if rows not in arrays or values not in arrays:
        return ""
    table = pack_table(arrays[rows], arrays[values])
    return ("\n\n# the grader: the earlier step, as the reference's values on this run's cases (no computation)\n"
            f"from {module} import encoding_table as _grader_encoding_table\n"
            f"{name} = _grader_encoding_table({table!r})\n")

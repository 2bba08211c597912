"""The checks behind the notebooks' check cells (part of the student kit).

One module per notebook topic (:mod:`~course_lib.checks.fundamental` for notebook 01, ...,
:mod:`~course_lib.checks.nerf_rendering` for notebook 08), and :mod:`~course_lib.checks.core`, the
machinery they share (verdicts, the scoring rule, the stored cases). A check function runs the
student's function on stored cases, compares with the reference's stored results and with
properties, and prints verdicts that name the likely mistake.

The checks hold no reference solution and import none (a test enforces that this package never
imports :mod:`course_lib.sfm` or :mod:`course_lib.nerf`): what they compare with are arrays made on
the instructor's side (:mod:`course_lib.instructor.cases` has a module of the same name for each check
module). Every module here ships to students.
"""

"""The instructor's side of the kit: release, grading, the hidden cases (never shipped to students).

* :mod:`~course_lib.instructor.notebooks` reads exercises, check cells and reference verdicts
  from the instructor notebooks; :mod:`~course_lib.instructor.plan` decides what of ``course_lib``
  ships; :mod:`~course_lib.instructor.release` writes the student kit.
* :mod:`~course_lib.instructor.cases` builds the cases behind the checks from the reference
  solutions: the public fixtures (:mod:`~course_lib.instructor.cli_fixtures`) and the hidden cases of a
  grading run (:mod:`~course_lib.instructor.hidden`).
* :mod:`~course_lib.instructor.grade` grades a submission (its steps: :mod:`~course_lib.instructor.grade_plan`,
  :mod:`~course_lib.instructor.grade_run`, :mod:`~course_lib.instructor.grade_report`):
  :mod:`~course_lib.instructor.extract` cuts each exercise out of its notebook,
  :mod:`~course_lib.instructor.student_process` runs it in a sandboxed process
  (:mod:`~course_lib.instructor.sandbox`: the wire format, bubblewrap's jail and the server that runs
  inside it) that a check calls through the proxies of :mod:`~course_lib.instructor.remote`,
  :mod:`~course_lib.instructor.hidden` checks it in a worker on the exercise's clock, and
  :mod:`~course_lib.instructor.nbval_run` runs the notebooks under nbval in the same sandbox; the
  limits and budgets are in :mod:`~course_lib.instructor.settings`.
* :mod:`~course_lib.instructor.cli_refresh_checks` stores new check verdicts in the notebooks.
"""

"""The sandbox of a student's code during grading, in four parts.

* :mod:`~course_lib.instructor.sandbox.wire`: the wire format (frames of JSON and ``.npy`` records,
  never pickle), bounded by construction; used on both sides.
* :mod:`~course_lib.instructor.sandbox.jail`: bubblewrap around the student's process, the seccomp
  filter, and the check of the sandbox before any of the student's code runs (fail closed).
* :mod:`~course_lib.instructor.sandbox.server`: the program that runs inside the sandbox (standard
  library only): it serves the student's function to the grader, or launches nbval.
* :mod:`~course_lib.instructor.sandbox.container`: container mode, where a container made for one grading is
  the isolation (Gradescope): the student's uid, a seccomp filter without network, totals; no bubblewrap.

The grader's side of the connection is :mod:`course_lib.instructor.student_process` (the process) and
:mod:`course_lib.instructor.remote` (the proxies a check calls); the limits and budgets are in
:mod:`course_lib.instructor.settings`.
"""

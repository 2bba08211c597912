"""The sandbox of a student's code during grading.

:mod:`~course_lib.instructor.sandbox.wire` (the wire format, bounded by construction, used on both sides),
:mod:`~course_lib.instructor.sandbox.jail` (bubblewrap around the student's process, checked before any of its code
runs), :mod:`~course_lib.instructor.sandbox.container` (container mode, where a container made for one grading is the
isolation), :mod:`~course_lib.instructor.sandbox.launch` (starting a process in the run's mode) and
:mod:`~course_lib.instructor.sandbox.server` (what runs inside, standard library only). The grader's side of the
connection is :mod:`course_lib.instructor.student_process` and :mod:`course_lib.instructor.remote`.
"""

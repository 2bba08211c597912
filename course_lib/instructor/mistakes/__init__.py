"""What classic mistakes give on a check's cases (instructor side only; never shipped).

The checks of the student kit recognise a mistake by comparing the student's result with what
that mistake gives on the same case. Those results are computed here, with the full library, when
the cases are built (:mod:`course_lib.instructor.cases`), and stored with the cases as arrays; the
kit itself holds no working variant of any exercise. One module per check
module, with the same name: ``variants(...) -> {key: array}``, whose keys the check module maps to
its sentences.
"""

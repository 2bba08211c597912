"""The literal-student catalogue: every exercise as a student writes it from the student release alone.

One module per notebook (``nb01`` ... ``nb08``). Each exercise is a top-level ``def`` (or ``class``)
with the released stub's signature and docstring, its body written only from the released notebook's
text, the stub's docstring and what its check cell prints: the documented types to the letter (the
dtype of the inputs is kept, no casts the stub does not ask for), only documented arguments, the
``rng`` / ``generator`` given, plain student style. None of it was written from the reference
solutions (``course_lib/sfm``, ``course_lib/nerf``), the instructor notebooks or the honest
catalogue (``tests/checks/catalogue``).

What a student puts into an exercise cell is the function's *body*: :mod:`tests.student.fill`
replaces the stub's ``# YOUR CODE HERE`` / ``raise NotImplementedError`` with it, and puts the
imports (and module-level helpers) the body uses at the top of the cell. Names the notebook itself
defines (``RansacResult``, ``pack_params``, ...) are written here too, as the notebook gives them,
so that each module imports on its own; they are not copied into the cells.
"""

MODULES = ("nb01", "nb02", "nb03", "nb04", "nb05", "nb06", "nb07", "nb08")

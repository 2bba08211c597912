"""The filler puts a literal solution into a released stub the way a student does, and refuses what it cannot fill."""

from __future__ import annotations

import ast

import pytest

from course_lib.instructor.release import stub_source
from tests.student.fill import FillError, catalogue, fill_source


@pytest.fixture(scope="module")
def solutions():
    return catalogue()


def _released(source: str) -> str:
    return stub_source(source.replace("<BODY>", "# BEGIN SOLUTION\n    pass\n    # END SOLUTION"))


def test_the_body_replaces_the_stub_and_the_signature_and_docstring_stay(solutions):
    cell = _released('def psnr(mse):\n    """The released docstring."""\n    <BODY>\n')
    out, done = fill_source(cell, solutions, notebook_names={"torch", "psnr"})
    assert done == ["psnr"]
    assert '"""The released docstring."""' in out and "NotImplementedError" not in out and "YOUR CODE" not in out
    assert out.startswith("import math\n")  # used by the body, not imported by the notebook
    namespace: dict = {"torch": __import__("torch")}  # the notebook imports torch
    exec(compile(out, "cell", "exec"), namespace)
    assert namespace["psnr"](0.01) == pytest.approx(20.0)


def test_hints_and_the_released_lines_before_the_stub_are_kept_once(solutions):
    cell = ("class NeRF(nn.Module):\n    \"\"\"doc\"\"\"\n\n"
            "    def __init__(self, depth=8, width=256, skips=(4,), pos_freqs=10, dir_freqs=4, use_viewdirs=True, "
            "view_width=128):\n        super().__init__()\n        # BEGIN SOLUTION\n        # HINT: the trunk first\n"
            "        pass\n        # END SOLUTION\n\n    def forward(self, pts, viewdirs):\n        # BEGIN SOLUTION\n"
            "        pass\n        # END SOLUTION\n")
    out, done = fill_source(stub_source(cell), solutions, notebook_names={"torch", "nn", "positional_encoding"})
    assert done == ["NeRF.__init__", "NeRF.forward"]
    assert out.count("super().__init__()") == 1 and "# HINT: the trunk first" in out
    ast.parse(out)


def test_a_changed_signature_or_an_unknown_exercise_is_an_error(solutions):
    with pytest.raises(FillError, match=r"released stub is psnr\(mse, peak\).*literal catalogue has psnr\(mse\)"):
        fill_source(_released("def psnr(mse, peak):\n    <BODY>\n"), solutions, set())
    with pytest.raises(FillError, match="no literal solution for new_exercise"):
        fill_source(_released("def new_exercise(x):\n    <BODY>\n"), solutions, set())


def test_a_cell_without_a_stub_is_left_as_it_is(solutions):
    assert fill_source("x = 1\n", solutions, set()) == ("x = 1\n", [])

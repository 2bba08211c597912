"""What a student reads holds no text of the kit's development: no issue numbers, dates or who measured what.

The notebooks (markdown, code and the outputs they are committed with), README.md, environment.txt,
docs/mistakes.md and the docstrings and comments of every module a student kit ships
(:func:`course_lib.instructor.release_names.student_texts`). ``release --verify`` runs the same scan on
the release itself (:func:`course_lib.instructor.release_names.false_claims`).
"""

from __future__ import annotations

import pytest

from course_lib.instructor.release_names import INTERNAL, internal_references
from course_lib.paths import REPO_ROOT


def test_no_development_text_where_a_student_reads():
    assert internal_references(REPO_ROOT) == []


@pytest.mark.parametrize("text", ["issue #6's targets", "Issue 12 asked for >= 32 dB", "(H12, 2026-11-22 00:00 UTC)",
                                  "5-min runs (H5, several loads)", "until issue 29", "in the last session",
                                  "as the issue asks", "the team measured 9 s", "ask the lead", "helper sessions",
                                  "merged from wt-text", "the session of 2026-11-29"])
def test_the_scan_finds_development_text(text):
    assert INTERNAL.search(text)


@pytest.mark.parametrize("text", ["(H0, W0) the image size", "H, W = 600, 800", "bwrap --new-session",
                                  "np.random.default_rng(2026)", "x_cam = R_cw X + t_cw",
                                  "The helpers below (given) pack and unpack p", "a stopped run resumes from its checkpoint",
                                  "mislead the solver", "a lead of 2 px", "--new-session", "the issued warning",
                                  "in this kernel session"])
def test_the_scan_leaves_ordinary_text_alone(text):
    assert not INTERNAL.search(text)

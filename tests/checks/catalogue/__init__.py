"""The catalogues behind the check tests: buggy versions, honest solutions and trivial answers.

One module per check module of :mod:`course_lib.checks` (same name). Each defines

* ``MISTAKES``: classic mistakes, each a buggy version of an exercise written as a student would
  (:class:`Mistake`), with the words its verdict must contain to *name* it;
* ``HONEST``: correct solutions (:class:`Honest`), written independently and in other valid
  styles and documented conventions; every one must score full marks;
* ``TRIVIAL`` (where there are some): constants of the right shape, which must earn nothing.

:mod:`tests.checks.test_mistakes` runs them all; ``python -m tests.checks.test_mistakes`` prints
the table.
"""

from __future__ import annotations

import contextlib
import importlib
import io
from dataclasses import dataclass
from typing import Callable

import numpy as np

from course_lib.checks import core

#: The catalogue modules, in notebook order.
TOPICS = ("fundamental", "essential", "triangulation", "pnp", "bundle_adjustment", "nerf_data", "nerf_model",
          "nerf_rendering", "students44")


@dataclass
class Mistake:
    """One classic mistake: a buggy version of an exercise and what its verdict must say."""

    exercise: str
    name: str  # the mistake, in a few words
    check: Callable  # the check function of the notebook
    fn: Callable  # the buggy version
    names: tuple[str, ...]  # the verdict names the mistake: all of these (lower case) appear in it
    defining: str | None = None  # the defining property it breaks, if any
    batch: str = "classic"  # "classic": the mistakes the checks were built from; "29", "44": written for those issues


@dataclass
class Honest:
    """A correct solution of an exercise (in some style or documented convention): it must score full marks."""

    exercise: str
    style: str  # what is particular about it, in a few words
    check: Callable
    fn: Callable


def misnamed(m: Mistake, result: core.CheckResult) -> list[str]:
    """The failed verdicts that confidently name a mistake (:attr:`core.Verdict.named`) that is not ``m``.

    A verdict names ``m`` when all of ``m.names`` appear in its text; one that names another mistake is
    a confident wrong name, the worst feedback (issue 29).
    """
    return [v.text for v in result.verdicts
            if not v.ok and v.named and not all(w.lower() in v.text.lower() for w in m.names)]


def run_check(check: Callable, fn: Callable) -> tuple[core.CheckResult, str]:
    """Run a check function on ``fn``; return its CheckResult and printed verdict."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        check(fn)
    out = buf.getvalue()
    exercise = out.splitlines()[0].strip()
    return core.RESULTS[exercise], out


def collect(kind: str) -> list:
    """``MISTAKES``, ``HONEST`` or ``TRIVIAL`` of every catalogue module, in notebook order."""
    out = []
    for t in TOPICS:
        out += getattr(importlib.import_module(f"{__name__}.{t}"), kind, [])
    return out


def _torch():
    import torch

    return torch


def _h(x):
    return np.column_stack([x, np.ones(len(x))])

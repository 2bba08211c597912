"""The honest catalogue graded on the hidden cases of many grading salts: where does honest code lose a point?

The grader builds new hidden cases for every grading salt (:func:`course_lib.instructor.hidden.build_in_process`)
and scores a student's run against the reference's run on the same cases (:func:`course_lib.checks.core.score_against`,
full marks: :func:`course_lib.instructor.hidden.all_pass`). An honest solution of the catalogue
(``tests/checks/catalogue``, ``HONEST``) must get full marks on every salt, not only on the public cases; the
randomized exercises (the RANSAC of notebooks 01 and 04) are the ones most likely to be unlucky on some salt.

``python -m tests.checks.honest_salts --salts 200`` grades every honest solution of the RANSAC exercises over salts
0..199 and prints, per solution, the salts where it lost a point and the failed verdicts (numbers masked, so that
the same verdict on two salts reads the same); ``--exercises all`` takes every exercise of the catalogue (the nerf
ones need torch and take longer). ``tests/checks/test_honest_salts.py`` runs it on a few salts.

Measured on salts 0..199 (2026-11-29): before the majority rule of :func:`course_lib.checks.ransac.call`, the three
catalogued F loops lost a point on 4 salts each, the literal student's on 1, the PnP loops on 1-3 (the embedded
scene); after it, none (stratified_samples and NeRF, the other seeded exercises: none, before and after).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import re
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from course_lib.checks import core
from course_lib.exercise_table import EXERCISES
from course_lib.instructor.hidden import all_pass, build_hidden_fixtures, run_check
from tests.checks.catalogue import Honest, collect

__all__ = ["RANDOMIZED", "Tally", "grade_salts", "honest_of", "reference_steps", "table", "main"]

#: The exercises whose verdicts depend on the student's own random draws (rng argument).
RANDOMIZED = ("ransac_fundamental", "pnp_ransac")


@dataclass
class Tally:
    """One honest solution over the salts: the salts where it lost a point and the verdicts it failed there."""

    honest: Honest
    salts: int = 0
    lost: list[int] = field(default_factory=list)
    verdicts: Counter = field(default_factory=Counter)

    @property
    def label(self) -> str:
        return f"{self.honest.exercise}: {self.honest.style}"


def honest_of(exercises: tuple[str, ...] | None) -> list[Honest]:
    """The honest solutions of the catalogue for ``exercises`` (None: all), and the literal student's
    (``tests/student/literal``, written from the released notebooks) for the exercises that have one."""
    out = [h for h in collect("HONEST") if exercises is None or h.exercise in exercises]
    checks = {h.exercise: h.check for h in out}
    for ex, check in checks.items():
        if ex not in EXERCISES:
            continue
        module = importlib.import_module(f"tests.student.literal.nb{EXERCISES[ex].notebook[:2]}")
        if callable(getattr(module, ex, None)):
            out.append(Honest(ex, "the literal student (tests/student/literal)", check, getattr(module, ex)))
    return out


def _reference(exercise: str):
    """The reference solution of ``exercise`` (None where it has no module in the kit, e.g. psnr)."""
    module = EXERCISES[exercise].module if exercise in EXERCISES else None
    return None if module is None else getattr(importlib.import_module(module), exercise)


@contextlib.contextmanager
def reference_steps(h: Honest):
    """Within the block, the earlier exercises that ``h`` calls are the references, as in the grader (its oracle
    answers a graded exercise's calls of the earlier steps, :mod:`course_lib.instructor.oracle`)."""
    names = list(EXERCISES)
    g = getattr(h.fn, "__globals__", {})
    before = names[:names.index(h.exercise)] if h.exercise in names else []
    saved = {n: g[n] for n in before if n in g and _reference(n) is not None}
    g.update({n: _reference(n) for n in saved})
    try:
        yield
    finally:
        g.update(saved)


def _masked(text: str) -> str:
    """A verdict with its numbers masked (the same verdict on two salts reads the same)."""
    return re.sub(r"-?\d+(\.\d+)?(e-?\d+)?", "#", text)[:200]


def grade_salts(honest: list[Honest], salts: list[int], steps: bool = True, log=None) -> list[Tally]:
    """Grade every solution of ``honest`` on the hidden cases of every salt of ``salts``; one :class:`Tally` each.

    Args:
        steps: the earlier exercises a solution calls are the references, as in the grader (:func:`reference_steps`);
            False: the catalogue's own (as in a notebook).
        log: called with a line per salt (its time, the solutions that lost a point there).
    """
    tallies = [Tally(h) for h in honest]
    modules = sorted({h.check.__module__ for h in honest})
    with tempfile.TemporaryDirectory(prefix="honest-salts-") as folder:
        for salt in salts:
            t0 = time.perf_counter()
            build_hidden_fixtures(Path(folder), modules, salt)  # as the grader does: written, then held in memory
            _grade_salt(tallies, folder, salt, steps)
            if log is not None:
                lost = [t.label for t in tallies if t.lost and t.lost[-1] == salt]
                log(f"salt {salt}: {time.perf_counter() - t0:.1f} s" + (f", lost: {lost}" if lost else ""))
    return tallies


def _grade_salt(tallies: list[Tally], folder: str, salt: int, steps: bool) -> None:
    """Grade every solution of ``tallies`` on the hidden cases in ``folder`` (made for ``salt``; ``steps``: with the
    references' earlier steps, :func:`reference_steps`)."""
    refs = {}
    for ex, check in {t.honest.exercise: t.honest.check for t in tallies}.items():
        ref = _reference(ex)
        refs[ex] = None if ref is None else run_check(check.__module__, check.__name__, folder, ref)[0]
    for t in tallies:
        h = t.honest
        with reference_steps(h) if steps else contextlib.nullcontext():
            result, printed = run_check(h.check.__module__, h.check.__name__, folder, h.fn)
        ref = refs[h.exercise]
        full = (all_pass(result, ref) if ref is not None else
                result is not None and result.ok and core.score(result) == 1.0)
        t.salts += 1
        if not full:
            t.lost.append(salt)
            failed = [v.text for v in result.verdicts if not v.ok] if result is not None else [printed[-200:]]
            t.verdicts.update(_masked(v) for v in failed)


def table(tallies: list[Tally]) -> str:
    """The table: per solution, the salts where it lost a point, and its failed verdicts (with their counts)."""
    w = max(len(t.label) for t in tallies) + 2
    lines = [f"{'honest solution':<{w}} lost/salts  salts"]
    for t in tallies:
        lines.append(f"{t.label:<{w}} {len(t.lost):>4}/{t.salts:<5}  {t.lost[:12]}{' ...' if len(t.lost) > 12 else ''}")
        lines += [f"{'':<{w}}   {n} x {v}" for v, n in t.verdicts.most_common()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m tests.checks.honest_salts", description=__doc__.splitlines()[0])
    p.add_argument("--salts", type=int, default=20, help="grade on salts first..first+N-1 (default 20)")
    p.add_argument("--first", type=int, default=0, help="the first salt (default 0)")
    p.add_argument("--only", default="", help="comma-separated salts to grade on (instead of --salts/--first)")
    p.add_argument("--exercises", default=",".join(RANDOMIZED),
                   help="comma-separated exercises, or 'all' (default: the randomized ones)")
    p.add_argument("--own-steps", action="store_true",
                   help="the earlier exercises a solution calls are the catalogue's own (default: the references, "
                        "as the grader's oracle answers them)")
    p.add_argument("--quiet", action="store_true", help="no line per salt")
    a = p.parse_args(argv)
    exercises = None if a.exercises == "all" else tuple(a.exercises.split(","))
    salts = [int(x) for x in a.only.split(",")] if a.only else list(range(a.first, a.first + a.salts))
    log = None if a.quiet else (lambda s: print(s, file=sys.stderr, flush=True))
    tallies = grade_salts(honest_of(exercises), salts, not a.own_steps, log)
    print(table(tallies))
    return 1 if any(t.lost for t in tallies) else 0


if __name__ == "__main__":
    sys.exit(main())

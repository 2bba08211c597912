"""Every valid variant and convention gets full marks through the real grader (issue 29).

The honest catalogue (``tests/checks/catalogue``) holds, beside each exercise's main solution, correct
solutions in other valid forms and conventions: F / F[2, 2] and -F, E up to scale and -E, the four pose
candidates in another order, a quaternion for the rotation vector, float32 answers throughout, near and far
per ray, slow but correct code (a residual per view, a dense Jacobian), ... Full marks are the two shares
of the grader:

* the hidden checks (90 %): the variants are pasted into a student release and graded by the real
  grader, in rounds (one variant per exercise in each round, the main solutions elsewhere);
* the check cell printing the reference verdict (10 %): each variant's check, run on the notebook's own
  cases, prints exactly what the main solution's prints (what nbval compares; the main solutions print
  the reference verdict under nbval in ``test_honest_grading``).

The slow variants (a style that says "(slow)") are graded only with ``GRADE_SLOW_TESTS=1`` (minutes);
``python -m tests.instructor.test_valid_variants`` grades them all and prints the table.
"""

from __future__ import annotations

import os

import pytest

from course_lib.checks import core
from course_lib.instructor.grade import HIDDEN_SHARE, grade_submission, prepare_hidden
from course_lib.instructor.notebooks import kit_specs
from tests.checks.catalogue import Honest, collect, run_check
from tests.instructor.honest import choose, honest_submission

SEED = 2029
SLOW = bool(os.environ.get("GRADE_SLOW_TESTS"))


def variants(slow: bool = SLOW) -> list[Honest]:
    """The catalogue's correct solutions other than each exercise's main one and the reference."""
    main = choose(variant=False)
    out = []
    for h in collect("HONEST"):
        if not h.fn.__module__.startswith("tests.checks.catalogue") or main.get(h.exercise) is h:
            continue
        if "(slow)" in h.style and not slow:
            continue
        out.append(h)
    return out


def rounds(vs: list[Honest]) -> list[dict[str, Honest]]:
    """``[{exercise: variant}]``: the k-th variant of every exercise in round k."""
    by_exercise: dict[str, list[Honest]] = {}
    for h in vs:
        by_exercise.setdefault(h.exercise, []).append(h)
    n = max((len(v) for v in by_exercise.values()), default=0)
    return [{ex: hs[k] for ex, hs in by_exercise.items() if k < len(hs)} for k in range(n)]


def _notebooks(picked: dict[str, Honest]) -> list[str]:
    return sorted({s.name[:2] for s in kit_specs() for e in s.exercises if e.name in picked})


def grade_round(tmp_path, picked: dict[str, Honest], hidden) -> dict[str, dict]:
    """Grade one round's variants (hidden checks only); ``{exercise: its grade}`` of the picked exercises."""
    nbs = _notebooks(picked)
    sub, filled = honest_submission(tmp_path / "sub", notebooks=nbs, picked=picked)
    assert set(picked) <= filled, f"not filled in: {set(picked) - filled}"
    report = grade_submission(sub, notebooks=nbs, hidden=hidden, run_nbval=False)
    return {g["name"]: g for g in report["exercises"] if g["name"] in picked}


@pytest.fixture(scope="module")
def hidden(tmp_path_factory):
    specs = [s for s in kit_specs() if s.exercises]
    return prepare_hidden(specs, SEED, tmp_path_factory.mktemp("hidden"))


@pytest.mark.parametrize("h", variants(), ids=lambda h: f"{h.exercise}: {h.style}")
def test_a_variant_prints_the_reference_verdict(h, capsys):
    """The nbval share: on the notebook's own cases the variant's check cell prints the reference verdict."""
    main = choose(variant=False)[h.exercise]
    _, want = run_check(main.check, main.fn)
    result, out = run_check(h.check, h.fn)
    assert core.score(result) == 1.0 and not result.details_failed and out == want, out


@pytest.mark.parametrize("k", range(len(rounds(variants()))))
def test_variants_get_the_full_hidden_share_through_the_grader(k, hidden, tmp_path):
    picked = rounds(variants())[k]
    graded = grade_round(tmp_path, picked, hidden)
    short = {ex: (picked[ex].style, g["points"], g["feedback"]) for ex, g in graded.items()
             if g["points"] < round(g["max_points"] * HIDDEN_SHARE, 2)}
    assert not short, short


def main() -> None:
    """Grade every variant (the slow ones too) and print ``exercise: style  hidden points  verdict as reference's``."""
    import tempfile
    from pathlib import Path

    vs = variants(slow=True)
    with tempfile.TemporaryDirectory() as tmp:
        hidden_cases = prepare_hidden([s for s in kit_specs() if s.exercises], SEED, Path(tmp) / "hidden")
        rows = []
        for k, picked in enumerate(rounds(vs)):
            graded = grade_round(Path(tmp) / f"round{k}", picked, hidden_cases)
            for ex, h in picked.items():
                g = graded[ex]
                main = choose(variant=False)[ex]
                _, want = run_check(main.check, main.fn)
                result, out = run_check(h.check, h.fn)
                same = core.score(result) == 1.0 and not result.details_failed and out == want
                rows.append((ex, h.style, g["points"], g["max_points"], g["hidden"].get("seconds"), same,
                             g["feedback"][-1] if g["feedback"] else ""))
    w = max(len(r[0]) + len(r[1]) for r in rows) + 3
    print(f"{'exercise: valid variant':<{w}} hidden/9  seconds  check cell = reference's  (full marks = 9 + 1)")
    for ex, style, pts, mx, sec, same, last in rows:
        print(f"{ex + ': ' + style:<{w}} {pts:>8.2f} {sec if sec is not None else '':>8} {'yes' if same else 'NO':>6}"
              + (f"   {last[:100]}" if "slow" in last else ""))
    full = sum(1 for r in rows if r[2] >= round(r[3] * HIDDEN_SHARE, 2) and r[5])
    print(f"\n{full}/{len(rows)} valid variants get full marks (hidden share through the grader and the reference verdict)")


if __name__ == "__main__":
    main()

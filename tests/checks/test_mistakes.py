"""The catalogues of :mod:`tests.checks.catalogue` run through the checks.

For every mistake of the catalogue: the check fails it (caught), the verdict names it (all the
expected words appear), no failed check confidently names *another* mistake (misnamed: a verdict
marked as naming a mistake, :attr:`course_lib.checks.core.Verdict.named`, whose text lacks the
expected words), and a mistake that breaks a defining property (see
:func:`course_lib.checks.core.declare_defining`) scores at most half and leads the verdict with
that property. Every honest solution scores full marks, and every declared defining property is
tested on at least three cases. Every trivial answer (a constant of the right shape) earns nothing.

``python -m tests.checks.test_mistakes`` prints the table: caught, named and misnamed per exercise
(for the whole catalogue and for issue 29's mistakes written as students write them), the points of
every mistake and of every honest solution (out of the grader's 10 per exercise: 90 %
from the hidden checks' score, 10 % from the nbval verdict, which a failing check never earns).
docs/mistakes.md explains how to add a mistake.
"""

from __future__ import annotations

import pytest

from course_lib.checks import core
from tests.checks.catalogue import Honest, Mistake, collect, misnamed, run_check

#: Points per exercise in the grader and the share of them that comes from the hidden checks.
POINTS, HIDDEN_SHARE = 10.0, 0.9

MISTAKES: list[Mistake] = collect("MISTAKES")
HONEST: list[Honest] = collect("HONEST")
TRIVIAL: list = collect("TRIVIAL")


def verdict(m: Mistake):
    """``(result, printed text, caught, named, misnamed verdicts)`` of one mistake."""
    result, out = run_check(m.check, m.fn)
    lines = out.lower()
    caught = not result.ok
    named = caught and all(w.lower() in lines for w in m.names)
    return result, out, caught, named, misnamed(m, result)


@pytest.mark.parametrize("m", MISTAKES, ids=[f"{m.exercise}: {m.name}" for m in MISTAKES])
def test_mistake_is_caught_named_and_weighed(m: Mistake):
    result, out, caught, named, wrong = verdict(m)
    if m.batch == "44":  # written before reading the checks: never confidently misnamed; caught and named are measured
        assert not wrong, f"the verdict confidently names another mistake than '{m.name}': {wrong}\n{out}"
        return
    assert caught, f"the check passes the mistake '{m.name}':\n{out}"
    assert not wrong, f"the verdict confidently names another mistake than '{m.name}': {wrong}\n{out}"
    assert named, f"the verdict does not name '{m.name}' (expected {m.names}):\n{out}"
    frac = core.score(result)
    assert frac < 1.0
    if m.defining:
        assert m.defining in result.defining_failed, f"'{m.name}' should break '{m.defining}':\n{out}"
        assert frac <= core.DEFINING_CAP, f"'{m.name}' breaks '{m.defining}' but scores {frac:.2f}:\n{out}"
        first = out.splitlines()[1]
        assert "defining property" in first and m.defining in first, f"the verdict does not lead with it:\n{out}"


def test_catalogue_size():
    per_exercise: dict[str, int] = {}
    for m in MISTAKES:
        per_exercise[m.exercise] = per_exercise.get(m.exercise, 0) + 1
    assert len(MISTAKES) >= 40
    assert min(per_exercise.values()) >= 2, per_exercise


@pytest.mark.parametrize("h", HONEST, ids=[f"{h.exercise}: {h.style}" for h in HONEST])
def test_honest_solution_scores_full_and_each_defining_property_is_tested_three_times(h: Honest):
    result, out = run_check(h.check, h.fn)
    assert result.ok and core.score(result) == 1.0, out
    for prop in core.DEFINING.get(result.exercise, {}):
        n = sum(1 for v in result.verdicts if v.defining == prop)
        assert n >= 3, f"{result.exercise}: defining property '{prop}' is tested on {n} cases, expected >= 3\n{out}"


@pytest.mark.parametrize("check, fn", TRIVIAL, ids=[f"{c.__name__}-{k}" for k, (c, _) in enumerate(TRIVIAL)])
def test_a_trivial_answer_earns_nothing(check, fn):
    result, out = run_check(check, fn)
    assert core.score(result) == 0.0, out


def main() -> None:
    """Print the tables: every mistake (caught, named, misnamed, points), the counts per exercise, honest points."""
    rows = []
    for m in MISTAKES:
        result, out, caught, named, wrong = verdict(m)
        diagnosed = any(v.named and not v.ok and all(w.lower() in v.text.lower() for w in m.names)
                        for v in result.verdicts)
        rows.append((m.exercise, m.name, caught, named, m.defining or "", POINTS * HIDDEN_SHARE * core.score(result),
                     bool(wrong), m.batch, wrong, diagnosed))
    w = max(len(r[0]) + len(r[1]) for r in rows) + 3
    print(f"{'exercise: mistake':<{w}} caught named    how misnamed points/10  defining property")
    for ex, name, caught, named, prop, pts, wrong, batch, texts, diag in rows:
        how = "diagnosis" if diag else ("property" if named else "")
        print(f"{ex + ': ' + name:<{w}} {'yes' if caught else 'NO':>6} {'yes' if named else 'NO':>5} {how:>9} "
              f"{'YES' if wrong else '':>8} {pts:>9.2f}  {prop}")
        for t in texts:
            print(f"{'':<{w}}   misnamed by: {t}")
    print("\n(named: the verdict holds the mistake's words; by a diagnosis: a verdict that names the mistake, said as "
          "what the student did; by a property: the failing property, with numbers and the formula)")
    for label, sel in (("whole catalogue", rows), ("issue 29's mistakes", [r for r in rows if r[7] == "29"]),
                       ("issue 44's mistakes", [r for r in rows if r[7] == "44"])):
        print(f"\n{label}: caught {sum(r[2] for r in sel)}/{len(sel)}, named {sum(r[3] for r in sel)}/{len(sel)} "
              f"({sum(r[9] for r in sel)} by a diagnosis, {sum(r[3] and not r[9] for r in sel)} by the failing property), "
              f"confidently misnamed {sum(r[6] for r in sel)}; {sum(1 for r in sel if r[4])} break a defining property, "
              f"max points among them {max((r[5] for r in sel if r[4]), default=0):.2f}/10")
    print(f"\n{'exercise':<28} mistakes caught named misnamed")
    for ex in dict.fromkeys(r[0] for r in rows):
        mine = [r for r in rows if r[0] == ex]
        print(f"{ex:<28} {len(mine):>8} {sum(r[2] for r in mine):>6} {sum(r[3] for r in mine):>5} "
              f"{sum(r[6] for r in mine):>8}")
    print(f"\n{'honest solution':<{w}} points/10")
    for h in HONEST:
        result, _ = run_check(h.check, h.fn)
        print(f"{h.exercise + ': ' + h.style:<{w}} {POINTS * HIDDEN_SHARE * core.score(result):>9.2f}")


if __name__ == "__main__":
    main()

"""The check machinery shared by every notebook: verdicts, fixtures, and safe calls.

A check cell in a notebook calls one function of a check module of
:mod:`course_lib.checks` (one per notebook topic, e.g. :mod:`course_lib.checks.fundamental`)
with the student's function. That check function runs the
student's code on stored cases (fixtures), compares with the stored reference results and with
properties (rank 2, det R = +1, points in front), and prints short verdicts through a
:class:`Check`::

    from course_lib.checks.fundamental import check_eight_point

    check_eight_point(eight_point)

    eight_point
      ✔ noiseless synthetic pair: F has shape (3, 3)
      ✔ noiseless synthetic pair: F equals the true F (up to scale and sign)
      ✘ noisy synthetic pair (1 px noise): F fits the true geometry worse than the reference's 8-point F:
        median epipolar distance of the noiseless points 0.698 px, reference 0.314 px: your F is the
        8-point result on raw pixels (not normalized): normalize both point sets with normalize_points, ...
      ...
      11 of 18 checks passed

Every check module works the same way: it reads its cases, names a mistake only when that mistake is the unique
explanation of what it saw on every case built to isolate it (what each mistake gives is stored with the cases:
:func:`unique_key`, :func:`report_cases`), and otherwise says which property fails, with numbers. Equal means one
rule for all (:func:`close_rel`, :func:`same_up_to_scale`, :data:`RTOL`): a correct answer in float32 passes.

Lines of passing checks are deterministic (no floating-point numbers), so nbval can compare
them; failing lines may carry numbers, since they never appear in a reference run.

Checks are weighed by what they test (:func:`score`, the grader's one rule): shape and dtype
checks are gates that earn no points; a check of a *defining* property (rank 2 for F, det +1 for
a rotation, Δ in α; declared per exercise with :func:`declare_defining`) caps the score at one
half when it fails, and the printed verdict then leads with it. docs/mistakes.md (in the instructor's kit)
documents the defining properties and the catalogue of classic mistakes that the checks name.

Fixtures are stored cases in ``data/fixtures/<name>.npz`` (inputs, the reference's results, the
results of classic mistakes), made from the reference solutions on the instructor's side by one
command, ``python -m course_lib fixtures`` (:mod:`course_lib.instructor.cases`); the test suite
rebuilds them and compares, to prove they are current. Check cells and step inputs read fixtures
only (:func:`load_fixture`), so a student release without the reference solutions still runs and
checks; the grader runs the same checks on hidden cases (:func:`using_cases`).
"""

from __future__ import annotations

import re
import traceback
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from course_lib.fixtures import load_fixture, using_cases  # noqa: F401 - the checks' way to their cases

__all__ = [
    "Check",
    "CheckResult",
    "Verdict",
    "score",
    "score_against",
    "score_reasons",
    "SCORING_RULE",
    "declare_defining",
    "DEFINING",
    "DEFINING_CAP",
    "RESULTS",
    "calls_name",
    "code_text",
    "FAILED",
    "load_fixture",
    "using_cases",
    "as_float",
    "Outcome",
    "report_cases",
    "refinement_verdicts",
    "EPS32",
    "RTOL",
    "close_rel",
    "same_up_to_scale",
    "scale_free_gap",
    "unique_key",
]

PASS, FAIL = "✔", "✘"


class _Failed:
    """Sentinel returned by :meth:`Check.call` when the student's function raised."""

    def __repr__(self) -> str:
        return "FAILED"

    def __bool__(self) -> bool:
        return False


FAILED = _Failed()


#: The most a result with a failed defining property can score (a fraction of the exercise's points).
DEFINING_CAP = 0.5

#: Defining properties per exercise: ``{exercise: {property: what it means}}`` (see :func:`declare_defining`).
DEFINING: dict[str, dict[str, str]] = {}


def declare_defining(exercise: str, properties: dict[str, str]) -> None:
    """Declare the defining properties of an exercise (called once by its check module).

    A defining property is what makes the result the thing it is named after: rank 2 for a
    fundamental matrix, det R = +1 for a rotation, the interval length Δ in α for volume
    rendering. A check that tests one passes ``defining=<property>`` to :meth:`Check.expect`;
    failing it caps the exercise's score at :data:`DEFINING_CAP` (see :func:`score`), and the
    printed verdict leads with it.

    Args:
        exercise: the exercise name (the name given to :class:`Check`).
        properties: ``{short name: one line that says why it is defining}``.
    """
    DEFINING[exercise] = dict(properties)


@dataclass(frozen=True)
class Verdict:
    """One recorded check.

    Attributes:
        ok: whether it passed.
        text: the printed line without its mark.
        kind: ``"points"`` (earns points), ``"gate"`` (shape, dtype: a precondition that earns
            nothing when it passes, and counts as a failed check when it fails, since the checks
            it guards could not run) or ``"detail"`` (correct maths in another documented form than
            the docstring asks for, e.g. another order: it neither earns nor costs hidden-check
            points, but the exercise is no longer perfect, which costs the last 10 % of the grade:
            one point of ten).
        defining: the defining property it tests (see :func:`declare_defining`), or None.
        named: for a failed check whose text names a mistake ("you compared the squared error with
            threshold_px"), the mistake's key; a check names one only when that mistake is the unique
            explanation of what it saw on every case built to isolate it. A failed check that states which
            property fails, with numbers, names none (None).
    """

    ok: bool
    text: str
    kind: str = "points"
    defining: str | None = None
    named: str | None = None


@dataclass
class CheckResult:
    """The outcome of one check cell: which exercise, how many checks passed, and the lines.

    ``passed`` and ``total`` count every recorded check (gates included), as printed in the
    summary line; ``verdicts`` says which of them earn points and which test a defining property,
    which is what :func:`score` uses.
    """

    exercise: str
    passed: int
    total: int
    lines: list[str] = field(default_factory=list)
    verdicts: list[Verdict] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.total > 0 and self.passed == self.total

    @property
    def defining_failed(self) -> list[str]:
        """The defining properties that failed, in the order of their first failure."""
        out: list[str] = []
        for v in self.verdicts:
            if v.defining and not v.ok and v.defining not in out:
                out.append(v.defining)
        return out

    @property
    def details_failed(self) -> list[str]:
        """The failed details (see :class:`Verdict`): correct maths, not in the documented form."""
        return [v.text for v in self.verdicts if v.kind == "detail" and not v.ok]

    def __repr__(self) -> str:  # deterministic, in case a cell displays it
        return f"CheckResult({self.exercise!r}, {self.passed}/{self.total})"


#: The scoring rule, as :func:`score` and :func:`score_against` apply it and the grader adds its last share. The
#: README (the kit's and the student release's) and docs/mistakes.md quote it verbatim (a test keeps them equal).
SCORING_RULE = """\
Each exercise is worth its points (10 for most). **90 %** come from the *hidden checks*: the exercise's
check runs again on new synthetic cases, and so does the reference solution; what the reference passes
is what there is to earn. Of those checks:

* every check of a value or a property (a *point check*) earns an equal share;
* a shape or dtype check (a *gate*) earns nothing when it passes; when it fails it counts as one failed
  check (the checks behind it could not run), and so does a check that never ran because a call
  returned nothing usable;
* a failed **defining property** (rank 2 for F, det R = +1 for a rotation, the interval length in the
  opacity, ...: the verdict names it on its first line) caps the exercise at **half** of these points,
  however many other checks pass.

The last **10 %** come when every hidden check passes in the documented form and the exercise's check
cell, with the notebook run top to bottom, prints the reference verdict. An exercise that calls the
kit's reference solution, whose check cell was edited, or that does not finish within its time limit
earns nothing; the other exercises are graded as usual. Speed earns and costs nothing within the limit.
"""


def _tally(result: CheckResult, reference: CheckResult | None = None) -> tuple[int, int, int]:
    """``(passed point checks, point checks to earn, failed gates)`` of ``result``.

    With ``reference`` (the grader), the point checks to earn are the reference's passing ones, and a check that the
    student's run did not pass *or did not record at all* counts as failed; without it (a check cell), ``result``'s own.
    """
    failed_gates = sum(1 for v in result.verdicts if v.kind == "gate" and not v.ok)
    if reference is None:
        pts = [v for v in result.verdicts if v.kind == "points"]
        return sum(v.ok for v in pts), len(pts), failed_gates
    want = Counter(v.text for v in reference.verdicts if v.ok and v.kind == "points")
    got = Counter(v.text for v in result.verdicts if v.ok and v.kind == "points")
    return sum((got & want).values()), sum(want.values()), failed_gates


def _fraction(result: CheckResult, reference: CheckResult | None = None) -> float:
    """The rule of :data:`SCORING_RULE` on :func:`_tally`'s counts: passed / (point checks + failed gates), capped
    at :data:`DEFINING_CAP` when a defining property fails."""
    passed, n_points, failed_gates = _tally(result, reference)
    counted = n_points + failed_gates
    frac = passed / counted if counted else 0.0
    return min(frac, DEFINING_CAP) if result.defining_failed else frac


def score_reasons(result: CheckResult, reference: CheckResult | None = None) -> list[str]:
    """Which parts of :data:`SCORING_RULE` cost ``result`` points, one line each (empty for a full score).

    With ``reference`` (the grader), point checks are counted as :func:`score_against` counts them: the
    reference's passing checks; without it (a check cell), as :func:`score` does.
    """
    passed, n_points, failed_gates = _tally(result, reference)
    counted = n_points + failed_gates
    out = []
    if n_points - passed:
        out.append(f"{n_points - passed} of {n_points} point checks fail (each costs an equal share)")
    if failed_gates:
        out.append(f"{failed_gates} shape/dtype gate(s) fail, each counted as a failed check (passing gates earn "
                   "nothing)")
    raw = passed / counted if counted else 0.0
    for name in result.defining_failed[:1]:
        out.append(f"the defining property '{name}' fails: capped at {DEFINING_CAP:.0%}"
                   + (f" (the other checks alone would give {raw:.0%})" if raw > DEFINING_CAP else ""))
    return out


def score(result: CheckResult) -> float:
    """The fraction (0..1) of an exercise's hidden-check points that ``result`` earns, by :data:`SCORING_RULE`.

    The grader's one rule (:mod:`course_lib.instructor.grade` calls it on the hidden checks' result, in its own
    process): passed point checks / (point checks + failed gates), capped at :data:`DEFINING_CAP` when a defining
    property fails. A result without verdicts (made by hand) scores ``passed / total``.
    """
    if not result.verdicts:
        return result.passed / result.total if result.total else 0.0
    return _fraction(result)


def score_against(result: CheckResult, reference: CheckResult) -> float:
    """The fraction (0..1) of the hidden-check points that ``result`` earns, measured on the reference's run.

    As :func:`score`, but what there is to earn is the reference's passing point checks on the same hidden cases: one
    that the student's run did not pass *or did not record at all* (the checks after an unusable answer never ran)
    counts as failed. Nothing to earn (the reference passed no point check) scores 0.
    """
    return _fraction(result, reference) if _tally(reference)[0] else 0.0


#: Results of the check cells run in this process, by exercise name (the grader reads it).
RESULTS: dict[str, CheckResult] = {}


def _functions_of(fn: Any) -> list | None:
    """The Python functions whose code is ``fn``'s: ``[fn]``, a class's methods, or None (no code to read)."""
    import types

    if isinstance(fn, type):
        return [v for v in vars(fn).values() if isinstance(v, types.FunctionType)]
    return [fn] if isinstance(fn, types.FunctionType) else None


def _code_objects(funcs: list):
    """Every code object of ``funcs``, nested ones (inner functions, comprehensions) included."""
    import types

    todo = [f.__code__ for f in funcs]
    while todo:
        code = todo.pop()
        yield code
        todo += [k for k in code.co_consts if isinstance(k, types.CodeType)]


def calls_name(fn: Any, name: str, depth: int = 3) -> bool | None:
    """Whether the code of ``fn`` (a function, or the methods of a class) names ``name``, directly or through the
    functions of its module that it names (``depth`` levels); None when ``fn`` has no code to read."""
    import types

    funcs = _functions_of(fn)
    if funcs is None:
        return None
    seen: set = set()
    for _ in range(depth + 1):
        names = {n for code in _code_objects(funcs) for n in code.co_names}
        if name in names:
            return True
        seen |= set(funcs)
        glob = funcs[0].__globals__ if funcs else {}
        funcs = [glob[n] for n in names if isinstance(glob.get(n), types.FunctionType) and glob[n] not in seen]
        if not funcs:
            return False
    return False


def code_text(fn: Any) -> str:
    """The source of ``fn`` (a function or class, in a module or a notebook cell); "" when it cannot be read."""
    import inspect

    try:
        return inspect.getsource(fn)
    except (OSError, TypeError):
        return ""


class Check:
    """Collects and prints the verdicts for one exercise.

    Use as a context manager; the verdicts are printed when the block ends, even when a check
    itself raised (that is reported as a failed check, never as a traceback)::

        with Check("estimate_fundamental_matrix") as c:
            F = c.call(student_fn, x1, x2, case="noiseless pair")
            if c.shape(F, (3, 3), "F"):
                c.expect(rank(F) == 2, "F has rank 2", "F has rank 3: enforce rank 2 with an SVD")
    """

    def __init__(self, exercise: str):
        self.exercise = exercise
        self.lines: list[str] = []
        self.notes: list[str] = []
        self.verdicts: list[Verdict] = []
        self.passed = 0
        self.total = 0
        self.case: str | None = None  # the case of the last call
        self.answered: dict[str, bool] = {}  # case called -> whether a verdict was recorded for it
        self.unanswered_call: str | None = None  # the case of a call after which no verdict was recorded yet

    # -- recording ---------------------------------------------------------------------------
    def expect(self, condition: bool, pass_msg: str, fail_msg: str, defining: str | None = None,
               kind: str = "points", named: str | None = None) -> bool:
        """Record one check; ``pass_msg`` must be deterministic, ``fail_msg`` should name the likely mistake.

        Args:
            condition: whether the check passed.
            pass_msg: the line printed when it passed (no floating-point numbers: nbval compares it).
            fail_msg: the line printed when it failed: the likely mistake, and what to change.
            defining: the defining property this check tests (declared with :func:`declare_defining`
                for this exercise); failing it caps the score at one half and leads the verdict.
            kind: ``"points"``, ``"gate"`` or ``"detail"`` (see :class:`Verdict`); :meth:`shape` and
                :meth:`gate` record gates, :meth:`detail` details.
            named: when ``fail_msg`` names a mistake (what the student did), its key (see :class:`Verdict`):
                only for the unique explanation of what the check saw.
        """
        if defining is not None and defining not in DEFINING.get(self.exercise, {}):
            raise ValueError(f"{defining!r} is not a declared defining property of {self.exercise!r} "
                             f"(declared: {sorted(DEFINING.get(self.exercise, {}))}); use declare_defining")
        if kind not in ("points", "gate", "detail"):
            raise ValueError(f"kind must be 'points', 'gate' or 'detail', got {kind!r}")
        self.total += 1
        ok = bool(condition)
        text = pass_msg if ok else fail_msg
        self.verdicts.append(Verdict(ok, text, kind, defining, None if ok else named))
        self.unanswered_call = None
        # a verdict answers the cases it names ("case A: ..." names case A, not "case A1"), and the case of the last
        # call when it names none or names that case's stem ("NeRF(): ..." after a call of case "NeRF() forward");
        # a check that records its verdicts after all its calls names each case
        named = [case for case in self.answered if f"{case}:" in text]
        if self.case in self.answered and (not named or any(self.case.startswith(n + " ") for n in named)):
            named.append(self.case)
        for case in named:
            self.answered[case] = True
        if ok:
            self.passed += 1
            self.lines.append(f"  {PASS} {pass_msg}")
            return True
        self.lines.append(f"  {FAIL} {fail_msg}")
        return False

    def fail(self, msg: str, defining: str | None = None, named: str | None = None) -> bool:
        """Record a failed check (of ``defining`` when it is a defining property's; ``named``: see :meth:`expect`)."""
        return self.expect(False, "", msg, defining=defining, named=named)

    def gate(self, condition: bool, pass_msg: str, fail_msg: str, defining: str | None = None,
             named: str | None = None) -> bool:
        """Record a precondition: no points when it passes, a failed check when not.

        For shape, dtype and type, and for properties that a trivial answer satisfies as well as a
        right one (rank 2, a rotation, unit norm, the same result for the same seed): passing them
        alone must earn nothing (``np.eye(3)`` or a constant is no solution), failing them costs.
        """
        return self.expect(condition, pass_msg, fail_msg, defining=defining, kind="gate", named=named)

    def detail(self, condition: bool, pass_msg: str, fail_msg: str) -> bool:
        """Record a detail: correct maths, but maybe not the documented form (an order, a layout).

        Failing it costs no hidden-check points, only the exercise's "perfect" share (one point of
        ten); the verdict should say so plainly, e.g. "correct maths, but not the order the
        docstring asks for".
        """
        return self.expect(condition, pass_msg, fail_msg, kind="detail")

    def note(self, text: str) -> None:
        """Print a line of advice under the verdict; it is no check and counts for nothing."""
        self.notes.append(text)

    def causes(self, fn: Any, candidates: list[tuple[str | tuple[str, ...], str]]) -> None:
        """After a failure that no verdict names: the common causes of this exercise that fit the student's code.

        Each candidate is ``(pattern, advice)``: a regular expression that the source of ``fn`` (:func:`code_text`)
        matches, ``"!pattern"`` for one it does not match, or a tuple of such (all must hold). Only the advice whose
        patterns hold is printed, under one note; nothing is printed when every check passed, when a failed verdict
        already names the mistake, or when the code cannot be read (a built-in, a callable object).
        """
        src = code_text(fn)
        if not src or self.passed == self.total or any(v.named for v in self.verdicts if not v.ok):
            return
        holds = lambda p: (re.search(p[1:], src) is None) if p.startswith("!") else bool(re.search(p, src))  # noqa: E731
        fits = [text for pats, text in candidates if all(map(holds, (pats,) if isinstance(pats, str) else pats))]
        if fits:
            self.note("common causes that fit your code: " + "; ".join(fits))

    def blame_earlier(self, *exercises: str, fn: Any = None) -> None:
        """After a failure: point at the earlier exercises the student's code calls whose checks have not passed.

        An exercise that calls a student's earlier function (``pnp_ransac`` calls ``pnp_linear``)
        fails when that one is wrong; the note says which to fix first. With ``fn`` (the student's
        function or class, defined in this kernel) only the ``exercises`` that its code calls (directly
        or through its module's other functions, :func:`calls_name`) are named, and an earlier check
        that failed *or has not run in this kernel* is named; without it (or when its code cannot be
        read), those whose check failed. The grader checks every exercise with the reference's
        earlier steps (:mod:`course_lib.instructor.oracle`), so there the mistake costs points once.
        """
        if self.passed == self.total:
            return
        calls = [calls_name(fn, e) for e in exercises] if fn is not None else [None] * len(exercises)
        failed = [e for e, k in zip(exercises, calls) if k is not False and e in RESULTS and not RESULTS[e].ok]
        not_run = [e for e, k in zip(exercises, calls) if k is True and e not in RESULTS]
        for bad, why in ((failed, "failed"), (not_run, "has not run in this kernel")):
            if bad:
                names = " and ".join(bad)
                self.note(f"{self.exercise} calls your {names}, whose check {why}: fix {names} first"
                          + (" (run its check cell)" if why != "failed" else ""))

    def call(self, fn: Callable, *args, case: str, **kwargs) -> Any:
        """Call the student's function; on an exception record a failure and return :data:`FAILED`.

        ``NotImplementedError`` is reported as "not implemented yet" rather than as a crash. A
        result that is nothing usable fails the call too (every exercise returns a result), so a
        missing answer is never a skipped case: ``None`` or a NaN number. A case whose result the
        check could not use at all (no verdict names it by the end of the check) counts as failed
        as well (see :meth:`account_for_cases`).
        Array arguments are copied so that a function that modifies its input cannot corrupt
        the next case.
        """
        args = tuple(a.copy() if isinstance(a, np.ndarray) else a for a in args)
        self.case = case
        self.answered.setdefault(case, False)
        try:
            out = fn(*args, **kwargs)
            unusable = _unusable(out)
            if unusable:
                self.fail(f"{case}: your function returned {unusable}: return the result (a missing return statement?)")
                return FAILED
            self.unanswered_call = case
            return out
        except NotImplementedError:
            self.fail(f"{case}: not implemented yet (the function raises NotImplementedError)")
        except Exception as exc:  # noqa: BLE001 - any student error becomes a verdict
            where = _student_frame(exc)
            self.fail(f"{case}: your function raised {type(exc).__name__}: {exc}{where}")
        return FAILED

    def call_explained(self, fn: Callable, *args, case: str, explain: Callable[[Exception], str | None] | None,
                       named: str | None = None, **kwargs) -> Any:
        """:meth:`call`, where an exception that ``explain`` has words for is a failed check in those words.

        ``explain(exc)`` returns what the exception means for this exercise (the verdict's text after the case,
        e.g. why least_squares refuses an (N, 2) residual), or None to report it as :meth:`call` does (as does an
        ``explain`` of None); ``named``:
        the mistake those words name (see :meth:`expect`). ``NotImplementedError`` is never explained.
        """
        said: list[str] = []

        def guarded(*a, **kw):
            try:
                return fn(*a, **kw)
            except NotImplementedError:
                raise
            except Exception as exc:  # noqa: BLE001 - unexplained ones are re-raised for call to report
                text = explain(exc) if explain is not None else None
                if text is None:
                    raise
                said.append(text)
                return said  # a usable stand-in: the verdict below answers the call

        out = self.call(guarded, *args, case=case, **kwargs)
        if said:
            self.fail(f"{case}: {said[0]}", named=named)
            return FAILED
        return out

    def fields(self, out: Any, case: str, names: tuple[str, ...], what: str, optional: int = 0) -> tuple | None:
        """The fields ``names`` of a returned result: its attributes of those names (a named tuple, a dataclass), or
        the first items of a tuple; the last ``optional`` may be missing (None). None for :data:`FAILED`, or after a
        failed check that says to return ``what`` (e.g. "a PnPResult(R_cw, t_cw, inliers, n_iters)")."""
        if out is FAILED:
            return None
        needed = len(names) - optional
        if all(hasattr(out, n) for n in names[:needed]):
            return tuple(getattr(out, n, None) for n in names)
        if isinstance(out, (tuple, list)) and len(out) >= needed:
            return tuple(out[:len(names)]) + (None,) * (len(names) - len(out))
        self.fail(f"{case}: return {what}, got {type(out).__name__}")
        return None

    def arrays(self, out: Any, case: str, shapes: dict[str, tuple], what: str) -> tuple | None:
        """The fields of a returned result (:meth:`fields`, named by ``shapes``' keys) as finite float arrays of
        those shapes (a shape ``(n,)`` takes any n values, e.g. a (3, 1) translation); None after a failed check."""
        out = self.fields(out, case, tuple(shapes), what)
        if out is None:
            return None
        arrs = [as_float(v) for v in out]
        if not all(a is not None and (a.shape == s or (len(s) == 1 and a.size == s[0]))
                   for a, s in zip(arrs, shapes.values())):
            got = ", ".join("no numeric array" if a is None else str(a.shape) for a in arrs)
            self.fail(f"{case}: {', '.join(shapes)} must have shapes {', '.join(map(str, shapes.values()))}, got {got}")
            return None
        if not all(np.isfinite(a).all() for a in arrs):
            self.fail(f"{case}: {' or '.join(shapes)} contains NaN or inf")
            return None
        return tuple(a.reshape(s) for a, s in zip(arrs, shapes.values()))

    def shape(self, value: Any, shape: tuple, what: str, hints: dict[tuple, str] | None = None) -> bool:
        """Check that ``value`` is an array of ``shape`` (``None`` entries match any size); ``hints``: what to change
        for a wrong shape that is a known mistake (``{(9,): "reshape the null vector to (3, 3)"}``)."""
        if value is FAILED:
            return False
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        arr = as_float(value)
        if arr is None:
            return self.gate(False, "", f"{what} is {_describe(value)}, expected a numeric array of shape {want}")
        ok = arr.ndim == len(shape) and all(s is None or s == a for s, a in zip(shape, arr.shape, strict=True))
        if not ok:
            hint = (hints or {}).get(tuple(arr.shape))
            return self.gate(False, "", f"{what} has shape {tuple(arr.shape)}" + (f": {hint}" if hint else
                                                                                  f", expected {want}"))
        if not np.isfinite(arr).all():
            return self.gate(False, "", f"{what} contains NaN or inf")
        return self.gate(True, f"{what} has shape {want}", "")

    # -- context manager -----------------------------------------------------------------------
    def __enter__(self) -> "Check":
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc is not None:
            self.fail(f"the check could not finish: {type(exc).__name__}: {exc}")
        self.report()
        return True  # the verdict is the output; never a traceback in a check cell

    def account_for_cases(self) -> None:
        """Fail every case that did not run or whose result no check could use (called by :meth:`report`).

        A case that was called but about which no verdict was recorded (its result was nothing the
        check could read), and a last call after which nothing was recorded, each count as one failed
        check, so that a missing answer never makes checks disappear from the count.
        """
        last = self.unanswered_call  # the last call's result led to no verdict at all
        unanswered = [case for case, answered in self.answered.items() if not answered]
        for case in unanswered:
            self.fail(f"{case}: the result could not be checked (nothing usable was returned); it counts as failed")
        if last is not None and last not in unanswered:
            self.fail(f"{last}: the result of the last call could not be checked (nothing usable was returned); "
                      "it counts as failed")

    def report(self) -> CheckResult:
        """Print the verdict and store the :class:`CheckResult` in :data:`RESULTS`.

        Cases that did not run, or whose result could not be used, are failed first
        (:meth:`account_for_cases`). A failed defining property leads: a first line names it (and
        that it caps the points at one half), followed by the failed checks that test it; then the
        other lines in order.
        """
        self.account_for_cases()
        result = CheckResult(self.exercise, self.passed, self.total, [], list(self.verdicts))
        broken = result.defining_failed
        lead = [i for i, v in enumerate(self.verdicts) if v.defining in broken and not v.ok]
        what = DEFINING.get(self.exercise, {})
        printed = [f"  {FAIL} the defining property fails: {name} ({what.get(name, '')}); "
                   "this costs at least half of the points" for name in broken]
        printed += [self.lines[i] for i in lead]
        printed += [line for i, line in enumerate(self.lines) if i not in lead]
        printed += [f"  note: {text}" for text in self.notes]
        result.lines = printed  # as printed, so that the grader's feedback leads with the property too
        RESULTS[self.exercise] = result
        print(self.exercise)
        for line in printed:
            print(line)
        if result.ok:
            print(f"  all {self.total} checks passed")
        else:
            print(f"  {self.passed} of {self.total} checks passed")
            reasons = score_reasons(result)
            if reasons:
                print(f"  scoring: {score(result):.0%} of the hidden-check points on these cases: " + "; ".join(reasons))
        return result


# ---------------------------------------------------------------------------------------------
# One rule for equivalences and tolerances
# ---------------------------------------------------------------------------------------------

#: float32's machine epsilon (1.2e-7): every tolerance of the checks is a multiple of it, relative to the answer's scale.
EPS32 = float(np.finfo(np.float32).eps)
#: Relative tolerance of a computed result (a few hundred float32 roundings through an SVD or a sum of
#: hundreds of terms): a correct answer computed in float32 passes, every named mistake is far beyond it.
RTOL = 1000 * EPS32


def close_rel(a: Any, b: Any, rtol: float = RTOL) -> bool:
    """``a`` equals ``b`` within ``rtol`` of ``b``'s scale (its largest magnitude, 1 when that is 0), same shape,
    all finite.

    The checks' one rule for "equal": relative to the answer's scale, so that a correct answer in
    float32 (or of large coordinates) passes.
    """
    try:
        a, b = np.asarray(a, float), np.asarray(b, float)
    except (TypeError, ValueError):
        return False
    if a.shape != b.shape or not np.isfinite(a).all():
        return False
    scale = float(np.abs(b).max(initial=0.0)) if np.isfinite(b).all() else 0.0
    return bool(np.abs(a - b).max(initial=0.0) <= rtol * (scale or 1.0))


def scale_free_gap(a: Any, b: Any) -> float:
    """The largest entry of ``a - b`` with both at unit norm, for the closer sign (inf: not comparable, or zero)."""
    try:
        a, b = np.asarray(a, float), np.asarray(b, float)
    except (TypeError, ValueError):
        return float("inf")
    if a.shape != b.shape or not (np.isfinite(a).all() and np.isfinite(b).all()):
        return float("inf")
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0 or nb == 0:
        return float("inf")
    a, b = a / na, b / nb
    return float(min(np.abs(a - b).max(), np.abs(a + b).max()))


def same_up_to_scale(a: Any, b: Any, rtol: float = RTOL) -> bool:
    """``a = λ b`` for some λ ≠ 0 of either sign (:func:`scale_free_gap` within ``rtol``).

    The checks' one rule for what is defined up to scale and sign (F, E, a null vector): F / F[2, 2],
    -F and F in float32 are the same F.
    """
    return scale_free_gap(a, b) <= rtol


def unique_key(per_case: list) -> str | None:
    """The one mistake that explains every case, else None (the rule for naming a mistake).

    ``per_case`` holds one entry for each case where the student's result failed: the set of mistakes whose
    result the student's equals there, or a pair ``(explained, testable)``: the mistakes it equals and the
    mistakes that can be told apart on that case at all (a case where a mistake cannot be tested neither
    supports nor vetoes it). A mistake is named when it explains every failing case where it can be tested,
    at least one, and no other mistake does.
    """
    if not per_case:
        return None
    pairs = [e if isinstance(e, tuple) else (set(e), None) for e in per_case]
    keys = set().union(*(exp for exp, _ in pairs))
    fits = [k for k in keys if all(k in exp for exp, testable in pairs if testable is None or k in testable)]
    return fits[0] if len(fits) == 1 else None


@dataclass
class Outcome:
    """One case of a check, read: what :func:`report_cases` needs to print its verdict.

    Attributes:
        case: the case's name (each line starts with it).
        ok: whether the result is right.
        passed: the passing line's text, after the case.
        failed: the failing line's facts (with numbers), after the case.
        keys: the mistakes whose result this one is on the case, as :func:`unique_key` takes them (a set, or
            ``(explained, testable)``); only read when the case fails.
        advice: what to change, printed after the facts when no mistake is named.
        data: whatever else the check's own verdicts of the case need.
        defining: the defining property the verdict tests (see :meth:`Check.expect`), or None.
    """

    case: str
    ok: bool
    passed: str
    failed: str = ""
    keys: Any = ()
    advice: str = ""
    data: Any = None
    defining: str | None = None


def report_cases(c: "Check", outcomes: list[Outcome], mistakes: dict[str, str],
                 first: Callable[[Outcome, str | None], None] | None = None,
                 then: Callable[[Outcome, str | None], None] | None = None) -> str | None:
    """The checks' one way from cases to verdicts: name the mistake, then print each case's verdict.

    The mistake named is the one that explains every failing case (:func:`unique_key`); each case then passes,
    or fails with its facts followed by that mistake's sentence (``mistakes[key]``, when the key is one of them)
    or else by its advice. ``first`` and ``then`` record the case's further verdicts, before and after its own
    (they are given the named key too). Returns the named key (None: none).
    """
    named = unique_key([o.keys for o in outcomes if not o.ok])
    own = named if named in mistakes else None
    for o in outcomes:
        if first is not None:
            first(o, named)
        if o.ok:
            c.expect(True, f"{o.case}: {o.passed}", "", defining=o.defining)
        else:
            c.fail(f"{o.case}: " + ": ".join(t for t in (o.failed, mistakes[own] if own else o.advice) if t),
                   defining=o.defining, named=own)
        if then is not None:
            then(o, named)
    return named


def refinement_verdicts(c: "Check", case: str, e0: float, e_s: float, ok: bool, facts: str, why: str | None,
                        advice: tuple[str, str], named: str | None) -> None:
    """The verdicts of a non-linear refinement whose RMS reprojection error goes from ``e0`` to ``e_s`` px: it lowers
    the error (a gate: returning the start satisfies it), then it reaches the least-squares optimum (``ok``; ``facts``:
    the numbers of a failure). ``why``: the named mistake's sentence, else ``advice`` (for each verdict) follows."""
    if c.gate(e_s <= e0 * (1 + 1e-9) + 1e-9, f"{case}: lowers the reprojection error",
              f"{case}: the refinement increased the RMS reprojection error ({e0:.3g} -> {e_s:.3g} px): "
              + (why or advice[0]), named=named):
        c.expect(ok, f"{case}: reaches the least-squares optimum", f"{case}: {facts}: " + (why or advice[1]),
                 named=named)


def as_float(value: Any) -> np.ndarray | None:
    """``value`` as a float64 numpy array (torch tensors included); None for :data:`FAILED`, None or what is none."""
    if value is FAILED or value is None:
        return None
    try:
        if hasattr(value, "detach"):
            value = value.detach().cpu().double().numpy()
        return np.asarray(value, dtype=float)
    except (TypeError, ValueError, RuntimeError):
        return None


def _describe(value: Any) -> str:
    """A short description of a returned value for a verdict ("a str", "a tuple of 2 items", "None")."""
    if value is None:
        return "None"
    if isinstance(value, (tuple, list)):
        return f"a {type(value).__name__} of {len(value)} items"
    arr = as_float(value)
    if arr is not None:
        return f"an array of shape {tuple(arr.shape)}"
    return f"a {type(value).__name__}"


def _unusable(out: Any) -> str | None:
    """What makes a returned value nothing usable ("None", "NaN"), or None.

    Results of the wrong type or shape are the check's to name (it knows what was asked for, e.g.
    "return a dict"); a check that cannot use a result at all fails its case in :meth:`Check.report`.
    """
    if out is None:
        return "None"
    if isinstance(out, (float, np.floating)) and np.isnan(out):
        return "NaN"
    return None


def _student_frame(exc: BaseException) -> str:
    """' (line N of your cell)' for the innermost frame that is not the kit's own code."""
    frames = traceback.extract_tb(exc.__traceback__)
    for fr in reversed(frames):
        if "course_lib" not in fr.filename and "site-packages" not in fr.filename:
            if fr.filename.startswith("<") or "ipykernel" in fr.filename or "/tmp/" in fr.filename:
                return f" (line {fr.lineno} of your cell)"
            return f" ({Path(fr.filename).name}, line {fr.lineno})"
    return ""

"""The RANSAC check shared by notebooks 01 (F from matches) and 04 (PnP): the mask, the count, the samples, the rng.

A RANSAC exercise is described once, by a :class:`Ransac` (its sample size, what it returns, the error that decides
an inlier); the verdicts that every RANSAC earns the same way are here, with one scoring: the mask follows the
*returned* model (:func:`mask_outcome`; another rule is named when one explains every case), the count adapts and
follows the confidence, N = log(1 - confidence) / log(1 - wᵏ), the rng argument is the only randomness
(:func:`sampling_verdicts`), and exactly k noiseless items are fitted exactly, with a sample that held an item twice
named from the recorded draws (:func:`minimal_verdicts`, :class:`RecordingRng`). The exercise's own properties (F
against the true geometry, the pose despite the outliers, the refit) stay in its check module.

A RANSAC's result depends on its draws: a call that fails (it raises, or fails the case's own verdicts) is judged by
the majority of three seeds (:func:`call`), so a right loop is not failed for one unlucky draw and a wrong one, which
fails on every seed, still is.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from course_lib.checks.core import FAILED, Check, Outcome, as_float

__all__ = ["Ransac", "Run", "RecordingRng", "read", "probe", "mask_outcome", "sampling_verdicts", "minimal_verdicts",
           "samples_needed", "threshold_interval", "within"]

#: The confidence the exercises default to, and the two the confidence verdict compares.
CONFIDENCE, LOW, HIGH = 0.999, 0.01, 0.99999
#: The randomness case: the rng seed and max_iters of its calls (a few samples, so that the result depends on them).
RNG_SEED, RNG_MAX_ITERS = 1, 3
#: The samples of the randomness case's calls where one with ``RNG_MAX_ITERS`` raised (every sample contaminated).
RNG_RETRY_ITERS = 30


@dataclass(frozen=True)
class Ransac:
    """One RANSAC exercise, as the shared verdicts see it.

    Attributes:
        k: the sample size (8 matches for F, 6 points for the DLT).
        item: the items, singular and plural (``("match", "matches")``).
        fields: the names of the returned fields, the model's first, then ``inliers`` and ``n_iters``.
        returns: what to return, for a verdict (``"a RansacResult(F, inliers, n_iters)"``).
        model: ``(c, case, model fields) -> model or None`` (after a failed check).
        error: ``(model, args) -> (N,)`` the error in pixels that decides an inlier (inf where there is none).
        error_name: that error, in words (``"Sampson distance"``).
        model_name: the model, in words (``"F"``, ``"pose"``).
        threshold: the default ``threshold_px``; max_iters: the default ``max_iters``.
        rules: the exercise's own rules a mask may follow (``{key: what the student did}``); see :func:`mask_outcome`.
    """

    k: int
    item: tuple[str, str]
    fields: tuple[str, ...]
    returns: str
    model: Callable
    error: Callable
    error_name: str
    model_name: str
    threshold: float
    max_iters: int
    rules: dict[str, str] = field(default_factory=dict)

    @property
    def mistakes(self) -> dict[str, str]:
        """Every rule a mask may follow, as what the student did (the shared ones and :attr:`rules`)."""
        e, items = self.error_name, self.item[1]
        return {"squared": f"you compared the SQUARED {e} with threshold_px: compare the {e} itself, in pixels",
                "threshold_squared": f"you compared the {e} with threshold_px² (not threshold_px): compare it with "
                                     "threshold_px itself",
                "constant": f"you compared with {self.threshold:g} px whatever threshold_px was passed: use the "
                            "threshold_px argument",
                "inverted": f"your inlier mask is inverted: inliers are the {items} with {e} BELOW the threshold",
                **self.rules}


@dataclass
class Run:
    """One call of the student's RANSAC, read: its case, arguments, model, mask, count and the model's errors."""

    case: str
    args: tuple
    model: Any
    inl: np.ndarray
    n_iters: int | None
    thr: float
    e: np.ndarray
    seed: int = 0  # the rng seed of the call that is judged (the probes of the same case draw the same samples)


def read(c: Check, spec: Ransac, out: Any, case: str, n: int) -> tuple | None:
    """``(model, inliers (n,) bool, n_iters or None)`` of a returned result, or None after a failed check."""
    fields = c.fields(out, case, spec.fields, spec.returns, optional=1)
    if fields is None:
        return None
    *parts, inl, n_iters = fields
    model = spec.model(c, case, parts)
    if model is None:
        return None
    inl = as_float(inl)
    if inl is None or inl.shape != (n,) or not np.isin(inl, (0, 1)).all():
        c.fail(f"{case}: inliers must be a bool array of shape ({n},), got "
               f"{'no array' if inl is None else inl.shape} (a mask over ALL {spec.item[1]}, not the inlier indices)")
        return None
    try:
        n_iters = None if n_iters is None else int(n_iters)
    except (TypeError, ValueError):
        n_iters = None
    return model, inl.astype(bool), n_iters


def call(c: Check, spec: Ransac, fn: Callable, args: tuple, case: str, seed: int = 0, rng=None,
         judge: Callable[[Check, Run], Any] | None = None, **kw) -> Run | None:
    """Call the student's RANSAC on ``args`` with ``rng`` (default: a Generator seeded with ``seed``); None after a
    failed check. Without ``rng``, a call that fails (it raises, returns nothing usable, or fails a verdict of
    ``judge(check, run)``: the case's own verdicts, recorded by the caller after the call) is judged by the majority
    of three seeds (:func:`_majority`)."""
    if rng is not None:
        return _run(c, spec, c.call(fn, *args, rng, case=case, **kw), args, case, kw)
    return _majority(c, spec, fn, args, case, seed, judge, kw)


#: Where a call failed, the seeds it is made again with (its own seed plus each).
RETRY_SEEDS = (1000, 2000)


@dataclass
class _Attempt:
    """One call with one seed, recorded on a scratch check: the run, why it failed ("" when it passed), whether it
    raised, and whether that may be the draws' luck (it raised, or the result failed a verdict of the case; not a
    result of the wrong form, which no draw explains)."""

    seed: int
    check: Check
    run: Run | None
    why: str
    raised: bool

    @property
    def luck(self) -> bool:
        return self.raised or (self.run is not None and bool(self.why))


def _attempt(c: Check, spec: Ransac, fn: Callable, args: tuple, case: str, seed: int, judge, kw: dict) -> _Attempt:
    raised = []

    def watched(*a, **k):
        try:
            return fn(*a, **k)
        except NotImplementedError:
            raise
        except Exception:
            raised.append(True)
            raise

    scratch = Check(c.exercise)
    run = _run(scratch, spec, scratch.call(watched, *args, np.random.default_rng(seed), case=case, **kw), args, case,
               kw, seed)
    judged = Check(c.exercise)
    if run is not None and judge is not None:
        judge(judged, run)
    why = next((v.text for v in scratch.verdicts + judged.verdicts if not v.ok), "")
    return _Attempt(seed, scratch, run, why, bool(raised))


def _majority(c: Check, spec: Ransac, fn: Callable, args: tuple, case: str, seed: int, judge, kw: dict) -> Run | None:
    """The call with ``seed``, and where it fails by bad luck, with the seeds :data:`RETRY_SEEDS` too: a RANSAC's
    result depends on its draws, and a right loop fails on an unlucky one now and then (a first sample whose model
    has one inlier among hundreds: 1 - wᵏ rounds to 1, N = log(1 - p) / log(1 - wᵏ) divides by zero or is -inf, the
    loop ends and the refit raises; or a plain loop settles on a poor consensus). Bad luck: the call raised or its
    result failed a verdict of ``judge``; a result of the wrong form is no draw's luck and is judged at once. When
    both other seeds pass, the first of them is judged (a note says so); else the call with ``seed`` is. What the
    judged call recorded (its failure, when it failed) is recorded on ``c``; the caller records the case's verdicts
    on the run returned."""
    tries = [_attempt(c, spec, fn, args, case, seed, judge, kw)]
    for d in RETRY_SEEDS if tries[0].luck else ():
        tries.append(_attempt(c, spec, fn, args, case, seed + d, judge, kw))
        if tries[-1].why:
            break  # two of three failed
    chosen = tries[1] if len(tries) == 3 and not tries[2].why else tries[0]
    c.case = case
    c.answered.setdefault(case, False)
    for v in chosen.check.verdicts:
        c.expect(v.ok, v.text, v.text, defining=v.defining, kind=v.kind, named=v.named)
    c.unanswered_call = chosen.check.unanswered_call
    if chosen is not tries[0]:
        k = spec.k
        c.note(f"{case}: with the rng seeded {seed} your function failed ({tries[0].why[:160]}), with the seeds "
               f"{tries[1].seed} and {tries[2].seed} it passed, and the first of those is judged: a RANSAC depends on "
               "its draws, so a case is judged by the majority of three seeds"
               + (f". If a first sample with almost no inliers ended your loop: 1 - w**{k} rounds to 1 for a tiny w, "
                  f"so log(1 - w**{k}) is 0; np.log1p(-w**{k}) keeps N finite" if tries[0].raised else ""))
    return chosen.run


def _run(c: Check, spec: Ransac, out: Any, args: tuple, case: str, kw: dict, seed: int = 0) -> Run | None:
    """The :class:`Run` of a call's result ``out`` (made with the keyword arguments ``kw`` and the rng seed ``seed``);
    None after a failed check."""
    got = read(c, spec, out, case, len(args[0]))
    if got is None:
        return None
    return Run(case, args, *got, kw.get("threshold_px", spec.threshold), spec.error(got[0], args), seed)


def probe(c: Check, spec: Ransac, fn: Callable, args: tuple, case: str, seed: int = 0, rng=None, **kw) -> Run | None:
    """As :func:`call`, for the probes of the loop's control (a low confidence, ``max_iters`` of a few): their few
    samples may all be contaminated or degenerate and leave fewer than ``k`` inliers to refit on, where a right
    function (or the grader's reference standing in for an earlier step) may raise; an exception there is no verdict
    (the calls with the default arguments are judged). None where it raised or after a failed check."""
    rng = np.random.default_rng(seed) if rng is None else rng
    try:
        out = fn(*(a.copy() if isinstance(a, np.ndarray) else a for a in args), rng, **kw)
    except Exception:  # noqa: BLE001 - see the docstring
        return None
    return _run(c, spec, out, args, case, kw)


def threshold_interval(values: np.ndarray, inl: np.ndarray) -> tuple[float, float] | None:
    """``(lo, hi)``: the inlier mask ``inl`` is ``values < τ`` for every τ in (lo, hi]; None when no threshold gives it
    (how a check reads which threshold, or which rule, a RANSAC's mask follows)."""
    lo = float(values[inl].max()) if inl.any() else -np.inf
    hi = float(values[~inl].min()) if (~inl).any() else np.inf
    return (lo, hi) if lo < hi else None


def within(interval: tuple[float, float] | None, tau: float) -> bool:
    """Whether the threshold ``tau`` lies in ``interval`` (:func:`threshold_interval`; ends within float rounding)."""
    return interval is not None and interval[0] < tau * (1 + 1e-9) and tau <= interval[1] * (1 + 1e-9)


def mask_outcome(spec: Ransac, run: Run, keys: set[str] = frozenset()) -> Outcome:
    """The mask of one call: the items whose error under the returned model is below threshold_px (a tie may go either
    way), and the rules it follows when it is not (the shared ones, and ``keys``: the exercise's own that it saw)."""
    e, inl, thr = run.e, run.inl, run.thr
    finite = np.isfinite(e)
    interval = threshold_interval(e[finite], inl[finite])
    wrong = int(((inl != (e < thr)) & ~(np.abs(e - thr) <= 1e-6 * thr)).sum())
    keys = set(keys)
    for key, tau in (("threshold_squared", thr**2), ("squared", np.sqrt(thr)), ("constant", spec.threshold)):
        if within(interval, tau) and not within(interval, thr):
            keys.add(key)
    if (inl == (e >= thr)).mean() > 0.9:
        keys.add("inverted")
    where = (f"no threshold on the {spec.error_name} gives your mask" if interval is None else
             f"your mask is the {spec.item[1]} with {spec.error_name} below some τ between {interval[0]:.3g} and "
             f"{interval[1]:.3g} px")
    return Outcome(run.case, wrong == 0, f"the inliers are the {spec.item[1]} within threshold_px of the returned "
                   f"{spec.model_name}", f"{wrong} {spec.item[1]} are labelled against the {spec.error_name}s of the "
                   f"returned {spec.model_name}", keys, f"{where}, threshold_px = {thr:g}: after the refit, recompute "
                   f"the inliers with the final {spec.model_name} ({spec.error_name} < threshold_px)")


def samples_needed(w: float, k: int, confidence: float, max_iters: int) -> float:
    """Adaptive RANSAC's count N = log(1 - confidence) / log(1 - wᵏ) for inlier ratio ``w`` and samples of ``k``, at
    most ``max_iters`` (1 when every item is an inlier)."""
    if w >= 1.0:
        return 1.0
    if w <= 0.0:
        return float(max_iters)
    return float(min(max_iters, np.log(1.0 - confidence) / np.log(1.0 - w**k)))


def _same(a: Run, b: Run) -> bool:
    """Whether two calls returned the same model, mask and count."""
    ma, mb = (np.concatenate([np.ravel(m) for m in (r.model if isinstance(r.model, tuple) else (r.model,))])
              for r in (a, b))
    return ma.shape == mb.shape and np.allclose(ma, mb, atol=1e-12) and np.array_equal(a.inl, b.inl) and \
        a.n_iters == b.n_iters


def _distinct(k: int, items: str) -> str:
    return (f"rng.choice(N, {k}) draws with replacement unless you pass replace=False; draw {k} distinct {items}, "
            f"rng.choice(N, {k}, replace=False)")


def sampling_verdicts(c: Check, spec: Ransac, fn: Callable, run: Run, rng_case: tuple[tuple, str] | None = None) -> None:
    """The count and the confidence on the case of ``run`` (a call with the default arguments), and the randomness on
    ``rng_case`` (``(args, name)``: a case where every sample of a few finds inliers; default ``run``'s)."""
    k, case = spec.k, run.case
    w = float(run.inl.mean())
    if run.n_iters is None:
        c.fail(f"{case}: n_iters is missing: return the number of samples drawn")
    else:
        need = samples_needed(w, k, CONFIDENCE, spec.max_iters)
        c.expect(1 <= run.n_iters < spec.max_iters and run.n_iters >= 0.25 * need - 1,
                 f"{case}: n_iters adapts to the inlier ratio",
                 f"{case}: n_iters = {run.n_iters}, while your inlier ratio {w:.0%} at confidence {CONFIDENCE} needs "
                 f"about {need:.0f} samples: N = log(1 - confidence) / log(1 - w^{k}), updated with the best inlier "
                 "ratio so far, at most max_iters, and the loop stops once it has drawn N samples")
    lo, hi = (probe(c, spec, fn, run.args, case, run.seed, confidence=p, threshold_px=run.thr) for p in (LOW, HIGH))
    if hi is not None and hi.n_iters is not None and (lo is None or lo.n_iters is not None):
        # lo None: the call at the low confidence raised where the same call at the high one ran, so it drew fewer
        # samples (none of them clean enough to refit on): the count followed the confidence
        need = samples_needed(float(hi.inl.mean()), k, HIGH, spec.max_iters)
        fewer = lo is None or lo.n_iters < hi.n_iters or hi.n_iters <= 1
        c.expect(fewer and hi.n_iters >= 0.7 * need, f"{case}: more samples for a higher confidence",
                 f"{case}: n_iters = {'none (it raised)' if lo is None else lo.n_iters} at confidence {LOW} and "
                 f"{hi.n_iters} at {HIGH} ({hi.inl.mean():.0%} "
                 f"inliers need about {need:.0f} samples at {HIGH}): the number of samples must follow the confidence "
                 f"argument, N = log(1 - confidence) / log(1 - w^{k})")
    args, name = rng_case or (run.args, case)
    _rng_verdicts(c, spec, fn, args, name)


def _under_global_seed(seed: int, call_: Callable[[], Any]) -> tuple[Any, bool]:
    """``call_()`` with numpy's global random state seeded with ``seed`` (restored after): ``(its result, whether it
    changed that state)``."""
    saved = np.random.get_state()
    try:
        np.random.seed(seed)
        before = np.random.get_state()[1].copy()
        out = call_()
        return out, not np.array_equal(np.random.get_state()[1], before)
    finally:
        np.random.set_state(saved)


def _rng_verdicts(c: Check, spec: Ransac, fn: Callable, args: tuple, name: str) -> None:
    """Gates (a constant answer satisfies them as well as a right one), with a few samples per call: the same rng seed
    under two global np.random states gives the same result, max_iters bounds the count, the rng argument is drawn
    from (its state advances), and numpy's global state is left as it was. Where a call with ``RNG_MAX_ITERS``
    samples raised (all of them contaminated), the three calls are made again with ``RNG_RETRY_ITERS``."""
    for m in (RNG_MAX_ITERS, RNG_RETRY_ITERS):
        case, runs, touched = f"{name}, max_iters={m}", [], False
        for global_seed in (11, 22):
            run, moved = _under_global_seed(global_seed, lambda: probe(c, spec, fn, args, case, RNG_SEED, max_iters=m))
            touched = touched or moved
            runs.append(run)
        rng = np.random.default_rng(RNG_SEED + 1)
        before = rng.bit_generator.state
        if None not in runs and probe(c, spec, fn, args, case, rng=rng, max_iters=m) is not None:
            break
    else:
        return
    its = [r.n_iters for r in runs]
    c.gate(all(i is not None and 1 <= i <= m for i in its), f"{case}: draws max_iters samples at most",
           f"{case}: n_iters = {its[0]} with max_iters={m}: stop after at most max_iters samples and "
           "return their count")
    c.gate(_same(*runs), f"{case}: the same rng seed gives the same result",
           f"{case}: the same rng seed gave different results when np.random's global state changed: draw every "
           f"sample from the rng argument (rng.choice(N, {spec.k}, replace=False)), not from np.random or a generator "
           "of your own")
    c.gate(not touched, f"{case}: numpy's global random state is left untouched",
           f"{case}: the call changed numpy's global random state (np.random.seed or a draw from np.random): draw "
           "from the rng argument only")
    c.gate(rng.bit_generator.state != before, f"{case}: the samples are drawn from the rng argument",
           f"{case}: the rng argument is untouched after the call (no number was drawn from it): draw every sample "
           f"from it (rng.choice(N, {spec.k}, replace=False)), not from a generator of your own or np.random")


class RecordingRng(np.random.Generator):
    """A numpy Generator (seeded like ``np.random.default_rng(seed)``) that records the index draws made with it.

    :func:`minimal_verdicts` hands it to a RANSAC as its ``rng`` argument, to tell whether a sample of ``k`` indices
    held one index twice (``rng.choice(N, k)`` draws with replacement unless ``replace=False``). Draws of ``choice``,
    ``integers`` and ``permutation`` are recorded; the numbers are those of a plain Generator.
    """

    def __init__(self, seed: int):
        super().__init__(np.random.PCG64(seed))
        self.draws: list[np.ndarray] = []
        self._depth = 0  # choice calls integers and permutation itself: only the outermost call is the student's draw

    def _draw(self, method, *args, **kwargs):
        self._depth += 1
        try:
            out = method(*args, **kwargs)
        finally:
            self._depth -= 1
        arr = np.asarray(out)
        if self._depth == 0 and arr.ndim >= 1 and arr.dtype.kind in "iu":
            self.draws.append(arr.copy())
        return out

    def choice(self, *args, **kwargs):
        return self._draw(super().choice, *args, **kwargs)

    def integers(self, *args, **kwargs):
        return self._draw(super().integers, *args, **kwargs)

    def permutation(self, *args, **kwargs):
        return self._draw(super().permutation, *args, **kwargs)

    def repeated(self, k: int) -> np.ndarray | None:
        """The first recorded draw of exactly ``k`` indices (a row of a batch counts) that holds an index twice."""
        rows = (row for d in self.draws if d.shape[-1] == k for row in d.reshape(-1, k))
        return next((row for row in rows if len(np.unique(row)) < k), None)

    def counted_repeats(self, k: int, n_iters: Any) -> int:
        """How many samples that held an index twice were drawn, skipped and counted in ``n_iters`` before the one
        sample of ``k`` distinct indices that ends the loop on ``k`` noiseless items; 0 when that is not what ran."""
        distinct = [len(np.unique(d)) == k for d in self.draws if d.shape == (k,)]
        if len(distinct) < 2 or not distinct[-1] or any(distinct[:-1]) or n_iters != len(distinct):
            return 0
        return len(distinct) - 1


def minimal_verdicts(c: Check, spec: Ransac, fn: Callable, args: tuple, case: str, seed: int, **kw) -> None:
    """Exactly ``k`` noiseless items in ``args``: the only sample of ``k`` distinct items is all of them, so the model
    fits every item (error below 0.05 px) and all are inliers. A sample that holds an item twice (``k - 1`` items
    leave the model undetermined) is named: drawn and counted before the one good sample, or seen in a failed run
    (``seed``: the recording rng's)."""
    k, (one, many) = spec.k, spec.item
    rng = RecordingRng(seed)

    def explain(exc: Exception) -> str | None:
        twice = rng.repeated(k)
        return None if twice is None else (
            f"your function raised {type(exc).__name__}: {str(exc)[:100]}, after a sample that held a {one} twice "
            f"(indices {twice.tolist()}): {_distinct(k, many)}")

    out = c.call_explained(fn, *args, rng, case=case, explain=explain, named="with_replacement", **kw)
    got = None if out is FAILED else read(c, spec, out, case, k)
    if got is None:
        return
    model, inl, n_iters = got
    e = spec.error(model, args)
    ok = bool(inl.all()) and float(e.max()) < 0.05
    skipped, twice = rng.counted_repeats(k, n_iters), None if ok else rng.repeated(k)
    if ok and skipped:
        c.fail(f"{case}: n_iters = {n_iters}, where the first sample of {k} distinct {many} has every {one} as inlier "
               f"(N = 1): the {skipped} samples before it each held a {one} twice (a degenerate sample, counted in "
               f"n_iters): {_distinct(k, many)}", named="with_replacement")
    elif twice is not None:
        c.fail(f"{case}: a sample held a {one} twice (indices {twice.tolist()}): {_distinct(k, many)}",
               named="with_replacement")
    else:
        c.expect(ok, f"{case}: the {spec.model_name} fits all {k} {many} exactly",
                 f"{case}: {int(inl.sum())} of {k} inliers, largest {spec.error_name} {float(e.max()):.3g} px; the "
                 f"only sample of {k} distinct {many} is all of them, so the {spec.model_name} must fit every {one} "
                 f"exactly (each sample is {k} distinct {many}, rng.choice(N, {k}, replace=False); the refit uses "
                 "every inlier)")

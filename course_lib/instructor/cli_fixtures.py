"""``python -m course_lib fixtures [--check] [NAME ...]``: rebuild the check cells' stored cases.

The fixtures in ``data/fixtures/<name>.npz`` are made from the reference solutions by the case
builders of :mod:`course_lib.instructor.cases`; the test suite rebuilds them and compares, to
prove that they are current. They ship with the student kit: the check cells and the step inputs
(:mod:`course_lib.starting_points`) read them, so the student kit runs and checks without the reference.
"""

from __future__ import annotations

import argparse

import numpy as np

from course_lib.fixtures import load_fixture
from course_lib.instructor.cases import builders
from course_lib.paths import FIXTURES_DIR

__all__ = ["build_fixtures", "same_arrays"]


def build_fixtures(names: list[str] | None = None, write: bool = True) -> dict[str, list[str]]:
    """Rebuild fixtures from the reference solutions.

    Args:
        names: fixtures to build (default all registered).
        write: write ``data/fixtures/<name>.npz``; with False only compare with the stored files.

    Returns:
        ``{name: [keys that differ from the stored file]}``; an empty list means up to date.
    """
    found = builders()
    todo = list(found) if names is None else names  # registration order: later fixtures may read earlier ones
    unknown = [n for n in todo if n not in found]
    if unknown:
        raise KeyError(f"unknown fixture(s) {unknown}; known: {sorted(found)}")
    diffs: dict[str, list[str]] = {}
    for name in todo:
        new = found[name]()
        old = load_fixture(name) if (FIXTURES_DIR / f"{name}.npz").exists() else {}
        changed = [k for k in sorted(set(new) | set(old)) if not same_arrays(new.get(k), old.get(k), mistake="_mis_" in k)]
        diffs[name] = changed
        if write and changed:
            FIXTURES_DIR.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(FIXTURES_DIR / f"{name}.npz", **{k: np.asarray(v) for k, v in new.items()})
    return diffs


def same_arrays(a, b, mistake: bool = False) -> bool:
    """True if two stored values agree: same shape and kind, floats to rounding (see the comments).

    Args:
        a, b: the values (None: missing, never the same).
        mistake: the value is what a classic mistake computes (a ``*_mis_*`` key): the checks only
            recognise it within a tolerance of a few percent, and it is often the end of a solver that
            stops where rounding decides, so it agrees to 1e-3 of its scale.
    """
    if a is None or b is None:
        return False
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape or a.dtype.kind != b.dtype.kind:
        return False
    if a.dtype.kind in "fc":
        # to rounding, relative to the array's scale: float32 results (torch's CPU kernels) differ in
        # the last bits between CPUs (AVX2 vs AVX-512 code paths), float64 results (LAPACK, solvers
        # that stop at a tolerance) far less
        single = np.float32 in (a.dtype, b.dtype) or np.complex64 in (a.dtype, b.dtype)
        rtol = 1e-3 if mistake else (1e-4 if single else 1e-6)
        finite = np.abs(b[np.isfinite(b)])
        scale = float(finite.max()) if finite.size else 0.0
        return bool(np.allclose(a, b, rtol=rtol, atol=max(1e-8, rtol * scale), equal_nan=True))
    return bool(np.array_equal(a, b))


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("names", nargs="*", help="fixtures to rebuild (default: all)")
    p.add_argument("--check", action="store_true", help="only compare with the stored files; exit 1 if any is stale")


def run(args) -> int:
    diffs = build_fixtures(args.names or None, write=not args.check)
    stale = {k: v for k, v in diffs.items() if v}
    for name, keys in diffs.items():
        state = "up to date" if not keys else ("stale: " if args.check else "rewritten: ") + ", ".join(keys)
        print(f"{name:32s} {state}")
    return 1 if (args.check and stale) else 0

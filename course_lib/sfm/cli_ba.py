"""``python -m course_lib ba PROBLEM_FILE [--json OUT.json]``: bundle-adjust a BAL problem.

Reads a "Bundle Adjustment in the Large" file (``.txt``, ``.bz2``, ``.gz``; see
:mod:`course_lib.data.bal`), runs the kit's sparse Levenberg-Marquardt
(:func:`course_lib.sfm.lm.solve` with :class:`~course_lib.sfm.lm.BALCamera`) and prints::

    initial_cost  final_cost  iterations  seconds

where cost is ``0.5 * sum(r**2)`` over all observations in BAL's pixel units (the SciPy
cookbook's and Ceres' definition), ``seconds`` the time of the optimization (``load_seconds``
the time to read the file). ``--json`` writes the same numbers to a file.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from course_lib.data.bal import load_bal
from course_lib.paths import course_data
from course_lib.sfm import lm
from course_lib.validate import KitInputError, output_dir


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "problem",
        nargs="?",
        default=None,
        metavar="PROBLEM_FILE",
        help="BAL problem file (.txt/.bz2/.gz); default: the course's Ladybug problem (course data 'bal-ladybug')",
    )
    parser.add_argument("--json", type=Path, default=None, metavar="OUT.json", help="also write the results to this JSON file")
    parser.add_argument("--ftol", type=float, default=1e-4, help="stop when a step lowers the cost by less than ftol * cost (default 1e-4, as Ceres' function_tolerance in the benchmark)")
    parser.add_argument("--max-iterations", type=int, default=100, help="at most this many accepted steps (default 100)")
    parser.add_argument("--loss", choices=["linear", "huber", "soft_l1", "cauchy"], default="linear", help="robust loss (default linear: plain least squares)")
    parser.add_argument("--f-scale", type=float, default=1.0, help="pixels where the robust loss starts to flatten (default 1)")
    parser.add_argument("--quiet", action="store_true", help="print only the summary line")


def run(args: argparse.Namespace) -> int:
    path = args.problem
    if path is None:
        path = course_data("bal-ladybug")
        if path is None:
            raise KitInputError("no PROBLEM_FILE given and the course data 'bal-ladybug' is not on this machine (set COURSE_DATA)")
    if args.ftol <= 0 or args.max_iterations < 1 or args.f_scale <= 0:
        raise KitInputError("--ftol and --f-scale must be positive and --max-iterations at least 1")
    if args.json is not None:  # checked before the optimization, which may take minutes
        if args.json.is_dir():
            raise KitInputError(f"--json {args.json} is a folder: give the path of a file to write "
                                f"(e.g. {args.json / 'ba.json'})")
        output_dir(args.json.parent, "--json")
    t0 = time.perf_counter()
    problem = load_bal(path)
    load_seconds = time.perf_counter() - t0
    if not args.quiet:
        print(f"{problem}, read in {load_seconds:.2f} s")

    def progress(it, cameras, points, cost):
        if not args.quiet:
            print(f"  iteration {it:3d}  cost {cost:.6e}", flush=True)

    res = lm.solve(
        lm.BALCamera(),
        problem.camera_params,
        problem.points,
        problem.cam_idx,
        problem.pt_idx,
        problem.obs,
        loss=args.loss,
        f_scale=args.f_scale,
        max_iterations=args.max_iterations,
        ftol=args.ftol,
        callback=progress,
    )
    out = {
        "problem": str(path),
        "n_cameras": problem.n_cameras,
        "n_points": problem.n_points,
        "n_observations": problem.n_obs,
        "initial_cost": res.initial_cost,
        "final_cost": res.final_cost,
        "iterations": res.iterations,
        "linear_solves": res.n_solves,
        "seconds": res.seconds,
        "load_seconds": load_seconds,
        "ftol": args.ftol,
        "loss": args.loss,
        "message": res.message,
    }
    print(
        f"initial_cost {res.initial_cost:.6e}  final_cost {res.final_cost:.6e}  "
        f"iterations {res.iterations}  seconds {res.seconds:.3f}  ({res.message})"
    )
    if args.json is not None:
        args.json.write_text(json.dumps(out, indent=2) + "\n")
        if not args.quiet:
            print(f"wrote {args.json}")
    return 0

"""How long grading a complete 8-notebook submission takes (target: <= 5 minutes on 2 cores).

    python benchmarks/grade_speed.py                 # the instructor notebooks as the submission
    python benchmarks/grade_speed.py --submission DIR

The default submission is a copy of the instructor notebooks graded in the instructor's self-test
mode (``--allow-reference``): every exercise is complete, so every hidden check, every calibration
run and every notebook under nbval runs in full, as for a student who solved everything. The
script prints the time and the score and writes the report to outputs/benchmarks/ (git-ignored).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

from course_lib.grading.grade import grade_submission, to_markdown
from course_lib.paths import REPO_ROOT


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--submission", type=Path, default=None, help="a student's kit (default: the instructor notebooks)")
    ap.add_argument("--hidden-seed", type=int, default=2026)
    ap.add_argument("--nbval-jobs", type=int, default=2)
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "outputs" / "benchmarks")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="grade-speed-") as tmp:
        sub = args.submission
        self_test = sub is None
        if sub is None:
            sub = Path(tmp) / "submission"
            shutil.copytree(REPO_ROOT / "notebooks", sub / "notebooks", ignore=shutil.ignore_patterns(".ipynb_checkpoints"))
        t0 = time.perf_counter()
        report = grade_submission(sub, salt=args.hidden_seed, allow_reference=self_test, nbval_jobs=args.nbval_jobs)
        dt = time.perf_counter() - t0
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "grade_speed.json").write_text(json.dumps({"seconds": round(dt, 1), "report": report}, indent=1,
                                                          ensure_ascii=False) + "\n")
    (args.out / "grade_speed.md").write_text(to_markdown(report))
    n_nb = len(report["notebooks"])
    n_ex = len(report["exercises"])
    slow = sorted(report["exercises"], key=lambda g: -g.get("hidden", {}).get("seconds", 0))[:3]
    print(f"graded {n_nb} notebooks, {n_ex} exercises in {dt:.0f} s (target <= 300 s): "
          f"{report['total']:g} / {report['max']:g} points")
    print("slowest hidden checks: " + ", ".join(f"{g['name']} {g.get('hidden', {}).get('seconds', 0):g} s" for g in slow))
    not_full = [f"{g['notebook']}::{g['name']} ({g['status']}, nbval {g['nbval']})" for g in report["exercises"]
                if g["points"] < g["max_points"]]
    if not_full:
        print("not full marks: " + "; ".join(not_full))
    return 0


if __name__ == "__main__":
    sys.exit(main())

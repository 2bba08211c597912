"""A class graded in one command: ``python -m course_lib grade-class`` on 30 submissions (target: <= 30 min on 2 cores).

    python benchmarks/grade_class.py                # 30 submissions, --jobs from the machine
    python benchmarks/grade_class.py --size 8 --jobs 2
    python benchmarks/grade_class.py --class-dir /tmp/class --build-only   # build once (outside a timing run) ...
    /work/bin/quiet python benchmarks/grade_class.py --class-dir /tmp/class --jobs 2   # ... then grade it alone

The class (built here from the student release and the test catalogues): complete submissions (the literal
student's, every exercise; the honest catalogue's main and variant solutions), partial ones (the first notebooks
only), the untouched release, catalogued mistakes (the honest catalogue with one mistake of
``tests/checks/catalogue`` in its exercise), and attacks (``tests/instructor/test_attacks.py``: the reference
through ``sys.modules``, reading the reference's source, ``os._exit``, an endless loop, writing outside, a fork
bomb, a link to another student's folder). ``--size`` keeps the first N of that list (the kinds interleaved).

Prints the wall time, the class process's peak memory (VmHWM) and the largest process under it, the reports, the
gradebook's rows, the CSV's shape, the time per submission (from the reports), the complete submissions' points,
and whether any report names another student's marker. Everything is written to outputs/benchmarks/grade_class/
(git-ignored).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import resource
import shutil
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import nbformat

from course_lib.instructor.release import write_release
from course_lib.paths import REPO_ROOT

sys.path.insert(0, str(REPO_ROOT))  # the catalogues of tests/ build the submissions

OUT = REPO_ROOT / "outputs" / "benchmarks" / "grade_class"


def build_class(root: Path, outside: Path) -> list[str]:
    """Write the class's submissions into ``root`` (one folder each); their names, kinds interleaved."""
    from tests.checks.catalogue import collect
    from tests.instructor import test_attacks as attacks
    from tests.instructor.honest import honest_submission
    from tests.instructor.severity import _notebook_of, _submission, mistake_source
    from tests.student.fill import fill_release

    complete, partial, mistakes, attack = [], [], [], []

    def literal(d):
        write_release(d)
        fill_release(d)

    complete += [("complete-literal", literal), ("complete-honest", lambda d: honest_submission(d)),
                 ("complete-variants", lambda d: honest_submission(d, variant=True))]
    for k in (1, 3, 5):
        partial.append((f"partial-{k}-notebooks", lambda d, k=k: honest_submission(d, notebooks=[f"{i:02d}"
                                                                                              for i in range(1, k + 1)])))
    partial.append(("untouched-release", write_release))
    seen: set[str] = set()
    for m in collect("MISTAKES"):
        if m.exercise in seen or "course_lib.sfm" in mistake_source(m) or "course_lib.nerf" in mistake_source(m):
            continue  # one mistake per exercise, written as a student would (not calling the reference)
        seen.add(m.exercise)
        mistakes.append((f"mistake-{m.exercise}", lambda d, m=m: _submission(d, m, _notebook_of(m.exercise))))
    target = outside / "do-not-touch.txt"
    target.write_text("the instructor's file\n")
    for name, body in (("stealth", attacks.STEALTH), ("read-reference", attacks.READ_REFERENCE),
                       ("os-exit", attacks.OS_EXIT), ("loop", attacks.LOOP), ("eye", attacks.EYE),
                       ("write-outside", attacks.write_outside(target)),
                       ("fork-bomb", f"    os = {attacks.SYS}['os']\n    while True:\n        os.fork()\n")):
        attack.append((f"attack-{name}", lambda d, body=body: attacks.submission(d, body)))

    def link(d):
        attacks.submission(d, attacks.HONEST)
        os.symlink("../../complete-literal/notebooks", d / "notebooks" / "other-student")

    attack.append(("attack-link-to-another-student", link))
    kinds = [complete, partial, mistakes, attack]
    order = []
    while any(kinds):
        for kind in kinds:
            if kind:
                order.append(kind.pop(0))
    names = []
    for name, make in order:
        d = root / name
        make(d)
        _mark(d, name)
        names.append(name)
    return names


def _mark(sub: Path, name: str) -> None:
    """A markdown cell naming the student in each of their notebooks (no report may show another's)."""
    for path in sorted((sub / "notebooks").glob("*.ipynb")):
        nb = nbformat.read(path, as_version=4)
        nb.cells.insert(0, nbformat.v4.new_markdown_cell(f"marker-of-{name}"))
        nbformat.write(nb, path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=30, help="submissions (the first N of the class; default 30)")
    ap.add_argument("--jobs", type=int, default=None, help="grade-class --jobs (default: its own)")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--class-dir", type=Path, default=None,
                    help="build the class here (kept), or grade the class already built here")
    ap.add_argument("--build-only", action="store_true", help="build the class into --class-dir and stop")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="grade-class-") as tmp:
        home = args.class_dir or Path(tmp)
        cls, outside = home / "class", home / "outside"
        if not cls.is_dir():
            outside.mkdir(parents=True)
            t_build = time.perf_counter()
            names = build_class(cls, outside)
            for extra in names[args.size:]:
                shutil.rmtree(cls / extra)
            (home / "names.json").write_text(json.dumps(names[:args.size]))
            print(f"built {args.size} submissions in {time.perf_counter() - t_build:.0f} s")
        names = json.loads((home / "names.json").read_text())[:args.size]
        print(f"the class: {', '.join(names)}")
        if args.build_only:
            return 0
        if args.out.exists():
            shutil.rmtree(args.out)
        args.out.mkdir(parents=True)
        cmd = [sys.executable, "-m", "course_lib", "grade-class", str(cls), "--gradebook",
               str(args.out / "grades.sqlite"), "--csv", str(args.out / "grades.csv"), "--reports",
               str(args.out / "reports")] + (["--jobs", str(args.jobs)] if args.jobs else [])
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, cwd=REPO_ROOT)
        peak = 0
        while proc.poll() is None:
            try:
                status = Path(f"/proc/{proc.pid}/status").read_text()
                peak = max(peak, int(next(ln for ln in status.splitlines() if ln.startswith("VmHWM")).split()[1]))
            except (OSError, StopIteration, ValueError):
                pass
            time.sleep(0.5)
        wall = time.perf_counter() - t0
        untouched = (outside / "do-not-touch.txt").read_text() == "the instructor's file\n"
    largest = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss  # KiB: the largest single process under it
    reports = {n: json.loads((args.out / "reports" / n / "report.json").read_text()) for n in names
               if (args.out / "reports" / n / "report.json").is_file()}
    with sqlite3.connect(args.out / "grades.sqlite") as db:
        rows = db.execute("SELECT count(*), count(DISTINCT student) FROM gradings").fetchone()
    table = list(csv.reader(open(args.out / "grades.csv")))
    crossed = [(n, o) for n in reports for o in names if o != n and f"marker-of-{o}" in
               (args.out / "reports" / n / "report.json").read_text() + (args.out / "reports" / n / "feedback.md").read_text()]
    secs = sorted(r.get("seconds") or 0 for r in reports.values())
    summary = {
        "submissions": len(names), "exit status": proc.returncode, "wall seconds": round(wall, 1),
        "class process peak MiB": round(peak / 1024), "largest process under it MiB": round(largest / 1024),
        "reports": len(reports), "gradebook rows": rows[0], "gradebook students": rows[1],
        "csv rows x columns": f"{len(table) - 1} x {len(table[0]) if table else 0}",
        "seconds per submission (min / median / max)": [secs[0], secs[len(secs) // 2], secs[-1]] if secs else None,
        "complete submissions": {n: f"{r['total']:g} / {r['max']:g}" for n, r in reports.items()
                                 if n.startswith("complete")},
        "not graded": {n: r.get("error") for n, r in reports.items() if r.get("status")},
        "another student's marker in a report": crossed, "file outside untouched": untouched,
        "points": {n: r["total"] for n, r in reports.items()},
    }
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(summary, indent=1))
    return 0 if proc.returncode == 0 and len(reports) == len(names) and not crossed and untouched else 1


if __name__ == "__main__":
    sys.exit(main())

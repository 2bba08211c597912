"""``python -m course_lib gradescope``: grade on Gradescope (its autograder package, and its ``results.json``).

    python -m course_lib gradescope --package autograder.zip [grade options, e.g. --notebooks 01 02]

writes the package to upload as a programming assignment's autograder: ``setup.sh`` (run once when Gradescope
builds the image: Python, the kit installed from its ``environment.txt``, the kit's folder closed to all but
root), ``run_autograder`` (run for each submission) and the instructor's kit under ``kit/``. ``run_autograder``
calls, in container mode (:mod:`course_lib.instructor.sandbox.container`: Gradescope runs each submission in a
container of its own, where bubblewrap's user namespaces are not allowed; ``COURSE_GRADER_CONTAINER=0`` before it
chooses bubblewrap)

    python -m course_lib gradescope --grade [--root /autograder]

which grades ``ROOT/submission`` with the single-submission grader in a process of its own
(:func:`course_lib.instructor.classroom.grade_one`: a crash or a timeout still gives a result) and writes
``ROOT/results/results.json`` in Gradescope's format: the score, the feedback (Markdown) and one test per exercise
with its points, the grader's messages and its visibility. Where the grader refuses to run a student's code (the
mode's checks fail), the result says the submission could not be graded.
"""

from __future__ import annotations

import argparse
import json
import shlex
import stat
import subprocess
import tempfile
import zipfile
from pathlib import Path

from course_lib.instructor.classroom import START_SECONDS, Submission, grade_one
from course_lib.instructor.cli_grade import add_grading_options, grading_argv
from course_lib.paths import REPO_ROOT
from course_lib.validate import KitInputError, output_dir

SETUP_SH = """#!/usr/bin/env bash
# Gradescope runs this once, as root, when it builds the autograder's image.
set -euo pipefail
apt-get update -qq
DEBIAN_FRONTEND=noninteractive apt-get install -y -qq python3 python3-venv bubblewrap
python3 -m venv /autograder/venv
cd /autograder/source/kit && /autograder/venv/bin/pip install -q -r environment.txt
chmod -R go-rwx /autograder/source  # the kit (the reference, the notebooks) closed to the students' uid
"""

RUN_AUTOGRADER = """#!/usr/bin/env bash
# Gradescope runs this for each submission: ROOT/submission in, ROOT/results/results.json out.
ROOT="${{AUTOGRADER_ROOT:-/autograder}}"
export COURSE_GRADER_CONTAINER="${{COURSE_GRADER_CONTAINER-1}}"  # the container is the isolation (0: bubblewrap)
cd "$ROOT/source/kit"
exec "${{AUTOGRADER_PYTHON:-/autograder/venv/bin/python}}" -m course_lib gradescope --grade --root "$ROOT" {options}
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    what = parser.add_mutually_exclusive_group(required=True)
    what.add_argument("--package", type=Path, metavar="AUTOGRADER.zip", help="write Gradescope's autograder package")
    what.add_argument("--grade", action="store_true",
                      help="grade ROOT/submission into ROOT/results/results.json (what run_autograder does)")
    parser.add_argument("--root", type=Path, default=Path("/autograder"), help="Gradescope's folder (default "
                        "/autograder)")
    add_grading_options(parser)


def run(args: argparse.Namespace) -> int:
    if args.package:
        return _package(args.package, grading_argv(args))
    submission, results = args.root / "submission", args.root / "results"
    if not submission.is_dir():
        raise KitInputError(f"{submission} is not a folder: --root must be laid out as Gradescope's /autograder")
    output_dir(results, "--root")
    with tempfile.TemporaryDirectory(prefix="course-gradescope-") as tmp:
        outcome = grade_one(Submission("submission", submission, ""), Path(tmp), grading_argv(args),
                            args.submission_timeout + START_SECONDS)
    (results / "results.json").write_text(json.dumps(results_json(outcome.report, outcome.feedback), indent=1) + "\n")
    print(f"{outcome.status}: {outcome.report.get('total', 0):g} / {outcome.report.get('max') or 0:g} points")
    return 0


def results_json(report: dict, feedback: str) -> dict:
    """Gradescope's ``results.json`` of a grader's report (or of a report of a grading that did not finish)."""
    tests = []
    for g in report.get("exercises", []):
        lines = list(g.get("feedback", []))
        if g.get("nbval", "not run") != "not run":
            lines.append(f"nbval check cell: {g['nbval']}")
        tests.append({"name": f"{g['notebook']}: {g['name']}", "score": g["points"], "max_score": g["max_points"],
                      "status": "passed" if g["status"] == "full" else "failed",
                      "output": "\n".join(lines), "visibility": "visible"})
    return {"score": report.get("total", 0.0), "execution_time": round(report.get("seconds") or 0),
            "output": feedback, "output_format": "md", "visibility": "visible", "stdout_visibility": "hidden",
            "tests": tests}


def _package(path: Path, options: list[str]) -> int:
    """Write the autograder package: setup.sh, run_autograder (with ``options`` for ``grade``), the kit in kit/."""
    output_dir(path.parent, "--package")
    files = subprocess.run(["git", "-C", str(REPO_ROOT), "ls-files", "-co", "--exclude-standard", "-z"],
                           capture_output=True)
    if files.returncode != 0:
        raise KitInputError(f"{REPO_ROOT} is not a git checkout: the package holds the files git lists (tracked, "
                            "and untracked but not ignored)")
    executable = stat.S_IFREG | 0o755
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for name, text in (("setup.sh", SETUP_SH),
                           ("run_autograder", RUN_AUTOGRADER.format(options=shlex.join(options)))):
            info = zipfile.ZipInfo(name)
            info.external_attr = executable << 16
            z.writestr(info, text)
        for rel in filter(None, files.stdout.decode().split("\0")):
            if (REPO_ROOT / rel).is_file() and not (REPO_ROOT / rel).is_symlink():
                z.write(REPO_ROOT / rel, f"kit/{rel}")
    print(f"wrote {path}: upload it as the autograder of a Gradescope programming assignment")
    return 0

"""``python -m course_lib grade SUBMISSION_DIR``: grade a student's kit (see :mod:`course_lib.instructor.grade`).

The grader refuses to run a student's code that it cannot isolate: where bubblewrap is missing or cannot make
a sandbox here, it stops with one line (exit status 2) that says what is missing and how to enable it.
``--insecure`` grades without a sandbox, for a trusted local run; the report and the feedback say so.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
from pathlib import Path

from course_lib.instructor.grade import grade_submission, to_markdown
from course_lib.instructor.notebooks import NOTEBOOKS_DIR
from course_lib.instructor.settings import DEFAULT_CELL_SECONDS, DEFAULT_EXERCISE_SECONDS, DEFAULT_SUBMISSION_SECONDS
from course_lib.validate import KitInputError, output_dir


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("submission", type=Path, help="the student's kit (or a folder with their notebooks)")
    parser.add_argument("--json", type=Path, default=None, metavar="REPORT.json", help="write the report as JSON")
    parser.add_argument("--markdown", type=Path, default=None, metavar="FEEDBACK.md", help="write the feedback as Markdown")
    add_grading_options(parser)


def add_grading_options(parser: argparse.ArgumentParser) -> None:
    """The options of one submission's grading (``grade-class`` passes them on to ``grade``)."""
    parser.add_argument("--notebooks", nargs="+", default=None, metavar="PREFIX",
                        help="grade only these notebooks (name prefixes, e.g. 01 02)")
    parser.add_argument("--exercises", nargs="+", default=None, metavar="NAME", help="grade only these exercises")
    parser.add_argument("--hidden-seed", type=int, default=None,
                        help="seed of the hidden cases (default: random, written into the report)")
    parser.add_argument("--timeout", type=float, default=DEFAULT_EXERCISE_SECONDS,
                        help=f"wall-clock seconds for the hidden checks of one exercise, the grader's checks of its "
                             f"results and its call-backs included (default {DEFAULT_EXERCISE_SECONDS:g}, so that correct "
                             "but slow code is graded; at least 10x "
                             "the reference's time + 5 s)")
    parser.add_argument("--submission-timeout", type=float, default=DEFAULT_SUBMISSION_SECONDS,
                        help=f"wall-clock seconds for everything of one submission, nbval included (default "
                             f"{DEFAULT_SUBMISSION_SECONDS:g}); what is not graded by then gets no credit")
    parser.add_argument("--cell-timeout", type=float, default=DEFAULT_CELL_SECONDS,
                        help="seconds for one notebook cell under nbval")
    parser.add_argument("--nbval-jobs", type=int, default=2, help="notebooks run under nbval at the same time")
    parser.add_argument("--no-nbval", action="store_true", help="skip the nbval run (hidden checks only)")
    parser.add_argument("--allow-reference", action="store_true",
                        help="instructor self-test: the reference notebooks may call the reference solutions")
    parser.add_argument("--notebooks-dir", type=Path, default=None, help="instructor notebooks (default: notebooks/)")
    parser.add_argument("--insecure", action="store_true",
                        help="run the students' code without a sandbox (a trusted local run only; written into the "
                             "report and the feedback)")


def grading_argv(args: argparse.Namespace) -> list[str]:
    """The options of :func:`add_grading_options` given on a command line, as arguments for ``grade``."""
    probe = argparse.ArgumentParser(add_help=False)
    add_grading_options(probe)
    argv = []
    for action in probe._actions:
        value = getattr(args, action.dest)
        if value == action.default:
            continue
        flag = action.option_strings[0]
        if action.nargs == 0:  # a flag (store_true)
            argv.append(flag)
        elif isinstance(value, list):
            argv += [flag, *map(str, value)]
        else:
            argv += [flag, str(value)]
    return argv


def run(args: argparse.Namespace) -> int:
    for opt, path, example in (("--json", args.json, "report.json"), ("--markdown", args.markdown, "feedback.md")):
        if path is not None:  # checked before the grading, which takes minutes
            if path.is_dir():
                raise KitInputError(f"{opt} {path} is a folder: give the path of a file to write (e.g. {path / example})")
            output_dir(path.parent, opt)

    # grade-class stops a grader past its time with SIGTERM: unwind, so that its temporary folders and cgroups go
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    report = grade_submission(
        args.submission, notebooks=args.notebooks, exercises=args.exercises, salt=args.hidden_seed,
        timeout=args.timeout, cell_timeout=args.cell_timeout, run_nbval=not args.no_nbval,
        allow_reference=args.allow_reference, notebooks_dir=args.notebooks_dir or NOTEBOOKS_DIR,
        nbval_jobs=args.nbval_jobs, insecure=args.insecure, submission_timeout=args.submission_timeout,
    )
    md = to_markdown(report)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1, ensure_ascii=False) + "\n")
    if args.markdown:
        args.markdown.write_text(md)
    _warn(report)
    for g in report["exercises"]:
        print(f"{g['notebook']:40s} {g['name']:28s} {g['points']:6g} / {g['max_points']:g}  {g['status']}")
    print(f"total {report['total']:g} / {report['max']:g} points (hidden seed {report['hidden_seed']}, "
          f"{report['seconds']:g} s)")
    sys.stdout.flush()
    return 0


def _warn(report: dict) -> None:
    """Warnings for the instructor: a run without a sandbox, files of the submission left out."""
    if report.get("insecure"):
        print("warning: --insecure: the students' code ran without a sandbox, as this user (the report says so)",
              file=sys.stderr)
    left_out = report.get("submission", {}).get("left out", [])
    if left_out:
        print(f"note: {len(left_out)} entries of the submission were not copied: " + "; ".join(left_out[:5]),
              file=sys.stderr)

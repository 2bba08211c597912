"""``python -m course_lib grade-class SUBMISSIONS_DIR --gradebook grades.sqlite``: grade a class (see
:mod:`course_lib.instructor.classroom`).

Every option of ``grade`` (``--timeout``, ``--notebooks``, ``--no-nbval``, ...) applies to each submission. Before
anything is graded, the grader makes and checks one sandbox: where it cannot (no bubblewrap, no user namespaces),
it stops with that one line (exit status 2), as ``grade`` does.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from course_lib.instructor.classroom import default_jobs, find_submissions, grade_class
from course_lib.instructor.cli_grade import add_grading_options, grading_argv
from course_lib.instructor.gradebook import Gradebook
from course_lib.validate import KitInputError, output_dir


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("submissions", type=Path, help="a folder with one sub-folder per student (named after them)")
    parser.add_argument("--gradebook", type=Path, required=True, metavar="GRADES.sqlite",
                        help="the class's SQLite gradebook (made if it does not exist)")
    parser.add_argument("--csv", type=Path, default=None, metavar="GRADES.csv",
                        help="export the gradebook: one row per student (latest grading): total, per notebook, per "
                             "exercise")
    parser.add_argument("--reports", type=Path, default=None, metavar="DIR",
                        help="write STUDENT/report.json, feedback.md and grader.log here (default: reports/ beside "
                             "the gradebook)")
    parser.add_argument("--jobs", type=int, default=None,
                        help=f"submissions graded at once (default here: {default_jobs()}, from the cores and memory)")
    parser.add_argument("--regrade", action="store_true",
                        help="grade commits already graded again (the earlier gradings stay in the gradebook)")
    add_grading_options(parser)


def run(args: argparse.Namespace) -> int:
    if not args.submissions.is_dir():
        raise KitInputError(f"{args.submissions} is not a folder: pass a folder with one sub-folder per submission")
    output_dir(args.gradebook.parent, "--gradebook")
    reports = args.reports or args.gradebook.parent / "reports"
    output_dir(reports, "--reports")
    subs = find_submissions(args.submissions)
    if not subs:
        raise KitInputError(f"{args.submissions} has no sub-folders: put each student's submission in a folder of "
                            "its own")
    if not args.insecure:
        from course_lib.instructor.grade import preflight

        preflight()  # one line, and nothing graded, where no sandbox can be made here
    book = Gradebook(args.gradebook)
    try:
        done = grade_class(subs, book, reports, grading_argv(args), jobs=args.jobs or default_jobs(),
                           regrade=args.regrade, submission_timeout=args.submission_timeout)
        for o in sorted(done, key=lambda o: o.sub.student):
            print(f"{o.sub.student:40s} {o.report.get('total', 0):7g} / {o.report.get('max') or 0:g}  {o.status}")
        failed = [o.sub.student for o in done if o.status != "graded"]
        print(f"graded {len(done)} of {len(subs)} submissions ({len(subs) - len(done)} already in the gradebook)"
              + (f"; not finished: {', '.join(failed)} (see their grader.log)" if failed else ""))
        if args.csv:
            print(f"{book.export_csv(args.csv)} students written to {args.csv}")
    finally:
        book.close()
    sys.stdout.flush()
    return 0


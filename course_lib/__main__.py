"""Command line of the kit: ``python -m course_lib <command> ...``.

Each command ``X`` lives in ``cli_X.py`` (``-`` as ``_``) of the package it belongs to
(``sfm/cli_sfm.py``, ``instructor/cli_grade.py``, ``data/cli_sfm_to_nerf.py`` ...), a module that
defines ``add_arguments(parser)`` and ``run(args) -> int``; this file only lists them, and imports
only the module of the command that runs (``--help`` imports none of them: torch, nbformat and
plotly are loaded by the commands that use them).
Bad input (a wrong path, a malformed file) ends with a one-line message that says what to fix
and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys

#: command name -> (module, one-line help)
COMMANDS = {
    "sfm": ("course_lib.sfm.cli_sfm", "run the incremental SfM pipeline on a P3 folder (default: the embedded scene)"),
    "nerf": ("course_lib.nerf.cli_nerf", "train a NeRF or render novel views from a checkpoint"),
    "fixtures": ("course_lib.instructor.cli_fixtures", "rebuild (or --check) the stored expected results behind the check cells"),
    "refresh-checks": ("course_lib.instructor.cli_refresh_checks", "re-run notebooks in quick mode and store their check cells' new verdicts (only those cells)"),
    "make-data": ("course_lib.data.cli_make_data", "regenerate the embedded synthetic data sets under data/"),
    "release": ("course_lib.instructor.cli_release", "write the student kit: notebooks with solution stubs, no reference solutions"),
    "grade": ("course_lib.instructor.cli_grade", "grade a student's kit: nbval against the reference verdicts + hidden checks"),
    "grade-class": ("course_lib.instructor.cli_grade_class", "grade a folder of submissions, several at once, into a SQLite gradebook (and a CSV)"),
    "gradescope": ("course_lib.instructor.cli_gradescope", "write Gradescope's autograder package, or grade there into results.json (--grade)"),
    "ba": ("course_lib.sfm.cli_ba", "bundle-adjust a 'Bundle Adjustment in the Large' problem with the kit's sparse LM"),
    "match": ("course_lib.data.cli_match", "SIFT-match a folder of your own photos into a P3 folder (K from --K, else from EXIF or a guess that sfm refines)"),
    "sfm-to-nerf": ("course_lib.data.cli_sfm_to_nerf", "turn an SfM reconstruction (COLMAP text) + its images into a NeRF Blender data set"),
}


def available(module: str) -> bool:
    """Whether ``module`` is part of this copy of the kit (the student release leaves some out), without importing it."""
    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:  # its package is left out
        return False


def build_parser(command: str | None) -> argparse.ArgumentParser:
    """The parser, with the arguments of ``command`` only (the others are listed by name and help)."""
    parser = argparse.ArgumentParser(prog="python -m course_lib", description="The SfM + NeRF course kit.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        if not available(module):
            continue
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == command:
            importlib.import_module(module).add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = argv[0] if argv and argv[0] in COMMANDS else None
    parser = build_parser(command)
    if command is not None and not available(COMMANDS[command][0]):
        parser.error(f"the command {command!r} is not available in this copy of the kit")
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    from course_lib.validate import KitInputError  # deferred: numpy, not needed by --help (start-up)

    runner = importlib.import_module(COMMANDS[args.command][0]).run
    try:
        return int(runner(args) or 0)
    except (KitInputError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

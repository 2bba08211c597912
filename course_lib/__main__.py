"""Command line of the kit: ``python -m course_lib <command> ...``.

Each command lives in a module that defines ``add_arguments(parser)`` and ``run(args) -> int``;
this file only lists them. Bad input (a wrong path, a malformed file) ends with a one-line
message that says what to fix and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from course_lib.validate import KitInputError

#: command name -> (module, one-line help)
COMMANDS = {
    "sfm": ("course_lib.sfm.cli", "run the incremental SfM pipeline on a P3 folder (default: the embedded scene)"),
    "nerf": ("course_lib.nerf.cli", "train a NeRF or render novel views from a checkpoint"),
    "fixtures": ("course_lib.instructor.fixtures", "rebuild (or --check) the stored expected results behind the check cells"),
    "refresh-checks": ("course_lib.instructor.refresh", "re-run notebooks in quick mode and store their check cells' new verdicts (only those cells)"),
    "make-data": ("course_lib.data.cli", "regenerate the embedded synthetic data sets under data/"),
    "release": ("course_lib.instructor.cli_release", "write the student kit: notebooks with solution stubs, no reference solutions"),
    "grade": ("course_lib.instructor.cli_grade", "grade a student's kit: nbval against the reference verdicts + hidden checks"),
    "ba": ("course_lib.sfm.ba_cli", "bundle-adjust a 'Bundle Adjustment in the Large' problem with the kit's sparse LM"),
    "match": ("course_lib.data.match_cli", "SIFT-match a folder of photos with known K into a P3 folder (your own photos -> course data)"),
    "sfm-to-nerf": ("course_lib.data.sfm_to_nerf", "turn an SfM reconstruction (COLMAP text) + its images into a NeRF Blender data set"),
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m course_lib", description="The SfM + NeRF course kit.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    runners = {}
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        try:
            mod = importlib.import_module(module)
        except ModuleNotFoundError as exc:
            if exc.name != module:
                raise
            continue  # a command whose module is not part of this release
        mod.add_arguments(p)
        runners[name] = mod.run
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    if args.command not in runners:
        parser.error(f"the command {args.command!r} is not available in this copy of the kit")
    try:
        return int(runners[args.command](args) or 0)
    except (KitInputError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

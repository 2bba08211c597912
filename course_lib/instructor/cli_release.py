"""``python -m course_lib release OUT_DIR``: write the student kit (see :mod:`course_lib.instructor.release`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from course_lib.instructor.notebooks import NOTEBOOKS_DIR, ReleaseError
from course_lib.instructor.release import verify_release, write_release
from course_lib.instructor.release_names import dangling_references, false_claims


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("out_dir", type=Path, help="folder for the student kit (replaced if it holds an earlier release)")
    parser.add_argument("--notebooks-dir", type=Path, default=None, help="instructor notebooks (default: notebooks/)")
    parser.add_argument("--verify", action="store_true",
                        help="then execute the released notebooks inside the kit and report any error other than "
                             "NotImplementedError, any module, name or file the kit's text (README, environment.txt, "
                             "notebooks, docstrings) names but the kit lacks, a notebook count or a pin that is not "
                             "so, and development text (issue numbers, dates) (a few minutes)")
    parser.add_argument("--force", action="store_true", help="replace a non-empty folder that is not an earlier release")


def run(args: argparse.Namespace) -> int:
    try:
        manifest = write_release(args.out_dir, args.notebooks_dir or NOTEBOOKS_DIR, force=args.force)
    except ReleaseError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    n_ex = sum(len(nb["exercises"]) for nb in manifest["notebooks"])
    print(f"student kit written to {args.out_dir}: {len(manifest['notebooks'])} notebooks, {n_ex} exercises, "
          f"{len(manifest['files'])} files")
    print(f"left out (reference solutions): {', '.join(manifest['omitted_modules']) or 'none'}")
    for mod, names in sorted(manifest["redacted"].items()):
        print(f"redacted {mod}: {', '.join(names)} call the student's own functions")
    for name in manifest["left_out_notebooks"]:
        print(f"left out notebooks/{name} (no exercises, needs the reference solutions)")
    for note in manifest["notes"]:
        print(f"note: {note}")
    if args.verify:
        problems = verify_release(args.out_dir)
        for name, found in problems.items():
            print(f"{name}: " + ("runs in the kit (only NotImplementedError where exercises are missing)"
                                 if not found else "; ".join(found)))

        dangling = dangling_references(args.out_dir) + false_claims(args.out_dir)
        for line in dangling:
            print(f"text: {line}")
        print(f"the kit's text names only what the kit has and says only what is so ({'no' if not dangling else len(dangling)} "
              "dangling references or false claims: README's notebook count, environment.txt's pins, development text)")
        if any(problems.values()) or dangling:
            print("error: some released notebooks fail in the student kit, or its text names what it lacks",
                  file=sys.stderr)
            return 1
    return 0

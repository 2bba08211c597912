"""``python -m course_lib fixtures [--check] [NAME ...]``: rebuild the check cells' stored results."""

from __future__ import annotations

import argparse

from course_lib.grading.core import build_fixtures


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

"""Where the kit finds its data.

* The embedded data sets live in the repository's ``data/`` folder; the kit generated them itself
  (see :mod:`course_lib.data.building`).
* The course's own data (WPI, UPenn, lego, BAL) is course material that the kit never copies or
  redistributes. Point the kit at it with the environment variable ``COURSE_DATA`` (a folder laid
  out as ``sfm-p3/wpi-unity-hall``, ``nerf-lego-100``, ...); without it the kit looks for
  ``../shared/data`` beside the repository.
* ``COURSE_LIB_QUICK=1`` asks notebooks that train for their quick setting (the test suite sets it).
"""

from __future__ import annotations

import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
DATA_DIR = REPO_ROOT / "data"
EMBEDDED_SFM = DATA_DIR / "synthetic-building"
EMBEDDED_NERF = DATA_DIR / "synthetic-building-nerf"
FIXTURES_DIR = DATA_DIR / "fixtures"

#: Names of the course data sets, relative to the course-data folder.
COURSE_SETS = {
    "wpi": "sfm-p3/wpi-unity-hall",
    "upenn": "sfm-p3/upenn-levine-hall",
    "lego": "nerf-lego-100",
    "bal-ladybug": "bal/problem-49-7776-pre.txt.bz2",
}


def course_data_root() -> Path | None:
    """The folder with the course's own data, or None when it is not on this machine."""
    env = os.environ.get("COURSE_DATA")
    candidates = [Path(env)] if env else []
    candidates.append(REPO_ROOT.parent / "shared" / "data")
    for c in candidates:
        if c.is_dir():
            return c
    return None


def course_data(name: str) -> Path | None:
    """Path of one course data set (``"wpi"``, ``"upenn"``, ``"lego"``, ``"bal-ladybug"``), or None if absent."""
    if name not in COURSE_SETS:
        raise KeyError(f"unknown course data set {name!r}; known: {sorted(COURSE_SETS)}")
    root = course_data_root()
    if root is None:
        return None
    p = root / COURSE_SETS[name]
    return p if p.exists() else None


def quick_mode() -> bool:
    """True when ``COURSE_LIB_QUICK`` is set to a true value (the tests and CI set it)."""
    return os.environ.get("COURSE_LIB_QUICK", "").lower() not in ("", "0", "false", "no")

"""``python -m course_lib make-data``: regenerate the embedded data sets under ``data/``.

    python -m course_lib make-data                      # both, into data/, with the committed seed
    python -m course_lib make-data --which sfm --out /tmp/data --seed 7

Writes ``<out>/synthetic-building/`` (P3 folder + ground_truth.json) and/or
``<out>/synthetic-building-nerf/`` (Blender format). The same seed gives the same files: the
renderer is plain numpy, OpenCV's JPEG/PNG encoders are deterministic for a given OpenCV build,
and SIFT keypoints are sorted before matching (see :mod:`course_lib.data.building`).
"""

from __future__ import annotations

import shutil
import time

from course_lib.data import building
from course_lib.paths import DATA_DIR, EMBEDDED_NERF, EMBEDDED_SFM
from course_lib.validate import output_dir


def add_arguments(parser) -> None:
    parser.add_argument("--out", default=str(DATA_DIR), help=f"data folder to write into (default: {DATA_DIR})")
    parser.add_argument("--seed", type=int, default=None, help="seed of everything random (default: the committed one)")
    parser.add_argument("--which", choices=("sfm", "nerf", "all"), default="all", help="which data set to make (default: all)")


def run(args) -> int:
    seed = building.DEFAULT_SEED if args.seed is None else int(args.seed)
    out = output_dir(args.out)
    todo = ["sfm", "nerf"] if args.which == "all" else [args.which]
    for what in todo:
        name = (EMBEDDED_SFM if what == "sfm" else EMBEDDED_NERF).name
        folder = out / name
        if folder.exists():  # start clean, so no stale file survives a change of the generator
            shutil.rmtree(folder)
        t0 = time.time()
        if what == "sfm":
            summary = building.make_sfm_dataset(folder, seed=seed, verbose=True)
            print(f"{folder}: {summary['tracks']} tracks; matches per pair {summary['pairs']}")
        else:
            summary = building.make_nerf_dataset(folder, seed=seed, verbose=True)
            print(f"{folder}: views per split {summary}")
        size = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
        print(f"  {size / 1e6:.2f} MB, {time.time() - t0:.0f} s")
    return 0

"""``python -m course_lib sfm [DATA_DIR] --out OUT_DIR [--seed S]``: run the SfM pipeline on a P3 folder.

Without ``DATA_DIR`` the embedded scene (``data/synthetic-building``) is used. Writes to ``OUT_DIR``
(default ``outputs/sfm``, git-ignored):

* ``colmap/cameras.txt``, ``colmap/images.txt``, ``colmap/points3D.txt``: the model as COLMAP text
  files (open it with ``pycolmap.Reconstruction(OUT_DIR / "colmap")`` or COLMAP's GUI);
* ``report.json``: the pipeline's per-stage report (pairs and RANSAC inliers, verified tracks,
  degenerate pairs, initial pair, every registration, images left out and why, reprojection
  errors before and after bundle adjustment, seconds) plus totals;
* ``scene.html``: the cameras and points in an interactive 3-D plot that opens offline.

Bad input (a missing folder or image, a truncated matching file, a K that is not invertible)
ends with a one-line message and exit status 2 (:mod:`course_lib.__main__`).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from course_lib.validate import KitInputError, output_dir

#: Default output folder, relative to the working directory (``outputs/`` is git-ignored).
DEFAULT_OUT = Path("outputs") / "sfm"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("data_dir", nargs="?", default=None,
                   help="P3 folder (calibration.txt, matching*.txt, images); default: the embedded scene data/synthetic-building")
    p.add_argument("--out", default=str(DEFAULT_OUT), help=f"output folder (default: {DEFAULT_OUT})")
    p.add_argument("--seed", type=int, default=0, help="seed of the random generator used by RANSAC (default 0)")
    p.add_argument("--ba", choices=("incremental", "final", "none"), default="incremental",
                   help="bundle adjustment after every registration (default), only at the end, or never")
    p.add_argument("--no-html", action="store_true", help="skip scene.html")
    p.add_argument("--quiet", action="store_true", help="print only the summary")


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def write_scene_html(rec, path: Path, title: str) -> Path:
    """The reconstruction as a standalone HTML page (plotly.js embedded, opens offline)."""
    from course_lib.viz.scene3d import scene_figure, write_html

    fig = scene_figure(cameras=rec.cameras(), points=rec.points(), title=title)
    return write_html(fig, path)


def run(args) -> int:
    from course_lib.data.p3 import read_p3
    from course_lib.paths import EMBEDDED_SFM
    from course_lib.sfm.pipeline import run_sfm

    t0 = time.perf_counter()
    cpu0 = time.process_time()
    data_dir = Path(args.data_dir) if args.data_dir else EMBEDDED_SFM
    if not data_dir.is_dir():
        raise KitInputError(f"P3 folder not found: {data_dir} (expected a folder with calibration.txt, matching1.txt, ... and 1.png, ...)")
    out = output_dir(args.out)  # before the work: a wrong --out costs nothing
    data = read_p3(data_dir)
    rec = run_sfm(data, np.random.default_rng(args.seed), bundle_adjustment=args.ba, verbose=not args.quiet)

    colmap_dir = rec.write_colmap(out / "colmap")
    html = None
    if not args.no_html:
        html = write_scene_html(rec, out / "scene.html", f"SfM: {data_dir.name} ({rec.n_registered} images, {rec.n_points} points)")
    report = dict(rec.report)
    report["data_dir"] = str(data_dir)
    report["seed"] = args.seed
    report["outputs"] = {"colmap": str(colmap_dir), "report": str(out / "report.json"), "scene_html": str(html) if html else None}
    report["totals"] = {
        "wall_seconds": round(time.perf_counter() - t0, 3),
        "cpu_seconds": round(time.process_time() - cpu0, 3),
        "registered_images": rec.n_registered,
        "n_images": len(rec.image_names),
        "points": rec.n_points,
        "mean_reprojection_error_px": report["final"]["mean_reprojection_error_px"],
    }
    with open(out / "report.json", "w") as f:
        json.dump(_jsonable(report), f, indent=2)

    fin = report["final"]
    print(
        f"SfM on {data_dir}: {rec.n_registered}/{len(rec.image_names)} images registered, {rec.n_points} points, "
        f"{fin['observations']} observations, mean reprojection error {fin['mean_reprojection_error_px']:.3f} px "
        f"(median {fin['median_reprojection_error_px']:.3f}), {report['totals']['wall_seconds']:.1f} s"
    )
    for d in report.get("left_out", []):
        print(f"left out: {d['name']}: {d['reason']}")
    for d in report.get("degenerate_pairs", []):
        print(f"degenerate pair (not used to start): {d['names'][0]}, {d['names'][1]}: {d['kind']}")
    print(f"outputs: {colmap_dir}/ (COLMAP text model), {out / 'report.json'}" + (f", {html}" if html else ""))
    return 0

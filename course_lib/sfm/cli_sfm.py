"""``python -m course_lib sfm [DATA_DIR] --out OUT_DIR [--seed S]``: run the SfM pipeline on a P3 folder.

Without ``DATA_DIR`` the embedded scene (``data/synthetic-building``) is used. Writes to ``OUT_DIR``
(default ``outputs/sfm``, git-ignored):

* ``colmap/cameras.txt``, ``colmap/images.txt``, ``colmap/points3D.txt``: the largest model as COLMAP
  text files (open it with ``pycolmap.Reconstruction(OUT_DIR / "colmap")`` or COLMAP's GUI); where
  registration stalled and the images left made models of their own, those go beside it, largest
  first: ``colmap-1/``, ``colmap-2/``, ... (the ``colmap-K/`` an earlier run left beyond these are
  removed);
* ``report.json``: the pipeline's per-stage report (pairs and their inliers, verified tracks, the
  camera (refined focal length and ``k1`` where the P3 folder came from ``match`` without ``--K``),
  degenerate pairs, initial pair, every registration, images left out and why, reprojection
  errors before and after bundle adjustment, seconds) of the largest model, ``models`` (one summary
  per model), ``others`` (the other models' reports) plus totals;
* ``scene.html``: the cameras and points in an interactive 3-D plot that opens offline (every
  model, the others drawn beside the largest).

Every field of :class:`~course_lib.sfm.mapper_options.MapperOptions` can be set with
``--option KEY=VALUE`` (repeatable); a bad key or value ends with one line and exit status 2.

Exit status 0 when at least one model exists; where no image pair can start one, a one-line
message and exit status 2.

Bad input (a missing folder or image, a truncated matching file, a K that is not invertible)
ends with a one-line message and exit status 2 (:mod:`course_lib.__main__`).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from course_lib.data.p3 import read_p3
from course_lib.paths import EMBEDDED_SFM
from course_lib.sfm.mapper_options import parse_assignments
from course_lib.sfm.pipeline import run_sfm
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
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="set any field of course_lib.sfm.mapper_options.MapperOptions, e.g. --option min_pnp_inliers=30 "
                        "--option refine_intrinsics=false (repeatable)")
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
    """The reconstruction as a standalone HTML page (plotly.js embedded, opens offline).

    The other models (``rec.others``) are drawn beside the largest one, each in its own legend
    group, scaled to its size and shifted along x: their world frames are unrelated.
    """
    # deferred: plotly, for --html only
    from course_lib.viz.scene3d import add_cameras, add_points, scene_figure, write_html

    fig = scene_figure(cameras=rec.cameras(), points=rec.points(), title=title, name="model 1")
    X0, _ = rec.points()
    lo, hi = (X0.min(0), X0.max(0)) if len(X0) else (np.zeros(3), np.ones(3))
    size = float(np.linalg.norm(hi - lo)) or 1.0
    right = hi[0]
    for m in rec.others:
        X, rgb = m.points()
        C = m.centers[m.registered]
        both = np.concatenate([X, C]) if len(X) else C
        s = size / max(float(np.linalg.norm(both.max(0) - both.min(0))), 1e-9)
        shift = np.array([right + 0.3 * size, 0.0, 0.0]) - s * np.array([both[:, 0].min(), 0.0, 0.0]) \
            - np.array([0.0, *(s * both[:, 1:].mean(0) - (lo[1:] + hi[1:]) / 2)])
        label = f"model {m.report['model']}"
        add_points(fig, s * X + shift, rgb, name=f"{label} points")
        R = m.R_cw[m.registered]
        add_cameras(fig, R, np.stack([-Ri @ (s * c + shift) for Ri, c in zip(R, C)]), m.K, m.image_size,
                    names=[m.image_names[i] for i in np.flatnonzero(m.registered)], legend_group=f"{label} cameras")
        right = float((s * both[:, 0] + shift[0]).max())
    return write_html(fig, path)


def run(args) -> int:
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    data_dir = Path(args.data_dir) if args.data_dir else EMBEDDED_SFM
    if not data_dir.is_dir():
        raise KitInputError(f"P3 folder not found: {data_dir} (expected a folder with calibration.txt, matching1.txt, ... and 1.png, ...)")
    options = {"bundle_adjustment": args.ba, **parse_assignments(args.option)}  # a bad --option: one line, before the work
    out = output_dir(args.out)  # before the work: a wrong --out costs nothing
    data = read_p3(data_dir)
    rec = run_sfm(data, np.random.default_rng(args.seed), **{"verbose": not args.quiet, **options})

    models = [rec] + rec.others
    folders = [m.write_colmap(out / m.report["models"][k]["folder"]) for k, m in enumerate(models)]
    _remove_stale_models(out, len(models))
    html = None
    if not args.no_html:
        counts = " + ".join(str(m.n_registered) for m in models)
        html = write_scene_html(rec, out / "scene.html", f"SfM: {data_dir.name} ({counts} images in {len(models)} model(s), "
                                f"{rec.n_points} points in the largest)")
    report = dict(rec.report)
    report["others"] = [{k: v for k, v in m.report.items() if k not in ("pairs", "tracks", "options", "models")} for m in rec.others]
    report["data_dir"] = str(data_dir)
    report["seed"] = args.seed
    report["outputs"] = {"colmap": str(folders[0]), "colmap_others": [str(f) for f in folders[1:]],
                         "report": str(out / "report.json"), "scene_html": str(html) if html else None}
    report["totals"] = {
        "wall_seconds": round(time.perf_counter() - t0, 3),
        "cpu_seconds": round(time.process_time() - cpu0, 3),
        "registered_images": rec.n_registered,
        "registered_images_all_models": sum(m.n_registered for m in models),
        "models": len(models),
        "n_images": len(rec.image_names),
        "points": rec.n_points,
        "mean_reprojection_error_px": report["final"]["mean_reprojection_error_px"],
    }
    with open(out / "report.json", "w") as f:
        json.dump(_jsonable(report), f, indent=2)
    _print_summary(report, data_dir, models, folders, out, html)
    return 0


def _remove_stale_models(out: Path, n_models: int) -> None:
    """Remove the ``colmap-K/`` models an earlier run wrote to ``out`` beyond this run's ``n_models``, so that no
    folder there describes another run. Only the files the kit writes go (a folder with anything else stays)."""
    written = {"cameras.txt", "images.txt", "points3D.txt"}
    for folder in out.glob("colmap-*"):
        k = folder.name.removeprefix("colmap-")
        if not (k.isdigit() and int(k) >= n_models and folder.is_dir()):
            continue
        files = list(folder.iterdir())
        if files and all(f.is_file() and f.name in written for f in files):
            for f in files:
                f.unlink()
            folder.rmdir()


def _print_summary(report: dict, data_dir: Path, models: list, folders: list, out: Path, html) -> None:
    """The summary line (the largest model), one line per other model, the images left out and the outputs."""
    rec, fin = models[0], report["final"]
    M = len(rec.image_names)
    print(
        f"SfM on {data_dir}: {rec.n_registered}/{M} images registered, {rec.n_points} points, "
        f"{fin['observations']} observations, mean reprojection error {fin['mean_reprojection_error_px']:.3f} px "
        f"(median {fin['median_reprojection_error_px']:.3f}), {report['totals']['wall_seconds']:.1f} s"
        + (f"; {len(models)} models: {' + '.join(str(m.n_registered) for m in models)} images" if len(models) > 1 else "")
    )
    for m, folder in zip(models[1:], folders[1:]):
        f = m.report["final"]
        print(f"model {m.report['model']} ({folder.name}/): {m.n_registered} images ({', '.join(f['registered'])}), "
              f"{m.n_points} points, mean reprojection error {f['mean_reprojection_error_px']:.3f} px")
    in_some = {n for m in models for n in m.report["final"]["registered"]}
    for d in report.get("left_out", []):
        if d["name"] not in in_some:
            print(f"left out: {d['name']}: {d['reason']}")
    for d in report.get("degenerate_pairs", []):
        if d["kind"] != "mostly planar":
            print(f"degenerate pair (not used to start): {d['names'][0]}, {d['names'][1]}: {d['kind']}")
    cam = report.get("camera", {})
    if cam.get("model") == "SIMPLE_RADIAL":
        start = cam.get("start_focal_px", cam["prior_focal_px"])
        via = f"; the mapping started from {start:.1f}" if abs(start - cam["prior_focal_px"]) > 1e-6 else ""
        print(f"camera refined (SIMPLE_RADIAL): f = {cam['K'][0][0]:.1f} px (from {cam['prior_focal_px']:.1f}{via}), k1 = {cam['k1']:.4f}")
    extra = f" (+ {', '.join(f.name + '/' for f in folders[1:])} for the other models)" if len(folders) > 1 else ""
    print(f"outputs: {folders[0]}/ (COLMAP text model){extra}, {out / 'report.json'}" + (f", {html}" if html else ""))

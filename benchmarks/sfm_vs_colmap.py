"""The kit's SfM pipeline side by side with COLMAP (pycolmap), on the same P3 matches.

For every scene both get the same correspondences (a P3 folder, read once with
:func:`course_lib.data.p3.read_p3`):

* **kit**: :func:`course_lib.sfm.pipeline.run_sfm` (RANSAC on F per pair, verified tracks,
  incremental mapping, bundle adjustment), default options, ``rng`` seeded with 0;
* **COLMAP**: a COLMAP database built from the same matches (one PINHOLE camera with the P3
  ``K``, the distinct pixels of each image as keypoints, the raw matches of each pair), then
  ``pycolmap.geometric_verification`` and ``pycolmap.incremental_mapping`` with the intrinsics
  held fixed. Its time includes writing the database (both start from the P3 matches in memory).

Each method runs as a **whole process**, timed from outside: the kit as ``python -m course_lib sfm
P3 --out TMP --quiet --no-html`` (its largest model read back from ``TMP/colmap``), COLMAP as
``python benchmarks/sfm_vs_colmap.py --colmap-worker P3 JSON`` (import pycolmap, read the P3
folder, the database, verification and mapping). A P3 folder without images gets grey
stand-ins in a temporary copy (the kit's ``sfm`` command reads the image size from them).

Printed per scene and method: registered images (of the largest model) and the sizes of all
models, 3-D points, mean reprojection error (pixels), mean and max rotation error (degrees) and
mean centre error (% of the scene size) against the ground truth after a similarity alignment on
rotations and centres (:func:`course_lib.alignment.pose_errors`), the seconds of the whole
process and of the reconstruction alone inside it. For the course data (no ground truth) the
pose columns compare the kit with COLMAP instead (marked ``vs COLMAP``).

Scenes: the embedded rendered scene (``data/synthetic-building``), synthetic scenes
(:func:`course_lib.data.synthetic.make_scene`) of 5, 8 and 12 cameras with 10-30 % wrong
observations of both kinds (``random``: uniform random pixels; ``swap``: the pixel of another
point's feature), the hard scenes of :mod:`course_lib.data.scenes` (16-view rings whose views fall
into weakly linked groups, a texture-poor ring, near-duplicate views), and WPI / UPenn where the
course data is present.

Usage::

    python benchmarks/sfm_vs_colmap.py                  # every scene
    python benchmarks/sfm_vs_colmap.py --scenes syn     # only the synthetic ones
    python benchmarks/sfm_vs_colmap.py --scenes hard    # only the hard scenes (rings, duplicates)
    python benchmarks/sfm_vs_colmap.py --json out.json  # also write the rows
    python benchmarks/sfm_vs_colmap.py --scenes none --p3 /tmp/bldg12/p3   # any P3 folder
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from course_lib.data.p3 import read_p3  # noqa: E402
from course_lib.data.synthetic import make_scene, write_scene_p3  # noqa: E402
from course_lib.paths import EMBEDDED_SFM, course_data  # noqa: E402
from course_lib.alignment import pose_errors  # noqa: E402
from course_lib.sfm.pipeline import run_sfm  # noqa: E402

REPO = Path(__file__).resolve().parent.parent

#: (name, n_cameras, noise_px, outlier_fraction, outlier_kind, seed)
SYNTHETIC = [
    ("syn-5-10%-random", 5, 0.5, 0.10, "random", 5),
    ("syn-5-10%-swap", 5, 0.5, 0.10, "swap", 5),
    ("syn-8-30%-random", 8, 1.0, 0.30, "random", 8),
    ("syn-8-30%-swap", 8, 1.0, 0.30, "swap", 8),
    ("syn-12-20%-random", 12, 0.5, 0.20, "random", 12),
    ("syn-12-20%-swap", 12, 0.5, 0.20, "swap", 12),
]
#: (name, generator in course_lib.data.scenes, seed)
HARD = [
    ("ring-groups-s0", "grouped_ring_scene", 0),
    ("ring-groups-s1", "grouped_ring_scene", 1),
    ("ring-groups-s2", "grouped_ring_scene", 2),
    ("ring-texture-poor", "texture_poor_ring_scene", 0),
    ("ring-texture-poor-s1", "texture_poor_ring_scene", 1),
    ("near-duplicates", "near_duplicate_scene", 0),
]


def _keypoints_and_matches(data):
    """Distinct pixels of each image (COLMAP keypoints) and each pair's matches as keypoint indices."""
    M = len(data.image_names)
    ends = [[] for _ in range(M)]
    for (i, j), pm in data.matches.items():
        ends[i].append(pm.x1)
        ends[j].append(pm.x2)
    kps = [np.unique(np.concatenate(e), axis=0) if e else np.zeros((0, 2)) for e in ends]
    index = [{(float(u), float(v)): k for k, (u, v) in enumerate(kp)} for kp in kps]
    matches = {}
    for (i, j), pm in data.matches.items():
        a = [index[i][(float(u), float(v))] for u, v in pm.x1]
        b = [index[j][(float(u), float(v))] for u, v in pm.x2]
        matches[(i, j)] = np.array([a, b], dtype=np.uint32).T.reshape(-1, 2)
    return kps, matches


def run_colmap(data, image_size, workdir: Path, seed: int = 0):
    """COLMAP's geometric verification and incremental mapping on the P3 matches.

    Returns:
        dict with ``R_cw (M, 3, 3)``, ``t_cw (M, 3)`` (NaN where unregistered), ``registered (M,)``,
        ``points``, ``mean_reprojection_error_px``, ``seconds``.
    """
    import pycolmap

    pycolmap.logging.minloglevel = 2  # warnings and errors only
    pycolmap.set_random_seed(seed)
    t0 = time.perf_counter()
    M = len(data.image_names)
    K = data.K
    W, H = image_size
    kps, matches = _keypoints_and_matches(data)
    db_path = workdir / "database.db"
    with pycolmap.Database.open(str(db_path)) as db:
        cam = pycolmap.Camera(model="PINHOLE", width=int(W), height=int(H), params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
        cid = db.write_camera(cam)
        ids = []
        for i in range(M):
            ids.append(db.write_image(pycolmap.Image(name=data.image_names[i], camera_id=cid)))
            db.write_keypoints(ids[-1], kps[i].astype(np.float32))
        for (i, j), m in matches.items():
            db.write_matches(ids[i], ids[j], m)
    tvg = pycolmap.TwoViewGeometryOptions()
    tvg.ransac.random_seed = seed  # COLMAP's RANSAC is seeded only where asked (else it varies run to run)
    pycolmap.geometric_verification(str(db_path), two_view_geometry_options=tvg)
    opts = pycolmap.IncrementalPipelineOptions()
    opts.ba_refine_focal_length = False
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    opts.random_seed = seed
    recs = pycolmap.incremental_mapping(str(db_path), str(workdir), str(workdir / "sparse"), opts)
    seconds = time.perf_counter() - t0
    R = np.full((M, 3, 3), np.nan)
    t = np.full((M, 3), np.nan)
    reg = np.zeros(M, bool)
    if not recs:
        return {"R_cw": R, "t_cw": t, "registered": reg, "points": 0, "mean_reprojection_error_px": float("nan"),
                "seconds": seconds, "models": []}
    models = sorted((int(r.num_reg_images()) for r in recs.values()), reverse=True)
    rec = max(recs.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))
    name_to_i = {n: i for i, n in enumerate(data.image_names)}
    for im in rec.images.values():
        if not im.has_pose:
            continue
        i = name_to_i[im.name]
        pose = im.cam_from_world()
        R[i], t[i] = pose.rotation.matrix(), pose.translation
        reg[i] = True
    return {"R_cw": R, "t_cw": t, "registered": reg, "points": int(rec.num_points3D()),
            "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()), "seconds": seconds, "models": models}


def run_kit(data):
    t0 = time.perf_counter()
    rec = run_sfm(data, np.random.default_rng(0))
    seconds = time.perf_counter() - t0
    return {"R_cw": rec.R_cw, "t_cw": rec.t_cw, "registered": rec.registered, "points": rec.n_points,
            "mean_reprojection_error_px": rec.report["final"]["mean_reprojection_error_px"], "seconds": seconds,
            "report": rec.report, "models": [m["registered_images"] for m in rec.report["models"]]}


def folder_with_images(data, image_size, workdir: Path) -> Path:
    """``data.folder`` if its images are there, else a copy of its text files with grey stand-in images."""
    import cv2

    folder = Path(data.folder)
    if all((folder / n).is_file() for n in data.image_names):
        return folder
    dst = workdir / "p3"
    dst.mkdir(parents=True, exist_ok=True)
    for f in folder.glob("*.txt"):
        shutil.copy(f, dst / f.name)
    W, H = (int(v) for v in image_size)
    grey = np.full((H, W, 3), 128, np.uint8)
    for n in data.image_names:
        cv2.imwrite(str(dst / n), grey)
    return dst


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}


def kit_process(folder: Path, names: list, workdir: Path) -> dict:
    """``python -m course_lib sfm`` as a whole process: the largest model read back from ``OUT/colmap``, wall seconds."""
    from course_lib.data.colmap import read_colmap_text

    out = workdir / "kit"
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "course_lib", "sfm", str(folder), "--out", str(out), "--quiet", "--no-html"],
                          cwd=REPO, env=_env(), capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    M = len(names)
    res = {"R_cw": np.full((M, 3, 3), np.nan), "t_cw": np.full((M, 3), np.nan), "registered": np.zeros(M, bool), "points": 0,
           "mean_reprojection_error_px": float("nan"), "seconds": seconds, "sfm_seconds": float("nan"), "models": [],
           "error": proc.stderr.strip().splitlines()[-1] if proc.returncode else ""}
    if proc.returncode:
        return res
    report = json.loads((out / "report.json").read_text())
    m = read_colmap_text(out / "colmap")
    for k, n in enumerate(m.image_names):
        i = names.index(n)
        res["R_cw"][i], res["t_cw"][i], res["registered"][i] = m.R_cw[k], m.t_cw[k], True
    res.update(points=int(len(m.X)), mean_reprojection_error_px=report["final"]["mean_reprojection_error_px"],
               sfm_seconds=report["seconds"]["total"], models=[d["registered_images"] for d in report["models"]])
    return res


def colmap_process(folder: Path, image_size, workdir: Path) -> dict:
    """:func:`run_colmap` in a process of its own (``--colmap-worker``), timed from outside."""
    out = workdir / "colmap.json"
    t0 = time.perf_counter()
    subprocess.run([sys.executable, str(Path(__file__).resolve()), "--colmap-worker", str(folder), str(out),
                    str(int(image_size[0])), str(int(image_size[1]))], cwd=REPO, env=_env(), check=True)
    seconds = time.perf_counter() - t0
    res = json.loads(out.read_text())
    res = {k: np.array(v, float) if k in ("R_cw", "t_cw") else v for k, v in res.items()}
    res["registered"] = np.array(res["registered"], bool)
    res["sfm_seconds"], res["seconds"] = res["seconds"], seconds
    return res


def _colmap_worker(folder: str, out: str, W: str, H: str) -> int:
    data = read_p3(Path(folder), require_images=False)
    with tempfile.TemporaryDirectory() as d:
        res = run_colmap(data, (int(W), int(H)), Path(d))
    Path(out).write_text(json.dumps({k: v.tolist() if isinstance(v, np.ndarray) else v for k, v in res.items()}))
    return 0


def _pose_columns(res, R_ref, t_ref, scene_size, only=None):
    both = res["registered"] & np.isfinite(R_ref).all(axis=(1, 2)) & (True if only is None else only)
    if both.sum() < 2:
        return float("nan"), float("nan"), float("nan")
    pe = pose_errors(res["R_cw"][both], res["t_cw"][both], R_ref[both], t_ref[both])
    return float(pe.rotation_deg.mean()), float(pe.rotation_deg.max()), float(100 * pe.center.mean() / scene_size)


def _p3_scene(folder: Path):
    """A P3 folder, with its ``ground_truth.json`` where there is one (:func:`course_lib.data.building.load_ground_truth`)."""
    from course_lib.data.building import load_ground_truth
    from course_lib.sfm.reconstruction import image_size_of as _image_size  # from the images, or the extent of the pixels without them

    data = read_p3(folder, require_images=False)
    size_px = _image_size(data)
    if not (folder / "ground_truth.json").is_file():
        return folder.name, data, None, None, None, size_px
    _, names, R, t = load_ground_truth(folder)
    order = [names.index(n) for n in data.image_names]
    size = json.loads((folder / "ground_truth.json").read_text()).get("scene_size", 1.0)
    return folder.name, data, R[order], t[order], float(size), size_px


def scenes(which: str, extra=()):
    """Yield ``(name, data, R_true, t_true, scene_size, image_size)``; truth None for the course data."""
    for folder in extra:
        yield _p3_scene(Path(folder))
    with tempfile.TemporaryDirectory(prefix="sfm_vs_colmap_") as folder:  # removed when the scenes are done
        tmp = Path(folder)
        if which in ("all", "embedded"):
            from course_lib.data.building import load_ground_truth

            data = read_p3(EMBEDDED_SFM)
            _, names, R, t = load_ground_truth(EMBEDDED_SFM)
            gt = json.loads((EMBEDDED_SFM / "ground_truth.json").read_text())
            assert names == data.image_names
            yield "embedded", data, R, t, float(gt["scene_size"]), data.image_size
        if which in ("all", "syn"):
            for name, M, noise, frac, kind, seed in SYNTHETIC:
                sc = make_scene(np.random.default_rng(seed), n_cameras=M, n_points=400, noise_px=noise,
                                outlier_fraction=frac, outlier_kind=kind)
                data, _ = write_scene_p3(sc, tmp / name)
                yield name, data, sc.R_cw, sc.t_cw, sc.scene_size, sc.image_size
        if which in ("all", "hard"):
            from course_lib.data import scenes as hard

            for name, gen, seed in HARD:
                sc = getattr(hard, gen)(np.random.default_rng(seed))
                data, _ = write_scene_p3(sc, tmp / name)
                yield name, data, sc.R_cw, sc.t_cw, sc.scene_size, sc.image_size
    if which in ("all", "course"):
        for key in ("wpi", "upenn"):
            folder = course_data(key)
            if folder is None:
                print(f"# {key}: course data not found (set COURSE_DATA); skipped")
                continue
            data = read_p3(folder)
            yield key, data, None, None, None, data.image_size


def _rows(name, M, kit, col, R_true, t_true, size) -> list[dict]:
    """Print and return the rows of one scene (kit, COLMAP) and their ratios."""
    rows = []
    for method, res in (("kit", kit), ("colmap", col)):
        if R_true is not None:
            rot, rmax, cerr = _pose_columns(res, R_true, t_true, size)
            ref = "truth"
        elif method == "kit":
            C = np.stack([-R.T @ t for R, t in zip(col["R_cw"], col["t_cw"])])
            ok = np.isfinite(C).all(axis=1)
            ref_size = float(np.linalg.norm(C[ok].max(0) - C[ok].min(0))) if ok.sum() >= 2 else 1.0
            rot, rmax, cerr = _pose_columns(res, col["R_cw"], col["t_cw"], ref_size)
            ref = "vs COLMAP (C err in % of the camera path)"
        else:
            rot = rmax = cerr = float("nan")
            ref = ""
        models = "+".join(str(v) for v in res["models"]) or "-"
        row = {"scene": name, "method": method, "registered": int(res["registered"].sum()), "images": M, "models": res["models"],
               "points": int(res["points"]), "mean_reprojection_error_px": round(res["mean_reprojection_error_px"], 4),
               "rotation_error_mean_deg": round(rot, 4), "rotation_error_max_deg": round(rmax, 4),
               "center_error_mean_pct": round(cerr, 4), "pose_reference": ref, "seconds": round(res["seconds"], 3),
               "sfm_seconds": round(res["sfm_seconds"], 3)}
        rows.append(row)
        print(f"{name:20s} {method:7s} {row['registered']:>2d}/{M:<3d} {models:>8s} {row['points']:>6d} "
              f"{row['mean_reprojection_error_px']:>9.3f} {rot:>9.4f} {rmax:>8.4f} {cerr:>8.3f} {res['seconds']:>9.2f} "
              f"{res['sfm_seconds']:>6.2f}" + (f"  ({ref})" if ref and ref != "truth" else "")
              + (f"  error: {res['error']}" if res.get("error") else ""))
    k, c = rows
    ratio = f"time kit/COLMAP {k['seconds'] / max(c['seconds'], 1e-12):.2f}x (whole process)"
    if R_true is not None:
        ratio = f"rotation error kit/COLMAP {k['rotation_error_mean_deg'] / max(c['rotation_error_mean_deg'], 1e-12):.2f}x, " + ratio
        common = kit["registered"] & col["registered"]
        if common.sum() >= 2 and common.sum() < max(kit["registered"].sum(), col["registered"].sum()):
            # the errors above are over each tool's own images; on the images both registered:
            rk, rc = (_pose_columns(res, R_true, t_true, size, common)[0] for res in (kit, col))
            k["rotation_error_common_deg"], c["rotation_error_common_deg"] = round(rk, 4), round(rc, 4)
            ratio += f"; on the {int(common.sum())} images both registered: {rk:.4f} vs {rc:.4f} deg ({rk / max(rc, 1e-12):.2f}x)"
    print(f"{'':20s} ratio   {ratio}")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    if argv is None and len(sys.argv) == 6 and sys.argv[1] == "--colmap-worker":
        return _colmap_worker(*sys.argv[2:])
    ap.add_argument("--scenes", choices=["all", "embedded", "syn", "hard", "course", "none"], default="all")
    ap.add_argument("--p3", nargs="*", default=[], help="more P3 folders (compared with their ground_truth.json if present)")
    ap.add_argument("--json", help="write the rows to this JSON file")
    args = ap.parse_args(argv)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"# load average (1 min) at start: {load:.2f}; cores: {os.cpu_count()}")
    print(f"{'scene':20s} {'method':7s} {'reg':>6s} {'models':>8s} {'points':>6s} {'reproj px':>9s} {'rot mean':>9s} {'rot max':>8s} "
          f"{'C err %':>8s} {'process s':>9s} {'sfm s':>6s}")
    rows = []
    for name, data, R_true, t_true, size, image_size in scenes(args.scenes, args.p3):
        with tempfile.TemporaryDirectory() as d:
            folder = folder_with_images(data, image_size, Path(d))
            col = colmap_process(folder, image_size, Path(d))
            kit = kit_process(folder, list(data.image_names), Path(d))
        rows += _rows(name, len(data.image_names), kit, col, R_true, t_true, size)
        sys.stdout.flush()
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"# load average (1 min) at end: {load:.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

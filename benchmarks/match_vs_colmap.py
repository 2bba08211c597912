"""The kit's ``match`` side by side with COLMAP's own matching, on the same photos.

For every photo set, three runs:

* **COLMAP end to end**: ``pycolmap.extract_features`` (its SIFT, one PINHOLE camera with the
  known K), ``pycolmap.match_exhaustive`` (its ratio test, cross-check and two-view geometric
  verification) and ``pycolmap.incremental_mapping`` (intrinsics held fixed);
* **kit match -> COLMAP**: :func:`course_lib.data.cli_match.match_images` (the ``match``
  command) written as a P3 folder and read back, then COLMAP's verification and mapping on
  those matches (:func:`sfm_vs_colmap.run_colmap`, the same database route as the SfM
  benchmark), so the only difference to the first run is who matched;
* **kit match -> kit sfm**: the kit end to end, :func:`course_lib.sfm.pipeline.run_sfm` on the
  same P3 folder (seed 0), as ``python -m course_lib match`` then ``python -m course_lib sfm`` do;
* optionally (``--variants``) the same with other ``match`` settings, to find what a gap comes
  from (ratio, RootSIFT, the feature cap, the verification threshold, the per-pair floor).

Printed per set and run: images registered, 3-D points, mean rotation error after a similarity
alignment (degrees; against the ground truth of a rendered set, else against COLMAP end to end,
marked ``vs COLMAP``), verified pairs and seconds.

Photo sets: the WPI and UPenn images of the course data (``../shared/data``, read in place,
never copied into the repository; their P3 matches are not used), the embedded building's six
photos, and two fresh renders of the synthetic building: a 16-view ring around it and the same
ring blurred and darkened (texture-poor: few features per image).

Usage::

    python benchmarks/match_vs_colmap.py                     # every set, default match settings
    python benchmarks/match_vs_colmap.py --sets wpi ring     # some of them
    python benchmarks/match_vs_colmap.py --variants          # also every match setting that may explain a gap
    python benchmarks/match_vs_colmap.py --variants "contrast 0.04" "no RootSIFT"   # some of them
    python benchmarks/match_vs_colmap.py --cache /tmp/rings  # keep the rendered rings between runs
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from course_lib.data.cli_match import match_images  # noqa: E402
from course_lib.data.p3 import read_calibration, read_p3, write_p3  # noqa: E402
from course_lib.alignment import pose_errors  # noqa: E402
from course_lib.paths import EMBEDDED_SFM, course_data  # noqa: E402
from course_lib.sfm.pipeline import run_sfm  # noqa: E402
from course_lib.validate import KitInputError  # noqa: E402
from sfm_vs_colmap import run_colmap  # noqa: E402

#: name -> keyword arguments of match_images (the kit's default first)
VARIANTS = {
    "kit default": {},
    "OpenCV SIFT defaults (match before)": {"contrast_threshold": 0.04, "rootsift": False, "max_features": 0},
    "contrast 0.04": {"contrast_threshold": 0.04},
    "no RootSIFT": {"rootsift": False},
    "ratio 0.7": {"ratio": 0.7},
    "verify 2 px": {"verify_px": 2.0},
    "floor 8": {"min_pair_matches": 8},
}


@dataclass
class PhotoSet:
    """Photos of one camera with known K, and the true poses where known."""

    name: str
    images: list  # M (H, W, 3) uint8 RGB
    K: np.ndarray
    R_cw: np.ndarray | None = None  # (M, 3, 3)
    t_cw: np.ndarray | None = None  # (M, 3)


# ------------------------------------------------------------------------------------------ sets


def _read_images(paths) -> list:
    from course_lib.data.cli_match import load_images

    return load_images(paths)


def course_set(name: str) -> PhotoSet | None:
    folder = course_data(name)
    if folder is None:
        return None
    from course_lib.data.cli_match import list_images

    return PhotoSet(name, _read_images(list_images(folder)), read_calibration(folder / "calibration.txt"))


def embedded_set() -> PhotoSet:
    from course_lib.data.building import load_ground_truth
    from course_lib.data.cli_match import list_images

    K, names, R, t = load_ground_truth(EMBEDDED_SFM)
    return PhotoSet("embedded", _read_images(list_images(EMBEDDED_SFM)), K, R, t)


def ring_cameras(n: int, radius: float = 14.0, rng: np.random.Generator | None = None):
    """``n`` cameras on a ring around the building, eye height, aimed at its middle."""
    from course_lib.data.synthetic import look_at

    rng = np.random.default_rng(0) if rng is None else rng
    Rs, ts = [], []
    for a in np.linspace(0.0, 2 * np.pi, n, endpoint=False) + rng.normal(0, 0.03, n):
        C = np.array([radius * np.sin(a), -1.5 - radius * np.cos(a), rng.uniform(1.3, 2.3)])
        R, _ = look_at(C, np.array([0.0, -1.5, 2.6]) + rng.normal(0, 0.3, 3), up=(0.0, 0.0, 1.0))
        Rs.append(R)
        ts.append(-R @ C)
    return np.stack(Rs), np.stack(ts)


def ring_set(n: int, poor: bool, cache: Path | None) -> PhotoSet:
    """A fresh render of the building from a ring of ``n`` views (640x480); ``poor``: blurred and dark."""
    import cv2

    from course_lib.data import building
    from course_lib.data.cli_match import scale_intrinsics

    size = (640, 480)
    K = scale_intrinsics(building.WPI_LIKE_K, building.SFM_IMAGE_SIZE, size)
    R, t = ring_cameras(n)
    images = []
    surfaces = None
    for i in range(n):
        f = cache / f"ring{n}-{i}.png" if cache else None
        if f is not None and f.is_file():
            images.append(cv2.imread(str(f))[:, :, ::-1].copy())
            continue
        if surfaces is None:
            surfaces = building.build_scene(np.random.default_rng(11), ground="large")
        rgb, _ = building.render(surfaces, K, R[i], t[i], size, supersample=1)
        img = np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)
        if f is not None:
            f.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(f), img[:, :, ::-1])
        images.append(img)
    if poor:  # texture-poor: the fine texture blurred away, low contrast
        images = [np.clip(cv2.GaussianBlur(im, (0, 0), 2.5).astype(float) * 0.45 + 40, 0, 255).astype(np.uint8)
                  for im in images]
    return PhotoSet(f"ring-{n}{'-poor' if poor else ''}", images, K, R, t)


# ------------------------------------------------------------------------------------------ runs


def colmap_end_to_end(ps: PhotoSet, workdir: Path, seed: int = 0) -> dict:
    """COLMAP's SIFT, exhaustive matching and verification, incremental mapping (K fixed)."""
    import cv2
    import pycolmap

    pycolmap.logging.minloglevel = 2
    pycolmap.set_random_seed(seed)
    img_dir = workdir / "images"
    img_dir.mkdir(parents=True)
    names = [f"{i + 1}.png" for i in range(len(ps.images))]
    for n, im in zip(names, ps.images):
        cv2.imwrite(str(img_dir / n), im[:, :, ::-1])
    t0 = time.perf_counter()
    db = workdir / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = ",".join(str(v) for v in (ps.K[0, 0], ps.K[1, 1], ps.K[0, 2], ps.K[1, 2]))
    pycolmap.extract_features(db, img_dir, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader)
    tvg = pycolmap.TwoViewGeometryOptions()
    tvg.ransac.random_seed = seed
    pycolmap.match_exhaustive(db, verification_options=tvg)
    with pycolmap.Database.open(str(db)) as d:
        _, n_inliers = d.read_two_view_geometry_num_inliers()
        pairs = int(sum(n >= 15 for n in n_inliers))  # COLMAP's floor: TwoViewGeometryOptions.min_num_inliers
    opts = pycolmap.IncrementalPipelineOptions()
    opts.ba_refine_focal_length = opts.ba_refine_principal_point = opts.ba_refine_extra_params = False
    opts.random_seed = seed
    recs = pycolmap.incremental_mapping(str(db), str(img_dir), str(workdir / "sparse"), opts)
    out = _poses_of(recs, names)
    out.update(seconds=time.perf_counter() - t0, pairs=pairs)
    return out


def _poses_of(recs, names) -> dict:
    M = len(names)
    R, t, reg = np.full((M, 3, 3), np.nan), np.full((M, 3), np.nan), np.zeros(M, bool)
    if not recs:
        return {"R_cw": R, "t_cw": t, "registered": reg, "points": 0}
    rec = max(recs.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))
    index = {n: i for i, n in enumerate(names)}
    for im in rec.images.values():
        if im.has_pose:
            pose = im.cam_from_world()
            i = index[im.name]
            R[i], t[i], reg[i] = pose.rotation.matrix(), pose.translation, True
    return {"R_cw": R, "t_cw": t, "registered": reg, "points": int(rec.num_points3D())}


def kit_match_then_colmap(ps: PhotoSet, workdir: Path, seed: int = 0, **match_kw) -> tuple[dict, dict]:
    """The kit's ``match`` (P3 written and read back), then COLMAP's verification and mapping on it, and the kit's ``run_sfm``."""
    import cv2

    t0 = time.perf_counter()
    res = match_images(ps.images, rng=np.random.default_rng(seed), **match_kw)
    names = [f"{i + 1}.png" for i in range(len(ps.images))]
    write_p3(workdir / "p3", names, ps.K, res.track_uv, res.track_rgb)
    t_match = time.perf_counter() - t0
    data = read_p3(workdir / "p3", require_images=False)
    H, W = ps.images[0].shape[:2]
    out = run_colmap(data, (W, H), workdir, seed)
    pairs = sum(1 for n in res.verified_matches.values() if n >= match_kw.get("min_pair_matches", 15))
    out.update(seconds=t_match + out["seconds"], match_seconds=t_match, pairs=pairs)
    for n, im in zip(names, ps.images):  # as `match` writes them: run_sfm reads the image size from them
        cv2.imwrite(str(workdir / "p3" / n), im[:, :, ::-1])
    t0 = time.perf_counter()
    try:
        rec = run_sfm(read_p3(workdir / "p3"), np.random.default_rng(seed))
        kit = {"R_cw": rec.R_cw, "t_cw": rec.t_cw, "registered": rec.registered, "points": rec.n_points}
    except KitInputError:  # no pair can start a model
        M = len(ps.images)
        kit = {"R_cw": np.full((M, 3, 3), np.nan), "t_cw": np.full((M, 3), np.nan), "registered": np.zeros(M, bool), "points": 0}
    kit.update(seconds=t_match + time.perf_counter() - t0, pairs=pairs)
    return out, kit


def rotation_error(out: dict, R_ref, t_ref) -> float:
    """Mean rotation error (degrees) of the images registered in ``out`` and known in the reference."""
    ok = out["registered"] & np.isfinite(R_ref).all(axis=(1, 2))
    if ok.sum() < 3:
        return float("nan")
    return float(pose_errors(out["R_cw"][ok], out["t_cw"][ok], R_ref[ok], t_ref[ok]).rotation_deg.mean())


def compare(ps: PhotoSet, variants: dict, seed: int = 0) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory(prefix="match-vs-colmap-") as tmp:
        ref = colmap_end_to_end(ps, Path(tmp) / "colmap", seed)
        runs = [("COLMAP end to end", ref)]
        for k, (label, kw) in enumerate(variants.items()):
            col, kit = kit_match_then_colmap(ps, Path(tmp) / f"kit{k}", seed, **kw)
            runs += [(f"kit match ({label}) -> COLMAP", col), (f"kit match ({label}) -> kit sfm", kit)]
    truth = ps.R_cw is not None
    R_ref, t_ref = (ps.R_cw, ps.t_cw) if truth else (ref["R_cw"], ref["t_cw"])
    for label, out in runs:
        rows.append({"set": ps.name, "run": label, "images": len(ps.images), "registered": int(out["registered"].sum()),
                     "points": out["points"], "pairs": out["pairs"],
                     "rot_deg": None if (not truth and out is ref) else round(rotation_error(out, R_ref, t_ref), 3),
                     "vs": "truth" if truth else "COLMAP", "seconds": round(out["seconds"], 1)})
    return rows


def print_rows(rows: list[dict]) -> None:
    print(f"{'set':<16}{'run':<46}{'registered':>11}{'points':>8}{'pairs':>7}{'rot err deg':>24}{'seconds':>9}", flush=True)
    for r in rows:
        rot = "-" if r["rot_deg"] is None else f"{r['rot_deg']:.3f}" + ("" if r["vs"] == "truth" else " vs COLMAP")
        print(f"{r['set']:<16}{r['run']:<46}{r['registered']:>5}/{r['images']:<5}{r['points']:>8}{r['pairs']:>7}"
              f"{rot:>24}{r['seconds']:>9.1f}", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sets", nargs="*", default=["wpi", "upenn", "embedded", "ring", "ring-poor"],
                    help="photo sets: wpi upenn embedded ring ring-poor (default: all)")
    ap.add_argument("--views", type=int, default=16, help="views of the rendered rings (default 16)")
    ap.add_argument("--variants", nargs="*", default=None, metavar="NAME",
                    help=f"also run match with these settings (no name: all of them): {', '.join(map(repr, VARIANTS))}")
    ap.add_argument("--cache", type=Path, default=None, help="folder that keeps the rendered ring photos between runs")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = ap.parse_args(argv)
    names = ["kit default"] + ([v for v in VARIANTS if v != "kit default"] if args.variants == [] else list(args.variants or []))
    unknown = [v for v in names if v not in VARIANTS]
    if unknown:
        ap.error(f"unknown variant(s) {unknown}; known: {list(VARIANTS)}")
    variants = {v: VARIANTS[v] for v in dict.fromkeys(names)}
    rows = []
    for name in args.sets:
        if name in ("wpi", "upenn"):
            ps = course_set(name)
            if ps is None:
                print(f"{name}: the course data is not on this machine (skipped)")
                continue
        elif name == "embedded":
            ps = embedded_set()
        elif name in ("ring", "ring-poor"):
            ps = ring_set(args.views, name == "ring-poor", args.cache)
        else:
            ap.error(f"unknown set {name!r}")
        new = compare(ps, variants, args.seed)
        print_rows(new)
        rows += new
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

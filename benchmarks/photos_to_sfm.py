"""Photos -> model: the kit's ``match`` + ``sfm`` against COLMAP end to end, whole processes, side by side.

For every photo set, in one run on the same machine:

* **kit**: the two commands of the README as separate processes, timed from outside::

      python -m course_lib match PHOTOS [--K PHOTOS/calibration.txt] --out P3 --quiet
      python -m course_lib sfm P3 --out SFM --quiet --no-html

  with ``--K`` where the set comes with a calibration file; without it the kit takes K from EXIF
  or a guess and refines the focal length and ``k1``. Sets without a calibration file are also run
  **with the true K** (``kit, true K``), the reference for "within 1.5x the error with the true K".
* **COLMAP**: ``pycolmap.extract_features`` (its own SIFT; one ``PINHOLE`` camera with the K held
  fixed where the set has a calibration file, else ``SIMPLE_RADIAL`` from EXIF or its guess,
  refined), ``pycolmap.match_exhaustive`` (ratio test, cross-check, two-view verification) and
  ``pycolmap.incremental_mapping``, as one process of this script (``--colmap-worker``), timed from
  outside the same way.

Printed per set and run: images registered (largest model), the sizes of all models, 3-D points,
mean and max rotation error (degrees) after a similarity alignment on the centres
(:func:`course_lib.alignment.pose_errors`; against the rendering's truth, or against COLMAP for real
photos), the focal length found (px) where it was estimated, seconds, and the kit's time over
COLMAP's; below each run, its seconds by stage as the process measured them (kit: ``match``'s load, features,
pairs, verification, tracks; ``sfm``'s pair checks with self-calibration, initial pair, registration, final BA and
the mappings a focal restart abandoned; COLMAP: features, matching with verification, mapping).

Photo sets (rendered once into ``--cache``, default ``outputs/photos-to-sfm``; git-ignored):

* ``ring-N``: N views on a ring around the synthetic building (640x480 PNG, K known);
* ``poor-ring-N``: the same ring blurred and darkened (texture-poor: few features, pairs that need
  the calibrated five-point start);
* ``walk-N``: a walk past the building (800x600 JPEG, K known; :func:`course_lib.data.building.sfm_photos`);
* ``street-N``: a walk along the street in front of the building, the camera turned 25 degrees towards the walking
  direction (640x480 PNG, K known; :func:`street_cameras`): a chain of views, no loop;
* ``facade-N``: the main facade from N places in front of it, the middle view from far to the side, a little blurred
  and washed out (640x480 PNG, K known; :func:`facade_cameras`): one weak view (facade-12: one partner with 79
  verified matches, the others 0-12);
* ``exif5-ring-N`` / ``exif17-ring-N``: the ring with no calibration file, EXIF
  ``FocalLengthIn35mmFilm`` rounded to whole mm and 5 % / 17 % off the true focal length;
* ``phone-ring-N``: phone-like JPEGs (1280x960, barrel distortion ``k1 = -0.05``, EXIF focal
  length and 35 mm equivalent of a phone, make and model), no calibration file;
* ``fX-ring-N`` / ``fXk-ring-N``: the ring seen by a camera whose focal length is X times COLMAP's guess
  (1.2 x 640 px; X from 0.5, a wide field of view, to 3, a narrow one), principal point at the centre, PNG
  without EXIF or calibration file; ``k``: barrel distortion ``k1 = -0.05``. The ring's radius grows with
  the focal length, so the building fills the views alike;
* ``wpi``, ``upenn``: the course's photos (``../shared/data``, read in place; their P3 matches are not used).

Every set that has a calibration file or EXIF is also run **without** them (``kit, no K``, ``COLMAP, no K``:
no ``--K`` / the camera not given, and the photos' EXIF stripped in a copy), so the focal length is found
from the images alone; ``--no-uncalibrated`` leaves those runs out. Note that the ``ring-N`` renders have
the principal point of the course's camera, a few pixels off the centre that a run without K assumes.

Usage::

    python benchmarks/photos_to_sfm.py --sets ring-16 ring-48 ring-100        # the time growth
    python benchmarks/photos_to_sfm.py --sets street-24 facade-12 ring-200 --no-uncalibrated
    python benchmarks/photos_to_sfm.py --sets poor-ring-24 exif5-ring-24 phone-ring-16 wpi upenn
    python benchmarks/photos_to_sfm.py --sets ring-16 --json out.json
"""

from __future__ import annotations

import argparse
import io
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO_ROOT))

from course_lib.data.camera import undistort_pixels  # noqa: E402
from course_lib.data.colmap import read_colmap_text  # noqa: E402
from course_lib.alignment import pose_errors  # noqa: E402
from course_lib.paths import course_data  # noqa: E402

DEFAULT_CACHE = REPO_ROOT / "outputs" / "photos-to-sfm"
PHONE_SIZE = (1280, 960)
PHONE_K1 = -0.05


# ------------------------------------------------------------------------------------------ photo sets


def ring_cameras(n: int, radius: float = 14.0, seed: int = 0, aim_sd: float = 0.3):
    """``n`` cameras on a ring around the building, eye height, aimed at its middle (``R_cw (n, 3, 3), t_cw (n, 3)``)."""
    from course_lib.data.synthetic import look_at

    rng = np.random.default_rng(seed)
    Rs, ts = [], []
    for a in np.linspace(0.0, 2 * np.pi, n, endpoint=False) + rng.normal(0, 0.03, n):
        C = np.array([radius * np.sin(a), -1.5 - radius * np.cos(a), rng.uniform(1.3, 2.3)])
        R, _ = look_at(C, np.array([0.0, -1.5, 2.6]) + rng.normal(0, aim_sd, 3), up=(0.0, 0.0, 1.0))
        Rs.append(R)
        ts.append(-R @ C)
    return np.stack(Rs), np.stack(ts)


def street_cameras(n: int, seed: int = 3):
    """``n`` cameras of a walk along the street in front of the building (``y = -10``, ``x`` from -12 to 4 m, eye height),
    each turned 25 degrees from the facades towards the walking direction, with jitter: a view overlaps its
    neighbours, hardly the views a few steps away, and no loop closes (``R_cw (n, 3, 3), t_cw (n, 3)``)."""
    from course_lib.data.synthetic import look_at

    rng = np.random.default_rng(seed)
    Rs, ts = [], []
    for x in np.linspace(-12.0, 4.0, n) + rng.normal(0, 0.1, n):
        C = np.array([x, -10.0 + rng.normal(0, 0.2), 1.6 + rng.normal(0, 0.05)])
        yaw = np.radians(25.0 + rng.normal(0, 4.0))
        R, _ = look_at(C, C + np.array([np.sin(yaw), np.cos(yaw), rng.normal(0, 0.03) + 0.1]), up=(0.0, 0.0, 1.0))
        Rs.append(R)
        ts.append(-R @ C)
    return np.stack(Rs), np.stack(ts)


def facade_cameras(n: int, seed: int = 5):
    """``n`` cameras in front of the main facade (``y`` about -12, ``x`` from -4 to 4 m), aimed at it with jitter; the
    middle one (``n // 2``) stands far to the side (``x = 11, y = -5``), seeing the facade at about 60 degrees: the
    weak view (``R_cw (n, 3, 3), t_cw (n, 3)``)."""
    from course_lib.data.synthetic import look_at

    rng = np.random.default_rng(seed)
    Rs, ts = [], []
    for k, x in enumerate(np.linspace(-4.0, 4.0, n)):
        C = np.array([x, -12.0 + rng.normal(0, 0.3), rng.uniform(1.3, 2.3)])
        if k == n // 2:
            C = np.array([11.0, -5.0, 1.7])
        R, _ = look_at(C, np.array([0.0, -2.0, 2.5]) + rng.normal(0, 0.3, 3), up=(0.0, 0.0, 1.0))
        Rs.append(R)
        ts.append(-R @ C)
    return np.stack(Rs), np.stack(ts)


def _render_ring(n: int, size: tuple[int, int], K: np.ndarray, k1: float = 0.0, radius: float = 14.0,
                 cameras=None) -> list[np.ndarray]:
    """The ring's views (or those of ``cameras = (R_cw, t_cw)``) as uint8 RGB, with the radial term ``k1`` applied
    (barrel for k1 < 0)."""
    import cv2

    from course_lib.data import building

    R, t = ring_cameras(n, radius) if cameras is None else cameras
    surfaces = building.build_scene(np.random.default_rng(11), ground="large")
    out = []
    W, H = size
    for i in range(n):
        rgb, _ = building.render(surfaces, K, R[i], t[i], size, supersample=1)
        img = np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)
        if k1:
            v, u = np.mgrid[0:H, 0:W].astype(np.float64)
            src = undistort_pixels(np.stack([u, v], axis=-1), K, k1).astype(np.float32)  # where the pinhole saw each pixel
            img = cv2.remap(img, src[..., 0], src[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        out.append(img)
    return out


def _poor(images: list[np.ndarray]) -> list[np.ndarray]:
    """Texture-poor: the fine texture blurred away, low contrast (as ``benchmarks/match_vs_colmap.py``)."""
    import cv2

    return [np.clip(cv2.GaussianBlur(im, (0, 0), 2.5).astype(float) * 0.45 + 40, 0, 255).astype(np.uint8) for im in images]


def _jpeg_with_exif(img: np.ndarray, exif: dict, quality: int = 92) -> bytes:
    """JPEG bytes of an RGB image with the EXIF tags ``{tag number: value}`` (0x8769 sub-IFD tags go there)."""
    from PIL import Image

    ex = Image.Exif()
    sub = ex.get_ifd(0x8769)
    for tag, val in exif.items():
        (sub if tag >= 0x8000 else ex)[tag] = val
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, "JPEG", quality=quality, exif=ex.tobytes())
    return buf.getvalue()


def build_set(name: str, cache: Path) -> dict:
    """Render (once) and describe a photo set: ``{"photos": folder, "calibration": file or None, "R", "t", "K", "k1"}``."""
    import cv2

    from course_lib.data import building
    from course_lib.data.cli_match import scale_intrinsics

    if name in ("wpi", "upenn"):
        folder = course_data(name)
        if folder is None:
            return {}
        return {"photos": folder, "calibration": folder / "calibration.txt", "R": None, "t": None, "K": None, "k1": 0.0}
    f = re.fullmatch(r"f(\d+(?:\.\d+)?)(k?)-ring-(\d+)", name)
    if f is not None:
        return _focal_ring(name, float(f.group(1)), bool(f.group(2)), int(f.group(3)), cache)
    m = re.fullmatch(r"(ring|poor-ring|walk|street|facade|exif5-ring|exif17-ring|phone-ring)-(\d+)", name)
    if m is None:
        raise SystemExit(f"unknown photo set {name!r}")
    kind, n = m.group(1), int(m.group(2))
    folder = cache / name
    truth = folder / "truth.npz"
    if truth.is_file():
        z = np.load(truth)
        calib = folder / "calibration.txt"
        return {"photos": folder, "calibration": calib if calib.is_file() else None, "R": z["R"], "t": z["t"], "K": z["K"],
                "k1": float(z["k1"])}
    folder.mkdir(parents=True, exist_ok=True)
    k1, has_calib = 0.0, kind in ("ring", "poor-ring", "walk", "street", "facade")
    if kind in ("street", "facade"):
        size = (640, 480)
        K = scale_intrinsics(building.WPI_LIKE_K, building.SFM_IMAGE_SIZE, size)
        R, t = street_cameras(n) if kind == "street" else facade_cameras(n)
        images = _render_ring(n, size, K, cameras=(R, t))
        if kind == "facade":  # the weak view: seen at 60 degrees, a little blurred and washed out as well
            images[n // 2] = np.clip(cv2.GaussianBlur(images[n // 2], (0, 0), 1.2).astype(float) * 0.7 + 30, 0, 255).astype(np.uint8)
        for i, img in enumerate(images):
            cv2.imwrite(str(folder / f"{i + 1}.png"), img[:, :, ::-1])
    elif kind == "walk":
        photos = building.sfm_photos(seed=7, n_cameras=n)
        K, R, t = next(photos)
        for i, (jpeg, _) in enumerate(photos):
            (folder / f"{i + 1}.jpg").write_bytes(jpeg)
    else:
        size = PHONE_SIZE if kind == "phone-ring" else (640, 480)
        K = scale_intrinsics(building.WPI_LIKE_K, building.SFM_IMAGE_SIZE, size)
        K[0, 0] = K[1, 1] = float(np.sqrt(K[0, 0] * K[1, 1]))  # one focal length (SIMPLE_RADIAL's)
        if not has_calib:  # a camera without a calibration file: its principal point at the centre, as the prior assumes
            K[0, 2], K[1, 2] = (size[0] - 1) / 2.0, (size[1] - 1) / 2.0
        R, t = ring_cameras(n)
        k1 = PHONE_K1 if kind == "phone-ring" else 0.0
        images = _render_ring(n, size, K, k1)
        if kind == "poor-ring":
            images = _poor(images)
        diag = float(np.hypot(*size))
        for i, img in enumerate(images):
            if kind in ("ring", "poor-ring"):
                cv2.imwrite(str(folder / f"{i + 1}.png"), img[:, :, ::-1])
                continue
            off = {"exif5-ring": 1.05, "exif17-ring": 1.17, "phone-ring": 1.0}[kind]
            f35 = int(round(K[0, 0] * off * 43.2666 / diag))
            exif = {0x010F: "KitPhone", 0x0110: "Ring 1", 0xA405: f35}
            if kind == "phone-ring":  # a phone's real focal length (mm) and 35 mm equivalent, no sensor resolution
                exif[0x920A] = (int(round(K[0, 0] * 4.8 / size[0] * 100)), 100)
            (folder / f"IMG_{i + 1:04d}.jpg").write_bytes(_jpeg_with_exif(img, exif))
    if has_calib:
        np.savetxt(folder / "calibration.txt", K)
    np.savez(truth, R=R, t=t, K=K, k1=k1)
    return build_set(name, cache)


def _focal_ring(name: str, factor: float, distorted: bool, n: int, cache: Path) -> dict:
    """``fX-ring-N`` (``fXk-ring-N``): N PNG views (640x480, no EXIF, no calibration file) of a camera whose focal
    length is X times COLMAP's guess (1.2 x 640 px), principal point at the centre, ``k1 = -0.05`` with ``k``; the ring's
    radius grows with the focal length so that the building fills the views alike."""
    import cv2

    folder = cache / name
    truth = folder / "truth.npz"
    if not truth.is_file():
        folder.mkdir(parents=True, exist_ok=True)
        size = (640, 480)
        f = factor * 1.2 * max(size)
        K = np.array([[f, 0.0, (size[0] - 1) / 2.0], [0.0, f, (size[1] - 1) / 2.0], [0.0, 0.0, 1.0]])
        radius = 14.0 * f / 425.0  # ring-N: f = 425 px at radius 14
        k1 = PHONE_K1 if distorted else 0.0
        for i, img in enumerate(_render_ring(n, size, K, k1, radius)):
            cv2.imwrite(str(folder / f"{i + 1}.png"), img[:, :, ::-1])
        R, t = ring_cameras(n, radius)
        np.savez(truth, R=R, t=t, K=K, k1=k1)
    z = np.load(truth)
    return {"photos": folder, "calibration": None, "R": z["R"], "t": z["t"], "K": z["K"], "k1": float(z["k1"])}


# ------------------------------------------------------------------------------------------ runs


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(REPO_ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}


def _timed(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO_ROOT, env=_env(), capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
    return time.perf_counter() - t0


def _models(out: Path) -> list[int]:
    rep = json.loads((out / "report.json").read_text())
    return [m["registered_images"] for m in rep["models"]]


def run_kit(photos: Path, calibration: Path | None, work: Path) -> dict:
    """The kit's two commands as whole processes: poses by image name, seconds of each."""
    py = sys.executable
    cmd = [py, "-m", "course_lib", "match", str(photos), "--out", str(work / "p3"), "--quiet"]
    if calibration is not None:
        cmd += ["--K", str(calibration)]
    t_match = _timed(cmd)
    try:
        t_sfm = _timed([py, "-m", "course_lib", "sfm", str(work / "p3"), "--out", str(work / "sfm"), "--quiet", "--no-html"])
    except RuntimeError as exc:  # no pair can start a model
        return {"poses": {}, "points": 0, "models": [], "seconds": t_match, "match_s": t_match, "sfm_s": float("nan"),
                "note": str(exc).splitlines()[-1][:120]}
    model = read_colmap_text(work / "sfm" / "colmap")
    report = json.loads((work / "p3" / "match_report.json").read_text())
    source = {im["p3_name"]: im["source"] for im in report["images"]}  # sfm names the images as the photos are named
    poses = {source.get(n, n): (R, t) for n, R, t in zip(model.image_names, model.R_cw, model.t_cw)}
    return {"poses": poses, "points": int(len(model.X)), "models": _models(work / "sfm"), "seconds": t_match + t_sfm,
            "match_s": t_match, "sfm_s": t_sfm, "focal": float(model.K[0, 0]), "k1": float(getattr(model, "k1", 0.0)),
            "stages": _kit_stages(report, json.loads((work / "sfm" / "report.json").read_text()))}


def _kit_stages(match_report: dict, sfm_report: dict) -> dict:
    """The kit's seconds by stage, as the processes measured them: ``match`` (load, features, pairs, verification,
    tracks, write) and ``sfm`` (pair checks and self-calibration, initial pair, registration, final BA, the mappings a
    focal restart abandoned)."""
    m, f = match_report.get("stage_seconds", {}), sfm_report.get("seconds", {})
    out = {"load": m.get("load"), "features": m.get("features"), "pairs": m.get("matching"),
           "verification": m.get("verification"), "tracks": (m.get("tracks") or 0) + (m.get("write") or 0),
           "sfm pairs": f.get("ransac_F"), "init": f.get("initial_pair"), "register": f.get("registration"),
           "final BA": f.get("final_ba"), "restarts": f.get("focal_restarts")}
    return {k: v for k, v in out.items() if v is not None}


def run_colmap(photos: Path, calibration: Path | None, work: Path, seed: int = 0) -> dict:
    """COLMAP end to end as one process of this script (``--colmap-worker``)."""
    out = work / "colmap.json"
    cmd = [sys.executable, str(Path(__file__).resolve()), "--colmap-worker", str(photos), str(work / "colmap"), str(out),
           "--seed", str(seed)]
    if calibration is not None:
        cmd += ["--K", str(calibration)]
    seconds = _timed(cmd)
    res = json.loads(out.read_text())
    return {"poses": {n: (np.array(R), np.array(t)) for n, (R, t) in res["poses"].items()}, "points": res["points"],
            "models": res["models"], "seconds": seconds, "focal": res.get("focal"), "k1": res.get("k1"),
            "stages": res.get("stages", {})}


def colmap_worker(photos: Path, work: Path, out: Path, calibration: Path | None, seed: int) -> None:
    """The COLMAP process: its SIFT, exhaustive matching and verification, incremental mapping; poses to ``out``."""
    import pycolmap

    from course_lib.data.cli_match import list_images
    from course_lib.data.p3 import read_calibration

    pycolmap.logging.minloglevel = 2
    pycolmap.set_random_seed(seed)
    work.mkdir(parents=True, exist_ok=True)
    names = [p.name for p in list_images(photos)]
    db = work / "database.db"
    reader = pycolmap.ImageReaderOptions()
    opts = pycolmap.IncrementalPipelineOptions()
    opts.random_seed = seed
    if calibration is not None:
        K = read_calibration(calibration)
        reader.camera_model = "PINHOLE"  # COLMAP's pixel centres are at +0.5
        reader.camera_params = ",".join(str(v) for v in (K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5))
        opts.ba_refine_focal_length = opts.ba_refine_principal_point = opts.ba_refine_extra_params = False
    t0 = time.perf_counter()
    pycolmap.extract_features(db, photos, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader)
    t1 = time.perf_counter()
    tvg = pycolmap.TwoViewGeometryOptions()
    tvg.ransac.random_seed = seed
    pycolmap.match_exhaustive(db, verification_options=tvg)  # matching and verification in one call
    t2 = time.perf_counter()
    recs = pycolmap.incremental_mapping(str(db), str(photos), str(work / "sparse"), opts)
    t3 = time.perf_counter()
    res = {"poses": {}, "points": 0, "models": sorted((int(r.num_reg_images()) for r in recs.values()), reverse=True),
           "stages": {"features": round(t1 - t0, 3), "pairs + verification": round(t2 - t1, 3), "mapping": round(t3 - t2, 3)}}
    if recs:
        rec = max(recs.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))
        for im in rec.images.values():
            if im.has_pose:
                pose = im.cam_from_world()
                res["poses"][im.name] = (pose.rotation.matrix().tolist(), pose.translation.tolist())
        cam = next(iter(rec.cameras.values()))
        res.update(points=int(rec.num_points3D()), focal=float(cam.params[0]),
                   k1=float(cam.params[3]) if cam.model.name == "SIMPLE_RADIAL" else 0.0)
    out.write_text(json.dumps(res))


def score(run: dict, names: list[str], R_ref, t_ref) -> dict:
    """Registered images and rotation errors (degrees) after a similarity alignment with the reference poses."""
    have = [k for k, n in enumerate(names) if n in run["poses"] and R_ref is not None and np.isfinite(R_ref[k]).all()]
    row = {"registered": len(run["poses"]), "models": run["models"], "points": run["points"], "seconds": run["seconds"]}
    if len(have) >= 3:
        R = np.stack([run["poses"][names[k]][0] for k in have])
        t = np.stack([run["poses"][names[k]][1] for k in have])
        err = pose_errors(R, t, R_ref[have], t_ref[have])
        row.update(rot_mean_deg=float(err.rotation_deg.mean()), rot_max_deg=float(err.rotation_deg.max()))
    return row


def _has_exif(photos: Path) -> bool:
    from PIL import Image

    from course_lib.data.cli_match import list_images

    with Image.open(list_images(photos)[0]) as im:
        return bool(im.getexif())


def _without_exif(photos: Path, out: Path) -> Path:
    """The photos copied without EXIF (JPEG: the APP1 segments dropped, pixels untouched); other files left out."""
    from course_lib.data.cli_match import find_images

    out.mkdir(parents=True, exist_ok=True)
    found = find_images(photos)
    for p, name in zip(found.paths, found.names):
        data = p.read_bytes()
        if data[:2] == b"\xff\xd8":
            keep, k = [data[:2]], 2
            while k + 4 <= len(data) and data[k] == 0xFF and data[k + 1] != 0xDA:  # up to the start of scan
                n = int.from_bytes(data[k + 2:k + 4], "big")
                if data[k + 1] != 0xE1:  # APP1: EXIF (and XMP)
                    keep.append(data[k:k + 2 + n])
                k += 2 + n
            data = b"".join(keep) + data[k:]
        (out / name).write_bytes(data)
    return out


def compare(name: str, cache: Path, seed: int = 0, uncalibrated: bool = True) -> list[dict]:
    """Every run on one photo set; rows for the table."""
    from course_lib.data.cli_match import list_images

    ps = build_set(name, cache)
    if not ps:
        print(f"{name}: the course data is not on this machine (skipped)", flush=True)
        return []
    names = [p.name for p in list_images(ps["photos"])]
    runs = {}
    with tempfile.TemporaryDirectory(prefix="photos-to-sfm-") as tmp:
        tmp = Path(tmp)
        runs["COLMAP"] = run_colmap(ps["photos"], ps["calibration"], tmp / "c", seed)
        runs["kit"] = run_kit(ps["photos"], ps["calibration"], tmp / "k")
        if ps["calibration"] is None and ps["K"] is not None:  # the reference for a run without K: the photos with the true K
            true_k = tmp / "true_K.txt"
            np.savetxt(true_k, ps["K"])
            runs["kit, true K"] = run_kit(ps["photos"], true_k, tmp / "kt")
        if uncalibrated and (ps["calibration"] is not None or _has_exif(ps["photos"])):
            bare = _without_exif(ps["photos"], tmp / "bare")
            runs["COLMAP, no K"] = run_colmap(bare, None, tmp / "cb", seed)
            runs["kit, no K"] = run_kit(bare, None, tmp / "kb")
    truth = ps["R"] is not None
    if truth:
        R_ref, t_ref = ps["R"], ps["t"]
    else:
        c = runs["COLMAP"]["poses"]
        R_ref = np.stack([c[n][0] if n in c else np.full((3, 3), np.nan) for n in names])
        t_ref = np.stack([c[n][1] if n in c else np.full(3, np.nan) for n in names])
    rows = []
    for label, run in runs.items():
        row = {"set": name, "run": label, "images": len(names), **score(run, names, R_ref, t_ref),
               "vs": "truth" if truth else "COLMAP", "focal_px": run.get("focal"), "k1": run.get("k1"),
               "true_focal_px": None if ps["K"] is None else float(ps["K"][0, 0])}
        if not truth and label.startswith("COLMAP"):
            row.pop("rot_mean_deg", None), row.pop("rot_max_deg", None)
        for k in ("match_s", "sfm_s", "note", "stages"):
            if k in run:
                row[k] = run[k]
        rows.append(row)
    col = {r["run"]: r["seconds"] for r in rows if r["run"].startswith("COLMAP")}
    for r in rows:  # a run without K against COLMAP's without K
        r["time_vs_colmap"] = r["seconds"] / col.get("COLMAP, no K" if r["run"].endswith("no K") else "COLMAP", col["COLMAP"])
        if r.get("focal_px") and r.get("true_focal_px"):
            r["focal_error_pct"] = 100.0 * (r["focal_px"] / r["true_focal_px"] - 1.0)
    return rows


def print_rows(rows: list[dict]) -> None:
    print(f"{'set':<15}{'run':<15}{'registered':>11}{'models':>12}{'points':>8}{'rot mean':>10}{'rot max':>9}{'vs':>7}"
          f"{'focal':>9}{'f err':>8}{'seconds':>9}{'x COLMAP':>9}  match + sfm", flush=True)
    for r in rows:
        rot = f"{r['rot_mean_deg']:.3f}" if "rot_mean_deg" in r else "-"
        rmax = f"{r['rot_max_deg']:.3f}" if "rot_max_deg" in r else "-"
        models = "+".join(map(str, r["models"])) or "-"
        focal = f"{r['focal_px']:.1f}" if r.get("focal_px") else "-"
        ferr = f"{r['focal_error_pct']:+.1f}%" if "focal_error_pct" in r else "-"
        split = f"{r['match_s']:.1f} + {r['sfm_s']:.1f}" if "match_s" in r else ""
        print(f"{r['set']:<15}{r['run']:<15}{r['registered']:>5}/{r['images']:<5}{models:>12}{r['points']:>8}{rot:>10}{rmax:>9}"
              f"{r['vs']:>7}{focal:>9}{ferr:>8}{r['seconds']:>9.1f}{r['time_vs_colmap']:>9.2f}  {split}"
              + (f"  ({r['note']})" if r.get("note") else ""), flush=True)
        if r.get("stages"):  # seconds by stage, as the process measured them (the rest: start-up, imports)
            print(f"{'':<30}stages: " + ", ".join(f"{k} {v:.2f}" for k, v in r["stages"].items()), flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sets", nargs="*", default=["ring-16", "ring-48", "ring-100", "poor-ring-24", "exif5-ring-24",
                                                  "phone-ring-16", "wpi", "upenn"], help="photo sets (see the module docstring)")
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE, help=f"where rendered sets are kept (default {DEFAULT_CACHE})")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    ap.add_argument("--no-uncalibrated", action="store_true", help="leave out the runs without calibration file and EXIF")
    ap.add_argument("--colmap-worker", nargs=3, metavar=("PHOTOS", "WORKDIR", "OUT_JSON"), help=argparse.SUPPRESS)
    ap.add_argument("--K", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.colmap_worker:
        photos, work, out = (Path(v) for v in args.colmap_worker)
        colmap_worker(photos, work, out, args.K, args.seed)
        return 0
    rows = []
    for name in args.sets:
        new = compare(name, args.cache, args.seed, not args.no_uncalibrated)
        print_rows(new)
        rows += new
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Photos -> ``match`` -> ``sfm``, the way a student runs it, scored against the true cameras.

Renders a fresh photo set of the synthetic building (:func:`course_lib.data.building.sfm_photos`:
another seed gives another walk past the building -- other distances, heights, aim and roll; the
same textured building), writes ``1.jpg ... N.jpg`` and ``calibration.txt`` into a temporary
folder (the true cameras stay in memory), then runs the two commands of the README as separate
processes::

    python -m course_lib match PHOTOS --K PHOTOS/calibration.txt --out P3
    python -m course_lib sfm P3 --out SFM

and reports the registered images and the rotation / centre errors of the COLMAP model it wrote
after a similarity alignment on rotations and centres (:func:`course_lib.evaluate.pose_errors`),
with the seconds of each command (process start included).

A folder of real photos works too (``--photos DIR --K calibration.txt``); without ground truth only
the registered count, points and reprojection error are reported.

Usage::

    python benchmarks/photos_to_sfm.py                    # 12 views, seed 7
    python benchmarks/photos_to_sfm.py --views 16 --seed 3
    python benchmarks/photos_to_sfm.py --photos ~/my_photos --K ~/my_photos/K.txt
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO_ROOT))

from course_lib.data.building import sfm_photos  # noqa: E402
from course_lib.data.colmap import read_colmap_text  # noqa: E402
from course_lib.evaluate import pose_errors  # noqa: E402


def render_photos(folder: Path, views: int, seed: int) -> dict:
    """Write ``1.jpg ... N.jpg``, ``calibration.txt``; return the true cameras by image name."""
    folder.mkdir(parents=True, exist_ok=True)
    photos = sfm_photos(seed=seed, n_cameras=views)
    K, R_cw, t_cw = next(photos)
    for i, (jpeg, _) in enumerate(photos):
        (folder / f"{i + 1}.jpg").write_bytes(jpeg)
    np.savetxt(folder / "calibration.txt", K, fmt="%.6f")
    return {f"{i + 1}": (R_cw[i], t_cw[i]) for i in range(views)}


def run(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO_ROOT, capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed:\n{proc.stdout}\n{proc.stderr}")
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--views", type=int, default=12, help="photos to render (default 12)")
    ap.add_argument("--seed", type=int, default=7, help="seed of the walk and the sensor noise (default 7)")
    ap.add_argument("--photos", type=Path, default=None, help="a folder of your own photos instead of rendered ones")
    ap.add_argument("--K", type=Path, default=None, help="calibration.txt of --photos")
    ap.add_argument("--json", type=Path, default=None, help="also write the result here")
    args = ap.parse_args()

    with tempfile.TemporaryDirectory(prefix="photos-to-sfm-") as tmp:
        tmp = Path(tmp)
        truth = None
        if args.photos is None:
            photos, K_file = tmp / "photos", tmp / "photos" / "calibration.txt"
            t0 = time.perf_counter()
            truth = render_photos(photos, args.views, args.seed)
            print(f"rendered {args.views} photos (seed {args.seed}) in {time.perf_counter() - t0:.1f} s")
        else:
            if args.K is None:
                sys.exit("--photos needs --K (the calibration file of the photos)")
            photos, K_file = args.photos, args.K
        py = sys.executable
        t_match = run([py, "-m", "course_lib", "match", str(photos), "--K", str(K_file), "--out", str(tmp / "p3")])
        t_sfm = run([py, "-m", "course_lib", "sfm", str(tmp / "p3"), "--out", str(tmp / "sfm"), "--quiet", "--no-html"])
        model = read_colmap_text(tmp / "sfm" / "colmap")
        n_photos = len(list((tmp / "p3").glob("matching*.txt"))) + 1
        result = {
            "photos": n_photos, "registered": len(model.image_names), "points": int(len(model.X)),
            "reprojection_px": float(np.mean(model.error)) if len(model.error) else float("nan"),
            "match_s": round(t_match, 2), "sfm_s": round(t_sfm, 2),
        }
        if truth is not None:
            keys = [Path(n).stem for n in model.image_names]
            err = pose_errors(model.R_cw, model.t_cw, np.stack([truth[k][0] for k in keys]),
                              np.stack([truth[k][1] for k in keys]))
            result.update(rot_mean_deg=float(err.rotation_deg.mean()), rot_max_deg=float(err.rotation_deg.max()),
                          centre_mean_m=float(err.center.mean()), centre_max_m=float(err.center.max()))
    print(f"registered {result['registered']}/{result['photos']}, {result['points']} points, "
          f"mean reprojection error {result['reprojection_px']:.3f} px; match {result['match_s']:.1f} s, sfm {result['sfm_s']:.1f} s")
    if "rot_mean_deg" in result:
        print(f"after alignment: rotation error mean {result['rot_mean_deg']:.3f} deg, max {result['rot_max_deg']:.3f} deg; "
              f"centre error mean {100 * result['centre_mean_m']:.1f} cm, max {100 * result['centre_max_m']:.1f} cm "
              f"(cameras 9.5-13.5 m from the building)")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()

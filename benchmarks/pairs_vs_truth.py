"""Which verified pairs of a rendered photo set are right: the kit's pair checks against the true cameras.

For a set of ``benchmarks/photos_to_sfm.py`` (rendered into its cache, with the true poses, K and
``k1`` in ``truth.npz``), ``match`` is run once and every matched pair is checked:

* ``F inliers``: OpenCV's F-RANSAC at 2 px on the matches (what ``match`` verifies);
* ``right``: how many of those fit the *true* epipolar geometry (Sampson distance under 3 px on
  pixels undistorted with the true ``k1``); a pair where fewer than half do is **wrong**
  (look-alike texture matched across different parts of the scene);
* ``E/F``: the share of F's inliers that the five-point E explains
  (:func:`course_lib.sfm.tracks.calibrated_check`, the check ``sfm`` applies with
  ``min_e_f_inlier_ratio``);
* ``rotation``: how far the pair's five-point relative rotation
  (:func:`course_lib.sfm.initial_pair.calibrated_pose`, what the structure-less registration
  starts from) is from the true one, in degrees.

Printed: the right and wrong pairs by their E/F share, how many of each a threshold keeps, and the
wrong pairs that pass it. Usage::

    python benchmarks/pairs_vs_truth.py phone-ring-16
    python benchmarks/pairs_vs_truth.py exif5-ring-24 --threshold 0.9 --rows
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO_ROOT))

from course_lib.data.camera import undistort_pixels  # noqa: E402
from course_lib.conventions import rotation_angle_deg  # noqa: E402
from course_lib.data.p3 import read_p3  # noqa: E402
from course_lib.sfm.initial_pair import calibrated_pose  # noqa: E402
from course_lib.validate import KitInputError  # noqa: E402
from course_lib.sfm.tracks import calibrated_check  # noqa: E402


def _skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def pair_rows(photos: Path, work: Path) -> list[dict]:
    """One row per matched pair: images (1-based, as the photos are numbered), matches, F inliers, right ones, E/F."""
    import cv2

    z = np.load(photos / "truth.npz")
    K, R, t, k1 = z["K"], z["R"], z["t"], float(z["k1"])
    cmd = [sys.executable, "-m", "course_lib", "match", str(photos), "--out", str(work / "p3"), "--quiet"]
    if (photos / "calibration.txt").is_file():
        cmd += ["--K", str(photos / "calibration.txt")]
    subprocess.run(cmd, check=True, cwd=REPO_ROOT)
    data = read_p3(work / "p3")
    sources = [im["source"] for im in json.loads((work / "p3" / "match_report.json").read_text())["images"]]
    index = [int("".join(c for c in Path(s).stem if c.isdigit())) - 1 for s in sources]
    Ki = np.linalg.inv(K)
    rows = []
    for (a, b), pm in sorted(data.matches.items()):
        A, B = index[a], index[b]
        R_ab = R[B] @ R[A].T
        F_true = Ki.T @ _skew(t[B] - R_ab @ t[A]) @ R_ab @ Ki
        h1 = np.c_[undistort_pixels(pm.x1, K, k1), np.ones(len(pm.x1))]
        h2 = np.c_[undistort_pixels(pm.x2, K, k1), np.ones(len(pm.x2))]
        Fx1, Ftx2 = h1 @ F_true.T, h2 @ F_true
        sampson = np.abs(np.sum(h2 * Fx1, 1)) / np.sqrt(Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2)
        F, mask = cv2.findFundamentalMat(pm.x1, pm.x2, cv2.FM_RANSAC, 2.0, 0.999, 2000)
        if F is None:
            continue
        inl = mask.ravel().astype(bool)
        _, share = calibrated_check(pm.x1[inl], pm.x2[inl], data.K, 2.0, 0)
        try:
            rotation = rotation_angle_deg(calibrated_pose(pm.x1[inl], pm.x2[inl], data.K, 4.0, 0)[0].R_cw, R_ab)
        except KitInputError:
            rotation = float("nan")
        rows.append({"pair": (A + 1, B + 1), "matches": len(pm.x1), "f_inliers": int(inl.sum()),
                     "right": int((inl & (sampson < 3.0)).sum()), "e_f": round(float(share), 3),
                     "rotation_deg": round(float(rotation), 2)})
    return rows


def main(argv=None) -> int:
    sys.path.insert(0, str(REPO_ROOT / "benchmarks"))
    from photos_to_sfm import DEFAULT_CACHE, build_set

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("set", help="a rendered set of benchmarks/photos_to_sfm.py, e.g. phone-ring-16")
    ap.add_argument("--threshold", type=float, default=0.9, help="the min_e_f_inlier_ratio to weigh (default 0.9)")
    ap.add_argument("--rows", action="store_true", help="also print every pair")
    args = ap.parse_args(argv)
    photos = build_set(args.set, DEFAULT_CACHE)["photos"]
    with tempfile.TemporaryDirectory() as tmp:
        rows = pair_rows(Path(photos), Path(tmp))
    for r in rows:
        r["wrong"] = r["right"] < 0.5 * r["f_inliers"]
    if args.rows:
        print("pair      matches  F inliers  right  E/F  rotation")
        for r in rows:
            print(f"{r['pair'][0]:>3}-{r['pair'][1]:<4} {r['matches']:>8} {r['f_inliers']:>10} {r['right']:>6}  {r['e_f']:.2f}"
                  f" {r['rotation_deg']:>8.2f}" + ("  wrong" if r["wrong"] else ""))
    for kind, sel in (("right", [r for r in rows if not r["wrong"]]), ("wrong", [r for r in rows if r["wrong"]])):
        ef = np.array([r["e_f"] for r in sel])
        kept = int((ef >= args.threshold).sum())
        rot = np.array([r["rotation_deg"] for r in sel])
        rot = rot[np.isfinite(rot)]
        if len(rot):
            print(f"{kind} pairs: five-point rotation off the truth by {np.percentile(rot, 10):.1f} / {np.median(rot):.1f} / "
                  f"{np.percentile(rot, 90):.1f} deg (10th percentile / median / 90th)")
        print(f"{kind} pairs: {len(sel)}; E/F median {np.median(ef) if len(ef) else float('nan'):.2f}, range "
              f"{ef.min() if len(ef) else float('nan'):.2f}-{ef.max() if len(ef) else float('nan'):.2f}; kept at {args.threshold}: {kept}; "
              f"F inliers {min((r['f_inliers'] for r in sel), default=0)}-{max((r['f_inliers'] for r in sel), default=0)}")
    lost = [r for r in rows if not r["wrong"] and r["e_f"] < args.threshold]
    passed = [r for r in rows if r["wrong"] and r["e_f"] >= args.threshold]
    print("right pairs dropped: " + (", ".join(f"{a}-{b} ({r['right']}/{r['f_inliers']} right, E/F {r['e_f']:.2f})"
                                               for r in lost for a, b in [r["pair"]]) or "none"))
    print("wrong pairs kept: " + (", ".join(f"{a}-{b} ({r['right']}/{r['f_inliers']} right, E/F {r['e_f']:.2f})"
                                            for r in passed for a, b in [r["pair"]]) or "none"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""``python -m course_lib match IMAGES_DIR --K calibration.txt --out P3_DIR``: your own photos -> P3 matches.

Turns any set of photos taken with one camera of known intrinsics K into the P3 folder that the
SfM lessons read (:mod:`course_lib.data.p3`), so a student's own photos become course data:

1. **Which images.** If ``IMAGES_DIR`` holds images named like the P3 convention (``1.png``,
   ``2.jpg``, ... numbered from 1 without gaps) *only those* are read, in numeric order, and
   every other file beside them is ignored (the course folders hold ``matching*.txt`` and other
   files too). Otherwise *all* image files (``.png .jpg .jpeg .bmp .tif .tiff``, any case) are
   read in natural name order (``IMG_2.jpg`` before ``IMG_10.jpg``). Either way the output names
   them ``1.png ... M.png`` and ``match_report.json`` maps them back to the source files.
2. **Same size.** All images must have the same size (one camera, one K).
3. **Optional downscaling** by a factor ``F >= 1`` (``cv2.INTER_AREA``). K follows with the kit's
   pixel convention (centre of the top-left pixel at (0, 0)): for an image resized from W to
   W' = round(W / F) pixels, ``s = W' / W`` and ``u' = s (u + 0.5) - 0.5``, so
   ``fx' = s fx`` and ``cx' = s (cx + 0.5) - 0.5`` (likewise ``fy, cy`` with H' / H).
4. **SIFT + ratio test across all pairs**, with
   :func:`course_lib.data.features.detect_and_match` (OpenCV SIFT, Lowe's ratio, mutual nearest
   neighbour, the +0.25 px SIFT offset corrected) -- the same code that made the embedded scene,
   here with COLMAP's SIFT settings (:data:`CONTRAST_THRESHOLD`, RootSIFT, at most 8192 features).
5. **Geometric verification** of every pair (new here): a fundamental matrix is fitted by
   RANSAC (OpenCV's, seeded, threshold ``--verify-px``, default :data:`VERIFY_PX` = 4 px as COLMAP's; see
   :func:`course_lib.data.features.keep_geometric_inliers`) and only its
   inliers are kept; pairs with fewer than
   ``--min-pair-matches`` inliers are dropped. Without it, one wrong match between two
   otherwise separate features joins their tracks, and with many views the reader's
   inconsistency rule then drops thousands of good observations (40 views of the synthetic
   building: 961 tracks and 10 227 dropped observations without it). ``--no-verify`` turns it off.
6. **Tracks** are joined by :func:`course_lib.data.p3.tracks_from_pairs` (the rule of
   :func:`~course_lib.data.p3.read_p3`) and written with :func:`~course_lib.data.p3.write_p3`
   together with ``calibration.txt`` (the possibly scaled K) and the images as PNG.

Bad input (a missing folder, fewer than 2 images, an unreadable image, images of different
sizes, a missing or malformed K) raises :class:`~course_lib.validate.KitInputError`, which the
command line turns into a one-line message.

Introduced in ``notebooks/10_photos_to_nerf.ipynb``.
"""

from __future__ import annotations

import argparse
import json
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from course_lib.validate import KitInputError, intrinsics, output_dir

__all__ = ["IMAGE_SUFFIXES", "MatchResult", "list_images", "load_images", "scale_intrinsics", "downscale_images",
           "match_images", "match_folder", "add_arguments", "run"]

#: SIFT settings of ``match``: COLMAP's defaults (``SiftExtractionOptions``). Its ``peak_threshold``
#: 0.02 / 3 is OpenCV's ``contrastThreshold`` 0.02 (OpenCV's own default, 0.04, keeps half as many
#: weak extrema: on a texture-poor 16-view ring COLMAP's mapper registered 0 views from those matches,
#: 4 from these, as from COLMAP's own; ``benchmarks/match_vs_colmap.py``), RootSIFT descriptors
#: (``normalization = L1_ROOT``) and at most 8192 features per image.
CONTRAST_THRESHOLD = 0.02
ROOTSIFT = True
MAX_FEATURES = 8192
#: Threshold (pixels) of the geometric verification: COLMAP's ``TwoViewGeometryOptions.ransac.max_error``
#: 4 px. At 2 px the F-RANSAC of the 1280x960 UPenn photos dropped good matches unevenly (7043 kept
#: instead of 7912), and COLMAP's mapper on those matches ended 0.8-1.0 deg from COLMAP's own result
#: (0.04 deg at 4 px, on two seeds); the kit's own sfm agrees better with COLMAP at 4 px on WPI
#: (0.085 deg, 0.119 at 2 px) and UPenn (0.062, 0.067), and on the texture-poor ring it has
#: 0.33 deg of rotation error at 4 px (0.44 at 2 px; COLMAP end to end 0.45).
VERIFY_PX = 4.0

#: File suffixes read as images (case-insensitive).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
_P3_NAME = re.compile(r"^(\d+)$")


def _natural_key(p: Path):
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", p.name)]


def list_images(folder) -> list[Path]:
    """The image files of a folder, by the rule of the module docstring (P3 names first, else all).

    Args:
        folder: a folder of photos.

    Returns:
        M paths in order (P3-numbered ``1.*, 2.*, ...`` if present, else natural name order).

    Raises:
        KitInputError: not a folder, fewer than 2 images, or P3 numbers with a gap / a duplicate.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise KitInputError(f"image folder not found: {folder} (pass a folder that holds your photos)")
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    numbered: dict[int, list[Path]] = {}
    for p in files:
        m = _P3_NAME.match(p.stem)
        if m:
            numbered.setdefault(int(m.group(1)), []).append(p)
    if numbered:
        ids = sorted(numbered)
        dup = [i for i in ids if len(numbered[i]) > 1]
        if dup:
            names = ", ".join(p.name for p in sorted(numbered[dup[0]]))
            raise KitInputError(f"{folder}: image number {dup[0]} exists twice ({names}); keep one file per number")
        if ids != list(range(1, len(ids) + 1)):
            missing = sorted(set(range(1, ids[-1] + 1)) - set(ids))
            raise KitInputError(f"{folder}: P3-numbered images must run 1, 2, ... without gaps; missing {missing[:5]} "
                                "(rename the files, or give them non-numeric names to use all images in name order)")
        out = [numbered[i][0] for i in ids]
    else:
        out = sorted(files, key=_natural_key)
    if len(out) < 2:
        raise KitInputError(f"{folder} holds {len(out)} image(s) ({', '.join(IMAGE_SUFFIXES)}): matching needs at least 2")
    return out


def load_images(paths) -> list[np.ndarray]:
    """Read images as ``(H, W, 3)`` uint8 RGB and check that they all have the same size.

    Raises:
        KitInputError: an unreadable file or images of different sizes.
    """
    import cv2

    images = []
    for p in paths:
        bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if bgr is None:
            raise KitInputError(f"cannot read the image {p}: is it a valid image file (PNG, JPEG, ...)?")
        images.append(np.ascontiguousarray(bgr[:, :, ::-1]))
    sizes = [im.shape[:2] for im in images]
    for p, s in zip(paths, sizes):
        if s != sizes[0]:
            raise KitInputError(f"{Path(p).name} is {s[1]}x{s[0]} but {Path(paths[0]).name} is {sizes[0][1]}x{sizes[0][0]}: "
                                "all photos must come from one camera at one size (one K); resize or drop the odd ones")
    return images


def scale_intrinsics(K, src_size: tuple[int, int], dst_size: tuple[int, int]) -> np.ndarray:
    """K of an image resized from ``src_size`` to ``dst_size`` (both ``(W, H)``), kit pixel convention.

    ``u' = sx (u + 0.5) - 0.5`` with ``sx = W' / W`` (pixel centres at integers), so
    ``fx' = sx fx``, ``cx' = sx (cx + 0.5) - 0.5``; likewise for y.

    Returns:
        ``(3, 3)`` the scaled K.
    """
    K = intrinsics(K)
    sx, sy = dst_size[0] / src_size[0], dst_size[1] / src_size[1]
    A = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
    return A @ K


def downscale_images(images: list[np.ndarray], K, factor: float) -> tuple[list[np.ndarray], np.ndarray]:
    """Shrink every image by ``factor`` (``cv2.INTER_AREA``) and scale K to match.

    Args:
        images: M ``(H, W, 3)`` uint8. K: ``(3, 3)``. factor: ``>= 1`` (1: unchanged).

    Returns:
        The resized images and the scaled ``(3, 3)`` K (:func:`scale_intrinsics`).
    """
    import cv2

    factor = float(factor)
    if not np.isfinite(factor) or factor < 1.0:
        raise KitInputError(f"downscale = {factor!r}: expected a factor >= 1 (2 halves the width and height)")
    K = intrinsics(K)
    if factor == 1.0:
        return list(images), K
    H, W = images[0].shape[:2]
    W2, H2 = max(int(round(W / factor)), 16), max(int(round(H / factor)), 16)
    out = [cv2.resize(im, (W2, H2), interpolation=cv2.INTER_AREA) for im in images]
    return out, scale_intrinsics(K, (W, H), (W2, H2))


@dataclass
class MatchResult:
    """Tracks of a set of photos, ready for :func:`course_lib.data.p3.write_p3`.

    Attributes:
        track_uv: ``(T, M, 2)`` pixels, NaN where unseen.
        track_rgb: ``(T, 3)`` uint8 colour at the track's first observation.
        raw_matches: ``{(i, j): N}`` SIFT matches per pair after the ratio test.
        verified_matches: ``{(i, j): N}`` after geometric verification (equal to raw without it).
        stats: track-building stats (inconsistent components, dropped observations).
    """

    track_uv: np.ndarray
    track_rgb: np.ndarray
    raw_matches: dict
    verified_matches: dict
    stats: dict = field(default_factory=dict)


def match_images(images: list[np.ndarray], ratio: float = 0.8, verify: bool = True, verify_px: float = VERIFY_PX,
                 min_pair_matches: int = 15, rng: np.random.Generator | None = None, rootsift: bool = ROOTSIFT,
                 max_features: int = MAX_FEATURES, contrast_threshold: float = CONTRAST_THRESHOLD) -> MatchResult:
    """SIFT matches of all pairs (ratio test), optionally verified by an F-RANSAC, joined into tracks.

    Args:
        images: M >= 2 ``(H, W, 3)`` uint8 RGB images of one size.
        ratio: Lowe's ratio in (0, 1].
        verify: geometric verification of each pair (:func:`course_lib.data.features.keep_geometric_inliers`).
        verify_px, min_pair_matches: its threshold and the fewest inliers a pair keeps.
        rng: generator for RANSAC (default: seed 0).
        rootsift, max_features, contrast_threshold: see :func:`course_lib.data.features.detect_features`.

    Returns:
        :class:`MatchResult`.

    Introduced in ``notebooks/10_photos_to_nerf.ipynb``.
    """
    from course_lib.data.features import check_ratio, detect_and_match, keep_geometric_inliers, track_colours
    from course_lib.data.p3 import tracks_from_pairs

    if len(images) < 2:
        raise KitInputError(f"{len(images)} image(s): matching needs at least 2")
    check_ratio(ratio)
    for k, im in enumerate(images):
        im = np.asarray(im)
        if im.dtype != np.uint8 or im.ndim != 3 or im.shape[2] != 3:
            raise KitInputError(f"image {k} has dtype {im.dtype} and shape {im.shape}: expected (H, W, 3) uint8 RGB")
        if im.shape != np.shape(images[0]):
            raise KitInputError(f"image {k} is {im.shape[1]}x{im.shape[0]} but image 0 is {images[0].shape[1]}x{images[0].shape[0]}: one size (one K) for all")
    rng = np.random.default_rng(0) if rng is None else rng
    pairs = detect_and_match(images, ratio, max_features, rootsift, contrast_threshold)
    raw = {k: len(v[0]) for k, v in pairs.items()}
    if verify:
        pairs, ver = keep_geometric_inliers(pairs, rng, verify_px, min_pair_matches)
    else:
        ver = dict(raw)
    M = len(images)
    track_uv, _, tstats = tracks_from_pairs(M, pairs)
    track_rgb = track_colours(track_uv, images)
    return MatchResult(track_uv, track_rgb, raw, ver, dict(tstats))


def match_folder(images_dir, K, out, downscale: float = 1.0, ratio: float = 0.8, verify: bool = True,
                 verify_px: float = VERIFY_PX, min_pair_matches: int = 15, seed: int = 0, rootsift: bool = ROOTSIFT,
                 max_features: int = MAX_FEATURES, contrast_threshold: float = CONTRAST_THRESHOLD) -> dict:
    """Match a folder of photos and write a P3 folder (the ``match`` command).

    Args:
        images_dir: folder of photos (:func:`list_images` says which files are read).
        K: ``(3, 3)`` intrinsics of the full-size photos, or the path of a ``calibration.txt``.
        out: output P3 folder (created; must not be ``images_dir``).
        downscale: factor >= 1 (K is scaled, see :func:`scale_intrinsics`).
        ratio, verify, verify_px, min_pair_matches, seed, rootsift, max_features, contrast_threshold:
            see :func:`match_images`.

    Returns:
        The report written to ``out/match_report.json``.

    Introduced in ``notebooks/10_photos_to_nerf.ipynb``.
    """
    from course_lib.data.p3 import read_calibration, write_p3

    t0 = time.perf_counter()
    paths = list_images(images_dir)
    if isinstance(K, (str, Path)):
        if not Path(K).exists():
            raise KitInputError(f"calibration file not found: {K} (pass --K with a file of 3 rows of 3 numbers: the camera's K)")
        K = read_calibration(K)
    K = intrinsics(K)
    out = Path(out)
    if out.resolve() == Path(images_dir).resolve():
        raise KitInputError(f"--out {out} is the image folder itself: write the P3 folder somewhere else")
    out = output_dir(out)
    images = load_images(paths)
    H0, W0 = images[0].shape[:2]
    images, K2 = downscale_images(images, K, downscale)
    res = match_images(images, ratio, verify, verify_px, min_pair_matches, np.random.default_rng(seed),
                       rootsift=rootsift, max_features=max_features, contrast_threshold=contrast_threshold)
    names = [f"{i + 1}.png" for i in range(len(images))]
    write_p3(out, names, K2, res.track_uv, res.track_rgb, images=images)
    n_obs = (~np.isnan(res.track_uv[..., 0])).sum(1) if len(res.track_uv) else np.zeros(0, int)
    report = {
        "images_dir": str(images_dir),
        "images": [{"p3_name": n, "source": p.name} for n, p in zip(names, paths)],
        "image_size_source": [W0, H0],
        "image_size": [int(images[0].shape[1]), int(images[0].shape[0])],
        "downscale": float(downscale),
        "K_source": K.tolist(),
        "K": K2.tolist(),
        "ratio": float(ratio), "rootsift": bool(rootsift), "max_features": int(max_features),
        "contrast_threshold": float(contrast_threshold),
        "verify": bool(verify), "verify_px": float(verify_px), "min_pair_matches": int(min_pair_matches), "seed": int(seed),
        "pairs": {f"{i + 1}-{j + 1}": {"sift": res.raw_matches[(i, j)], "verified": res.verified_matches.get((i, j), 0)}
                  for (i, j) in sorted(res.raw_matches)},
        "tracks": int(len(res.track_uv)),
        "observations": int(n_obs.sum()),
        "tracks_by_length": {str(k): int((n_obs == k).sum()) for k in sorted(set(n_obs.tolist()))},
        **{k: v for k, v in res.stats.items() if isinstance(v, (int, float))},
        "seconds": round(time.perf_counter() - t0, 2),
    }
    (out / "match_report.json").write_text(json.dumps(report, indent=1))
    return report


# --------------------------------------------------------------------------------------------- CLI


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("images_dir", help="folder of photos: only 1.png, 2.png, ... (P3 numbering) if there are such files, else all images in name order")
    p.add_argument("--K", required=True, help="calibration file of the full-size photos: 3 rows of 3 numbers, or 'K = [a b c; d e f; g h i]'")
    p.add_argument("--out", required=True, help="output P3 folder (calibration.txt, matching*.txt, 1.png ...; match_report.json)")
    p.add_argument("--downscale", type=float, default=1.0, help="shrink the photos by this factor first (K is scaled; default 1)")
    p.add_argument("--ratio", type=float, default=0.8, help="Lowe's ratio test (default 0.8)")
    p.add_argument("--verify-px", type=float, default=VERIFY_PX,
                   help=f"F-RANSAC threshold of the geometric verification, pixels (default {VERIFY_PX:g}, COLMAP's)")
    p.add_argument("--min-pair-matches", type=int, default=15, help="pairs with fewer verified matches are dropped (default 15)")
    p.add_argument("--no-verify", action="store_true", help="keep all ratio-test matches (no geometric verification)")
    p.add_argument("--seed", type=int, default=0, help="seed of the verification's RANSAC (default 0)")
    p.add_argument("--contrast-threshold", type=float, default=CONTRAST_THRESHOLD,
                   help=f"SIFT contrast threshold (OpenCV's contrastThreshold; default {CONTRAST_THRESHOLD}, COLMAP's; OpenCV's own 0.04 finds fewer features)")
    p.add_argument("--max-features", type=int, default=MAX_FEATURES,
                   help=f"keep at most this many SIFT features per photo (default {MAX_FEATURES}, COLMAP's; 0: all)")
    p.add_argument("--no-rootsift", action="store_true", help="match plain SIFT descriptors instead of RootSIFT")


def run(args) -> int:
    rep = match_folder(args.images_dir, args.K, args.out, args.downscale, args.ratio, not args.no_verify,
                       args.verify_px, args.min_pair_matches, args.seed, rootsift=not args.no_rootsift,
                       max_features=args.max_features, contrast_threshold=args.contrast_threshold)
    n = len(rep["images"])
    kept = sum(1 for v in rep["pairs"].values() if v["verified"] >= args.min_pair_matches or (args.no_verify and v["sift"]))
    print(f"matched {n} images ({rep['image_size'][0]}x{rep['image_size'][1]}): {kept}/{n * (n - 1) // 2} pairs kept, "
          f"{rep['tracks']} tracks, {rep['observations']} observations, {rep['seconds']:.1f} s")
    print(f"P3 folder: {args.out} (read it with course_lib.data.p3.read_p3, or run: python -m course_lib sfm {args.out})")
    return 0

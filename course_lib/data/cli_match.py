"""``python -m course_lib match IMAGES_DIR [--K calibration.txt] --out P3_DIR``: your own photos -> P3 matches.

Turns any set of photos taken with one camera into the P3 folder that the SfM lessons read
(:mod:`course_lib.data.p3`), so a student's own photos become course data:

1. **Which images** (:func:`find_images`): photos of any names. Where ``IMAGES_DIR`` holds numbered
   photos (names that are only a number: ``1.png``, ``0000.jpg``; from 0 or 1, gaps allowed) *only
   those* are read, in numeric order, and other images beside them are ignored and named (a course
   P3 folder, ``1.png ... N.png`` beside ``matching*.txt``, is read as it is). Otherwise *all* image
   files (``.png .jpg .jpeg .bmp .tif .tiff``, any case) are read in natural name order
   (``frame_2.png`` before ``frame_10.png``); ``--recursive`` reads the subfolders too. The P3 folder
   names them ``1.png ... M.png`` (or ``.jpg``), and :data:`course_lib.data.p3.SOURCE_NAMES_FILE`
   keeps the photos' own names, which ``sfm`` writes into its outputs (the COLMAP model,
   ``report.json``, ``scene.html``).
2. **Same size.** All images must have the same size (one camera, one K).
3. **The camera.** ``--K`` gives K (held fixed by ``sfm``). Without it, K comes from the photos'
   EXIF (focal length and sensor size, or the 35 mm equivalent) or COLMAP's guess (1.2 x the
   longer side), and ``sfm`` refines the focal length and one radial term (:mod:`course_lib.data.camera`;
   ``camera.json`` in the P3 folder says which).
4. **Optional downscaling** by a factor ``F >= 1`` (``cv2.INTER_AREA``). K follows with the kit's
   pixel convention (centre of the top-left pixel at (0, 0)): for an image resized from W to
   W' = round(W / F) pixels, ``s = W' / W`` and ``u' = s (u + 0.5) - 0.5``, so
   ``fx' = s fx`` and ``cx' = s (cx + 0.5) - 0.5`` (likewise ``fy, cy`` with H' / H).
5. **SIFT** (:func:`course_lib.data.features.detect_features`, OpenCV, the +0.25 px SIFT offset
   corrected) with COLMAP's settings (:data:`CONTRAST_THRESHOLD`, RootSIFT, at most 8192 features),
   several photos at once.
6. **Which pairs** (``--pairs``, :mod:`course_lib.data.pairing`): every pair up to 150 photos,
   above that each photo with the 30 that look most alike (image retrieval) and its 10 neighbours
   in file order; ``sequential`` for a video or a walk photographed in order.
7. **Matching** (:func:`course_lib.data.features.match_pairs`): Lowe's ratio test and mutual
   nearest neighbours, both from one matrix of descriptor distances per pair (BLAS), several pairs
   at once -- the code that made the embedded scene.
8. **Geometric verification** (:mod:`course_lib.data.two_view`): a fundamental matrix per pair by
   RANSAC (OpenCV's USAC, seeded, threshold ``--verify-px``, default :data:`VERIFY_PX` = 4 px as
   COLMAP's), only its inliers kept, pairs with fewer than ``--min-pair-matches`` inliers dropped;
   the pairs of a photo with few verified matches are matched a second time, along their
   epipolar lines (``--no-guided`` turns it off). Without verification, one wrong match between two
   otherwise separate features joins their tracks, and with many views the reader's
   inconsistency rule then drops thousands of good observations (40 views of the synthetic
   building: 961 tracks and 10 227 dropped observations without it). The verified pairs' F go
   into ``two_view_geometries.json``, which ``sfm`` uses instead of a RANSAC of its own.
   Identical or near-identical photos (no baseline) are named. ``--no-verify`` turns it off.
9. **Tracks** are joined by :func:`course_lib.data.tracks.join_tracks` (the most trusted matches
   first; a link that would put two features of one photo into one track is refused, so a wrong
   match splits a track instead of losing it: on a 48-view ring the reader's rule would have
   dropped 5 810 of 26 061 observations) and written with :func:`~course_lib.data.p3.write_p3`
   together with ``calibration.txt`` (the possibly scaled K). Photos that need no change are
   copied (PNG or JPEG without an EXIF rotation), the others written as PNG (fast compression).

Bad input (a missing folder, fewer than 2 images, an unreadable image, images of different
sizes, a malformed K, EXIF focal lengths that differ) raises
:class:`~course_lib.validate.KitInputError`, which the command line turns into a one-line message.

Introduced in ``notebooks/10_photos_to_nerf.ipynb``.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from course_lib.data.camera import CameraPrior, camera_prior, write_camera
from course_lib.data.features import check_ratio, detect_features, match_pairs, track_colours
from course_lib.data.p3 import IMAGE_EXTENSIONS, read_calibration, write_p3, write_source_names
from course_lib.data.pairing import PAIR_MODES, select_pairs
from course_lib.data.tracks import join_tracks
from course_lib.data.two_view import MIN_INLIERS, VERIFY_PX, epipolar_distances, verify_pairs, write_two_view_geometries
from course_lib.threads import thread_map
from course_lib.validate import KitInputError, intrinsics, output_dir

__all__ = ["IMAGE_SUFFIXES", "VERIFY_PX", "MatchResult", "ImageList", "find_images", "list_images", "load_images", "scale_intrinsics",
           "downscale_images", "match_images", "match_folder", "add_arguments", "run"]

#: SIFT settings of ``match``: COLMAP's defaults (``SiftExtractionOptions``). Its ``peak_threshold``
#: 0.02 / 3 is OpenCV's ``contrastThreshold`` 0.02 (OpenCV's own default, 0.04, keeps half as many
#: weak extrema: on a texture-poor 16-view ring COLMAP's mapper registered 0 views from those matches,
#: 4 from these, as from COLMAP's own; ``benchmarks/match_vs_colmap.py``), RootSIFT descriptors
#: (``normalization = L1_ROOT``) and at most 8192 features per image.
CONTRAST_THRESHOLD = 0.02
ROOTSIFT = True
MAX_FEATURES = 8192
#: The verification's threshold (pixels) is :data:`course_lib.data.two_view.VERIFY_PX`, COLMAP's
#: ``TwoViewGeometryOptions.ransac.max_error`` 4 px. At 2 px the F-RANSAC of the 1280x960 UPenn
#: photos dropped good matches unevenly (7043 kept instead of 7912), and COLMAP's mapper on those
#: matches ended 0.8-1.0 deg from COLMAP's own result (0.04 deg at 4 px, on two seeds).

#: File suffixes read as images (case-insensitive).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
#: Suffixes of photos the kit cannot read, with what to do (named when a folder holds too few images).
_UNREADABLE = {".heic": "HEIC/HEIF (iPhone): export or convert them to JPEG", ".heif": "HEIC/HEIF: convert them to JPEG",
               ".dng": "raw: develop them to JPEG or PNG", ".cr2": "raw: develop them to JPEG or PNG",
               ".cr3": "raw: develop them to JPEG or PNG", ".nef": "raw: develop them to JPEG or PNG",
               ".arw": "raw: develop them to JPEG or PNG", ".raw": "raw: develop them to JPEG or PNG",
               ".webp": "WebP: convert them to PNG or JPEG", ".gif": "GIF: convert them to PNG"}
_NUMBER = re.compile(r"^(\d+)$")


def _natural_key(name: str):
    """Natural order of a relative path: numbers as numbers (``IMG_2`` before ``IMG_10``), letters without case."""
    key = []
    for part in name.split("/"):
        key.append([(0, int(t), "") if t.isdigit() else (1, 0, t.lower()) for t in re.split(r"(\d+)", part) if t])
    return key, name


@dataclass
class ImageList:
    """The photos ``match`` reads from a folder (:func:`find_images`).

    Attributes:
        paths: M paths in the order they are read (image ``i`` becomes P3 image ``i + 1``).
        names: M names kept in the outputs: the path relative to the folder, ``/``-separated.
        ignored: names of images beside them that are not read (rule of :func:`find_images`).
        rule: how they were chosen, in words.
    """

    paths: list
    names: list
    ignored: list = field(default_factory=list)
    rule: str = ""


def find_images(folder, recursive: bool = False, exclude=None) -> ImageList:
    """The photos of a folder, in the order ``match`` reads them, with the names the outputs keep.

    * **Numbered photos** (names that are only a number: ``1.png``, ``0000.jpg``, ``17.JPG``): where the
      folder holds such images, only those are read, in numeric order -- from 0 or 1, with gaps or
      without -- and the other images beside them are ignored (and named). A P3 folder of the course
      (``1.png ... N.png`` beside ``matching*.txt``) is read as it is.
    * **Any other names** (``frame_0001.png``, ``IMG_1234.JPG``, ``DSC 7.jpeg``): all images, in natural
      name order (``IMG_2.jpg`` before ``IMG_10.jpg``; upper and lower case alike).
    * ``recursive``: all images in the folder and its subfolders (hidden ones left out), in natural
      order of their paths (``a/IMG_2.jpg`` before ``a/IMG_10.jpg`` before ``b/IMG_1.jpg``), named by
      their path inside the folder.

    Args:
        folder: a folder of photos.
        recursive: also read the images in subfolders.
        exclude: a folder inside ``folder`` to leave out (``match``'s output folder).

    Returns:
        :class:`ImageList`.

    Raises:
        KitInputError: not a folder; fewer than 2 images (the message says what the folder holds
            instead: photos in formats the kit cannot read, images in subfolders); two images with
            the same number.

    Introduced in ``notebooks/10_photos_to_nerf.ipynb``.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise KitInputError(f"image folder not found: {folder} (pass a folder that holds your photos)")
    skip = Path(exclude).resolve() if exclude is not None else None
    found = _walk(folder, recursive, skip)
    images = [p for p in found if p.suffix.lower() in IMAGE_SUFFIXES]
    name = {p: p.relative_to(folder).as_posix() for p in images}
    ignored: list = []
    if recursive:
        paths = sorted(images, key=lambda p: _natural_key(name[p]))
        rule = "all images in the folder and its subfolders, in natural name order"
    else:
        numbered: dict[int, list[Path]] = {}
        for p in images:
            if _NUMBER.match(p.stem):
                numbered.setdefault(int(p.stem), []).append(p)
        dup = sorted(k for k, v in numbered.items() if len(v) > 1)
        if dup:
            shown = "; ".join(", ".join(sorted(name[p] for p in numbered[k])) for k in dup[:3])
            raise KitInputError(f"{folder}: {len(dup)} image number(s) occur in two files ({shown}): numbered photos are read "
                                "in numeric order, so keep one file per number (move or rename the others)")
        if numbered:
            paths = [numbered[k][0] for k in sorted(numbered)]
            ignored = sorted((name[p] for p in images if not _NUMBER.match(p.stem)), key=_natural_key)
            ids = sorted(numbered)
            rule = (f"numbered images {ids[0]}..{ids[-1]}" + (f" ({ids[-1] - ids[0] + 1 - len(ids)} numbers missing)"
                                                               if ids[-1] - ids[0] + 1 != len(ids) else "") + ", in numeric order")
        else:
            paths = sorted(images, key=lambda p: _natural_key(name[p]))
            rule = "all images, in natural name order"
    if len(paths) < 2:
        raise KitInputError(_too_few_message(folder, paths, found, recursive, skip))
    return ImageList(paths, [name[p] for p in paths], ignored, rule)


def _walk(folder: Path, recursive: bool, skip: Path | None) -> list[Path]:
    """The files of ``folder`` (and of its subfolders, hidden ones and ``skip`` left out, where ``recursive``)."""
    out = []
    for p in sorted(folder.iterdir()):
        if p.name.startswith("."):
            continue
        if p.is_file():
            out.append(p)
        elif recursive and p.is_dir() and (skip is None or p.resolve() != skip):
            out += _walk(p, True, skip)
    return out


def _too_few_message(folder: Path, paths: list, found: list, recursive: bool, skip: Path | None) -> str:
    """Why a folder gives fewer than 2 photos, and what to do."""
    msg = (f"{folder} holds {len(paths)} image(s) that match can read ({', '.join(IMAGE_SUFFIXES)}, any case)"
           + (f": {paths[0].name}" if paths else "") + "; matching needs at least 2")
    other: dict[str, int] = {}
    for p in found:
        if p.suffix.lower() in _UNREADABLE:
            other[p.suffix.lower()] = other.get(p.suffix.lower(), 0) + 1
    if other:
        msg += ". It also holds " + "; ".join(f"{n} {suf} file(s) ({_UNREADABLE[suf]})" for suf, n in sorted(other.items()))
    if not recursive:
        below = [p for p in _walk(folder, True, skip) if p.suffix.lower() in IMAGE_SUFFIXES and p.parent != folder]
        if below:
            subs = sorted({p.parent.relative_to(folder).as_posix() for p in below})
            msg += (f". Its subfolders hold {len(below)} image(s) ({', '.join(subs[:3])}{', ...' if len(subs) > 3 else ''}): "
                    "pass --recursive to read them, or point match at one subfolder")
    return msg


def list_images(folder, recursive: bool = False) -> list[Path]:
    """The photo files of a folder in the order ``match`` reads them (:func:`find_images`).

    Returns:
        M paths.
    """
    return find_images(folder, recursive).paths


def load_images(paths) -> list[np.ndarray]:
    """Read images as ``(H, W, 3)`` uint8 RGB and check that they all have the same size.

    Raises:
        KitInputError: an unreadable file or images of different sizes.
    """
    import cv2

    def one(p):
        bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)  # EXIF orientation applied
        if bgr is None:
            raise KitInputError(f"cannot read the image {p}: is it a valid image file (PNG, JPEG, ...)?")
        return np.ascontiguousarray(bgr[:, :, ::-1])

    images = thread_map(one, paths)
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
        raw_matches: ``{(i, j): N}`` SIFT matches per pair after the ratio test (pairs with any).
        verified_matches: ``{(i, j): N}`` after geometric verification (equal to raw without it).
        stats: track-building stats of :func:`course_lib.data.tracks.join_tracks` (matches used,
            links refused, tracks).
        geometries: ``{(i, j): TwoViewGeometry}`` of the verification (empty without it).
        pair_mode: how the pairs were chosen (:func:`course_lib.data.pairing.select_pairs`).
        pairs_matched: how many pairs were matched.
        identical: ``[(i, j), ...]`` pairs of identical or near-identical photos (no baseline).
        guided: ``{(i, j): N}`` matches the guided second pass added.
        seconds: per stage.
    """

    track_uv: np.ndarray
    track_rgb: np.ndarray
    raw_matches: dict
    verified_matches: dict
    stats: dict = field(default_factory=dict)
    geometries: dict = field(default_factory=dict)
    pair_mode: str = "exhaustive"
    pairs_matched: int = 0
    identical: list = field(default_factory=list)
    guided: dict = field(default_factory=dict)
    seconds: dict = field(default_factory=dict)


def _check_images(images: list[np.ndarray]) -> None:
    if len(images) < 2:
        raise KitInputError(f"{len(images)} image(s): matching needs at least 2")
    for k, im in enumerate(images):
        im = np.asarray(im)
        if im.dtype != np.uint8 or im.ndim != 3 or im.shape[2] != 3:
            raise KitInputError(f"image {k} has dtype {im.dtype} and shape {im.shape}: expected (H, W, 3) uint8 RGB")
        if im.shape != np.shape(images[0]):
            raise KitInputError(f"image {k} is {im.shape[1]}x{im.shape[0]} but image 0 is {images[0].shape[1]}x{images[0].shape[0]}: one size (one K) for all")


def match_images(images: list[np.ndarray], ratio: float = 0.8, verify: bool = True, verify_px: float = VERIFY_PX,
                 min_pair_matches: int = MIN_INLIERS, rng: np.random.Generator | None = None, rootsift: bool = ROOTSIFT,
                 max_features: int = MAX_FEATURES, contrast_threshold: float = CONTRAST_THRESHOLD, pairs: str = "auto",
                 guided: bool = True, workers: int = 0, progress: bool = False) -> MatchResult:
    """SIFT features, matched over the chosen pairs (ratio test), verified by an F-RANSAC, joined into tracks.

    Args:
        images: M >= 2 ``(H, W, 3)`` uint8 RGB images of one size.
        ratio: Lowe's ratio in (0, 1].
        verify: geometric verification of each pair (:func:`course_lib.data.two_view.verify_pairs`).
        verify_px, min_pair_matches: its threshold and the fewest inliers a pair keeps.
        rng: generator for the vocabulary of ``pairs="retrieval"`` and for RANSAC (default: seed 0).
        rootsift, max_features, contrast_threshold: see :func:`course_lib.data.features.detect_features`.
        pairs: which pairs to match (:data:`course_lib.data.pairing.PAIR_MODES`).
        guided: a second, guided matching pass for pairs with few inliers.
        workers: threads (0: one per core); the result does not depend on it.
        progress: progress bars for the long stages.

    Returns:
        :class:`MatchResult`.

    Introduced in ``notebooks/10_photos_to_nerf.ipynb``.
    """
    _check_images(images)
    check_ratio(ratio)
    rng = np.random.default_rng(0) if rng is None else rng
    t0 = time.perf_counter()
    feats = detect_features(images, max_features, rootsift, contrast_threshold, workers, progress)
    t1 = time.perf_counter()
    todo, mode = select_pairs(pairs, feats, rng)
    found = match_pairs(feats, todo, ratio, workers, progress)
    t2 = time.perf_counter()
    raw = {k: len(v) for k, v in found.items()}
    geoms, identical, added = {}, [], {}
    if verify:
        geoms = verify_pairs(feats, found, rng, verify_px, min_pair_matches, guided, workers, progress)
        keep = {k: g.matches[g.inliers] for k, g in geoms.items() if g.F is not None}
        ver = {k: g.n_inliers for k, g in geoms.items()}
        identical = [k for k, g in geoms.items() if g.note == "identical"]
        added = {k: g.guided for k, g in geoms.items() if g.guided}
    else:
        keep, ver = found, dict(raw)
    t3 = time.perf_counter()
    tracks = join_tracks(len(images), _edges(feats, keep, geoms))
    track_uv, tstats = tracks.uv, tracks.stats
    track_rgb = track_colours(track_uv, images)
    seconds = {"features": t1 - t0, "matching": t2 - t1, "verification": t3 - t2, "tracks": time.perf_counter() - t3}
    return MatchResult(track_uv, track_rgb, raw, ver, dict(tstats), geoms, mode, len(todo), identical, added,
                       {k: round(v, 3) for k, v in seconds.items()})


def _edges(feats, keep: dict, geoms: dict) -> list:
    """The matches of the kept pairs as edges for :func:`course_lib.data.tracks.join_tracks`, the most trusted first:
    pairs with more matches first, within a pair the matches nearest the epipolar lines of its F."""
    edges = []
    for i, j in sorted(keep, key=lambda k: (-len(keep[k]), k)):
        m = keep[(i, j)]
        x1, x2 = feats[i].xy[m[:, 0]], feats[j].xy[m[:, 1]]
        g = geoms.get((i, j))
        if g is not None and g.F is not None:
            order = np.argsort(epipolar_distances(g.F, x1, x2), kind="stable")
            x1, x2 = x1[order], x2[order]
        edges.append((i, j, x1, x2, None))
    return edges


def _copyable(path: Path) -> bool:
    """Whether a photo can be copied into the P3 folder as it is: PNG or JPEG, no EXIF rotation (others are rewritten)."""
    if path.suffix.lower() not in (".png", ".jpg", ".jpeg"):
        return False
    from PIL import Image

    try:
        with Image.open(path) as im:
            return int(im.getexif().get(0x0112, 1) or 1) == 1  # Orientation: 1 = as stored
    except (OSError, ValueError, SyntaxError):
        return False


def _write_photos(out: Path, paths: list[Path], images: list[np.ndarray], downscaled: bool) -> list[str]:
    """The photos under P3 names in ``out``: copied where possible (:func:`_copyable`), else PNG; returns the names."""
    import cv2

    for old in out.iterdir():  # images of an earlier run would shadow these (1.png before 1.jpg)
        if re.fullmatch(r"\d+", old.stem) and old.suffix.lower() in IMAGE_EXTENSIONS and old.is_file():
            old.unlink()

    def one(k):
        src, img = paths[k], images[k]
        if not downscaled and _copyable(src):
            name = f"{k + 1}{'.png' if src.suffix.lower() == '.png' else '.jpg'}"
            shutil.copyfile(src, out / name)
        else:
            name = f"{k + 1}.png"
            if not cv2.imwrite(str(out / name), np.ascontiguousarray(img[:, :, ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 1]):
                raise KitInputError(f"could not write image {out / name}")
        return name

    return thread_map(one, range(len(paths)))


def match_folder(images_dir, K, out, downscale: float = 1.0, ratio: float = 0.8, verify: bool = True,
                 verify_px: float = VERIFY_PX, min_pair_matches: int = MIN_INLIERS, seed: int = 0, rootsift: bool = ROOTSIFT,
                 max_features: int = MAX_FEATURES, contrast_threshold: float = CONTRAST_THRESHOLD, pairs: str = "auto",
                 guided: bool = True, workers: int = 0, progress: bool = False, recursive: bool = False) -> dict:
    """Match a folder of photos and write a P3 folder (the ``match`` command).

    Args:
        images_dir: folder of photos (:func:`find_images` says which files are read; their names, kept in
            :data:`course_lib.data.p3.SOURCE_NAMES_FILE`, are the names ``sfm`` writes).
        K: ``(3, 3)`` intrinsics of the full-size photos, the path of a ``calibration.txt``, or
            None: from EXIF or a guess, refined by ``sfm`` (:func:`course_lib.data.camera.camera_prior`).
        out: output P3 folder (created; must not be ``images_dir``).
        downscale: factor >= 1 (K is scaled, see :func:`scale_intrinsics`).
        ratio, verify, verify_px, min_pair_matches, rootsift, max_features, contrast_threshold, pairs,
            guided, workers, progress: see :func:`match_images`. seed: its generator's seed.
        recursive: also read the photos in the subfolders of ``images_dir``.

    Returns:
        The report written to ``out/match_report.json``.

    Introduced in ``notebooks/10_photos_to_nerf.ipynb``.
    """
    t0 = time.perf_counter()
    out = Path(out)
    found = find_images(images_dir, recursive, exclude=out)
    paths = found.paths
    if isinstance(K, (str, Path)):
        if not Path(K).exists():
            raise KitInputError(f"calibration file not found: {K} (pass --K with a file of 3 rows of 3 numbers: the camera's K, "
                                "or leave --K out to take K from the photos' EXIF)")
        K = read_calibration(K)
    if out.resolve() == Path(images_dir).resolve():
        raise KitInputError(f"--out {out} is the image folder itself: write the P3 folder somewhere else")
    images = load_images(paths)
    H0, W0 = images[0].shape[:2]
    prior = CameraPrior(intrinsics(K)) if K is not None else camera_prior(paths, (W0, H0))
    out = output_dir(out)
    t_load = time.perf_counter() - t0
    images, K2 = downscale_images(images, prior.K, downscale)
    prior.K = K2
    res = match_images(images, ratio, verify, verify_px, min_pair_matches, np.random.default_rng(seed), rootsift=rootsift,
                       max_features=max_features, contrast_threshold=contrast_threshold, pairs=pairs, guided=guided,
                       workers=workers, progress=progress)
    t1 = time.perf_counter()
    names = _write_photos(out, paths, images, downscale != 1.0)
    write_p3(out, names, K2, res.track_uv, res.track_rgb)
    write_source_names(out, names, found.names)
    for stale in ("camera.json", "two_view_geometries.json"):
        (out / stale).unlink(missing_ok=True)
    if prior.refine:
        write_camera(out, prior)
    if verify:
        write_two_view_geometries(out, res.geometries, verify_px, min_pair_matches)
    n_obs = (~np.isnan(res.track_uv[..., 0])).sum(1) if len(res.track_uv) else np.zeros(0, int)
    report = {
        "images_dir": str(images_dir),
        "images": [{"p3_name": n, "source": src} for n, src in zip(names, found.names)],
        "image_order": found.rule,
        "ignored_images": found.ignored,
        "image_size_source": [W0, H0],
        "image_size": [int(images[0].shape[1]), int(images[0].shape[0])],
        "downscale": float(downscale),
        "camera": prior.summary(),
        "K": K2.tolist(),
        "ratio": float(ratio), "rootsift": bool(rootsift), "max_features": int(max_features),
        "contrast_threshold": float(contrast_threshold), "pair_selection": res.pair_mode, "pairs_matched": res.pairs_matched,
        "verify": bool(verify), "verify_px": float(verify_px), "min_pair_matches": int(min_pair_matches), "seed": int(seed),
        "guided": bool(guided),
        "pairs": {f"{i + 1}-{j + 1}": {"sift": res.raw_matches[(i, j)], "verified": res.verified_matches.get((i, j), 0),
                                       **({"guided": res.guided[(i, j)]} if (i, j) in res.guided else {})}
                  for (i, j) in sorted(res.raw_matches)},
        "identical_photos": [[names[i], names[j]] for i, j in res.identical],
        "tracks": int(len(res.track_uv)),
        "observations": int(n_obs.sum()),
        "tracks_by_length": {str(k): int((n_obs == k).sum()) for k in sorted(set(n_obs.tolist()))},
        **{k: v for k, v in res.stats.items() if isinstance(v, (int, float))},
        "stage_seconds": {"load": round(t_load, 3), **res.seconds, "write": round(time.perf_counter() - t1, 3)},
        "seconds": round(time.perf_counter() - t0, 2),
    }
    (out / "match_report.json").write_text(json.dumps(report, indent=1))
    return report


# --------------------------------------------------------------------------------------------- CLI


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("images_dir", help="folder of photos, any names: numbered photos (0.png, 0001.jpg, ...; gaps allowed) in numeric "
                                      "order where there are such files (other images beside them ignored), else all images in "
                                      "natural name order; sfm keeps their names")
    p.add_argument("--recursive", action="store_true",
                   help="also read the photos in the subfolders (named by their path inside IMAGES_DIR), in natural path order")
    p.add_argument("--K", default=None,
                   help="calibration file of the full-size photos: 3 rows of 3 numbers, or 'K = [a b c; d e f; g h i]' "
                        "(default: K from the photos' EXIF, else 1.2 x the longer side; sfm then refines it)")
    p.add_argument("--out", required=True, help="output P3 folder (calibration.txt, matching*.txt, 1.png ...; match_report.json)")
    p.add_argument("--downscale", type=float, default=1.0, help="shrink the photos by this factor first (K is scaled; default 1)")
    p.add_argument("--ratio", type=float, default=0.8, help="Lowe's ratio test (default 0.8)")
    p.add_argument("--pairs", choices=PAIR_MODES, default="auto",
                   help="which pairs to match: all (exhaustive), each photo with the next 10 (sequential), or the most alike "
                        "(retrieval); default auto: all up to 150 photos, retrieval above")
    p.add_argument("--verify-px", type=float, default=VERIFY_PX,
                   help=f"F-RANSAC threshold of the geometric verification, pixels (default {VERIFY_PX:g}, COLMAP's)")
    p.add_argument("--min-pair-matches", type=int, default=MIN_INLIERS,
                   help=f"pairs with fewer verified matches are dropped (default {MIN_INLIERS})")
    p.add_argument("--no-verify", action="store_true", help="keep all ratio-test matches (no geometric verification)")
    p.add_argument("--no-guided", action="store_true", help="no second, guided matching pass for pairs with few inliers")
    p.add_argument("--seed", type=int, default=0, help="seed of the verification's RANSAC (default 0)")
    p.add_argument("--contrast-threshold", type=float, default=CONTRAST_THRESHOLD,
                   help=f"SIFT contrast threshold (OpenCV's contrastThreshold; default {CONTRAST_THRESHOLD}, COLMAP's; OpenCV's own 0.04 finds fewer features)")
    p.add_argument("--max-features", type=int, default=MAX_FEATURES,
                   help=f"keep at most this many SIFT features per photo (default {MAX_FEATURES}, COLMAP's; 0: all)")
    p.add_argument("--no-rootsift", action="store_true", help="match plain SIFT descriptors instead of RootSIFT")
    p.add_argument("--workers", type=int, default=0, help="threads (default 0: one per core)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def run(args) -> int:
    rep = match_folder(args.images_dir, args.K, args.out, args.downscale, args.ratio, not args.no_verify,
                       args.verify_px, args.min_pair_matches, args.seed, rootsift=not args.no_rootsift,
                       max_features=args.max_features, contrast_threshold=args.contrast_threshold, pairs=args.pairs,
                       guided=not args.no_guided, workers=args.workers, progress=not args.quiet, recursive=args.recursive)
    n = len(rep["images"])
    first, last = rep["images"][0]["source"], rep["images"][-1]["source"]
    print(f"read {n} photos: {rep['image_order']} ({first} ... {last})")
    if rep["ignored_images"]:
        shown = ", ".join(rep["ignored_images"][:5]) + (", ..." if len(rep["ignored_images"]) > 5 else "")
        print(f"ignored {len(rep['ignored_images'])} image(s) without a number beside the numbered photos: {shown} "
              "(move them out, or number them too, to use them)")
    kept = sum(1 for v in rep["pairs"].values() if v["verified"] >= args.min_pair_matches or (args.no_verify and v["sift"]))
    print(f"matched {n} images ({rep['image_size'][0]}x{rep['image_size'][1]}): {rep['pairs_matched']} of {n * (n - 1) // 2} "
          f"pairs matched ({rep['pair_selection']}), {kept} kept, {rep['tracks']} tracks, {rep['observations']} observations, "
          f"{rep['seconds']:.1f} s")
    cam = rep["camera"]
    if cam["refine"]:
        guessed = str(cam["source"]).startswith("guess")
        print(f"camera: f = {cam['K'][0][0]:.1f} px from {cam['source']}; sfm "
              + ("estimates f from the images (self-calibration), then " if guessed else "") + f"refines f and k1 ({cam['model']})")
    for a, b in rep["identical_photos"]:
        print(f"identical or near-identical photos (no baseline): {a}, {b} -- the same view twice adds nothing to a "
              "reconstruction; keep one, and take the others from different positions")
    print(f"P3 folder: {args.out} (read it with course_lib.data.p3.read_p3, or run: python -m course_lib sfm {args.out})")
    return 0

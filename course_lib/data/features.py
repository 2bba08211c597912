"""Features of photos: SIFT detection, matching across all pairs, geometric verification, tracks.

What turns photos into correspondences (the P3 matches the SfM lessons read), in one place: the
embedded scene is made with it (:mod:`course_lib.data.building`) and so are students' own photos
(``python -m course_lib match``, :mod:`course_lib.data.match_cli`).

1. :func:`detect_features`: OpenCV SIFT per image, keypoints sorted by position (so the result
   does not depend on OpenCV's threading), the +0.25 px offset of OpenCV's keypoints corrected
   (:data:`SIFT_OFFSET`); optionally RootSIFT descriptors (:func:`root_sift`).
2. :func:`match_descriptors`: Lowe's ratio test and mutual nearest neighbours for one pair;
   :func:`detect_and_match` runs both over all pairs.
3. :func:`keep_geometric_inliers`: per pair, only the matches that fit one fundamental matrix
   (OpenCV's RANSAC: this module ships in the student kit, the kit's RANSAC is an exercise), and
   only pairs with enough of them.
4. :func:`tracks_from_images`: the matches joined into tracks
   (:func:`course_lib.data.p3.tracks_from_pairs`) with each track's colour.

Points are rows ``(u, v)`` in pixels, origin at the centre of the top-left pixel
(:mod:`course_lib.conventions`).

Introduced in ``notebooks/10_photos_to_nerf.ipynb``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from course_lib import validate
from course_lib.validate import KitInputError

__all__ = ["SIFT_OFFSET", "RATIO", "Features", "detect_features", "root_sift", "match_descriptors",
           "check_ratio", "detect_and_match", "keep_geometric_inliers", "track_colours", "tracks_from_images"]

#: OpenCV SIFT's keypoint offset from the kit's pixel convention (subtracted; see :func:`detect_features`).
SIFT_OFFSET = 0.25
#: Lowe's ratio for the SIFT matches.
RATIO = 0.8


@dataclass
class Features:
    """The features of one image.

    Attributes:
        xy: ``(F, 2)`` float64 keypoint pixels ``(u, v)``.
        descriptors: ``(F, 128)`` float32 descriptors.
    """

    xy: np.ndarray
    descriptors: np.ndarray

    def __len__(self) -> int:
        return int(len(self.xy))


def root_sift(descriptors: np.ndarray) -> np.ndarray:
    """RootSIFT (Arandjelović and Zisserman 2012): L1-normalize, then take the square root.

    Euclidean distance between RootSIFT vectors is the Hellinger kernel between the SIFT
    histograms, which matches better than L2 on raw SIFT (COLMAP's default, as
    ``FeatureExtraction.normalization = L1_ROOT``).

    Args:
        descriptors: ``(F, 128)`` SIFT descriptors (non-negative).

    Returns:
        ``(F, 128)`` float32 RootSIFT descriptors (unit L2 norm).
    """
    d = np.asarray(descriptors, np.float32)
    return np.sqrt(d / np.maximum(d.sum(axis=1, keepdims=True), 1e-12))


def detect_features(images: list[np.ndarray], max_features: int = 0, rootsift: bool = False,
                    contrast_threshold: float = 0.04) -> list[Features]:
    """SIFT features of every image (OpenCV), sorted by position.

    Args:
        images: M ``(H, W, 3)`` uint8 RGB images.
        max_features: keep at most this many per image (the strongest; 0: all, OpenCV's default).
        rootsift: replace the descriptors by :func:`root_sift`.
        contrast_threshold: OpenCV's ``contrastThreshold`` (its default 0.04 keeps extrema of
            contrast >= 0.04 / 3 on a [0, 1] image; COLMAP's ``peak_threshold`` 0.02 / 3 is the
            same rule at 0.02: more features on weak texture).

    Returns:
        M :class:`Features`.
    """
    import cv2

    sift = cv2.SIFT_create(nfeatures=int(max_features), contrastThreshold=float(contrast_threshold))
    out = []
    for img in images:
        gray = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
        kps, des = sift.detectAndCompute(gray, None)
        # OpenCV's SIFT reports points 0.25 px right of and below the kit's pixel-centre convention
        # (measured on Gaussian blobs at known sub-pixel positions: +0.250 +- 0.02 px at every
        # scale; it comes from the doubled first octave). Left in, it acts like a principal point
        # shifted by a quarter pixel and costs ~0.03 deg of rotation accuracy.
        pts = np.array([k.pt for k in kps], np.float64).reshape(-1, 2) - SIFT_OFFSET
        key = np.array([(k.pt[1], k.pt[0], k.size, k.angle, k.response) for k in kps]).reshape(-1, 5)
        order = np.lexsort(key.T[::-1])
        des = np.zeros((0, 128), np.float32) if des is None else des[order]
        out.append(Features(pts[order], np.ascontiguousarray(root_sift(des) if rootsift else des)))
    return out


def match_descriptors(f1: Features, f2: Features, ratio: float = RATIO, matcher=None) -> np.ndarray:
    """Matches of one pair: Lowe's ratio test, kept only where they are mutual nearest neighbours.

    A feature of image 1 is matched to its nearest neighbour in image 2 if that is closer than
    ``ratio`` times the second nearest, and if image 2's feature has it as its own nearest
    neighbour in image 1 (or a feature at the same pixel: SIFT gives several orientations per
    keypoint).

    Args:
        f1, f2: the features of the two images.
        ratio: Lowe's ratio in (0, 1].
        matcher: an OpenCV ``BFMatcher(NORM_L2)`` to reuse (made if None).

    Returns:
        ``(N, 2)`` int indices ``(feature in image 1, feature in image 2)``.
    """
    import cv2

    if len(f1) < 2 or len(f2) < 2:
        return np.zeros((0, 2), int)
    bf = cv2.BFMatcher(cv2.NORM_L2) if matcher is None else matcher
    fwd = bf.knnMatch(f1.descriptors, f2.descriptors, k=2)
    back = np.full(len(f2), -1)
    for m in bf.match(f2.descriptors, f1.descriptors):
        back[m.queryIdx] = m.trainIdx
    sel = []
    for m in fwd:
        if len(m) == 2 and m[0].distance < ratio * m[1].distance:
            q, t = m[0].queryIdx, m[0].trainIdx
            if back[t] == q or np.array_equal(f1.xy[back[t]], f1.xy[q]):
                sel.append((q, t))
    return np.array(sel, int).reshape(-1, 2)


def check_ratio(ratio) -> float:
    """Check Lowe's ratio: a number in (0, 1]."""
    try:
        r = float(ratio)
    except (TypeError, ValueError):
        r = float("nan")
    if not 0.0 < r <= 1.0:
        raise KitInputError(f"ratio = {ratio!r}: Lowe's ratio must be in (0, 1] (0.8 is usual; smaller is stricter)")
    return r


def detect_and_match(images: list[np.ndarray], ratio: float = RATIO, max_features: int = 0,
                     rootsift: bool = False, contrast_threshold: float = 0.04) -> dict:
    """SIFT features of every image, matched across all pairs (ratio test + mutual nearest neighbour).

    Args:
        images: M ``(H, W, 3)`` uint8 RGB images.
        ratio: Lowe's ratio (the best match must be closer than ``ratio`` times the second best).
        max_features, rootsift, contrast_threshold: see :func:`detect_features`.

    Returns:
        ``{(i, j): (x1 (N, 2), x2 (N, 2))}`` for every pair ``i < j`` with matches (float64 pixels).
    """
    import cv2

    check_ratio(ratio)
    feats = detect_features(images, max_features, rootsift, contrast_threshold)
    bf = cv2.BFMatcher(cv2.NORM_L2)
    pairs = {}
    for i in range(len(feats)):
        for j in range(i + 1, len(feats)):
            m = match_descriptors(feats[i], feats[j], ratio, bf)
            if len(m):
                pairs[(i, j)] = (feats[i].xy[m[:, 0]], feats[j].xy[m[:, 1]])
    return pairs


def keep_geometric_inliers(pairs: dict, rng: np.random.Generator, threshold_px: float = 2.0,
                           min_matches: int = 15) -> tuple[dict, dict]:
    """Keep the matches of each pair that fit one fundamental matrix; drop pairs with too few.

    This is plumbing, not the lesson (the lesson's RANSAC is notebook 01's ``ransac_fundamental``,
    which the SfM pipeline runs again on the written matches: the student's own in the student kit,
    :func:`course_lib.sfm.fundamental.ransac` in the instructor's kit): OpenCV's ``findFundamentalMat(FM_RANSAC)``
    (C++, fast on the hundreds of mostly empty pairs of a 40-view capture). ``cv2.setRNGSeed``
    with a seed drawn from ``rng`` makes it repeatable.

    Args:
        pairs: ``{(i, j): (x1 (N, 2), x2 (N, 2))}`` (:func:`detect_and_match`).
        rng: seeded generator.
        threshold_px: distance to the epipolar line, pixels.
        min_matches: pairs with fewer inliers (or fewer matches) are dropped.

    Returns:
        ``(kept pairs, {(i, j): number of inliers})`` (the counts include dropped pairs).
    """
    import cv2

    validate.generator(rng)
    threshold_px = validate.positive(threshold_px, "threshold_px", "a positive number of pixels")
    out, counts = {}, {}
    for key in sorted(pairs):
        x1, x2 = (np.ascontiguousarray(np.asarray(x, float).reshape(-1, 2)) for x in pairs[key])
        counts[key] = 0
        if len(x1) < max(8, min_matches):
            continue
        cv2.setRNGSeed(int(rng.integers(2**31 - 1)))
        F, mask = cv2.findFundamentalMat(x1, x2, cv2.FM_RANSAC, threshold_px, 0.999, 2000)
        if mask is None or F is None or F.shape != (3, 3):
            continue
        inl = mask.ravel().astype(bool)
        counts[key] = int(inl.sum())
        if counts[key] >= min_matches:
            out[key] = (x1[inl], x2[inl])
    return out, counts


def track_colours(track_uv: np.ndarray, images: list[np.ndarray]) -> np.ndarray:
    """``(T, 3)`` uint8 colour of each track at its first observation (nearest pixel).

    Args:
        track_uv: ``(T, M, 2)`` pixels, NaN where unseen; every track seen at least once.
        images: M ``(H, W, 3)`` uint8 RGB images.
    """
    if not len(track_uv):
        return np.zeros((0, 3), np.uint8)
    first = np.argmax(~np.isnan(track_uv[..., 0]), axis=1)
    uv0 = track_uv[np.arange(len(track_uv)), first]
    H, W = images[0].shape[:2]
    cols = np.clip(np.round(uv0[:, 0]).astype(int), 0, W - 1)
    rows = np.clip(np.round(uv0[:, 1]).astype(int), 0, H - 1)
    return np.stack([images[f][r, c] for f, r, c in zip(first, rows, cols)]).astype(np.uint8)


def tracks_from_images(images: list[np.ndarray], ratio: float = RATIO):
    """SIFT matches of all pairs joined into tracks, with each track's colour.

    Args:
        images: M ``(H, W, 3)`` uint8 RGB images.
        ratio: Lowe's ratio.

    Returns:
        ``track_uv (T, M, 2)``, ``track_rgb (T, 3)`` uint8 (colour at the first observation),
        ``pairs`` (the raw matches of :func:`detect_and_match`) and the stats of
        :func:`course_lib.data.p3.tracks_from_pairs`.
    """
    from course_lib.data.p3 import tracks_from_pairs

    pairs = detect_and_match(images, ratio)
    track_uv, _, tstats = tracks_from_pairs(len(images), pairs)
    return track_uv, track_colours(track_uv, images), pairs, tstats

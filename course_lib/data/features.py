"""Features of photos: SIFT detection and descriptor matching.

What turns photos into correspondences (the P3 matches the SfM lessons read), in one place: the
embedded scene is made with it (:mod:`course_lib.data.building`) and so are students' own photos
(``python -m course_lib match``, :mod:`course_lib.data.cli_match`).

1. :func:`detect_features`: OpenCV SIFT per image, keypoints sorted by position (so the result
   does not depend on OpenCV's threading), the +0.25 px offset of OpenCV's keypoints corrected
   (:data:`SIFT_OFFSET`); optionally RootSIFT descriptors (:func:`root_sift`).
2. :func:`match_descriptors`: Lowe's ratio test and mutual nearest neighbours for one pair, both
   directions from one matrix of distances (one BLAS product); :func:`match_pairs` runs it over a
   list of pairs on several threads (:mod:`course_lib.data.pairing` says which pairs), and
   :func:`detect_and_match` over all pairs. (The geometric verification of the matches is
   :mod:`course_lib.data.two_view`.)
3. :func:`track_colours`: each track's colour; :func:`course_lib.data.tracks.tracks_from_images`
   joins the matches of all pairs into tracks (:func:`course_lib.data.p3.tracks_from_pairs`).

Points are rows ``(u, v)`` in pixels, origin at the centre of the top-left pixel
(:mod:`course_lib.conventions`).

Introduced in ``notebooks/10_photos_to_nerf.ipynb``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from course_lib.threads import thread_map
from course_lib.validate import KitInputError

__all__ = ["SIFT_OFFSET", "RATIO", "Features", "detect_features", "root_sift", "augmented_descriptors",
           "match_descriptors", "match_pairs", "check_ratio", "detect_and_match", "track_colours"]

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

    def augmented(self) -> tuple[np.ndarray, np.ndarray]:
        """:func:`augmented_descriptors` of these features (computed once)."""
        if getattr(self, "_aug", None) is None:
            self._aug = augmented_descriptors(self.descriptors)
        return self._aug


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
                    contrast_threshold: float = 0.04, workers: int = 1, progress: bool = False) -> list[Features]:
    """SIFT features of every image (OpenCV), sorted by position.

    Args:
        images: M ``(H, W, 3)`` uint8 RGB images.
        max_features: keep at most this many per image (the strongest; 0: all, OpenCV's default).
        rootsift: replace the descriptors by :func:`root_sift`.
        contrast_threshold: OpenCV's ``contrastThreshold`` (its default 0.04 keeps extrema of
            contrast >= 0.04 / 3 on a [0, 1] image; COLMAP's ``peak_threshold`` 0.02 / 3 is the
            same rule at 0.02: more features on weak texture).
        workers: images detected at once (threads; 0: one per core). The result does not depend on it.
        progress: show a progress bar.

    Returns:
        M :class:`Features`.
    """
    import cv2

    def one(img):
        sift = cv2.SIFT_create(nfeatures=int(max_features), contrastThreshold=float(contrast_threshold))
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
        return Features(pts[order], np.ascontiguousarray(root_sift(des) if rootsift else des))

    return thread_map(one, images, workers, progress, "SIFT", "image")


def augmented_descriptors(descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two ``(F, D + 2)`` float32 forms of descriptors whose product is the squared distance.

    With ``a' = [a, |a|^2, 1]`` and ``b' = [-2 b, 1, |b|^2]``, ``a' . b' = |a - b|^2``: one matrix
    product (BLAS) gives every squared distance of a pair, no second pass to add the norms.

    Args:
        descriptors: ``(F, D)`` descriptors.

    Returns:
        ``(as_query (F, D + 2), as_index (F, D + 2))``.
    """
    d = np.asarray(descriptors, np.float32).reshape(len(descriptors), -1)
    n = np.einsum("ij,ij->i", d, d, dtype=np.float64).astype(np.float32)[:, None]
    one = np.ones_like(n)
    return np.hstack([d, n, one]), np.hstack([-2.0 * d, one, n])


#: Entries of the distance matrix computed at once (rows are split beyond it: 64 MB of float32).
_CHUNK_ENTRIES = 1 << 24


def match_descriptors(f1: Features, f2: Features, ratio: float = RATIO, allowed=None) -> np.ndarray:
    """Matches of one pair: Lowe's ratio test, kept only where they are mutual nearest neighbours.

    A feature of image 1 is matched to its nearest neighbour in image 2 if that is closer than
    ``ratio`` times the second nearest, and if image 2's feature has it as its own nearest
    neighbour in image 1 (or a feature at the same pixel: SIFT gives several orientations per
    keypoint).

    Both directions come from ONE matrix of squared distances, one BLAS product of the
    :func:`augmented_descriptors` (row by row in chunks for large images): the row minima give the
    forward nearest and second nearest neighbours, the column minima the backward ones. The
    distances of the two neighbours are recomputed exactly for the ratio test.

    Args:
        f1, f2: the features of the two images.
        ratio: Lowe's ratio in (0, 1].
        allowed: optional constraint (guided matching, :func:`course_lib.data.two_view.guided_matches`):
            ``allowed(rows: slice) -> (rows, len(f2)) bool``, the candidates each feature of image 1
            in ``rows`` may be matched to; the neighbours of both directions are taken among them
            (where a feature has one candidate only, the ratio test passes).

    Returns:
        ``(N, 2)`` int indices ``(feature in image 1, feature in image 2)``, sorted by the first.
    """
    n1, n2 = len(f1), len(f2)
    if n1 < 2 or n2 < 2:
        return np.zeros((0, 2), int)
    q_aug, _ = f1.augmented()
    _, t_aug = f2.augmented()
    best = np.empty((n1, 2), np.int64)
    dd = np.empty((n1, 2), np.float32)  # squared distances of the two neighbours, as the product gave them
    col_min = np.full(n2, np.inf, np.float32)
    step = max(1, _CHUNK_ENTRIES // n2)
    for s in range(0, n1, step):
        D = q_aug[s:s + step] @ t_aug.T  # (rows, n2) squared distances
        if allowed is not None:
            D[~allowed(slice(s, s + len(D)))] = np.inf
        rows = np.arange(len(D))
        np.minimum(col_min, D.min(axis=0), out=col_min)
        j0 = D.argmin(axis=1)
        d0 = D[rows, j0]
        D[rows, j0] = np.inf
        j1 = D.argmin(axis=1)
        best[s:s + len(D)] = np.stack([j0, j1], axis=1)
        dd[s:s + len(D)] = np.stack([d0, D[rows, j1]], axis=1)
    dist = np.sqrt(((f1.descriptors[:, None, :] - f2.descriptors[best]).astype(np.float64) ** 2).sum(axis=2))  # exact
    dist[~np.isfinite(dd)] = np.inf  # no such neighbour (guided matching)
    q = np.flatnonzero(np.isfinite(dist[:, 0]) & (dist[:, 0] < ratio * dist[:, 1]))
    t = best[q, 0]
    mutual = dd[q, 0] <= col_min[t]  # the same entries of the same product: no rounding between them
    if not mutual.all():  # a feature at the same pixel as q may be t's nearest (another orientation)
        tf = t[~mutual]
        back = (q_aug @ t_aug[tf].T).argmin(axis=0)
        mutual[~mutual] = np.all(f1.xy[back] == f1.xy[q[~mutual]], axis=1)
    return np.stack([q[mutual], t[mutual]], axis=1)


def check_ratio(ratio) -> float:
    """Check Lowe's ratio: a number in (0, 1]."""
    try:
        r = float(ratio)
    except (TypeError, ValueError):
        r = float("nan")
    if not 0.0 < r <= 1.0:
        raise KitInputError(f"ratio = {ratio!r}: Lowe's ratio must be in (0, 1] (0.8 is usual; smaller is stricter)")
    return r


def match_pairs(feats: list[Features], pairs, ratio: float = RATIO, workers: int = 0,
                progress: bool = False) -> dict:
    """:func:`match_descriptors` for the given image pairs, several pairs at once (threads).

    Args:
        feats: M :class:`Features`.
        pairs: ``[(i, j), ...]`` image pairs (0-based, ``i != j``).
        ratio: Lowe's ratio.
        workers: pairs matched at once (0: one per core); the result does not depend on it.
        progress: show a progress bar.

    Returns:
        ``{(i, j): (N, 2) int feature indices}`` for the pairs with at least one match.
    """
    check_ratio(ratio)
    pairs = [(int(i), int(j)) for i, j in pairs]
    found = thread_map(lambda ij: match_descriptors(feats[ij[0]], feats[ij[1]], ratio), pairs, workers, progress,
                       "match", "pair")
    return {ij: m for ij, m in zip(pairs, found) if len(m)}


def detect_and_match(images: list[np.ndarray], ratio: float = RATIO, max_features: int = 0,
                     rootsift: bool = False, contrast_threshold: float = 0.04, workers: int = 1) -> dict:
    """SIFT features of every image, matched across all pairs (ratio test + mutual nearest neighbour).

    Args:
        images: M ``(H, W, 3)`` uint8 RGB images.
        ratio: Lowe's ratio (the best match must be closer than ``ratio`` times the second best).
        max_features, rootsift, contrast_threshold: see :func:`detect_features`.
        workers: threads (0: one per core); the result does not depend on it.

    Returns:
        ``{(i, j): (x1 (N, 2), x2 (N, 2))}`` for every pair ``i < j`` with matches (float64 pixels).
    """
    check_ratio(ratio)
    feats = detect_features(images, max_features, rootsift, contrast_threshold, workers)
    M = len(feats)
    found = match_pairs(feats, [(i, j) for i in range(M) for j in range(i + 1, M)], ratio, workers)
    return {(i, j): (feats[i].xy[m[:, 0]], feats[j].xy[m[:, 1]]) for (i, j), m in found.items()}


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

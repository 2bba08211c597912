"""Geometric verification of matched image pairs: the one RANSAC that ``match`` runs, carried to ``sfm``.

A pair's descriptor matches (:mod:`course_lib.data.features`) hold wrong matches; the right ones
fit one fundamental matrix F (``x2ᵀ F x1 = 0``). :func:`verify_pairs` finds it per pair and keeps
its inliers, as COLMAP's two-view geometry does:

1. **RANSAC on F** (:func:`verify_pair`): OpenCV's USAC (``USAC_ACCURATE``: SPRT early stopping,
   graph-cut local optimization, a final least-squares fit; seeded), threshold
   :data:`VERIFY_PX` on the distance to the epipolar lines (the larger of the two images'),
   COLMAP's 4 px. It is plumbing, not the lesson: this module ships in the student kit, and the
   lesson's own RANSAC (notebook 01) runs in ``sfm`` only on P3 folders that carry no verification
   (the course's own matching files).
2. **Weak photos get a second, guided pass** (:func:`guided_matches`): the verified pairs of a
   photo whose best pair has fewer than :data:`GUIDED_BELOW` inliers are matched again with the
   ratio test taken among the features near each other's epipolar line of the pair's F only
   (:data:`GUIDED_PX`), and verified again: a photo whose neighbours share few matches (weak texture, a
   wide step) gets the matches it needs to register.
3. **Identical photos are named** (:func:`identical_photos`): where the matches barely move between
   the two photos (the median displacement below :data:`IDENTICAL_PX`), the pair has no baseline
   (the same photo twice, or taken from the same spot): ``match`` and ``sfm`` say so.

The result is carried in the P3 folder (:func:`write_two_view_geometries`, read by
:func:`course_lib.data.p3.read_p3`): ``sfm`` takes each verified pair's F and inliers from it
instead of running RANSAC again (:func:`course_lib.sfm.tracks.verify_pairs`).

Points are rows ``(u, v)`` in pixels (:mod:`course_lib.conventions`).

Introduced in ``notebooks/10_photos_to_nerf.ipynb``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from course_lib.data.features import Features, match_descriptors
from course_lib.threads import thread_map
from course_lib.validate import KitInputError

__all__ = ["VERIFY_PX", "MIN_INLIERS", "GUIDED_BELOW", "GUIDED_PX", "GUIDED_RATIO", "IDENTICAL_PX", "GEOMETRY_FILE", "TwoViewGeometry",
           "epipolar_distances", "verify_pair", "identical_photos", "guided_matches", "verify_pairs",
           "write_two_view_geometries", "read_two_view_geometries"]

#: RANSAC threshold (pixels) on the distance to the epipolar lines: COLMAP's
#: ``TwoViewGeometryOptions.ransac.max_error`` 4 px.
VERIFY_PX = 4.0
#: A pair is verified with at least this many inliers (COLMAP's ``min_num_inliers`` 15).
MIN_INLIERS = 15
#: A photo whose best verified pair has fewer inliers gets a second, guided matching pass on its
#: pairs (:func:`guided_matches`): below about 50, a photo risks too few 2D-3D matches for PnP.
GUIDED_BELOW = 50
#: How near its epipolar line a guided match must lie (pixels): half the verification's threshold.
GUIDED_PX = 2.0
#: Lowe's ratio of the guided pass, taken among the candidates near the epipolar line: the line rules
#: out the look-alikes elsewhere in the photo (repeated texture), which is what makes the global
#: ratio test fail. On four 400x300 renders of the building the weakest photo's pairs went from
#: 45-85 to 114-135 matches, 76-87 % of them right (0.9 gave more, 63-78 % right; 4 px no more right ones).
GUIDED_RATIO = 0.8
#: A pair whose matches move by less than this (median, pixels) has no baseline: identical photos.
IDENTICAL_PX = 1.0
#: The file of the P3 folder that carries the verification.
GEOMETRY_FILE = "two_view_geometries.json"


@dataclass
class TwoViewGeometry:
    """The verification of one image pair.

    Attributes:
        F: ``(3, 3)`` fundamental matrix (``x2ᵀ F x1 = 0``, unit Frobenius norm), None if none was found.
        matches: ``(N, 2)`` int feature indices (image 1, image 2) of the pair's matches (the
            guided pass may have added some).
        inliers: ``(N,)`` bool, the matches within the threshold of F.
        guided: matches the guided pass added (0 if it did not run).
        note: ``""`` for a verified pair, else why not; ``"identical"`` for a pair without baseline
            (:func:`identical_photos`; still verified).
    """

    F: np.ndarray | None
    matches: np.ndarray
    inliers: np.ndarray
    guided: int = 0
    note: str = ""

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


def epipolar_distances(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """``(N,)`` the larger of the distances (pixels) of ``x2`` to the line ``F x1`` and of ``x1`` to ``Fᵀ x2``.

    OpenCV's RANSAC error for F. Args: F ``(3, 3)``; x1, x2 ``(N, 2)`` pixels.
    """
    h1 = np.hstack([x1, np.ones((len(x1), 1))])
    h2 = np.hstack([x2, np.ones((len(x2), 1))])
    l2, l1 = h1 @ F.T, h2 @ F
    e = np.abs(np.einsum("ij,ij->i", h2, l2))
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.maximum(e / np.hypot(l2[:, 0], l2[:, 1]), e / np.hypot(l1[:, 0], l1[:, 1]))
    return np.where(np.isfinite(d), d, np.inf)


def identical_photos(x1: np.ndarray, x2: np.ndarray) -> bool:
    """Whether matches ``x1, x2 (N, 2)`` barely move: the median displacement is below :data:`IDENTICAL_PX` (no baseline)."""
    return len(x1) > 0 and float(np.median(np.linalg.norm(np.asarray(x2) - np.asarray(x1), axis=1))) < IDENTICAL_PX


def verify_pair(f1: Features, f2: Features, m: np.ndarray, seed: int, threshold_px: float = VERIFY_PX,
                min_inliers: int = MIN_INLIERS) -> tuple[np.ndarray | None, np.ndarray, str]:
    """RANSAC on F for the matches ``m`` of two photos: ``(F or None, inliers (N,) bool, note)``.

    OpenCV's USAC (``USAC_ACCURATE``) with the given seed; the inliers are the matches within
    ``threshold_px`` of F (:func:`epipolar_distances`). It takes the photos' features and the
    matches' indices, as ``match`` has them (the student kit ships it: no kit function takes the
    two point sets of notebook 01's ``ransac_fundamental``).

    Args:
        f1, f2: the two photos' :class:`~course_lib.data.features.Features`.
        m: ``(N, 2)`` int feature indices (row k matches ``f1.xy[m[k, 0]]`` with ``f2.xy[m[k, 1]]``).
        seed: OpenCV's RANSAC seed.
        threshold_px: inlier threshold on :func:`epipolar_distances`. min_inliers: fewest inliers
            of a verified pair.

    Returns:
        F (unit norm; None with a note where the pair is not verified), the inliers, and the note
        (``""``, ``"identical"``, or why not).
    """
    import cv2

    m = np.asarray(m, np.int64).reshape(-1, 2)
    x1, x2 = f1.xy[m[:, 0]], f2.xy[m[:, 1]]
    n = len(m)
    none = np.zeros(n, bool)
    if n < max(8, min_inliers):
        return None, none, f"{n} matches: fewer than {max(8, min_inliers)}"
    cv2.setRNGSeed(int(seed))
    try:
        F, mask = cv2.findFundamentalMat(np.ascontiguousarray(x1, np.float64), np.ascontiguousarray(x2, np.float64),
                                         cv2.USAC_ACCURATE, threshold_px, 0.999, 10000)
    except cv2.error:  # degenerate input (all points on a line, repeated points)
        F = mask = None
    if F is None or mask is None or F.shape != (3, 3):
        return None, none, "no F fits the matches (degenerate: on a line, or repeated points?)"
    F = F / np.linalg.norm(F)
    inl = epipolar_distances(F, x1, x2) <= threshold_px
    if inl.sum() < min_inliers:
        return None, inl, f"{int(inl.sum())} inliers: fewer than {min_inliers}"
    return F, inl, "identical" if identical_photos(x1[inl], x2[inl]) else ""


def guided_matches(f1: Features, f2: Features, F: np.ndarray, threshold_px: float = GUIDED_PX,
                   ratio: float = GUIDED_RATIO) -> np.ndarray:
    """Matches of one pair among the features near each other's epipolar line of ``F`` (ratio test among them).

    Args:
        f1, f2: the two images' features. F: ``(3, 3)`` their fundamental matrix.
        threshold_px: how near the line (:func:`epipolar_distances`). ratio: Lowe's ratio.

    Returns:
        ``(N, 2)`` int feature indices (:func:`course_lib.data.features.match_descriptors` with the
        epipolar constraint).
    """
    h1 = np.hstack([f1.xy, np.ones((len(f1), 1))])
    h2 = np.hstack([f2.xy, np.ones((len(f2), 1))])
    l2 = h1 @ F.T  # (n1, 3) lines in image 2
    l1 = h2 @ F  # (n2, 3) lines in image 1
    n2 = np.hypot(l2[:, 0], l2[:, 1])[:, None]
    n1 = np.hypot(l1[:, 0], l1[:, 1])[None, :]

    def allowed(rows: slice) -> np.ndarray:
        e = np.abs(l2[rows] @ h2.T)  # (rows, n2) algebraic errors x2ᵀ F x1
        with np.errstate(divide="ignore", invalid="ignore"):
            return (e <= threshold_px * n2[rows]) & (e <= threshold_px * n1)

    return match_descriptors(f1, f2, ratio, allowed=allowed)


def verify_pairs(feats: list[Features], matches: dict, rng: np.random.Generator, threshold_px: float = VERIFY_PX,
                 min_inliers: int = MIN_INLIERS, guided: bool = True, workers: int = 0,
                 progress: bool = False) -> dict:
    """Verify every matched pair (RANSAC on F), with a guided second pass where a photo's matches are few.

    The guided pass (:func:`guided_matches`) runs on the verified pairs of the *weak* photos: those
    whose best verified pair has fewer than :data:`GUIDED_BELOW` inliers. (On well-textured photos
    it would mostly add wrong matches along the epipolar band of repeated texture; where a photo
    has few matches, every right one counts.) It replaces a pair's matches where its F keeps more
    inliers than before.

    Args:
        feats: M :class:`~course_lib.data.features.Features`.
        matches: ``{(i, j): (N, 2) int feature indices}`` (:func:`course_lib.data.features.match_pairs`).
        rng: seeded generator (one RANSAC seed per pair is drawn from it, in sorted pair order, so
            the result does not depend on ``workers``).
        threshold_px, min_inliers: see :func:`verify_pair`.
        guided: run the guided pass.
        workers: pairs verified at once (threads; 0: one per core). progress: a progress bar.

    Returns:
        ``{(i, j): TwoViewGeometry}`` for every pair of ``matches``.
    """
    keys = sorted(matches)
    seeds = dict(zip(keys, rng.integers(2**31 - 1, size=len(keys)).tolist()))

    def first(key):
        i, j = key
        m = np.asarray(matches[key], np.int64).reshape(-1, 2)
        F, inl, note = verify_pair(feats[i], feats[j], m, seeds[key], threshold_px, min_inliers)
        return TwoViewGeometry(F, m, inl, 0, note)

    out = dict(zip(keys, thread_map(first, keys, workers, progress, "verify", "pair")))
    if not guided:
        return out
    best = np.zeros(len(feats), int)
    for (i, j), g in out.items():
        if g.F is not None:
            best[i], best[j] = max(best[i], g.n_inliers), max(best[j], g.n_inliers)
    weak = [k for k, g in out.items() if g.F is not None and g.note != "identical" and min(best[k[0]], best[k[1]]) < GUIDED_BELOW]

    def second(key):
        i, j = key
        g = out[key]
        m = guided_matches(feats[i], feats[j], g.F)
        if len(m) <= g.n_inliers:
            return g
        F, inl, note = verify_pair(feats[i], feats[j], m, seeds[key], threshold_px, min_inliers)
        if F is None or inl.sum() <= g.n_inliers:
            return g
        return TwoViewGeometry(F, m, inl, int(inl.sum()) - g.n_inliers, note)

    out.update(zip(weak, thread_map(second, weak, workers, progress, "guided matching", "pair")))
    return out


# ------------------------------------------------------------------------------------ the P3 folder's file


def write_two_view_geometries(folder, geometries: dict, threshold_px: float, min_inliers: int) -> Path:
    """Write the verified pairs' F into ``folder/two_view_geometries.json`` (:data:`GEOMETRY_FILE`).

    Args:
        folder: the P3 folder. geometries: ``{(i, j): TwoViewGeometry}`` (0-based; only verified
            pairs are written, with 1-based image numbers as in the P3 files).
        threshold_px, min_inliers: the verification's settings (recorded).

    Returns:
        The file's path.
    """
    rows = [{"images": [i + 1, j + 1], "F": [float(v) for v in g.F.ravel()], "inliers": g.n_inliers,
             **({"identical": True} if g.note == "identical" else {})}
            for (i, j), g in sorted(geometries.items()) if g.F is not None]
    path = Path(folder) / GEOMETRY_FILE
    path.write_text(json.dumps({"method": "RANSAC on F (OpenCV USAC_ACCURATE), distance to the epipolar lines",
                                "threshold_px": float(threshold_px), "min_inliers": int(min_inliers), "pairs": rows},
                               indent=0))
    return path


def read_two_view_geometries(folder, n_images: int) -> dict | None:
    """The verified pairs a P3 folder carries: ``{(i, j): F (3, 3)}`` (0-based), or None without the file.

    Raises:
        KitInputError: a malformed file, or image numbers outside ``1 .. n_images``.
    """
    path = Path(folder) / GEOMETRY_FILE
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text())
        out = {}
        for row in doc["pairs"]:
            i, j = (int(v) - 1 for v in row["images"])
            if not (0 <= i < j < n_images):
                raise ValueError(f"pair {row['images']} is not two image numbers 1..{n_images} in increasing order")
            out[(i, j)] = np.asarray(row["F"], float).reshape(3, 3)
    except (ValueError, KeyError, TypeError) as exc:
        raise KitInputError(f"{path}: not a valid {GEOMETRY_FILE} ({exc}); delete it to verify the pairs again in sfm") from None
    return out

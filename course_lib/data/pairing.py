"""Which image pairs to match: every pair, neighbours in file order, or pairs found by image retrieval.

Matching every pair costs ``M (M - 1) / 2`` descriptor matchings; for large photo sets most pairs
share nothing. COLMAP offers the same three choices (``exhaustive_matcher``,
``sequential_matcher``, ``vocab_tree_matcher``):

* :func:`exhaustive_pairs`: all pairs (the default up to :data:`EXHAUSTIVE_MAX` photos).
* :func:`sequential_pairs`: each photo with the next ``overlap`` ones in file order (a video, a
  walk photographed in order).
* :func:`retrieval_pairs`: each photo with the ``k`` photos that look most alike, by a bag of
  visual words (:func:`visual_words`: k-means over a sample of the descriptors; tf-idf weighted,
  cosine similarity: the scoring of a vocabulary tree, with a flat vocabulary), plus the sequential
  neighbours.

:func:`select_pairs` picks by name (``"auto"``: exhaustive up to :data:`EXHAUSTIVE_MAX` photos,
retrieval above).

Introduced in ``notebooks/10_photos_to_nerf.ipynb``.
"""

from __future__ import annotations

import numpy as np

from course_lib.validate import KitInputError

__all__ = ["PAIR_MODES", "EXHAUSTIVE_MAX", "RETRIEVAL_K", "SEQUENTIAL_OVERLAP", "exhaustive_pairs", "sequential_pairs",
           "visual_words", "retrieval_pairs", "select_pairs"]

#: Pair selections by name (``match --pairs``).
PAIR_MODES = ("auto", "exhaustive", "sequential", "retrieval")
#: ``"auto"`` matches every pair up to this many photos (11 175 pairs; about a minute on 2 cores at
#: 1 500 features per photo), retrieval above.
EXHAUSTIVE_MAX = 150
#: Photos retrieved per photo (``"retrieval"``).
RETRIEVAL_K = 30
#: Sequential neighbours per photo (``"sequential"``, and added to ``"retrieval"``).
SEQUENTIAL_OVERLAP = 10


def exhaustive_pairs(n_images: int) -> list[tuple[int, int]]:
    """Every pair ``(i, j)``, ``i < j``, of ``n_images`` photos."""
    M = int(n_images)
    return [(i, j) for i in range(M) for j in range(i + 1, M)]


def sequential_pairs(n_images: int, overlap: int = SEQUENTIAL_OVERLAP) -> list[tuple[int, int]]:
    """``(i, i + d)`` for ``d = 1 .. overlap``: each photo with the next ``overlap`` in file order."""
    M, w = int(n_images), int(overlap)
    if w < 1:
        raise KitInputError(f"overlap = {overlap!r}: expected at least 1 neighbour")
    return [(i, j) for i in range(M) for j in range(i + 1, min(M, i + w + 1))]


def visual_words(feats, n_words: int = 512, sample: int = 100_000, rng: np.random.Generator | None = None):
    """A flat visual vocabulary and the tf-idf weighted, L2-normalized word histogram of every photo.

    Args:
        feats: M :class:`~course_lib.data.features.Features`.
        n_words: vocabulary size (fewer where there are fewer descriptors).
        sample: descriptors drawn (all photos pooled) to run k-means on.
        rng: seeded generator (default seed 0).

    Returns:
        ``(M, n_words)`` float32 histograms; row ``i`` dot row ``j`` is the similarity of photos i and j.
    """
    import cv2

    rng = np.random.default_rng(0) if rng is None else rng
    pooled = np.concatenate([f.descriptors for f in feats if len(f)] or [np.zeros((0, 128), np.float32)])
    if len(pooled) == 0:
        return np.zeros((len(feats), 1), np.float32)
    take = rng.choice(len(pooled), min(sample, len(pooled)), replace=False)
    data = np.ascontiguousarray(pooled[take], np.float32)
    k = int(min(n_words, max(1, len(data) // 20)))
    cv2.setRNGSeed(int(rng.integers(2**31 - 1)))
    _, _, centres = cv2.kmeans(data, k, None, (cv2.TERM_CRITERIA_MAX_ITER + cv2.TERM_CRITERIA_EPS, 8, 1e-3), 1,
                               cv2.KMEANS_PP_CENTERS)
    c2 = (centres**2).sum(axis=1)
    H = np.zeros((len(feats), k), np.float32)
    for i, f in enumerate(feats):
        if len(f):
            words = np.argmin(c2[None, :] - 2.0 * (f.descriptors @ centres.T), axis=1)
            H[i] = np.bincount(words, minlength=k)
    idf = np.log(len(feats) / np.maximum((H > 0).sum(axis=0), 1)).astype(np.float32)
    H = H * idf
    return H / np.maximum(np.linalg.norm(H, axis=1, keepdims=True), 1e-12)


def retrieval_pairs(feats, k: int = RETRIEVAL_K, overlap: int = SEQUENTIAL_OVERLAP,
                    rng: np.random.Generator | None = None) -> list[tuple[int, int]]:
    """Each photo with its ``k`` most similar photos (:func:`visual_words`), plus ``overlap`` sequential neighbours.

    Args:
        feats: M :class:`~course_lib.data.features.Features`.
        k: photos retrieved per photo. overlap: sequential neighbours added (0: none).
        rng: seeded generator for the vocabulary.

    Returns:
        Sorted pairs ``(i, j)``, ``i < j``, each once.
    """
    M = len(feats)
    if M <= k + 1:
        return exhaustive_pairs(M)
    H = visual_words(feats, rng=rng)
    sim = H @ H.T
    np.fill_diagonal(sim, -np.inf)
    top = np.argsort(-sim, axis=1, kind="stable")[:, :k]
    pairs = {(min(i, int(j)), max(i, int(j))) for i in range(M) for j in top[i]}
    if overlap > 0:
        pairs |= set(sequential_pairs(M, overlap))
    return sorted(pairs)


def select_pairs(mode: str, feats, rng: np.random.Generator | None = None, k: int = RETRIEVAL_K,
                 overlap: int = SEQUENTIAL_OVERLAP) -> tuple[list[tuple[int, int]], str]:
    """The pairs to match by ``mode`` (:data:`PAIR_MODES`); ``(pairs, the mode used)``.

    ``"auto"`` is ``"exhaustive"`` up to :data:`EXHAUSTIVE_MAX` photos, ``"retrieval"`` above.
    """
    if mode not in PAIR_MODES:
        raise KitInputError(f"pairs = {mode!r}: expected one of {', '.join(PAIR_MODES)}")
    M = len(feats)
    if mode == "auto":
        mode = "exhaustive" if M <= EXHAUSTIVE_MAX else "retrieval"
    if mode == "exhaustive":
        return exhaustive_pairs(M), mode
    if mode == "sequential":
        return sequential_pairs(M, overlap), mode
    return retrieval_pairs(feats, k, overlap, rng), mode

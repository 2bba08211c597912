"""Two models of one photo set made one: the similarity between their frames, and one model carried into the other.

A later model that grows into the images of an earlier one (:mod:`course_lib.sfm.pipeline`) sees the
same scene in its own frame and scale. :func:`similarity_ransac` finds the similarity
``X_dst = s R X_src + T`` from the points both models triangulated (the same tracks), three at a
time (:func:`course_lib.alignment.align_similarity`, Umeyama); :func:`carry` then brings the
images and points one model has and the other lacks into the other's frame. The mapper's
:meth:`~course_lib.sfm.mapper.IncrementalMapper.merge` decides which model is the base (the larger)
and what counts as an agreeing point (its reprojection in the base's images).

Introduced in ``notebooks/05_bundle_adjustment.ipynb`` (the mapper's stages).
"""

from __future__ import annotations

import numpy as np

from course_lib.alignment import align_similarity

__all__ = ["similarity_ransac", "carry"]


def similarity_ransac(X_src: np.ndarray, X_dst: np.ndarray, agrees, rng: np.random.Generator, max_iterations: int = 200,
                      score_on: int = 500, confidence: float = 0.999):
    """RANSAC for ``X_dst ≈ s R X_src + T`` on corresponding points, refitted on its inliers.

    Args:
        X_src, X_dst: ``(N, 3)`` the same points in the two frames, ``N >= 3``.
        agrees: ``agrees(s, R, T, rows) -> (len(rows),) bool``, which of the points ``rows`` (an
            index array or a slice) the similarity carries onto their counterparts.
        rng: the generator the samples are drawn from.
        max_iterations: at most this many samples of three; fewer once ``confidence`` is reached.
        score_on: samples are scored on at most this many of the points (drawn once).

    Returns:
        ``((s, R (3, 3), T (3,)), inliers (N,) bool)`` or None where no sample has three agreeing points.
    """
    n_pts = len(X_src)
    rows = np.sort(rng.choice(n_pts, min(n_pts, score_on), replace=False))
    best, best_sim, n_iter, trial = 0, None, max_iterations, 0
    while trial < n_iter:
        trial += 1
        pick = rng.choice(n_pts, 3, replace=False)
        sim = align_similarity(X_src[pick], X_dst[pick])
        if not np.isfinite(sim[0]) or sim[0] <= 0 or not np.isfinite(sim[2]).all():
            continue
        n = int(agrees(*sim, rows).sum())
        if n > best:
            best, best_sim = n, sim
            w = n / len(rows)
            n_iter = min(n_iter, int(np.ceil(np.log(1.0 - confidence) / np.log1p(-(w ** 3)))) if w < 1 else 1)
    if best_sim is None or best < 3:
        return None
    inl = agrees(*best_sim, slice(None))
    sim = align_similarity(X_src[inl], X_dst[inl])
    return sim, agrees(*sim, slice(None))


def carry(base: dict, other: dict, s: float, R: np.ndarray, T: np.ndarray) -> tuple[dict, np.ndarray, np.ndarray]:
    """``other``'s images and points that ``base`` lacks, carried into ``base``'s frame by ``X_base = s R X_other + T``.

    Args:
        base, other: model states (:meth:`course_lib.sfm.mapper.IncrementalMapper.state`: ``registered (M,)``,
            ``R (M, 3, 3)``, ``t (M, 3)``, ``X (T, 3)``, ``candidate (T, M)``, ``ref``).
        s, R, T: the similarity from ``other``'s frame to ``base``'s.

    Returns:
        ``(merged state, images carried, points carried)``; where both have an image or a point, ``base``'s is kept.
    """
    new_images = np.flatnonzero(other["registered"] & ~base["registered"])
    new_points = np.flatnonzero(np.isfinite(other["X"]).all(axis=1) & ~np.isfinite(base["X"]).all(axis=1))
    out = {"R": base["R"].copy(), "t": base["t"].copy(), "X": base["X"].copy(), "candidate": base["candidate"].copy(),
           "registered": base["registered"] | other["registered"], "ref": base["ref"]}
    for i in new_images:  # x = R_i X + t_i with X = R^T (X' - T) / s; scaled by s: R_i R^T X' + s t_i - R_i R^T T
        out["R"][i] = other["R"][i] @ R.T
        out["t"][i] = s * other["t"][i] - out["R"][i] @ T
        out["candidate"][:, i] = other["candidate"][:, i]
    out["X"][new_points] = s * other["X"][new_points] @ R.T + T
    return out, new_images, new_points

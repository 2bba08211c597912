"""Refit a model on its inliers while the inlier set grows: the last step of RANSAC.

One loop for every caller, with the solver and the error function as arguments (as
:func:`course_lib.sfm.fundamental.ransac` takes them): notebook 01's RANSAC ends with it, and the
verification of an F carried into a P3 folder (:func:`course_lib.sfm.tracks.from_carried_geometry`)
is nothing else, in the instructor's kit with the batched 8-point and Sampson distance, in the
student kit with the student's own ``eight_point`` and ``sampson_distance``.

Introduced in ``notebooks/01_fundamental_matrix.ipynb``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["refit_on_inliers"]


def refit_on_inliers(solver, error, x1, x2, model, threshold: float, min_size: int, rounds: int = 5):
    """Refit the model on all its inliers and recount them, while the inlier set grows.

    The first refit is always taken (a fit to all inliers beats the fit to a minimal sample);
    later ones only if they keep at least as many inliers.

    Args:
        solver: ``solver(x1 (B, n, 2), x2 (B, n, 2)) -> (models (B, ...), ok (B,) bool)``.
        error: ``error(models (B, ...), x1 (N, 2), x2 (N, 2)) -> (B, N)``.
        x1, x2: ``(N, 2)`` matches. model: the starting model (one, not batched).
        threshold: inlier threshold on ``error``. min_size: the fewest inliers ``solver`` takes.
        rounds: at most this many refits.

    Returns:
        ``(model, distances (N,))``.
    """
    d = error(model[None], x1, x2)[0]
    inliers = d < threshold
    for round_ in range(rounds):
        if inliers.sum() < min_size:
            break
        new, ok = solver(x1[inliers][None], x2[inliers][None])
        if not ok[0]:
            break
        d_new = error(new, x1, x2)[0]
        inl_new = d_new < threshold
        if round_ > 0 and inl_new.sum() < inliers.sum():
            break
        done = np.array_equal(inl_new, inliers)
        model, d, inliers = new[0], d_new, inl_new
        if done:
            break
    return model, d

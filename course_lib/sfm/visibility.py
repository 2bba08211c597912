"""The visibility matrix: which image sees which 3-D point, and the list of observations it implies.

In the course handout the visibility matrix :math:`V` of a scene with :math:`I` cameras and
:math:`J` points has entries

.. math::

    V_{ij} = \\begin{cases} 1 & \\text{if point } j \\text{ is observed in image } i,\\\\
                            0 & \\text{otherwise,} \\end{cases}

and bundle adjustment sums the reprojection error over exactly the pairs with :math:`V_{ij} = 1`.
The kit stores points as rows (see :mod:`course_lib.conventions`), so its visibility matrix is the
transpose, shape ``(T, M)`` for ``T`` points (tracks) and ``M`` images::

    vis[j, i] == V_ij       # point j seen in image i

Observations are kept as a ``(T, M, 2)`` array of pixels with NaN where a point is not seen
(``P3Data.track_uv``, ``SyntheticScene.uv``); :func:`observation_list` flattens it into the three
parallel arrays ``point_idx, camera_idx, uv`` that the residual function of bundle adjustment
works on (one row per term of the sum).

Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from course_lib.conventions import observed_entries
from course_lib.validate import KitInputError

__all__ = ["visibility_matrix", "Observations", "observation_list", "observations_to_uv", "track_lengths"]


def _check_uv(track_uv, name: str = "track_uv") -> np.ndarray:
    try:
        a = np.asarray(track_uv, dtype=float)
    except (TypeError, ValueError):
        raise KitInputError(f"{name} must be a numeric array of shape (T, M, 2), got {type(track_uv).__name__}") from None
    if a.ndim != 3 or a.shape[2] != 2:
        raise KitInputError(
            f"{name} has shape {a.shape}: expected (T, M, 2) = (points, images, pixel u/v) with NaN where a point is not seen"
        )
    half = np.isnan(a[..., 0]) != np.isnan(a[..., 1])
    if half.any():
        j, i = np.argwhere(half)[0]
        raise KitInputError(f"{name}[{j}, {i}] has one NaN coordinate and one number: use NaN for both u and v of an unseen point")
    if np.isinf(a).any():
        raise KitInputError(f"{name} contains inf: use NaN for unseen points")
    return a


def visibility_matrix(track_uv: np.ndarray) -> np.ndarray:
    """The visibility matrix of a set of tracks.

    Args:
        track_uv: ``(T, M, 2)`` pixel coordinates of point ``j`` in image ``i`` at ``[j, i]``, NaN
            in both u and v where the point is not seen.

    Returns:
        ``(T, M)`` bool, ``vis[j, i]`` is True when point ``j`` is seen in image ``i``; this is the
        transpose of the handout's :math:`V_{ij}` (``I x J``, cameras by points) because the kit
        stores points as rows.

    Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
    """
    uv = _check_uv(track_uv)
    return ~np.isnan(uv[..., 0])


@dataclass
class Observations:
    """The observed (point, camera) pairs, one row each: the terms of the bundle-adjustment sum.

    Attributes:
        point_idx: ``(K,)`` int, index of the 3-D point (row of ``X``).
        camera_idx: ``(K,)`` int, index of the image / camera.
        uv: ``(K, 2)`` observed pixel ``(u, v)``.
    """

    point_idx: np.ndarray
    camera_idx: np.ndarray
    uv: np.ndarray

    def __len__(self) -> int:
        return int(self.point_idx.shape[0])


def observation_list(track_uv: np.ndarray, mask: np.ndarray | None = None) -> Observations:
    """Flatten a ``(T, M, 2)`` observation array into the list of observations.

    Args:
        track_uv: ``(T, M, 2)`` pixels, NaN where not seen.
        mask: optional ``(T, M)`` bool; only observations that are seen *and* True here are listed
            (e.g. the inlier observations of registered images).

    Returns:
        :class:`Observations` ordered point by point (row-major over ``(T, M)``).

    Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
    """
    uv = _check_uv(track_uv)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != uv.shape[:2]:
            raise KitInputError(f"mask has shape {mask.shape}: expected {uv.shape[:2]}, the shape of track_uv without the last axis")
    return Observations(*observed_entries(uv, mask))


def observations_to_uv(obs: Observations, n_points: int, n_cameras: int) -> np.ndarray:
    """The inverse of :func:`observation_list`: a ``(n_points, n_cameras, 2)`` array, NaN where unseen."""
    out = np.full((n_points, n_cameras, 2), np.nan)
    pj, ci = np.asarray(obs.point_idx), np.asarray(obs.camera_idx)
    if len(pj) and (pj.max() >= n_points or ci.max() >= n_cameras or pj.min() < 0 or ci.min() < 0):
        raise KitInputError(f"observation indices out of range for {n_points} points and {n_cameras} cameras")
    out[pj, ci] = obs.uv
    return out


def track_lengths(track_uv: np.ndarray) -> np.ndarray:
    """``(T,)`` int: in how many images each point is seen."""
    return visibility_matrix(track_uv).sum(axis=1)

"""The result of incremental SfM (:class:`Reconstruction`) and the small geometric helpers its stages share.

:class:`Reconstruction` holds one model: the poses of its registered images, one 3-D point per
verified track, and the observations it uses. :func:`reprojection_error_matrix` and
:func:`triangulation_angles_deg` are the two measures every stage of the mapper
(:mod:`course_lib.sfm.mapper`) filters with.

Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from course_lib.conventions import camera_center
from course_lib.data.colmap import write_colmap_text
from course_lib.sfm.bundle_adjustment import reprojection_error_stats
from course_lib.validate import KitInputError

__all__ = ["Reconstruction", "reprojection_error_matrix", "triangulation_angles_deg", "error_summary", "image_size_of"]


@dataclass
class Reconstruction:
    """One model of :func:`course_lib.sfm.pipeline.run_sfm`.

    Attributes:
        K: ``(3, 3)`` intrinsics.
        image_names: M file names.
        image_size: ``(W, H)``.
        registered: ``(M,)`` bool, images with a pose.
        R_cw: ``(M, 3, 3)`` rotations, NaN for unregistered images.
        t_cw: ``(M, 3)`` translations, NaN for unregistered images.
        X: ``(T, 3)`` one point per track, NaN where the track was not triangulated.
        rgb: ``(T, 3)`` uint8 colour of each track.
        track_uv: ``(T, M, 2)`` all observations of the verified tracks
            (:mod:`course_lib.sfm.tracks`, not the reader's ``P3Data.track_uv``), NaN where unseen.
        inlier: ``(T, M)`` bool, the observations the reconstruction uses (registered image,
            triangulated point, not rejected as an outlier).
        report: per-stage numbers (see :func:`course_lib.sfm.pipeline.run_sfm`), JSON-serializable.
        others: the other models, largest first, where registration stalled and new models were
            started from the images left over (empty for one model; each has the same fields, its
            own world frame and scale, and ``others == []``).
        k1: radial distortion of a ``SIMPLE_RADIAL`` camera (:mod:`course_lib.data.camera`); the
            pixels in ``track_uv`` are then *undistorted* (where the pinhole ``K`` sees them), and
            :meth:`write_colmap` writes the photos' own pixels and the model.
        camera_model: ``"PINHOLE"`` (K from a calibration file) or ``"SIMPLE_RADIAL"`` (refined).
    """

    K: np.ndarray
    image_names: list[str]
    image_size: tuple[int, int]
    registered: np.ndarray
    R_cw: np.ndarray
    t_cw: np.ndarray
    X: np.ndarray
    rgb: np.ndarray
    track_uv: np.ndarray
    inlier: np.ndarray
    report: dict = field(default_factory=dict)
    others: list = field(default_factory=list)
    k1: float = 0.0
    camera_model: str = "PINHOLE"

    @property
    def n_points(self) -> int:
        """Number of triangulated points."""
        return int(np.isfinite(self.X).all(axis=1).sum())

    @property
    def n_registered(self) -> int:
        """Number of registered images (of this model)."""
        return int(self.registered.sum())

    @property
    def observations(self) -> np.ndarray:
        """``(T, M, 2)`` pixels of the inlier observations, NaN elsewhere (the input of BA)."""
        return np.where(self.inlier[..., None], self.track_uv, np.nan)

    @property
    def centers(self) -> np.ndarray:
        """``(M, 3)`` camera centres, NaN for unregistered images."""
        C = np.full((len(self.image_names), 3), np.nan)
        for i in np.flatnonzero(self.registered):
            C[i] = camera_center(self.R_cw[i], self.t_cw[i])
        return C

    def reprojection_errors(self) -> np.ndarray:
        """``(T, M)`` reprojection error of each inlier observation in pixels, NaN elsewhere."""
        return reprojection_error_matrix(self.K, self.R_cw, self.t_cw, self.X, self.observations)

    def error_stats(self) -> dict[str, float]:
        """rms / mean / median / max reprojection error over the inlier observations (pixels)."""
        e = self.reprojection_errors()
        return reprojection_error_stats(e[np.isfinite(e)])

    def cameras(self) -> list[tuple]:
        """``[(R_cw, t_cw, K, (W, H), name), ...]`` of the registered images (for :mod:`course_lib.viz`)."""
        return [
            (self.R_cw[i], self.t_cw[i], self.K, self.image_size, self.image_names[i]) for i in np.flatnonzero(self.registered)
        ]

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """``(X (P, 3), rgb (P, 3))`` of the triangulated points."""
        ok = np.isfinite(self.X).all(axis=1)
        return self.X[ok], self.rgb[ok]

    def write_colmap(self, folder) -> Path:
        """Write the model as COLMAP text files (:func:`course_lib.data.colmap.write_colmap_text`)."""
        return write_colmap_text(
            folder, self.K, self.image_size, self.image_names, self.R_cw, self.t_cw, self.registered, self.X, self.rgb,
            self.observations, camera_model=self.camera_model, k1=self.k1,
        )


# ---------------------------------------------------------------------------------------------
# Small geometric helpers
# ---------------------------------------------------------------------------------------------


def reprojection_error_matrix(K, R_cw, t_cw, X, uv) -> np.ndarray:
    """``(T, M)`` reprojection errors (pixels) of the finite observations ``uv (T, M, 2)``, NaN elsewhere.

    Observations behind the camera get ``inf``.
    """
    K = np.asarray(K, float)
    T, M = uv.shape[:2]
    E = np.full((T, M), np.nan)
    seen = np.isfinite(uv).all(axis=2) & np.isfinite(X).all(axis=1)[:, None]
    for i in range(M):
        j = np.flatnonzero(seen[:, i])
        if len(j) == 0 or not np.isfinite(R_cw[i]).all():
            continue
        xc = X[j] @ R_cw[i].T + t_cw[i]
        xh = xc @ K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            e = np.linalg.norm(xh[:, :2] / xh[:, 2:3] - uv[j, i], axis=1)
        e[~(xc[:, 2] > 0)] = np.inf
        E[j, i] = e
    return E


def triangulation_angles_deg(X: np.ndarray, centers: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``(T,)`` the largest angle (degrees) between the rays from the observing cameras to each point.

    Args:
        X: ``(T, 3)`` points. centers: ``(M, 3)`` camera centres. mask: ``(T, M)`` which cameras see
            each point. Points seen by fewer than two cameras get 0; NaN where a ray is undefined.

    The rays of each point are unit vectors; the largest angle is the arccosine of the smallest
    dot product between two of them. Points are grouped by how many cameras see them, so each
    group is one batched Gram matrix (no loop over camera pairs).
    """
    mask = np.asarray(mask, bool)
    T = mask.shape[0]
    best = np.zeros(T)
    t, i = np.nonzero(mask)  # row-major: the observations of a point are contiguous
    if len(t) == 0:
        return best
    d = X[t] - centers[i]
    with np.errstate(divide="ignore", invalid="ignore"):
        rays = d / np.linalg.norm(d, axis=1, keepdims=True)
    counts = np.bincount(t, minlength=T)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    for L in np.unique(counts[counts >= 2]):
        pts = np.flatnonzero(counts == L)
        r = rays[start[pts][:, None] + np.arange(L)]  # (n, L, 3)
        dots = np.clip((r @ np.transpose(r, (0, 2, 1))).min(axis=(1, 2)), -1.0, 1.0)
        best[pts] = np.degrees(np.arccos(dots))
    return best


def error_summary(E: np.ndarray) -> dict[str, float]:
    """rms / mean / median / max of the finite entries of a reprojection error array (pixels), rounded to 4 decimals."""
    e = E[np.isfinite(E)]
    s = reprojection_error_stats(e)
    return {k: round(v, 4) for k, v in s.items()}


def image_size_of(data) -> tuple[int, int]:
    """``(W, H)`` of a P3 data set: from its images, or the extent of its pixels where the images are absent."""
    try:
        return tuple(int(v) for v in data.image_size)
    except (KitInputError, FileNotFoundError, OSError, AttributeError):
        uv = data.track_uv
        return (int(np.ceil(np.nanmax(uv[..., 0]) + 1)), int(np.ceil(np.nanmax(uv[..., 1]) + 1)))

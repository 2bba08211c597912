"""The two-view start of a model: a calibrated relative pose, and the pairs that cannot start one.

The mapper (:mod:`course_lib.sfm.mapper`) starts every model from one image pair. Its relative pose
comes from the **calibrated** route, as COLMAP's initial pair does:

1. :func:`calibrated_pose`: the five-point essential matrix (Nistér; OpenCV's
   ``findEssentialMat`` with USAC, on the pair's verified matches, threshold in pixels through
   ``K``), its four pose candidates and the cheirality test (the exercises ``pose_candidates`` and
   ``choose_pose`` of notebooks 02-03, called through :func:`course_lib.exercises.call`: the
   references in the instructor's kit, the student's own in the student kit), then the pose
   refined on the inliers (:func:`refine_pose`: least squares on their Sampson distances to
   ``F = K⁻ᵀ [t]ₓ R K⁻¹``, five parameters).

   The lessons' route -- the 8-point F, then ``E = Kᵀ F K`` -- stays in the notebooks: F has two
   degrees of freedom more than the calibrated geometry, which it spends fitting the noise. On
   texture-poor pairs (a few hundred matches in a small part of the image) the pose taken from it
   fitted the pair's own inliers at a median Sampson distance of 24-26 px while F fitted them at
   0.2 px; the five-point pose keeps them all, and the pair can start a model.
2. :func:`pair_degeneracy`: a pair that a homography explains (pure rotation, a planar scene) or
   whose matches barely move (identical photos: no baseline) cannot start a model; it is named. A
   pair that sees a plane and enough structure off it (``"mostly planar"``: a facade with a few
   balconies) can: the five-point E is not degenerate for a plane, and the points off the plane
   decide between the two poses a plane alone allows. The mapper tries such pairs after the others.

Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from course_lib.conventions import skew
from course_lib.data.two_view import identical_photos
from course_lib.exercises import Fields, call
from course_lib.validate import KitInputError

try:  # the instructor's kit: notebook 01's Sampson distance for many F at once
    from course_lib.sfm.fundamental import sampson_distance_batch
except ImportError:  # the student kit: your sampson_distance of notebook 01
    sampson_distance_batch = None

__all__ = ["H_INLIER_RATIO", "InitialPair", "pair_degeneracy", "calibrated_pose", "refine_pose", "fundamental_from_pose",
           "fundamental_from_essential", "sampson_pixels", "five_point_essential"]

#: A pair whose inliers a homography explains this well is degenerate for a two-view start.
H_INLIER_RATIO = 0.8


@dataclass
class InitialPair:
    """A candidate initial pair: ``images (a, b)``, the two-view ``choice`` (:func:`calibrated_pose`'s, with
    ``R_cw, t_cw, X, in_front, counts``; camera ``a`` at the origin), ``score`` (points in front with an angle >= ``init_min_angle_deg``),
    verified ``inliers`` of the pair, the ``median_angle_deg`` of the points in front, and the
    ``pose_inliers`` of the calibrated pose."""

    images: tuple[int, int]
    choice: object
    score: int
    inliers: int
    median_angle_deg: float
    pose_inliers: int = 0

    def row(self) -> dict:
        return {"images": list(self.images), "score": self.score, "ransac_inliers": self.inliers,
                "pose_inliers": self.pose_inliers, "median_angle_deg": round(self.median_angle_deg, 2)}


def pair_degeneracy(x1: np.ndarray, x2: np.ndarray, K: np.ndarray, threshold_px: float,
                    min_off_plane: int = 20) -> tuple[str, float]:
    """Can a pair start a reconstruction? Identical photos, pure rotation and planar scenes cannot.

    * **identical or near-identical photos**: the matches barely move (median displacement below
      :data:`course_lib.data.two_view.IDENTICAL_PX`): no baseline at all;
    * otherwise a homography ``H`` (OpenCV's RANSAC, ``threshold_px``) is fitted to the pair's
      inliers. If it explains more than :data:`H_INLIER_RATIO` of them: if ``K⁻¹ H K`` is a rotation
      (equal singular values), the camera only turned (no baseline, nothing to triangulate);
      otherwise the points lie on a plane (F is not unique, and a plane alone allows two poses),
      ``"planar"`` -- or ``"mostly planar"`` where ``min_off_plane`` or more matches lie off it:
      those decide between the two poses, and the pair can start a model when no other can.

    Args:
        x1, x2: ``(N, 2)`` inlier matches. K: ``(3, 3)``. threshold_px: pixels.
        min_off_plane: matches the homography does not explain that make a planar pair ``"mostly planar"``.

    Returns:
        ``(kind, ratio)``: kind ``""`` (fine), ``"identical or near-identical photos"``,
        ``"pure rotation"``, ``"planar"`` or ``"mostly planar"``; the share of the matches the
        homography explains.
    """
    import cv2

    if len(x1) < 8:
        return "", 0.0
    if identical_photos(x1, x2):
        return "identical or near-identical photos", 1.0
    # 200 samples of 4 find a homography that explains 80 % of the matches with certainty
    # (1 - 0.8^4)^200 < 1e-40; OpenCV's default of 2000 costs 10x more on the pairs where none does
    H, mask = cv2.findHomography(x1.astype(np.float64), x2.astype(np.float64), cv2.RANSAC, threshold_px,
                                 maxIters=200, confidence=0.999)
    if H is None:
        return "", 0.0
    ratio = float(mask.ravel().astype(bool).mean())
    if ratio <= H_INLIER_RATIO:
        return "", ratio
    s = np.linalg.svd(np.linalg.inv(K) @ H @ K, compute_uv=False)
    if s[0] / s[2] < 1.02:
        return "pure rotation", ratio
    return ("mostly planar" if (~mask.ravel().astype(bool)).sum() >= min_off_plane else "planar"), ratio


def fundamental_from_pose(K: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray) -> np.ndarray:
    """``F = K⁻ᵀ [t]ₓ R K⁻¹`` of camera 2 at ``(R_cw, t_cw)`` against camera 1 at the origin (unit norm)."""
    return fundamental_from_essential(K, skew(t_cw) @ R_cw)


def fundamental_from_essential(K: np.ndarray, E: np.ndarray) -> np.ndarray:
    """``F = K⁻ᵀ E K⁻¹`` (unit norm) of two cameras with the same ``K (3, 3)``; ``E (3, 3)``."""
    Ki = np.linalg.inv(K)
    F = Ki.T @ E @ Ki
    return F / np.linalg.norm(F)


def refine_pose(x1: np.ndarray, x2: np.ndarray, K: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The relative pose refined on matches: least squares on their Sampson distances (pixels).

    Five parameters: a rotation vector (a correction of ``R_cw``) and two angles that turn the
    unit translation within the plane orthogonal to it (its length is not observable).

    Args:
        x1, x2: ``(N, 2)`` inlier matches (N >= 5). K: ``(3, 3)``. R_cw, t_cw: the start.

    Returns:
        ``(R_cw (3, 3), t_cw (3,))``, ``|t_cw| = 1``.
    """
    t0 = t_cw / np.linalg.norm(t_cw)
    e1 = np.cross(t0, [1.0, 0.0, 0.0] if abs(t0[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(t0, e1)

    def pose(p):
        R = Rotation.from_rotvec(p[:3]).as_matrix() @ R_cw
        t = t0 * np.cos(np.hypot(p[3], p[4])) + np.sinc(np.hypot(p[3], p[4]) / np.pi) * (p[3] * e1 + p[4] * e2)
        return R, t / np.linalg.norm(t)

    def residuals(p):
        return sampson_pixels(fundamental_from_pose(K, *pose(p)), x1, x2)

    sol = least_squares(residuals, np.zeros(5), method="lm", xtol=1e-10, ftol=1e-10, max_nfev=200)
    return pose(sol.x)


def sampson_pixels(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """``(N,)`` Sampson distances (pixels) of the matches to ``F``: notebook 01's (the exercise in the student kit)."""
    if sampson_distance_batch is not None:
        return sampson_distance_batch(F[None], x1, x2)[0]
    return np.asarray(call("sampson_distance", F, x1, x2), float).reshape(-1)


def five_point_essential(x1: np.ndarray, x2: np.ndarray, K: np.ndarray, threshold_px: float,
                         seed: int) -> tuple[np.ndarray, np.ndarray] | None:
    """OpenCV's five-point essential matrix inside USAC: ``(E (3, 3), inliers (N,) bool)``, or None where none is found.

    Args:
        x1, x2: ``(N, 2)`` matches (pixels), ``N >= 5``. K: ``(3, 3)`` of both cameras.
        threshold_px: RANSAC threshold (pixels). seed: OpenCV's RANSAC seed (set before the call).
    """
    cv2.setRNGSeed(int(seed))
    E, mask = cv2.findEssentialMat(np.ascontiguousarray(x1, np.float64), np.ascontiguousarray(x2, np.float64),
                                   np.asarray(K, np.float64), cv2.USAC_ACCURATE, 0.999, float(threshold_px))
    if E is None or mask is None or E.shape[0] < 3:
        return None
    return np.array(E[:3]), mask.ravel().astype(bool)


def calibrated_pose(x1: np.ndarray, x2: np.ndarray, K: np.ndarray, threshold_px: float, seed: int):
    """The relative pose of a pair from the five-point essential matrix, refined: ``(choice, inliers (N,) bool)``.

    Camera 1 is the world frame (``R = I, t = 0``), ``|t| = 1``. ``choice`` has the fields of
    ``choose_pose``'s result (``R_cw (3, 3), t_cw (3,), X (N, 3), in_front (N,) bool, counts (4,)``),
    ``X`` and ``in_front`` over all ``N`` matches (the exercise ``triangulate_linear``).

    Args:
        x1, x2: ``(N, 2)`` the pair's verified matches (pixels). K: ``(3, 3)``.
        threshold_px: RANSAC and inlier threshold (Sampson distance, pixels). seed: OpenCV's RANSAC seed.

    Raises:
        KitInputError: fewer than 5 matches, or no essential matrix found.
    """
    if len(x1) < 5:
        raise KitInputError(f"{len(x1)} matches: the five-point algorithm needs at least 5")
    found = five_point_essential(x1, x2, K, threshold_px, seed)
    if found is None:
        raise KitInputError("no essential matrix fits the matches (too few, or all on a line?)")
    E, inl = found
    choice = call("choose_pose", *call("pose_candidates", E), K, x1[inl], x2[inl])
    R, t = refine_pose(x1[inl], x2[inl], K, choice.R_cw, choice.t_cw.reshape(3))
    inl = sampson_pixels(fundamental_from_pose(K, R, t), x1, x2) < threshold_px
    # the refinement cannot tell t from -t (the epipolar geometry is the same): the cheirality test decides again
    choice = call("choose_pose", *call("pose_candidates", skew(t) @ R), K, x1[inl], x2[inl])
    R, t = choice.R_cw.reshape(3, 3), choice.t_cw.reshape(3)
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    X = call("triangulate_linear", P1, K @ np.hstack([R, t[:, None]]), x1, x2)
    front = (X[:, 2] > 0) & ((X @ R.T + t)[:, 2] > 0)  # in front of both cameras
    return Fields(("R_cw", "t_cw", "X", "in_front", "counts"), (R, t, X, front, choice.counts)), inl

"""The camera models of the bundle adjuster: projection and its analytic Jacobian (Ceres' cost functions).

A camera model is a small object with ``n_params``, ``project`` and ``project_jacobian``
(:class:`CameraModel`); :func:`course_lib.sfm.lm.solve` needs nothing else of it. The rotations are
rotation vectors ``r`` with ``R = exp([r]_x)`` and additive updates; ``d(R X)/dr = -[R X]_x R J_r(r)``
(:func:`right_jacobian_so3`). The whole method: :mod:`course_lib.sfm.lm`.

Introduced in ``notebooks/05_bundle_adjustment.ipynb`` ("How does this scale?").
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from scipy.spatial.transform import Rotation

from course_lib.validate import intrinsics

__all__ = ["CameraModel", "PinholeCamera", "BALCamera", "SimpleRadialCamera", "rotvec_to_matrix", "right_jacobian_so3"]


def rotvec_to_matrix(rvec: np.ndarray) -> np.ndarray:
    """``(M, 3, 3)`` rotation matrices ``exp([r]_x)`` of rotation vectors ``(M, 3)`` (Rodrigues)."""
    return Rotation.from_rotvec(np.asarray(rvec, float).reshape(-1, 3)).as_matrix().reshape(-1, 3, 3)


def _skew_rows(v: np.ndarray) -> np.ndarray:
    """``(K, 3, 3)`` cross-product matrices of the rows of ``v (K, 3)``."""
    S = np.zeros((len(v), 3, 3))
    S[:, 0, 1], S[:, 0, 2] = -v[:, 2], v[:, 1]
    S[:, 1, 0], S[:, 1, 2] = v[:, 2], -v[:, 0]
    S[:, 2, 0], S[:, 2, 1] = -v[:, 1], v[:, 0]
    return S


def right_jacobian_so3(rvec: np.ndarray) -> np.ndarray:
    """``(M, 3, 3)`` right Jacobians of SO(3), ``exp([r + d]_x) ~ exp([r]_x) exp([J_r(r) d]_x)``.

    ``J_r(r) = I - (1 - cos a)/a^2 [r]_x + (a - sin a)/a^3 [r]_x^2`` with ``a = |r|`` (Taylor
    series below ``a = 1e-4``).
    """
    rvec = np.asarray(rvec, float).reshape(-1, 3)
    a = np.linalg.norm(rvec, axis=1)
    small = a < 1e-4
    a_safe = np.where(small, 1.0, a)
    c1 = np.where(small, 0.5 - a**2 / 24.0, (1.0 - np.cos(a_safe)) / a_safe**2)
    c2 = np.where(small, 1.0 / 6.0 - a**2 / 120.0, (a_safe - np.sin(a_safe)) / a_safe**3)
    S = _skew_rows(rvec)
    return np.eye(3) - c1[:, None, None] * S + c2[:, None, None] * (S @ S)


def _mm(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Batched small matrix product ``(K, a, b) @ (K, b, c) -> (K, a, c)``."""
    return np.matmul(A, B)


def _rigid(cameras: np.ndarray, X: np.ndarray, cam_idx: np.ndarray, with_jacobian: bool):
    """``P = R(r) X + t`` per observation, and optionally ``dP/dr`` (K, 3, 3) and ``R`` per observation."""
    R = rotvec_to_matrix(cameras[:, :3])
    Rk = R[cam_idx]
    RX = np.einsum("kij,kj->ki", Rk, X)
    P = RX + cameras[cam_idx, 3:6]
    if not with_jacobian:
        return P, None, None
    RJ = (R @ right_jacobian_so3(cameras[:, :3]))[cam_idx]
    dP_dr = -_mm(_skew_rows(RX), RJ)
    return P, dP_dr, Rk


class CameraModel(Protocol):
    """What :func:`solve` needs from a camera model.

    Attributes:
        n_params: parameters per camera (``n``).
        param_names: their names, for messages and docs.
    """

    n_params: int
    param_names: tuple[str, ...]

    def project(self, cameras: np.ndarray, X: np.ndarray, cam_idx: np.ndarray) -> np.ndarray:
        """Project the observation's point ``X[k]`` (``(K, 3)``, gathered per observation) with
        camera ``cameras[cam_idx[k]]`` (``cameras``: ``(M, n)``); returns ``(K, 2)``."""

    def project_jacobian(self, cameras: np.ndarray, X: np.ndarray, cam_idx: np.ndarray):
        """Like :meth:`project`, also returning ``d proj / d camera`` ``(K, 2, n)`` and
        ``d proj / d X`` ``(K, 2, 3)``: ``(proj, J_cam, J_pt)``."""


class PinholeCamera:
    """The lesson's camera: ``K`` fixed (shared), 6 parameters ``(r, t_cw)`` in the kit's OpenCV axes.

    ``x_c = R(r) X + t``, ``(u, v) = (K x_c)[:2] / z_c`` (:func:`course_lib.conventions.project`).
    The projection is notebook 05's exercise ``reprojection_residuals`` (called with observations
    at 0: in the instructor's kit the reference, in the student kit the student's own; see
    :mod:`course_lib.exercises`); the Jacobian is the kit's, analytic.
    """

    param_names = ("rx", "ry", "rz", "tx", "ty", "tz")
    n_params = 6

    def __init__(self, K: np.ndarray):
        self.K = intrinsics(K)

    def project(self, cameras, X, cam_idx):
        from course_lib.exercises import call

        n = len(cam_idx)
        params = np.concatenate([np.asarray(cameras, float).ravel(), np.asarray(X, float).ravel()])
        r = call("reprojection_residuals", params, len(cameras), n, np.asarray(cam_idx, np.int64), np.arange(n),
                 np.zeros((n, 2)), self.K)
        return r.reshape(n, 2)

    def project_jacobian(self, cameras, X, cam_idx):
        proj = self.project(cameras, X, cam_idx)
        P, dP_dr, Rk = _rigid(cameras, X, cam_idx, True)
        K = self.K
        x, y, z = P[:, 0], P[:, 1], P[:, 2]
        iz = 1.0 / z
        fx, s, fy = K[0, 0], K[0, 1], K[1, 1]
        G = np.zeros((len(z), 2, 3))  # d proj / d P
        G[:, 0, 0] = fx * iz
        G[:, 0, 1] = s * iz
        G[:, 0, 2] = -(fx * x + s * y) * iz**2
        G[:, 1, 1] = fy * iz
        G[:, 1, 2] = -fy * y * iz**2
        J_cam = np.empty((len(z), 2, 6))
        J_cam[:, :, 0:3] = _mm(G, dP_dr)
        J_cam[:, :, 3:6] = G
        return proj, J_cam, _mm(G, Rk)


class BALCamera:
    """The camera of "Bundle Adjustment in the Large": 9 parameters ``(r, t, f, k1, k2)``.

    ``P = R(r) X + t``, ``p = -P[:2] / P.z``, ``proj = f (1 + k1 |p|^2 + k2 |p|^4) p`` (pixels from
    the image centre, y up, camera looking down -z; see :mod:`course_lib.data.bal`).
    """

    param_names = ("rx", "ry", "rz", "tx", "ty", "tz", "f", "k1", "k2")
    n_params = 9

    def project(self, cameras, X, cam_idx):
        P, _, _ = _rigid(cameras, X, cam_idx, False)
        p = -P[:, :2] / P[:, 2:3]
        n = (p**2).sum(axis=1)
        f, k1, k2 = cameras[cam_idx, 6], cameras[cam_idx, 7], cameras[cam_idx, 8]
        return (f * (1.0 + k1 * n + k2 * n**2))[:, None] * p

    def project_jacobian(self, cameras, X, cam_idx):
        P, dP_dr, Rk = _rigid(cameras, X, cam_idx, True)
        iz = 1.0 / P[:, 2]
        p = -P[:, :2] * iz[:, None]
        n = (p**2).sum(axis=1)
        f, k1, k2 = cameras[cam_idx, 6], cameras[cam_idx, 7], cameras[cam_idx, 8]
        rad = 1.0 + k1 * n + k2 * n**2
        proj = (f * rad)[:, None] * p
        # d proj / d p = f (rad I + 2 (k1 + 2 k2 n) p p^T);  d p / d P = -[[1/z, 0, -x/z^2], [0, 1/z, -y/z^2]]
        c = 2.0 * f * (k1 + 2.0 * k2 * n)
        fr = f * rad
        Dp = c[:, None, None] * (p[:, :, None] * p[:, None, :])
        Dp[:, 0, 0] += fr
        Dp[:, 1, 1] += fr
        # G = Dp @ dp/dP, with dp/dP = [[-iz, 0, -p_x iz], [0, -iz, -p_y iz]] (since -x/z = p_x)
        G = np.empty((len(n), 2, 3))
        G[:, :, 0] = -Dp[:, :, 0] * iz[:, None]
        G[:, :, 1] = -Dp[:, :, 1] * iz[:, None]
        G[:, :, 2] = -(Dp[:, :, 0] * p[:, 0, None] + Dp[:, :, 1] * p[:, 1, None]) * iz[:, None]
        J_cam = np.empty((len(n), 2, 9))
        J_cam[:, :, 0:3] = _mm(G, dP_dr)
        J_cam[:, :, 3:6] = G
        J_cam[:, :, 6] = rad[:, None] * p
        J_cam[:, :, 7] = (f * n)[:, None] * p
        J_cam[:, :, 8] = (f * n**2)[:, None] * p
        return proj, J_cam, _mm(G, Rk)


class SimpleRadialCamera:
    """COLMAP's ``SIMPLE_RADIAL`` camera with its intrinsics *shared* by all cameras and refined.

    Per camera 6 parameters ``(r, t_cw)`` (the kit's OpenCV axes, as :class:`PinholeCamera`); shared
    by every camera 2 parameters ``(f, k1)`` (:attr:`n_shared`), the principal point ``(cx, cy)``
    fixed. ``P = R(r) X + t``, ``(x, y) = P[:2] / P.z``, ``d = 1 + k1 (x^2 + y^2)``,
    ``(u, v) = f d (x, y) + (cx, cy)`` (:func:`course_lib.data.camera.distort`).

    Args:
        principal_point: ``(cx, cy)`` in pixels (kit convention).
    """

    param_names = ("rx", "ry", "rz", "tx", "ty", "tz")
    n_params = 6
    shared_names = ("f", "k1")
    n_shared = 2

    def __init__(self, principal_point):
        self.c = np.asarray(principal_point, float).reshape(2)

    def project(self, cameras, X, cam_idx, shared):
        P, _, _ = _rigid(cameras, X, cam_idx, False)
        xy = P[:, :2] / P[:, 2:3]
        f, k1 = shared
        return f * (1.0 + k1 * (xy**2).sum(axis=1))[:, None] * xy + self.c

    def project_jacobian(self, cameras, X, cam_idx, shared):
        """``(proj (K, 2), J_cam (K, 2, 6), J_pt (K, 2, 3), J_shared (K, 2, 2))``."""
        P, dP_dr, Rk = _rigid(cameras, X, cam_idx, True)
        iz = 1.0 / P[:, 2]
        xy = P[:, :2] * iz[:, None]
        r2 = (xy**2).sum(axis=1)
        f, k1 = shared
        d = 1.0 + k1 * r2
        proj = (f * d)[:, None] * xy + self.c
        # d proj / d xy = f (d I + 2 k1 xy xyᵀ);  d xy / d P = [[1/z, 0, -x/z], [0, 1/z, -y/z]]
        Dxy = (2.0 * f * k1) * (xy[:, :, None] * xy[:, None, :])
        Dxy[:, 0, 0] += f * d
        Dxy[:, 1, 1] += f * d
        G = np.empty((len(iz), 2, 3))
        G[:, :, 0] = Dxy[:, :, 0] * iz[:, None]
        G[:, :, 1] = Dxy[:, :, 1] * iz[:, None]
        G[:, :, 2] = -(Dxy[:, :, 0] * xy[:, 0, None] + Dxy[:, :, 1] * xy[:, 1, None]) * iz[:, None]
        J_cam = np.empty((len(iz), 2, 6))
        J_cam[:, :, 0:3] = _mm(G, dP_dr)
        J_cam[:, :, 3:6] = G
        J_sh = np.stack([d[:, None] * xy, (f * r2)[:, None] * xy], axis=2)
        return proj, J_cam, _mm(G, Rk), J_sh

"""Loader (and writer) for "Bundle Adjustment in the Large" (BAL) problems.

BAL (Agarwal, Snavely, Seitz, Szeliski, ECCV 2010, https://grail.cs.washington.edu/projects/bal/)
publishes real bundle-adjustment problems as text files, usually compressed with bzip2::

    <n_cameras> <n_points> <n_observations>
    <camera_index> <point_index> <x> <y>        # n_observations lines
    <9 numbers per camera, one per line>        # Rodrigues r (3), t (3), f, k1, k2
    <3 numbers per point, one per line>         # X, Y, Z

Camera model of BAL (not the kit's!)
    ::

        P  = R(r) X + t                         # R(r): Rodrigues rotation of the rotation vector r
        p  = -P[:2] / P[2]                      # perspective division with a minus sign
        p' = f (1 + k1 |p|^2 + k2 |p|^4) p      # radial distortion, then the focal length

    The observed ``(x, y)`` is in pixels with the origin at the image **centre**, x to the right
    and **y up**, and the camera looks down its **-z** axis (points in front have ``P.z < 0``),
    the OpenGL / Bundler convention.

How it relates to the kit's convention (:mod:`course_lib.conventions`: OpenCV axes, x right, y
down, z forward, pixel origin at the top-left corner)
    Flip the camera's y and z axes, ``D = diag(1, -1, -1)``: ``R_cw = D R(r)``, ``t_cw = D t``.
    Then ``x_cam = D P`` has ``z_cam = -P.z > 0`` in front, and ``x_cam[:2] / z_cam = (p_x, -p_y)``.
    So with the kit's pixels ``(u, v) = (c_x + x, c_y - y)`` (image centre ``(c_x, c_y)``, unknown
    in BAL, so the kit keeps BAL's own centred coordinates) and ``K = [[f, 0, c_x], [0, f, c_y],
    [0, 0, 1]]`` the two models agree when ``k1 = k2 = 0``; BAL's distortion is COLMAP's
    ``RADIAL`` camera model (``f, cx, cy, k1, k2``). :func:`bal_to_opencv` does this conversion.

Introduced in ``notebooks/05_bundle_adjustment.ipynb`` ("How does this scale?").
"""

from __future__ import annotations

import bz2
import gzip
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from course_lib.validate import KitInputError, existing_path

__all__ = ["BALProblem", "load_bal", "write_bal", "bal_to_opencv"]

#: y/z flip between BAL's camera axes (y up, looking down -z) and the kit's OpenCV axes.
FLIP_YZ = np.diag([1.0, -1.0, -1.0])


@dataclass
class BALProblem:
    """One bundle-adjustment problem in BAL's conventions (see the module docstring).

    Attributes:
        camera_params: ``(n_cameras, 9)``: Rodrigues rotation vector (3), t (3), f, k1, k2.
        points: ``(n_points, 3)`` world points.
        cam_idx: ``(n_obs,)`` int, camera of each observation.
        pt_idx: ``(n_obs,)`` int, point of each observation.
        obs: ``(n_obs, 2)`` observed ``(x, y)``, pixels from the image centre, y up.
        name: file name it came from (or "").
    """

    camera_params: np.ndarray
    points: np.ndarray
    cam_idx: np.ndarray
    pt_idx: np.ndarray
    obs: np.ndarray
    name: str = ""

    @property
    def n_cameras(self) -> int:
        return int(self.camera_params.shape[0])

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_obs(self) -> int:
        return int(self.obs.shape[0])

    def __repr__(self) -> str:
        return f"BALProblem({self.name!r}: {self.n_cameras} cameras, {self.n_points} points, {self.n_obs} observations)"


def _open_text(path: Path) -> str:
    raw = path.read_bytes()
    try:
        if raw[:3] == b"BZh":
            raw = bz2.decompress(raw)
        elif raw[:2] == b"\x1f\x8b":
            raw = gzip.decompress(raw)
    except (OSError, EOFError, ValueError) as exc:
        raise KitInputError(f"{path} is a damaged or truncated compressed file ({exc}): download it again") from None
    try:
        return raw.decode("ascii")
    except UnicodeDecodeError:
        raise KitInputError(f"{path} is not a BAL text file (it contains non-text bytes); .txt, .bz2 or .gz expected") from None


def load_bal(path) -> BALProblem:
    """Read a BAL problem from a ``.txt``, ``.txt.bz2`` or ``.txt.gz`` file.

    Args:
        path: file path, e.g. ``course_data("bal-ladybug")``.

    Returns:
        :class:`BALProblem` (float64 arrays, int64 indices).

    Raises:
        KitInputError: the file is missing, compressed badly, not numeric, truncated (fewer
            numbers than the header announces), has extra numbers, or indices out of range.

    Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
    """
    path = existing_path(path, "BAL problem file")
    text = _open_text(path)
    tokens = text.split()
    if len(tokens) < 3:
        raise KitInputError(f"{path} is empty or has no header: expected '<n_cameras> <n_points> <n_observations>'")
    try:
        n_cam, n_pts, n_obs = (int(tok) for tok in tokens[:3])
    except ValueError:
        raise KitInputError(
            f"{path}: the first line must be three integers '<n_cameras> <n_points> <n_observations>', got {' '.join(tokens[:3])!r}"
        ) from None
    if min(n_cam, n_pts, n_obs) <= 0:
        raise KitInputError(f"{path}: header says {n_cam} cameras, {n_pts} points, {n_obs} observations; all must be positive")
    expected = 3 + 4 * n_obs + 9 * n_cam + 3 * n_pts
    if len(tokens) < expected:
        have = len(tokens) - 3
        where = (
            f"in the observations (line {2 + have // 4})" if have < 4 * n_obs else
            "in the camera parameters" if have < 4 * n_obs + 9 * n_cam else "in the points"
        )
        raise KitInputError(
            f"{path} is truncated: the header announces {n_obs} observations, {n_cam} cameras and {n_pts} points "
            f"({expected} numbers) but the file has {len(tokens)}; it ends {where}. Download it again."
        )
    if len(tokens) > expected:
        raise KitInputError(
            f"{path} has {len(tokens) - expected} more numbers than its header announces ({n_obs} observations, "
            f"{n_cam} cameras, {n_pts} points): is it a BAL file?"
        )
    try:
        values = np.array(tokens[3:], dtype=float)
    except ValueError:
        bad = next(tok for tok in tokens[3:] if not _is_number(tok))
        raise KitInputError(f"{path} contains {bad!r} where a number was expected: is it a BAL file?") from None
    if not np.isfinite(values).all():
        raise KitInputError(f"{path} contains NaN or inf values")
    o = values[: 4 * n_obs].reshape(n_obs, 4)
    idx = o[:, :2]
    if not np.array_equal(idx, np.round(idx)):
        k = int(np.flatnonzero((idx != np.round(idx)).any(axis=1))[0])
        raise KitInputError(f"{path}: observation {k} (line {k + 2}) has non-integer indices {idx[k].tolist()}")
    cam_idx = idx[:, 0].astype(np.int64)
    pt_idx = idx[:, 1].astype(np.int64)
    for arr, n, what in ((cam_idx, n_cam, "camera"), (pt_idx, n_pts, "point")):
        bad = (arr < 0) | (arr >= n)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise KitInputError(f"{path}: observation {k} (line {k + 2}) names {what} {arr[k]}, but there are only {n} {what}s")
    cams = values[4 * n_obs : 4 * n_obs + 9 * n_cam].reshape(n_cam, 9)
    pts = values[4 * n_obs + 9 * n_cam :].reshape(n_pts, 3)
    return BALProblem(cams, pts, cam_idx, pt_idx, o[:, 2:].copy(), name=path.name)


def _is_number(tok: str) -> bool:
    try:
        float(tok)
        return True
    except ValueError:
        return False


def write_bal(path, problem: BALProblem) -> Path:
    """Write a problem in BAL's text format (bzip2-compressed if ``path`` ends with ``.bz2``)."""
    p = problem
    lines = [f"{p.n_cameras} {p.n_points} {p.n_obs}"]
    lines += [f"{c} {j} {x:.10e} {y:.10e}" for c, j, (x, y) in zip(p.cam_idx, p.pt_idx, p.obs)]
    lines += [f"{v:.16e}" for v in np.asarray(p.camera_params, float).ravel()]
    lines += [f"{v:.16e}" for v in np.asarray(p.points, float).ravel()]
    data = ("\n".join(lines) + "\n").encode("ascii")
    path = Path(path)
    path.write_bytes(bz2.compress(data) if path.suffix == ".bz2" else data)
    return path


def bal_to_opencv(camera_params: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """BAL cameras in the kit's OpenCV axes.

    Args:
        camera_params: ``(M, 9)`` BAL camera parameters.

    Returns:
        ``R_cw (M, 3, 3)``, ``t_cw (M, 3)`` (OpenCV axes: z forward, y down) and ``(M, 3)``
        intrinsics ``(f, k1, k2)``. A point with BAL observation ``(x, y)`` has the kit's pixel
        ``(c_x + x, c_y - y)`` for an image centre ``(c_x, c_y)``.
    """
    from scipy.spatial.transform import Rotation

    c = np.asarray(camera_params, float).reshape(-1, 9)
    R = Rotation.from_rotvec(c[:, :3]).as_matrix()
    return FLIP_YZ @ R, c[:, 3:6] @ FLIP_YZ, c[:, 6:9].copy()

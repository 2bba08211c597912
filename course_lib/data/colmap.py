"""COLMAP text models: write the kit's reconstruction so COLMAP / pycolmap can read it, and read one back.

A COLMAP text model is a folder with three files (https://colmap.github.io/format.html):

``cameras.txt``
    ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]``; the kit writes one camera shared by all images:
    ``PINHOLE`` (``fx fy cx cy``) where K came from a calibration file, ``SIMPLE_RADIAL``
    (``f cx cy k1``, :mod:`course_lib.data.camera`) where sfm refined it.
``images.txt``
    two lines per registered image: ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME``, then
    ``POINTS2D[]`` as ``(X, Y, POINT3D_ID)`` triples (``-1`` for a 2-D point without a 3-D point).
    The pose is COLMAP's ``cam_from_world``, the kit's ``R_cw, t_cw`` (x_cam = R_cw X + t_cw): the
    quaternion is that of ``R_cw`` (scalar first), ``T = t_cw``.
``points3D.txt``
    ``POINT3D_ID X Y Z R G B ERROR TRACK[]`` with the track as ``(IMAGE_ID, POINT2D_IDX)`` pairs;
    ``ERROR`` is the point's mean reprojection error in pixels.

Pixel convention: COLMAP puts the *corner* of the top-left pixel at (0, 0), so the centre of
that pixel is (0.5, 0.5); the kit puts the centre at (0, 0) (:mod:`course_lib.conventions`). The
writer adds 0.5 to the principal point and to every 2-D point and the reader subtracts it, so
projections and reprojection errors are the same in both.

Image ids are ``index + 1`` (the P3 numbering); only registered images are written, so ids of
unregistered images are missing from the model.

Introduced in ``notebooks/05_bundle_adjustment.ipynb`` (the pipeline's output).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from course_lib.data.camera import distort_pixels
from course_lib.validate import KitInputError, existing_path, intrinsics, rotation

__all__ = ["ColmapModel", "read_colmap_text", "write_colmap_text"]

#: Added to kit pixel coordinates to get COLMAP's (centre of the top-left pixel at 0.5, 0.5).
PIXEL_OFFSET = 0.5


@dataclass
class ColmapModel:
    """A COLMAP text model read back by :func:`read_colmap_text`.

    Attributes:
        K: ``(3, 3)`` intrinsics in the kit's pixel convention.
        image_size: ``(W, H)``.
        image_names: names of the images in the model (registered ones), by increasing image id.
        image_ids: ``(M,)`` their COLMAP ids.
        R_cw: ``(M, 3, 3)``. t_cw: ``(M, 3)``.
        point_ids: ``(P,)`` COLMAP ids of the 3-D points.
        X: ``(P, 3)``. rgb: ``(P, 3)`` uint8. error: ``(P,)`` mean reprojection error (pixels).
        uv: ``(P, M, 2)`` the track of each point in the kit's pixel convention, NaN where unseen
            (the photos' own pixels: distorted, for a ``SIMPLE_RADIAL`` camera).
        camera_model: ``"PINHOLE"``, ``"SIMPLE_PINHOLE"`` or ``"SIMPLE_RADIAL"``.
        k1: the radial term of ``SIMPLE_RADIAL`` (0 otherwise; ``K`` is its pinhole part).
    """

    K: np.ndarray
    image_size: tuple[int, int]
    image_names: list[str]
    image_ids: np.ndarray
    R_cw: np.ndarray
    t_cw: np.ndarray
    point_ids: np.ndarray
    X: np.ndarray
    rgb: np.ndarray
    error: np.ndarray
    uv: np.ndarray
    camera_model: str = "PINHOLE"
    k1: float = 0.0


def _num(v) -> str:
    """Shortest text that reads back to the same double (numpy scalars print as np.float64(...))."""
    return repr(float(v))


def _mean_errors(K, R_cw, t_cw, X, uv, mask):
    """``(T,)`` mean reprojection error of each point over its observations in ``mask``."""
    T, M = mask.shape
    err = np.full(T, np.nan)
    tot = np.zeros(T)
    cnt = np.zeros(T)
    for i in range(M):
        j = np.flatnonzero(mask[:, i])
        if len(j) == 0:
            continue
        xc = X[j] @ R_cw[i].T + t_cw[i]
        xh = xc @ K.T
        e = np.linalg.norm(xh[:, :2] / xh[:, 2:3] - uv[j, i], axis=1)
        tot[j] += e
        cnt[j] += 1
    ok = cnt > 0
    err[ok] = tot[ok] / cnt[ok]
    return err


def write_colmap_text(
    folder,
    K: np.ndarray,
    image_size: tuple[int, int],
    image_names: list[str],
    R_cw: np.ndarray,
    t_cw: np.ndarray,
    registered: np.ndarray,
    X: np.ndarray,
    rgb: np.ndarray,
    observations: np.ndarray,
    camera_model: str = "PINHOLE",
    k1: float = 0.0,
) -> Path:
    """Write a reconstruction as a COLMAP text model (``cameras.txt``, ``images.txt``, ``points3D.txt``).

    Args:
        folder: output folder (created if needed; the three files are overwritten).
        K: ``(3, 3)`` intrinsics (kit pixel convention), shared by all images.
        image_size: ``(W, H)`` in pixels.
        image_names: M file names.
        R_cw: ``(M, 3, 3)`` rotations; rows of unregistered images are ignored (may be NaN).
        t_cw: ``(M, 3)`` translations; likewise.
        registered: ``(M,)`` bool, which images have a pose (only these are written).
        X: ``(T, 3)`` points, NaN rows for tracks that were not triangulated (not written).
        rgb: ``(T, 3)`` uint8 colours.
        observations: ``(T, M, 2)`` pixels of the observations to write (the inliers), NaN elsewhere.
            Observations of points that were not triangulated are written as 2-D points with
            ``POINT3D_ID = -1``; observations in unregistered images are dropped. For
            ``SIMPLE_RADIAL`` these are the undistorted pixels (the pinhole ``K``'s); the file gets
            the photos' own (distorted) ones.
        camera_model: ``"PINHOLE"`` or ``"SIMPLE_RADIAL"`` (then ``K[0, 0]`` is the focal length).
        k1: the radial term of ``SIMPLE_RADIAL``.

    Returns:
        The folder.

    Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
    """
    K = intrinsics(K)
    W, H = (int(v) for v in image_size)
    names = [str(n) for n in image_names]
    registered, R_cw, t_cw = _checked_poses(names, registered, R_cw, t_cw)
    X, rgb, uv = _checked_points(len(names), X, rgb, observations)
    has_X = np.isfinite(X).all(axis=1)
    seen = np.isfinite(uv).all(axis=2) & registered[None, :]  # the observations written (2-D points)
    point_id = np.full(len(X), -1, dtype=np.int64)
    point_id[has_X] = np.arange(1, int(has_X.sum()) + 1)

    if camera_model not in ("PINHOLE", "SIMPLE_RADIAL"):
        raise KitInputError(f"camera_model={camera_model!r}: the kit writes PINHOLE or SIMPLE_RADIAL")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    _write_cameras(folder / "cameras.txt", K, W, H, camera_model, k1)
    uv_file = distort_pixels(uv, K, k1) if camera_model == "SIMPLE_RADIAL" else uv
    point2d_idx = _write_images(folder / "images.txt", names, R_cw, t_cw, registered, uv_file, seen, point_id)
    R_safe = np.where(registered[:, None, None], R_cw, np.eye(3))
    t_safe = np.where(registered[:, None], t_cw, 0.0)
    in_track = seen & has_X[:, None]
    errors = _mean_errors(K, R_safe, t_safe, np.where(has_X[:, None], X, 0.0), uv, in_track)
    _write_points(folder / "points3D.txt", X, rgb, errors, in_track, point_id, point2d_idx)
    return folder


def _checked_poses(names, registered, R_cw, t_cw):
    """``registered`` (M,) bool, ``R_cw`` (M, 3, 3), ``t_cw`` (M, 3), checked for the registered images."""
    M = len(names)
    registered = np.asarray(registered, dtype=bool)
    if registered.shape != (M,):
        raise KitInputError(f"registered has shape {registered.shape}: expected ({M},), one flag per image name")
    R_cw = np.asarray(R_cw, float)
    t_cw = np.asarray(t_cw, float)
    if R_cw.shape != (M, 3, 3) or t_cw.shape != (M, 3):
        raise KitInputError(f"R_cw {R_cw.shape} and t_cw {t_cw.shape} must be ({M}, 3, 3) and ({M}, 3)")
    for i in np.flatnonzero(registered):
        rotation(R_cw[i], f"R_cw[{i}]", atol=1e-5)
        if not np.isfinite(t_cw[i]).all():
            raise KitInputError(f"t_cw[{i}] of registered image {names[i]} contains NaN")
    return registered, R_cw, t_cw


def _checked_points(M: int, X, rgb, observations):
    """``X`` (T, 3) float, ``rgb`` (T, 3) uint8, observations (T, M, 2) float, checked."""
    X = np.asarray(X, float)
    if X.ndim != 2 or X.shape[1] != 3:
        raise KitInputError(f"X has shape {X.shape}: expected (T, 3)")
    T = X.shape[0]
    rgb = np.asarray(rgb)
    if rgb.shape != (T, 3):
        raise KitInputError(f"rgb has shape {rgb.shape}: expected ({T}, 3), one colour per point")
    uv = np.asarray(observations, float)
    if uv.shape != (T, M, 2):
        raise KitInputError(f"observations has shape {uv.shape}: expected ({T}, {M}, 2), NaN where not observed")
    return X, np.clip(np.round(rgb.astype(float)), 0, 255).astype(np.uint8), uv


def _write_cameras(path: Path, K: np.ndarray, W: int, H: int, model: str, k1: float) -> None:
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2] + PIXEL_OFFSET, K[1, 2] + PIXEL_OFFSET
    params = (fx, fy, cx, cy) if model == "PINHOLE" else (fx, cx, cy, k1)
    with open(path, "w") as f:
        f.write("# Camera list with one line of data per camera:\n")
        f.write("#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
        f.write("# Number of cameras: 1\n")
        f.write(f"1 {model} {W} {H} {' '.join(_num(v) for v in params)}\n")


def _write_images(path: Path, names, R_cw, t_cw, registered, uv, seen, point_id) -> np.ndarray:
    """Write ``images.txt``; returns (T, M) the index of each observation in its image's POINTS2D list."""
    T, M = seen.shape
    point2d_idx = np.full((T, M), -1, dtype=np.int64)
    lines = []
    for i in np.flatnonzero(registered):
        j = np.flatnonzero(seen[:, i])
        point2d_idx[j, i] = np.arange(len(j))
        q = Rotation.from_matrix(R_cw[i]).as_quat()  # x, y, z, w
        qw, qx, qy, qz = (q if q[3] >= 0 else -q)[[3, 0, 1, 2]]
        tx, ty, tz = t_cw[i]
        lines.append(f"{i + 1} {_num(qw)} {_num(qx)} {_num(qy)} {_num(qz)} {_num(tx)} {_num(ty)} {_num(tz)} 1 {names[i]}\n")
        pts = uv[j, i] + PIXEL_OFFSET
        lines.append(" ".join(f"{_num(u)} {_num(v)} {int(point_id[jj])}" for (u, v), jj in zip(pts, j)) + "\n")
    n_reg = int(registered.sum())
    with open(path, "w") as f:
        f.write("# Image list with two lines of data per image:\n")
        f.write("#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n")
        f.write("#   POINTS2D[] as (X, Y, POINT3D_ID)\n")
        f.write(f"# Number of images: {n_reg}, mean observations per image: {seen.sum() / max(n_reg, 1):.6f}\n")
        f.writelines(lines)
    return point2d_idx


def _write_points(path: Path, X, rgb, errors, in_track, point_id, point2d_idx) -> None:
    has_X = np.isfinite(X).all(axis=1)
    n_pts = int(has_X.sum())
    tracks = in_track.sum(axis=1)
    with open(path, "w") as f:
        f.write("# 3D point list with one line of data per point:\n")
        f.write("#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n")
        f.write(f"# Number of points: {n_pts}, mean track length: {tracks[has_X].mean() if n_pts else 0:.6f}\n")
        for j in np.flatnonzero(has_X):
            track = " ".join(f"{i + 1} {int(point2d_idx[j, i])}" for i in np.flatnonzero(in_track[j]))
            e = errors[j] if np.isfinite(errors[j]) else 0.0
            x, y, z = X[j]
            r, g, b = (int(c) for c in rgb[j])
            f.write(f"{int(point_id[j])} {_num(x)} {_num(y)} {_num(z)} {r} {g} {b} {_num(e)} {track}\n")


def _data_lines(path: Path) -> list[str]:
    with open(path) as f:
        return [ln.rstrip("\r\n") for ln in f if not ln.startswith("#")]


def _read_camera(path: Path):
    """The one camera of ``cameras.txt``: ``(K (3, 3) in the kit's pixels, (W, H), model name, k1)``."""
    cams = [ln.split() for ln in _data_lines(path) if ln.strip()]
    if len(cams) != 1:
        raise KitInputError(f"{path} has {len(cams)} cameras: the kit reads models with one shared camera")
    c = cams[0]
    try:
        model, W, H, params = c[1], int(c[2]), int(c[3]), [float(v) for v in c[4:]]
    except (IndexError, ValueError):
        raise KitInputError(f"{path}: malformed camera line {' '.join(c)!r}") from None
    k1 = 0.0
    if model == "PINHOLE" and len(params) == 4:
        fx, fy, cx, cy = params
    elif model == "SIMPLE_PINHOLE" and len(params) == 3:
        fx, cx, cy = params
        fy = fx
    elif model == "SIMPLE_RADIAL" and len(params) == 4:
        fx, cx, cy, k1 = params
        fy = fx
    else:
        raise KitInputError(f"camera model {model} with {len(params)} parameters: the kit reads PINHOLE, SIMPLE_PINHOLE and "
                            "SIMPLE_RADIAL only (re-run COLMAP's mapper with one of them, or undistort the images first)")
    K = np.array([[fx, 0.0, cx - PIXEL_OFFSET], [0.0, fy, cy - PIXEL_OFFSET], [0.0, 0.0, 1.0]])
    return K, (W, H), model, k1


def _read_images(path: Path):
    """``images.txt``, sorted by image id: ``(image_ids (M,), names, R_cw (M, 3, 3), t_cw (M, 3), points2d [(n_m, 3)])``."""
    lines = _data_lines(path)
    # Drop trailing blank lines only; a blank POINTS2D line is legal.
    while lines and not lines[-1].strip():
        lines.pop()
    if len(lines) % 2 == 1:
        lines.append("")
    image_ids, names, R, t, points2d = [], [], [], [], []
    for k in range(0, len(lines), 2):
        head = lines[k].split()
        try:
            iid = int(head[0])
            qw, qx, qy, qz, tx, ty, tz = (float(v) for v in head[1:8])
            name = " ".join(head[9:])
        except (IndexError, ValueError):
            raise KitInputError(f"{path}: malformed image line {lines[k]!r}") from None
        vals = lines[k + 1].split()
        if len(vals) % 3:
            raise KitInputError(f"{path}: the POINTS2D line of image {iid} is not a list of (X, Y, POINT3D_ID) triples")
        p2 = np.array(vals, dtype=float).reshape(-1, 3)
        image_ids.append(iid)
        names.append(name)
        R.append(Rotation.from_quat([qx, qy, qz, qw]).as_matrix())
        t.append([tx, ty, tz])
        points2d.append(p2)
    order = np.argsort(image_ids)
    image_ids = np.array(image_ids, dtype=np.int64)[order]
    names = [names[k] for k in order]
    R_cw = np.array([R[k] for k in order]).reshape(-1, 3, 3)
    t_cw = np.array([t[k] for k in order], dtype=float).reshape(-1, 3)
    points2d = [points2d[k] for k in order]
    return image_ids, names, R_cw, t_cw, points2d


def _read_points(path: Path, image_ids: np.ndarray, points2d: list):
    """``points3D.txt``: ``(point_ids (P,), X (P, 3), rgb (P, 3), error (P,), uv (P, M, 2))``, uv in the kit's pixels."""
    col = {int(iid): m for m, iid in enumerate(image_ids)}
    rows = [ln.split() for ln in _data_lines(path) if ln.strip()]
    P, M = len(rows), len(image_ids)
    point_ids = np.zeros(P, dtype=np.int64)
    X = np.zeros((P, 3))
    rgb = np.zeros((P, 3), dtype=np.uint8)
    error = np.zeros(P)
    uv = np.full((P, M, 2), np.nan)
    for p, r in enumerate(rows):
        try:
            point_ids[p] = int(r[0])
            X[p] = [float(v) for v in r[1:4]]
            rgb[p] = [int(v) for v in r[4:7]]
            error[p] = float(r[7])
            track = np.array(r[8:], dtype=np.int64).reshape(-1, 2)
        except (IndexError, ValueError):
            raise KitInputError(f"{path}: malformed point line {' '.join(r)[:80]!r}") from None
        for iid, idx in track:
            m = col.get(int(iid))
            if m is None or idx >= len(points2d[m]):
                raise KitInputError(f"{path}: point {point_ids[p]} refers to a missing image {iid} or 2-D point {idx}")
            uv[p, m] = points2d[m][idx, :2] - PIXEL_OFFSET
    return point_ids, X, rgb, error, uv


def read_colmap_text(folder) -> ColmapModel:
    """Read a COLMAP text model with one ``PINHOLE``, ``SIMPLE_PINHOLE`` or ``SIMPLE_RADIAL`` camera.

    Args:
        folder: folder with ``cameras.txt``, ``images.txt`` and ``points3D.txt``.

    Returns:
        :class:`ColmapModel` (kit pixel convention: 0.5 subtracted from COLMAP's coordinates).

    Raises:
        KitInputError: missing files, several or unsupported cameras, malformed lines.

    Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
    """
    folder = existing_path(folder, "COLMAP model folder")
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        existing_path(folder / name, f"COLMAP file {name}")

    K, (W, H), model, k1 = _read_camera(folder / "cameras.txt")
    image_ids, names, R_cw, t_cw, points2d = _read_images(folder / "images.txt")
    point_ids, X, rgb, error, uv = _read_points(folder / "points3D.txt", image_ids, points2d)
    return ColmapModel(K, (W, H), names, image_ids, R_cw, t_cw, point_ids, X, rgb, error, uv, model, k1)

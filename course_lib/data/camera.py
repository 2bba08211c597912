"""The camera of a photo set without a calibration file: K from EXIF or a guess, and one radial term.

SfM needs the intrinsics K. With a calibration file (``match --K``) they are known and held fixed.
Without one, :func:`camera_prior` starts from what the photos say, in COLMAP's order:

1. **EXIF focal length and sensor size**: ``FocalLength`` (mm) times ``FocalPlaneXResolution``
   (pixels per ``FocalPlaneResolutionUnit`` on the sensor), scaled from the EXIF image width to
   the photo's;
2. **EXIF 35 mm equivalent**: ``FocalLengthIn35mmFilm`` relates the focal length to the 43.27 mm
   diagonal of a 36 x 24 mm frame: ``f = f35 / 43.27 * (the photo's diagonal in pixels)``;
3. **a guess**: ``f = 1.2 * max(W, H)`` (COLMAP's ``default_focal_length_factor``; a field of view
   of about 45 degrees across the longer side).

The principal point is the image centre. Such a prior is only a start (the 35 mm equivalent is
rounded, phones crop; the guess can be off by a factor of two or three), so ``sfm`` refines it: where the
focal length is a guess it first estimates it from the images alone (:mod:`course_lib.sfm.self_calibration`),
then the focal length and one radial distortion term ``k1`` are parameters of the bundle adjustment, shared by all photos
(COLMAP's ``SIMPLE_RADIAL`` camera, :func:`distort`). The P3 folder carries the prior in
:data:`CAMERA_FILE` (:func:`write_camera`, read by :func:`course_lib.data.p3.read_p3`), beside
``calibration.txt`` (its K).

``SIMPLE_RADIAL`` (COLMAP's): a point ``(x, y)`` in normalized coordinates (``x = X / Z``) is
seen at ``f x (1 + k1 r²) + cx``, ``f y (1 + k1 r²) + cy`` with ``r² = x² + y²``; the kit's
``K`` is its pinhole part ``[[f, 0, cx], [0, f, cy], [0, 0, 1]]`` (kit pixel convention:
the centre of the top-left pixel at (0, 0), :mod:`course_lib.conventions`).

Introduced in ``notebooks/10_photos_to_nerf.ipynb``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from course_lib.validate import KitInputError, intrinsics

__all__ = ["FOCAL_GUESS_FACTOR", "DIAGONAL_35MM", "CAMERA_FILE", "CameraPrior", "exif_focal_px", "camera_prior",
           "write_camera", "read_camera", "distort", "undistort", "undistort_pixels", "distort_pixels", "undistort_image"]

#: COLMAP's guess without EXIF: ``f = 1.2 * max(W, H)``.
FOCAL_GUESS_FACTOR = 1.2
#: Diagonal of the 36 x 24 mm frame the 35 mm equivalent focal length refers to (mm).
DIAGONAL_35MM = float(np.hypot(36.0, 24.0))
#: The P3 folder's file that says where K came from and whether sfm refines it.
CAMERA_FILE = "camera.json"
#: EXIF tags (numbers) read by :func:`exif_focal_px`.
_EXIF_IFD, _FOCAL, _FOCAL_35, _PLANE_X_RES, _PLANE_UNIT, _EXIF_W, _EXIF_H = 0x8769, 0x920A, 0xA405, 0xA20E, 0xA210, 0xA002, 0xA003
_MAKE, _MODEL = 0x010F, 0x0110
#: FocalPlaneResolutionUnit -> millimetres (2 inch, 3 cm, 4 mm, 5 micrometre).
_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}


@dataclass
class CameraPrior:
    """The intrinsics a photo set starts from.

    Attributes:
        K: ``(3, 3)`` pinhole intrinsics of the photos as matched (after any downscaling).
        model: ``"PINHOLE"`` (K from a calibration file, held fixed) or ``"SIMPLE_RADIAL"``
            (focal length and ``k1`` refined by sfm).
        k1: radial distortion (0 at the start).
        source: where the focal length came from, in words.
        refine: whether sfm refines the focal length and ``k1``.
        camera: the camera's make and model from EXIF ("" if none).
    """

    K: np.ndarray
    model: str = "PINHOLE"
    k1: float = 0.0
    source: str = "calibration file"
    refine: bool = False
    camera: str = ""
    per_photo: list = field(default_factory=list)

    def summary(self) -> dict:
        return {"model": self.model, "K": np.asarray(self.K).tolist(), "k1": float(self.k1), "source": self.source,
                "refine": bool(self.refine), "camera": self.camera}


def _rational(v) -> float | None:
    try:
        x = float(v[0]) / float(v[1]) if isinstance(v, tuple) else float(v)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return x if np.isfinite(x) and x > 0 else None


def exif_focal_px(path, image_size: tuple[int, int]) -> tuple[float | None, str, str]:
    """The focal length in pixels that a photo's EXIF gives, for the photo at ``image_size`` ``(W, H)``.

    Returns:
        ``(f_px or None, how it was found, "make model")``; None where EXIF has neither the sensor's
        resolution nor a 35 mm equivalent (or no EXIF at all).
    """
    from PIL import Image

    W, H = image_size
    try:
        with Image.open(path) as im:
            exif = im.getexif()
            ifd = exif.get_ifd(_EXIF_IFD)
    except (OSError, ValueError, SyntaxError):
        return None, "", ""
    camera = " ".join(str(exif.get(t, "")).strip().strip("\x00") for t in (_MAKE, _MODEL)).strip()
    f_mm, f35 = _rational(ifd.get(_FOCAL)), _rational(ifd.get(_FOCAL_35))
    res, unit = _rational(ifd.get(_PLANE_X_RES)), _UNIT_MM.get(int(ifd.get(_PLANE_UNIT, 2) or 2))
    if f_mm and res and unit:
        ew, eh = _rational(ifd.get(_EXIF_W)), _rational(ifd.get(_EXIF_H))
        scale = max(W, H) / max(ew, eh) if ew and eh else 1.0
        return f_mm * res / unit * scale, f"EXIF FocalLength {f_mm:g} mm and FocalPlaneXResolution", camera
    if f35:
        return f35 / DIAGONAL_35MM * float(np.hypot(W, H)), f"EXIF FocalLengthIn35mmFilm {f35:g} mm", camera
    return None, "", camera


def camera_prior(paths, image_size: tuple[int, int]) -> CameraPrior:
    """The intrinsics of photos without a calibration file: EXIF, else COLMAP's guess (module docstring).

    Args:
        paths: the photo files (one camera at one zoom). image_size: ``(W, H)`` of the photos.

    Returns:
        A ``SIMPLE_RADIAL`` :class:`CameraPrior` to be refined, principal point at the image centre.

    Raises:
        KitInputError: the photos' EXIF focal lengths differ by more than 1 % (several cameras or zooms).
    """
    W, H = image_size
    found = [(Path(p).name, *exif_focal_px(p, image_size)) for p in paths]
    known = [(n, f, how, cam) for n, f, how, cam in found if f is not None]
    if known:
        fs = np.array([f for _, f, _, _ in known])
        if fs.max() > 1.01 * fs.min():
            groups = sorted({round(float(f), 1) for f in fs})
            raise KitInputError(f"the photos' EXIF focal lengths differ ({', '.join(f'{g:g} px' for g in groups[:5])}): "
                                "they come from several cameras or zoom settings, and the kit reconstructs photos of one "
                                "camera at one zoom; keep the photos of one focal length, or pass --K")
        f = float(np.median(fs))
        how = known[0][2] + (f" ({len(known)} of {len(found)} photos)" if len(known) < len(found) else "")
        camera = known[0][3]
    else:
        f = FOCAL_GUESS_FACTOR * max(W, H)
        how = f"guess: {FOCAL_GUESS_FACTOR} x the longer side (no focal length in EXIF)"
        camera = next((c for *_, c in found if c), "")
    K = np.array([[f, 0.0, (W - 1) / 2.0], [0.0, f, (H - 1) / 2.0], [0.0, 0.0, 1.0]])
    return CameraPrior(K, "SIMPLE_RADIAL", 0.0, how, True, camera, [{"photo": n, "focal_px": fp, "source": h}
                                                                    for n, fp, h, _ in found])


def write_camera(folder, prior: CameraPrior) -> Path:
    """Write :data:`CAMERA_FILE` into a P3 folder (the model, the source of K, whether to refine it)."""
    path = Path(folder) / CAMERA_FILE
    path.write_text(json.dumps(prior.summary(), indent=1))
    return path


def read_camera(folder) -> CameraPrior | None:
    """The :class:`CameraPrior` a P3 folder carries, or None without :data:`CAMERA_FILE`.

    Raises:
        KitInputError: a malformed file.
    """
    path = Path(folder) / CAMERA_FILE
    if not path.is_file():
        return None
    try:
        d = json.loads(path.read_text())
        prior = CameraPrior(intrinsics(np.asarray(d["K"], float)), str(d["model"]), float(d.get("k1", 0.0)),
                            str(d.get("source", "")), bool(d.get("refine", False)), str(d.get("camera", "")))
    except (ValueError, KeyError, TypeError, KitInputError) as exc:
        raise KitInputError(f"{path}: not a valid {CAMERA_FILE} ({exc}); delete it to hold calibration.txt's K fixed") from None
    if prior.model not in ("PINHOLE", "SIMPLE_RADIAL"):
        raise KitInputError(f"{path}: camera model {prior.model!r}; the kit knows PINHOLE and SIMPLE_RADIAL")
    return prior


# ------------------------------------------------------------------------------------------- SIMPLE_RADIAL


def distort(xn: np.ndarray, k1: float) -> np.ndarray:
    """``(N, 2)`` normalized coordinates moved by the radial term: ``x (1 + k1 r²)``."""
    xn = np.asarray(xn, float)
    return xn * (1.0 + k1 * (xn**2).sum(axis=-1, keepdims=True))


def undistort(xd: np.ndarray, k1: float, iterations: int = 20) -> np.ndarray:
    """The inverse of :func:`distort` (fixed-point iteration; exact to ~1e-12 for ``|k1 r²| < 0.3``)."""
    xd = np.asarray(xd, float)
    x = xd.copy()
    if k1 == 0.0:
        return x
    for _ in range(iterations):
        x = xd / (1.0 + k1 * (x**2).sum(axis=-1, keepdims=True))
    return x


def _in_normalized(fn, uv: np.ndarray, K: np.ndarray, k1: float) -> np.ndarray:
    """``fn`` (:func:`distort` or :func:`undistort`) applied to pixels ``(..., 2)`` through normalized coordinates."""
    uv = np.asarray(uv, float)
    if k1 == 0.0:
        return uv.copy()
    f, c = np.array([K[0, 0], K[1, 1]]), np.array([K[0, 2], K[1, 2]])
    return fn((uv - c) / f, k1) * f + c


def undistort_pixels(uv: np.ndarray, K: np.ndarray, k1: float) -> np.ndarray:
    """Pixels ``(..., 2)`` of a ``SIMPLE_RADIAL`` camera moved to where the pinhole ``K`` would see them (NaN stays NaN)."""
    return _in_normalized(undistort, uv, K, k1)


def distort_pixels(uv: np.ndarray, K: np.ndarray, k1: float) -> np.ndarray:
    """The inverse of :func:`undistort_pixels`: pinhole pixels ``(..., 2)`` to where the ``SIMPLE_RADIAL`` camera sees them."""
    return _in_normalized(distort, uv, K, k1)


def undistort_image(img: np.ndarray, K: np.ndarray, k1: float) -> np.ndarray:
    """A photo of a ``SIMPLE_RADIAL`` camera resampled onto its pinhole ``K`` (same size; bilinear, edges replicated).

    Args:
        img: ``(H, W)`` or ``(H, W, C)`` image. K: ``(3, 3)`` the camera's pinhole part. k1: its radial term.

    Returns:
        The undistorted image (a copy where ``k1 == 0``).
    """
    import cv2

    if k1 == 0.0:
        return img.copy()
    H, W = img.shape[:2]
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    src = distort_pixels(np.stack([u, v], axis=-1), K, k1).astype(np.float32)  # where the photo saw each pinhole pixel
    return cv2.remap(img, src[..., 0], src[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

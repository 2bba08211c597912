"""NeRF's Blender data format (``transforms_{split}.json`` + PNGs): loader, writer, tiny_nerf npz.

The ``nerf_synthetic`` scenes (lego, ...) and the kit's embedded NeRF scene are stored as::

    folder/
      transforms_train.json   {"camera_angle_x": a, "frames": [{"file_path": "./images/r_0",
      transforms_test.json                                       "transform_matrix": 4x4}, ...]}
      images/r_0.png ...      RGBA (transparent background) or RGB, 8 bit

``file_path`` has no extension (``.png`` is added) and is relative to the JSON's folder.
``transform_matrix`` is **camera-to-world** in **Blender/OpenGL camera axes**.

Axis conventions -- THE one place in the kit that converts them
    * Blender / OpenGL camera: x right, **y up**, the camera looks along **-z** (z points backwards,
      out of the screen towards the viewer).
    * The kit / OpenCV / COLMAP camera (:mod:`course_lib.conventions`): x right, **y down**,
      **z forward** (the optical axis, into the scene).

    The two frames share the camera centre and the x axis; y and z are flipped. A camera-to-world
    matrix maps camera coordinates to the world, so the flip acts on its *columns* (the camera
    axes expressed in the world)::

        c2w_cv = c2w_gl @ diag(1, -1, -1, 1)        (and back: c2w_gl = c2w_cv @ diag(1, -1, -1, 1))

    The flip is its own inverse. Everything outside this module (rays, rendering, the notebooks)
    sees OpenCV axes only.

Intrinsics
    Blender renders with square pixels and the principal point at the image centre. The focal
    length follows from the horizontal field of view: ``f = 0.5 W / tan(0.5 camera_angle_x)``
    (138.889 px for the 100x100 lego). In the kit's pixel convention the centre of the top-left
    pixel is (0, 0), so the image centre is ``cx = (W - 1) / 2, cy = (H - 1) / 2``. (The original
    NeRF code uses ``W / 2`` with integer pixel coordinates, i.e. it shoots rays through pixel
    corners; half a pixel, invisible at 800 px, a visible shift at 100 px.)

Images
    RGBA images are composited onto a white background (``white_background=True``, as NeRF's
    Blender configs do) or onto black: ``rgb = rgb * alpha + bg * (1 - alpha)``, as float32 in
    [0, 1] -- or, with ``dtype="uint8"``, rounded back to 8 bit after compositing (and
    downscaling): a quarter of the memory (100 views at 800 x 800: 192 MB instead of 768 MB), what
    the trainer keeps anyway.

Introduced in ``notebooks/06_nerf_data_and_rays.ipynb``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from course_lib.validate import KitInputError, existing_path

__all__ = ["BlenderData", "GL_FROM_CV", "opengl_to_opencv", "opencv_to_opengl", "intrinsics_from_fov", "load_blender",
           "read_rgb", "write_blender", "load_tiny_nerf_npz"]

#: ``diag(1, -1, -1, 1)``: flips the camera's y and z axes (OpenGL <-> OpenCV). Its own inverse.
GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])

SPLITS = ("train", "val", "test")


@dataclass
class BlenderData:
    """One split of a NeRF scene, in the kit's conventions.

    Attributes:
        images: ``(N, H, W, 3)`` float32 RGB in [0, 1] (or uint8 in [0, 255], ``load_blender(..., dtype="uint8")``),
            alpha already composited.
        c2w: ``(N, 4, 4)`` float64 camera-to-world matrices in the kit's **OpenCV** camera axes
            (x right, y down, z forward). ``c2w[i, :3, 3]`` is camera i's centre, ``c2w[i, :3, 2]``
            its optical axis in the world.
        K: ``(3, 3)`` float64 intrinsics shared by all views (pixels, principal point at the
            image centre ``((W - 1) / 2, (H - 1) / 2)``).
        H: image height in pixels.
        W: image width in pixels.
        names: the frames' names (file name without extension), length N.
        camera_angle_x: horizontal field of view in radians.
        split: ``"train"``, ``"val"``, ``"test"`` (or ``"all"`` for a tiny_nerf npz).
        folder: where the data came from (None if built in memory).
    """

    images: np.ndarray
    c2w: np.ndarray
    K: np.ndarray
    H: int
    W: int
    names: list[str]
    camera_angle_x: float
    split: str = "train"
    folder: Path | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return int(self.images.shape[0])

    @property
    def focal(self) -> float:
        """Focal length in pixels (``K[0, 0]``)."""
        return float(self.K[0, 0])

    @property
    def centers(self) -> np.ndarray:
        """``(N, 3)`` camera centres in the world."""
        return self.c2w[:, :3, 3].copy()

    def subset(self, index) -> "BlenderData":
        """A new BlenderData with only the views ``index`` (a slice, a list of ints or a bool mask)."""
        idx = np.arange(len(self))[index]
        idx = np.atleast_1d(idx)
        return BlenderData(
            images=self.images[idx], c2w=self.c2w[idx], K=self.K.copy(), H=self.H, W=self.W,
            names=[self.names[i] for i in idx], camera_angle_x=self.camera_angle_x,
            split=self.split, folder=self.folder,
        )


def opengl_to_opencv(c2w_gl: np.ndarray) -> np.ndarray:
    """Camera-to-world from Blender/OpenGL camera axes (y up, z back) to OpenCV axes (y down, z forward).

    Args:
        c2w_gl: ``(..., 4, 4)`` camera-to-world, OpenGL camera axes.

    Returns:
        ``(..., 4, 4)`` camera-to-world, OpenCV camera axes: ``c2w_gl @ diag(1, -1, -1, 1)``.
    """
    return np.asarray(c2w_gl, dtype=float) @ GL_FROM_CV


def opencv_to_opengl(c2w_cv: np.ndarray) -> np.ndarray:
    """The inverse of :func:`opengl_to_opencv` (the same flip: ``c2w_cv @ diag(1, -1, -1, 1)``)."""
    return np.asarray(c2w_cv, dtype=float) @ GL_FROM_CV


def intrinsics_from_fov(W: int, H: int, camera_angle_x: float) -> np.ndarray:
    """``K`` of a Blender camera: square pixels, ``f = 0.5 W / tan(0.5 camera_angle_x)``, centred.

    Args:
        W, H: image size in pixels.
        camera_angle_x: horizontal field of view in radians, in (0, pi).

    Returns:
        ``(3, 3)`` intrinsics with ``cx = (W - 1) / 2``, ``cy = (H - 1) / 2`` (the kit's pixel centres).
    """
    a = float(camera_angle_x)
    if not (0.0 < a < np.pi):
        raise KitInputError(f"camera_angle_x = {a!r} rad: expected a horizontal field of view in (0, pi) radians")
    f = 0.5 * W / np.tan(0.5 * a)
    return np.array([[f, 0.0, (W - 1) / 2.0], [0.0, f, (H - 1) / 2.0], [0.0, 0.0, 1.0]])


# --------------------------------------------------------------------------- reading


def _check_c2w(M: np.ndarray, where: str) -> np.ndarray:
    M = np.asarray(M, dtype=float)
    if M.shape == (3, 4):
        M = np.vstack([M, [0.0, 0.0, 0.0, 1.0]])
    if M.shape != (4, 4):
        raise KitInputError(f"{where}: transform_matrix has shape {M.shape}: expected a 4x4 camera-to-world matrix")
    if not np.isfinite(M).all():
        raise KitInputError(f"{where}: transform_matrix contains NaN or inf")
    if not np.allclose(M[3], [0, 0, 0, 1], atol=1e-6):
        raise KitInputError(f"{where}: transform_matrix's last row is {M[3].tolist()}, expected [0, 0, 0, 1]")
    R = M[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0:
        raise KitInputError(
            f"{where}: the rotation part of transform_matrix is not a rotation (orthonormal, det +1); "
            "scaled or mirrored camera matrices are not supported"
        )
    return M


def read_rgb(path, hint: str = "the file is missing or not an image") -> np.ndarray:
    """An image file as RGB or RGBA ``(H, W, 3 or 4)``, in its own dtype (uint8, or uint16 for 16-bit files).

    Args:
        path: the image file (anything ``cv2.imread`` reads).
        hint: what to fix, in the error when the file cannot be read.

    Raises:
        KitInputError: ``"cannot read the image <path>: <hint>"``.
    """
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise KitInputError(f"cannot read the image {path}: {hint}")
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _read_image(path: Path) -> np.ndarray:
    """Read an image file as float32 RGB or RGBA in [0, 1] (8 or 16 bit)."""
    img = read_rgb(path)
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    return img.astype(np.float32) / np.float32(scale)


def _composite(img: np.ndarray, white_background: bool) -> np.ndarray:
    if img.shape[2] == 3:
        return img
    rgb, a = img[..., :3], img[..., 3:4]
    bg = 1.0 if white_background else 0.0
    return rgb * a + bg * (1.0 - a)


def _read_transforms(folder: Path, split: str):
    """``transforms_{split}.json`` of ``folder``, checked: ``(its path, frames, camera_angle_x, the whole object)``."""
    jpath = folder / f"transforms_{split}.json"
    if not jpath.exists():
        have = sorted(p.name for p in folder.glob("transforms_*.json"))
        raise KitInputError(f"{jpath} not found (this folder has {have or 'no transforms_*.json'}): is it a NeRF Blender scene?")
    try:
        meta = json.loads(jpath.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise KitInputError(f"{jpath} is not valid JSON ({exc})") from None
    if not isinstance(meta, dict) or "camera_angle_x" not in meta or "frames" not in meta:
        raise KitInputError(f"{jpath}: expected an object with 'camera_angle_x' and 'frames' (the Blender NeRF format)")
    frames = meta["frames"]
    if not isinstance(frames, list) or not frames:
        raise KitInputError(f"{jpath}: 'frames' must be a non-empty list")
    try:
        camera_angle_x = float(meta["camera_angle_x"])
    except (TypeError, ValueError):
        raise KitInputError(f"{jpath}: camera_angle_x = {meta['camera_angle_x']!r} is not a number") from None
    return jpath, frames, camera_angle_x, meta


def load_blender(folder, split: str = "train", downscale: int = 1, white_background: bool = True,
                 dtype: str = "float32") -> BlenderData:
    """Load one split of a NeRF Blender scene, in the kit's OpenCV camera axes.

    Args:
        folder: the scene folder holding ``transforms_{split}.json``.
        split: ``"train"``, ``"val"`` or ``"test"``.
        downscale: integer factor to shrink the images by (``cv2.INTER_AREA``); K follows.
        white_background: composite RGBA onto white (True, NeRF's Blender setting) or black.
        dtype: ``"float32"`` (images in [0, 1]) or ``"uint8"`` (in [0, 255], rounded after
            compositing and downscaling: a quarter of the memory).

    Returns:
        :class:`BlenderData` with ``images (N, H, W, 3)`` float32 in [0, 1] (or uint8), ``c2w (N, 4, 4)``
        (OpenCV axes: ``c2w_cv = c2w_gl @ diag(1, -1, -1, 1)``), ``K (3, 3)``, ``H``, ``W``, ``names``.

    Raises:
        KitInputError: missing folder/JSON/image, malformed JSON, frames of different sizes, or a
            ``camera_angle_y`` that contradicts square pixels.

    Introduced in ``notebooks/06_nerf_data_and_rays.ipynb``.
    """
    folder = existing_path(folder, "NeRF scene folder")
    if not folder.is_dir():
        raise KitInputError(f"{folder} is a file: pass the scene folder that holds transforms_{split}.json")
    if split not in SPLITS:
        raise KitInputError(f"split = {split!r}: expected one of {SPLITS}")
    if int(downscale) != downscale or downscale < 1:
        raise KitInputError(f"downscale = {downscale!r}: expected an integer >= 1")
    downscale = int(downscale)
    if dtype not in ("float32", "uint8"):
        raise KitInputError(f"dtype = {dtype!r}: expected 'float32' or 'uint8'")
    jpath, frames, camera_angle_x, meta = _read_transforms(folder, split)

    images, c2ws, names = [], [], []
    size = None
    for k, fr in enumerate(frames):
        where = f"{jpath.name}, frame {k}"
        if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
            raise KitInputError(f"{where}: each frame needs 'file_path' and 'transform_matrix'")
        rel = str(fr["file_path"])
        p = (folder / rel).resolve()
        if p.suffix.lower() not in (".png", ".jpg", ".jpeg", ".exr"):
            p = p.with_name(p.name + ".png")
        if not p.exists():
            raise KitInputError(f"{where}: image {p} not found (file_path {rel!r} is relative to {folder}, '.png' added)")
        img = _composite(_read_image(p), white_background)
        if size is None:
            size = img.shape[:2]
        elif img.shape[:2] != size:
            raise KitInputError(f"{where}: image {p.name} is {img.shape[1]}x{img.shape[0]} but the first frame is {size[1]}x{size[0]}")
        if downscale > 1:
            img = cv2.resize(img, (size[1] // downscale, size[0] // downscale), interpolation=cv2.INTER_AREA)
        images.append((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8) if dtype == "uint8" else img.astype(np.float32))
        try:
            M = np.array(fr["transform_matrix"], dtype=float)
        except (TypeError, ValueError):
            raise KitInputError(f"{where}: transform_matrix is not a numeric 4x4 matrix") from None
        # Blender/OpenGL (x right, y up, looks along -z) -> OpenCV (x right, y down, z forward).
        c2ws.append(opengl_to_opencv(_check_c2w(M, where)))
        names.append(Path(rel).stem)

    H, W = images[0].shape[:2]
    K = intrinsics_from_fov(W, H, camera_angle_x)
    if "camera_angle_y" in meta:
        fy = 0.5 * H / np.tan(0.5 * float(meta["camera_angle_y"]))
        if abs(fy - K[0, 0]) > 0.01 * K[0, 0]:
            raise KitInputError(
                f"{jpath}: camera_angle_y gives fy = {fy:.3f} px but camera_angle_x gives fx = {K[0, 0]:.3f} px; "
                "the kit assumes square pixels (fx = fy)"
            )
    return BlenderData(
        images=np.stack(images), c2w=np.stack(c2ws), K=K, H=int(H), W=int(W),
        names=names, camera_angle_x=camera_angle_x, split=split, folder=folder,
    )


# --------------------------------------------------------------------------- writing


def write_blender(folder, split: str, images, c2w, camera_angle_x: float, names=None) -> Path:
    """Write one split in the Blender NeRF format (the inverse of :func:`load_blender`).

    Args:
        folder: scene folder (created if needed); images go to ``folder/images/<name>.png``.
        split: ``"train"``, ``"val"`` or ``"test"``; writes ``folder/transforms_{split}.json``.
        images: ``(N, H, W, 3)`` RGB or ``(N, H, W, 4)`` RGBA, uint8 (float in [0, 1] is converted).
        c2w: ``(N, 4, 4)`` (or ``(N, 3, 4)``) camera-to-world in the kit's **OpenCV** axes; stored
            in OpenGL axes (``c2w_gl = c2w_cv @ diag(1, -1, -1, 1)``).
        camera_angle_x: horizontal field of view in radians.
        names: N file names without extension (default ``"{split}_{i:03d}"``).

    Returns:
        Path of the JSON written.
    """
    if split not in SPLITS:
        raise KitInputError(f"split = {split!r}: expected one of {SPLITS}")
    images = np.asarray(images)
    if images.ndim != 4 or images.shape[-1] not in (3, 4):
        raise KitInputError(f"images has shape {images.shape}: expected (N, H, W, 3) RGB or (N, H, W, 4) RGBA")
    if images.dtype != np.uint8:
        if not np.issubdtype(images.dtype, np.floating):
            raise KitInputError(f"images has dtype {images.dtype}: expected uint8 (or float in [0, 1])")
        images = np.clip(np.round(images * 255.0), 0, 255).astype(np.uint8)
    N, H, W = images.shape[:3]
    c2w = np.asarray(c2w, dtype=float)
    if c2w.ndim != 3 or c2w.shape[0] != N or c2w.shape[1:] not in ((4, 4), (3, 4)):
        raise KitInputError(f"c2w has shape {c2w.shape}: expected ({N}, 4, 4) camera-to-world matrices, one per image")
    if names is None:
        names = [f"{split}_{i:03d}" for i in range(N)]
    names = [str(n) for n in names]
    if len(names) != N or len(set(names)) != N:
        raise KitInputError(f"names: expected {N} distinct names, got {len(names)} ({len(set(names))} distinct)")
    intrinsics_from_fov(W, H, camera_angle_x)  # validates the angle
    folder = Path(folder)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(N):
        M = _check_c2w(c2w[i], f"c2w[{i}]")
        img = images[i]
        bgr = cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA if img.shape[2] == 4 else cv2.COLOR_RGB2BGR)
        if not cv2.imwrite(str(folder / "images" / f"{names[i]}.png"), bgr):
            raise KitInputError(f"could not write {folder / 'images' / (names[i] + '.png')}")
        # OpenCV (x right, y down, z forward) -> Blender/OpenGL (x right, y up, looks along -z).
        frames.append({"file_path": f"./images/{names[i]}", "transform_matrix": opencv_to_opengl(M).tolist()})
    jpath = folder / f"transforms_{split}.json"
    jpath.write_text(json.dumps({"camera_angle_x": float(camera_angle_x), "frames": frames}, indent=2))
    return jpath


def load_tiny_nerf_npz(path) -> BlenderData:
    """Load the classic ``tiny_nerf_data.npz`` (the original tiny_nerf notebook's 100x100 lego).

    The file holds ``images (N, H, W, 3)`` float32 in [0, 1] (RGB as stored; the original file's
    background is black, so train it with ``white_background=False``),
    ``poses (N, 4, 4)`` camera-to-world in OpenGL axes, and ``focal`` (pixels). The tiny_nerf
    notebook trains on ``images[:100]`` and shows ``images[101]``; use :meth:`BlenderData.subset`.

    Returns:
        :class:`BlenderData` with ``split="all"``, ``c2w`` in OpenCV axes, ``names = ["tiny_000", ...]``.
    """
    path = existing_path(path, "tiny_nerf npz file")
    try:
        with np.load(path) as z:
            missing = {"images", "poses", "focal"} - set(z.files)
            if missing:
                raise KitInputError(f"{path}: missing arrays {sorted(missing)} (expected images, poses, focal)")
            images = np.asarray(z["images"], dtype=np.float32)
            poses = np.asarray(z["poses"], dtype=float)
            focal = float(np.asarray(z["focal"]).reshape(-1)[0])
    except (OSError, ValueError) as exc:
        raise KitInputError(f"{path} is not a readable .npz file ({exc})") from None
    if images.ndim != 4 or images.shape[-1] not in (3, 4):
        raise KitInputError(f"{path}: images has shape {images.shape}, expected (N, H, W, 3)")
    if images.shape[-1] == 4:
        images = images[..., :3] * images[..., 3:] + (1.0 - images[..., 3:])
    N, H, W = images.shape[:3]
    if poses.shape[0] != N:
        raise KitInputError(f"{path}: {N} images but {poses.shape[0]} poses")
    c2w = np.stack([opengl_to_opencv(_check_c2w(poses[i], f"{path.name}, pose {i}")) for i in range(N)])
    camera_angle_x = float(2.0 * np.arctan(0.5 * W / focal))
    return BlenderData(
        images=images, c2w=c2w, K=intrinsics_from_fov(W, H, camera_angle_x), H=int(H), W=int(W),
        names=[f"tiny_{i:03d}" for i in range(N)], camera_angle_x=camera_angle_x, split="all", folder=path.parent,
    )

"""What training knows about the scene: its bounds (a typed object) and the rays of its training images.

* :class:`SceneBounds` -- the box the cameras look at, and the near/far of the rays. It travels
  with the model (checkpoints, renders); the grid's schedule replaces its box once
  (:meth:`SceneBounds.with_box`), it is never changed in place.
* :class:`TrainingRays` -- the training images (uint8, on the training device: 100 views at
  800 x 800 take 192 MB) and their cameras; :meth:`TrainingRays.sample` draws a batch of random
  pixels across all images and makes their rays on the fly from ``get_rays`` (the exercise of
  notebook 06: in the student kit the student's own) in the camera frame, rotated by each
  pixel's view (nothing per pixel is stored besides its colour and one direction per pixel of
  the image grid).

Introduced in ``notebooks/08_nerf_rendering_and_training.ipynb``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np
import torch

from course_lib.data.blender import BlenderData
from course_lib.nerf.rays import camera_rays
from course_lib.validate import KitInputError

__all__ = ["SceneBounds", "scene_bounds", "TrainingRays"]


@dataclass(frozen=True)
class SceneBounds:
    """A box around what the cameras look at, and the ray bounds that contain it.

    Attributes:
        center: ``(3,)`` the point closest to all optical axes. radius: of the sphere around it.
        box_min, box_max: ``(3,)`` corners of the modelled box (world units).
        near, far: depths (in units of ``rays_d``) that bracket the sphere from every camera.
        shrunk: True once the box was fitted around the surfaces (the grid's schedule).

    Read-only access by key (``bounds["near"]``) works too, as for the dict of earlier versions.
    """

    center: tuple
    radius: float
    box_min: tuple
    box_max: tuple
    near: float
    far: float
    shrunk: bool = False

    @classmethod
    def from_cameras(cls, c2w: np.ndarray, K: np.ndarray, W: int) -> "SceneBounds":
        """The bounds of an object-centred capture (see :func:`scene_bounds`)."""
        C = c2w[:, :3, 3]
        z = c2w[:, :3, 2] / np.linalg.norm(c2w[:, :3, 2], axis=1, keepdims=True)
        A, b = np.zeros((3, 3)), np.zeros(3)
        for c, d in zip(C, z):
            P = np.eye(3) - np.outer(d, d)  # projector orthogonal to the axis
            A += P
            b += P @ c
        center = np.linalg.lstsq(A, b, rcond=None)[0] if len(C) > 1 else C[0] + 4.0 * z[0]
        dist = np.linalg.norm(C - center, axis=1)
        radius = float(dist.min() * math.sin(math.atan(0.5 * W / K[0, 0])))
        near = float(max(0.05 * dist.min(), dist.min() - radius * math.sqrt(3)))
        far = float(dist.max() + radius * math.sqrt(3))
        return cls(center=tuple(center.tolist()), radius=radius, box_min=tuple((center - radius).tolist()),
                   box_max=tuple((center + radius).tolist()), near=near, far=far)

    def with_box(self, box_min, box_max) -> "SceneBounds":
        """A copy whose box is ``[box_min, box_max]`` (marked ``shrunk``)."""
        return replace(self, box_min=tuple(float(x) for x in box_min), box_max=tuple(float(x) for x in box_max),
                       shrunk=True)

    def with_rays(self, near: float | None, far: float | None) -> "SceneBounds":
        """A copy with ``near``/``far`` replaced where given (a config's override)."""
        return replace(self, near=self.near if near is None else float(near), far=self.far if far is None else float(far))

    def to_dict(self) -> dict:
        """Plain lists and floats (checkpoints, ``metrics.json``)."""
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict) -> "SceneBounds":
        return cls(center=tuple(d["center"]), radius=float(d["radius"]), box_min=tuple(d["box_min"]),
                   box_max=tuple(d["box_max"]), near=float(d["near"]), far=float(d["far"]),
                   shrunk=bool(d.get("shrunk", False)))

    def __getitem__(self, key: str):
        value = getattr(self, key)
        return list(value) if isinstance(value, tuple) else value


def scene_bounds(c2w: np.ndarray, K: np.ndarray, W: int) -> SceneBounds:
    """A box and ray bounds that contain what the cameras look at (object-centred captures).

    The centre is the point closest (least squares) to all optical axes; the radius is the
    largest sphere around it that fits in the horizontal field of view of the nearest camera,
    ``r = d_min sin(fov_x / 2)``. near/far bracket that sphere from every camera.

    Args:
        c2w: ``(N, 4, 4)`` camera-to-world, OpenCV axes. K: ``(3, 3)``. W: image width.

    Returns:
        :class:`SceneBounds` (``center (3,)``, ``radius``, ``box_min``, ``box_max``, ``near``, ``far``;
        also readable by key, ``bounds["near"]``).

    Introduced in ``notebooks/06_nerf_data_and_rays.ipynb``.
    """
    return SceneBounds.from_cameras(np.asarray(c2w, float), np.asarray(K, float), W)


class TrainingRays:
    """The training images and cameras on the device; random batches of their pixels' rays.

    The rays come from ``get_rays`` (:func:`course_lib.nerf.rays.camera_rays`): once for the
    identity pose, which gives every pixel's direction in the camera frame, ``d_cam (H W, 3)``;
    a pixel of view ``i`` then has ``rays_o = C_i``, ``rays_d = R_i d_cam``. That is what
    ``get_rays`` computes for view ``i`` itself, and it is checked on three views: a ``get_rays``
    whose rays do not turn with the camera stops here with a message, instead of training on rays
    that its renders would not use.

    Args:
        data: the training views (float or uint8 images).
        device: where the colours and cameras live.

    Raises:
        KitInputError: ``get_rays`` of a view differs from the rotated camera-frame rays.
    """

    def __init__(self, data: BlenderData, device: torch.device):
        images = torch.as_tensor(np.asarray(data.images))
        if images.dtype != torch.uint8:  # uint8 on the device: a quarter of float32
            images = (images.clamp(0, 1) * 255 + 0.5).to(torch.uint8)
        self.colors = images.reshape(-1, 3).to(device)
        self.n_views, self.H, self.W = len(data), int(data.H), int(data.W)
        c2w = np.asarray(data.c2w)
        self.R = torch.as_tensor(c2w[:, :3, :3], dtype=torch.float32, device=device)  # (N, 3, 3)
        self.C = torch.as_tensor(c2w[:, :3, 3], dtype=torch.float32, device=device)  # (N, 3)
        self.device = device
        _, d_cam = camera_rays(self.H, self.W, data.K, torch.eye(4, device=device), device=device)
        self.d_cam = d_cam.reshape(-1, 3)  # (H W, 3): every pixel's direction in the camera frame
        for i in sorted({0, self.n_views // 2, self.n_views - 1}):
            self._check_view(i, data.K, c2w[i])

    def _check_view(self, i: int, K, c2w: np.ndarray) -> None:
        o, d = camera_rays(self.H, self.W, K, c2w, device=self.device)
        want_d = (self.d_cam @ self.R[i].T).reshape(o.shape)
        scale = float(want_d.abs().max()) + float(self.C[i].abs().max())
        err_o = float((o - self.C[i]).abs().max())
        err_d = float((d - want_d).abs().max())
        if max(err_o, err_d) > 1e-4 * max(scale, 1.0):
            raise KitInputError(
                f"get_rays of training view {i} is not the camera-frame rays turned by its pose (largest difference: "
                f"{err_o:.3g} in rays_o, {err_d:.3g} in rays_d): rays_o must be c2w[:3, 3] and rays_d = c2w[:3, :3] @ "
                "d_cam for every pixel (notebook 06's check cell of get_rays says which property fails)")

    def __len__(self) -> int:
        return self.colors.shape[0]

    def rays(self, index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``rays_o (B, 3), rays_d (B, 3)`` of the pixels ``index (B,)`` (flat over view, row, column).

        The rays of ``get_rays`` of the pixel's view, made for these pixels only.
        """
        view = index // (self.H * self.W)
        rays_d = torch.einsum("bij,bj->bi", self.R[view], self.d_cam[index % (self.H * self.W)])
        return self.C[view], rays_d

    def sample(self, n: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``n`` random pixels of all views: ``rays_o (n, 3), rays_d (n, 3), rgb (n, 3)`` float in [0, 1]."""
        index = torch.randint(0, len(self), (n,), generator=generator, device=self.device)
        rays_o, rays_d = self.rays(index)
        return rays_o, rays_d, self.colors[index].float() / 255.0

"""Rays through pixels and samples along them (notebook 06).

A pixel ``(u, v)`` (u = column, v = row; the centre of the top-left pixel is (0, 0), see
:mod:`course_lib.conventions`) is seen along the camera-frame direction::

    d_cam = K^-1 [u, v, 1]^T = [(u - cx) / fx, (v - cy) / fy, 1]

(OpenCV axes: x right, y down, z forward). Rotated into the world by the camera-to-world matrix,
``rays_d = R_c2w d_cam`` and ``rays_o = C`` (the camera centre). ``rays_d`` is **not** normalized:
its camera-z component is 1, so a point ``rays_o + t * rays_d`` lies at depth ``t`` in front of
the camera, and the "depth" that volume rendering returns is the z-depth of the camera frame.

Shapes are NeRF's common vocabulary: ``rays_o, rays_d (R, 3)``, ``z_vals (R, S)``, ``pts (R, S, 3)``.
Functions take and return torch tensors; the device and floating dtype follow ``c2w``.

The kit's own code (trainer, renders, notebooks 07-10) makes rays with :func:`camera_rays`, which
calls the exercise ``get_rays`` exactly as its stub documents (in the student kit: the student's
own ``get_rays``, :mod:`course_lib.saved_solutions`).
"""

from __future__ import annotations

import numpy as np
import torch

from course_lib.validate import KitInputError

__all__ = ["get_rays", "stratified_samples", "query_points", "ray_box_intersection", "camera_rays"]


def _as_tensor(x, like: torch.Tensor | None = None, name: str = "x") -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        t = x
    else:
        try:
            t = torch.as_tensor(np.asarray(x, dtype=np.float64))
        except (TypeError, ValueError):
            raise KitInputError(f"{name} must be a numeric array, got {type(x).__name__}") from None
    if like is not None:
        t = t.to(device=like.device, dtype=like.dtype)
    elif not t.is_floating_point():
        t = t.float()
    return t


def get_rays(H: int, W: int, K, c2w) -> tuple[torch.Tensor, torch.Tensor]:
    """One ray per pixel, through the pixel centres.

    The pixel grid is built with ``torch.meshgrid(u, v, indexing="xy")``: with "xy" indexing the
    outputs have shape ``(H, W)`` (rows first, like the image) and ``u[row, col] = col``,
    ``v[row, col] = row``. (With "ij" they would come out ``(W, H)``, transposed -- a classic bug:
    the rendered image looks mirrored about its diagonal.)

    Args:
        H, W: image size in pixels.
        K: ``(3, 3)`` intrinsics (numpy or torch), pixels.
        c2w: ``(4, 4)`` or ``(3, 4)`` camera-to-world in OpenCV axes (x right, y down, z forward),
            numpy or torch. Its device (and dtype, if a float tensor; else float32) is used.

    Returns:
        ``rays_o (H, W, 3)``: the camera centre, repeated; ``rays_d (H, W, 3)``: world directions,
        unnormalized, with camera-frame z component 1 (``rays_d[v, u] = R_c2w K^-1 [u, v, 1]``).

    Introduced in ``notebooks/06_nerf_data_and_rays.ipynb``.
    """
    if isinstance(c2w, torch.Tensor) and c2w.is_floating_point():
        c2w_t = c2w
    else:
        c2w_t = _as_tensor(c2w, name="c2w").float()
    if tuple(c2w_t.shape) not in ((4, 4), (3, 4)):
        raise KitInputError(f"c2w has shape {tuple(c2w_t.shape)}: expected one (4, 4) camera-to-world matrix")
    K_t = _as_tensor(K, like=c2w_t, name="K")
    if tuple(K_t.shape) != (3, 3):
        raise KitInputError(f"K has shape {tuple(K_t.shape)}: expected (3, 3)")
    if int(H) != H or int(W) != W or H < 1 or W < 1:
        raise KitInputError(f"H, W = {H}, {W}: expected positive integers (image height and width)")
    fx, fy, cx, cy = K_t[0, 0], K_t[1, 1], K_t[0, 2], K_t[1, 2]
    u = torch.arange(int(W), device=c2w_t.device, dtype=c2w_t.dtype)  # pixel centres: 0, 1, ..., W-1
    v = torch.arange(int(H), device=c2w_t.device, dtype=c2w_t.dtype)
    uu, vv = torch.meshgrid(u, v, indexing="xy")  # (H, W) each: uu[row, col] = col, vv[row, col] = row
    d_cam = torch.stack([(uu - cx) / fx, (vv - cy) / fy, torch.ones_like(uu)], dim=-1)  # (H, W, 3), z = 1
    R = c2w_t[:3, :3]
    rays_d = d_cam @ R.T  # row-vector form of R @ d for every pixel
    rays_o = c2w_t[:3, 3].expand(rays_d.shape)
    return rays_o, rays_d


def stratified_samples(near, far, n_samples: int, n_rays: int, perturb: bool, generator: torch.Generator | None = None,
                       device=None, dtype=torch.float32) -> torch.Tensor:
    """Depths of ``n_samples`` points per ray between ``near`` and ``far``.

    Without perturbation the samples are evenly spaced, ``near`` and ``far`` included:
    ``z_i = near + (far - near) * i / (S - 1)``. With ``perturb=True`` (training) each sample is
    drawn uniformly inside its bin, the bins being bounded by the midpoints between the even
    samples (the paper's stratified sampling), so over many iterations the network sees every
    depth, not only S fixed ones.

    Args:
        near, far: floats or ``(R,)`` tensors (per-ray bounds).
        n_samples: S >= 2.
        n_rays: R.
        perturb: jitter inside the bins (training) or not (evaluation).
        generator: torch Generator for the jitter (reproducible runs).
        device, dtype: of the result (default: those of ``near`` if it is a tensor, else CPU float32).

    Returns:
        ``z_vals (R, S)``, sorted along each ray.

    Introduced in ``notebooks/06_nerf_data_and_rays.ipynb``.
    """
    if n_samples < 2:
        raise KitInputError(f"n_samples = {n_samples}: need at least 2 samples per ray")
    if isinstance(near, torch.Tensor):
        device = near.device if device is None else device
        dtype = near.dtype if near.is_floating_point() else dtype
    near_t = torch.as_tensor(near, device=device, dtype=dtype).reshape(-1, 1)
    far_t = torch.as_tensor(far, device=device, dtype=dtype).reshape(-1, 1)
    if (far_t < near_t).any():
        raise KitInputError("far < near for some rays: the sampling interval must be [near, far] with near <= far")
    t = torch.linspace(0.0, 1.0, n_samples, device=device, dtype=dtype)
    z_vals = (near_t * (1.0 - t) + far_t * t).expand(n_rays, n_samples)
    if perturb:
        mids = 0.5 * (z_vals[:, 1:] + z_vals[:, :-1])
        upper = torch.cat([mids, z_vals[:, -1:]], dim=-1)
        lower = torch.cat([z_vals[:, :1], mids], dim=-1)
        u = torch.rand(z_vals.shape, generator=generator, device=device, dtype=dtype)
        z_vals = lower + (upper - lower) * u
    return z_vals.contiguous()


def query_points(rays_o: torch.Tensor, rays_d: torch.Tensor, z_vals: torch.Tensor) -> torch.Tensor:
    """The 3-D sample points ``pts[r, s] = rays_o[r] + z_vals[r, s] * rays_d[r]``.

    Args:
        rays_o: ``(R, 3)``. rays_d: ``(R, 3)``. z_vals: ``(R, S)``.

    Returns:
        ``(R, S, 3)`` world points.

    Introduced in ``notebooks/06_nerf_data_and_rays.ipynb``.
    """
    if (rays_o.ndim != 2 or z_vals.ndim != 2 or rays_o.shape != rays_d.shape or rays_o.shape[-1] != 3
            or z_vals.shape[0] != rays_o.shape[0]):
        raise KitInputError(
            f"rays_o {tuple(rays_o.shape)}, rays_d {tuple(rays_d.shape)}, z_vals {tuple(z_vals.shape)}: "
            "expected (R, 3), (R, 3), (R, S) (flatten the image's rays with .reshape(-1, 3) first)"
        )
    return rays_o[:, None, :] + z_vals[..., None] * rays_d[:, None, :]


def ray_box_intersection(rays_o: torch.Tensor, rays_d: torch.Tensor, box_min, box_max) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry and exit ``t`` of each ray in an axis-aligned box (the slab method).

    Args:
        rays_o, rays_d: ``(R, 3)``. box_min, box_max: ``(3,)`` corners.

    Returns:
        ``t_near (R,), t_far (R,)``; rays that miss the box get ``t_far <= t_near``.
    """
    bmin = _as_tensor(box_min, like=rays_o)
    bmax = _as_tensor(box_max, like=rays_o)
    d = torch.where(rays_d.abs() < 1e-9, torch.full_like(rays_d, 1e-9), rays_d)
    t0 = (bmin - rays_o) / d
    t1 = (bmax - rays_o) / d
    t_near = torch.minimum(t0, t1).amax(dim=-1)
    t_far = torch.maximum(t0, t1).amin(dim=-1)
    return t_near, t_far


def camera_rays(H: int, W: int, K, c2w, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """The rays of one view, by ``get_rays`` called exactly as its stub documents.

    The kit's one call of the exercise ``get_rays`` (the trainer, the renders, the notebooks): ``H``,
    ``W`` as Python ints, ``K`` a ``(3, 3)`` and ``c2w`` a ``(4, 4)`` float32 tensor on one device
    (numpy, float64 and ``(3, 4)`` poses are converted first); the result is checked and returned
    as float32.

    Args:
        H, W: image size in pixels. K: ``(3, 3)`` intrinsics. c2w: ``(4, 4)`` or ``(3, 4)``
            camera-to-world, OpenCV axes (numpy or torch).
        device: where the rays go (default: ``c2w``'s device if it is a tensor, else the CPU).

    Returns:
        ``rays_o (H, W, 3)``, ``rays_d (H, W, 3)`` float32 tensors on ``device``.

    Raises:
        KitInputError: bad camera, or ``get_rays`` returned something else than its stub documents.
    """
    if device is None:
        device = c2w.device if isinstance(c2w, torch.Tensor) else torch.device("cpu")
    c2w_t = _as_tensor(c2w, name="c2w").to(device=device, dtype=torch.float32)
    if tuple(c2w_t.shape) == (3, 4):
        c2w_t = torch.cat([c2w_t, torch.tensor([[0.0, 0.0, 0.0, 1.0]], device=device)], dim=0)
    if tuple(c2w_t.shape) != (4, 4):
        raise KitInputError(f"c2w has shape {tuple(c2w_t.shape)}: expected one (4, 4) camera-to-world matrix")
    K_t = _as_tensor(K, name="K").to(device=device, dtype=torch.float32)
    if tuple(K_t.shape) != (3, 3):
        raise KitInputError(f"K has shape {tuple(K_t.shape)}: expected (3, 3)")
    if int(H) != H or int(W) != W or H < 1 or W < 1:
        raise KitInputError(f"H, W = {H}, {W}: expected positive integers (image height and width)")
    out = get_rays(int(H), int(W), K_t, c2w_t)
    if not isinstance(out, (tuple, list)) or len(out) != 2:
        raise KitInputError(f"get_rays returned a {type(out).__name__}: its docstring documents (rays_o, rays_d)")
    rays = []
    for name, r in zip(("rays_o", "rays_d"), out):
        r = torch.as_tensor(r)
        if tuple(r.shape) != (int(H), int(W), 3):
            raise KitInputError(f"get_rays returned {name} of shape {tuple(r.shape)}: expected (H, W, 3) = "
                                f"({int(H)}, {int(W)}, 3), rows first (torch.meshgrid(..., indexing='xy'))")
        rays.append(r.to(device=device, dtype=torch.float32))
    return rays[0], rays[1]

"""Rendering a trained field, forward only (notebooks 08-09): evaluation, snapshots, ``nerf render``, widgets.

Training needs every sample of every ray, because the gradient flows through all of them. A
render of a trained voxel-grid field (:class:`course_lib.nerf.grid.GridField`) does not; it
marches each ray front to back, ``segment`` samples at a time, at the same sample depths as
training (``n_samples`` evenly spaced between the ray's entry into and exit from the grid's box,
so a render shows exactly what the loss saw), and skips what cannot change the pixel:

* **no autograd** (``torch.inference_mode``): no graph, no saved tensors;
* **rays that miss the box** are background at once;
* **empty space**: a sample in a voxel that the occupancy grid marks empty has sigma = 0 and
  costs its position and one look-up in the occupancy table (padded with empty voxels, so no
  inside test), no trilinear interpolation;
* **corners read once**: an occupied sample's 8 corners and weights (:func:`corners`) serve its
  density and, where its weight counts, its colour; the grids are read voxel by voxel
  (:func:`grid_tables`: views of the channels-last grids), so a corner's channels are one
  contiguous row;
* **a sample's position in voxel units** is one multiply-add per axis (:func:`_voxel_rays`);
* **early ray termination**: once a ray's transmittance ``T`` falls below ``min_transmittance``
  (1e-4) nothing behind can add more than that to its colour, and the ray leaves the march;
* **colour only where it counts**: a sample's colour is read only where its weight exceeds
  ``color_threshold``, and added straight to its ray;
* **chunks sized to the device** (:func:`course_lib.nerf.device.render_chunk`).

Within a segment the compositing is ``volume_render`` (notebook 08; in the student kit the
student's own), given one more sample of zero density one interval beyond the segment so that its
last interval is the real gap (:func:`course_lib.nerf.render.composite`); across segments ``T``
carries over (each segment's weights are scaled by the transmittance before it). The MLP has no occupancy grid:
:func:`render_view` renders it with :func:`course_lib.nerf.render.render_chunked` (also without
gradients).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from course_lib.data.cli_match import scale_intrinsics
from course_lib.data.synthetic import look_at
from course_lib.nerf.device import render_chunk
from course_lib.nerf.grid import GridField, corners, read_corners, voxel_rows
from course_lib.nerf.rays import camera_rays
from course_lib.nerf.render import LAST_DELTA, composite, render_chunked
from course_lib.validate import KitInputError

__all__ = ["RenderSettings", "trilinear_rows", "corners", "read_corners", "grid_tables", "march_grid", "render_rays_forward", "render_view", "render_views", "evaluate",
           "spread_views", "circular_path", "render_path", "save_gif", "save_png", "to_uint8"]

#: a ray whose transmittance is below this leaves the march (its colour can change by less than that)
MIN_TRANSMITTANCE = 1e-4
#: samples per ray marched at once (between two early-termination tests). The building at 400 px
#: (139 samples per ray), 2 CPU threads: 4 -> 106 k rays/s, 8 -> 110-115 k, 16 -> 92 k, 32 -> 89 k
SEGMENT = 8
#: rays per forward-only chunk on a CPU (the march keeps ``SEGMENT`` samples per ray at once)
CPU_FORWARD_CHUNK = 16384


class RenderSettings:
    """How a trained field is rendered: what :func:`render_rays_forward` needs besides the rays.

    Args:
        n_samples: samples per ray (the training's coarse count). n_importance: fine samples (MLP only).
        white_background: composite onto white.
        color_threshold: read colours only where the weight exceeds it.
        near, far: the scene's ray bounds (used by the MLP and by a grid with ``box_bounds=False``).
        box_bounds: a grid samples only inside its box.
        chunk: rays per forward pass (0: from the device).
    """

    def __init__(self, n_samples: int, n_importance: int = 0, white_background: bool = True,
                 color_threshold: float = 0.0, near: float = 0.0, far: float = 1.0, box_bounds: bool = True,
                 chunk: int = 0):
        self.n_samples, self.n_importance = int(n_samples), int(n_importance)
        self.white_background, self.color_threshold = bool(white_background), float(color_threshold)
        self.near, self.far, self.box_bounds, self.chunk = float(near), float(far), bool(box_bounds), int(chunk)

    @classmethod
    def of(cls, cfg, bounds, model=None) -> "RenderSettings":
        """From a :class:`~course_lib.nerf.presets.TrainConfig`, the scene's bounds (SceneBounds or dict) and the model.

        An automatic ``n_samples = 0`` is resolved as training resolves it (from the grid's final resolution).
        """
        near = cfg.near if cfg.near is not None else bounds["near"]
        far = cfg.far if cfg.far is not None else bounds["far"]
        n_samples = cfg.n_samples
        if not n_samples:
            res = cfg.grid_resolution or getattr(model, "resolution", 0)
            n_samples = max(16, int(round(0.8 * res))) if res else 64
        return cls(n_samples, cfg.n_importance, cfg.white_background, cfg.color_threshold, near, far,
                   cfg.box_bounds, cfg.chunk)

    def chunk_for(self, model) -> int:
        """Rays per chunk on the model's device."""
        if self.chunk:
            return self.chunk
        device = next(model.parameters()).device
        if isinstance(model, GridField):
            return CPU_FORWARD_CHUNK if device.type == "cpu" else 4 * render_chunk(device, SEGMENT)
        return render_chunk(device, self.n_samples + self.n_importance)


def trilinear_rows(table: torch.Tensor, shape: tuple, xyz: torch.Tensor) -> torch.Tensor:
    """Trilinear interpolation in a voxel-major table: the forward pass of :class:`~course_lib.nerf.grid.Trilinear`.

    The grid is stored voxel by voxel (``table (D H W, C)``, channels last), so the 8 corners of a
    point are 8 rows of C contiguous values: one gather, then one small matrix product per point
    with the 8 weights (:func:`~course_lib.nerf.grid.corners`, :func:`~course_lib.nerf.grid.read_corners`).

    Args:
        table: ``(D H W, C)``. shape: ``(D, H, W)``. xyz: ``(N, 3)`` grid coordinates in [-1, 1] (x along W).

    Returns:
        ``(N, C)``; points outside the grid read the nearest face's values (callers pass inside points).
    """
    D, H, W = shape
    hi = torch.tensor([W - 1, H - 1, D - 1], dtype=xyz.dtype, device=xyz.device)
    return read_corners(table, *corners(shape, (xyz + 1.0) * 0.5 * hi))


def grid_tables(field: GridField) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """What a march reads: the density and feature grids voxel-major, and the padded occupancy.

    Returns:
        ``density (V, 1)`` and ``features (V, C)`` for :func:`read_corners` (views of the grids:
        :func:`~course_lib.nerf.grid.voxel_rows`, they are stored channels-last), and
        ``occupancy ((D + 2) (H + 2) (W + 2),)``, the occupancy grid with one empty voxel on every
        side, flat (:func:`_occupancy_test`; made here, once for all the chunks and views of a render).
    """
    D, H, W = field.shape
    occupancy = torch.zeros(D + 2, H + 2, W + 2, dtype=torch.bool, device=field.occupancy.device)
    occupancy[1:-1, 1:-1, 1:-1] = field.occupancy
    return voxel_rows(field.density_grid.detach()), voxel_rows(field.feature_grid.detach()), occupancy.reshape(-1)


def _ray_interval(field: GridField, rays_o, rays_d, s: RenderSettings):
    """Per-ray ``(t0, t1)`` where the samples go (the box, or near/far) and the rays that hit."""
    if s.box_bounds:
        t0, t1 = field.ray_bounds(rays_o, rays_d, near=s.near)
    else:
        t0 = torch.full_like(rays_o[:, 0], s.near)
        t1 = torch.full_like(rays_o[:, 0], s.far)
    return t0, t1


def _voxel_rays(field: GridField, rays_o: torch.Tensor, rays_d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays in voxel units: ``(a, b)`` with ``a + b t`` the voxel coordinates (x along W) of the point at depth ``t``.

    :meth:`GridField.normalized` followed by :class:`~course_lib.nerf.grid.Trilinear`'s
    ``(xyz + 1) 0.5 hi`` is ``(x - box_min) / voxel_size``; for the points of a ray that is an
    affine function of the depth, so a sample costs one multiply-add per axis instead of eight
    operations. (Rounding makes a sample within about 1e-6 voxel of a voxel boundary fall on
    either side, in a render as in training.)
    """
    vs = field.voxel_size
    return (rays_o - field.box_min) / vs, rays_d / vs


def _occupancy_test(field: GridField, table: torch.Tensor, in_box: bool):
    """A function ``p (N, 3) -> (n,)``: the indices of the points ``p`` (voxel coordinates) in occupied voxels.

    The rule of :meth:`GridField.occupied` (inside the grid, and its nearest voxel occupied), with
    one look-up per point in ``table``, the occupancy grid padded by one empty voxel on every side
    (:func:`grid_tables`): a point clamped to the padding reads "empty", so there is no inside
    test, only where the samples may leave the box (``in_box=False``: samples between the scene's
    near and far).
    """
    D, H, W = field.shape
    dev, dt = table.device, field.density_grid.dtype
    lo = torch.full((3,), -1.0, dtype=dt, device=dev)
    hi = torch.tensor([W, H, D], dtype=dt, device=dev)  # one past the last voxel: the padding
    strides = torch.tensor([1, W + 2, (H + 2) * (W + 2)], device=dev)
    first = int(strides.sum())  # voxel (0, 0, 0) in the padded table

    def occupied(p: torch.Tensor) -> torch.Tensor:
        q = torch.clamp(p, lo, hi).round_().long()
        occ = table[(q * strides).sum(dim=1).add_(first)]
        if not in_box:
            occ &= ((p >= 0) & (p <= hi - 1)).all(dim=-1)
        return torch.nonzero(occ).squeeze(1)

    return occupied


@torch.inference_mode()
def march_grid(field: GridField, rays_o: torch.Tensor, rays_d: torch.Tensor, s: RenderSettings,
               min_transmittance: float = MIN_TRANSMITTANCE, segment: int = SEGMENT, tables=None) -> dict:
    """Render rays through a grid field front to back, skipping empty space and stopping opaque rays.

    The samples are those of training without jitter: ``n_samples`` evenly spaced depths
    ``t0 + (t1 - t0) i / (S - 1)`` in the ray's interval, every interval ``(t1 - t0) / (S - 1)``
    long (the field ends at its box, so the last interval repeats the previous one). An empty
    sample costs its position and one occupancy look-up; only the occupied ones read the density
    (their 8 corners, kept for the colour of those whose weight counts).

    Args:
        field: the trained :class:`GridField`.
        rays_o, rays_d: ``(R, 3)`` on the field's device.
        s: :class:`RenderSettings`.
        min_transmittance: rays whose transmittance falls below it stop.
        segment: samples per ray marched between two termination tests.
        tables: the field's :func:`grid_tables` (``density (V, 1)``, ``features (V, C)``, padded
            occupancy; made here when None).

    Returns:
        dict with ``rgb_map (R, 3)`` (in [0, 1]), ``depth_map (R,)``, ``acc_map (R,)`` and
        ``samples (R,)``: how many samples of each ray were marched (for the statistics).
    """
    R, S = rays_o.shape[0], s.n_samples
    rgb = rays_o.new_zeros(R, 3)
    depth, acc, marched = rays_o.new_zeros(R), rays_o.new_zeros(R), rays_o.new_zeros(R)
    t0, t1 = _ray_interval(field, rays_o, rays_d, s)
    alive = torch.nonzero(t1 - t0 > 2e-4).squeeze(1)  # rays that cross the box (a miss has t1 = t0 + 1e-4)
    vs = field.voxel_size
    dirs = rays_d / torch.linalg.norm(rays_d, dim=-1, keepdim=True)
    T = rays_o.new_ones(R)
    no_color = rays_o.new_zeros(1, 1, 3)  # the weights need no colours: they are read only where a weight counts
    offsets = torch.arange(segment + 1, device=rays_o.device, dtype=rays_o.dtype)
    density_table, feature_table, occupancy_table = grid_tables(field) if tables is None else tables
    density_flat = density_table.reshape(-1)
    occupied, threshold = _occupancy_test(field, occupancy_table, s.box_bounds), max(s.color_threshold, 0.0)
    ray_a, ray_b = _voxel_rays(field, rays_o, rays_d)
    for first in range(0, S, segment):
        if alive.numel() == 0:
            break
        L = min(segment, S - first)
        u = ((first + offsets[:L + 1]) / (S - 1))[None, :]  # the depths of stratified_samples, bit for bit
        z_ext = t0[alive, None] * (1.0 - u) + t1[alive, None] * u  # (A, L + 1): the segment and the next depth
        z = z_ext[:, :L]
        p = torch.addcmul(ray_a[alive, None, :], ray_b[alive, None, :], z[..., None]).reshape(-1, 3)
        sel = occupied(p)
        sigma = z.new_zeros(z.numel())
        if sel.numel():
            idx, wc = corners(field.shape, p[sel])
            raw = torch.linalg.vecdot(density_flat.index_select(0, idx.reshape(-1)).reshape(idx.shape), wc)
            sigma[sel] = torch.nn.functional.softplus(raw + field.shift) / vs
        # volume_render on the segment, plus the next depth with density 0: the last interval is the real gap
        sigma_ext = torch.cat([sigma.reshape(-1, L), z.new_zeros(len(alive), 1)], dim=1)
        seg = composite(no_color.expand(len(alive), L + 1, 3), sigma_ext, z_ext, rays_d[alive], white_background=False)
        T_alive = T[alive]
        w = seg["weights"][:, :L] * T_alive[:, None]  # weights within the segment, times T before it
        if sel.numel():
            w_sel = w.reshape(-1)[sel]
            lit = torch.nonzero(w_sel > threshold).squeeze(1)  # among the occupied samples (weight 0 elsewhere)
            if lit.numel():
                ray = alive[sel[lit] // L]
                col = field.color_from_features(read_corners(feature_table, idx[lit], wc[lit]), dirs[ray])
                rgb.index_add_(0, ray, col * w_sel[lit, None])
        depth.index_add_(0, alive, (w * z).sum(dim=1))
        acc.index_add_(0, alive, w.sum(dim=1))
        marched.index_add_(0, alive, torch.full_like(z[:, 0], float(L)))
        T_next = T_alive * (1.0 - seg["acc_map"])
        T[alive] = T_next
        alive = alive[T_next > min_transmittance]
    if s.white_background:
        rgb = rgb + (1.0 - acc[:, None])
    return dict(rgb_map=rgb.clamp(0, 1), depth_map=depth, acc_map=acc, samples=marched)


@torch.inference_mode()
def render_rays_forward(model, model_fine, rays_o: torch.Tensor, rays_d: torch.Tensor, s: RenderSettings,
                        tables=None) -> dict:
    """Render any number of rays with a trained model, chunk by chunk, without gradients.

    A :class:`GridField` is marched (:func:`march_grid`; ``tables``: its :func:`grid_tables`, made
    here when None); the MLP renders every sample (:func:`course_lib.nerf.render.render_chunked`).

    Returns:
        dict with ``rgb_map (R, 3)``, ``depth_map (R,)``, ``acc_map (R,)`` on the rays' device.
    """
    chunk = s.chunk_for(model)
    if not isinstance(model, GridField):
        bounds = (lambda o, d: (s.near, s.far))
        return render_chunked(model, rays_o, rays_d, None, None, s.n_samples, s.n_importance, model_fine,
                              white_background=s.white_background, chunk=chunk, color_threshold=s.color_threshold,
                              ray_bounds=bounds, last_delta=LAST_DELTA)
    tables = grid_tables(model) if tables is None else tables  # once for all the chunks
    parts = [march_grid(model, rays_o[i:i + chunk], rays_d[i:i + chunk], s, tables=tables)
             for i in range(0, rays_o.shape[0], chunk)]
    return {k: torch.cat([p[k] for p in parts]) for k in ("rgb_map", "depth_map", "acc_map")}


def render_view(model, model_fine, cfg, bounds, H: int, W: int, K, c2w, tables=None) -> dict:
    """Render one view with a trained model (forward only, chunks sized to the device).

    Args:
        model, model_fine: the trained field(s). cfg: their :class:`~course_lib.nerf.presets.TrainConfig`.
        bounds: the scene's bounds (``SceneBounds`` or its dict). H, W, K, c2w: the camera (OpenCV axes).
        tables: a grid's :func:`grid_tables` (when rendering several views of the same field).

    Returns:
        dict with ``rgb (H, W, 3)``, ``depth (H, W)``, ``acc (H, W)`` tensors on the model's device.

    Introduced in ``notebooks/08_nerf_rendering_and_training.ipynb``.
    """
    device = next(model.parameters()).device
    was = model.training
    model.eval()
    try:
        o, d = camera_rays(H, W, K, c2w, device=device)
        out = render_rays_forward(model, model_fine, o.reshape(-1, 3), d.reshape(-1, 3), RenderSettings.of(cfg, bounds, model),
                                  tables)
    finally:
        model.train(was)
    return dict(rgb=out["rgb_map"].reshape(H, W, 3), depth=out["depth_map"].reshape(H, W),
                acc=out["acc_map"].reshape(H, W))


def render_views(model, model_fine, cfg, bounds, H: int, W: int, K, c2ws):
    """Render several views, one after the other: yields ``(H, W, 3)`` rgb tensors on the model's device.

    A grid field's :func:`grid_tables` are taken once for all the views (the field must not change
    meanwhile).
    """
    tables = grid_tables(model) if isinstance(model, GridField) else None
    for c2w in c2ws:
        yield render_view(model, model_fine, cfg, bounds, H, W, K, c2w, tables)["rgb"]


def preview_camera(H: int, W: int, K, max_side: int) -> tuple[int, int, np.ndarray]:
    """The camera ``(H, W, K)`` shrunk so that its longest side is at most ``max_side`` pixels (0: as it is).

    The same view at fewer pixels (a snapshot's preview): ``K`` scaled about the pixel centres
    (:func:`course_lib.data.cli_match.scale_intrinsics`).
    """
    K = np.asarray(K, dtype=float)
    s = min(1.0, max_side / max(H, W)) if max_side else 1.0
    if s >= 1.0:
        return int(H), int(W), K
    h, w = max(1, round(H * s)), max(1, round(W * s))
    return h, w, scale_intrinsics(K, (W, H), (w, h))


def shrink(img: np.ndarray, H: int, W: int) -> np.ndarray:
    """An ``(h, w, 3)`` float image resized to ``(H, W)`` by area averaging (a render -> its preview)."""
    import cv2

    if img.shape[:2] == (H, W):
        return img
    return cv2.resize(np.ascontiguousarray(img, dtype=np.float32), (W, H), interpolation=cv2.INTER_AREA)


def spread_views(n: int, k: int) -> list[int]:
    """``k`` of ``n`` view indices spread evenly over the set (always the same ones for the same ``k``)."""
    k = max(1, min(int(k), int(n)))
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, k)}) if k < n else list(range(n))


def evaluate(model, model_fine, cfg, bounds, data, views=None, return_renders: bool = True) -> tuple[float, list, list]:
    """Mean PSNR over views of ``data`` (all by default), rendered forward only.

    PSNR per view is ``-10 log10(MSE)`` against the ground truth (uint8 or float images), computed on
    the model's device; only the numbers (and the renders, if ``return_renders``) come to the host.

    Returns:
        ``(mean PSNR, [PSNR per view], [(H, W, 3) float32 numpy renders] or [])``.
    """
    views = list(range(len(data)) if views is None else views)
    if not views:
        raise KitInputError("evaluate: no views to render")
    device = next(model.parameters()).device
    images = np.asarray(data.images)
    scale = 255.0 if images.dtype == np.uint8 else 1.0
    per_view, renders = [], []
    for i, img in zip(views, render_views(model, model_fine, cfg, bounds, data.H, data.W, data.K, np.asarray(data.c2w)[views])):
        gt = torch.as_tensor(images[i]).to(device).float() / scale
        mse = float(torch.mean((img - gt) ** 2))
        per_view.append(float("inf") if mse <= 0 else -10.0 * math.log10(mse))
        if return_renders:
            renders.append(img.cpu().numpy())
    return float(np.mean(per_view)), per_view, renders


def to_uint8(img) -> np.ndarray:
    """``(..., 3)`` float image in [0, 1] -> uint8 (rounded)."""
    return (np.clip(np.asarray(img, dtype=np.float32), 0, 1) * 255 + 0.5).astype(np.uint8)


def save_png(path, img) -> None:
    """Write an ``(H, W, 3)`` image (float in [0, 1], or uint8) as a PNG, creating its folder."""
    from pathlib import Path

    import imageio.v3 as iio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.asarray(img)
    iio.imwrite(path, img if img.dtype == np.uint8 else to_uint8(img))


def circular_path(c2w: np.ndarray, center, n_frames: int = 40, elevation_deg: float | None = None,
                  radius: float | None = None) -> np.ndarray:
    """Cameras on a circle around ``center``, looking at it (OpenCV axes, camera-to-world).

    The world "up" is the mean of the training cameras' up vectors (their -y axes); radius and
    elevation default to the training cameras' mean distance and mean elevation.

    Returns:
        ``(n_frames, 4, 4)`` camera-to-world matrices.
    """
    if n_frames < 1:
        raise KitInputError(f"n_frames {n_frames}: expected at least 1")
    center = np.asarray(center, float)
    up = -c2w[:, :3, 1].mean(axis=0)
    up /= np.linalg.norm(up)
    rel = c2w[:, :3, 3] - center
    dist = np.linalg.norm(rel, axis=1)
    r = float(radius if radius is not None else dist.mean())
    elev = math.radians(elevation_deg) if elevation_deg is not None else float(np.mean(np.arcsin(np.clip(rel @ up / dist, -1, 1))))
    # an orthonormal basis (a, b) of the plane perpendicular to up, a towards the first camera
    a = rel[0] - (rel[0] @ up) * up
    a = a / np.linalg.norm(a) if np.linalg.norm(a) > 1e-9 else np.cross(up, [1.0, 0, 0])
    b = np.cross(up, a)
    out = []
    for k in range(n_frames):
        th = 2 * math.pi * k / n_frames
        C = center + r * (math.cos(elev) * (math.cos(th) * a + math.sin(th) * b) + math.sin(elev) * up)
        R_cw, _t_cw = look_at(C, center, up=up)
        M = np.eye(4)
        M[:3, :3] = R_cw.T
        M[:3, 3] = C
        out.append(M)
    return np.stack(out)


def render_path(model, model_fine, cfg, bounds, H: int, W: int, K, c2w_path: np.ndarray,
                progress: bool = False) -> np.ndarray:
    """Render views along a path (forward only); returns ``(n, H, W, 3)`` uint8 frames."""
    from tqdm.auto import tqdm

    views = render_views(model, model_fine, cfg, bounds, H, W, K, c2w_path)
    bar = tqdm(views, total=len(c2w_path), disable=not progress, desc=f"render on {next(model.parameters()).device.type}")
    return np.stack([to_uint8(img.cpu().numpy()) for img in bar])


def save_gif(path, frames: np.ndarray, fps: float = 12.0):
    """Write ``(n, H, W, 3)`` uint8 frames as a looping GIF; returns its path."""
    from pathlib import Path

    import imageio.v2 as imageio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.mimsave(path, list(frames), duration=1.0 / fps, loop=0)
    return path

"""Volume rendering (notebook 08): from colours and densities along a ray to a pixel.

For samples at depths ``z_1 < ... < z_S`` along a ray with colours ``c_i`` and densities ``sigma_i``::

    delta_i = (z_{i+1} - z_i) |rays_d|        (distance between samples in world units; delta_S = 1e10)
    alpha_i = 1 - exp(-sigma_i delta_i)       (probability that the ray stops in interval i)
    T_i     = prod_{j<i} (1 - alpha_j)        (transmittance: the ray got to sample i; T_1 = 1,
                                                an *exclusive* cumulative product)
    w_i     = T_i alpha_i                     (weights; they sum to acc = 1 - T_{S+1} <= 1)
    C       = sum_i w_i c_i,   depth = sum_i w_i z_i,   acc = sum_i w_i

With a white background the light that passes through everything is white: ``C += 1 - acc``.
The last interval is "to infinity" (1e10), as in the paper's code: whatever density sits at the
last sample stops the ray.

:func:`sample_pdf` draws the fine samples of hierarchical sampling from the coarse weights;
:func:`render_rays` runs coarse (+ fine) sampling, the network and volume rendering for a batch of
rays; :func:`render_chunked` renders any number of rays (several views at once) in chunks without gradients,
:func:`render_image` one whole view. Devices follow the inputs.
"""

from __future__ import annotations

import torch

from course_lib.nerf.rays import camera_rays, query_points, stratified_samples
from course_lib.validate import KitInputError

__all__ = ["volume_render", "composite", "sample_pdf", "render_rays", "render_chunked", "render_image"]

LAST_DELTA = 1e10


def volume_render(rgb: torch.Tensor, sigma: torch.Tensor, z_vals: torch.Tensor, rays_d: torch.Tensor,
                  white_background: bool = True) -> dict[str, torch.Tensor]:
    """Composite samples along each ray (the NeRF quadrature).

    Args:
        rgb: ``(R, S, 3)`` colours in [0, 1].
        sigma: ``(R, S)`` densities >= 0 (per world unit).
        z_vals: ``(R, S)`` sorted sample depths (in units of ``|rays_d|``).
        rays_d: ``(R, 3)`` ray directions (unnormalized; deltas are scaled by their norm).
        white_background: add ``1 - acc`` (white behind the scene).

    The last interval is 1e10, "to infinity", as in the paper (the kit's :func:`composite` gives a
    field that ends at its last sample a real last interval).

    Returns:
        dict with ``rgb_map (R, 3)``, ``depth_map (R,)`` (``sum w z``, in the units of ``z_vals``),
        ``acc_map (R,)`` (opacity), ``weights (R, S)``, ``transmittance (R, S)`` (``T_i``),
        ``alpha (R, S)``.

    Introduced in ``notebooks/08_nerf_rendering_and_training.ipynb``.
    """
    if sigma.ndim != 2 or rgb.shape != (*sigma.shape, 3) or z_vals.shape != sigma.shape:
        raise KitInputError(
            f"rgb {tuple(rgb.shape)}, sigma {tuple(sigma.shape)}, z_vals {tuple(z_vals.shape)}: expected (R, S, 3), (R, S), (R, S)"
        )
    if rays_d.shape != (sigma.shape[0], 3):
        raise KitInputError(f"rays_d has shape {tuple(rays_d.shape)}: expected ({sigma.shape[0]}, 3)")
    dists = z_vals[:, 1:] - z_vals[:, :-1]
    dists = torch.cat([dists, torch.full_like(z_vals[:, :1], LAST_DELTA)], dim=-1)  # (R, S)
    dists = dists * torch.linalg.norm(rays_d, dim=-1, keepdim=True)
    alpha = 1.0 - torch.exp(-sigma * dists)
    # exclusive cumulative product: T_1 = 1, T_i = prod_{j<i} (1 - alpha_j); 1e-10 keeps it > 0 (as the paper's code)
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha + 1e-10], dim=-1), dim=-1)[:, :-1]
    weights = alpha * trans
    rgb_map = (weights[..., None] * rgb).sum(dim=-2)
    depth_map = (weights * z_vals).sum(dim=-1)
    acc_map = weights.sum(dim=-1)
    if white_background:
        rgb_map = rgb_map + (1.0 - acc_map[..., None])
    return dict(rgb_map=rgb_map, depth_map=depth_map, acc_map=acc_map, weights=weights, transmittance=trans, alpha=alpha)


def composite(rgb: torch.Tensor, sigma: torch.Tensor, z_vals: torch.Tensor, rays_d: torch.Tensor,
              white_background: bool = True, last_delta: float | None = LAST_DELTA) -> dict[str, torch.Tensor]:
    """The kit's call of :func:`volume_render`: exactly its documented arguments, its result checked.

    ``last_delta=None`` gives the last sample the previous interval instead of 1e10, for a field
    that ends at its last sample (a voxel grid in its box: with 1e10 its boundary voxels would stop
    every ray and take the background's colour). ``volume_render`` has no such argument, so one
    sample of zero density is appended one interval beyond the last (it stops nothing: ``alpha = 0``)
    and dropped from the weights afterwards.

    Args:
        rgb, sigma, z_vals, rays_d, white_background: as :func:`volume_render`.
        last_delta: ``1e10`` (:data:`LAST_DELTA`, the paper) or None (the previous interval).

    Returns:
        dict with ``rgb_map (R, 3)``, ``depth_map (R,)``, ``acc_map (R,)``, ``weights (R, S)``.
    """
    S = z_vals.shape[-1]
    if last_delta is None:
        if S < 2:
            raise KitInputError("last_delta=None repeats the previous interval: it needs at least 2 samples per ray")
        z_vals = torch.cat([z_vals, 2.0 * z_vals[:, -1:] - z_vals[:, -2:-1]], dim=-1)
        sigma = torch.cat([sigma, torch.zeros_like(sigma[:, :1])], dim=-1)
        rgb = torch.cat([rgb, torch.zeros_like(rgb[:, :1])], dim=-2)
    elif last_delta != LAST_DELTA:
        raise KitInputError(f"last_delta={last_delta}: expected {LAST_DELTA:g} (the paper) or None (the previous interval)")
    out = volume_render(rgb, sigma, z_vals, rays_d, white_background=white_background)
    if not isinstance(out, dict) or not {"rgb_map", "depth_map", "acc_map", "weights"} <= set(out):
        have = sorted(out) if isinstance(out, dict) else type(out).__name__
        raise KitInputError(f"volume_render returned {have}: its docstring documents a dict with rgb_map, depth_map, "
                            "acc_map and weights")
    R = z_vals.shape[0]
    res = {k: out[k] for k in ("rgb_map", "depth_map", "acc_map", "weights")}
    if tuple(res["weights"].shape) != (R, z_vals.shape[-1]) or tuple(res["rgb_map"].shape) != (R, 3):
        raise KitInputError(f"volume_render returned rgb_map {tuple(res['rgb_map'].shape)}, weights "
                            f"{tuple(res['weights'].shape)}: expected ({R}, 3) and ({R}, {z_vals.shape[-1]})")
    if last_delta is None:
        res["weights"] = res["weights"][:, :S]
    return res


def sample_pdf(bins: torch.Tensor, weights: torch.Tensor, n_samples: int, perturb: bool = False,
               generator: torch.Generator | None = None) -> torch.Tensor:
    """Inverse-transform sampling of a piecewise-constant PDF (hierarchical sampling).

    The coarse weights say where along the ray the surface is; the fine network samples there.

    Args:
        bins: ``(R, B + 1)`` sorted bin edges (NeRF: midpoints of the coarse ``z_vals``).
        weights: ``(R, B)`` non-negative weight of each bin (NeRF: the coarse weights without the
            first and last).
        n_samples: number of new samples per ray.
        perturb: random uniform ``u`` (training) or evenly spaced ``u`` (deterministic).
        generator: torch Generator for ``u``.

    Returns:
        ``(R, n_samples)`` depths, sorted, detached (no gradient flows through the sampling).

    Introduced in ``notebooks/08_nerf_rendering_and_training.ipynb``.
    """
    if bins.shape[:-1] != weights.shape[:-1] or bins.shape[-1] != weights.shape[-1] + 1:
        raise KitInputError(f"bins {tuple(bins.shape)}, weights {tuple(weights.shape)}: expected (R, B + 1), (R, B)")
    bins, weights = bins.detach(), weights.detach()
    weights = weights + 1e-5  # no zero-probability bins (and no NaN for empty rays)
    pdf = weights / weights.sum(dim=-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, dim=-1)], dim=-1)  # (R, B + 1)
    R = bins.shape[0]
    if perturb:
        u = torch.rand((R, n_samples), generator=generator, device=bins.device, dtype=bins.dtype)
    else:
        u = torch.linspace(0.0, 1.0, n_samples, device=bins.device, dtype=bins.dtype).expand(R, n_samples)
    u = u.contiguous()
    idx = torch.searchsorted(cdf.contiguous(), u, right=True)
    below = (idx - 1).clamp(min=0)
    above = idx.clamp(max=cdf.shape[-1] - 1)
    cdf_lo, cdf_hi = torch.gather(cdf, 1, below), torch.gather(cdf, 1, above)
    bin_lo, bin_hi = torch.gather(bins, 1, below), torch.gather(bins, 1, above)
    denom = cdf_hi - cdf_lo
    denom = torch.where(denom < 1e-5, torch.ones_like(denom), denom)
    t = (u - cdf_lo) / denom
    return (bin_lo + t * (bin_hi - bin_lo)).detach()


def _run_model(model, pts: torch.Tensor, viewdirs: torch.Tensor, z_vals, rays_d, white_background, color_threshold,
               last_delta):
    """Network + volume rendering; optionally skip the colour of points that do not contribute."""
    R, S = z_vals.shape
    dirs = viewdirs[:, None, :].expand(R, S, 3)
    if color_threshold > 0 and hasattr(model, "density") and hasattr(model, "color"):
        # Two passes: density everywhere (cheap for grid models), colour only where the weight
        # is above the threshold -- empty space and hidden points cost nothing.
        sigma = model.density(pts)
        out = composite(torch.zeros_like(pts), sigma, z_vals, rays_d, white_background=False, last_delta=last_delta)
        mask = out["weights"] > color_threshold
        rgb = torch.zeros_like(pts)
        if mask.any():
            rgb = rgb.index_put((mask,), model.color(pts[mask], dirs[mask]))
    else:
        rgb, sigma = model(pts, dirs)
    return composite(rgb, sigma, z_vals, rays_d, white_background, last_delta)


def _checked(t, shape: tuple, name: str, like: torch.Tensor) -> torch.Tensor:
    """An exercise's tensor result, checked against the shape its stub documents, on ``like``'s device and dtype."""
    t = torch.as_tensor(t)
    if tuple(t.shape) != tuple(shape):
        raise KitInputError(f"{name} returned shape {tuple(t.shape)}: expected {tuple(shape)} (see its docstring)")
    return t.to(device=like.device, dtype=like.dtype)


def render_rays(model, rays_o: torch.Tensor, rays_d: torch.Tensor, near, far, n_samples: int,
                n_importance: int = 0, model_fine=None, perturb: bool = False, white_background: bool = True,
                generator: torch.Generator | None = None, color_threshold: float = 0.0,
                last_delta: float | None = LAST_DELTA) -> dict[str, torch.Tensor]:
    """Render a batch of rays: stratified coarse samples, network, volume rendering (+ fine pass).

    Args:
        model: callable ``model(pts (R, S, 3), viewdirs (R, S, 3)) -> rgb (R, S, 3), sigma (R, S)``.
        rays_o, rays_d: ``(R, 3)`` (``rays_d`` as from :func:`get_rays`; view directions are its
            normalized copy).
        near, far: floats or ``(R,)`` tensors.
        n_samples: coarse samples per ray.
        n_importance: extra fine samples per ray drawn with :func:`sample_pdf` (0: coarse only).
        model_fine: network for the fine pass (default: ``model``).
        perturb: stratified jitter (training) or not.
        white_background: composite onto white.
        generator: torch Generator for the jitter.
        color_threshold: if > 0 and the model has ``density``/``color`` methods, evaluate colours
            only where the weight exceeds it (a speed-up for grid models).
        last_delta: the last interval, see :func:`composite`.

    Returns:
        dict of the (fine, if any) pass: ``rgb_map (R, 3)``, ``depth_map (R,)``, ``acc_map (R,)``,
        ``weights (R, S')``, ``z_vals (R, S')``; with a fine pass also ``rgb_map_coarse``,
        ``depth_map_coarse``, ``acc_map_coarse``.

    Introduced in ``notebooks/08_nerf_rendering_and_training.ipynb``.
    """
    if rays_o.ndim != 2 or rays_o.shape != rays_d.shape or rays_o.shape[-1] != 3:
        raise KitInputError(f"rays_o {tuple(rays_o.shape)}, rays_d {tuple(rays_d.shape)}: expected (R, 3) each")
    R = rays_o.shape[0]
    if not isinstance(near, torch.Tensor):
        near = torch.full((R,), float(near), device=rays_o.device, dtype=rays_o.dtype)
    if not isinstance(far, torch.Tensor):
        far = torch.full((R,), float(far), device=rays_o.device, dtype=rays_o.dtype)
    viewdirs = rays_d / torch.linalg.norm(rays_d, dim=-1, keepdim=True)
    z_vals = _checked(stratified_samples(near, far, n_samples, R, perturb, generator=generator), (R, n_samples),
                      "stratified_samples", rays_o)
    pts = _checked(query_points(rays_o, rays_d, z_vals), (R, n_samples, 3), "query_points", rays_o)
    out = _run_model(model, pts, viewdirs, z_vals, rays_d, white_background, color_threshold, last_delta)
    out["z_vals"] = z_vals
    if n_importance > 0:
        z_mid = 0.5 * (z_vals[:, 1:] + z_vals[:, :-1])
        z_new = sample_pdf(z_mid, out["weights"][:, 1:-1], n_importance, perturb=perturb, generator=generator)
        z_all, _ = torch.sort(torch.cat([z_vals, z_new], dim=-1), dim=-1)
        pts = _checked(query_points(rays_o, rays_d, z_all), (*z_all.shape, 3), "query_points", rays_o)
        fine = _run_model(model_fine if model_fine is not None else model, pts, viewdirs, z_all, rays_d,
                          white_background, color_threshold, last_delta)
        fine["z_vals"] = z_all
        for k in ("rgb_map", "depth_map", "acc_map"):
            fine[k + "_coarse"] = out[k]
        out = fine
    return out


@torch.no_grad()
def render_chunked(model, rays_o: torch.Tensor, rays_d: torch.Tensor, near, far, n_samples: int, n_importance: int = 0,
                   model_fine=None, white_background: bool = True, chunk: int = 4096, color_threshold: float = 0.0,
                   ray_bounds=None, last_delta: float | None = LAST_DELTA) -> dict[str, torch.Tensor]:
    """Render many rays (any number of views at once) in chunks of ``chunk`` rays, without gradients.

    Args:
        model, n_samples, n_importance, model_fine, white_background, color_threshold, last_delta: as
            :func:`render_rays`.
        rays_o, rays_d: ``(R, 3)`` on the model's device.
        near, far: floats (or None when ``ray_bounds`` is given).
        chunk: rays per forward pass (:func:`course_lib.nerf.device.render_chunk` picks it per device).
        ray_bounds: optional callable ``(rays_o, rays_d) -> (near (R,), far (R,))`` (e.g. a box).

    Returns:
        dict with ``rgb_map (R, 3)`` (clamped to [0, 1]), ``depth_map (R,)``, ``acc_map (R,)`` on the
        rays' device (no copy to the host).

    Introduced in ``notebooks/08_nerf_rendering_and_training.ipynb``.
    """
    if chunk < 1:
        raise KitInputError(f"chunk {chunk}: expected a positive number of rays")
    rgb, depth, acc = [], [], []
    for i in range(0, rays_o.shape[0], chunk):
        o, d = rays_o[i:i + chunk], rays_d[i:i + chunk]
        n, f = ray_bounds(o, d) if ray_bounds is not None else (near, far)
        out = render_rays(model, o, d, n, f, n_samples, n_importance, model_fine, perturb=False,
                          white_background=white_background, color_threshold=color_threshold, last_delta=last_delta)
        rgb.append(out["rgb_map"])
        depth.append(out["depth_map"])
        acc.append(out["acc_map"])
    return dict(rgb_map=torch.cat(rgb).clamp(0, 1), depth_map=torch.cat(depth), acc_map=torch.cat(acc))


@torch.no_grad()
def render_image(model, H: int, W: int, K, c2w, near, far, n_samples: int, n_importance: int = 0, model_fine=None,
                 white_background: bool = True, chunk: int = 4096, color_threshold: float = 0.0,
                 ray_bounds=None, last_delta: float | None = LAST_DELTA) -> dict[str, torch.Tensor]:
    """Render a whole view, in chunks of rays, without gradients (evaluation, novel views).

    Args:
        model, n_samples, n_importance, model_fine, white_background, color_threshold, last_delta: as
            :func:`render_rays`.
        H, W, K, c2w: the camera (OpenCV axes), as :func:`course_lib.nerf.rays.get_rays`.
        near, far: floats (or None when ``ray_bounds`` is given).
        chunk: rays per forward pass (memory vs. speed).
        ray_bounds: optional callable ``(rays_o, rays_d) -> (near (R,), far (R,))`` (e.g. a box).

    Returns:
        dict with ``rgb (H, W, 3)``, ``depth (H, W)``, ``acc (H, W)`` tensors on the model's device.

    Introduced in ``notebooks/08_nerf_rendering_and_training.ipynb``.
    """
    try:
        device = next(model.parameters()).device
    except (StopIteration, AttributeError):
        device = torch.device("cpu")
    rays_o, rays_d = camera_rays(H, W, K, c2w, device=device)
    out = render_chunked(model, rays_o.reshape(-1, 3), rays_d.reshape(-1, 3), near, far, n_samples, n_importance,
                         model_fine, white_background=white_background, chunk=chunk, color_threshold=color_threshold,
                         ray_bounds=ray_bounds, last_delta=last_delta)
    return dict(rgb=out["rgb_map"].reshape(H, W, 3), depth=out["depth_map"].reshape(H, W),
                acc=out["acc_map"].reshape(H, W))

"""Training a NeRF (notebook 08): random rays, volume rendering, MSE, Adam; checkpoints and metrics.

One step::

    rays  <- a batch of random pixels across ALL training images (seeded torch.Generator)
    out   <- render_rays(model, rays_o, rays_d, near, far, ...)        (stratified jitter on)
    loss  <- mean((out.rgb_map - pixel colours)^2)                     (+ coarse loss, + TV prior)
    Adam step;  PSNR = -10 log10(MSE)

:func:`train` runs steps on the chosen device (:func:`course_lib.nerf.device.pick_device`) until the
time budget or the number of steps is reached (whichever comes first), shows a ``tqdm.auto`` bar
(seconds trained of seconds allowed for a time budget, else steps; loss and PSNR beside it),
renders a held-out view every ``snapshot_every`` steps (PNG), saves checkpoints (model + optimizer
+ step + config + RNG states + device) that a stopped run resumes from on any device, evaluates
the test views in device-sized batches and writes ``metrics.json``. Time spent on snapshots,
evaluation and checkpoints is not training time: it is recorded (``overhead_seconds``,
``overhead_fraction`` of the wall time, per kind in ``overhead_breakdown``) and kept below
``overhead_budget`` of the training time by letting due snapshots/checkpoints wait.
:func:`render_path` renders novel views along a circle around the scene (GIF).
"""

from __future__ import annotations

import json
import math
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from course_lib.data.blender import BlenderData
from course_lib.nerf.device import device_name, pick_device, render_chunk
from course_lib.nerf.grid import GridField
from course_lib.nerf.model import NeRF
from course_lib.nerf.presets import TrainConfig, preset
from course_lib.nerf.rays import get_rays
from course_lib.nerf.render import LAST_DELTA, render_chunked, render_image, render_rays
from course_lib.threads import set_torch_threads
from course_lib.validate import KitInputError

__all__ = [
    "TrainResult", "TrainingInterrupted", "train", "scene_bounds", "surface_box", "build_model", "psnr", "evaluate", "render_view", "load_checkpoint",
    "render_path", "circular_path", "save_gif",
]

CHECKPOINT = "checkpoint.pt"


def psnr(mse) -> float:
    """PSNR in dB of images in [0, 1]: ``-10 log10(MSE)``."""
    mse = float(mse)
    return float("inf") if mse <= 0 else -10.0 * math.log10(mse)


def scene_bounds(c2w: np.ndarray, K: np.ndarray, W: int) -> dict:
    """A box and ray bounds that contain what the cameras look at (object-centred captures).

    The centre is the point closest (least squares) to all optical axes; the radius is the
    largest sphere around it that fits in the horizontal field of view of the nearest camera,
    ``r = d_min sin(fov_x / 2)``. near/far bracket that sphere from every camera.

    Args:
        c2w: ``(N, 4, 4)`` camera-to-world, OpenCV axes. K: ``(3, 3)``. W: image width.

    Returns:
        dict with ``center (3,)``, ``radius``, ``box_min``, ``box_max`` (lists), ``near``, ``far``.
    """
    C = c2w[:, :3, 3]
    z = c2w[:, :3, 2] / np.linalg.norm(c2w[:, :3, 2], axis=1, keepdims=True)
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in zip(C, z):
        P = np.eye(3) - np.outer(d, d)  # projector orthogonal to the axis
        A += P
        b += P @ c
    center = np.linalg.lstsq(A, b, rcond=None)[0] if len(C) > 1 else C[0] + 4.0 * z[0]
    dist = np.linalg.norm(C - center, axis=1)
    half_fov = math.atan(0.5 * W / K[0, 0])
    radius = float(dist.min() * math.sin(half_fov))
    near = float(max(0.05 * dist.min(), dist.min() - radius * math.sqrt(3)))
    far = float(dist.max() + radius * math.sqrt(3))
    return dict(center=center.tolist(), radius=radius, box_min=(center - radius).tolist(),
                box_max=(center + radius).tolist(), near=near, far=far)


@torch.no_grad()
def surface_box(model: GridField, cfg: TrainConfig, rays_o: torch.Tensor, rays_d: torch.Tensor,
                generator: torch.Generator, n_rays: int = 16384, min_weight: float = 0.05,
                margin_voxels: float = 3.0) -> tuple[list, list]:
    """The box around the points where (a sample of) the training rays stop, with a margin.

    After a short coarse stage the density in empty space is still noisy ("fog" of small
    opacity), but the points that carry most of each ray's weight already sit on the surfaces;
    their bounding box is a tight box for the fine grid (robust quantiles, then a margin).

    Returns:
        ``(box_min, box_max)`` lists, inside the current box.
    """
    idx = torch.randint(0, rays_o.shape[0], (min(n_rays, rays_o.shape[0]),), generator=generator, device=rays_o.device)
    o, d = rays_o[idx], rays_d[idx]
    near, far = model.ray_bounds(o, d)
    pts_all = []
    chunk = _chunk(cfg, model)
    for i in range(0, o.shape[0], chunk):
        out = render_rays(model, o[i:i + chunk], d[i:i + chunk], near[i:i + chunk], far[i:i + chunk],
                          cfg.n_samples, white_background=cfg.white_background, last_delta=None)
        w, z = out["weights"], out["z_vals"]
        keep = w > min_weight
        pts = o[i:i + chunk, None, :] + z[..., None] * d[i:i + chunk, None, :]
        pts_all.append(pts[keep])
    pts = torch.cat(pts_all)
    if pts.shape[0] < 100:
        return model.box_min.tolist(), model.box_max.tolist()
    lo = torch.quantile(pts, 0.001, dim=0) - margin_voxels * model.voxel_size
    hi = torch.quantile(pts, 0.999, dim=0) + margin_voxels * model.voxel_size
    lo = torch.maximum(lo, model.box_min)
    hi = torch.minimum(hi, model.box_max)
    return lo.tolist(), hi.tolist()


def build_model(cfg: TrainConfig, bounds: dict, resolution: int | None = None):
    """The model(s) of a config: ``(model, model_fine or None)``; weights from the global torch RNG."""
    if cfg.model == "nerf":
        kw = dict(depth=cfg.depth, width=cfg.width, skips=tuple(cfg.skips), pos_freqs=cfg.pos_freqs,
                  dir_freqs=cfg.dir_freqs, use_viewdirs=cfg.use_viewdirs, view_width=cfg.view_width, density=cfg.density)
        fine = NeRF(**kw) if (cfg.fine and cfg.n_importance > 0) else None
        return NeRF(**kw), fine
    if cfg.model == "grid":
        res = resolution or (cfg.grid_schedule[0][1] if cfg.grid_schedule else cfg.grid_resolution)
        return GridField(bounds["box_min"], bounds["box_max"], resolution=res, mlp_width=cfg.grid_mlp_width,
                         feature_dim=cfg.grid_feature_dim, dir_freqs=cfg.grid_dir_freqs, alpha_init=cfg.alpha_init,
                         sh_degree=cfg.grid_sh_degree if not cfg.grid_sh_start else 0), None
    raise KitInputError(f"model {cfg.model!r}: expected 'nerf' or 'grid'")


def _optimizer(cfg: TrainConfig, model, model_fine) -> torch.optim.Optimizer:
    """Adam: grid values at ``grid_lr``, network weights at ``lr``.

    On a CPU or a CUDA GPU the fused implementation (one pass over the memory instead of several)
    runs the same update: a grid's Adam step touches every voxel, and fused it costs about a
    quarter of the time on a CPU (4 M values: 6 ms instead of 29 ms).
    """
    device = next(model.parameters()).device
    fused = True if device.type in ("cpu", "cuda") else None
    if isinstance(model, GridField):
        groups = [{"params": [model.density_grid, model.feature_grid], "lr": cfg.grid_lr, "kind": "grid"}]
        rest = [p for n, p in model.named_parameters() if not n.endswith("_grid")]
        if rest:
            groups.append({"params": rest, "lr": cfg.lr, "kind": "mlp"})
        return torch.optim.Adam(groups, betas=(0.9, 0.99), fused=fused)
    params = list(model.parameters()) + (list(model_fine.parameters()) if model_fine is not None else [])
    return torch.optim.Adam([{"params": params, "lr": cfg.lr, "kind": "mlp"}], betas=(0.9, 0.999), fused=fused)


def _set_lr(opt: torch.optim.Optimizer, cfg: TrainConfig, progress: float) -> None:
    """Exponential decay from the initial to the final learning rate over the run."""
    for g in opt.param_groups:
        lo, hi = (cfg.grid_lr_final, cfg.grid_lr) if g.get("kind") == "grid" else (cfg.lr_final, cfg.lr)
        g["lr"] = hi * (lo / hi) ** min(max(progress, 0.0), 1.0)


def _bounds_fn(model, cfg: TrainConfig, bounds: dict):
    """Per-ray (near, far): the grid's box (``cfg.box_bounds``), or the config's/scene's near and far."""
    near = cfg.near if cfg.near is not None else bounds["near"]
    far = cfg.far if cfg.far is not None else bounds["far"]
    if isinstance(model, GridField) and cfg.box_bounds:
        return lambda o, d: model.ray_bounds(o, d, near=near)
    return lambda o, d: (near, far)


def _last_delta(model):
    """The paper's "to infinity" last interval for MLPs; the grid's field ends at its box (None)."""
    return None if isinstance(model, GridField) else LAST_DELTA


def _chunk(cfg: TrainConfig, model) -> int:
    """Rays per render chunk: ``cfg.chunk``, or (0) what the model's device takes."""
    if cfg.chunk:
        return int(cfg.chunk)
    return render_chunk(next(model.parameters()).device, cfg.n_samples + cfg.n_importance)


def render_view(model, model_fine, cfg: TrainConfig, bounds: dict, H: int, W: int, K, c2w) -> dict:
    """Render one view with a trained model (no gradients, chunks of rays sized to the device).

    Returns:
        dict with ``rgb (H, W, 3)``, ``depth (H, W)``, ``acc (H, W)`` tensors on the model's device.
    """
    was = model.training
    model.eval()
    out = render_image(model, H, W, K, c2w, None, None, cfg.n_samples, cfg.n_importance, model_fine,
                       white_background=cfg.white_background, chunk=_chunk(cfg, model),
                       color_threshold=cfg.color_threshold, ray_bounds=_bounds_fn(model, cfg, bounds),
                       last_delta=_last_delta(model))
    model.train(was)
    return out


def evaluate(model, model_fine, cfg: TrainConfig, bounds: dict, data: BlenderData, views=None,
             return_renders: bool = True) -> tuple[float, list, list]:
    """Mean PSNR over views of ``data`` (all by default); returns ``(mean, per_view, renders)``.

    The views are rendered together, several per batch where the device's chunk holds more rays
    than one view, and compared with the ground truth on the device; only the per-view PSNRs (and
    the renders, if ``return_renders``) come back to the host.

    Returns:
        ``(mean PSNR, [PSNR per view], [(H, W, 3) float32 numpy renders] or [])``.
    """
    views = list(range(len(data)) if views is None else views)
    if not views:
        raise KitInputError("evaluate: no views to render")
    device = next(model.parameters()).device
    chunk = _chunk(cfg, model)
    H, W = data.H, data.W
    per_batch = max(1, chunk // (H * W))
    ray_bounds = _bounds_fn(model, cfg, bounds)
    was = model.training
    model.eval()
    mse_all, renders = [], []
    for b in range(0, len(views), per_batch):
        vb = views[b:b + per_batch]
        c2w = torch.as_tensor(np.asarray(data.c2w)[vb], dtype=torch.float32, device=device)
        rays = [get_rays(H, W, data.K, c2w[k]) for k in range(len(vb))]
        rays_o = torch.cat([r[0].reshape(-1, 3) for r in rays])
        rays_d = torch.cat([r[1].reshape(-1, 3) for r in rays])
        out = render_chunked(model, rays_o, rays_d, None, None, cfg.n_samples, cfg.n_importance, model_fine,
                             white_background=cfg.white_background, chunk=chunk, color_threshold=cfg.color_threshold,
                             ray_bounds=ray_bounds, last_delta=_last_delta(model))
        img = out["rgb_map"].reshape(len(vb), H, W, 3)
        gt = torch.as_tensor(np.asarray(data.images)[vb], dtype=img.dtype).to(device)
        mse_all.append(((img - gt) ** 2).mean(dim=(1, 2, 3)))
        if return_renders:
            renders.extend(img.cpu().numpy())
    model.train(was)
    vals = [psnr(m) for m in torch.cat(mse_all).cpu().tolist()]
    return float(np.mean(vals)), vals, renders


def _to_uint8(img) -> np.ndarray:
    return (np.clip(np.asarray(img, dtype=np.float32), 0, 1) * 255 + 0.5).astype(np.uint8)


def _save_png(path: Path, img) -> None:
    import imageio.v3 as iio

    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, _to_uint8(img))


@dataclass
class TrainResult:
    """What :func:`train` returns.

    Attributes:
        model, model_fine: the trained field(s) (``model_fine`` None without a fine network).
        config: the :class:`TrainConfig` used.
        bounds: the scene box / near / far (:func:`scene_bounds`).
        metrics: the dict written to ``metrics.json``.
        history: ``iterations, loss, psnr, seconds`` per step and ``test_iterations, test_psnr``.
        snapshots: list of ``(step, (H, W, 3) float image)`` of the held-out view.
        test_renders: ``(N, H, W, 3)`` renders of the test views (empty without test data).
    """

    model: torch.nn.Module
    model_fine: torch.nn.Module | None
    config: TrainConfig
    bounds: dict
    metrics: dict
    history: dict
    snapshots: list = field(default_factory=list)
    test_renders: np.ndarray | None = None


def _progress(cfg: TrainConfig, step: int, elapsed: float) -> float:
    """Fraction of the run done (for the learning-rate decay): steps of ``iters`` or seconds of ``minutes``."""
    p = step / max(cfg.iters, 1)
    if cfg.minutes:
        p = max(p, elapsed / (60.0 * cfg.minutes))
    return min(p, 1.0)


def _target_resolution(cfg: TrainConfig, step: int) -> int:
    res = cfg.grid_resolution
    for at, r in cfg.grid_schedule:
        if step >= at:
            res = r
    return int(res)


class TrainingInterrupted(KeyboardInterrupt):
    """Ctrl-C during :func:`train`: raised after the checkpoint was written (a ``KeyboardInterrupt``).

    Attributes:
        step: the last completed step. checkpoint: the checkpoint's path (None without ``out_dir``).
    """

    def __init__(self, step: int, checkpoint: Path | None):
        super().__init__(f"interrupted at step {step}")
        self.step, self.checkpoint = step, checkpoint


def _save_checkpoint(path: Path, model, model_fine, opt, cfg, bounds, step, elapsed, history, gen, camera=None,
                     device=None) -> None:
    torch.save({
        "camera": camera, "device": str(device) if device is not None else None,
        "model": model.state_dict(), "model_config": model.config(), "model_kind": cfg.model,
        "model_fine": model_fine.state_dict() if model_fine is not None else None,
        "optimizer": opt.state_dict(), "step": step, "train_seconds": elapsed, "config": cfg.to_dict(),
        "bounds": bounds, "history": history, "generator_state": gen.get_state(),
        "torch_rng_state": torch.get_rng_state(),
    }, path.with_suffix(".tmp"))
    path.with_suffix(".tmp").replace(path)


def load_checkpoint(path, device="cpu") -> dict:
    """Load a checkpoint written by :func:`train` onto any device, whichever device wrote it.

    Args:
        path: ``checkpoint.pt`` or the training output folder.
        device: where the rebuilt models go (``"auto"``, ``"cpu"``, ``"cuda"``, ``"mps"``, a torch.device).

    Returns:
        The stored dict (``step``, ``config``, ``bounds``, ``history``, ``device`` it was written on, ...)
        plus the rebuilt ``model``, ``model_fine`` (on ``device``) and ``cfg``.
    """
    path = Path(path)
    if path.is_dir():
        path = path / CHECKPOINT
    if not path.exists():
        raise KitInputError(f"checkpoint {path} not found: pass a checkpoint.pt (or the training output folder)")
    device = pick_device(device)
    try:
        # everything to the CPU first: RNG states must stay CPU tensors, the models move afterwards
        ck = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001 -- any unreadable file
        raise KitInputError(f"{path} is not a readable checkpoint ({exc})") from None
    cfg = TrainConfig.from_dict(ck["config"])
    if ck["model_kind"] == "grid":
        mc = ck["model_config"]
        model = GridField(mc["box_min"], mc["box_max"], resolution=mc["resolution"], mlp_width=mc["mlp_width"],
                          feature_dim=mc["feature_dim"], dir_freqs=mc["dir_freqs"], alpha_init=mc["alpha_init"],
                          sh_degree=mc.get("sh_degree", 0))
        model_fine = None
    else:
        mc = ck["model_config"]
        model = NeRF(**{**mc, "skips": tuple(mc["skips"])})
        model_fine = NeRF(**{**mc, "skips": tuple(mc["skips"])}) if ck["model_fine"] is not None else None
    model.load_state_dict(ck["model"])
    if model_fine is not None:
        model_fine.load_state_dict(ck["model_fine"])
    model.to(device)
    if model_fine is not None:
        model_fine.to(device)
    ck.setdefault("device", None)
    ck.update(model=model, model_fine=model_fine, cfg=cfg)
    return ck


class _Clock:
    """Wall time outside the training steps, by kind, and the rule that keeps it small.

    ``due(kind)`` is True when a snapshot/evaluation/checkpoint may run now: while the time spent
    outside training exceeds ``budget`` x the training time of this call, due work waits.
    """

    def __init__(self, budget: float):
        self.budget = float(budget)
        self.seconds: dict[str, float] = {}
        self.pending: set[str] = set()

    @property
    def total(self) -> float:
        return sum(self.seconds.values())

    def allowed(self, train_seconds: float) -> bool:
        return self.budget <= 0 or self.total <= self.budget * train_seconds

    def timed(self, kind: str, fn, *args):
        t = time.perf_counter()
        try:
            return fn(*args)
        finally:
            self.seconds[kind] = self.seconds.get(kind, 0.0) + time.perf_counter() - t


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    elif device.type == "mps":
        torch.mps.synchronize()


class _Bar:
    """The progress bar: seconds trained of seconds allowed (a time budget), else steps of steps."""

    def __init__(self, cfg: TrainConfig, step: int, elapsed: float, enabled: bool, device: torch.device):
        from tqdm.auto import tqdm

        self.by_time = bool(cfg.minutes)
        desc = f"nerf {cfg.preset} on {device.type}"
        if self.by_time:
            self.bar = tqdm(total=round(60.0 * cfg.minutes, 1), initial=round(min(elapsed, 60.0 * cfg.minutes), 1),
                            disable=not enabled, desc=desc, mininterval=1.0, unit="s",
                            bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} s trained "
                                       "[{elapsed} wall{postfix}]")
        else:
            self.bar = tqdm(total=cfg.iters, initial=step, disable=not enabled, desc=desc, mininterval=1.0,
                            unit="step")
        self.shown = elapsed if self.by_time else step

    def update(self, step: int, elapsed: float, info: dict | None) -> None:
        now = min(elapsed, self.bar.total) if self.by_time else step
        if info is not None:
            self.bar.set_postfix(info, refresh=False)
        self.bar.update(now - self.shown)
        self.shown = now

    def close(self) -> None:
        self.bar.close()


def train(train_data: BlenderData, test_data: BlenderData | None = None, config: TrainConfig | str = "fast",
          out_dir=None, resume: bool = True, progress: bool = True, device="auto", callback=None,
          snapshot_view: int = 0) -> TrainResult:
    """Train a NeRF (or the grid field of the "fast" preset) on one scene.

    Args:
        train_data: the training views (:func:`course_lib.data.blender.load_blender`, split "train").
        test_data: held-out views: snapshots show ``test_data[snapshot_view]``; the final test PSNR
            is the mean over all of them (None: snapshots of a training view, no test PSNR).
        config: a :class:`TrainConfig` or a preset name (``"paper"``, ``"fast"``).
        out_dir: folder for ``metrics.json``, ``snapshots/step_XXXXXX.png``, ``test/<name>.png``
            and ``checkpoint.pt`` (None: write nothing, e.g. in a notebook).
        resume: continue from ``out_dir/checkpoint.pt`` if there is one (same step, optimizer,
            RNG states; the time already trained counts against ``minutes``). A checkpoint resumes
            on any device; the ray sampler's random stream continues exactly only on the device
            type that wrote it (elsewhere it is reseeded from the seed and the step).
        progress: show a tqdm.auto progress bar: with a time budget (``minutes``) it counts seconds
            trained of seconds allowed, else steps of ``iters``; loss, PSNR and step beside it.
        device: ``"auto"`` (CUDA, then MPS, then the CPU), ``"cpu"``, ``"cuda"``, ``"mps"`` or a
            torch.device (:func:`course_lib.nerf.device.pick_device`).
        callback: optional ``callback(step, info: dict) -> bool``, called after each step with
            ``loss, psnr, seconds`` (training time so far), ``model, model_fine, config, bounds``;
            return True to stop (a checkpoint is written). Its own time is not training time.
        snapshot_view: index of the held-out view in the snapshots.

    Returns:
        :class:`TrainResult` (model, metrics, history, snapshots, test renders).

    Raises:
        TrainingInterrupted: Ctrl-C (a ``KeyboardInterrupt``), after the checkpoint was written.

    Introduced in ``notebooks/08_nerf_rendering_and_training.ipynb``.
    """
    cfg = preset(config) if isinstance(config, str) else config
    if not isinstance(train_data, BlenderData) or len(train_data) == 0:
        raise KitInputError("train_data must be a non-empty BlenderData (course_lib.data.blender.load_blender)")
    device = pick_device(device)
    if device.type == "cpu":
        set_torch_threads(cfg.threads)
    out = Path(out_dir) if out_dir is not None else None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    t_wall = time.perf_counter()
    clock = _Clock(cfg.overhead_budget)

    # ---------------------------------------------------------------- all rays of all training images
    H, W = train_data.H, train_data.W
    c2w_all = torch.as_tensor(train_data.c2w, dtype=torch.float32, device=device)
    rays = [get_rays(H, W, train_data.K, c2w_all[i]) for i in range(len(train_data))]
    rays_o = torch.stack([r[0] for r in rays]).reshape(-1, 3)
    rays_d = torch.stack([r[1] for r in rays]).reshape(-1, 3)
    target = torch.as_tensor(train_data.images).to(device).reshape(-1, 3)
    del rays
    n_rays = rays_o.shape[0]
    bounds = scene_bounds(train_data.c2w, train_data.K, W)
    if cfg.near is not None:
        bounds["near"] = cfg.near
    if cfg.far is not None:
        bounds["far"] = cfg.far

    # ---------------------------------------------------------------- model, optimizer, RNG (or resume)
    gen = torch.Generator(device=device).manual_seed(cfg.seed)
    ckpt_path = out / CHECKPOINT if out is not None else None
    history = {"iterations": [], "loss": [], "psnr": [], "seconds": [], "test_iterations": [], "test_psnr": []}
    step, elapsed = 0, 0.0
    resumed_from = None
    if resume and ckpt_path is not None and ckpt_path.exists():
        ck = load_checkpoint(ckpt_path, device)
        model, model_fine = ck["model"], ck["model_fine"]
        if ck["cfg"].model != cfg.model:
            raise KitInputError(f"{ckpt_path} holds a {ck['cfg'].model!r} model but the config asks for {cfg.model!r}: "
                                "use another --out folder or delete the checkpoint")
        bounds = ck["bounds"]
        opt = _optimizer(cfg, model, model_fine)
        opt.load_state_dict(ck["optimizer"])
        step, elapsed, history = ck["step"], ck["train_seconds"], ck["history"]
        written_on = torch.device(ck["device"]).type if ck.get("device") else "cpu"
        if written_on == device.type:
            gen.set_state(ck["generator_state"])
        else:  # another device's generator state does not fit: a new, reproducible stream
            gen.manual_seed(cfg.seed + 1_000_003 * step)
        torch.set_rng_state(ck["torch_rng_state"])
        resumed_from = {"step": step, "train_seconds": round(elapsed, 2), "device": ck.get("device")}
    else:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(cfg.seed)
            model, model_fine = build_model(cfg, bounds)
        model.to(device)
        if model_fine is not None:
            model_fine.to(device)
        opt = _optimizer(cfg, model, model_fine)
    is_grid = isinstance(model, GridField)
    last_delta = _last_delta(model)
    near_far = _bounds_fn(model, cfg, bounds)

    camera = {"H": H, "W": W, "K": np.asarray(train_data.K).tolist(), "c2w": np.asarray(train_data.c2w).tolist()}
    snap_data = test_data if test_data is not None and len(test_data) else train_data
    snap_i = min(snapshot_view, len(snap_data) - 1)
    snapshots: list = []
    budget_s = 60.0 * cfg.minutes if cfg.minutes else None
    eval_views = list(range(min(cfg.n_eval_views, len(test_data)))) if test_data is not None else []
    # history on a GPU: losses stay on the device and come to the host every `sync_every` steps
    sync_every = 1 if device.type == "cpu" else 25
    pending: list = []  # (step, seconds, loss tensor, mse tensor) not yet in the history

    def flush():
        if pending:
            vals = torch.stack([torch.stack([lo.detach(), ms.detach()]) for _, _, lo, ms in pending]).cpu().tolist()
            for (st, sec, _, _), (lo, ms) in zip(pending, vals):
                history["iterations"].append(st)
                history["loss"].append(float(lo))
                history["psnr"].append(psnr(ms))
                history["seconds"].append(round(sec, 3))
            pending.clear()

    def snapshot():
        img = render_view(model, model_fine, cfg, bounds, snap_data.H, snap_data.W, snap_data.K, snap_data.c2w[snap_i])["rgb"]
        img = img.cpu().numpy()
        snapshots.append((step, img))
        if out is not None:
            _save_png(out / "snapshots" / f"step_{step:06d}.png", img)

    def test_eval():
        history["test_iterations"].append(step)
        history["test_psnr"].append(evaluate(model, model_fine, cfg, bounds, test_data, eval_views, return_renders=False)[0])

    def checkpoint():
        if ckpt_path is not None:
            flush()
            _save_checkpoint(ckpt_path, model, model_fine, opt, cfg, bounds, step, elapsed, history, gen, camera, device)

    clock.seconds["setup"] = time.perf_counter() - t_wall
    bar = _Bar(cfg, step, elapsed, progress, device)
    if cfg.snapshot_every and step == 0:
        clock.timed("snapshots", snapshot)
    samples_done, run_seconds = 0, 0.0  # this call only (a resumed run has trained before)
    stopped_by = "iterations"
    last = {}
    try:
        while step < cfg.iters:
            if budget_s is not None and elapsed >= budget_s:
                stopped_by = "time"
                break
            t0 = time.perf_counter()
            frac = _progress(cfg, step, elapsed)
            if is_grid and cfg.shrink_box_at and not bounds.get("shrunk") and step >= cfg.shrink_box_at:
                # coarse geometry found: resample the grids into the box around the occupied voxels
                lo, hi = surface_box(model, cfg, rays_o, rays_d, gen)
                model.rebox(lo, hi, _target_resolution(cfg, step))
                model.update_occupancy(cfg.occupancy_threshold)
                bounds.update(box_min=lo, box_max=hi, shrunk=True)
                opt = _optimizer(cfg, model, model_fine)
            if is_grid and cfg.grid_schedule:
                res = _target_resolution(cfg, step)
                if res > model.resolution:
                    model.upsample(res)
                    model.update_occupancy(cfg.occupancy_threshold)
                    opt = _optimizer(cfg, model, model_fine)
            if is_grid and cfg.grid_sh_degree and model.sh_degree == 0 and step >= cfg.grid_sh_start:
                model.enable_sh(cfg.grid_sh_degree)  # RGB first (cheap steps), view-dependent colour from here
                opt = _optimizer(cfg, model, model_fine)
            _set_lr(opt, cfg, frac)
            idx = torch.randint(0, n_rays, (cfg.batch_rays,), generator=gen, device=device)
            o, d, rgb_true = rays_o[idx], rays_d[idx], target[idx]
            near, far = near_far(o, d)
            res_out = render_rays(model, o, d, near, far, cfg.n_samples, cfg.n_importance, model_fine,
                                  perturb=cfg.perturb, white_background=cfg.white_background, generator=gen,
                                  color_threshold=cfg.color_threshold, last_delta=last_delta)
            mse = F.mse_loss(res_out["rgb_map"], rgb_true)
            loss = mse
            if "rgb_map_coarse" in res_out:
                loss = loss + F.mse_loss(res_out["rgb_map_coarse"], rgb_true)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if is_grid and cfg.tv_weight > 0:  # + tv_weight * TV(density), its gradient written out (cheaper)
                loss = loss.detach() + cfg.tv_weight * model.add_total_variation_grad(cfg.tv_weight)
            opt.step()
            step += 1
            samples_done += cfg.batch_rays * (cfg.n_samples + cfg.n_importance)
            if is_grid and cfg.occupancy_every and step >= cfg.occupancy_start and step % cfg.occupancy_every == 0:
                model.update_occupancy(cfg.occupancy_threshold)
            pending.append((step, 0.0, loss, mse))
            synced = step % sync_every == 0 or step == 1 or callback is not None
            if synced:
                _sync(device)
            dt = time.perf_counter() - t0
            elapsed += dt
            run_seconds += dt
            pending[-1] = (step, elapsed, loss, mse)
            if synced:
                flush()
                last = {"loss": history["loss"][-1], "psnr": history["psnr"][-1]}
            show = synced and last and (step % 10 == 0 or step == 1)
            bar.update(step, elapsed, {"step": step, "loss": f"{last['loss']:.4f}", "psnr": f"{last['psnr']:.2f}"}
                       if show else None)

            for kind, every, fn in (("snapshots", cfg.snapshot_every, snapshot),
                                    ("evaluations", cfg.eval_every if eval_views else 0, test_eval),
                                    ("checkpoints", cfg.checkpoint_every, checkpoint)):
                if every and step % every == 0:
                    clock.pending.add(kind)
                if kind in clock.pending and clock.allowed(run_seconds):
                    clock.pending.discard(kind)
                    clock.timed(kind, fn)
            if callback is not None:
                t_cb = time.perf_counter()
                stop = callback(step, {"loss": last.get("loss"), "psnr": last.get("psnr"), "seconds": elapsed,
                                       "model": model, "model_fine": model_fine, "config": cfg, "bounds": bounds})
                clock.seconds["callback"] = clock.seconds.get("callback", 0.0) + time.perf_counter() - t_cb
                if stop:
                    stopped_by = "callback"
                    break
    except KeyboardInterrupt:
        bar.close()
        checkpoint()
        raise TrainingInterrupted(step, ckpt_path) from None
    bar.close()
    flush()
    if budget_s is not None and elapsed >= budget_s and stopped_by == "iterations" and step < cfg.iters:
        stopped_by = "time"
    clock.timed("checkpoints", checkpoint)
    if cfg.snapshot_every and (not snapshots or snapshots[-1][0] != step):
        clock.timed("snapshots", snapshot)

    # ---------------------------------------------------------------- final evaluation and metrics
    metrics = {
        "preset": cfg.preset, "iterations": step, "train_seconds": round(elapsed, 2), "stopped_by": stopped_by,
        "final_train_psnr": float(np.mean(history["psnr"][-50:])) if history["psnr"] else None,
        "rays_per_second": round(samples_done / max(cfg.n_samples + cfg.n_importance, 1) / max(run_seconds, 1e-9), 1),
        "samples_per_second": round(samples_done / max(run_seconds, 1e-9), 1) if samples_done else None,
        "n_parameters": int(sum(p.numel() for p in model.parameters())
                            + (sum(p.numel() for p in model_fine.parameters()) if model_fine is not None else 0)),
        "n_train_views": len(train_data), "image_size": [W, H], "bounds": bounds, "device": str(device),
        "device_name": device_name(device), "render_chunk": _chunk(cfg, model), "resumed_from": resumed_from,
        "threads": torch.get_num_threads(), "torch": torch.__version__, "config": cfg.to_dict(),
        "data": str(train_data.folder) if train_data.folder is not None else None,
    }
    test_renders = None
    if test_data is not None and len(test_data):
        t = time.perf_counter()
        mean, per_view, renders = evaluate(model, model_fine, cfg, bounds, test_data)
        test_renders = np.stack(renders)
        clock.seconds["final_evaluation"] = time.perf_counter() - t
        metrics.update(test_psnr=round(mean, 3), test_psnr_per_view=[round(v, 3) for v in per_view],
                       n_test_views=len(test_data), eval_seconds=round(clock.seconds["final_evaluation"], 2))
        history["test_iterations"].append(step)
        history["test_psnr"].append(mean)
        if out is not None:
            clock.timed("final_evaluation", lambda: [_save_png(out / "test" / f"{name}.png", img)
                                                    for name, img in zip(test_data.names, renders)])
    else:
        metrics["test_psnr"] = None
    if device.type == "cuda":
        metrics["peak_gpu_memory_mb"] = round(torch.cuda.max_memory_allocated(device) / 2**20, 1)
    metrics["peak_memory_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)
    wall = time.perf_counter() - t_wall
    # wall time of this call = training steps of this call + everything else (setup, snapshots, evaluations,
    # checkpoints, the caller's callback, the final evaluation): the overhead, with its parts
    metrics["wall_seconds"] = round(wall, 2)
    metrics["overhead_seconds"] = round(wall - run_seconds, 2)
    metrics["overhead_fraction"] = round((wall - run_seconds) / max(wall, 1e-9), 4)
    metrics["overhead_breakdown"] = {k: round(v, 2) for k, v in clock.seconds.items()}
    metrics["history"] = history
    if out is not None:
        (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    return TrainResult(model=model, model_fine=model_fine, config=cfg, bounds=bounds, metrics=metrics, history=history,
                       snapshots=snapshots, test_renders=test_renders)


# ------------------------------------------------------------------------------------ novel views


def circular_path(c2w: np.ndarray, center, n_frames: int = 40, elevation_deg: float | None = None,
                  radius: float | None = None) -> np.ndarray:
    """Cameras on a circle around ``center``, looking at it (OpenCV axes, camera-to-world).

    The world "up" is the mean of the training cameras' up vectors (their -y axes); radius and
    elevation default to the training cameras' mean distance and mean elevation.

    Returns:
        ``(n_frames, 4, 4)`` camera-to-world matrices.
    """
    from course_lib.data.synthetic import look_at

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
        R_cw, t_cw = look_at(C, center, up=up)
        M = np.eye(4)
        M[:3, :3] = R_cw.T
        M[:3, 3] = C
        out.append(M)
    return np.stack(out)


def render_path(model, model_fine, cfg: TrainConfig, bounds: dict, H: int, W: int, K, c2w_path: np.ndarray,
                progress: bool = False) -> np.ndarray:
    """Render views along a path; returns ``(n, H, W, 3)`` uint8 frames."""
    from tqdm.auto import tqdm

    frames = []
    for M in tqdm(c2w_path, disable=not progress, desc=f"render on {next(model.parameters()).device.type}"):
        frames.append(_to_uint8(render_view(model, model_fine, cfg, bounds, H, W, K, M)["rgb"].cpu().numpy()))
    return np.stack(frames)


def save_gif(path, frames: np.ndarray, fps: float = 12.0) -> Path:
    """Write ``(n, H, W, 3)`` uint8 frames as a looping GIF."""
    import imageio.v2 as imageio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.mimsave(path, list(frames), duration=1.0 / fps, loop=0)
    return path

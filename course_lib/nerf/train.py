"""Training a NeRF (notebook 08): random rays, volume rendering, MSE, Adam; a short loop over small parts.

One step::

    rays  <- a batch of random pixels across ALL training images (seeded torch.Generator)
    out   <- render_rays(model, rays_o, rays_d, near, far, ...)        (stratified jitter on)
    loss  <- mean((out.rgb_map - pixel colours)^2)                     (+ coarse loss, + TV prior)
    Adam step;  PSNR = -10 log10(MSE)

:func:`train` is the loop (as nerfstudio's ``Trainer.train``); around it, one part per job:

* :class:`~course_lib.nerf.scene.TrainingRays` -- the training pixels (uint8) and their rays;
  :class:`~course_lib.nerf.scene.SceneBounds` -- the scene's box and ray bounds (typed, replaced
  only by the model's schedule);
* :class:`TrainState` -- model, optimizer, step, clocks, history, RNG: what a checkpoint holds
  (:mod:`course_lib.nerf.checkpoint`);
* the model's own callbacks (``model.training_callbacks(cfg)``; the grid's schedule lives in
  :mod:`course_lib.nerf.schedule`), run before or after a step when due;
* :class:`RunClock` -- the budget: ``minutes`` covers the whole run (loading included when the
  caller passes ``started_at``), so training stops early enough for the final evaluation; time
  outside training by kind (``overhead_breakdown``), snapshots/evaluations/checkpoints that come
  due wait while they would take it (loading included) over ``overhead_budget`` of the training time;
* :class:`RunOutputs` -- snapshots (PNG), checkpoints, evaluations during the run and at the end
  (forward-only renders, :mod:`course_lib.nerf.inference`), ``metrics.json``.

With a time budget the final evaluation renders the test views that fit in ``final_eval_share``
of it -- all of them when they fit, else a fixed, evenly spread subset, and ``metrics.json`` says
which (``test_views``, ``n_test_views``); ``eval_all`` renders all of them whatever the time.
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
from course_lib.nerf.checkpoint import CHECKPOINT, build_model, load_checkpoint, save_checkpoint
from course_lib.nerf.device import device_name, pick_device
from course_lib.nerf.grid import GridField
from course_lib.nerf.inference import (RenderSettings, circular_path, evaluate, preview_camera, render_path,
                                       render_view, save_gif, save_png, shrink, spread_views)
from course_lib.nerf.optim import GridAdam
from course_lib.nerf.presets import TrainConfig, preset, resolve
from course_lib.nerf.render import LAST_DELTA, render_rays
from course_lib.nerf.scene import SceneBounds, TrainingRays, scene_bounds
from course_lib.nerf.schedule import surface_box
from course_lib.threads import set_torch_threads
from course_lib.validate import KitInputError

__all__ = [
    "TrainResult", "TrainState", "TrainingInterrupted", "RunClock", "RunOutputs", "train", "scene_bounds",
    "SceneBounds", "surface_box", "build_model", "evaluate", "render_view", "load_checkpoint", "render_path",
    "circular_path", "save_gif", "CHECKPOINT",
]


@dataclass
class TrainResult:
    """What :func:`train` returns.

    Attributes:
        model, model_fine: the trained field(s) (``model_fine`` None without a fine network).
        config: the :class:`TrainConfig` used (automatic values filled in, :func:`~course_lib.nerf.presets.resolve`).
        bounds: the scene's :class:`~course_lib.nerf.scene.SceneBounds`.
        metrics: the dict written to ``metrics.json``.
        history: ``iterations, loss, psnr, seconds`` per step and ``test_iterations, test_psnr``.
        snapshots: list of ``(step, (H, W, 3) float image)`` of the held-out view.
        test_renders: ``(N, H, W, 3)`` renders of the evaluated test views (None without test data).
    """

    model: torch.nn.Module
    model_fine: torch.nn.Module | None
    config: TrainConfig
    bounds: SceneBounds
    metrics: dict
    history: dict
    snapshots: list = field(default_factory=list)
    test_renders: np.ndarray | None = None


class TrainingInterrupted(KeyboardInterrupt):
    """Ctrl-C during :func:`train`: raised after the checkpoint was written (a ``KeyboardInterrupt``).

    Attributes:
        step: the last completed step. checkpoint: the checkpoint's path (None without ``out_dir``).
    """

    def __init__(self, step: int, checkpoint: Path | None):
        super().__init__(f"interrupted at step {step}")
        self.step, self.checkpoint = step, checkpoint


@dataclass
class TrainState:
    """Everything that changes during training (and goes into a checkpoint).

    Attributes:
        model, model_fine, optimizer, config, bounds, rays, generator, device: the run's objects.
        step: steps done. train_seconds: time in steps, wall_seconds: the run's time (both over resumes).
        progress: fraction of the run done, in [0, 1]. history: per-step loss and PSNR, test PSNRs.
        callbacks: the model's training callbacks (:class:`~course_lib.nerf.schedule.TrainingCallback`).
    """

    model: torch.nn.Module
    model_fine: torch.nn.Module | None
    optimizer: torch.optim.Optimizer
    config: TrainConfig
    bounds: SceneBounds
    rays: TrainingRays
    generator: torch.Generator
    device: torch.device
    step: int = 0
    train_seconds: float = 0.0
    wall_seconds: float = 0.0
    progress: float = 0.0
    history: dict = field(default_factory=lambda: {k: [] for k in ("iterations", "loss", "psnr", "seconds",
                                                                  "test_iterations", "test_psnr")})
    callbacks: list = field(default_factory=list)

    def new_optimizer(self) -> None:
        self.optimizer = make_optimizer(self.config, self.model, self.model_fine)

    def run_callbacks(self, where: str) -> None:
        for cb in self.callbacks:
            if cb.where == where and cb.due(self) and cb.run(self):
                self.new_optimizer()


def make_optimizer(cfg: TrainConfig, model, model_fine) -> torch.optim.Optimizer:
    """Adam: grid values at ``grid_lr``, network weights at ``lr``.

    A grid model gets :class:`~course_lib.nerf.optim.GridAdam`: dense Adam over the grids' voxel
    rows, fused (one pass over the memory instead of several: about a quarter of the time on a
    CPU), or with ``cfg.grid_sparse_adam`` only the voxels that the step read (the grid records its
    reads, :meth:`GridField.track_reads`). The grids' gradients are written in place
    (:meth:`GridField.write_grads_in_place`; :func:`train_step` zeroes them instead of freeing them).
    The MLP gets ``torch.optim.Adam``, fused on a CPU or a CUDA GPU.
    """
    device = next(model.parameters()).device
    fused = True if device.type in ("cpu", "cuda") else None
    if isinstance(model, GridField):
        sparse = bool(cfg.grid_sparse_adam)
        model.track_reads(sparse)
        model.write_grads_in_place()
        groups = [{"params": [model.density_grid, model.feature_grid], "lr": cfg.grid_lr, "kind": "grid", "sparse": sparse}]
        rest = [p for n, p in model.named_parameters() if not n.endswith("_grid")]
        if rest:
            groups.append({"params": rest, "lr": cfg.lr, "kind": "mlp"})
        return GridAdam(groups, betas=(0.9, 0.99))
    params = list(model.parameters()) + (list(model_fine.parameters()) if model_fine is not None else [])
    return torch.optim.Adam([{"params": params, "lr": cfg.lr, "kind": "mlp"}], betas=(0.9, 0.999), fused=fused)


def set_learning_rate(opt: torch.optim.Optimizer, cfg: TrainConfig, progress: float) -> None:
    """Exponential decay from the initial to the final learning rate over the run."""
    for g in opt.param_groups:
        lo, hi = (cfg.grid_lr_final, cfg.grid_lr) if g.get("kind") == "grid" else (cfg.lr_final, cfg.lr)
        g["lr"] = hi * (lo / hi) ** min(max(progress, 0.0), 1.0)


def ray_bounds_of(model, cfg: TrainConfig, bounds: SceneBounds):
    """Per-ray ``(near, far)``: the grid's box (``cfg.box_bounds``), or the scene's near and far."""
    near, far = bounds.near, bounds.far
    if isinstance(model, GridField) and cfg.box_bounds:
        return lambda o, d: model.ray_bounds(o, d, near=near)
    return lambda o, d: (near, far)


def train_step(state: TrainState) -> tuple[torch.Tensor, torch.Tensor]:
    """One optimizer step on a random batch of rays; returns ``(loss, mse)`` (0-d tensors, detached)."""
    cfg, model = state.config, state.model
    o, d, rgb_true = state.rays.sample(cfg.batch_rays, state.generator)
    near, far = ray_bounds_of(model, cfg, state.bounds)(o, d)
    out = render_rays(model, o, d, near, far, cfg.n_samples, cfg.n_importance, state.model_fine, perturb=cfg.perturb,
                      white_background=cfg.white_background, generator=state.generator,
                      color_threshold=cfg.color_threshold, last_delta=None if isinstance(model, GridField) else LAST_DELTA)
    mse = F.mse_loss(out["rgb_map"], rgb_true)
    loss = mse + (F.mse_loss(out["rgb_map_coarse"], rgb_true) if "rgb_map_coarse" in out else 0.0)
    state.optimizer.zero_grad(set_to_none=not isinstance(model, GridField))  # a grid's gradient is kept, zeroed
    if loss.requires_grad:  # else no sample of the batch was in an occupied voxel: nothing to learn from it
        loss.backward()
    sparse = any(g.get("sparse") for g in state.optimizer.param_groups)
    reads = model.take_reads() if sparse else {}  # {grid: the voxels this step read}
    if isinstance(model, GridField) and cfg.tv_weight > 0:  # + tv_weight * TV(density), its gradient written out
        voxels = reads.get(model.density_grid, torch.zeros(0, dtype=torch.long, device=o.device)) if sparse else None
        loss = loss.detach() + cfg.tv_weight * model.add_total_variation_grad(cfg.tv_weight, voxels=voxels)
    state.optimizer.step(**({"voxels": reads} if sparse else {}))
    return loss.detach(), mse.detach()


class RunClock:
    """The run's time: the budget (``minutes``: the whole run) and the time outside training, by kind.

    Args:
        cfg: the config (``minutes``, ``iters``, ``overhead_budget``, ``final_eval_share``).
        started_at: ``time.perf_counter()`` when the run began (before loading the data; default: now).
        before: wall seconds of earlier runs that this one resumes.
    """

    def __init__(self, cfg: TrainConfig, started_at: float | None = None, before: float = 0.0):
        self.cfg, self.started = cfg, time.perf_counter() if started_at is None else started_at
        self.budget_s = 60.0 * cfg.minutes if cfg.minutes else None
        self.before, self.train_seconds, self.reserve = before, 0.0, 0.0
        self.seconds: dict[str, float] = {"setup": 0.0}
        self.last: dict[str, float] = {}  # the duration of each kind's last run
        self.pending: set[str] = set()

    def setup_done(self, before: float = 0.0) -> None:
        """Training starts: the time so far was setup; ``before``: wall seconds of earlier runs (resumed)."""
        self.before, self.seconds["setup"] = before, time.perf_counter() - self.started

    def wall(self) -> float:
        """Seconds since this call began."""
        return time.perf_counter() - self.started

    def spent(self) -> float:
        """Seconds of the budget spent (earlier runs included; the caller's callback is not ours)."""
        return self.before + self.wall() - self.seconds.get("callback", 0.0)

    def progress(self, step: int) -> float:
        """Fraction of the run done: of the steps, or of the time left for training (whichever is further)."""
        p = step / max(self.cfg.iters, 1)
        if self.budget_s:
            p = max(p, self.spent() / (self.budget_s * (1.0 - self.cfg.final_eval_share)))
        return min(p, 1.0)

    def time_up(self) -> bool:
        """True when the time left is what the end of the run needs (``reserve`` seconds)."""
        return self.budget_s is not None and self.spent() + self.reserve >= self.budget_s

    def allowed(self, cost: float = 0.0) -> bool:
        """May a due snapshot/evaluation/checkpoint that takes about ``cost`` seconds run now?

        Yes while the time outside training (loading included, the caller's callback not) plus
        ``cost`` stays within ``overhead_budget`` x the training time so far.
        """
        outside = sum(v for k, v in self.seconds.items() if k != "callback")
        return self.cfg.overhead_budget <= 0 or outside + cost <= self.cfg.overhead_budget * self.train_seconds

    def timed(self, kind: str, fn, *args):
        t = time.perf_counter()
        try:
            return fn(*args)
        finally:
            self.last[kind] = time.perf_counter() - t
            self.seconds[kind] = self.seconds.get(kind, 0.0) + self.last[kind]


class RunOutputs:
    """Snapshots, evaluations, checkpoints and the final evaluation of a run (all forward-only renders).

    Args:
        out: output folder (None: write nothing). state: the run. clock: its :class:`RunClock`.
        test_data: held-out views (or None). snap_data, snap_view: the view the snapshots show.
        camera: the training camera (stored in checkpoints for ``nerf render``).
    """

    def __init__(self, out: Path | None, state: TrainState, clock: RunClock, test_data, snap_data, snap_view: int,
                 camera: dict):
        self.out, self.clock, self.test, self.camera = out, clock, test_data, camera
        self.snap_data, self.snap_view = snap_data, min(snap_view, len(snap_data) - 1)
        self.preview = preview_camera(snap_data.H, snap_data.W, snap_data.K, clock.cfg.snapshot_max_side)  # (H, W, K)
        self.snapshots: list = []
        self.test_renders: np.ndarray | None = None
        self.render_seconds_per_ray: float | None = None
        self.ckpt = out / CHECKPOINT if out is not None else None
        self.checkpoint_at = clock.spent()  # when the last checkpoint was written (the run's start: none yet)

    def _measure(self, n_rays: int, seconds: float) -> None:
        self.render_seconds_per_ray = seconds / max(n_rays, 1)

    def snapshot(self, state: TrainState) -> None:
        """Render the held-out view at preview size (``snapshot_max_side``)."""
        t = time.perf_counter()
        H, W, K = self.preview
        img = render_view(state.model, state.model_fine, state.config, state.bounds, H, W, K,
                          self.snap_data.c2w[self.snap_view])["rgb"].cpu().numpy()
        self._measure(H * W, time.perf_counter() - t)
        self.add_snapshot(state.step, img)

    def add_snapshot(self, step: int, img: np.ndarray) -> None:
        self.snapshots.append((step, img))
        if self.out is not None:
            save_png(self.out / "snapshots" / f"step_{step:06d}.png", img)

    def test_eval(self, state: TrainState) -> None:
        views = list(range(min(state.config.n_eval_views, len(self.test))))
        state.history["test_iterations"].append(state.step)
        state.history["test_psnr"].append(evaluate(state.model, state.model_fine, state.config, state.bounds,
                                                   self.test, views, return_renders=False)[0])

    def checkpoint(self, state: TrainState) -> None:
        if self.ckpt is not None:
            state.wall_seconds = self.checkpoint_at = self.clock.spent()
            save_checkpoint(self.ckpt, state, self.camera)

    def periodic(self, state: TrainState, rays_per_second: float) -> None:
        """Run the snapshots, evaluations and checkpoints that are due and fit in the overhead budget.

        ``rays_per_second``: the training speed so far (the guess of a render's speed before one was measured).
        """
        cfg = state.config
        for kind, every, fn in (("snapshots", cfg.snapshot_every, self.snapshot),
                                ("evaluations", cfg.eval_every if self.test is not None else 0, self.test_eval),
                                ("checkpoints", cfg.checkpoint_every, self.checkpoint)):
            if every and state.step % every == 0 and (
                    kind != "checkpoints" or self.clock.spent() - self.checkpoint_at >= cfg.checkpoint_seconds):
                self.clock.pending.add(kind)
            if kind in self.clock.pending and self.clock.allowed(self.predicted(kind, rays_per_second)):
                self.clock.pending.discard(kind)
                self.clock.timed(kind, fn, state)

    def predicted(self, kind: str, rays_per_second: float) -> float:
        """Seconds a snapshot, evaluation or checkpoint will take: renders from their rays, checkpoints as the last one."""
        if kind == "checkpoints":
            return self.clock.last.get(kind, 0.0)
        if kind == "snapshots":
            H, W, _ = self.preview
            return H * W * self.seconds_per_ray(rays_per_second)
        n = min(self.clock.cfg.n_eval_views, len(self.test))
        return n * self.test.H * self.test.W * self.seconds_per_ray(rays_per_second)

    def final_views(self, rays_per_second: float) -> list[int]:
        """The test views of the final evaluation: all, or (a time budget) those that fit in its share."""
        n = len(self.test) if self.test is not None else 0
        cfg = self.clock.cfg
        if n == 0 or cfg.eval_all or not self.clock.budget_s:
            return list(range(n))
        per_view = self.test.H * self.test.W * self.seconds_per_ray(rays_per_second)
        return spread_views(n, int(cfg.final_eval_share * self.clock.budget_s / max(per_view, 1e-9)))

    def seconds_per_ray(self, train_rays_per_second: float) -> float:
        """Measured forward-render time per ray, else a guess: three times the training rate."""
        return self.render_seconds_per_ray or 1.0 / max(3.0 * train_rays_per_second, 1.0)

    def final_seconds(self, rays_per_second: float) -> float:
        """Predicted time of the run's end: the final checkpoint and evaluation (or a snapshot without test views)."""
        spr = self.seconds_per_ray(rays_per_second)
        views = self.final_views(rays_per_second)
        H, W, _ = self.preview
        ckpt = self.clock.last.get("checkpoints", 0.0) if self.ckpt is not None else 0.0
        return ckpt + (spr * self.test.H * self.test.W * len(views) if views else spr * H * W)

    def finish(self, state: TrainState) -> dict:
        """Final checkpoint, evaluation (with PNGs of the renders) and snapshot; returns test metrics."""
        self.clock.timed("checkpoints", self.checkpoint, state)
        rays_per_second = state.config.batch_rays * state.step / max(state.train_seconds, 1e-9)
        views = self.final_views(rays_per_second)
        res: dict = {"test_psnr": None}
        if views:
            t = time.perf_counter()
            mean, per_view, renders = evaluate(state.model, state.model_fine, state.config, state.bounds, self.test, views)
            self._measure(len(views) * self.test.H * self.test.W, time.perf_counter() - t)
            self.test_renders = np.stack(renders)
            res.update(test_psnr=round(mean, 3), test_psnr_per_view=[round(v, 3) for v in per_view],
                       test_views=views, n_test_views=len(views), n_test_views_available=len(self.test),
                       eval_seconds=round(time.perf_counter() - t, 2),
                       render_rays_per_second=round(1.0 / self.render_seconds_per_ray, 1))
            state.history["test_iterations"].append(state.step)
            state.history["test_psnr"].append(mean)
            fresh = not self.snapshots or self.snapshots[-1][0] != state.step
            if fresh and self.snap_data is self.test and self.snap_view in views and state.config.snapshot_every:
                H, W, _ = self.preview  # the final render of the snapshots' view, at their size
                self.add_snapshot(state.step, shrink(renders[views.index(self.snap_view)], H, W))
            if self.out is not None:
                for i, img in zip(views, renders):
                    save_png(self.out / "test" / f"{self.test.names[i]}.png", img)
            self.clock.seconds["final_evaluation"] = time.perf_counter() - t
        if state.config.snapshot_every and (not self.snapshots or self.snapshots[-1][0] != state.step):
            self.clock.timed("snapshots", self.snapshot, state)
        return res


class _Bar:
    """The progress bar: seconds of the budget spent (a time budget), else steps of steps."""

    def __init__(self, cfg: TrainConfig, state: TrainState, clock: RunClock, enabled: bool):
        from tqdm.auto import tqdm

        self.by_time = bool(cfg.minutes)
        desc = f"nerf {cfg.preset} on {state.device.type}"
        if self.by_time:
            total = round(clock.budget_s, 1)
            self.bar = tqdm(total=total, initial=round(min(clock.spent(), total), 1), disable=not enabled, desc=desc,
                            mininterval=1.0, unit="s", bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} s "
                            "of the run [{elapsed} wall{postfix}]")
        else:
            self.bar = tqdm(total=cfg.iters, initial=state.step, disable=not enabled, desc=desc, mininterval=1.0,
                            unit="step")
        self.shown = self.bar.n

    def update(self, state: TrainState, clock: RunClock, show: bool) -> None:
        now = min(clock.spent(), self.bar.total) if self.by_time else state.step
        if show and state.history["loss"]:
            self.bar.set_postfix({"step": state.step, "loss": f"{state.history['loss'][-1]:.4f}",
                                  "psnr": f"{state.history['psnr'][-1]:.2f}"}, refresh=False)
        self.bar.update(now - self.shown)
        self.shown = now

    def close(self) -> None:
        self.bar.close()


def _start(train_data: BlenderData, cfg: TrainConfig, device: torch.device, ckpt: Path | None,
           resume: bool) -> tuple[TrainState, dict | None]:
    """A new :class:`TrainState` (model from the seed), or the one in ``ckpt``; and what was resumed."""
    rays = TrainingRays(train_data, device)
    gen = torch.Generator(device=device).manual_seed(cfg.seed)
    if resume and ckpt is not None and ckpt.exists():
        ck = load_checkpoint(ckpt, device)
        if ck["cfg"].model != cfg.model:
            raise KitInputError(f"{ckpt} holds a {ck['cfg'].model!r} model but the config asks for {cfg.model!r}: "
                                "use another --out folder or delete the checkpoint")
        state = TrainState(ck["model"], ck["model_fine"], None, cfg, ck["bounds"], rays, gen, device, step=ck["step"],
                           train_seconds=ck["train_seconds"], wall_seconds=ck["wall_seconds"], history=ck["history"])
        state.new_optimizer()
        state.optimizer.load_state_dict(ck["optimizer"])
        written_on = torch.device(ck["device"]).type if ck.get("device") else "cpu"
        if written_on == device.type:
            gen.set_state(ck["generator_state"])
        else:  # another device's generator state does not fit: a new, reproducible stream
            gen.manual_seed(cfg.seed + 1_000_003 * state.step)
        torch.set_rng_state(ck["torch_rng_state"])
        resumed = {"step": state.step, "train_seconds": round(state.train_seconds, 2), "device": ck.get("device")}
    else:
        bounds = scene_bounds(train_data.c2w, train_data.K, train_data.W).with_rays(cfg.near, cfg.far)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(cfg.seed)
            model, model_fine = build_model(cfg, bounds)
        model.to(device)
        if model_fine is not None:
            model_fine.to(device)
        state = TrainState(model, model_fine, None, cfg, bounds, rays, gen, device)
        state.new_optimizer()
        resumed = None
    callbacks = getattr(state.model, "training_callbacks", None)
    state.callbacks = callbacks(cfg) if callbacks is not None else []
    return state, resumed


def _record(state: TrainState, pending: list) -> None:
    """Move the pending ``(step, loss, mse)`` tensors of the last steps into the history (one sync)."""
    if pending:
        vals = torch.stack([torch.stack([lo, ms]) for _, lo, ms in pending]).cpu().tolist()
        for (st, _, _), (lo, ms) in zip(pending, vals):
            state.history["iterations"].append(st)
            state.history["loss"].append(float(lo))
            state.history["psnr"].append(float("inf") if ms <= 0 else -10.0 * math.log10(ms))
            state.history["seconds"].append(round(state.train_seconds, 3))
        pending.clear()


def _metrics(state: TrainState, clock: RunClock, train_data: BlenderData, stopped_by: str, steps: int,
             resumed: dict | None, test: dict) -> dict:
    cfg, model, fine = state.config, state.model, state.model_fine
    wall = clock.wall()
    m = {
        "preset": cfg.preset, "iterations": state.step, "train_seconds": round(state.train_seconds, 2),
        "stopped_by": stopped_by, "final_train_psnr": float(np.mean(state.history["psnr"][-50:])) if steps else None,
        "rays_per_second": round(steps * cfg.batch_rays / max(clock.train_seconds, 1e-9), 1),
        "samples_per_second": round(steps * cfg.batch_rays * (cfg.n_samples + cfg.n_importance)
                                    / max(clock.train_seconds, 1e-9), 1) if steps else None,
        "n_parameters": int(sum(p.numel() for p in model.parameters())
                            + (sum(p.numel() for p in fine.parameters()) if fine is not None else 0)),
        "n_train_views": len(train_data), "image_size": [train_data.W, train_data.H], "bounds": state.bounds.to_dict(),
        "device": str(state.device), "device_name": device_name(state.device),
        "render_chunk": RenderSettings.of(cfg, state.bounds, model).chunk_for(model), "resumed_from": resumed,
        "threads": torch.get_num_threads(), "torch": torch.__version__, "config": cfg.to_dict(),
        "data": str(train_data.folder) if train_data.folder is not None else None, **test,
    }
    if state.device.type == "cuda":
        m["peak_gpu_memory_mb"] = round(torch.cuda.max_memory_allocated(state.device) / 2**20, 1)
    m["peak_memory_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)
    # wall time of this call = training steps + everything else (setup, snapshots, evaluations, checkpoints,
    # the caller's callback, the final evaluation): the overhead, with its parts
    m.update(wall_seconds=round(wall, 2), overhead_seconds=round(wall - clock.train_seconds, 2),
             overhead_fraction=round((wall - clock.train_seconds) / max(wall, 1e-9), 4),
             overhead_breakdown={k: round(v, 2) for k, v in clock.seconds.items()}, history=state.history)
    return m


def _info(state: TrainState, clock: RunClock) -> dict:
    """What the caller's callback sees after a step."""
    return {"loss": state.history["loss"][-1], "psnr": state.history["psnr"][-1], "seconds": state.train_seconds,
            "wall_seconds": clock.spent(), "model": state.model, "model_fine": state.model_fine,
            "config": state.config, "bounds": state.bounds}


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    elif device.type == "mps":
        torch.mps.synchronize()


def train(train_data: BlenderData, test_data: BlenderData | None = None, config: TrainConfig | str = "fast",
          out_dir=None, resume: bool = True, progress: bool = True, device="auto", callback=None,
          snapshot_view: int = 0, started_at: float | None = None) -> TrainResult:
    """Train a NeRF (or the grid field of the "fast" preset) on one scene.

    Args:
        train_data: the training views (:func:`course_lib.data.blender.load_blender`, split "train").
        test_data: held-out views: snapshots show ``test_data[snapshot_view]``; the final test PSNR
            is the mean over the evaluated ones (None: snapshots of a training view, no test PSNR).
        config: a :class:`TrainConfig` or a preset name (``"paper"``, ``"fast"``).
        out_dir: folder for ``metrics.json``, ``snapshots/step_XXXXXX.png``, ``test/<name>.png``
            and ``checkpoint.pt`` (None: write nothing, e.g. in a notebook).
        resume: continue from ``out_dir/checkpoint.pt`` if there is one (same step, optimizer,
            RNG states; the time already spent counts against ``minutes``). A checkpoint resumes
            on any device; the ray sampler's random stream continues exactly only on the device
            type that wrote it (elsewhere it is reseeded from the seed and the step).
        progress: show a tqdm.auto progress bar (seconds of the budget, else steps; loss, PSNR).
        device: ``"auto"`` (CUDA, then MPS, then the CPU), ``"cpu"``, ``"cuda"``, ``"mps"`` or a
            torch.device (:func:`course_lib.nerf.device.pick_device`).
        callback: optional ``callback(step, info: dict) -> bool``, called after each step with
            ``loss, psnr, seconds`` (training time so far), ``wall_seconds`` (of the budget),
            ``model, model_fine, config, bounds``; return True to stop (a checkpoint is written).
            Its own time is not counted against the budget.
        snapshot_view: index of the held-out view in the snapshots.
        started_at: ``time.perf_counter()`` at the start of the run (before loading the data), so
            that ``minutes`` covers the loading too (default: when ``train`` is called).

    Returns:
        :class:`TrainResult` (model, metrics, history, snapshots, test renders).

    Raises:
        TrainingInterrupted: Ctrl-C (a ``KeyboardInterrupt``), after the checkpoint was written.

    Introduced in ``notebooks/08_nerf_rendering_and_training.ipynb``.
    """
    if not isinstance(train_data, BlenderData) or len(train_data) == 0:
        raise KitInputError("train_data must be a non-empty BlenderData (course_lib.data.blender.load_blender)")
    cfg = resolve(preset(config) if isinstance(config, str) else config, train_data.H, train_data.W)
    device = pick_device(device)
    if device.type == "cpu":
        set_torch_threads(cfg.threads)
    out = Path(out_dir) if out_dir is not None else None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    clock = RunClock(cfg, started_at)
    state, resumed = _start(train_data, cfg, device, out / CHECKPOINT if out is not None else None, resume)
    clock.setup_done(before=state.wall_seconds)  # a resumed run's earlier time counts against the budget
    camera = {"H": train_data.H, "W": train_data.W, "K": np.asarray(train_data.K).tolist(),
              "c2w": np.asarray(train_data.c2w).tolist()}
    has_test = test_data is not None and len(test_data) > 0
    outputs = RunOutputs(out, state, clock, test_data if has_test else None, test_data if has_test else train_data,
                         snapshot_view, camera)
    bar = _Bar(cfg, state, clock, progress)
    if cfg.snapshot_every and state.step == 0 and not cfg.minutes:  # (untrained: the slowest render of all)
        clock.timed("snapshots", outputs.snapshot, state)
    pending, steps, stopped_by = [], 0, "iterations"
    sync_every = 1 if device.type == "cpu" else 25  # on a GPU the losses come to the host every 25 steps
    try:
        while state.step < cfg.iters:
            if steps:  # what the end of the run will need, from the speeds measured so far
                clock.reserve = outputs.final_seconds(cfg.batch_rays * steps / clock.train_seconds)
            if clock.time_up():
                stopped_by = "time"
                break
            t0 = time.perf_counter()
            state.progress = clock.progress(state.step)
            state.run_callbacks("before")
            set_learning_rate(state.optimizer, cfg, state.progress)
            loss, mse = train_step(state)
            state.step += 1
            steps += 1
            state.run_callbacks("after")
            pending.append((state.step, loss, mse))
            synced = state.step % sync_every == 0 or steps == 1 or callback is not None
            if synced:
                _sync(device)
            dt = time.perf_counter() - t0
            state.train_seconds += dt
            clock.train_seconds += dt
            if synced:
                _record(state, pending)
            bar.update(state, clock, synced and (state.step % 10 == 0 or steps == 1))
            outputs.periodic(state, cfg.batch_rays * steps / clock.train_seconds)
            if callback is not None and clock.timed("callback", callback, state.step, _info(state, clock)):
                stopped_by = "callback"
                break
    except KeyboardInterrupt:
        bar.close()
        _record(state, pending)
        outputs.checkpoint(state)
        raise TrainingInterrupted(state.step, outputs.ckpt) from None
    bar.close()
    _record(state, pending)
    test = outputs.finish(state)
    metrics = _metrics(state, clock, train_data, stopped_by, steps, resumed, test)
    if out is not None:
        (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    return TrainResult(model=state.model, model_fine=state.model_fine, config=cfg, bounds=state.bounds, metrics=metrics,
                       history=state.history, snapshots=outputs.snapshots,
                       test_renders=outputs.test_renders)

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
* :class:`TrainState` -- model, optimizer, step, clock, history, RNG: what a checkpoint holds
  (:mod:`course_lib.nerf.checkpoint`); its config is the run's one config, its clock the run's
  one clock;
* the model's own callbacks (``model.training_callbacks(cfg)``; the grid's schedule lives in
  :mod:`course_lib.nerf.schedule`), run before or after a step when due;
* the run around the loop (:mod:`course_lib.nerf.run`): :class:`~course_lib.nerf.run.RunClock`
  (``minutes`` covers the whole run, so training stops early enough for the final evaluation),
  :class:`~course_lib.nerf.run.RunOutputs` (snapshots, checkpoints, evaluations, the final
  evaluation on every test view that fits, ``metrics.json``) and the progress bar.
"""

from __future__ import annotations

import json
import math
import signal
import threading
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from course_lib.data.blender import BlenderData
from course_lib.nerf.checkpoint import CHECKPOINT, build_model, load_checkpoint
from course_lib.nerf.device import pick_device
from course_lib.nerf.grid import GridField
from course_lib.nerf.optim import GridAdam
from course_lib.nerf.presets import TrainConfig, preset, resolve
from course_lib.nerf.render import LAST_DELTA, render_rays
from course_lib.nerf.run import ProgressBar, RunClock, RunOutputs, run_metrics
from course_lib.nerf.scene import SceneBounds, TrainingRays, scene_bounds
from course_lib.threads import set_torch_threads
from course_lib.validate import KitInputError

__all__ = ["TrainResult", "TrainState", "TrainingInterrupted", "train", "train_step", "make_optimizer",
           "set_learning_rate", "ray_bounds_of"]


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
        model, model_fine, optimizer, config, bounds, rays, generator, device: the run's objects
            (``config`` is the run's config, resolved: every other part reads it from here).
        clock: the run's :class:`~course_lib.nerf.run.RunClock` (training seconds, the budget).
        step: steps done. progress: fraction of the run done, in [0, 1].
        rays_trained: rays of the steps of this call (the batch may change during a run, ``cfg.adapt_batch``).
        history: per-step loss and PSNR, test PSNRs.
        callbacks: the model's training callbacks (:class:`~course_lib.nerf.schedule.TrainingCallback`).
    """

    model: torch.nn.Module
    model_fine: torch.nn.Module | None
    optimizer: torch.optim.Optimizer | None
    config: TrainConfig
    bounds: SceneBounds
    rays: TrainingRays
    generator: torch.Generator
    device: torch.device
    clock: RunClock
    step: int = 0
    progress: float = 0.0
    rays_trained: int = 0
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


def start_state(train_data: BlenderData, cfg: TrainConfig, device: torch.device, clock: RunClock,
                ckpt: Path | None = None, resume: bool = True) -> tuple[TrainState, dict | None]:
    """A new :class:`TrainState` (the model from the seed), or the one in ``ckpt``; and what was resumed.

    Args:
        train_data: the training views. cfg: the run's resolved config. device: where it trains.
        clock: the run's clock (a resumed run's earlier seconds are added to it).
        ckpt: the checkpoint to resume from, if it exists and ``resume``.
    """
    rays = TrainingRays(train_data, device)
    gen = torch.Generator(device=device).manual_seed(cfg.seed)
    if resume and ckpt is not None and ckpt.exists():
        ck = load_checkpoint(ckpt, device)
        if ck["cfg"].model != cfg.model:
            raise KitInputError(f"{ckpt} holds a {ck['cfg'].model!r} model but the config asks for {cfg.model!r}: "
                                "use another --out folder or delete the checkpoint")
        clock.resume(ck["train_seconds"], ck["wall_seconds"])  # the earlier time counts against the budget
        state = TrainState(ck["model"], ck["model_fine"], None, cfg, ck["bounds"], rays, gen, device, clock,
                           step=ck["step"], history=ck["history"])
        state.new_optimizer()
        state.optimizer.load_state_dict(ck["optimizer"])
        written_on = torch.device(ck["device"]).type if ck.get("device") else "cpu"
        if written_on == device.type:
            gen.set_state(ck["generator_state"])
        else:  # another device's generator state does not fit: a new, reproducible stream
            gen.manual_seed(cfg.seed + 1_000_003 * state.step)
        torch.set_rng_state(ck["torch_rng_state"])
        resumed = {"step": state.step, "train_seconds": round(clock.train_seconds, 2), "device": ck.get("device")}
    else:
        bounds = scene_bounds(train_data.c2w, train_data.K, train_data.W).with_rays(cfg.near, cfg.far)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(cfg.seed)
            model, model_fine = build_model(cfg, bounds)
        model.to(device)
        if model_fine is not None:
            model_fine.to(device)
        state = TrainState(model, model_fine, None, cfg, bounds, rays, gen, device, clock)
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
            state.history["seconds"].append(round(state.clock.train_seconds, 3))
        pending.clear()


def _info(state: TrainState) -> dict:
    """What the caller's callback sees after a step."""
    return {"loss": state.history["loss"][-1], "psnr": state.history["psnr"][-1], "seconds": state.clock.train_seconds,
            "wall_seconds": state.clock.spent(), "model": state.model, "model_fine": state.model_fine,
            "config": state.config, "bounds": state.bounds}


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    elif device.type == "mps":
        torch.mps.synchronize()


class CtrlC:
    """Ctrl-C deferred to the top of a training step, so that a checkpoint is always consistent.

    A ``KeyboardInterrupt`` raised wherever SIGINT lands could stop a step half done: after the
    optimizer step but before ``state.step += 1``, or after it but before the history got the step
    (a checkpoint at step n whose history ended at n - 1: the resumed history skipped a step).
    While :meth:`deferred` is active the handler only sets :attr:`requested`; the loop stops at
    the next step boundary (:meth:`check`). A second Ctrl-C before then interrupts at once (a
    stuck step); that interrupt is not ``safe`` and :func:`train` writes no checkpoint for it.
    """

    def __init__(self):
        self.requested = False
        self.safe = False  # True when the KeyboardInterrupt came from check(): the state is whole

    def handle(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True

    def check(self) -> None:
        if self.requested:
            self.safe = True
            raise KeyboardInterrupt

    @contextmanager
    def deferred(self):
        """Install :meth:`handle` for SIGINT (only in the main thread, over Python's default handler)."""
        ours = (threading.current_thread() is threading.main_thread()
                and signal.getsignal(signal.SIGINT) is signal.default_int_handler)
        if ours:
            signal.signal(signal.SIGINT, self.handle)
        try:
            yield self
        finally:
            if ours:
                signal.signal(signal.SIGINT, signal.default_int_handler)


def _train_loop(state: TrainState, clock: RunClock, outputs: RunOutputs, bar: ProgressBar, callback, device: torch.device,
                pending: list, ctrl_c: CtrlC) -> tuple[str, int]:
    """The steps of :func:`train` until the iterations or the time run out or ``callback`` stops it.

    ``pending`` collects the ``(step, loss, mse)`` not yet recorded (they come to the host every
    25 steps on a GPU). A Ctrl-C stops it at the top of a step (``ctrl_c``, :class:`CtrlC`).
    Returns ``(what stopped it, steps taken)``.
    """
    cfg = state.config
    steps = 0
    sync_every = 1 if device.type == "cpu" else 25  # on a GPU the losses come to the host every 25 steps
    while state.step < cfg.iters:
        ctrl_c.check()  # between steps: model, optimizer, step and history agree
        if steps >= 2:  # what the end of the run will need, from the speeds measured so far (not the first step's)
            clock.reserve = outputs.end_seconds(state)
        if clock.time_up():
            return "time", steps
        with clock.training():
            state.progress = clock.progress(state.step)
            state.run_callbacks("before")
            set_learning_rate(state.optimizer, cfg, state.progress)
            loss, mse = train_step(state)
            state.rays_trained += state.config.batch_rays
            state.step += 1
            steps += 1
            state.run_callbacks("after")
            pending.append((state.step, loss, mse))
            synced = state.step % sync_every == 0 or steps == 1 or callback is not None
            if synced:
                _sync(device)
        if synced:
            _record(state, pending)
        bar.update(state, synced and (state.step % 10 == 0 or steps == 1))
        outputs.periodic(state)
        if callback is not None and clock.timed("callback", callback, state.step, _info(state)):
            return "callback", steps
    return "iterations", steps


def train(train_data: BlenderData, test_data: BlenderData | None = None, config: TrainConfig | str = "fast",
          out_dir=None, resume: bool = True, progress: bool = True, device="auto", callback=None,
          snapshot_view: int = 0, started_at: float | None = None) -> TrainResult:
    """Train a NeRF (or the grid field of the "fast" preset) on one scene.

    Args:
        train_data: the training views (:func:`course_lib.data.blender.load_blender`, split "train").
        test_data: held-out views: snapshots show ``test_data[snapshot_view]``; the final evaluation
            renders all of them that fit in its share of the budget (None: snapshots of a training
            view, no test PSNR).
        config: a :class:`~course_lib.nerf.presets.TrainConfig` or a preset name (``"paper"``,
            ``"fast"``); its defaults are the command line's (5 minutes, threads from the load).
        out_dir: folder for ``metrics.json``, ``snapshots/step_XXXXXX.png``, ``test/<name>.png``
            and ``checkpoint.pt`` (None: write nothing, e.g. in a notebook).
        resume: continue from ``out_dir/checkpoint.pt`` if there is one (same step, optimizer,
            RNG states; the time already spent counts against ``minutes``). A checkpoint resumes
            on any device; the ray sampler's random stream continues exactly only on the device
            type that wrote it (elsewhere it is reseeded from the seed and the step).
        progress: show a tqdm.auto progress bar (seconds of the budget, else steps; loss, PSNR).
        device: ``"auto"`` (CUDA, then MPS, then the CPU), ``"cpu"``, ``"cuda"``, ``"mps"`` or a
            torch.device (:func:`course_lib.nerf.device.pick_device`). On a CPU, ``train`` sets
            torch's threads (``config.threads``).
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
        TrainingInterrupted: Ctrl-C (a ``KeyboardInterrupt``) at the end of its step, checkpoint written (:class:`CtrlC`).

    Introduced in ``notebooks/08_nerf_rendering_and_training.ipynb``.
    """
    if not isinstance(train_data, BlenderData) or len(train_data) == 0:
        raise KitInputError("train_data must be a non-empty BlenderData (course_lib.data.blender.load_blender)")
    cfg = resolve(preset(config) if isinstance(config, str) else config, train_data.H, train_data.W)
    device = pick_device(device)
    if device.type == "cpu":
        set_torch_threads(cfg.threads)  # the one place that sets them
    out = Path(out_dir) if out_dir is not None else None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    clock = RunClock.of(cfg, started_at)
    state, resumed = start_state(train_data, cfg, device, clock, out / CHECKPOINT if out is not None else None, resume)
    clock.setup_done()
    camera = {"H": train_data.H, "W": train_data.W, "K": np.asarray(train_data.K).tolist(),
              "c2w": np.asarray(train_data.c2w).tolist()}
    has_test = test_data is not None and len(test_data) > 0
    outputs = RunOutputs(out, state, test_data if has_test else None, test_data if has_test else train_data,
                         snapshot_view, camera)
    bar = ProgressBar(state, progress)
    if cfg.snapshot_every and state.step == 0 and not cfg.minutes:  # (untrained: the slowest render of all)
        clock.timed("snapshots", outputs.snapshot, state)
    pending: list = []
    ctrl_c = CtrlC()
    try:
        with ctrl_c.deferred():
            stopped_by, steps = _train_loop(state, clock, outputs, bar, callback, device, pending, ctrl_c)
            ctrl_c.check()  # a Ctrl-C during the last step stops the run too
    except KeyboardInterrupt:
        bar.close()
        if not ctrl_c.safe:  # a second Ctrl-C inside a step: the state may be half updated, keep the last checkpoint
            raise
        _record(state, pending)
        outputs.checkpoint(state)
        raise TrainingInterrupted(state.step, outputs.ckpt) from None
    bar.close()
    _record(state, pending)
    final = outputs.finish(state)
    metrics = run_metrics(state, train_data, stopped_by, steps, resumed, final)
    if out is not None:
        (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    return TrainResult(model=state.model, model_fine=state.model_fine, config=cfg, bounds=state.bounds, metrics=metrics,
                       history=state.history, snapshots=outputs.snapshots, test_renders=outputs.test_renders)

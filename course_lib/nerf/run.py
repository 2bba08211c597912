"""Around the training loop: the run's clock, its outputs and its progress bar (notebook 08's ``train``).

:func:`course_lib.nerf.train.train` is the loop the notebook teaches; what a long run needs
besides it lives here, one owner per job:

* :class:`RunClock` -- the run's time: the budget (``minutes`` covers the whole run, loading
  included when the caller passes ``started_at``, and is a total over resumes), the seconds spent
  in training steps, the time outside training by kind (``seconds``), and whether a due
  snapshot/evaluation/checkpoint may run now (``overhead_budget``) or training must stop to leave
  the end of the run its time (``reserve``).
* :class:`RunOutputs` -- snapshots (PNG previews), checkpoints, evaluations during the run and the
  final evaluation (forward-only renders, :mod:`course_lib.nerf.inference`), and the metrics.
* :class:`ProgressBar` -- seconds of the budget (a time budget), else steps of steps.

The final evaluation renders every test view when they fit in ``final_eval_share`` of the budget
at the render speed *measured* on the first view; when they do not, at least
``final_eval_min_views`` evenly spread views, and the metrics call that figure "PSNR on k of n test
views" (``final_psnr``, ``final_psnr_label``); ``test_psnr`` is only ever the mean over all test
views (None otherwise). ``python -m course_lib nerf eval OUT DATA`` gives it for any checkpoint.
"""

from __future__ import annotations

import math
import resource
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

from course_lib.data.blender import BlenderData
from course_lib.nerf.checkpoint import CHECKPOINT, save_checkpoint
from course_lib.nerf.device import device_name
from course_lib.nerf.inference import RenderSettings, evaluate, preview_camera, render_view, save_png, shrink, spread_views

__all__ = ["RunClock", "RunOutputs", "ProgressBar", "psnr_label", "run_metrics", "END_MARGIN"]

#: the end of a run (final checkpoint and evaluation) is reserved this much more time than predicted: a
#: full-size render of the trained field runs a little slower than the previews it is predicted from
#: (the building at 800 px, 10 minutes, 8192-ray batches: 603 s of wall without a margin)
END_MARGIN = 1.15


class RunClock:
    """The run's time, in one place: the budget, the seconds of training and the time outside it.

    Args:
        minutes: the whole run's budget (None: no time limit).
        iters: the run's step limit (for :meth:`progress`).
        final_eval_share: the share of the budget left for the final evaluation (training's
            progress reaches 1 before it).
        overhead_budget: snapshots/evaluations/checkpoints wait while the time outside training
            would exceed this fraction of the training time (0: they never wait).
        started_at: ``time.perf_counter()`` when the run began (before loading the data; default: now).

    Attributes:
        train_seconds: seconds in training steps, over resumes. seconds: time outside training by
            kind (``setup``, ``snapshots``, ``checkpoints``, ``final_evaluation``, ``callback``, ...).
        reserve: seconds the end of the run needs (training stops when only that is left).
    """

    def __init__(self, minutes: float | None, iters: int, final_eval_share: float = 0.0, overhead_budget: float = 0.0,
                 started_at: float | None = None):
        self.started = time.perf_counter() if started_at is None else started_at
        self.budget_s = 60.0 * minutes if minutes else None
        self.iters, self.final_eval_share, self.overhead_budget = int(iters), float(final_eval_share), float(overhead_budget)
        self.before = 0.0  # wall seconds of the earlier runs this one resumes
        self.train_seconds = self.train_before = 0.0
        self.reserve = 0.0
        self.seconds: dict[str, float] = {"setup": 0.0}
        self.last: dict[str, float] = {}  # the duration of each kind's last run
        self.pending: set[str] = set()

    @classmethod
    def of(cls, cfg, started_at: float | None = None) -> "RunClock":
        """The clock of a run of :class:`~course_lib.nerf.presets.TrainConfig` ``cfg``."""
        return cls(cfg.minutes, cfg.iters, cfg.final_eval_share, cfg.overhead_budget, started_at)

    def resume(self, train_seconds: float, wall_seconds: float) -> None:
        """Continue a run that already spent ``train_seconds`` in training and ``wall_seconds`` of its budget."""
        self.train_seconds = self.train_before = float(train_seconds)
        self.before = float(wall_seconds)

    def setup_done(self) -> None:
        """Training starts: the time so far was setup (loading, building the model)."""
        self.seconds["setup"] = time.perf_counter() - self.started

    def wall(self) -> float:
        """Seconds since this call began."""
        return time.perf_counter() - self.started

    def spent(self) -> float:
        """Seconds of the budget spent (earlier runs included; the caller's callback is not ours)."""
        return self.before + self.wall() - self.seconds.get("callback", 0.0)

    def trained_now(self) -> float:
        """Seconds of training in this call (without the runs it resumes)."""
        return self.train_seconds - self.train_before

    @contextmanager
    def training(self):
        """Count the time of the block as training."""
        t = time.perf_counter()
        try:
            yield
        finally:
            self.train_seconds += time.perf_counter() - t

    def progress(self, step: int) -> float:
        """Fraction of the run done: of the steps, or of the time left for training (whichever is further)."""
        p = step / max(self.iters, 1)
        if self.budget_s:
            p = max(p, self.spent() / (self.budget_s * (1.0 - self.final_eval_share)))
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
        return self.overhead_budget <= 0 or outside + cost <= self.overhead_budget * self.trained_now()

    def timed(self, kind: str, fn, *args):
        """``fn(*args)``, its time counted as ``kind`` (outside training)."""
        t = time.perf_counter()
        try:
            return fn(*args)
        finally:
            self.last[kind] = time.perf_counter() - t
            self.seconds[kind] = self.seconds.get(kind, 0.0) + self.last[kind]


def psnr_label(k: int, n: int) -> str:
    """What a mean PSNR over ``k`` of ``n`` test views is called: the test PSNR only when ``k == n``."""
    return f"test PSNR on all {n} test views" if k == n else f"PSNR on {k} of {n} test views"


class RunOutputs:
    """Snapshots, evaluations, checkpoints and the final evaluation of a run (all forward-only renders).

    Args:
        out: output folder (None: write nothing). state: the run
            (:class:`~course_lib.nerf.train.TrainState`: its config and clock are read from it).
        test_data: held-out views (or None). snap_data, snap_view: the view the snapshots show.
        camera: the training camera (stored in checkpoints for ``nerf render``).
    """

    def __init__(self, out: Path | None, state, test_data: BlenderData | None, snap_data: BlenderData, snap_view: int,
                 camera: dict):
        self.out, self.test, self.camera = out, test_data, camera
        self.snap_data, self.snap_view = snap_data, min(snap_view, len(snap_data) - 1)
        self.preview = preview_camera(snap_data.H, snap_data.W, snap_data.K, state.config.snapshot_max_side)  # (H, W, K)
        self.snapshots: list = []
        self.test_renders: np.ndarray | None = None
        self.render_seconds_per_ray: float | None = None
        self.ckpt = out / CHECKPOINT if out is not None else None
        self.checkpoint_at = state.clock.spent()  # when the last checkpoint was written (the run's start: none yet)

    # ------------------------------------------------------------------ during the run
    def snapshot(self, state) -> None:
        """Render the held-out view at preview size (``snapshot_max_side``)."""
        t = time.perf_counter()
        H, W, K = self.preview
        img = render_view(state.model, state.model_fine, state.config, state.bounds, H, W, K,
                          self.snap_data.c2w[self.snap_view])["rgb"].cpu().numpy()
        self.render_seconds_per_ray = (time.perf_counter() - t) / (H * W)
        self.add_snapshot(state.step, img)

    def add_snapshot(self, step: int, img: np.ndarray) -> None:
        self.snapshots.append((step, img))
        if self.out is not None:
            save_png(self.out / "snapshots" / f"step_{step:06d}.png", img)

    def test_eval(self, state) -> None:
        views = list(range(min(state.config.n_eval_views, len(self.test))))
        state.history["test_iterations"].append(state.step)
        state.history["test_psnr"].append(evaluate(state.model, state.model_fine, state.config, state.bounds,
                                                   self.test, views, return_renders=False)[0])

    def checkpoint(self, state) -> None:
        if self.ckpt is not None:
            self.checkpoint_at = state.clock.spent()
            save_checkpoint(self.ckpt, state, self.camera)

    def periodic(self, state) -> None:
        """Run the snapshots, evaluations and checkpoints that are due and fit in the overhead budget."""
        cfg, clock = state.config, state.clock
        for kind, every, fn in (("snapshots", cfg.snapshot_every, self.snapshot),
                                ("evaluations", cfg.eval_every if self.test is not None else 0, self.test_eval),
                                ("checkpoints", cfg.checkpoint_every, self.checkpoint)):
            if every and state.step % every == 0 and (
                    kind != "checkpoints" or clock.spent() - self.checkpoint_at >= cfg.checkpoint_seconds):
                clock.pending.add(kind)
            if kind in clock.pending and clock.allowed(self.predicted(state, kind)):
                clock.pending.discard(kind)
                clock.timed(kind, fn, state)

    def seconds_per_ray(self, state) -> float:
        """The last measured forward-render time per ray, else a guess: three times the training rate.

        The training rate is that of the last (up to) 20 recorded steps: the first step of a run is
        many times slower than the others (allocations), and a guess from it alone ended short runs
        after one step (1.5 minutes at 200 px: a 106 s reserve for the evaluation).
        """
        if self.render_seconds_per_ray is not None:
            return self.render_seconds_per_ray
        it, sec = state.history["iterations"], state.history["seconds"]
        k = max(0, len(it) - 21)
        if len(it) >= 2 and sec[-1] > sec[k]:
            rays_per_second = state.config.batch_rays * (it[-1] - it[k]) / (sec[-1] - sec[k])
        else:
            rays_per_second = state.rays_trained / max(state.clock.trained_now(), 1e-9)
        return 1.0 / max(3.0 * rays_per_second, 1.0)

    def predicted(self, state, kind: str) -> float:
        """Seconds a snapshot, evaluation or checkpoint will take: renders from their rays, checkpoints as the last one."""
        if kind == "checkpoints":
            return state.clock.last.get(kind, 0.0)
        if kind == "snapshots":
            H, W, _ = self.preview
            return H * W * self.seconds_per_ray(state)
        n = min(state.config.n_eval_views, len(self.test))
        return n * self.test.H * self.test.W * self.seconds_per_ray(state)

    def end_seconds(self, state) -> float:
        """Predicted time of the run's end: the final checkpoint and evaluation (or a snapshot without test views).

        The evaluation is predicted from the last measured render speed: all test views, or as
        many as fit in its share of the budget but at least ``final_eval_min_views``
        (:meth:`final_evaluation` decides on the speed it measures then).
        """
        cfg = state.config
        ckpt = state.clock.last.get("checkpoints", 0.0) if self.ckpt is not None else 0.0
        if self.test is None:
            H, W, _ = self.preview
            return ckpt + H * W * self.seconds_per_ray(state)
        per_view = self.test.H * self.test.W * self.seconds_per_ray(state)
        evaluation = len(self.test) * per_view
        if state.clock.budget_s and not cfg.eval_all:
            fewest = min(len(self.test), cfg.final_eval_min_views) * per_view
            evaluation = max(min(evaluation, cfg.final_eval_share * state.clock.budget_s), fewest)
        return END_MARGIN * (ckpt + evaluation)

    # ------------------------------------------------------------------ the end
    def final_evaluation(self, state) -> dict:
        """Render the test views that fit (all of them whenever they do) and measure their PSNR.

        The first view is rendered and timed; if all ``n`` views fit in ``final_eval_share`` of
        the budget at that speed (or there is no time budget, or ``eval_all``), all are rendered,
        else at least ``final_eval_min_views`` evenly spread ones (:func:`spread_views`, which
        always holds the first).

        Returns:
            the metrics of the evaluation (``test_psnr`` only when all views were rendered).
        """
        cfg, clock, n = state.config, state.clock, len(self.test)
        t = time.perf_counter()
        first = evaluate(state.model, state.model_fine, cfg, state.bounds, self.test, [0])
        per_view = time.perf_counter() - t
        share = cfg.final_eval_share * clock.budget_s if clock.budget_s and not cfg.eval_all else math.inf
        fits = n if share == math.inf else int(share // max(per_view, 1e-9))
        views = list(range(n)) if fits >= n else spread_views(n, max(cfg.final_eval_min_views, fits))
        psnrs, renders = {0: first[1][0]}, {0: first[2][0]}
        rest = [v for v in views if v != 0]
        if rest:
            _, per, imgs = evaluate(state.model, state.model_fine, cfg, state.bounds, self.test, rest)
            psnrs.update(zip(rest, per))
            renders.update(zip(rest, imgs))
        seconds = time.perf_counter() - t
        mean = float(np.mean([psnrs[v] for v in views]))
        self.test_renders = np.stack([renders[v] for v in views])
        self.render_seconds_per_ray = seconds / (len(views) * self.test.H * self.test.W)
        state.history["test_iterations"].append(state.step)
        state.history["test_psnr"].append(mean)
        if self.out is not None:
            for v in views:
                save_png(self.out / "test" / f"{self.test.names[v]}.png", renders[v])
        if cfg.snapshot_every and self.snap_data is self.test and self.snap_view in views and (
                not self.snapshots or self.snapshots[-1][0] != state.step):
            H, W, _ = self.preview  # the final render of the snapshots' view, at their size
            self.add_snapshot(state.step, shrink(renders[self.snap_view], H, W))
        return {"test_psnr": round(mean, 3) if len(views) == n else None, "final_psnr": round(mean, 3),
                "final_psnr_label": psnr_label(len(views), n), "final_psnr_per_view": [round(psnrs[v], 3) for v in views],
                "test_views": views, "n_test_views": len(views), "n_test_views_available": n,
                "first_view_seconds": round(per_view, 3), "eval_seconds": round(seconds, 2),
                "render_rays_per_second": round(1.0 / self.render_seconds_per_ray, 1)}

    def finish(self, state) -> dict:
        """Final checkpoint, evaluation (with PNGs of the renders) and snapshot; returns the evaluation's metrics."""
        clock = state.clock
        clock.timed("checkpoints", self.checkpoint, state)
        res: dict = {"test_psnr": None, "final_psnr": None}
        if self.test is not None:
            res = clock.timed("final_evaluation", self.final_evaluation, state)
        if state.config.snapshot_every and (not self.snapshots or self.snapshots[-1][0] != state.step):
            clock.timed("snapshots", self.snapshot, state)
        return res


class ProgressBar:
    """The progress bar (``tqdm.auto``): seconds of the budget spent (a time budget), else steps of steps."""

    def __init__(self, state, enabled: bool):
        from tqdm.auto import tqdm

        cfg, clock = state.config, state.clock
        self.by_time = bool(clock.budget_s)
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

    def update(self, state, show: bool) -> None:
        """Move to the time spent (or the step); ``show``: also the last loss and PSNR."""
        now = min(state.clock.spent(), self.bar.total) if self.by_time else state.step
        if show and state.history["loss"]:
            self.bar.set_postfix({"step": state.step, "loss": f"{state.history['loss'][-1]:.4f}",
                                  "psnr": f"{state.history['psnr'][-1]:.2f}"}, refresh=False)
        self.bar.update(now - self.shown)
        self.shown = now

    def close(self) -> None:
        self.bar.close()


def peak_memory_mb() -> float:
    """The peak resident memory of this process's own address space, in MB.

    Linux's ``VmHWM`` (reset by ``exec``), not ``ru_maxrss``, which a process started by ``fork`` + ``exec``
    inherits from its parent: a benchmark that rendered a large scene before starting ``nerf train`` would
    charge the run with the benchmark's own peak. ``ru_maxrss`` where ``/proc`` is not there (macOS: bytes).
    """
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return round(int(line.split()[1]) / 1024.0, 1)
    except OSError:
        pass
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return round(rss / (2**20 if sys.platform == "darwin" else 1024.0), 1)


def run_metrics(state, train_data: BlenderData, stopped_by: str, steps: int, resumed: dict | None, final: dict) -> dict:
    """What ``metrics.json`` holds: the result, the speeds, the time outside training by kind, the config, the history.

    Args:
        state: the run. train_data: its training views. stopped_by: ``"iterations"``, ``"time"`` or
            ``"callback"``. steps: steps of this call. resumed: what was resumed (or None).
        final: :meth:`RunOutputs.finish`'s metrics.
    """
    cfg, clock, model, fine = state.config, state.clock, state.model, state.model_fine
    trained = max(clock.trained_now(), 1e-9)
    wall = clock.wall()
    m = {
        "preset": cfg.preset, "iterations": state.step, "train_seconds": round(clock.train_seconds, 2),
        "stopped_by": stopped_by, "final_train_psnr": float(np.mean(state.history["psnr"][-50:])) if steps else None,
        "rays_per_second": round(state.rays_trained / trained, 1),
        "samples_per_second": round(state.rays_trained * (cfg.n_samples + cfg.n_importance) / trained, 1) if steps else None,
        "n_parameters": int(sum(p.numel() for p in model.parameters())
                            + (sum(p.numel() for p in fine.parameters()) if fine is not None else 0)),
        "n_train_views": len(train_data), "image_size": [train_data.W, train_data.H], "bounds": state.bounds.to_dict(),
        "device": str(state.device), "device_name": device_name(state.device),
        "render_chunk": RenderSettings.of(cfg, state.bounds, model).chunk_for(model), "resumed_from": resumed,
        "threads": torch.get_num_threads(), "torch": torch.__version__, "config": cfg.to_dict(),
        "data": str(train_data.folder) if train_data.folder is not None else None, **final,
    }
    if state.device.type == "cuda":
        m["peak_gpu_memory_mb"] = round(torch.cuda.max_memory_allocated(state.device) / 2**20, 1)
    m["peak_memory_mb"] = peak_memory_mb()
    # wall time of this call = training steps + everything else (setup, snapshots, evaluations, checkpoints,
    # the caller's callback, the final evaluation): the overhead, with its parts
    outside = wall - clock.trained_now()
    m.update(wall_seconds=round(wall, 2), overhead_seconds=round(outside, 2),
             overhead_fraction=round(outside / max(wall, 1e-9), 4),
             overhead_breakdown={k: round(v, 2) for k, v in clock.seconds.items()}, history=state.history)
    return m

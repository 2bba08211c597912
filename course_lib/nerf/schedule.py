"""The grid field's training schedule, as callbacks the field hands to the trainer (notebook 09).

The training loop (:func:`course_lib.nerf.train.train`) knows nothing about voxel grids: it asks
the model for its callbacks (``model.training_callbacks(cfg)``, as nerfstudio's models do) and
runs each one before or after a step when it is due. A :class:`GridField` has four:

* **shrink the box** (``cfg.shrink_box_at``): after a short coarse stage, resample the grids into
  the box around the surfaces that the training rays hit (:func:`surface_box`) -- once they are
  found: until enough samples carry a clear share of a ray's weight the box is looked at again
  every :data:`SHRINK_RETRY` of the run, for at most :data:`SHRINK_PATIENCE` after ``shrink_box_at``;
* **coarse to fine** (``cfg.grid_schedule``): a finer grid at each stage;
* **spherical harmonics** (``cfg.grid_sh_start``): the RGB colour grid turns view-dependent;
* **occupancy** (``cfg.occupancy_every``): refresh the empty-space grid every N steps;
* **adapt the batch** (``cfg.adapt_batch``, :class:`BatchTuner`): rays per step from the measured
  cost of a step, so that a scene whose rays cost more (many occupied samples: fine detail) gets
  smaller batches and more steps, and a sparse one larger batches.

Every time in the schedule is a **fraction of the run** (``progress`` in [0, 1]: of the time
budget, or of the steps when there is none), so a 1-minute and a 20-minute run go through the
same stages. Each callback reads what is already done from the model itself (its resolution, its
SH degree, ``bounds.shrunk``), so a resumed run does not repeat a stage.
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass, replace
from typing import Callable

import torch

from course_lib.nerf.render import render_rays

__all__ = ["TrainingCallback", "BatchTuner", "grid_callbacks", "surface_box", "target_resolution", "SHRINK_RETRY",
           "SHRINK_PATIENCE"]

#: when no surface is found yet at ``shrink_box_at``, look again this much later (a fraction of the run)
SHRINK_RETRY = 0.01
#: and give up (keep the first box) this long after ``shrink_box_at``
SHRINK_PATIENCE = 0.15


@dataclass
class TrainingCallback:
    """Something the model does to itself during training.

    Attributes:
        name: what it does (shown in errors and logs).
        where: ``"before"`` or ``"after"`` the optimizer step.
        due: ``due(state) -> bool``.
        run: ``run(state) -> bool``: True when it replaced parameters (the trainer then builds a
            new optimizer).

    ``state`` is the trainer's :class:`~course_lib.nerf.train.TrainState`: ``step`` (steps done),
    ``progress`` (fraction of the run), ``bounds`` (which a callback may replace), ``rays``, ``generator``.
    """

    name: str
    where: str
    due: Callable[[int, float], bool]
    run: Callable[[object], bool]


def target_resolution(cfg, progress: float) -> int:
    """The grid resolution at ``progress``: ``cfg.grid_resolution`` times the share of the last stage reached."""
    share = 1.0
    for at, s in cfg.grid_schedule:
        if progress >= at:
            share = s
    return max(2, int(round(share * cfg.grid_resolution)))


@torch.no_grad()
def surface_box(model, cfg, rays, generator: torch.Generator, n_rays: int = 16384, min_weight: float = 0.05,
                margin_voxels: float = 3.0, min_acc: float = 0.0, min_points: int = 100) -> tuple[list, list] | None:
    """The box around the points where (a sample of) the training rays stop, with a margin.

    After a short coarse stage the density in empty space is still noisy ("fog" of small
    opacity), but the points that carry most of each ray's weight already sit on the surfaces;
    their bounding box is a tight box for the fine grid (robust quantiles, then a margin).
    With ``min_acc > 0`` only the rays whose opacity already reaches it count (rays that stop on
    the object): where the object covers little of the images, the fog on the many background
    rays would otherwise hold the box at its first size.

    Args:
        model: the :class:`~course_lib.nerf.grid.GridField`. cfg: the run's config.
        rays: :class:`~course_lib.nerf.scene.TrainingRays`. generator: picks the rays.
        min_weight: a sample counts where its weight exceeds this. margin_voxels: added on every side.
        min_acc: the opacity a ray needs for its samples to count (0: every ray).
        min_points: the fewest such samples that make a box.

    Returns:
        ``(box_min, box_max)`` lists, inside the current box; None while fewer than ``min_points`` samples
        carry ``min_weight`` (early in a run, when the field is still a faint fog: no surface is found yet).
    """
    o, d, _rgb = rays.sample(min(n_rays, len(rays)), generator)
    near, far = model.ray_bounds(o, d)
    pts_all = []
    for i in range(0, o.shape[0], 4096):
        out = render_rays(model, o[i:i + 4096], d[i:i + 4096], near[i:i + 4096], far[i:i + 4096], cfg.n_samples,
                          white_background=cfg.white_background, last_delta=None)
        pts = o[i:i + 4096, None, :] + out["z_vals"][..., None] * d[i:i + 4096, None, :]
        pts_all.append(pts[(out["weights"] > min_weight) & (out["acc_map"] >= min_acc)[:, None]])
    pts = torch.cat(pts_all)
    if pts.shape[0] < min_points:
        return None
    lo = torch.quantile(pts, 0.001, dim=0) - margin_voxels * model.voxel_size
    hi = torch.quantile(pts, 0.999, dim=0) + margin_voxels * model.voxel_size
    return torch.maximum(lo, model.box_min).tolist(), torch.minimum(hi, model.box_max).tolist()


class BatchTuner:
    """Rays per step from the measured cost of a step: ``t(B) = a B + g`` (``cfg.adapt_batch``).

    A step of the grid costs a part that grows with its batch ``B`` (``a`` seconds a ray: the
    samples of the ray that fall in occupied voxels, their colours, the backward pass) and a part
    ``g`` that does not (the dense Adam update of every voxel, the TV prior). ``a`` depends on the
    scene (fine detail everywhere: many occupied samples a ray) and ``g`` on the grid, so a batch
    chosen from the image size alone is too large for a detailed scene (few, slow steps) and too
    small for a sparse one. Once the grid is final -- and again when the colour turns
    view-dependent, or the box shrinks late, which change ``a`` -- the tuner times ``window`` steps
    at the configured batch ``B`` and ``window`` at ``B / 2`` (real training steps: nothing is thrown
    away), solves for ``a`` and ``g`` (medians of the step times, robust to the occupancy refreshes
    between them) and sets
    ``B = adapt_batch * g / a`` -- the rays' part of a step ``adapt_batch`` times the grid's --
    within ``[B / 4, 2 B]``, at least 1024 rays, a multiple of 256. Without a clear measurement
    (``a`` or ``g`` not positive: a noisy machine) it keeps the batch. It runs only with a time
    budget (``cfg.minutes``): there the number of steps depends on the clock anyway, while a run of
    a fixed number of steps stays reproducible.

    ``changes`` records ``(step, a, g, new batch)`` (``metrics.json``'s ``history["batch_changes"]``).
    """

    def __init__(self, model, cfg, window: int = 16, skip: int = 3):
        self.model, self.cfg, self.window, self.skip = model, cfg, window, skip
        self.final_at = max((at for at, _ in cfg.grid_schedule), default=0.0)
        self.key = None  # (resolution, SH degree) last measured
        self.phase, self.start, self.t_full = None, 0, None

    def due(self, st) -> bool:
        # only with a time budget: a run of a fixed number of steps stays reproducible (no batch from a clock)
        return bool(self.cfg.adapt_batch and self.cfg.minutes) and st.progress >= max(self.final_at, self.cfg.shrink_box_at) and (
            self.model.resolution >= target_resolution(self.cfg, st.progress))

    @staticmethod
    def _step_seconds(history: dict, after: int) -> float | None:
        """Median seconds a step over the recorded steps after step ``after``."""
        it, sec = history["iterations"], history["seconds"]
        dts = [(sec[i] - sec[i - 1]) / (it[i] - it[i - 1]) for i in range(1, len(it)) if it[i - 1] >= after]
        return statistics.median(dts) if dts else None

    def run(self, st) -> bool:
        key = (self.model.resolution, self.model.sh_degree, st.bounds.shrunk)  # a later box: other costs
        if self.phase is None:
            if key != self.key:  # the step's cost changed: measure at the configured batch, then at half of it
                self.key, self.phase, self.start = key, "full", st.step
                st.config = replace(st.config, batch_rays=self.cfg.batch_rays)
            return False
        if st.step - self.start < self.window + self.skip or key != self.key:
            if key != self.key:
                self.phase = None
            return False
        t = self._step_seconds(st.history, self.start + self.skip)
        B = self.cfg.batch_rays
        if self.phase == "full":
            self.t_full, self.phase, self.start = t, "half", st.step
            st.config = replace(st.config, batch_rays=B // 2)
            return False
        self.phase = None
        a = (self.t_full - t) / (B - B // 2) if t is not None and self.t_full is not None else 0.0
        g = self.t_full - a * B if self.t_full is not None else 0.0
        new = B
        if a > 0 and g > 0:
            new = self.cfg.adapt_batch * g / a
            new = int(round(min(2 * B, max(B / 4, 1024, new)) / 256)) * 256
        st.config = replace(st.config, batch_rays=new)
        st.history.setdefault("batch_changes", []).append([st.step, a, g, new])
        return False


def grid_callbacks(model, cfg) -> list[TrainingCallback]:
    """The callbacks of a :class:`~course_lib.nerf.grid.GridField` trained with ``cfg`` (see the module)."""

    next_look = cfg.shrink_box_at  # when the box is looked at (again)

    def shrink(state) -> bool:
        nonlocal next_look
        box = surface_box(model, cfg, state.rays, state.generator, min_weight=cfg.shrink_min_weight,
                          min_acc=cfg.shrink_min_acc)
        if box is None:  # no surface yet: look again a little later, or keep the first box for good
            if state.progress < cfg.shrink_box_at + SHRINK_PATIENCE:
                next_look = state.progress + SHRINK_RETRY
                return False
            state.bounds = state.bounds.with_box(model.box_min.tolist(), model.box_max.tolist())
            return False
        lo, hi = box
        model.rebox(lo, hi, target_resolution(cfg, state.progress))
        model.update_occupancy(cfg.occupancy_threshold)
        state.bounds = state.bounds.with_box(lo, hi)
        return True

    def upsample(state) -> bool:
        model.upsample(target_resolution(cfg, state.progress))
        model.update_occupancy(cfg.occupancy_threshold)
        return True

    def spherical_harmonics(state) -> bool:
        model.enable_sh(cfg.grid_sh_degree)  # RGB first (cheap steps), view-dependent colour from here
        return True

    def occupancy(state) -> bool:
        model.update_occupancy(cfg.occupancy_threshold)
        return False

    tuner = BatchTuner(model, cfg)

    return [
        TrainingCallback("shrink the box", "before", lambda st: bool(cfg.shrink_box_at) and not st.bounds.shrunk
                         and st.progress >= next_look, shrink),
        TrainingCallback("coarse to fine", "before", lambda st: bool(cfg.grid_schedule)
                         and target_resolution(cfg, st.progress) > model.resolution, upsample),
        TrainingCallback("spherical harmonics", "before", lambda st: bool(cfg.grid_sh_degree) and model.sh_degree == 0
                         and st.progress >= cfg.grid_sh_start, spherical_harmonics),
        TrainingCallback("occupancy", "after", lambda st: bool(cfg.occupancy_every) and st.progress >= cfg.occupancy_start
                         and st.step % cfg.occupancy_every == 0, occupancy),
        TrainingCallback("adapt the batch", "after", tuner.due, tuner.run),
    ]

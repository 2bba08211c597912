"""Training configurations: :class:`TrainConfig` and the presets ``"paper"`` and ``"fast"``.

``"paper"``
    The paper's model and optimizer: the 8x256 MLP with the encoded input concatenated again after
    layer 4 (0-based, as the official code), L = 10 / 4 octaves, view-dependent colour, ReLU
    density, 64 stratified coarse samples per ray (``fine=True`` adds the paper's fine network
    with its 128 importance samples), Adam with lr 5e-4 decaying exponentially to 5e-5 over the
    run, batches of random rays across all training images. One difference, for a CPU: 1024 rays
    per batch (the paper: 4096). On a CPU it learns slowly: minutes give a grey blur, hours a
    sharp scene.

``"fast"``
    Same data, same rays, same volume rendering, same loss; the field is a voxel grid
    (:class:`course_lib.nerf.grid.GridField`: density + colour, trilinear interpolation) instead of
    an MLP, with the usual speed-ups: only the scene's box is sampled (ray-box bounds), a coarse
    grid first (40 % of the final resolution); at 6 % of the run the grid is resampled into the
    box around the surfaces the rays hit (:func:`course_lib.nerf.schedule.surface_box`: the samples
    that carry 1 % of a ray's weight, so that a surface still faint then is not cut away) at 80 %,
    at 15 % refined to the final resolution; an occupancy grid skips empty space (and the faint
    fog of voxels whose opacity stays below 1 %); colours only where the weight is > 1e-4; a
    small density total-variation prior (its gradient written out); fused Adam at a high
    learning rate (0.1 decaying to 0.01) on batches that grow with the grid (:func:`auto_batch_rays`:
    2048 rays at 100 voxels, 6144 at 200), then, in a run with a time budget, follow the measured cost of a
    step once the grid is final (``adapt_batch``, :class:`course_lib.nerf.schedule.BatchTuner`: smaller
    batches and more steps where the rays are costly, e.g. an object that fills the frame). Colour is an RGB grid
    (view-independent, cheap steps) for the first 45 % of the run, then spherical harmonics of
    degree 1 (view-dependent, for shiny surfaces; 4x the colour channels; notebook 09's 7b).
    Every stage is a fraction of the run (of ``minutes``, else of ``iters``), so short and long
    runs go through the same stages. The final resolution and the samples per ray follow the
    images (:func:`auto_grid_resolution`: 100 voxels at 100 x 100 px, more for larger images and
    longer budgets) unless ``grid_resolution`` / ``n_samples`` are set.

Both run for 5 minutes (``minutes``: the whole run, loading and the final evaluation included)
and use ``threads=-1``: ``OMP_NUM_THREADS`` where it is set, else ``torch.set_num_threads(1)`` when the
machine is busy (other work on more than 3/4 of the cores), else all cores -- on a shared machine
several torch threads wait for each other at every operation and run many times slower than one.

Every default lives here, in :class:`TrainConfig` or a preset: ``train(data, config="fast")`` and
``python -m course_lib nerf train`` run the same thing. Every field can be overridden
(``preset("fast", n_samples=96)``, ``dataclasses.replace(cfg, n_samples=96)``, or the CLI's
``--n-samples 96``: :mod:`course_lib.nerf.cli_nerf` makes one option per field, its help from the
field's docstring).
"""

from __future__ import annotations

import ast
import inspect
import re
import textwrap
import typing
from dataclasses import dataclass, fields, replace
from typing import Annotated, Literal

from course_lib.validate import KitInputError

__all__ = ["TrainConfig", "FractionOfRun", "preset", "PRESETS", "auto_grid_resolution", "auto_batch_rays", "resolve",
           "field_docs", "FINE_SAMPLES", "BATCH_EXPONENT"]

#: A moment of the run as a fraction of it, in [0, 1]: of ``minutes``, or of ``iters`` without a time budget.
FractionOfRun = Annotated[float, "fraction of the run"]

#: the paper's fine samples per ray (N_f), used when ``fine`` is on and ``n_importance`` is 0
FINE_SAMPLES = 128
#: how fast a grid's batch grows with its resolution (:func:`auto_batch_rays`)
BATCH_EXPONENT = 1.5


@dataclass
class TrainConfig:
    """Everything that defines a training run (stored in checkpoints and ``metrics.json``).

    One section per component -- the model, the voxel grid, the sampling of the rays, the
    optimizer, the run's budget and outputs -- and a docstring under each field (the CLI's help,
    :func:`field_docs`). ``0`` means "automatic" where a field says so; :func:`resolve` fills those
    in for the images at hand.
    """

    preset: str = "custom"
    """The preset this config came from (``"paper"``, ``"fast"``, or ``"custom"``)."""

    # ---- model
    model: Literal["nerf", "grid"] = "nerf"
    """The field: ``nerf``, the paper's MLP (:class:`course_lib.nerf.model.NeRF`), or ``grid``, a voxel grid (:class:`course_lib.nerf.grid.GridField`)."""
    depth: int = 8
    """MLP: Linear + ReLU trunk layers."""
    width: int = 256
    """MLP: width of the trunk layers."""
    skips: tuple[int, ...] = (4,)
    """MLP: 0-based trunk layers whose output is concatenated with the encoded input again."""
    pos_freqs: int = 10
    """MLP: octaves L of the position encoding."""
    dir_freqs: int = 4
    """MLP: octaves L of the view-direction encoding."""
    use_viewdirs: bool = True
    """MLP: the colour depends on the viewing direction."""
    view_width: int = 128
    """MLP: width of the colour branch."""
    density: Literal["relu", "softplus"] = "relu"
    """MLP: activation of the density output."""
    fine: bool = False
    """MLP: train a second (fine) network for the importance samples (the paper); else the coarse network evaluates them too."""

    # ---- voxel grid
    grid_resolution: int = 128
    """Final voxels along the longest box side (0: from the image size and the budget, :func:`auto_grid_resolution`)."""
    grid_schedule: tuple[tuple[float, float], ...] = ()
    """Coarse to fine: ``(fraction of the run, share)`` pairs; from that moment on the grid has ``share`` x ``grid_resolution`` voxels."""
    shrink_box_at: FractionOfRun = 0.0
    """When the grid is resampled into the box around the surfaces seen so far (:func:`course_lib.nerf.schedule.surface_box`; 0: never)."""
    shrink_min_weight: float = 0.05
    """The box around the surfaces counts the samples that carry at least this share of their ray's weight (:func:`course_lib.nerf.schedule.surface_box`)."""
    shrink_min_acc: float = 0.0
    """The box around the surfaces counts only the rays whose opacity reaches this (:func:`course_lib.nerf.schedule.surface_box`; 0: every ray)."""
    grid_mlp_width: int = 0
    """Width of an optional tiny colour MLP on a feature grid (0: none)."""
    grid_feature_dim: int = 12
    """Channels of the feature grid read by the tiny colour MLP."""
    grid_dir_freqs: int = 2
    """Octaves of the view-direction encoding of the tiny colour MLP."""
    grid_sh_degree: Literal[0, 1, 2] = 0
    """View-dependent colour from spherical harmonics of this degree (0: view-independent RGB)."""
    grid_sh_start: FractionOfRun = 0.0
    """From when the colour grid holds spherical harmonics (0: from the start); before it an RGB grid, whose steps are cheaper (:meth:`GridField.enable_sh`)."""
    alpha_init: float = 1e-2
    """Initial opacity of one voxel."""

    # ---- sampling
    n_samples: int = 64
    """Coarse samples per ray (0: 0.8 x the grid's final resolution for a grid, 64 for the MLP)."""
    n_importance: int = 0
    """Fine samples per ray drawn from the coarse weights (0: none, or 128, the paper's, with ``fine``)."""
    near: float | None = None
    """Near bound of the rays (None: from the cameras, :func:`course_lib.nerf.scene.scene_bounds`)."""
    far: float | None = None
    """Far bound of the rays (None: from the cameras)."""
    white_background: bool = True
    """Composite onto white (Blender scenes); False: onto black."""
    box_bounds: bool = True
    """Grid: sample each ray only inside the grid's box (ray-box bounds); False: between near and far, as the MLP (notebook 09's ablation)."""
    perturb: bool = True
    """Stratified jitter of the training samples."""
    color_threshold: float = 0.0
    """Grid: compute colours only where a sample's weight exceeds this."""
    occupancy_every: int = 0
    """Grid: refresh the occupancy grid (empty-space skipping) every N steps (0: never)."""
    occupancy_start: FractionOfRun = 0.0
    """Grid: from when the occupancy grid is refreshed."""
    occupancy_threshold: float = 1e-3
    """Grid: a voxel is empty below this one-voxel opacity (never above the grid's mean opacity)."""

    # ---- optimizer
    batch_rays: int = 1024
    """Random rays per step, across all training images (0: from the grid's resolution, :func:`auto_batch_rays`)."""
    lr: float = 5e-4
    """Adam's learning rate of the networks, decayed exponentially to ``lr_final`` over the run."""
    lr_final: float = 5e-5
    """The networks' learning rate at the end of the run."""
    grid_lr: float = 0.1
    """Adam's learning rate of the voxel grids, decayed exponentially to ``grid_lr_final``."""
    grid_lr_final: float = 0.01
    """The grids' learning rate at the end of the run."""
    adapt_batch: float = 0.0
    """Grid: once the grid is final (and again when its colour turns view-dependent), time steps at the batch and at half of it, and set the batch so that the rays' part of a step is this many times the grid's part (:class:`course_lib.nerf.schedule.BatchTuner`; 0: keep ``batch_rays``)."""
    tv_weight: float = 0.0
    """Weight of the density total-variation prior (grid)."""
    grid_sparse_adam: bool = False
    """Grid: Adam only on the voxels each step read (lazy Adam, :class:`course_lib.nerf.optim.GridAdam`) instead of dense Adam."""
    seed: int = 0
    """Seed of the torch Generator (rays, jitter) and of the initial weights."""
    threads: int = -1
    """Torch threads on a CPU (0: torch's default; -1: OMP_NUM_THREADS where set, else all cores, or 1 on a busy machine)."""

    # ---- budget and outputs
    minutes: float | None = 5.0
    """Time budget of the whole run: loading, training, snapshots, checkpoints, final evaluation (a total over resumes; 0 or None: no time limit)."""
    iters: int = 200_000
    """Maximum number of steps (a total over resumes; whichever of ``minutes`` and ``iters`` comes first)."""
    snapshot_every: int = 0
    """Render the held-out view every N steps (0: never)."""
    snapshot_max_side: int = 200
    """Snapshots are previews with their longest side at most this many pixels (0: full size); final renders are full size."""
    checkpoint_every: int = 0
    """Save a checkpoint every N steps (0: only at the end)."""
    checkpoint_seconds: float = 0.0
    """And not within this many seconds of the last one (0: no limit); a 400 px grid's checkpoint takes about 0.7 s."""
    eval_every: int = 0
    """PSNR on ``n_eval_views`` test views every N steps (0: only at the end)."""
    n_eval_views: int = 2
    """Test views of the evaluations during the run."""
    chunk: int = 0
    """Rays per forward pass of a render (0: from the device, :func:`course_lib.nerf.device.render_chunk`)."""
    overhead_budget: float = 0.05
    """A due snapshot, evaluation or checkpoint waits while the time outside training (loading included) plus its own would exceed this fraction of the training time (0: never waits)."""
    final_eval_share: float = 0.03
    """With ``minutes``, the share of the budget for the final evaluation: all test views when they fit at the measured render speed, else at least ``final_eval_min_views`` evenly spread ones."""
    final_eval_min_views: int = 8
    """The fewest test views the final evaluation renders (when all of them do not fit in its share)."""
    eval_all: bool = False
    """Render all test views at the end, whatever the budget."""

    def to_dict(self) -> dict:
        """Plain values (checkpoints, ``metrics.json``)."""
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["skips"] = list(self.skips)
        d["grid_schedule"] = [list(x) for x in self.grid_schedule]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        """The inverse of :meth:`to_dict` (also reads the configs of older checkpoints)."""
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise KitInputError(f"unknown TrainConfig fields {sorted(unknown)}")
        d = dict(d)
        if "skips" in d:
            d["skips"] = tuple(d["skips"])
        if "grid_schedule" in d:
            d["grid_schedule"] = tuple(tuple(x) for x in d["grid_schedule"])
        return cls(**d)


PRESETS: dict[str, TrainConfig] = {
    "paper": TrainConfig(
        preset="paper", model="nerf", depth=8, width=256, skips=(4,), pos_freqs=10, dir_freqs=4, use_viewdirs=True,
        view_width=128, density="relu", n_samples=64, n_importance=0, batch_rays=1024, lr=5e-4, lr_final=5e-5,
        snapshot_every=50, checkpoint_every=100, eval_every=0,
    ),
    "fast": TrainConfig(
        preset="fast", model="grid", grid_resolution=0, grid_schedule=((0.0, 0.4), (0.06, 0.8), (0.15, 1.0)),
        shrink_box_at=0.06, shrink_min_weight=0.01, grid_mlp_width=0, alpha_init=1e-2, n_samples=0, color_threshold=1e-4,
        grid_sh_degree=1, grid_sh_start=0.45,
        occupancy_every=50, occupancy_start=0.03, occupancy_threshold=1e-2, batch_rays=0, adapt_batch=1.4,
        lr=1e-3, lr_final=1e-4,
        grid_lr=0.1, grid_lr_final=0.01, tv_weight=1e-4, snapshot_every=100, checkpoint_every=200,
        checkpoint_seconds=60.0, eval_every=0,
    ),
}


def preset(name: str, **overrides) -> TrainConfig:
    """A copy of the preset ``name`` (``"paper"`` or ``"fast"``) with ``overrides`` applied.

    Introduced in ``notebooks/08_nerf_rendering_and_training.ipynb``.
    """
    if name not in PRESETS:
        raise KitInputError(f"unknown preset {name!r}: choose one of {sorted(PRESETS)}")
    known = {f.name for f in fields(TrainConfig)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise KitInputError(f"preset({name!r}): unknown TrainConfig fields {unknown}")
    return replace(PRESETS[name], **overrides)


def auto_grid_resolution(H: int, W: int, minutes: float | None = None) -> int:
    """Voxels along the box's longest side for images of ``H x W`` pixels and a budget of ``minutes``.

    100 voxels at 100 x 100 px (where lego reaches 33 dB in 5 minutes on 2 CPU cores); larger
    images show finer detail, so the grid grows with the image side -- but much more slowly than
    it, because a larger grid also costs more per step and needs more steps to be fitted:
    ``100 (side / 100)^0.3`` (123 at 200 px, 152 at 400 px, 187 at 800 px), times
    ``(minutes / 5)^0.1`` for other budgets, within [64, 256]: the best of the resolutions tried on
    the building (the scene the presets are tuned on) at 2 CPU threads.
    """
    side = max(int(H), int(W))
    scale = (side / 100.0) ** 0.3 * ((minutes / 5.0) ** 0.1 if minutes else 1.0)
    return int(min(256, max(64, round(100 * scale))))


def auto_batch_rays(resolution: int) -> int:
    """Rays per step for a voxel grid of ``resolution`` voxels along its longest side.

    A step of the grid costs a part that grows with the batch (its rays' samples) and a part that
    grows with the grid: the dense Adam update of every voxel, zeroing the gradients, the TV
    prior (about 20 ms of a 48 ms step at 152 voxels, 2 CPU threads). A larger grid therefore asks
    for a larger batch, or the step is mostly spent on voxels the batch never saw:
    ``2048 (resolution / 100)^K`` rays (:data:`BATCH_EXPONENT`), a multiple of 1024, at least 2048
    (2048 at 100 px, 4096 at 400 px, 6144 at 800 px in 10 minutes): the best of the batches tried
    on the building at 400 and 800 px, 2 CPU threads.
    """
    return max(2048, 1024 * int(round(2.0 * (resolution / 100.0) ** BATCH_EXPONENT)))


def _hints() -> dict:
    return typing.get_type_hints(TrainConfig, include_extras=True)


def _check(cfg: TrainConfig) -> None:
    """Values a run cannot use, with what to do instead."""
    for name, hint in _hints().items():
        value = getattr(cfg, name)
        if hint is FractionOfRun and not 0.0 <= value <= 1.0:
            raise KitInputError(f"{name} = {value}: expected a fraction of the run in [0, 1]")
        if typing.get_origin(hint) is Literal and value not in typing.get_args(hint):
            raise KitInputError(f"{name} = {value!r}: expected one of {', '.join(map(repr, typing.get_args(hint)))}")
    for at, share in cfg.grid_schedule:
        if not (0.0 <= at <= 1.0 and 0.0 < share <= 1.0):
            raise KitInputError(f"grid_schedule entry ({at}, {share}): expected (fraction of the run in [0, 1], "
                                "share of grid_resolution in (0, 1]), e.g. ((0, 0.4), (0.06, 0.8), (0.15, 1.0))")
    if cfg.minutes is not None and cfg.minutes < 0:
        raise KitInputError(f"minutes = {cfg.minutes}: expected a positive number of minutes (0 or None: no time limit)")
    if cfg.iters < 1:
        raise KitInputError(f"iters = {cfg.iters}: expected at least 1")
    if cfg.batch_rays < 0:
        raise KitInputError(f"batch_rays = {cfg.batch_rays}: expected a number of rays (0: automatic)")
    if not 0.0 <= cfg.final_eval_share <= 1.0:
        raise KitInputError(f"final_eval_share = {cfg.final_eval_share}: expected a share of the budget in [0, 1]")


def resolve(cfg: TrainConfig, H: int, W: int) -> TrainConfig:
    """``cfg`` checked, with its automatic values filled in for images of ``H x W`` pixels.

    ``grid_resolution = 0`` -> :func:`auto_grid_resolution`; ``n_samples = 0`` -> 0.8 x the grid's
    final resolution (about two samples per voxel along a ray through the box; 64 for the MLP);
    ``batch_rays = 0`` -> :func:`auto_batch_rays` (1024 for the MLP); ``n_importance = 0`` with
    ``fine`` -> :data:`FINE_SAMPLES`; ``minutes = 0`` -> None (no time limit).

    Raises:
        KitInputError: a value a run cannot use (a fraction outside [0, 1], an unknown model, ...).
    """
    _check(cfg)
    res = cfg.grid_resolution or auto_grid_resolution(H, W, cfg.minutes)
    samples = cfg.n_samples or (max(16, int(round(0.8 * res))) if cfg.model == "grid" else 64)
    fine = cfg.n_importance or (FINE_SAMPLES if cfg.fine else 0)
    batch = cfg.batch_rays or (auto_batch_rays(res) if cfg.model == "grid" else 1024)
    return replace(cfg, grid_resolution=int(res), n_samples=int(samples), n_importance=int(fine), batch_rays=int(batch),
                   minutes=cfg.minutes or None)


def field_docs(cls=TrainConfig) -> dict[str, tuple[str, str]]:
    """``{field: (section, docstring)}`` of a config dataclass: the string under each field, the ``# ---- section`` above it.

    Read from the source (as nerfstudio's configs are read by tyro); empty where the source is not available.
    """
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return {}
    sections = [(i + 1, m.group(1)) for i, line in enumerate(source.splitlines())
                if (m := re.match(r"\s*# ---- (.+)$", line))]
    body = ast.parse(source).body[0].body
    out = {}
    for node, nxt in zip(body, body[1:] + [None]):
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            doc = (nxt.value.value if isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant)
                   and isinstance(nxt.value.value, str) else "")
            section = next((name for line, name in reversed(sections) if line < node.lineno), "")
            out[node.target.id] = (section, " ".join(doc.split()))
    return out

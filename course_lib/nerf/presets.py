"""Training configurations: :class:`TrainConfig` and the presets ``"paper"`` and ``"fast"``
    Same data, same rays, same volume rendering, same loss; the field is a voxel grid
    (:class:`course_lib.nerf.grid.GridField`: density + colour, trilinear interpolation) instead of
    an MLP, with the usual speed-ups: only the scene's box is sampled (ray-box bounds), a coarse
    grid first (40 % of the final resolution); at 6 % of the run the grid is resampled into the box
    around the surfaces the rays hit (:func:`course_lib.nerf.schedule.surface_box`) at 80 %, at
    15 % refined to the final resolution; an occupancy grid skips empty space (and the faint fog of
    voxels whose opacity stays below 1 %); colours only where
    the weight is > 1e-4; a small density total-variation prior (its gradient written out); fused
    Adam at a high learning rate (0.1 decaying to 0.01) on 2048-ray batches. Colour is an RGB grid
    (view-independent, cheap steps) for the first 45 % of the run, then spherical harmonics of
    degree 1 (view-dependent, for shiny surfaces; 4x the colour channels; notebook 09's 7b).
    Every stage is a fraction of the run (of ``minutes``, else of ``iters``), so short and long
    runs go through the same stages. The final resolution and the samples per ray follow the
    images (:func:`auto_grid_resolution`: 100 voxels at 100 x 100 px, more for larger images and
    longer budgets) unless ``grid_resolution`` / ``n_samples`` are set.

Both use ``threads=-1``: ``torch.set_num_threads(1)`` when the machine is busy (other work on more than
3/4 of the cores), else all cores -- on a shared machine several torch threads wait for each
other at every operation and run many times slower than one.

Every field can be overridden (``dataclasses.replace(preset("fast"), n_samples=96)`` or the CLI's
options).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

from course_lib.validate import KitInputError

__all__ = ["TrainConfig", "preset", "PRESETS", "auto_grid_resolution", "resolve"]


@dataclass
class TrainConfig:
    """Everything that defines a training run (stored in checkpoints and metrics.json).

    Model
        model: ``"nerf"`` (:class:`course_lib.nerf.model.NeRF`) or ``"grid"`` (:class:`course_lib.nerf.grid.GridField`).
        depth, width, skips, pos_freqs, dir_freqs, use_viewdirs, view_width, density: NeRF MLP sizes.
        fine: train a second (fine) NeRF for the ``n_importance`` samples (the paper); else the
            coarse network also evaluates the fine samples.
        grid_resolution: final voxels along the longest box side (0: from the image size and the
            budget, :func:`auto_grid_resolution`); grid_schedule: list of ``(progress, share)``:
            from that fraction of the run on, ``share`` x the final resolution (coarse to fine).
        shrink_box_at: fraction of the run at which the grid is resampled into the box around the
            surfaces seen so far (:func:`course_lib.nerf.schedule.surface_box`; 0: never).
        grid_mlp_width, grid_feature_dim, grid_dir_freqs: optional tiny colour MLP of the grid.
        grid_sh_degree: view-dependent colour of the grid from spherical harmonics (0: none, 1, 2).
        grid_sh_start: fraction of the run from which the colour grid holds spherical harmonics (0: from the start);
            before it an RGB grid, whose steps are cheaper (:meth:`GridField.enable_sh`).
        alpha_init: initial per-voxel opacity of the grid.
    Sampling
        n_samples: coarse samples per ray (0, grid models: 0.8 x the final resolution).
            n_importance: fine samples per ray (0: none).
        near, far: ray bounds (None: from the cameras, see :func:`course_lib.nerf.train.scene_bounds`).
        white_background: composite onto white (Blender scenes).
        box_bounds: grid models sample each ray only between its entry into and exit from the
            grid's box (ray-box bounds); False: between the scene's near and far, as the MLP does
            (an ablation switch, notebook 09).
        color_threshold: compute colours only where the weight exceeds it (grid models).
        occupancy_every, occupancy_threshold, occupancy_start: refresh the grid's occupancy every
            N steps from that fraction of the run on.
    Optimisation
        batch_rays: random rays per step (across all training images). lr, lr_final: Adam
            learning rate, decayed exponentially over the run (MLP: lr; grid: grid_lr / mlp lr).
        grid_lr, grid_lr_final: learning rate of the voxel grids. tv_weight: density TV prior.
        grid_sparse_adam: update only the voxels each step read (:class:`course_lib.nerf.optim.GridAdam`,
            lazy Adam; the TV prior then acts on those voxels too) instead of a dense Adam over the grids.
        seed: torch Generator seed (rays, jitter, initial weights).
        threads: torch.set_num_threads (0: torch's default; -1: auto, 1 thread on a busy machine).
    Budget and outputs
        iters: maximum number of steps; minutes: the whole run's time budget, training and
            everything around it (whichever of the two comes first).
        snapshot_every: render the held-out view every N steps (0: never).
        snapshot_max_side: snapshots are previews: rendered with their longest side at most this many
            pixels (the camera scaled, :func:`~course_lib.nerf.inference.preview_camera`; 0: full size).
            The final test renders are always full size.
        checkpoint_every: save a checkpoint every N steps (0: only at the end); checkpoint_seconds: and
            not within this many seconds of the run after the last one (0: no limit). A checkpoint of
            a grid at 400 px holds 150 MB of voxels and twice that of Adam moments (0.7 s); a crash then
            loses at most about a minute, and the overhead budget is left to the snapshots.
        eval_every: test PSNR on ``n_eval_views`` test views every N steps (0: only at the end).
        chunk: rays per forward pass when rendering images (0: from the device,
            :func:`course_lib.nerf.device.render_chunk`).
        overhead_budget: a snapshot, evaluation or checkpoint that comes due waits while the time
            outside training so far (loading included) plus its own predicted time would exceed this
            fraction of the training time so far (0: never wait). With ``final_eval_share`` it bounds
            everything outside training: about 8 % of the run with the defaults. The
            snapshot at step 0 (runs without ``minutes``: with a budget the untrained field, the
            slowest render of all, is not drawn) and the final checkpoint, snapshot and evaluation always run.
        final_eval_share: with ``minutes``, the share of the budget for the final evaluation: it
            renders the test views that fit (an evenly spread subset, at least one). 3 %: at 400 px
            on 2 CPU cores 9 of 25 views in a 5-minute run, all of them at 100-200 px.
        eval_all: render all test views at the end, whatever the budget.
    """

    preset: str = "custom"
    model: str = "nerf"
    # NeRF MLP
    depth: int = 8
    width: int = 256
    skips: tuple = (4,)
    pos_freqs: int = 10
    dir_freqs: int = 4
    use_viewdirs: bool = True
    view_width: int = 128
    density: str = "relu"
    fine: bool = False
    # voxel grid
    grid_resolution: int = 128
    grid_schedule: tuple = ()
    shrink_box_at: int = 0
    grid_mlp_width: int = 0
    grid_feature_dim: int = 12
    grid_dir_freqs: int = 2
    grid_sh_degree: int = 0
    grid_sh_start: int = 0
    alpha_init: float = 1e-2
    # sampling
    n_samples: int = 64
    n_importance: int = 0
    near: float | None = None
    far: float | None = None
    white_background: bool = True
    box_bounds: bool = True
    perturb: bool = True
    color_threshold: float = 0.0
    occupancy_every: int = 0
    occupancy_start: int = 0
    occupancy_threshold: float = 1e-3
    # optimisation
    batch_rays: int = 1024
    lr: float = 5e-4
    lr_final: float = 5e-5
    grid_lr: float = 0.1
    grid_lr_final: float = 0.01
    tv_weight: float = 0.0
    grid_sparse_adam: bool = False
    seed: int = 0
    threads: int = 0
    # budget and outputs
    iters: int = 200_000
    minutes: float | None = None
    snapshot_every: int = 0
    snapshot_max_side: int = 400
    checkpoint_every: int = 0
    checkpoint_seconds: float = 0.0
    eval_every: int = 0
    n_eval_views: int = 2
    chunk: int = 0
    overhead_budget: float = 0.05
    final_eval_share: float = 0.03
    eval_all: bool = False

    def to_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["skips"] = list(self.skips)
        d["grid_schedule"] = [list(x) for x in self.grid_schedule]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
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
        threads=-1, snapshot_every=50, checkpoint_every=100, eval_every=0,
    ),
    "fast": TrainConfig(
        preset="fast", model="grid", grid_resolution=0, grid_schedule=((0.0, 0.4), (0.06, 0.8), (0.15, 1.0)),
        shrink_box_at=0.06, grid_mlp_width=0, alpha_init=1e-2, n_samples=0, color_threshold=1e-4,
        grid_sh_degree=1, grid_sh_start=0.45,
        occupancy_every=50, occupancy_start=0.03, occupancy_threshold=1e-2, batch_rays=2048, lr=1e-3, lr_final=1e-4,
        grid_lr=0.1, grid_lr_final=0.01, tv_weight=1e-4, threads=-1, snapshot_every=100, checkpoint_every=200,
        checkpoint_seconds=60.0, eval_every=0,
    ),
}


def preset(name: str, **overrides) -> TrainConfig:
    """A copy of the preset ``name`` (``"paper"`` or ``"fast"``) with ``overrides`` applied."""
    if name not in PRESETS:
        raise KitInputError(f"unknown preset {name!r}: choose one of {sorted(PRESETS)}")
    return replace(PRESETS[name], **overrides)


def auto_grid_resolution(H: int, W: int, minutes: float | None = None) -> int:
    """Voxels along the box's longest side for images of ``H x W`` pixels and a budget of ``minutes``.

    100 voxels at 100 x 100 px (where lego reaches 33 dB in 5 minutes on 2 CPU cores); larger
    images show finer detail, so the grid grows with the image side -- but much more slowly than
    it, because a larger grid also costs more per step and needs more steps to be fitted:
    ``100 (side / 100)^0.3`` (123 at 200 px, 152 at 400 px, 187 at 800 px), times
    ``(minutes / 5)^0.1`` for other budgets, within [64, 256]. Measured on the building at 400 px,
    5 minutes, 2 CPU threads (test PSNR on all 25 views, steps): 136 voxels 30.71 dB (5612 steps),
    152 voxels 31.12 dB (4506), 174 voxels 30.79 dB (3323), 200 voxels 29.75 dB (2338).
    """
    side = max(int(H), int(W))
    scale = (side / 100.0) ** 0.3 * ((minutes / 5.0) ** 0.1 if minutes else 1.0)
    return int(min(256, max(64, round(100 * scale))))


def resolve(cfg: TrainConfig, H: int, W: int) -> TrainConfig:
    """``cfg`` with its automatic values filled in for images of ``H x W`` pixels.

    ``grid_resolution = 0`` -> :func:`auto_grid_resolution`; ``n_samples = 0`` -> 0.8 x the grid's
    final resolution (about two samples per voxel along a ray through the box; 64 for the MLP).
    """
    for name in ("shrink_box_at", "grid_sh_start", "occupancy_start", "final_eval_share"):
        if not 0.0 <= getattr(cfg, name) <= 1.0:
            raise KitInputError(f"{name} = {getattr(cfg, name)}: expected a fraction of the run in [0, 1]")
    for at, share in cfg.grid_schedule:
        if not (0.0 <= at <= 1.0 and 0.0 < share <= 1.0):
            raise KitInputError(f"grid_schedule entry ({at}, {share}): expected (fraction of the run in [0, 1], "
                                "share of grid_resolution in (0, 1]), e.g. ((0, 0.4), (0.06, 0.8), (0.15, 1.0))")
    res = cfg.grid_resolution or auto_grid_resolution(H, W, cfg.minutes)
    samples = cfg.n_samples or (max(16, int(round(0.8 * res))) if cfg.model == "grid" else 64)
    return replace(cfg, grid_resolution=int(res), n_samples=int(samples))

"""Checkpoints of a training run: written by :func:`course_lib.nerf.train.train`, read on any device.

A checkpoint holds the model (its weights and the arguments that rebuild it), the optimizer, the
step, the training and wall seconds spent so far (``--minutes`` is a total over resumes), the
config, the scene bounds, the history, the RNG states and the device and camera it was trained
with. It is written to ``checkpoint.tmp`` and renamed, so a run killed while writing keeps the
previous one.
"""

from __future__ import annotations

from pathlib import Path

import torch

from course_lib.nerf.device import pick_device
from course_lib.nerf.grid import GridField
from course_lib.nerf.model import NeRF
from course_lib.nerf.presets import TrainConfig
from course_lib.nerf.scene import SceneBounds
from course_lib.nerf.schedule import target_resolution
from course_lib.validate import KitInputError, file_in

__all__ = ["CHECKPOINT", "save_checkpoint", "load_checkpoint", "build_model", "nerf_arguments"]

#: the file name in a training output folder
CHECKPOINT = "checkpoint.pt"


def nerf_arguments(cfg: TrainConfig) -> dict:
    """The arguments the kit builds ``NeRF`` with: those its stub documents (notebook 07), plus
    ``density`` only where the config asks for the reference's non-default ``"softplus"``."""
    kw = dict(depth=cfg.depth, width=cfg.width, skips=tuple(cfg.skips), pos_freqs=cfg.pos_freqs,
              dir_freqs=cfg.dir_freqs, use_viewdirs=cfg.use_viewdirs, view_width=cfg.view_width)
    if cfg.density != "relu":
        kw["density"] = cfg.density
    return kw


def build_model(cfg: TrainConfig, bounds: SceneBounds, resolution: int | None = None):
    """The model(s) of a config: ``(model, model_fine or None)``; weights from the global torch RNG."""
    if cfg.model == "nerf":
        kw = nerf_arguments(cfg)
        fine = NeRF(**kw) if (cfg.fine and cfg.n_importance > 0) else None
        return NeRF(**kw), fine
    if cfg.model == "grid":
        res = resolution or target_resolution(cfg, 0.0)
        return GridField(bounds["box_min"], bounds["box_max"], resolution=res, mlp_width=cfg.grid_mlp_width,
                         feature_dim=cfg.grid_feature_dim, dir_freqs=cfg.grid_dir_freqs, alpha_init=cfg.alpha_init,
                         sh_degree=cfg.grid_sh_degree if not cfg.grid_sh_start else 0), None
    raise KitInputError(f"model {cfg.model!r}: expected 'nerf' or 'grid'")


def save_checkpoint(path: Path, state, camera: dict | None = None) -> None:
    """Write the trainer's :class:`~course_lib.nerf.train.TrainState` to ``path`` (atomically)."""
    model, fine = state.model, state.model_fine
    torch.save({
        "camera": camera, "device": str(state.device),
        "model": model.state_dict(), "model_kind": state.config.model,
        "model_config": model.config() if hasattr(model, "config") else {**nerf_arguments(state.config),
                                                                         "skips": list(state.config.skips)},
        "model_fine": fine.state_dict() if fine is not None else None,
        "optimizer": state.optimizer.state_dict(), "step": state.step, "train_seconds": state.clock.train_seconds,
        "wall_seconds": state.clock.spent(), "config": state.config.to_dict(), "bounds": state.bounds.to_dict(),
        "history": state.history, "generator_state": state.generator.get_state(),
        "torch_rng_state": torch.get_rng_state(),
    }, path.with_suffix(".tmp"))
    path.with_suffix(".tmp").replace(path)


def _rebuild(ck: dict):
    mc = ck["model_config"]
    if ck["model_kind"] == "grid":
        model = GridField(mc["box_min"], mc["box_max"], resolution=mc["resolution"], mlp_width=mc["mlp_width"],
                          feature_dim=mc["feature_dim"], dir_freqs=mc["dir_freqs"], alpha_init=mc["alpha_init"],
                          sh_degree=mc.get("sh_degree", 0))
        return model, None
    kw = {**mc, "skips": tuple(mc["skips"])}
    if kw.get("density") == "relu":  # the default: not passed (the stub of notebook 07 has no such argument)
        kw.pop("density")
    return NeRF(**kw), (NeRF(**kw) if ck["model_fine"] is not None else None)


def load_checkpoint(path, device="cpu") -> dict:
    """Load a checkpoint written by :func:`course_lib.nerf.train.train` onto any device.

    Args:
        path: ``checkpoint.pt`` or the training output folder.
        device: where the rebuilt models go (``"auto"``, ``"cpu"``, ``"cuda"``, ``"mps"``, a torch.device).

    Returns:
        The stored dict (``step``, ``config``, ``history``, ``device`` it was written on, ...) with
        the rebuilt ``model``, ``model_fine`` (on ``device``), ``cfg`` (:class:`TrainConfig`) and
        ``bounds`` (:class:`~course_lib.nerf.scene.SceneBounds`).

    Introduced in ``notebooks/08_nerf_rendering_and_training.ipynb``.
    """
    path = file_in(path, CHECKPOINT, "checkpoint {path} not found: pass a checkpoint.pt (or the training output folder)")
    device = pick_device(device)
    try:
        # everything to the CPU first: RNG states must stay CPU tensors, the models move afterwards
        ck = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001 -- any unreadable file
        raise KitInputError(f"{path} is not a readable checkpoint ({exc})") from None
    model, model_fine = _rebuild(ck)
    model.load_state_dict(ck["model"])
    model.to(device)
    if model_fine is not None:
        model_fine.load_state_dict(ck["model_fine"])
        model_fine.to(device)
    ck.setdefault("device", None)
    ck.setdefault("wall_seconds", ck.get("train_seconds", 0.0))
    ck.update(model=model, model_fine=model_fine, cfg=TrainConfig.from_dict(ck["config"]),
              bounds=SceneBounds.from_dict(ck["bounds"]))
    return ck

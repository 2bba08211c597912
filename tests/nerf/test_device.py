"""Device choice (course_lib.nerf.device): auto = CUDA, then MPS, then the CPU; a clear error for a
GPU that is not there; checkpoints that load on any device; CUDA training and CPU/CUDA agreement
where a CUDA GPU exists (skipped, saying why, elsewhere)."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from course_lib.nerf import device as dev
from course_lib.nerf.device import available_devices, pick_device, render_chunk
from course_lib.nerf.presets import preset
from course_lib.nerf.checkpoint import load_checkpoint
from course_lib.nerf.inference import render_view
from course_lib.nerf.train import train
from course_lib.validate import KitInputError

from tests.nerf.test_train import make_scene

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU on this machine")


@pytest.fixture(scope="module")
def scene():
    return make_scene()


def tiny_grid(**kw):
    base = dict(iters=40, minutes=None, batch_rays=256, n_samples=32, snapshot_every=0, checkpoint_every=0,
                occupancy_start=0.25, occupancy_every=10, grid_schedule=((0, 0.75), (0.5, 1.0)), grid_resolution=16,
                shrink_box_at=0.5, threads=1, grid_lr=0.3, grid_lr_final=0.1)
    base.update(kw)
    return preset("fast", **base)


def test_cpu_is_always_there():
    assert pick_device("cpu") == torch.device("cpu")
    assert pick_device(torch.device("cpu")) == torch.device("cpu")
    assert available_devices()[-1] == "cpu"
    assert render_chunk("cpu") == dev.CPU_CHUNK


def test_auto_prefers_cuda_then_mps_then_cpu(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(dev, "_mps_available", lambda: False)
    assert pick_device("auto") == torch.device("cpu") and pick_device(None) == torch.device("cpu")
    monkeypatch.setattr(dev, "_mps_available", lambda: True)
    assert pick_device("auto") == torch.device("mps")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert pick_device("auto") == torch.device("cuda", 0)
    assert available_devices() == ["cuda", "mps", "cpu"]


def test_missing_gpu_says_what_to_do(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(dev, "_mps_available", lambda: False)
    with pytest.raises(KitInputError, match=r"no CUDA GPU here.*--device auto \(available here: cpu\)"):
        pick_device("cuda")
    with pytest.raises(KitInputError, match="no Apple GPU"):
        pick_device("mps")
    with pytest.raises(KitInputError, match="expected one of auto, cpu, cuda, mps"):
        pick_device("gpu")
    with pytest.raises(KitInputError, match="expected one of"):
        pick_device(3)


def test_training_records_the_device_and_resumes_after_a_device_change(scene, tmp_path):
    # a checkpoint written "on another device": its generator state does not fit here, so the resumed
    # run reseeds the ray sampler and goes on (models and optimizer state load on any device)
    cfg = tiny_grid(iters=6, checkpoint_every=3)
    train(scene, None, cfg, out_dir=tmp_path, progress=False, device="cpu", callback=lambda step, info: step == 3)
    ck = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    assert ck["device"] == "cpu"
    ck["device"] = "cuda:0"
    ck["generator_state"] = torch.zeros(16, dtype=torch.uint8)  # a CUDA generator's state has another size
    torch.save(ck, tmp_path / "checkpoint.pt")
    res = train(scene, None, cfg, out_dir=tmp_path, progress=False, device="cpu")
    assert res.metrics["iterations"] == 6 and res.metrics["resumed_from"] == {"step": 3, "train_seconds": pytest.approx(
        ck["train_seconds"], abs=0.01), "device": "cuda:0"}
    assert res.metrics["device"] == "cpu" and load_checkpoint(tmp_path, "cpu")["device"] == "cpu"


@needs_cuda
def test_cuda_training(scene, tmp_path):
    res = train(scene.subset(slice(0, 6)), scene.subset([6, 7]), tiny_grid(), out_dir=tmp_path, progress=False,
                device="cuda")
    assert res.metrics["device"].startswith("cuda") and next(res.model.parameters()).is_cuda
    assert res.metrics["final_train_psnr"] > 17 and np.isfinite(res.metrics["test_psnr"])
    ck = load_checkpoint(tmp_path, "cpu")  # written on the GPU, loads on the CPU
    assert ck["device"].startswith("cuda") and not next(ck["model"].parameters()).is_cuda


@needs_cuda
def test_cpu_and_cuda_agree(scene):
    # the same trained field renders the same image on both devices, and training on either reaches
    # the same quality on a tiny scene (their random streams differ, so not the same numbers)
    cfg = tiny_grid()
    on_cpu = train(scene, None, cfg, progress=False, device="cpu")
    on_gpu = train(scene, None, cfg, progress=False, device="cuda")
    assert abs(on_cpu.metrics["final_train_psnr"] - on_gpu.metrics["final_train_psnr"]) < 1.5
    import copy

    gpu_model = copy.deepcopy(on_cpu.model).to("cuda")
    a = render_view(on_cpu.model, None, cfg, on_cpu.bounds, scene.H, scene.W, scene.K, scene.c2w[0])["rgb"]
    b = render_view(gpu_model, None, cfg, on_cpu.bounds, scene.H, scene.W, scene.K, scene.c2w[0])["rgb"]
    torch.testing.assert_close(a, b.cpu(), atol=2e-3, rtol=0)
    mlp_cfg = preset("paper", depth=2, width=32, skips=(), pos_freqs=4, dir_freqs=2, view_width=16, n_samples=16,
                     iters=5, snapshot_every=0, checkpoint_every=0, threads=1)
    mlp = train(scene, None, mlp_cfg, progress=False, device="cpu")
    mlp_gpu = copy.deepcopy(mlp.model).to("cuda")
    a = render_view(mlp.model, None, mlp_cfg, mlp.bounds, scene.H, scene.W, scene.K, scene.c2w[1])["rgb"]
    b = render_view(mlp_gpu, None, replace(mlp_cfg, chunk=0), mlp.bounds, scene.H, scene.W, scene.K, scene.c2w[1])["rgb"]
    torch.testing.assert_close(a, b.cpu(), atol=1e-4, rtol=0)

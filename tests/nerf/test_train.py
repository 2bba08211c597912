"""Training: a tiny synthetic scene (an analytic two-coloured ball) -- the loss falls, a stopped
run resumes to exactly the same state, metrics/snapshots/checkpoints are written; the CLI."""

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from course_lib.data.blender import BlenderData, intrinsics_from_fov, write_blender
from course_lib.data.synthetic import look_at
from course_lib.nerf.presets import preset
from course_lib.nerf.render import render_image
from course_lib.nerf.checkpoint import build_model, load_checkpoint
from course_lib.nerf.inference import circular_path
from course_lib.nerf.scene import scene_bounds
from course_lib.nerf.train import train


class Ball(torch.nn.Module):
    """Radius-0.8 ball at the origin: red above z = 0, blue below."""

    def forward(self, pts, viewdirs=None):
        inside = (pts.norm(dim=-1) < 0.8).to(pts.dtype)
        top = (pts[..., 2] > 0).to(pts.dtype)
        rgb = torch.stack([top, 0.2 * torch.ones_like(top), 1 - top], dim=-1)
        return rgb, 30.0 * inside


def make_scene(n=8, size=16, dist=3.0):
    K = intrinsics_from_fov(size, size, 0.9)
    c2ws, imgs = [], []
    for k in range(n):
        th = 2 * np.pi * k / n
        C = dist * np.array([np.cos(th) * 0.9, np.sin(th) * 0.9, 0.45 if k % 2 else -0.3])
        R_cw, _ = look_at(C, np.zeros(3), up=np.array([0, 0, 1.0]))
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = R_cw.T, C
        c2ws.append(M)
        imgs.append(render_image(Ball(), size, size, K, M, 1.0, 5.0, 96)["rgb"].numpy())
    return BlenderData(images=np.stack(imgs).astype(np.float32), c2w=np.stack(c2ws), K=K, H=size, W=size,
                       names=[f"v{k}" for k in range(n)], camera_angle_x=0.9)


@pytest.fixture(scope="module")
def scene():
    return make_scene()


def tiny_nerf_config(**kw):
    base = dict(depth=2, width=32, skips=(), pos_freqs=4, dir_freqs=2, view_width=16, density="softplus",
                n_samples=16, batch_rays=256, lr=5e-3, lr_final=5e-3, snapshot_every=0, checkpoint_every=0, threads=1,
                minutes=None)
    base.update(kw)
    return preset("paper", **base)


def test_scene_bounds(scene):
    b = scene_bounds(scene.c2w, scene.K, scene.W)
    np.testing.assert_allclose(b["center"], 0.0, atol=1e-6)
    assert 0.8 < b["radius"] < 3.0 and 0 < b["near"] < 3.0 - 0.8 and b["far"] > 3.0 + 0.8


def test_grid_training_lowers_the_loss(scene, tmp_path):
    cfg = preset("fast", iters=60, minutes=None, batch_rays=512, n_samples=48, snapshot_every=30, checkpoint_every=0,
                 occupancy_start=1 / 3, occupancy_every=10, grid_schedule=((0, 2 / 3), (1 / 3, 1.0)), grid_resolution=24,
                 shrink_box_at=1 / 3, threads=1, grid_lr=0.3, grid_lr_final=0.1, overhead_budget=0)
    res = train(scene.subset(slice(0, 6)), scene.subset([6, 7]), cfg, out_dir=tmp_path, progress=False, device="cpu")
    loss = res.history["loss"]
    assert np.mean(loss[-10:]) < 0.3 * np.mean(loss[:5])
    assert res.metrics["final_train_psnr"] > 17
    m = json.loads((tmp_path / "metrics.json").read_text())
    for key in ("test_psnr", "iterations", "train_seconds", "preset", "history"):
        assert key in m
    assert m["iterations"] == 60 and m["preset"] == "fast" and np.isfinite(m["test_psnr"])  # 6 views of 16x16 px: no generalisation expected
    assert (tmp_path / "test" / "v6.png").exists() and (tmp_path / "checkpoint.pt").exists()
    assert sorted(p.name for p in (tmp_path / "snapshots").iterdir()) == ["step_000000.png", "step_000030.png", "step_000060.png"]
    assert len(res.snapshots) == 3 and res.test_renders.shape == (2, 16, 16, 3)
    # the box was fitted around the ball (radius 0.8, plus a margin) and the grid refined
    assert res.bounds["shrunk"] and res.model.resolution == 24
    assert np.all(np.array(res.bounds["box_max"]) > 0.75) and np.all(np.array(res.bounds["box_min"]) < -0.75)
    # the device and the time outside training are recorded
    assert m["device"] == "cpu" and load_checkpoint(tmp_path)["device"] == "cpu"
    assert m["wall_seconds"] >= m["train_seconds"] and 0 < m["overhead_fraction"] < 1
    assert {"setup", "snapshots", "checkpoints", "final_evaluation"} <= set(m["overhead_breakdown"])


def test_grid_training_with_sparse_adam(scene):
    # lazy Adam on the voxels each step read (and the TV prior on them): the loss falls as with dense Adam
    from course_lib.nerf.optim import GridAdam

    cfg = preset("fast", iters=60, minutes=None, batch_rays=512, n_samples=48, snapshot_every=0, checkpoint_every=0,
                 occupancy_start=1 / 3, occupancy_every=10, grid_schedule=((0, 2 / 3), (1 / 3, 1.0)), grid_resolution=24,
                 shrink_box_at=1 / 3, threads=1, grid_lr=0.3, grid_lr_final=0.1, grid_sparse_adam=True)
    seen = []
    res = train(scene.subset(slice(0, 6)), None, cfg, progress=False, device="cpu",
                callback=lambda step, info: seen.append(step) and False)
    loss = res.history["loss"]
    assert np.mean(loss[-10:]) < 0.3 * np.mean(loss[:5]) and res.metrics["final_train_psnr"] > 17
    assert res.model.density_grid.reads == [] and len(seen) == 60  # every step's reads were used
    from course_lib.nerf.train import make_optimizer

    assert isinstance(make_optimizer(res.config, res.model, None), GridAdam)


def test_overhead_budget_defers_snapshots(scene):
    # a snapshot due every step would cost more than training: with a 5 % budget most of them wait
    cfg = tiny_nerf_config(iters=30, snapshot_every=1, overhead_budget=0.05)
    res = train(scene, scene.subset([0]), cfg, progress=False, device="cpu")
    steps = [s for s, _ in res.snapshots]
    assert steps[0] == 0 and steps[-1] == 30 and len(steps) < 15
    unlimited = train(scene, scene.subset([0]), replace(cfg, overhead_budget=0), progress=False, device="cpu")
    assert [s for s, _ in unlimited.snapshots] == list(range(31))
    assert res.metrics["overhead_breakdown"]["snapshots"] < unlimited.metrics["overhead_breakdown"]["snapshots"]


def test_snapshots_are_previews_and_wait_for_their_predicted_time(scene):
    # snapshots of large images are rendered at preview size (the final one too); a snapshot that
    # would take the time outside training over the budget waits, however long ago it came due
    big = make_scene(n=6, size=48)
    cfg = tiny_nerf_config(iters=8, snapshot_every=4, snapshot_max_side=24, overhead_budget=0)
    res = train(big.subset(range(4)), big.subset([4, 5]), replace(cfg, eval_all=True), progress=False, device="cpu")
    assert [s for s, _ in res.snapshots] == [0, 4, 8] and all(img.shape == (24, 24, 3) for _, img in res.snapshots)
    assert res.test_renders.shape == (2, 48, 48, 3)
    slow = train(big.subset(range(4)), big.subset([4, 5]), replace(cfg, overhead_budget=1e-9), progress=False,
                 device="cpu")
    assert [s for s, _ in slow.snapshots] == [0, 8]  # step 0 (runs without minutes) and the final one


def test_progress_bar_counts_time_or_steps(scene, capsys):
    train(scene, None, tiny_nerf_config(iters=10**6, minutes=0.01), progress=True, device="cpu")
    err = capsys.readouterr().err
    assert "/1 s of the run" in err and "1000000" not in err  # seconds of the 0.6 s allowed, not steps
    train(scene, None, tiny_nerf_config(iters=7), progress=True, device="cpu")
    err = capsys.readouterr().err
    assert "7/7" in err and "s of the run" not in err


def test_nerf_training_lowers_the_loss(scene):
    res = train(scene, None, tiny_nerf_config(iters=40), progress=False)
    loss = res.history["loss"]
    assert np.mean(loss[-5:]) < 0.6 * np.mean(loss[:5])
    assert res.metrics["test_psnr"] is None and res.metrics["iterations"] == 40


def test_fine_network_runs(scene):
    res = train(scene, None, tiny_nerf_config(iters=3, n_importance=8, fine=True), progress=False)
    assert res.model_fine is not None and len(res.history["loss"]) == 3


def test_resume_gives_the_same_state(scene, tmp_path):
    cfg = tiny_nerf_config(iters=8, checkpoint_every=4)
    full = train(scene, None, cfg, out_dir=tmp_path / "full", progress=False)
    # a run stopped after 4 steps (the callback stops it; a checkpoint is written) ...
    part = train(scene, None, cfg, out_dir=tmp_path / "part", progress=False, callback=lambda step, info: step == 4)
    assert part.metrics["iterations"] == 4 and load_checkpoint(tmp_path / "part")["step"] == 4
    # ... resumed continues at step 5 and ends where the uninterrupted run ends
    resumed = train(scene, None, cfg, out_dir=tmp_path / "part", progress=False)
    assert resumed.history["iterations"] == list(range(1, 9))
    assert resumed.history["loss"] == pytest.approx(full.history["loss"], rel=1e-5)
    for a, b in zip(full.model.state_dict().values(), resumed.model.state_dict().values()):
        torch.testing.assert_close(a, b)


def test_checkpoints_at_most_every_checkpoint_seconds(scene, tmp_path, monkeypatch):
    # checkpoint_every is in steps, checkpoint_seconds spaces them in time: with a long spacing only
    # the final checkpoint is written (a checkpoint of a large grid takes about a second)
    import course_lib.nerf.run as tr

    saved = []
    real = tr.save_checkpoint
    monkeypatch.setattr(tr, "save_checkpoint", lambda *a, **k: (saved.append(a[1].step), real(*a, **k)))
    cfg = tiny_nerf_config(iters=6, checkpoint_every=2, overhead_budget=0)
    train(scene, None, cfg, out_dir=tmp_path / "every", progress=False)
    assert saved == [2, 4, 6, 6]  # every 2 steps, and the final one
    saved.clear()
    train(scene, None, replace(cfg, checkpoint_seconds=3600), out_dir=tmp_path / "spaced", progress=False)
    assert saved == [6]
    assert load_checkpoint(tmp_path / "spaced")["step"] == 6


class _Ticks:
    """A clock that moves ``tick`` seconds at every reading: time counted in the code's steps, not the machine's."""

    def __init__(self, tick: float):
        self.now, self.tick = 0.0, tick

    def perf_counter(self) -> float:
        self.now += self.tick
        return self.now


def test_time_budget_covers_the_whole_run(scene, tmp_path, monkeypatch):
    # --minutes is the budget of the run, not of training alone: setup, checkpoints, snapshots and the
    # final evaluation fit in it (training stops early enough for them). The run's clock is one that
    # ticks at every reading, so the test does not depend on the machine's speed or load.
    import course_lib.nerf.run as tr

    ticks = _Ticks(0.01)
    monkeypatch.setattr(tr, "time", ticks)
    cfg = tiny_nerf_config(iters=10**6, minutes=0.05, snapshot_every=20, checkpoint_every=50)
    res = train(scene, scene.subset([6, 7]), cfg, out_dir=tmp_path, progress=False)
    m = res.metrics
    assert m["stopped_by"] == "time" and m["train_seconds"] > 1.0
    assert m["wall_seconds"] <= 3.0 + 0.1  # the budget, and at most a few readings of the clock more
    assert m["test_psnr"] is not None and m["n_test_views"] >= 1


def test_final_evaluation_renders_every_view_that_fits(scene):
    # the final evaluation times its first view and renders all of them when they fit in its share of
    # the budget; else at least final_eval_min_views evenly spread ones (the same every time), and only a
    # mean over all views is called the test PSNR; eval_all renders them all whatever the time
    from course_lib.nerf.inference import spread_views

    assert spread_views(25, 5) == [0, 6, 12, 18, 24] and spread_views(3, 10) == [0, 1, 2]
    train4, test4 = scene.subset(range(4)), scene.subset(range(4, 8))
    cfg = tiny_nerf_config(iters=10**6, minutes=0.03)
    m = train(train4, test4, cfg, progress=False).metrics  # 16 x 16 px views: all of them fit
    assert m["test_views"] == [0, 1, 2, 3] and m["test_psnr"] == m["final_psnr"] is not None
    assert m["final_psnr_label"] == "test PSNR on all 4 test views" and m["first_view_seconds"] > 0
    squeezed = replace(cfg, final_eval_share=1e-9)
    m = train(train4, test4, squeezed, progress=False).metrics  # nothing fits: at least 8 views, here all 4
    assert m["test_views"] == [0, 1, 2, 3] and m["test_psnr"] is not None
    res = train(train4, test4, replace(squeezed, final_eval_min_views=2), progress=False)
    m = res.metrics
    assert m["test_views"] == [0, 3] and m["n_test_views_available"] == 4 and res.test_renders.shape[0] == 2
    assert m["test_psnr"] is None and m["final_psnr_label"] == "PSNR on 2 of 4 test views"
    assert m["final_psnr"] == pytest.approx(np.mean(m["final_psnr_per_view"]), abs=2e-3)
    res = train(train4, test4, replace(squeezed, final_eval_min_views=2, eval_all=True), progress=False)
    assert res.metrics["test_views"] == [0, 1, 2, 3] and res.test_renders.shape[0] == 4


def test_circular_path(scene):
    path = circular_path(scene.c2w, [0, 0, 0], n_frames=6)
    assert path.shape == (6, 4, 4)
    # every camera looks at the centre and keeps the world up (z) up in the image (camera y down)
    for M in path:
        np.testing.assert_allclose(M[:3, 2], -M[:3, 3] / np.linalg.norm(M[:3, 3]), atol=1e-9)
        assert M[2, 1] < 0


def test_cli_train_eval_and_render(scene, tmp_path, capsys):
    from course_lib.__main__ import main

    folder = tmp_path / "scene"
    u8 = (scene.images * 255).round().astype(np.uint8)
    write_blender(folder, "train", u8[:6], scene.c2w[:6], scene.camera_angle_x)
    write_blender(folder, "test", u8[6:], scene.c2w[6:], scene.camera_angle_x)
    out = tmp_path / "out"
    rc = main(["nerf", "train", str(folder), "--out", str(out), "--preset", "fast", "--iters", "5", "--quiet",
               "--threads", "1", "--samples", "16", "--batch", "128"])
    m = json.loads((out / "metrics.json").read_text())
    assert rc == 0 and m["iterations"] == 5 and m["test_views"] == [0, 1]
    # nerf eval: the PSNR of any checkpoint on every view of a split (here the same as the run's own)
    capsys.readouterr()
    assert main(["nerf", "eval", str(out), str(folder), "--out", str(tmp_path / "eval")]) == 0
    said = capsys.readouterr().out
    assert said.startswith("test PSNR on all 2 test views: ") and "checkpoint step 5" in said
    ev = json.loads((tmp_path / "eval" / "eval.json").read_text())
    assert ev["psnr"] == pytest.approx(m["test_psnr"], abs=1e-2) and sorted(ev["psnr_per_view"]) == ["test_000", "test_001"]
    assert (tmp_path / "eval" / "test_001.png").exists()
    assert main(["nerf", "eval", str(out), str(folder), "--split", "val"]) == 2  # no such split: a clear error
    assert "has no transforms_val.json" in capsys.readouterr().err
    rc = main(["nerf", "render", str(out / "checkpoint.pt"), "--out", str(tmp_path / "views"), "--frames", "3"])
    assert rc == 0 and (tmp_path / "views" / "path.gif").exists() and (tmp_path / "views" / "frame_002.png").exists()
    assert main(["nerf", "train", str(tmp_path / "nope"), "--out", str(out)]) == 2
    assert main(["nerf", "render", str(tmp_path / "nope.pt"), "--out", str(out)]) == 2



def test_cli_out_is_a_file_and_missing_device(scene, tmp_path, capsys):
    from course_lib.__main__ import main

    folder = tmp_path / "scene"
    u8 = (scene.images * 255).round().astype(np.uint8)
    write_blender(folder, "train", u8[:6], scene.c2w[:6], scene.camera_angle_x)
    a_file = tmp_path / "a_file.txt"
    a_file.write_text("not a folder")
    capsys.readouterr()
    assert main(["nerf", "train", str(folder), "--out", str(a_file), "--iters", "1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --out") and "is a file, not a folder" in err and len(err.strip().splitlines()) == 1
    out = tmp_path / "out"
    assert main(["nerf", "train", str(folder), "--out", str(out), "--iters", "2", "--quiet", "--threads", "1",
                 "--samples", "8", "--batch", "64", "--device", "cpu"]) == 0
    assert main(["nerf", "render", str(out), "--out", str(a_file), "--frames", "1"]) == 2
    assert "is a file, not a folder" in capsys.readouterr().err
    if not torch.cuda.is_available():
        assert main(["nerf", "train", str(folder), "--out", str(out), "--device", "cuda"]) == 2
        err = capsys.readouterr().err
        assert "no CUDA GPU" in err and "--device auto" in err
        assert main(["nerf", "render", str(out), "--out", str(tmp_path / "v"), "--device", "cuda"]) == 2


@pytest.mark.slow  # trains twice in a process of its own: pytest -m "not slow" leaves it out
def test_ctrl_c_saves_a_checkpoint_and_resumes(scene, tmp_path):
    import os
    import re
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    folder = tmp_path / "scene"
    u8 = (scene.images * 255).round().astype(np.uint8)
    write_blender(folder, "train", u8[:6], scene.c2w[:6], scene.camera_angle_x)
    out = tmp_path / "out"
    repo = Path(__file__).resolve().parents[2]
    cmd = [sys.executable, "-X", "faulthandler", "-m", "course_lib", "nerf", "train", str(folder), "--out", str(out),
           "--quiet", "--threads", "1", "--samples", "16", "--batch", "128", "--device", "cpu", "--checkpoint-seconds", "0"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    # Ctrl-C as in a terminal: a command started in the background of a shell (pytest under `cmd &`, as CI or
    # try-as-new-user may run it) inherits SIGINT ignored, and a Python started so keeps ignoring it
    proc = subprocess.Popen(cmd + ["--iters", "1000000"], cwd=repo, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.time() + 120
    while not (out / "checkpoint.pt").exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.2)  # the first checkpoint: training is under way
    assert (out / "checkpoint.pt").exists(), proc.communicate()
    proc.send_signal(signal.SIGINT)
    try:
        stdout, stderr = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:  # seen once under heavy load: ask faulthandler where the process is
        proc.send_signal(signal.SIGABRT)
        stdout, stderr = proc.communicate()
        pytest.fail(f"no exit 120 s after Ctrl-C; where it was:\n{stderr[-8000:]}\nstdout:\n{stdout[-2000:]}")
    assert proc.returncode == 130, (stdout, stderr)
    assert "Traceback" not in stderr, stderr
    found = re.search(r"interrupted at step (\d+); checkpoint saved; run the same command to resume", stdout)
    assert found, stdout
    n = int(found.group(1))
    assert n > 0 and load_checkpoint(out)["step"] == n
    # the same command (with a reachable total) resumes at step n
    done = subprocess.run(cmd + ["--iters", str(n + 5)], cwd=repo, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "resuming from" in done.stdout
    m = json.loads((out / "metrics.json").read_text())
    assert m["iterations"] == n + 5 and m["resumed_from"]["step"] == n
    assert m["history"]["iterations"][-6:] == list(range(n, n + 6))


@pytest.fixture
def sigint_as_in_a_terminal():
    """Python's own SIGINT handler for the test, as in a terminal: pytest started in the background of a shell
    inherits SIGINT ignored, and train() then leaves Ctrl-C alone (it defers only Python's default handler)."""
    import signal

    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


@pytest.mark.usefixtures("sigint_as_in_a_terminal")
@pytest.mark.parametrize("where", ["set_learning_rate", "train_step", "run_callbacks", "_sync", "_record", "periodic"])
def test_ctrl_c_anywhere_in_a_step_saves_a_consistent_checkpoint(scene, tmp_path, monkeypatch, where):
    # SIGINT raised (deterministically) inside the 3rd step at each point of it: the checkpoint's
    # model, optimizer, step and history must agree, and resuming must end where an uninterrupted run ends
    import signal
    from course_lib.nerf import run as run_mod, train as train_mod
    from course_lib.nerf.train import TrainingInterrupted

    owner = {"periodic": run_mod.RunOutputs, "run_callbacks": train_mod.TrainState}.get(where, train_mod)
    original, calls = getattr(owner, where), []

    def ctrl_c_after(*args, **kw):
        out = original(*args, **kw)
        calls.append(1)
        if len(calls) == 3 if where != "run_callbacks" else len(calls) == 6:  # run_callbacks: "before" and "after"
            signal.raise_signal(signal.SIGINT)
        return out

    cfg = tiny_nerf_config(iters=6, checkpoint_every=0)
    full = train(scene, None, cfg, progress=False)
    monkeypatch.setattr(owner, where, ctrl_c_after)
    with pytest.raises(TrainingInterrupted) as stopped:
        train(scene, None, cfg, out_dir=tmp_path, progress=False)
    monkeypatch.setattr(owner, where, original)
    ck = load_checkpoint(tmp_path)
    n = stopped.value.step
    assert ck["step"] == n == 3 and ck["history"]["iterations"] == [1, 2, 3]
    assert {len(v) for k, v in ck["history"].items() if not k.startswith("test_")} == {3}
    resumed = train(scene, None, cfg, out_dir=tmp_path, progress=False)
    assert resumed.history["iterations"] == list(range(1, 7))
    assert resumed.history["loss"] == pytest.approx(full.history["loss"], rel=1e-5)
    for a, b in zip(full.model.state_dict().values(), resumed.model.state_dict().values()):
        torch.testing.assert_close(a, b)


@pytest.mark.usefixtures("sigint_as_in_a_terminal")
def test_a_second_ctrl_c_inside_a_step_stops_at_once_without_a_checkpoint(scene, tmp_path, monkeypatch):
    import signal
    from course_lib.nerf import train as train_mod
    from course_lib.nerf.train import TrainingInterrupted

    original = train_mod.train_step

    def two_ctrl_c(state):
        signal.raise_signal(signal.SIGINT)  # deferred: the step goes on
        signal.raise_signal(signal.SIGINT)  # the user insists: stop here
        return original(state)

    monkeypatch.setattr(train_mod, "train_step", two_ctrl_c)
    with pytest.raises(KeyboardInterrupt) as stopped:
        train(scene, None, tiny_nerf_config(iters=6), out_dir=tmp_path, progress=False)
    assert not isinstance(stopped.value, TrainingInterrupted) and not (tmp_path / "checkpoint.pt").exists()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # train put Python's handler back


@pytest.mark.parametrize("sh", [{"grid_sh_degree": 0}, {"grid_sh_degree": 1, "grid_sh_start": 0.5},
                                {"grid_sh_degree": 1, "grid_sh_start": 0.7},
                                {"grid_sh_degree": 1, "grid_sh_start": 0.5, "grid_sparse_adam": True}],
                         ids=["rgb", "sh-before-checkpoint", "sh-after-checkpoint", "sparse-adam"])
def test_grid_resume_across_rebox_and_upsample(scene, tmp_path, sh):
    # stop after the box was shrunk (step 4) and before the upsampling (step 8): the resumed run
    # must rebuild the re-boxed grid, keep it, upsample at step 8 and end where the full run ends;
    # the same when the colour grid turns into spherical harmonics before or after the checkpoint
    cfg = preset("fast", iters=10, minutes=None, batch_rays=128, n_samples=24, snapshot_every=0, checkpoint_every=6,
                 occupancy_start=0.2, occupancy_every=2, grid_schedule=((0, 0.6), (0.4, 0.8), (0.8, 1.0)), grid_resolution=20,
                 shrink_box_at=0.4, threads=1, **sh)
    full = train(scene, None, cfg, out_dir=tmp_path / "full", progress=False)
    train(scene, None, cfg, out_dir=tmp_path / "part", progress=False, callback=lambda step, info: step == 6)
    resumed = train(scene, None, cfg, out_dir=tmp_path / "part", progress=False)
    assert resumed.model.resolution == full.model.resolution == 20
    assert resumed.bounds == full.bounds
    assert resumed.history["loss"] == pytest.approx(full.history["loss"], rel=1e-5)
    torch.testing.assert_close(resumed.model.density_grid, full.model.density_grid)
    torch.testing.assert_close(resumed.model.feature_grid, full.model.feature_grid)
    assert resumed.model.sh_degree == full.model.sh_degree == sh.get("grid_sh_degree", 0)


def test_grid_box_bounds_switch(scene):
    # box_bounds=False (notebook 09's ablation): the grid's rays are sampled between the scene's
    # near and far like the MLP's; the default samples only the stretch inside the grid's box
    from course_lib.nerf.train import ray_bounds_of

    cfg = preset("fast", grid_schedule=(), grid_resolution=12)
    bounds = scene_bounds(scene.c2w, scene.K, scene.W)
    model, _ = build_model(cfg, bounds)
    o = torch.tensor([[0.0, 0.0, 3.0]]).repeat(2, 1)
    d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    n_box, f_box = ray_bounds_of(model, cfg, bounds)(o, d)
    n_all, f_all = ray_bounds_of(model, replace(cfg, box_bounds=False), bounds)(o, d)
    assert (n_all, f_all) == (bounds["near"], bounds["far"])
    assert torch.all(n_box >= bounds["near"] - 1e-6) and torch.all(f_box <= bounds["far"] + 1e-6)
    assert torch.all(f_box - n_box < 0.9 * (f_all - n_all))
    res = train(scene, None, replace(cfg, iters=3, minutes=None, batch_rays=64, n_samples=16, box_bounds=False,
                                     snapshot_every=0, checkpoint_every=0, threads=1), progress=False)
    assert res.metrics["iterations"] == 3 and res.metrics["config"]["box_bounds"] is False

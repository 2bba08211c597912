"""One trained grid, one process: training steps (dense vs sparse Adam) against forward-only rendering.

    python benchmarks/nerf_step_vs_render.py --size 400            # the building at 400 x 400 px
    python benchmarks/nerf_step_vs_render.py --size 200 --profile  # + cProfile of a step and of a render

On a shared machine absolute times mean little, so everything here is a ratio of two things
measured in the same process, one thread, interleaved (A, B, A, B, ...) so that a change of the
machine's load hits both:

* **sparse vs dense Adam**: training steps of the same state, one with the fast preset's
  :class:`~course_lib.nerf.optim.GridAdam` and one with the dense fused Adam (each on its own copy
  of the model and optimizer state), steps/s of each;
* **render vs train**: rays/s of :func:`~course_lib.nerf.inference.render_view` (test views) and of
  training steps (``batch_rays`` per step), on the same model.

The state is the end of a short run of the fast preset (``--iters`` steps, so the schedule --
box shrink, coarse to fine, spherical harmonics, occupancy -- has gone through all its stages; the
checkpoint is kept under ``outputs/bench-step-SIZE``, git-ignored, and reused). The scene is the
embedded building rendered at SIZE x SIZE (as ``benchmarks/nerf_speed.py`` makes it).
"""

from __future__ import annotations

import argparse
import copy
import cProfile
import dataclasses
import os
import pstats
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve()
REPO = HERE.parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(HERE.parent))


def trained_state(size: int, iters: int):
    """The fast preset trained ``iters`` steps on the building at ``size`` px: ``(state, test data)``."""
    from nerf_speed import _building

    from course_lib.data.blender import load_blender
    from course_lib.nerf.presets import preset
    from course_lib.nerf.run import RunClock
    from course_lib.nerf.train import start_state, train

    data = _building(size)
    tr, te = load_blender(data, "train", dtype="uint8"), load_blender(data, "test", dtype="uint8")
    out = REPO / "outputs" / f"bench-step-{size}"
    cfg = preset("fast", iters=iters, minutes=None, threads=1, snapshot_every=0, checkpoint_every=0, grid_resolution=0)
    if not (out / "checkpoint.pt").exists():
        print(f"training {iters} steps at {size} px into {out} ...", flush=True)
        t = time.perf_counter()
        train(tr, None, cfg, out_dir=out, progress=False, device="cpu")
        print(f"  {time.perf_counter() - t:.0f} s", flush=True)
    from course_lib.nerf.presets import resolve
    from course_lib.threads import set_torch_threads

    set_torch_threads(1)
    cfg = resolve(cfg, tr.H, tr.W)
    state, _ = start_state(tr, cfg, __import__("torch").device("cpu"), RunClock.of(cfg), out / "checkpoint.pt")
    state.progress = 1.0
    return state, te


def variant(state, sparse: bool):
    """A copy of ``state`` whose grids are trained with sparse (or dense fused) Adam, moments carried over."""
    from course_lib.nerf.train import make_optimizer

    st = copy.copy(state)
    st.model = copy.deepcopy(state.model)
    st.config = dataclasses.replace(state.config, grid_sparse_adam=sparse)
    st.generator = copy.deepcopy(state.generator)
    st.optimizer = make_optimizer(st.config, st.model, None)
    st.optimizer.load_state_dict(copy.deepcopy(state.optimizer.state_dict()))
    return st


def timed(fn, *args) -> float:
    t = time.perf_counter()
    fn(*args)
    return time.perf_counter() - t


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, default=400, help="image side of the building (px)")
    p.add_argument("--iters", type=int, default=400, help="steps of the run that makes the state")
    p.add_argument("--steps", type=int, default=10, help="timed training steps per variant")
    p.add_argument("--views", type=int, default=2, help="timed test-view renders")
    p.add_argument("--profile", action="store_true", help="cProfile one step of each variant and one render")
    a = p.parse_args(argv)
    import torch

    from course_lib.nerf.inference import render_view
    from course_lib.nerf.train import train_step

    state, te = trained_state(a.size, a.iters)
    m = state.model
    print(f"load average before: {os.getloadavg()}   threads: {torch.get_num_threads()}")
    print(f"grid {m.shape} x (1 + {m.feature_dim}) channels = {m.density_grid.numel() * (1 + m.feature_dim) / 1e6:.1f} M "
          f"values, occupied {float(m.occupancy.float().mean()):.1%}, {state.config.n_samples} samples/ray, "
          f"{state.config.batch_rays} rays/step")
    runs = {"dense": variant(state, False), "sparse": variant(state, True)}
    for st in runs.values():
        train_step(st)  # warm-up (allocations, moments)
    steps = {k: [] for k in runs}
    render = []
    views = list(range(min(a.views, len(te))))
    for i in range(a.steps):
        for k, st in runs.items():
            steps[k].append(timed(train_step, st))
        if i < len(views):
            render.append(timed(render_view, state.model, None, state.config, state.bounds, te.H, te.W, te.K,
                                te.c2w[views[i]]))
    med = {k: sorted(v)[len(v) // 2] for k, v in steps.items()}
    rays = state.config.batch_rays
    r_rps = te.H * te.W / (sum(render) / len(render))
    print(f"load average after: {os.getloadavg()}")
    for k in runs:
        print(f"{k:>6} Adam: {1.0 / med[k]:.2f} steps/s, {rays / med[k]:.0f} training rays/s (median of {a.steps})")
    print(f"sparse / dense steps/s: {med['dense'] / med['sparse']:.2f}x")
    print(f"render: {r_rps:.0f} rays/s ({len(render)} views); render / train (sparse): {r_rps * med['sparse'] / rays:.2f}x, "
          f"render / train (dense): {r_rps * med['dense'] / rays:.2f}x")
    if a.profile:
        for k, st in runs.items():
            print(f"--- one training step, {k} Adam")
            pr = cProfile.Profile()
            pr.runcall(train_step, st)
            pstats.Stats(pr).sort_stats("tottime").print_stats(12)
        print("--- one render_view")
        pr = cProfile.Profile()
        pr.runcall(render_view, state.model, None, state.config, state.bounds, te.H, te.W, te.K, te.c2w[0])
        pstats.Stats(pr).sort_stats("tottime").print_stats(15)
    return 0


if __name__ == "__main__":
    sys.exit(main())

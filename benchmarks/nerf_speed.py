"""NeRF training speed: PSNR after 1, 2, 5 minutes of training for the presets, samples/s, memory.

    python benchmarks/nerf_speed.py                          # lego-100 if present, else the embedded scene
    python benchmarks/nerf_speed.py DATA_DIR --minutes 5 --presets fast paper --at 1 2 5
    python benchmarks/nerf_speed.py --building 200 --presets fast   # the embedded building rendered at 200x200
    python benchmarks/nerf_speed.py --device cuda --minutes 1 --at 0.5 1   # on a GPU

Each preset trains in its own process (so the peak memory is its own), on the scene's train split;
at each ``--at`` minute of *training* time (evaluation time excluded) it renders all test views
and records their mean PSNR. Prints a table and the machine's load average before and after (on
a shared machine, other processes slow the run down: compare numbers taken at similar load).

"outside training" is the share of the wall time not spent in training steps: setup, snapshots,
checkpoints and the final evaluation (``overhead_fraction`` in metrics.json, with the same
snapshot/checkpoint settings as ``nerf train``); the renders at the intermediate marks are the
benchmark's own and are left out of it.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path


def _one(data: str, preset_name: str, minutes: float, at: list[float], seed: int, threads: int | None,
         mark_views: int | None, device: str) -> dict:
    import torch

    from course_lib.data.blender import load_blender
    from course_lib.nerf.presets import preset
    from course_lib.nerf.train import evaluate, train

    tr = load_blender(data, "train")
    te = None
    for split in ("test", "val"):
        if (Path(data) / f"transforms_{split}.json").exists():
            te = load_blender(data, split)
            break
    import tempfile

    over = dict(minutes=minutes, seed=seed)  # snapshots and checkpoints as `nerf train` (their cost is measured)
    if threads is not None:
        over["threads"] = threads
    cfg = preset(preset_name, **over)
    marks = sorted(m * 60.0 for m in at if m < minutes)
    psnr_at: dict[str, float] = {}
    if mark_views is None:  # the MLP renders slowly on a CPU: its intermediate marks use 2 test views
        mark_views = 2 if cfg.model == "nerf" else len(te) if te is not None else 0
    views = list(range(min(mark_views, len(te)))) if te is not None else []

    def callback(step, info):
        while marks and info["seconds"] >= marks[0]:
            t = marks.pop(0)
            psnr_at[f"{t / 60:g}"] = round(evaluate(info["model"], info["model_fine"], info["config"], info["bounds"], te,
                                                    views)[0], 2)
        return False

    with tempfile.TemporaryDirectory() as out:
        res = train(tr, te, cfg, out_dir=out, progress=False, device=device,
                    callback=callback if te is not None else None)
    m = res.metrics
    psnr_at[f"{minutes:g}"] = m["test_psnr"]
    marks_s = m["overhead_breakdown"].get("callback", 0.0)
    kit_overhead = (m["overhead_seconds"] - marks_s) / max(m["wall_seconds"] - marks_s, 1e-9)
    return dict(preset=preset_name, psnr_at=psnr_at, mark_views=len(views), eval_seconds=m.get("eval_seconds"), iterations=m["iterations"], train_seconds=m["train_seconds"],
                samples_per_second=m["samples_per_second"], rays_per_second=m["rays_per_second"],
                peak_memory_mb=m["peak_memory_mb"], peak_gpu_memory_mb=m.get("peak_gpu_memory_mb"), threads=m["threads"],
                n_parameters=m["n_parameters"], torch_threads=torch.get_num_threads(), device=m["device_name"],
                wall_seconds_run=m["wall_seconds"], overhead_breakdown=m["overhead_breakdown"],
                outside_training=round(kit_overhead, 4))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", nargs="?", default=None, help="Blender scene folder (default: lego-100, else embedded)")
    p.add_argument("--minutes", type=float, default=5.0)
    p.add_argument("--at", type=float, nargs="+", default=[1, 2, 5], help="minutes at which to measure test PSNR")
    p.add_argument("--presets", nargs="+", default=["paper", "fast"])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--mark-views", type=int, default=None,
                   help="test views rendered at the intermediate marks (default: all; 2 for the MLP preset)")
    p.add_argument("--device", default="auto", help="auto (CUDA, then MPS, then CPU), cpu, cuda or mps")
    p.add_argument("--building", type=int, default=None, metavar="SIZE",
                   help="train on the embedded building rendered at SIZE x SIZE (made once under outputs/)")
    p.add_argument("--json", default=None, help="also write the results here")
    p.add_argument("--_one", default=None, help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.building is not None and not a._one:
        from course_lib.data.building import make_nerf_dataset
        from course_lib.paths import REPO_ROOT

        folder = REPO_ROOT / "outputs" / f"bench-building-{a.building}"
        if not (folder / "transforms_test.json").exists():
            print(f"rendering the building at {a.building}x{a.building} into {folder} ...", flush=True)
            make_nerf_dataset(folder, size=a.building, splits=("train", "test"))
        a.data = str(folder)
    if a.data is None:
        from course_lib.paths import EMBEDDED_NERF, course_data

        a.data = str(course_data("lego") or EMBEDDED_NERF)
    if a._one:
        print("RESULT " + json.dumps(_one(a.data, a._one, a.minutes, a.at, a.seed, a.threads, a.mark_views, a.device)))
        return 0
    rows = []
    for name in a.presets:
        load0 = os.getloadavg()
        t0 = time.time()
        cmd = [sys.executable, __file__, a.data, "--minutes", str(a.minutes), "--seed", str(a.seed), "--_one", name,
               "--at", *map(str, a.at), "--device", a.device] + (["--threads", str(a.threads)] if a.threads is not None else []) \
            + (["--mark-views", str(a.mark_views)] if a.mark_views is not None else [])
        out = subprocess.run(cmd, capture_output=True, text=True)
        line = next((ln for ln in out.stdout.splitlines() if ln.startswith("RESULT ")), None)
        if line is None:
            print(out.stdout, out.stderr, file=sys.stderr)
            return 1
        r = json.loads(line[7:])
        r.update(load_before=[round(x, 2) for x in load0], load_after=[round(x, 2) for x in os.getloadavg()],
                 wall_seconds=round(time.time() - t0, 1))
        rows.append(r)
    marks = [f"{m:g}" for m in a.at if m <= a.minutes]
    if f"{a.minutes:g}" not in marks:
        marks.append(f"{a.minutes:g}")
    views = ", ".join("{}: {}".format(r["preset"], r["mark_views"]) for r in rows)
    print(f"data: {a.data}   cores: {os.cpu_count()}   device: {rows[0]['device']}")
    print(f"PSNR = mean over the test views: all of them at the end, at earlier marks the first N ({views})")
    head = ["preset"] + [f"PSNR@{m}min" for m in marks] + ["iters", "samples/s", "rays/s", "peak MB", "GPU MB",
                                                          "outside training", "threads", "load 1-min before/after"]
    print(" | ".join(head))
    for r in rows:
        cells = [r["preset"]] + [f"{r['psnr_at'].get(m, float('nan')):.2f}" for m in marks]
        cells += [str(r["iterations"]), f"{r['samples_per_second']:.0f}", f"{r['rays_per_second']:.0f}",
                  f"{r['peak_memory_mb']:.0f}", f"{r['peak_gpu_memory_mb']:.0f}" if r["peak_gpu_memory_mb"] else "-",
                  f"{100 * r['outside_training']:.1f} %", str(r["torch_threads"]), f"{r['load_before'][0]}/{r['load_after'][0]}"]
        print(" | ".join(cells))
    if a.json:
        Path(a.json).write_text(json.dumps({"data": a.data, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

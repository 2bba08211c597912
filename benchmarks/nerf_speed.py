"""NeRF speed and quality by image resolution: the "fast" preset's ladder, on the scene family and lego-100.

    python benchmarks/nerf_speed.py --ladder                       # the family at 200, 400, 800 px, and lego-100
    python benchmarks/nerf_speed.py --scenes family --sizes 100 --budget-scale 0.3 --lego   # quick: 1.5 min rungs
    python benchmarks/nerf_speed.py --scene excavator --sizes 400  # one rung of the held-out excavator
    python benchmarks/nerf_speed.py --ladder --baseline-tree /tmp/nerf-base    # + another checkout at 400 px
    python benchmarks/nerf_speed.py --sizes 400 --minutes 0.3 --at 0.1 0.2     # a smoke test
    python benchmarks/nerf_speed.py DATA_DIR --minutes 5 --presets fast paper  # any Blender scene
    python benchmarks/nerf_speed.py --ladder --device cuda                     # on a GPU

Rungs: the family (``--scene family`` or some of ``bricks plant crates gloss figurine``, the five
scenes of :mod:`course_lib.data.family` that the presets' rules are chosen on: 75 training and
25 test views, rendered once at the run's largest size and written at every size that divides it,
under ``outputs/bench-family-rTOP/``, git-ignored; bricks at 800 px takes the longest, ~45 minutes
of one core), ``--scene building`` (the embedded building, rendered at SIZE x SIZE: 100 training
views, 25 test views on a ring; under ``outputs/bench-building-SIZE-t25``), ``--scene excavator``
(:mod:`course_lib.data.excavator`: rendered once at 800 px, 100 training and 25 test views, under
``outputs/bench-excavator/``) and, with ``--lego`` (part of ``--ladder``), lego-100 from the course
data (``../shared/data/nerf-lego-100``, read in place). A rung of SIZE px runs ``--minutes``
(default 5), except where ``--minutes-at`` says otherwise (default ``800=10``: the 800 px rung
runs 10 minutes), times ``--budget-scale``. The family's median and worst per rung close the
report (and ``--table``'s).

Each run is ``nerf train``'s: one process per run (so the peak memory is its own), the data
loaded as the CLI loads it, ``--minutes`` as the CLI passes it, snapshots and checkpoints as the
preset has them. Reported per run:

* PSNR at the ``--at`` marks (minutes of the run's budget clock: wall time for this tree, whose
  ``--minutes`` covers the whole run; training time for a baseline whose ``--minutes`` counts
  training only), on ``--mark-views`` evenly spread test views, rendered by the benchmark (its
  time is left out of everything);
* PSNR at the end on **all** test views (rendered by the benchmark after the run when the run
  itself evaluated a subset), and the run's own final PSNR with the number of views it used;
* steps, training rays/s, rendering rays/s of the run's final evaluation (and their ratio);
* "outside training": the share of the run's wall time (loading included) not spent in training
  steps, the benchmark's own renders left out; the run's wall time against its ``--minutes``;
  the peak memory (RSS, MB).

``--json FILE`` saves the rows after each run (``--append``: add them to the rows already in
FILE, so that rungs run one at a time -- each in its own quiet slot -- make one table; ``--table
FILE`` prints such a file's table).
``--baseline-tree PATH`` runs the same rungs (``--baseline-at``, default 400) with the
``course_lib`` of another checkout, e.g. today's main: ``git worktree add /tmp/nerf-base e138692``.
The load average before and after each run is printed: compare numbers taken at similar load.
"""

from __future__ import annotations

import argparse
import ast
import inspect
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve()
REPO = HERE.parents[1]


def _psnr_all(evaluate, model, fine, cfg, bounds, te, views) -> float:
    """Mean PSNR over ``views`` with the tree's own ``evaluate``."""
    return round(evaluate(model, fine, cfg, bounds, te, views)[0], 2)


def _spread(n: int, k: int) -> list[int]:
    k = max(1, min(k, n))
    return sorted({round(i * (n - 1) / max(k - 1, 1)) for i in range(k)}) if k < n else list(range(n))


def _one(data: str, preset_name: str, minutes: float, at: list[float], seed: int, threads, mark_views: int,
         device: str, sets: dict | None = None) -> dict:
    """One run, in this process, with whatever ``course_lib`` is first on the path."""
    t_start = time.perf_counter()
    from course_lib.data.blender import load_blender
    from course_lib.nerf.presets import preset
    from course_lib.nerf.train import train

    try:
        from course_lib.nerf.inference import evaluate
    except ImportError:  # an older tree
        from course_lib.nerf.train import evaluate

    kw = {"dtype": "uint8"} if "dtype" in inspect.signature(load_blender).parameters else {}
    tr = load_blender(data, "train", **kw)
    te = next((load_blender(data, s, **kw) for s in ("test", "val") if (Path(data) / f"transforms_{s}.json").exists()), None)
    load_s = time.perf_counter() - t_start
    over = dict(minutes=minutes, seed=seed)
    if threads is not None:
        over["threads"] = threads
    cfg = preset(preset_name, **over, **(sets or {}))
    whole_run = "started_at" in inspect.signature(train).parameters  # --minutes covers the whole run
    marks = sorted(m * 60.0 for m in at if m < minutes)
    views = _spread(len(te), mark_views) if te is not None else []
    psnr_at: dict[str, float] = {}

    def callback(step, info):
        clock = info.get("wall_seconds", info["seconds"]) if whole_run else info["seconds"]
        while marks and clock >= marks[0]:
            psnr_at[f"{marks.pop(0) / 60:g}"] = _psnr_all(evaluate, info["model"], info["model_fine"], info["config"],
                                                          info["bounds"], te, views)
        return False

    extra = {"started_at": t_start} if whole_run else {}
    with tempfile.TemporaryDirectory() as out:
        res = train(tr, te, cfg, out_dir=out, progress=False, device=device, callback=callback if te is not None else None,
                    **extra)
    m = res.metrics
    n_eval = m.get("n_test_views", len(te) if te is not None else 0)
    run_psnr = m.get("final_psnr", m["test_psnr"])
    final_all = run_psnr
    if te is not None and n_eval < len(te):  # the run evaluated a subset: the benchmark renders them all
        final_all = _psnr_all(evaluate, res.model, res.model_fine, res.config, res.bounds, te, None)
    psnr_at[f"{minutes:g}"] = final_all
    cb = m["overhead_breakdown"].get("callback", 0.0)
    wall = m["wall_seconds"] + (0.0 if whole_run else load_s)
    outside = (wall - cb - (m["wall_seconds"] - m["overhead_seconds"])) / max(wall - cb, 1e-9)
    render_rps = m.get("render_rays_per_second") or (
        n_eval * te.H * te.W / m["eval_seconds"] if te is not None and m.get("eval_seconds") else None)
    return dict(preset=preset_name, psnr_at=psnr_at, run_psnr=run_psnr, run_views=n_eval, minutes=minutes,
                n_test=len(te) if te is not None else 0, mark_views=len(views), iterations=m["iterations"],
                train_seconds=m["train_seconds"], rays_per_second=m["rays_per_second"], render_rays_per_second=render_rps,
                peak_memory_mb=m["peak_memory_mb"], peak_gpu_memory_mb=m.get("peak_gpu_memory_mb"),
                threads=m["threads"], device=m["device_name"], wall_seconds=round(wall - cb, 1),
                outside_training=round(outside, 4), breakdown=m["overhead_breakdown"], load_seconds=round(load_s, 2),
                grid_resolution=m["config"].get("grid_resolution"), n_samples=m["config"].get("n_samples"),
                batch_rays=m["config"].get("batch_rays"), batch_changes=m.get("history", {}).get("batch_changes"),
                box=[m["bounds"].get(k) for k in ("box_min", "box_max")] if "bounds" in m else None,
                image_size=m["image_size"])


def _building(size: int) -> str:
    from course_lib.data.building import make_nerf_dataset

    folder = REPO / "outputs" / f"bench-building-{size}-t25"
    if not (folder / "transforms_test.json").exists():
        print(f"rendering the building at {size}x{size} into {folder} ...", flush=True)
        make_nerf_dataset(folder, size=size, n_test=25, splits=("train", "test"))
    return str(folder)


def _excavator(size: int) -> str:
    from course_lib.data.excavator import make_excavator_datasets

    root = REPO / "outputs" / "bench-excavator"
    folder = root / f"excavator-{size}"
    if not (folder / "transforms_test.json").exists():
        print(f"rendering the excavator at 800 px into {root} (every size of the ladder) ...", flush=True)
        sizes = {100, 200, 400, 800} | ({size} if 800 % size == 0 else set())
        if 800 % size:
            raise SystemExit(f"the excavator comes in sizes that divide 800 px, not {size}")
        make_excavator_datasets(root, sizes=sorted(sizes), verbose=True)
    return str(folder)


def _family(name: str):
    """The rung maker of the family scene ``name``: rendered once at the ladder's largest size (``_family.top``)."""

    def make(size: int) -> str:
        from course_lib.data.family import make_family_datasets

        top = max(_family.top, size)
        if top % size:
            raise SystemExit(f"the family is rendered at {top} px this run: its sizes divide {top}, {size} does not")
        root = REPO / "outputs" / f"bench-family-r{top}"
        folder = root / f"{name}-{size}"
        if not (folder / "transforms_test.json").exists():
            sizes = sorted({s for s in (100, 200, 400, 800, size) if s <= top and top % s == 0})
            print(f"rendering {name} at {top} px into {root} (sizes {sizes}) ...", flush=True)
            make_family_datasets(root, names=[name], sizes=sizes, verbose=False)
        return str(folder)

    return make


_family.top = 800  # set by main() to the largest size of the run's rungs

#: the family of :mod:`course_lib.data.family` (the presets' rules are chosen on its median and worst)
FAMILY_NAMES = ("bricks", "plant", "crates", "gloss", "figurine")
SCENES = {"building": _building, "excavator": _excavator, **{n: _family(n) for n in FAMILY_NAMES}}


def _minutes_at(a, size: int) -> float:
    """The budget of a rung of ``size`` px: ``--minutes`` or ``--minutes-at``, times ``--budget-scale``."""
    minutes = a.minutes
    for spec in a.minutes_at:
        at, _, m = spec.partition("=")
        if int(at) == size:
            minutes = float(m)
    return round(minutes * a.budget_scale, 4)


def _summary(rows: list[dict]) -> None:
    """The family's median and worst per rung (size, budget, tree): PSNR, render/train, outside training, memory."""
    import statistics

    rungs: dict[tuple, list[dict]] = {}
    for r in rows:
        name, _, size = r["scene"].rpartition("-")
        if name in FAMILY_NAMES:
            rungs.setdefault((int(size), r.get("minutes"), r["tree"], r["preset"]), []).append(r)
    if not rungs:
        return
    print("\nfamily per rung | scenes | PSNR median | PSNR worst (scene) | steps median | render/train median / worst | "
          "outside training median / worst | peak MB worst")
    print(" | ".join("---" for _ in range(8)))
    for (size, minutes, tree, preset), rs in sorted(rungs.items(), key=lambda kv: (kv[0][0], kv[0][1] or 0)):
        psnr = [r["psnr_at"][f"{r['minutes']:g}"] for r in rs]
        ratio = [r["render_rays_per_second"] / r["rays_per_second"] for r in rs
                 if r["render_rays_per_second"] and r["rays_per_second"]]
        worst = min(rs, key=lambda r: r["psnr_at"][f"{r['minutes']:g}"])
        out = [100 * r["outside_training"] for r in rs]
        print(f"{size} px, {minutes:g} min, {tree}, {preset} | {len(rs)} | {statistics.median(psnr):.2f} | "
              f"{min(psnr):.2f} ({worst['scene']}) | {statistics.median([r['iterations'] for r in rs]):.0f} | "
              + (f"{statistics.median(ratio):.1f}x / {min(ratio):.1f}x | " if ratio else "- | ")
              + f"{statistics.median(out):.1f} % / {max(out):.1f} % | {max(r['peak_memory_mb'] for r in rs):.0f}", flush=True)


def _run(tree: Path, data: str, name: str, a, minutes: float) -> dict | None:
    """One run in its own process, importing ``course_lib`` from ``tree``."""
    cmd = [sys.executable, str(HERE), data, "--minutes", str(minutes), "--seed", str(a.seed), "--_one", name,
           "--at", *map(str, a.at), "--device", a.device, "--mark-views", str(a.mark_views)]
    cmd += ["--threads", str(a.threads)] if a.threads is not None else []
    cmd += [x for kv in a.set for x in ("--set", kv)]
    if a.budget_scale < 1 and not any(kv.startswith("final_eval_min_views=") for kv in a.set):
        cmd += ["--set", "final_eval_min_views=1"]  # the benchmark renders every test view after the run anyway
    env = {**os.environ, "PYTHONPATH": str(tree)}
    load0 = os.getloadavg()[0]
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=str(tree))
    line = next((ln for ln in out.stdout.splitlines() if ln.startswith("RESULT ")), None)
    if line is None:
        print(f"run failed ({tree}, {data}, {name}):\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}", file=sys.stderr)
        return None
    r = json.loads(line[7:])
    r.update(load=f"{load0:.1f}/{os.getloadavg()[0]:.1f}")
    return r


def _head(marks: list[str]) -> None:
    head = (["scene", "tree", "preset", "min"] + [f"PSNR@{m}" for m in marks]
            + ["PSNR all views", "run PSNR (views)", "steps", "train rays/s", "render rays/s", "render/train",
               "outside training", "wall s / budget", "peak MB", "grid/samples/batch", "load 1-min"])
    print(" | ".join(head))
    print(" | ".join("---" for _ in head), flush=True)


def _table(rows: list[dict], marks: list[str], head: bool = True) -> None:
    if head:
        _head(marks)
    for r in rows:
        ratio = (r["render_rays_per_second"] / r["rays_per_second"] if r["render_rays_per_second"] and r["rays_per_second"]
                 else float("nan"))
        minutes = r.get("minutes")
        final = r["psnr_at"].get(f"{minutes:g}") if minutes is not None else None
        cells = [r["scene"], r["tree"], r["preset"], f"{minutes:g}" if minutes is not None else "?"] + [
            f"{r['psnr_at'][m]:.2f}" if r["psnr_at"].get(m) is not None else "-" for m in marks]
        cells += [f"{final:.2f}" if final is not None else "-",
                  f"{r['run_psnr']:.2f} ({r['run_views']}/{r['n_test']})" if r["run_psnr"] is not None else "-",
                  str(r["iterations"]), f"{r['rays_per_second']:.0f}",
                  f"{r['render_rays_per_second']:.0f}" if r["render_rays_per_second"] else "-", f"{ratio:.1f}x",
                  f"{100 * r['outside_training']:.1f} %",
                  f"{r['wall_seconds']:.0f} / {60 * minutes:.0f}" if minutes is not None else f"{r['wall_seconds']:.0f}",
                  f"{r['peak_memory_mb']:.0f}", f"{r['grid_resolution']}/{r['n_samples']}/{r.get('batch_rays', '?')}", r["load"]]
        print(" | ".join(cells), flush=True)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", nargs="?", default=None, help="a Blender scene folder (instead of the ladder's rungs)")
    p.add_argument("--ladder", action="store_true",
                   help="every --scene (default: the family) at 200, 400 and 800 px, and lego-100")
    p.add_argument("--scene", "--scenes", nargs="+", choices=sorted(SCENES) + ["family"], default=None,
                   help="the rungs' scenes ('family': the five of course_lib.data.family; default: the family with "
                        "--ladder, else building)")
    p.add_argument("--sizes", type=int, nargs="+", default=None, metavar="SIZE", help="rungs (pixels)")
    p.add_argument("--lego", action="store_true", help="also lego-100 from the course data")
    p.add_argument("--minutes", type=float, default=5.0, help="each run's --minutes (default 5)")
    p.add_argument("--minutes-at", nargs="*", default=["800=10"], metavar="SIZE=MINUTES",
                   help="other budgets for some sizes (default 800=10)")
    p.add_argument("--budget-scale", type=float, default=1.0,
                   help="multiply every rung's budget (e.g. 0.3: a quick comparison of rules on the whole family); "
                        "below 1 the runs evaluate as few test views as their budget share allows, at least one "
                        "(final_eval_min_views=1; at 1.5 minutes, 8 views at 200 px took a third of the run)")
    p.add_argument("--at", type=float, nargs="+", default=[1, 2], help="minutes at which to measure PSNR (default 1 2)")
    p.add_argument("--presets", nargs="+", default=["fast"])
    p.add_argument("--baseline-tree", default=None, type=Path,
                   help="another checkout whose course_lib runs the same rungs (e.g. a worktree of e138692)")
    p.add_argument("--baseline-at", type=int, nargs="+", default=[400], metavar="SIZE",
                   help="rungs the baseline runs (default 400; 0: every rung, lego included)")
    p.add_argument("--mark-views", type=int, default=5, help="test views rendered at the --at marks (default 5)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=os.cpu_count(),
                   help="torch threads of every run (default: all cores; -1: the kit's automatic choice, which "
                        "depends on the load when a run starts)")
    p.add_argument("--device", default="auto", help="auto (CUDA, then MPS, then CPU), cpu, cuda or mps")
    p.add_argument("--json", default=None, help="also write the results here")
    p.add_argument("--append", action="store_true", help="add the rows to those already in --json")
    p.add_argument("--table", default=None, metavar="JSON", help="print the table of a --json file and stop")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="override a TrainConfig field of every run (a Python literal), e.g. --set batch_rays=4096")
    p.add_argument("--_one", default=None, help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    sets = {k: ast.literal_eval(v) for k, _, v in (kv.partition("=") for kv in a.set)}
    if a._one:
        print("RESULT " + json.dumps(_one(a.data, a._one, a.minutes, a.at, a.seed, a.threads, a.mark_views, a.device,
                                          sets)))
        return 0
    marks = [f"{m:g}" for m in a.at]
    if a.table:
        rows = json.loads(Path(a.table).read_text())["rows"]
        _table(rows, marks)
        _summary(rows)
        return 0
    sys.path.insert(0, str(REPO))
    from course_lib.paths import course_data

    sizes = a.sizes or ([200, 400, 800] if a.ladder else [])
    names = a.scene or (["family"] if a.ladder else ["building"])
    names = [n for name in names for n in (FAMILY_NAMES if name == "family" else [name])]
    _family.top = max(sizes, default=100)
    scenes = [(f"{name}-{s}", SCENES[name](s), s, s) for name in names for s in sizes]
    if a.lego or a.ladder:
        lego = course_data("lego")
        if lego is None:
            print("lego-100 is not in the course data (../shared/data): its rung is skipped", file=sys.stderr)
        else:
            scenes.append(("lego-100", str(lego), "lego", 100))  # runs --minutes (times --budget-scale)
    scenes = [sc[:4] for sc in sorted(scenes, key=lambda sc: sc[3])]  # smallest first: the longest rung runs last
    if a.data:
        scenes.append((Path(a.data).name, a.data, "data", 0))
    if not scenes:
        p.error("nothing to run: pass --ladder, --sizes, --lego or a DATA folder")
    rows: list[dict] = []
    earlier = json.loads(Path(a.json).read_text())["rows"] if a.append and a.json and Path(a.json).exists() else []

    def save() -> None:  # after every run, so an interrupted ladder keeps the rungs it finished
        if a.json:
            Path(a.json).write_text(json.dumps({"rows": earlier + rows}, indent=1))

    for scene, folder, key, size in scenes:
        minutes = _minutes_at(a, size)
        trees = [("this", REPO)]
        if a.baseline_tree and (0 in a.baseline_at or key in a.baseline_at):
            trees.append(("baseline", a.baseline_tree.resolve()))
        for tree_name, tree in trees:
            for name in a.presets:
                print(f"{scene}: {tree_name} tree, preset {name}, {minutes:g} min ...", flush=True)
                r = _run(tree, folder, name, a, minutes)
                if r is not None:
                    rows.append({"scene": scene, "tree": tree_name + "".join(f" {k}={v}" for k, v in sets.items()), **r})
                    _table(rows[-1:], marks, head=len(rows) == 1)
                    save()
    print(f"\ncores: {os.cpu_count()}   device: {rows[0]['device'] if rows else '?'}")
    print(f"PSNR@m = mean test PSNR at m minutes of the budget clock on {a.mark_views} evenly spread test views; "
          "'PSNR all views' = at the end, on every test view. 'run PSNR' = the run's own final figure (views it evaluated).")
    _table(earlier + rows, marks)
    _summary(earlier + rows)
    return 0 if rows else 1


if __name__ == "__main__":
    sys.exit(main())

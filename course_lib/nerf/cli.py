"""``python -m course_lib nerf train|render``: train a NeRF on a Blender scene, render novel views.

Examples::

    python -m course_lib nerf train --out outputs/nerf-fast --minutes 5 --preset fast
    python -m course_lib nerf train ../shared/data/nerf-lego-100 --out outputs/lego-paper --minutes 5 --preset paper
    python -m course_lib nerf render outputs/nerf-fast/checkpoint.pt --out outputs/nerf-fast/path
    python -m course_lib nerf train --device cuda --minutes 1 --out outputs/nerf-gpu     # an NVIDIA GPU

``train`` writes ``OUT/metrics.json`` (test PSNR, iterations, seconds, preset, loss/PSNR history),
``OUT/test/<view>.png`` (renders of the evaluated test views), ``OUT/snapshots/step_XXXXXX.png`` (the held-out
view during training, a preview at most 400 px on its longest side) and ``OUT/checkpoint.pt``; run it again with the same ``--out`` to resume
(``--minutes`` and ``--iters`` are totals). ``render`` writes ``OUT/path.gif`` and
``OUT/frame_XXX.png`` along a circle around the scene.

``--minutes`` is the budget of the whole run: loading the images, training, snapshots, checkpoints
and the final evaluation. Everything outside training stays below 10 % of it: loading, snapshots and
checkpoints within 5 % of the training time (a due snapshot waits while it would not fit; the fast
preset checkpoints at most once a minute, so a crash loses about a minute), and the
final evaluation renders the test views that fit in 3 % of the budget: all of them when they fit,
else a fixed, evenly spread subset (the summary says how many; ``--eval-all`` renders all of them,
whatever the time). Renders (evaluation, snapshots, ``render``) run forward
only, with empty-space skipping and early ray termination (:mod:`course_lib.nerf.inference`).

``--device auto`` (the default) trains and renders on a CUDA GPU if there is one, else on an Apple
GPU (MPS), else on the CPU, and says which; a checkpoint written on one device loads on any other.
Ctrl-C during ``train`` saves a checkpoint and says how to resume (exit status 130).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from course_lib.nerf.device import DEVICE_CHOICES
from course_lib.paths import EMBEDDED_NERF
from course_lib.validate import KitInputError, output_dir

DEVICE_HELP = "cpu, cuda (NVIDIA GPU), mps (Apple GPU) or auto: CUDA, then MPS, then the CPU (default: auto)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="nerf_command", metavar="{train,render}")
    t = sub.add_parser("train", help="train on a Blender-format scene (default: the embedded scene)")
    t.add_argument("data", nargs="?", default=None,
                   help=f"scene folder with transforms_train.json (default: {EMBEDDED_NERF})")
    t.add_argument("--out", required=True, help="output folder (metrics.json, test/, snapshots/, checkpoint.pt)")
    t.add_argument("--preset", choices=["paper", "fast"], default="fast", help="training preset (default: fast)")
    t.add_argument("--minutes", type=float, default=None,
                   help="time budget of the whole run in minutes: loading, training, final evaluation "
                        "(total, resumes count; default 5 without --iters)")
    t.add_argument("--iters", type=int, default=None, help="maximum number of steps (total)")
    t.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    t.add_argument("--downscale", type=int, default=1, help="shrink the images by this integer factor")
    t.add_argument("--batch", type=int, default=None, help="rays per step (preset default otherwise)")
    t.add_argument("--samples", type=int, default=None,
                   help="coarse samples per ray (default: the preset's; fast: from the grid resolution)")
    t.add_argument("--grid-resolution", type=int, default=None,
                   help="final voxels along the box's longest side (fast preset; default: from the image size)")
    t.add_argument("--importance", type=int, default=None, help="fine samples per ray (hierarchical sampling)")
    t.add_argument("--fine", action="store_true", help="train a separate fine network (paper preset)")
    t.add_argument("--near", type=float, default=None, help="near bound of the rays (default: from the cameras)")
    t.add_argument("--far", type=float, default=None, help="far bound of the rays (default: from the cameras)")
    t.add_argument("--device", default="auto", metavar="{" + ",".join(DEVICE_CHOICES) + "}", help=DEVICE_HELP)
    t.add_argument("--threads", type=int, default=None, help="torch threads (-1: auto, 1 on a busy machine)")
    t.add_argument("--snapshot-every", type=int, default=None, help="render the held-out view every N steps")
    t.add_argument("--checkpoint-seconds", type=float, default=None,
                   help="at most one checkpoint per this many seconds of the run (fast preset: 60; 0: no limit)")
    t.add_argument("--black-background", action="store_true", help="composite RGBA onto black instead of white")
    t.add_argument("--eval-all", action="store_true",
                   help="evaluate all test views at the end, even where they do not fit in --minutes")
    t.add_argument("--sparse-adam", action="store_true",
                   help="fast preset: Adam only on the voxels each step read (lazy Adam; see course_lib/nerf/optim.py)")
    t.add_argument("--gif", action="store_true", help="also render novel views along a circle (OUT/path.gif)")
    t.add_argument("--no-resume", action="store_true", help="ignore an existing checkpoint in --out")
    t.add_argument("--quiet", action="store_true", help="no progress bar")
    r = sub.add_parser("render", help="render novel views along a circle from a checkpoint (GIF + PNGs)")
    r.add_argument("checkpoint", help="checkpoint.pt written by `nerf train` (or its output folder)")
    r.add_argument("--out", required=True, help="output folder for path.gif and frame_XXX.png")
    r.add_argument("--frames", type=int, default=40, help="number of views on the circle (default 40)")
    r.add_argument("--elevation", type=float, default=None, help="elevation in degrees (default: the training cameras')")
    r.add_argument("--fps", type=float, default=12.0, help="GIF frames per second")
    r.add_argument("--device", default="auto", metavar="{" + ",".join(DEVICE_CHOICES) + "}", help=DEVICE_HELP)
    parser.set_defaults(_parser=parser)


def _load_scene(folder, downscale: int, white: bool, dtype: str = "uint8"):
    from course_lib.data.blender import load_blender

    folder = Path(folder)
    if not folder.exists():
        raise KitInputError(f"scene folder {folder} not found (expected a folder with transforms_train.json)")
    if not (folder / "transforms_train.json").exists():
        raise KitInputError(f"{folder} has no transforms_train.json: is it a NeRF Blender scene folder?")
    train_data = load_blender(folder, "train", downscale=downscale, white_background=white, dtype=dtype)
    test_data = None
    for split in ("test", "val"):
        if (folder / f"transforms_{split}.json").exists():
            test_data = load_blender(folder, split, downscale=downscale, white_background=white, dtype=dtype)
            break
    return train_data, test_data


def _train(args) -> int:
    from course_lib.nerf.device import device_name, pick_device
    from course_lib.nerf.presets import preset
    from course_lib.nerf.inference import circular_path, render_path, save_gif
    from course_lib.nerf.train import CHECKPOINT, TrainingInterrupted, train

    started_at = time.perf_counter()  # --minutes covers the loading too
    device = pick_device(args.device)
    data = Path(args.data) if args.data else EMBEDDED_NERF
    if args.data is None and not (data / "transforms_train.json").exists():
        raise KitInputError(f"the embedded NeRF scene {data} is not there (run `python -m course_lib make-data`) "
                            "or pass a scene folder, e.g. ../shared/data/nerf-lego-100")
    train_data, test_data = _load_scene(data, args.downscale, not args.black_background)
    out = output_dir(args.out)
    over = {"seed": args.seed, "white_background": not args.black_background}
    if args.minutes is not None:
        if args.minutes <= 0:
            raise KitInputError(f"--minutes {args.minutes}: expected a positive number")
        over["minutes"] = args.minutes
    if args.iters is not None:
        over["iters"] = args.iters
    for name, key in (("batch", "batch_rays"), ("samples", "n_samples"), ("importance", "n_importance"),
                      ("near", "near"), ("far", "far"), ("threads", "threads"), ("snapshot_every", "snapshot_every"),
                      ("grid_resolution", "grid_resolution"), ("checkpoint_seconds", "checkpoint_seconds")):
        v = getattr(args, name)
        if v is not None:
            over[key] = v
    if args.eval_all:
        over["eval_all"] = True
    if args.sparse_adam:
        over["grid_sparse_adam"] = True
    if args.fine:
        over["fine"] = True
        over.setdefault("n_importance", 128)
    if args.minutes is None and args.iters is None:
        over["minutes"] = 5.0
    cfg = preset(args.preset, **over)
    if device.type == "cpu":
        from course_lib.threads import set_torch_threads

        set_torch_threads(cfg.threads)
    budget = f"{cfg.minutes:g} min" if cfg.minutes else f"{cfg.iters} steps"
    print(f"training {cfg.preset} on {data} ({len(train_data)} views {train_data.W}x{train_data.H}, "
          f"{len(test_data) if test_data else 0} test views) for {budget} on {device_name(device)} -> {out}")
    if not args.no_resume and (out / CHECKPOINT).exists():
        print(f"resuming from {out / CHECKPOINT} (--no-resume starts afresh)")
    try:
        res = train(train_data, test_data, cfg, out_dir=out, resume=not args.no_resume, progress=not args.quiet,
                    device=device, started_at=started_at)
    except TrainingInterrupted as exc:
        print(f"\ninterrupted at step {exc.step}; checkpoint saved; run the same command to resume", flush=True)
        return 130
    except KeyboardInterrupt:
        print("\ninterrupted before training started; nothing saved", flush=True)
        return 130
    m = res.metrics
    tp = f"{m['test_psnr']:.2f} dB" if m.get("test_psnr") is not None else "n/a (no test split)"
    if m.get("test_psnr") is not None and m["n_test_views"] < m["n_test_views_available"]:
        tp += (f" on {m['n_test_views']} of {m['n_test_views_available']} test views (an evenly spread subset: "
               "all of them do not fit in --minutes; --eval-all renders every one)")
    print(f"{m['iterations']} steps in {m['train_seconds']:.0f} s of training on {m['device']} ({m['stopped_by']}), "
          f"{m['wall_seconds']:.0f} s wall ({100 * m['overhead_fraction']:.0f} % outside training); test PSNR {tp}; "
          f"metrics: {out / 'metrics.json'}")
    if args.gif:
        path = circular_path(train_data.c2w, res.bounds.center, n_frames=40)
        frames = render_path(res.model, res.model_fine, res.config, res.bounds, train_data.H, train_data.W,
                             train_data.K, path, progress=not args.quiet)
        print(f"novel views: {save_gif(out / 'path.gif', frames)}")
    return 0


def _render(args) -> int:
    from course_lib.nerf.device import device_name, pick_device
    from course_lib.nerf.checkpoint import load_checkpoint
    from course_lib.nerf.inference import circular_path, render_path, save_gif, save_png

    device = pick_device(args.device)
    ck = load_checkpoint(args.checkpoint, device)
    out = output_dir(args.out)
    cam = ck.get("camera")
    if cam is None:
        raise KitInputError(f"{args.checkpoint} has no camera information (written by an older version): retrain")
    import numpy as np

    c2w_train = np.asarray(cam["c2w"], dtype=float)
    K = np.asarray(cam["K"], dtype=float)
    if args.frames < 1:
        raise KitInputError(f"--frames {args.frames}: expected at least 1")
    path = circular_path(c2w_train, ck["bounds"].center, n_frames=args.frames, elevation_deg=args.elevation)
    frames = render_path(ck["model"], ck["model_fine"], ck["cfg"], ck["bounds"], cam["H"], cam["W"], K, path, progress=True)
    for i, f in enumerate(frames):
        save_png(out / f"frame_{i:03d}.png", f)
    gif = save_gif(out / "path.gif", frames, fps=args.fps)
    (out / "path.json").write_text(json.dumps({"checkpoint": str(args.checkpoint), "K": K.tolist(), "H": cam["H"],
                                               "W": cam["W"], "c2w": path.tolist()}))
    print(f"{len(frames)} views of step {ck['step']} (trained on {ck.get('device') or 'cpu'}, rendered on "
          f"{device_name(device)}): {gif} and {out}/frame_*.png")
    return 0


def run(args) -> int:
    if getattr(args, "nerf_command", None) is None:
        args._parser.print_help()
        return 0
    if args.nerf_command == "train":
        return _train(args)
    return _render(args)

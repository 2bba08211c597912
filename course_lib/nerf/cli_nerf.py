"""``python -m course_lib nerf train|eval|render``: train a NeRF on a Blender scene, measure it, render novel views.

Examples::

    python -m course_lib nerf train --out outputs/nerf-fast --preset fast
    python -m course_lib nerf train ../shared/data/nerf-lego-100 --out outputs/lego-paper --minutes 5 --preset paper
    python -m course_lib nerf eval outputs/lego-paper ../shared/data/nerf-lego-100   # PSNR on every test view
    python -m course_lib nerf render outputs/nerf-fast/checkpoint.pt --out outputs/nerf-fast/path
    python -m course_lib nerf train --device cuda --minutes 1 --out outputs/nerf-gpu     # an NVIDIA GPU

``train``'s options are made from :class:`~course_lib.nerf.presets.TrainConfig`: one option per
field (``n_samples`` -> ``--n-samples``; a switch ``--fine`` / ``--no-fine``), its help the field's
docstring, its default the preset's (``--preset``, default ``fast``) -- so the command line and
``train(data, config="fast")`` in a notebook run the same thing. Shorter names kept from earlier
versions: ``--batch``, ``--samples``, ``--importance``, ``--sparse-adam``, ``--black-background``.

``train`` writes ``OUT/metrics.json`` (the PSNR, iterations, seconds, preset, loss/PSNR history),
``OUT/test/<view>.png`` (renders of the evaluated test views), ``OUT/snapshots/step_XXXXXX.png``
(the held-out view during training, a preview at most 200 px on its longest side) and
``OUT/checkpoint.pt``; run it again with the same ``--out`` to resume (``--minutes`` and
``--iters`` are totals). ``eval`` renders every view of a split with a checkpoint and prints its
mean PSNR. ``render`` writes ``OUT/path.gif`` and ``OUT/frame_XXX.png`` along a circle around the
scene.

``--minutes`` (default 5) is the budget of the whole run: loading the images, training, snapshots,
checkpoints and the final evaluation. Everything outside training stays below 10 % of it:
loading, snapshots and checkpoints within 5 % of the training time (a due snapshot waits while it
would not fit; the fast preset checkpoints at most once a minute, so a crash loses about a
minute), and the final evaluation renders every test view when they fit in 3 % of the budget at
the speed it measures on the first one; when they do not, at least 8 evenly spread views, and the
summary calls that "PSNR on k of n test views" (``--eval-all`` renders all of them whatever the
time; ``nerf eval`` afterwards). Renders (evaluation, snapshots, ``render``) run forward only,
with empty-space skipping and early ray termination (:mod:`course_lib.nerf.inference`).

``--device auto`` (the default) trains and renders on a CUDA GPU if there is one, else on an Apple
GPU (MPS), else on the CPU, and says which; a checkpoint written on one device loads on any other.
Ctrl-C during ``train`` saves a checkpoint and says how to resume (exit status 130).
"""

from __future__ import annotations

import argparse
import ast
import json
import re
import time
import typing
from dataclasses import fields
from pathlib import Path

from course_lib.data.blender import load_blender
from course_lib.nerf.checkpoint import CHECKPOINT, load_checkpoint
from course_lib.nerf.device import DEVICE_CHOICES, device_name, pick_device
from course_lib.nerf.inference import circular_path, evaluate, render_path, save_gif, save_png
from course_lib.nerf.presets import PRESETS, TrainConfig, field_docs, preset, resolve
from course_lib.nerf.run import psnr_label
from course_lib.nerf.train import TrainingInterrupted, train
from course_lib.paths import EMBEDDED_NERF
from course_lib.validate import KitInputError, output_dir

DEVICE_HELP = "cpu, cuda (NVIDIA GPU), mps (Apple GPU) or auto: CUDA, then MPS, then the CPU (default: auto)"

#: shorter option names kept from earlier versions of the command line
ALIASES = {"batch_rays": ("--batch",), "n_samples": ("--samples",), "n_importance": ("--importance",),
           "grid_sparse_adam": ("--sparse-adam",)}
#: fields that are not options of their own (the preset is chosen with --preset)
NOT_OPTIONS = {"preset"}


def _none_or(kind):
    def parse(text: str):
        return None if text.strip().lower() == "none" else kind(text)

    parse.__name__ = kind.__name__  # argparse names the type in its error messages
    return parse


def _python_value(text: str):
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        raise argparse.ArgumentTypeError(f"{text!r} is not a Python literal, e.g. ((0, 0.4), (0.06, 0.8))") from None


def _plain(doc: str) -> str:
    """A docstring's reST as plain text: ``:class:`~a.b.C``` -> ``C``, double backquotes dropped."""
    doc = re.sub(r":\w+:`~?([^`]+)`", lambda m: m.group(1).split(".")[-1], doc)
    return doc.replace("``", "")


def _option(hint) -> dict:
    """argparse keywords for a field of this type."""
    if typing.get_origin(hint) is typing.Annotated:
        hint = typing.get_args(hint)[0]
    if hint is bool:
        return {"action": argparse.BooleanOptionalAction}
    if typing.get_origin(hint) is typing.Literal:
        choices = typing.get_args(hint)
        return {"type": type(choices[0]), "choices": choices}
    args = typing.get_args(hint)
    if type(None) in args:  # X | None
        kind = next(a for a in args if a is not type(None))
        return {"type": _none_or(kind), "metavar": kind.__name__.upper()}
    if hint in (int, float, str):
        return {"type": hint, "metavar": hint.__name__.upper()}
    return {"type": _python_value, "metavar": "TUPLE"}


def add_config_options(parser: argparse.ArgumentParser) -> None:
    """One option per :class:`TrainConfig` field, grouped by its section, its help from the field's docstring.

    Every option defaults to "not given" (the preset's value); :func:`config_from_args` applies the given ones.
    """
    docs = field_docs(TrainConfig)
    hints = typing.get_type_hints(TrainConfig, include_extras=True)
    groups: dict[str, argparse._ArgumentGroup] = {}
    for f in fields(TrainConfig):
        if f.name in NOT_OPTIONS:
            continue
        section, doc = docs.get(f.name, ("", ""))
        if section not in groups:
            groups[section] = parser.add_argument_group(f"{section} (TrainConfig)" if section else "TrainConfig")
        defaults = {name: getattr(cfg, f.name) for name, cfg in PRESETS.items()}
        shown = (f"default {next(iter(defaults.values()))!r}" if len(set(map(repr, defaults.values()))) == 1
                 else "; ".join(f"{name}: {v!r}" for name, v in defaults.items()))
        text = f"{_plain(doc)} ({shown})".replace("%", "%%")
        groups[section].add_argument("--" + f.name.replace("_", "-"), *ALIASES.get(f.name, ()), dest=f.name,
                                     default=argparse.SUPPRESS, help=text, **_option(hints[f.name]))
        if f.name == "white_background":
            groups[section].add_argument("--black-background", dest="white_background", action="store_false",
                                         default=argparse.SUPPRESS, help="the same as --no-white-background")


def config_from_args(args):
    """The preset ``args.preset`` with the options that were given on the command line."""
    names = {f.name for f in fields(TrainConfig)} - NOT_OPTIONS
    return preset(args.preset, **{k: v for k, v in vars(args).items() if k in names})


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="nerf_command", metavar="{train,eval,render}")
    t = sub.add_parser("train", help="train on a Blender-format scene (default: the embedded scene)",
                       description="Train a NeRF. Every TrainConfig field is an option; its default is the preset's.")
    t.add_argument("data", nargs="?", default=None,
                   help=f"scene folder with transforms_train.json (default: {EMBEDDED_NERF})")
    t.add_argument("--out", required=True, help="output folder (metrics.json, test/, snapshots/, checkpoint.pt)")
    t.add_argument("--preset", choices=sorted(PRESETS), default="fast", help="training preset (default: fast)")
    t.add_argument("--device", default="auto", metavar="{" + ",".join(DEVICE_CHOICES) + "}", help=DEVICE_HELP)
    t.add_argument("--downscale", type=int, default=1, help="shrink the images by this integer factor")
    t.add_argument("--gif", action="store_true", help="also render novel views along a circle (OUT/path.gif)")
    t.add_argument("--no-resume", action="store_true", help="ignore an existing checkpoint in --out")
    t.add_argument("--quiet", action="store_true", help="no progress bar")
    add_config_options(t)
    e = sub.add_parser("eval", help="PSNR of a checkpoint on every view of a scene's test split")
    e.add_argument("checkpoint", help="checkpoint.pt written by `nerf train` (or its output folder)")
    e.add_argument("data", help="scene folder with transforms_test.json (the scene the checkpoint was trained on)")
    e.add_argument("--split", choices=("test", "val", "train"), default="test", help="which views (default: test)")
    e.add_argument("--downscale", type=int, default=None,
                   help="shrink the images by this factor (default: to the checkpoint's training size)")
    e.add_argument("--out", default=None, help="also write the renders (PNG) and eval.json into this folder")
    e.add_argument("--device", default="auto", metavar="{" + ",".join(DEVICE_CHOICES) + "}", help=DEVICE_HELP)
    r = sub.add_parser("render", help="render novel views along a circle from a checkpoint (GIF + PNGs)")
    r.add_argument("checkpoint", help="checkpoint.pt written by `nerf train` (or its output folder)")
    r.add_argument("--out", required=True, help="output folder for path.gif and frame_XXX.png")
    r.add_argument("--frames", type=int, default=40, help="number of views on the circle (default 40)")
    r.add_argument("--elevation", type=float, default=None, help="elevation in degrees (default: the training cameras')")
    r.add_argument("--fps", type=float, default=12.0, help="GIF frames per second")
    r.add_argument("--device", default="auto", metavar="{" + ",".join(DEVICE_CHOICES) + "}", help=DEVICE_HELP)
    parser.set_defaults(_parser=parser)


def _scene_folder(folder, split: str = "train") -> Path:
    folder = Path(folder)
    if not folder.exists():
        raise KitInputError(f"scene folder {folder} not found (expected a folder with transforms_{split}.json)")
    if not (folder / f"transforms_{split}.json").exists():
        raise KitInputError(f"{folder} has no transforms_{split}.json: is it a NeRF Blender scene folder?")
    return folder


def _load_scene(folder, downscale: int, white: bool):
    folder = _scene_folder(folder)
    train_data = load_blender(folder, "train", downscale=downscale, white_background=white, dtype="uint8")
    test_data = None
    for split in ("test", "val"):
        if (folder / f"transforms_{split}.json").exists():
            test_data = load_blender(folder, split, downscale=downscale, white_background=white, dtype="uint8")
            break
    return train_data, test_data


def _where(device) -> str:
    return device.type if device.type == "cpu" else device_name(device)  # the CPU's threads are set by train()


def _train(args) -> int:
    started_at = time.perf_counter()  # --minutes covers the loading too
    device = pick_device(args.device)
    cfg = config_from_args(args)
    data = Path(args.data) if args.data else EMBEDDED_NERF
    if args.data is None and not (data / "transforms_train.json").exists():
        raise KitInputError(f"the embedded NeRF scene {data} is not there (run `python -m course_lib make-data`) "
                            "or pass a scene folder, e.g. ../shared/data/nerf-lego-100")
    train_data, test_data = _load_scene(data, args.downscale, cfg.white_background)
    out = output_dir(args.out)
    run = resolve(cfg, train_data.H, train_data.W)
    budget = f"{run.minutes:g} min" if run.minutes else f"{run.iters} steps"
    print(f"training {cfg.preset} on {data} ({len(train_data)} views {train_data.W}x{train_data.H}, "
          f"{len(test_data) if test_data else 0} test views) for {budget} on {_where(device)} -> {out}")
    if not args.no_resume and (out / CHECKPOINT).exists():
        print(f"resuming from {out / CHECKPOINT} (--no-resume starts afresh)")
    try:
        res = train(train_data, test_data, cfg, out_dir=out, resume=not args.no_resume, progress=not args.quiet,
                    device=device, started_at=started_at)
    except TrainingInterrupted as exc:
        print(f"\ninterrupted at step {exc.step}; checkpoint saved; run the same command to resume", flush=True)
        return 130
    except KeyboardInterrupt:
        print("\ninterrupted before training started (or by a second Ctrl-C inside a step); nothing saved now",
              flush=True)
        return 130
    m = res.metrics
    if m.get("final_psnr") is None:
        result = "no test split, no test PSNR"
    else:
        result = f"{m['final_psnr_label']}: {m['final_psnr']:.2f} dB"
        if m["test_psnr"] is None:
            result += (f" (all {m['n_test_views_available']} do not fit in {100 * run.final_eval_share:g} % of --minutes "
                       f"at {m['first_view_seconds']:.1f} s a view; `python -m course_lib nerf eval {out} {data}` "
                       "renders every one)")
    print(f"{m['iterations']} steps in {m['train_seconds']:.0f} s of training on {m['device_name']} ({m['stopped_by']}), "
          f"{m['wall_seconds']:.0f} s wall ({100 * m['overhead_fraction']:.0f} % outside training); {result}; "
          f"metrics: {out / 'metrics.json'}")
    if args.gif:
        path = circular_path(train_data.c2w, res.bounds.center, n_frames=40)
        frames = render_path(res.model, res.model_fine, res.config, res.bounds, train_data.H, train_data.W,
                             train_data.K, path, progress=not args.quiet)
        print(f"novel views: {save_gif(out / 'path.gif', frames)}")
    return 0


def _eval(args) -> int:
    device = pick_device(args.device)
    ck = load_checkpoint(args.checkpoint, device)
    cfg, cam = ck["cfg"], ck.get("camera")
    folder = _scene_folder(args.data, args.split)
    downscale = args.downscale
    data = load_blender(folder, args.split, downscale=downscale or 1, white_background=cfg.white_background, dtype="uint8")
    if downscale is None and cam is not None and (data.W, data.H) != (cam["W"], cam["H"]):
        factor = data.W // cam["W"]
        if factor < 1 or (data.W // factor, data.H // factor) != (cam["W"], cam["H"]):
            raise KitInputError(f"{folder} has {data.W}x{data.H} px views but the checkpoint was trained on "
                                f"{cam['W']}x{cam['H']} px: pass --downscale (or the scene it was trained on)")
        data = load_blender(folder, args.split, downscale=factor, white_background=cfg.white_background, dtype="uint8")
    t = time.perf_counter()
    mean, per_view, renders = evaluate(ck["model"], ck["model_fine"], cfg, ck["bounds"], data,
                                       return_renders=args.out is not None)
    seconds = time.perf_counter() - t
    label = psnr_label(len(data), len(data)) if args.split == "test" else f"PSNR on all {len(data)} {args.split} views"
    result = {"checkpoint": str(args.checkpoint), "data": str(folder), "split": args.split, "step": ck["step"],
              "psnr": round(mean, 3), "label": label, "n_views": len(data), "image_size": [data.W, data.H],
              "psnr_per_view": {n: round(v, 3) for n, v in zip(data.names, per_view)}, "seconds": round(seconds, 2),
              "device": device_name(device)}
    if args.out is not None:
        out = output_dir(args.out)
        for name, img in zip(data.names, renders):
            save_png(out / f"{name}.png", img)
        (out / "eval.json").write_text(json.dumps(result, indent=1))
    print(f"{label}: {mean:.2f} dB (checkpoint step {ck['step']}; {len(data)} views of {data.W}x{data.H} px rendered "
          f"in {seconds:.1f} s on {device_name(device)})")
    return 0


def _render(args) -> int:
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
    return {"train": _train, "eval": _eval, "render": _render}[args.nerf_command](args)

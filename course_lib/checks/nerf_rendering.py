"""Checks of notebook 08 (volume rendering): ``volume_render``.

``check_volume_render(volume_render)`` runs the student's function on

* rays through a slab of constant density (hand-computable: behind a slab of density sigma and
  thickness L the transmittance is exp(-sigma L), whatever the sample spacing), and
* random rays with unnormalized directions, compared with the reference stored in fixture
  ``nerf_rendering`` (``python -m course_lib fixtures nerf_rendering``), with a white and a black
  background,

and names the likely mistake: alpha = 1 - exp(-sigma) without the interval length delta, delta
not scaled by |d|, inclusive instead of exclusive cumulative product in the transmittance, the
last interval, no white background (or one where black was asked for), depth or accumulation
computed differently, weights that forget alpha (w = T) or the transmittance (w = alpha).

Defining property (failing it costs at least half of the points): Δ in α, the interval length in
the opacity, checked on the slabs and on the random rays with both backgrounds.

The cases and the reference's results on them are stored arrays, made on the instructor's side
by :mod:`course_lib.instructor.cases.nerf_rendering`; this module imports no reference solution and ships
to students.
"""

from __future__ import annotations

import itertools
from typing import Callable

import numpy as np

from course_lib.checks.core import FAILED, Check, declare_defining, load_fixture
from course_lib.checks.nerf_data import close, to_numpy

__all__ = ["check_volume_render", "render_variant"]

FIXTURE = "nerf_rendering"
KEYS = ("rgb_map", "depth_map", "acc_map", "weights")

declare_defining("volume_render", {
    "Δ in α": "alpha_i = 1 - exp(-sigma_i delta_i): the opacity of a sample depends on the length of its interval",
})
DELTA = "Δ in α"

#: Weights that are not alpha_i T_i: (mistake, form) for :func:`render_variant`.
FORM_HINTS = {
    "T": "the weights forget alpha: w_i = T_i alpha_i (the light that reaches sample i times the share it absorbs), "
         "not T_i alone",
    "alpha": "the weights forget the transmittance: w_i = T_i alpha_i with T_i = prod_{j<i} (1 - alpha_j), "
             "not alpha_i alone (samples behind opaque matter must not count)",
}


def _slab_case():
    """Rays along +z (|d| = 1) through slabs of constant density; empty space elsewhere."""
    z = np.tile(np.linspace(2.0, 6.0, 41), (3, 1))  # delta = 0.1
    sigma = np.zeros_like(z)
    slabs = [(3.0, 4.0, 5.0), (2.5, 3.0, 2.0), (4.0, 5.5, 0.4)]  # (start, end, density)
    for r, (a, b, s) in enumerate(slabs):
        sigma[r, (z[r] >= a - 1e-9) & (z[r] < b - 1e-9)] = s
    rgb = np.zeros((3, 41, 3))
    rgb[..., 0] = 1.0  # red matter
    d = np.tile([0.0, 0.0, 1.0], (3, 1))
    trans = np.array([np.exp(-s * (b - a)) for a, b, s in slabs])
    return rgb.astype(np.float32), sigma.astype(np.float32), z.astype(np.float32), d.astype(np.float32), trans


# --------------------------------------------------------------------------- variants


def render_variant(rgb, sigma, z, d, white: bool = True, delta: str = "norm", last: str = "1e10",
                   cumprod: str = "exclusive", depth: str = "sum", form: str = "alpha_T") -> dict[str, np.ndarray]:
    """One way of writing volume rendering (the reference is one of them, the others are mistakes).

    delta: "norm" (dists * |d|), "plain" (dists, no |d|), "none" (alpha = 1 - exp(-sigma)).
    last: the last interval: "1e10" (NeRF's), "zero" (ignored), "repeat" (the previous one).
    cumprod: "exclusive" (T_i = prod_{j<i}), "inclusive" (prod_{j<=i}).
    depth: "sum" (sum w z), "normalized" (sum w z / acc).
    form: the weights: "alpha_T" (alpha_i T_i), "T" (T_i, alpha forgotten), "alpha" (alpha_i, T forgotten).
    """
    rgb, sigma, z, d = (np.asarray(a, float) for a in (rgb, sigma, z, d))
    dists = np.diff(z, axis=-1)
    tail = {"1e10": np.full_like(z[:, :1], 1e10), "zero": np.zeros_like(z[:, :1]), "repeat": dists[:, -1:]}[last]
    dists = np.concatenate([dists, tail], axis=-1)
    if delta == "norm":
        dists = dists * np.linalg.norm(d, axis=-1, keepdims=True)
    elif delta == "none":
        dists = np.ones_like(dists)
    alpha = 1.0 - np.exp(-sigma * dists)
    keep = np.cumprod(1.0 - alpha + 1e-10, axis=-1)
    if cumprod == "exclusive":
        keep = np.concatenate([np.ones_like(keep[:, :1]), keep[:, :-1]], axis=-1)
    w = {"alpha_T": alpha * keep, "T": keep, "alpha": alpha}[form]
    acc = w.sum(-1)
    rgb_map = (w[..., None] * rgb).sum(-2)
    if white:
        rgb_map = rgb_map + (1.0 - acc[:, None])
    dep = (w * z).sum(-1)
    if depth == "normalized":
        dep = dep / np.maximum(acc, 1e-10)
    return {"rgb_map": rgb_map, "depth_map": dep, "acc_map": acc, "weights": w}


def _weights_params(args, w) -> dict | None:
    for delta, last, cp in itertools.product(("norm", "plain", "none"), ("1e10", "zero", "repeat"), ("exclusive", "inclusive")):
        if close(w, render_variant(*args, delta=delta, last=last, cumprod=cp)["weights"], rtol=1e-3, atol=1e-5):
            return {"delta": delta, "last": last, "cumprod": cp}
    return None


LAST = {"1e10": "a very long last interval (1e10), so that the last sample absorbs what is left",
        "zero": "no last interval (alpha = 0 for the last sample)", "repeat": "the last interval equal to the one before"}


def _weights_hint(mine: dict, ref: dict) -> str:
    hints = []
    if mine["delta"] != ref["delta"]:
        if mine["delta"] == "none":
            hints.append("forgot delta: alpha_i = 1 - exp(-sigma_i * delta_i) with delta_i = z_{i+1} - z_i "
                         "(times |d|), not 1 - exp(-sigma_i)")
        elif mine["delta"] == "plain":
            hints.append("delta is not scaled by |d|: rays_d is not normalized, so the distance between samples is "
                         "(z_{i+1} - z_i) * |rays_d|")
        else:
            hints.append("delta should be z_{i+1} - z_i without |d|")
    if mine["cumprod"] != ref["cumprod"]:
        hints.append("inclusive cumprod: the transmittance T_i = prod_{j<i} (1 - alpha_j) excludes sample i itself "
                     "(shift the cumulative product right by one and start with 1)")
    if mine["last"] != ref["last"]:
        hints.append(f"the last interval: the kit uses {LAST[ref['last']]}; yours looks like {LAST[mine['last']]}")
    return "; ".join(hints) or "weights differ from the reference"


def _call(c: Check, fn, args, white: bool, case: str):
    import torch

    out = c.call(fn, *(torch.as_tensor(a) for a in args), white_background=white, case=case)
    if out is FAILED:
        return None
    if not isinstance(out, dict):
        c.fail(f"{case}: return a dict with keys {', '.join(KEYS)}, got {type(out).__name__}")
        return None
    missing = [k for k in KEYS if k not in out]
    if missing:
        c.fail(f"{case}: the result has no {', '.join(missing)}: return a dict with keys {', '.join(KEYS)}")
        return None
    res = {k: to_numpy(out[k]) for k in KEYS}
    R, S = np.shape(args[1])
    shapes = {"rgb_map": (R, 3), "depth_map": (R,), "acc_map": (R,), "weights": (R, S)}
    for k in KEYS:
        if res[k] is None or res[k].shape != shapes[k]:
            got = None if res[k] is None else res[k].shape
            c.fail(f"{case}: {k} has shape {got}, expected {shapes[k]}")
            return None
        if not np.isfinite(res[k]).all():
            c.fail(f"{case}: {k} contains NaN or inf")
            return None
    return res


def check_volume_render(volume_render: Callable) -> None:
    """Check ``volume_render(rgb, sigma, z_vals, rays_d, white_background=True) -> dict`` (notebook 08).

    The dict holds ``rgb_map (R, 3)``, ``depth_map (R,)``, ``acc_map (R,)``, ``weights (R, S)``.
    """
    f = load_fixture(FIXTURE)
    with Check("volume_render") as c:
        # 1. hand-computable slabs
        rgb, sigma, z, d, trans = _slab_case()
        case = "rays through slabs of constant density"
        res = _call(c, volume_render, (rgb, sigma, z, d), True, case)
        if res is not None:
            c.gate(True, f"{case}: returns rgb_map, depth_map, acc_map, weights of the right shapes", "")
            acc = res["acc_map"]
            ok = np.allclose(acc, 1.0 - trans, atol=1e-4)
            if ok:
                c.expect(True, f"{case}: the light that gets through is exp(-sigma L)", "", defining=DELTA)
            else:
                slab = (rgb, sigma, z, d)
                no_delta = render_variant(*slab, delta="none")["acc_map"]
                incl = render_variant(*slab, cumprod="inclusive")["acc_map"]
                form = next((k for k in FORM_HINTS if close(res["weights"], render_variant(*slab, form=k)["weights"],
                                                                rtol=1e-3, atol=1e-5)), None)
                prop = None
                if close(acc, no_delta, atol=1e-4):
                    hint, prop = "forgot delta: alpha_i = 1 - exp(-sigma_i * delta_i), not 1 - exp(-sigma_i)", DELTA
                elif form is not None:
                    hint = FORM_HINTS[form]
                elif close(acc, incl, atol=1e-4):
                    hint = "inclusive cumprod: T_i = prod_{j<i} (1 - alpha_j) must exclude sample i"
                else:
                    hint = f"acc_map = {np.round(acc, 3).tolist()}, expected 1 - exp(-sigma L) = {np.round(1 - trans, 3).tolist()}"
                c.fail(f"{case}: {hint}", defining=prop)
            c.gate(np.allclose(res["weights"].sum(-1), acc, atol=1e-4), f"{case}: acc_map is the sum of the weights",
                     f"{case}: acc_map must be the sum of the weights along each ray")
            if ok:  # the colour only makes sense once the opacity is right
                want = np.stack([np.ones(3), trans, trans], axis=1)  # red matter in front of a white background
                c.expect(np.allclose(res["rgb_map"], want, atol=1e-3),
                         f"{case}: the colour is red matter over the white background",
                         f"{case}: rgb_map should be sum_i w_i c_i + (1 - acc_map) (white background); "
                         f"expected {np.round(want, 3).tolist()}, got {np.round(res['rgb_map'], 3).tolist()}")
        # 2. random rays vs the reference
        args = tuple(f[k] for k in ("rgb", "sigma", "z_vals", "rays_d"))
        ref_w = f["white_weights"].astype(float)
        ref_params = _weights_params(args, ref_w)
        for white in (True, False):
            bg = "white" if white else "black"
            case = f"random rays, {bg} background"
            res = _call(c, volume_render, args, white, case)
            if res is None:
                continue
            ref = {k: f[f"{bg}_{k}"].astype(float) for k in KEYS}
            if close(res["weights"], ref["weights"], rtol=1e-3, atol=1e-5):
                c.expect(True, f"{case}: weights match the reference", "", defining=DELTA)
            else:
                mine = _weights_params(args, res["weights"])
                form = next((k for k in FORM_HINTS if close(res["weights"], render_variant(*args, form=k, **{
                    k2: v for k2, v in (ref_params or {}).items()})["weights"], rtol=1e-3, atol=1e-5)), None)
                if form is not None:
                    c.fail(f"{case}: {FORM_HINTS[form]}")
                else:
                    c.fail(f"{case}: " + (_weights_hint(mine, ref_params) if mine and ref_params else
                                          "weights differ from the reference: w_i = T_i (1 - exp(-sigma_i delta_i)), "
                                          "T_i = prod_{j<i} exp(-sigma_j delta_j)"),
                           defining=DELTA if mine and mine["delta"] == "none" else None)
                continue
            c.expect(close(res["acc_map"], ref["acc_map"], rtol=1e-3), f"{case}: acc_map matches the reference",
                     f"{case}: acc_map must be the sum of the weights along each ray")
            if close(res["rgb_map"], ref["rgb_map"], rtol=1e-3):
                c.expect(True, f"{case}: rgb_map matches the reference", "")
            else:
                other = render_variant(*args, white=not white, **(ref_params or {}))["rgb_map"]
                if close(res["rgb_map"], other, rtol=1e-3):
                    hint = ("no white background: add (1 - acc_map) to rgb_map when white_background=True" if white else
                            "white background added although white_background=False")
                else:
                    hint = "rgb_map = sum_i w_i c_i (+ (1 - acc_map) on a white background)"
                c.fail(f"{case}: {hint}")
            if close(res["depth_map"], ref["depth_map"], rtol=1e-3):
                c.expect(True, f"{case}: depth_map matches the reference", "")
            else:
                norm = (ref["weights"] * args[2]).sum(-1) / np.maximum(ref["acc_map"], 1e-10)
                hint = ("depth_map divided by acc_map: the kit's depth is the expected depth sum_i w_i z_i"
                        if close(res["depth_map"], norm, rtol=1e-3) else "depth_map = sum_i w_i z_i")
                c.fail(f"{case}: {hint}")

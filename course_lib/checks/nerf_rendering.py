"""Checks of notebook 08 (volume rendering): ``volume_render``.

``check_volume_render(volume_render)`` runs the student's function on rays through slabs of constant density
(hand-computable: behind a slab of density sigma and thickness L the transmittance is exp(-sigma L), whatever the
sample spacing) and on random rays with unnormalized directions, with a white and a black background, compared with
the reference (fixture ``nerf_rendering``, :mod:`course_lib.instructor.cases.nerf_rendering`, which also stores what
each mistake of :data:`RENDER_HINTS` gives). Δ in α (the interval length in the opacity) is the defining property,
checked on the slabs and on the random rays with both backgrounds.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from course_lib.checks.core import (FAILED, Check, Outcome, as_float, declare_defining, load_fixture, report_cases,
                                    unique_key)
from course_lib.checks.nerf_data import close, matching

__all__ = ["check_volume_render", "RENDER_HINTS"]

FIXTURE = "nerf_rendering"
KEYS = ("rgb_map", "depth_map", "acc_map", "weights")

declare_defining("volume_render", {
    "Δ in α": "alpha_i = 1 - exp(-sigma_i delta_i): the opacity of a sample depends on the length of its interval",
})
DELTA = "Δ in α"

#: Weights that are not alpha_i T_i: what to change.
FORM_HINTS = {
    "T": "the weights forget alpha: w_i = T_i alpha_i (the light that reaches sample i times the share it absorbs), "
         "not T_i alone",
    "alpha": "the weights forget the transmittance: w_i = T_i alpha_i with T_i = prod_{j<i} (1 - alpha_j), "
             "not alpha_i alone (samples behind opaque matter must not count)",
}


#: Rendering mistakes stored per case (``<case>__<label>_<key>``): label -> what to change.
RENDER_HINTS = {
    "no_delta": "forgot delta: alpha_i = 1 - exp(-sigma_i * delta_i) with delta_i = z_{i+1} - z_i (times |d|), "
                "not 1 - exp(-sigma_i)",
    "plain_delta": "delta is not scaled by |d|: rays_d is not normalized, so the distance between samples is "
                   "(z_{i+1} - z_i) * |rays_d|",
    "inclusive": "inclusive cumprod: the transmittance T_i = prod_{j<i} (1 - alpha_j) excludes sample i itself "
                 "(shift the cumulative product right by one and start with 1)",
    "last_zero": "the last interval: the kit uses a very long last interval (1e10), so that the last sample absorbs "
                 "what is left; yours looks like no last interval (alpha = 0 for the last sample)",
    "last_repeat": "the last interval: the kit uses a very long last interval (1e10), so that the last sample absorbs "
                   "what is left; yours repeats the interval before",
    "dists_first": "the intervals are shifted by one: delta_i = z_{i+1} - z_i belongs to sample i, and the long "
                   "interval (1e10) goes last, not first",
    "form_T": FORM_HINTS["T"],
    "form_alpha": FORM_HINTS["alpha"],
}
#: the mistakes that leave Δ out of α (the defining property)
NO_DELTA = {"no_delta"}


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
    res = {k: as_float(out[k]) for k in KEYS}
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


def _slab_eval(c: Check, volume_render: Callable, f) -> Outcome | None:
    args = tuple(f[f"slab_{k}"] for k in ("rgb", "sigma", "z_vals", "rays_d"))
    case = "rays through slabs of constant density"
    res = _call(c, volume_render, args, True, case)
    if res is None:
        return None
    c.gate(True, f"{case}: returns rgb_map, depth_map, acc_map, weights of the right shapes", "")
    trans = f["slab_trans"].astype(float)
    absorbed = res["weights"].sum(-1)  # the light the samples absorb: sum_i w_i = 1 - exp(-sigma L)
    return Outcome(case, close(absorbed, 1.0 - trans), "the light that gets through is exp(-sigma L)",
                   keys=set(matching(res["weights"], f, "slab", RENDER_HINTS, "_weights")),
                   advice=f"the weights absorb {np.round(absorbed, 3).tolist()} of the light, expected 1 - exp(-sigma L) "
                   f"= {np.round(1 - trans, 3).tolist()}: alpha_i = 1 - exp(-sigma_i delta_i), w_i = T_i alpha_i",
                   data=(res, trans))


def _slab_verdicts(c: Check, o: Outcome) -> None:
    """After the slabs' light: acc_map is the sum of the weights, then the colour (red matter, white background)."""
    case, (res, trans) = o.case, o.data
    acc = res["acc_map"]
    c.gate(close(acc, res["weights"].sum(-1)), f"{case}: acc_map is the sum of the weights",
           f"{case}: acc_map is not the sum of the weights along each ray (acc_map = sum_i w_i; yours differs by up to "
           f"{float(np.abs(res['weights'].sum(-1) - acc).max()):.3g})")
    if o.ok and close(acc, res["weights"].sum(-1)):  # the colour only makes sense once the opacity is right
        want = np.stack([np.ones_like(trans), trans, trans], axis=1)  # red matter in front of a white background
        c.expect(close(res["rgb_map"], want), f"{case}: the colour is red matter over the white background",
                 f"{case}: rgb_map should be sum_i w_i c_i + (1 - acc_map) (white background); "
                 f"expected {np.round(want, 3).tolist()}, got {np.round(res['rgb_map'], 3).tolist()}")


def _random_eval(c: Check, volume_render: Callable, f, white: bool) -> Outcome | None:
    args = tuple(f[k] for k in ("rgb", "sigma", "z_vals", "rays_d"))
    bg = "white" if white else "black"
    case = f"random rays, {bg} background"
    res = _call(c, volume_render, args, white, case)
    if res is None:
        return None
    return Outcome(case, close(res["weights"], f[f"{bg}_weights"].astype(float)), "weights match the reference",
                   keys=set(matching(res["weights"], f, bg, RENDER_HINTS, "_weights")),
                   advice="weights differ from the reference: w_i = T_i (1 - exp(-sigma_i delta_i)), "
                   "T_i = prod_{j<i} exp(-sigma_j delta_j), delta_i = (z_{i+1} - z_i) |d|, delta_S = 1e10",
                   data=(res, bg, white))


def _random_verdicts(c: Check, f, o: Outcome) -> None:
    """After right weights: acc_map, rgb_map (the background named) and depth_map against the reference's."""
    if not o.ok:
        return
    case, (res, bg, white) = o.case, o.data
    ref = {k: f[f"{bg}_{k}"].astype(float) for k in KEYS}
    c.expect(close(res["acc_map"], ref["acc_map"]), f"{case}: acc_map matches the reference",
             f"{case}: acc_map is not the sum of the weights along each ray (acc_map = sum_i w_i)")
    if close(res["rgb_map"], ref["rgb_map"]):
        c.expect(True, f"{case}: rgb_map matches the reference", "")
    else:
        other = f[f"{bg}__other_background_rgb_map"].astype(float)
        named_bg = None
        if close(res["rgb_map"], other):
            hint = ("no white background: add (1 - acc_map) to rgb_map when white_background=True" if white else
                    "white background added although white_background=False")
            named_bg = "background"
        else:
            hint = "rgb_map = sum_i w_i c_i (+ (1 - acc_map) on a white background)"
        c.fail(f"{case}: {hint}", named=named_bg)
    if close(res["depth_map"], ref["depth_map"]):
        c.expect(True, f"{case}: depth_map matches the reference", "")
    else:
        norm = f[f"{bg}__depth_normalized_depth_map"].astype(float)
        normed = close(res["depth_map"], norm)
        c.fail(f"{case}: " + ("depth_map divided by acc_map: the kit's depth is the expected depth sum_i w_i z_i"
                              if normed else "depth_map = sum_i w_i z_i"), named="depth_normalized" if normed else None)


def check_volume_render(volume_render: Callable) -> None:
    """Check ``volume_render(rgb, sigma, z_vals, rays_d, white_background=True) -> dict`` (notebook 08).

    The dict holds ``rgb_map (R, 3)``, ``depth_map (R,)``, ``acc_map (R,)``, ``weights (R, S)``. The light through
    the slabs and the random rays' weights test Δ in α, the defining property, when they pass or when the mistake
    named leaves Δ out of α.
    """
    f = load_fixture(FIXTURE)
    with Check("volume_render") as c:
        slab = _slab_eval(c, volume_render, f)
        runs = [o for o in [slab] + [_random_eval(c, volume_render, f, white) for white in (True, False)] if o]
        named = unique_key([o.keys for o in runs if not o.ok])
        for o in runs:
            o.defining = DELTA if o.ok or named in NO_DELTA else None
        report_cases(c, runs, RENDER_HINTS,
                     then=lambda o, _: _slab_verdicts(c, o) if o is slab else _random_verdicts(c, f, o))

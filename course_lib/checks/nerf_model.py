"""Checks of notebook 07 (the NeRF MLP): the ``NeRF`` module and ``psnr``.

``check_nerf_model(NeRF)`` builds the student's class with its default arguments (the paper's
network: 8 ReLU layers of width 256, the encoded position concatenated again after the 4th, a
density head, a view-dependent branch of width 128 and a sigmoid RGB head) and with a small
configuration, and compares with the reference stored in fixture ``nerf_model``
(``python -m course_lib fixtures nerf_model``):

* the fully connected layers (in -> out features) and the parameter count: names a missing skip
  connection, a missing view-direction branch, a missing positional encoding, one output head;
* the forward pass: shapes ``rgb (..., 3)``, ``sigma (...)``; rgb in [0, 1] (sigmoid), sigma >= 0
  (ReLU); sigma independent of the viewing direction, rgb dependent on it;
* defining properties (failing one costs at least half of the points): the skip input
  ``[γ(x), h]`` (checked in the layer table of three configurations, and in the wiring), and the
  ReLU density (sigma >= 0, and with the reference's weights exactly ReLU of the density head, so
  that a sigmoid, softplus, exp or no activation on the density is named);
* with the reference's weights copied in (matched layer by layer in order of definition) the
  outputs equal the reference's, which pins down the wiring (ReLU after every layer, the order
  of concatenations, where the heads branch off).

The cases and the reference's results on them are stored arrays, made on the instructor's side
by :mod:`course_lib.instructor.cases.nerf_model`; this module imports no reference solution and ships
to students.
"""

from __future__ import annotations

import math
from collections import Counter
from typing import Callable

import numpy as np

from course_lib.checks.core import FAILED, Check, declare_defining, load_fixture
from course_lib.checks.nerf_data import close, to_numpy

__all__ = ["check_nerf_model", "check_psnr", "layer_table", "set_test_weights"]

FIXTURE = "nerf_model"

#: the configurations the check builds: (name, constructor kwargs)
CONFIGS = (
    ("default", {}),
    ("small", {"depth": 4, "width": 32, "skips": (2,), "pos_freqs": 3, "dir_freqs": 2}),
    ("tiny", {"depth": 3, "width": 16, "skips": (1,), "pos_freqs": 2, "dir_freqs": 1}),
)

declare_defining("NeRF", {
    "skip input": "the encoded position γ(x) is concatenated again, as torch.cat([γ(x), h], -1), after the skip layer",
    "ReLU density": "the density is ReLU(raw) >= 0, unbounded above (a sigmoid caps it at 1: nothing is opaque)",
})

#: Wrong density activations, applied to the raw density output: (mistake, function).
DENSITY_VARIANTS = (
    ("the density goes through a sigmoid, which caps it at 1 so that nothing becomes opaque: use "
     "torch.relu on the density head (sigmoid belongs on the RGB head only)", lambda r: 1.0 / (1.0 + np.exp(-r))),
    ("the density head has no activation, so sigma can be negative: apply torch.relu to it", lambda r: r),
    ("the density goes through exp: use torch.relu (the paper) on the density head", np.exp),
    ("the density goes through softplus: the kit's network uses torch.relu on the density head",
     lambda r: np.logaddexp(0.0, r)),
    ("the density is |raw|: use torch.relu on the density head", np.abs),
)


def layer_table(model) -> list[tuple[int, int]]:
    """``[(in_features, out_features), ...]`` of the model's ``nn.Linear`` layers, in order of definition."""
    import torch.nn as nn

    return [(m.in_features, m.out_features) for m in model.modules() if isinstance(m, nn.Linear)]


def _test_tensors(shapes: list[tuple[int, ...]]):
    """Deterministic test values for parameters of the given shapes (seed = position in the list)."""
    import torch

    out = []
    for i, shp in enumerate(shapes):
        g = torch.Generator().manual_seed(1000 + i)
        fan_in = shp[1] if len(shp) == 2 else 1
        scale = 1.5 / math.sqrt(fan_in) if len(shp) == 2 else 0.1
        out.append(torch.randn(shp, generator=g, dtype=torch.float32) * scale)
    return out


def set_test_weights(model, ref_shapes: list[tuple[int, ...]]) -> bool:
    """Copy the reference's test weights into ``model``, matching parameters by shape in order.

    Parameter k of the reference gets test tensor k; each goes to the first not yet used
    parameter of ``model`` with the same shape. Returns False (model unchanged) when the shapes
    do not match one to one.
    """
    import torch

    params = list(model.parameters())
    if sorted(tuple(p.shape) for p in params) != sorted(ref_shapes):
        return False
    used = [False] * len(params)
    assign = []
    for k, shp in enumerate(ref_shapes):
        j = next(j for j, p in enumerate(params) if not used[j] and tuple(p.shape) == shp)
        used[j] = True
        assign.append(j)
    vals = _test_tensors(ref_shapes)
    with torch.no_grad():
        for k, j in enumerate(assign):
            params[j].copy_(vals[k])
    return True


def _shapes(f, name) -> list[tuple[int, ...]]:
    return [tuple(int(v) for v in row[:n]) for row, n in zip(f[f"{name}_param_shapes"], f[f"{name}_param_ndim"])]


def _layer_hint(mine: list[tuple[int, int]], ref: list[tuple[int, int]], kw: dict) -> str:
    """Name the likely mistake from the difference of the layer tables."""
    cm, cr = Counter(mine), Counter(ref)
    missing, extra = list((cr - cm).elements()), list((cm - cr).elements())
    W = kw.get("width", 256)
    Lx, Ld = kw.get("pos_freqs", 10), kw.get("dir_freqs", 4)
    enc_x, enc_d = 3 * (1 + 2 * Lx), 3 * (1 + 2 * Ld)
    hints = []
    if (W + enc_x, W) in missing:
        hints.append(f"no skip connection: the layer after the skip takes [γ(x), h] ({enc_x} + {W} inputs)")
    if (enc_x, W) in missing and (3, W) in extra:
        hints.append(f"the positions are not encoded: the first layer takes γ(x) ({enc_x} inputs), not x (3)")
    if any(i == W + enc_d for i, _ in missing):
        hints.append(f"the view direction is not used: the colour branch takes [feature, γ(d)] ({W} + {enc_d} inputs)")
    if any(o == 4 for _, o in extra):
        hints.append("one head with 4 outputs: the density comes from the position branch (W -> 1) and the colour "
                     "from the view-dependent branch (-> 3)")
    detail = f"missing {missing}, unexpected {extra}" if (missing or extra) else "the same layers in another order"
    return "; ".join(hints + [f"layers (in, out): {detail}"])


def check_nerf_model(NeRF: Callable) -> None:
    """Check the student's ``NeRF`` class (notebook 07); prints one verdict per property."""
    import torch

    f = load_fixture(FIXTURE)
    pts, dirs = torch.as_tensor(f["pts"]), torch.as_tensor(f["dirs"])
    lead = tuple(f["pts"].shape[:-1])
    with Check("NeRF") as c:
        for name, kw in CONFIGS:
            args = ", ".join(f"{k}={v}" for k, v in kw.items())
            case = f"NeRF({args})"
            torch.manual_seed(0)
            model = c.call(NeRF, case=case, **kw)
            if model is FAILED:
                continue
            if not isinstance(model, torch.nn.Module):
                c.fail(f"{case}: expected an nn.Module, got {type(model).__name__}")
                continue
            ref_layers = [tuple(int(v) for v in r) for r in f[f"{name}_layers"]]
            mine = layer_table(model)
            enc_x = 3 * (1 + 2 * kw.get("pos_freqs", 10))
            W = kw.get("width", 256)
            n_skip = Counter(ref_layers)[(W + enc_x, W)]
            got_skip = Counter(mine)[(W + enc_x, W)]
            if got_skip >= n_skip:
                c.expect(True, f"{case}: the layer after the skip takes [γ(x), h]", "", defining="skip input")
            elif Counter(mine)[(W + 3, W)] > Counter(ref_layers)[(W + 3, W)]:
                c.fail(f"{case}: the skip concatenates the raw position x (3 values): concatenate the ENCODED "
                       f"position, torch.cat([γ(x), h], -1) ({enc_x} + {W} inputs)", defining="skip input")
            else:
                c.fail(f"{case}: no skip connection: after trunk layer {tuple(kw.get('skips', (4,)))} concatenate the "
                       f"encoded input again, h = torch.cat([γ(x), h], -1), so the next layer takes {enc_x} + {W} "
                       "inputs", defining="skip input")
            c.expect(sorted(mine) == sorted(ref_layers),
                     f"{case}: {len(ref_layers)} linear layers with the reference's sizes",
                     f"{case}: {_layer_hint(mine, ref_layers, kw)}")
            n_ref = int(f[f"{name}_n_params"])
            n = sum(p.numel() for p in model.parameters())
            c.expect(n == n_ref, f"{case}: {n_ref:,} parameters, as the reference",
                     f"{case}: {n:,} parameters, the reference has {n_ref:,} ({n - n_ref:+,})")
            # forward with the student's own initialisation
            with torch.no_grad():
                out = c.call(model, pts, dirs, case=f"{case} forward")
            if out is FAILED:
                continue
            if not isinstance(out, (tuple, list)) or len(out) != 2:
                c.fail(f"{case}: forward must return (rgb, sigma), got {type(out).__name__}")
                continue
            rgb, sigma = to_numpy(out[0]), to_numpy(out[1])
            if sigma is not None and sigma.shape == (*lead, 1):
                c.fail(f"{case}: sigma has shape {sigma.shape}: drop the last axis (sigma[..., 0]) so that it is {lead}")
                continue
            if not (c.shape(rgb, (*lead, 3), f"{case}: rgb") & c.shape(sigma, lead, f"{case}: sigma")):
                continue
            if name == "default":
                c.gate(rgb.min() >= 0 and rgb.max() <= 1, f"{case}: rgb in [0, 1]",
                         f"{case}: rgb ranges over [{rgb.min():.3g}, {rgb.max():.3g}]: no sigmoid on the RGB head")
                c.gate(sigma.min() >= 0, f"{case}: sigma >= 0",
                         f"{case}: sigma has negative values (min {sigma.min():.3g}): the density must be non-negative, "
                         "apply a ReLU to the density head", defining="ReLU density")
                other = torch.flip(dirs, dims=(0,))
                with torch.no_grad():
                    out2 = c.call(model, pts, other, case=f"{case} forward")
                if out2 is not FAILED:
                    rgb2, sigma2 = to_numpy(out2[0]), to_numpy(out2[1])
                    c.gate(close(sigma2, sigma), f"{case}: sigma does not depend on the viewing direction",
                             f"{case}: sigma changes with the viewing direction: the density head must branch off "
                             "before the view direction is concatenated")
                    c.gate(not close(rgb2, rgb, rtol=1e-6, atol=1e-7), f"{case}: rgb depends on the viewing direction",
                             f"{case}: rgb ignores viewdirs: concatenate γ(d) with the feature vector before the colour layer")
            # forward with the reference's test weights: pins the wiring
            shapes = _shapes(f, name)
            if not set_test_weights(model, shapes):
                c.fail(f"{case}: the parameters' shapes differ from the reference's, so its weights cannot be copied in "
                       "(see the layer sizes above)")
                continue
            with torch.no_grad():
                out = c.call(model, pts, dirs, case=f"{case} forward")
            if out is FAILED:
                continue
            rgb, sigma = to_numpy(out[0]), to_numpy(out[1]).reshape(lead)
            ok_rgb = close(rgb, f[f"{name}_rgb"].astype(float))
            ok_sig = close(sigma, f[f"{name}_sigma"].astype(float))
            raw = f[f"{name}_sigma_raw"].astype(float)
            act = next((why for why, g in DENSITY_VARIANTS if close(sigma, g(raw))), None)
            c.expect(act is None and (ok_sig or sigma.min() >= 0),
                     f"{case}: with the reference's weights, sigma = ReLU(density head)",
                     f"{case}: {act or 'sigma is negative: apply torch.relu to the density head'}",
                     defining="ReLU density")
            if not ok_sig and f"{name}_sigma_skip_hx" in f and close(sigma, f[f"{name}_sigma_skip_hx"].astype(float)):
                c.fail(f"{case}: the skip concatenates [h, γ(x)]: the order is torch.cat([γ(x), h], -1) (the "
                       "reference's weights expect γ(x) first)", defining="skip input")
                continue
            if ok_rgb and ok_sig:
                c.expect(True, f"{case}: with the reference's weights, rgb and sigma equal the reference's", "")
            elif ok_rgb and act is not None:  # the one mistake is named above: no list of suspects
                c.fail(f"{case}: with the reference's weights rgb equals the reference's and sigma differs only by "
                       "its activation (see above)")
            else:
                what = " and ".join(w for w, ok in (("rgb", ok_rgb), ("sigma", ok_sig)) if not ok)
                hint = ("check the ReLU after every layer, the skip input torch.cat([γ(x), h], -1), that sigma comes "
                        "from the last trunk layer, and the colour input torch.cat([feature, γ(d)], -1)")
                if not ok_sig and sigma.min() < 0:
                    hint = "sigma is negative: ReLU on the density head; " + hint
                if not ok_rgb and (rgb.min() < 0 or rgb.max() > 1):
                    hint = "rgb outside [0, 1]: sigmoid on the RGB head; " + hint
                c.fail(f"{case}: with the reference's weights (copied layer by layer in order of definition) "
                       f"{what} differ: {hint}")


def check_psnr(psnr: Callable) -> None:
    """Check ``psnr(mse) -> float``: peak signal-to-noise ratio in dB of images in [0, 1], -10 log10(mse)."""
    import torch

    cases = [(100, 20.0), (1000, 30.0), (4, 10 * math.log10(4))]
    with Check("psnr") as c:
        for n, want in cases:
            mse = 1.0 / n
            case = f"mse = 1/{n}"
            got = c.call(psnr, torch.tensor(mse), case=case)
            v = to_numpy(got)
            if v is None:
                continue
            if v.size != 1:
                c.fail(f"{case}: expected a single number, got shape {v.shape}")
                continue
            v = float(v.reshape(()))
            if abs(v - want) < 1e-4:
                c.expect(True, f"{case}: PSNR = -10 log10(mse)", "")
            elif abs(v + want) < 1e-4:
                c.fail(f"{case}: got {v:.3f} dB: the sign is flipped, PSNR = -10 log10(mse)")
            elif abs(v + 10 * math.log(mse)) < 1e-3 or abs(v + math.log10(mse)) < 1e-4:
                c.fail(f"{case}: got {v:.3f} dB: PSNR = -10 log10(mse), with the base-10 logarithm and the factor 10")
            elif abs(v - want / 2) < 1e-4:
                c.fail(f"{case}: got {v:.3f} dB: PSNR = -10 log10(mse) = -20 log10(rmse); the factor is 10 for the MSE")
            else:
                c.fail(f"{case}: got {v:.3f} dB, expected {want:.2f}: PSNR = -10 log10(mse) for images in [0, 1]")

"""Checks of notebook 07 (the NeRF MLP): the ``NeRF`` module and ``psnr``.

``check_nerf_model(NeRF)`` grades the network by **what it computes**, never by the layers it
declares: it builds the student's class with its default arguments (the paper's network: 8 ReLU
layers of width 256, the encoded position concatenated again after the 4th, a density head, a
view-dependent branch and a sigmoid RGB head) and with two small configurations (drawn per fixture),
copies the reference's test weights into its layers and compares the outputs with the reference's
on the fixture's points (``nerf_model``, built by ``python -m course_lib fixtures nerf_model``):

* points: with the reference's weights, the density equals the reference's (the trunk with its skip
  input, the density head, its ReLU) and the colour equals the reference's (the view branch);
* gates (they earn nothing, a failure costs): the layer sizes, the output shapes, rgb in [0, 1],
  sigma >= 0, sigma independent of the viewing direction, rgb dependent on it. A class with the
  right layers whose forward returns constants earns nothing;
* defining properties (failing one costs at least half of the points): the skip input (the
  encoded position concatenated again) and the ReLU density (a sigmoid, softplus, exp, abs or no
  activation on the density is named).

Conventions that are the same maths are accepted: the skip concatenated as ``[h, γ(x)]`` as well as
``[γ(x), h]``, and the heads defined before the trunk (the test weights are copied by role).

**Graded on its own:** the network is fed the *reference* positional encoding of the check's points
(notebook 06's exercise). In the notebook, :func:`encoding_table` answers ``positional_encoding``
from the stored reference values (a table, no computation: the kit ships no encoding); the check
puts it in place of the notebook's ``positional_encoding`` while it runs. In grading, the grader
answers the student's ``positional_encoding`` with the reference's, through a call-back
(:mod:`course_lib.instructor.oracle`). A mistake in notebook 06 never costs NeRF points.

``check_psnr(psnr)``: PSNR in dB of images in [0, 1] on the fixture's MSE values; names the
flipped sign, a peak of 255, the natural logarithm, the factor 20 with the MSE.
"""

from __future__ import annotations

import contextlib
import math
import sys
from collections import Counter
from typing import Callable

import numpy as np

from course_lib.checks.core import FAILED, Check, Outcome, as_float, declare_defining, load_fixture, report_cases
from course_lib.checks.nerf_data import close

__all__ = ["check_nerf_model", "check_psnr", "layer_table", "expected_layers", "config_kwargs", "probe_weights",
           "copy_probe_weights", "encoding_table", "CONFIG_NAMES"]

FIXTURE = "nerf_model"

#: The configurations the check builds, by name; their sizes are stored in the fixture (``<name>_config``).
CONFIG_NAMES = ("default", "small", "tiny")
#: ``<name>_config`` holds: depth, width, skip index, pos_freqs, dir_freqs, view_width.
CONFIG_FIELDS = ("depth", "width", "skips", "pos_freqs", "dir_freqs", "view_width")

SKIP, RELU = "skip input", "ReLU density"
declare_defining("NeRF", {
    SKIP: "the encoded position γ(x) is concatenated again with the trunk's features after the skip layer",
    RELU: "the density is ReLU(raw) >= 0, unbounded above (a sigmoid caps it at 1: nothing is opaque)",
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


# --------------------------------------------------------------------------- the reference encoding, as a table


def encoding_table(rows, values) -> Callable:
    """``positional_encoding(x, n_freqs, include_input=True)`` answered from stored reference values.

    The table holds the reference's encoding (identity term first, then sin and cos of each
    frequency, ``L_max`` frequencies) of the check's points and directions; asked for ``L <= L_max``
    it returns the first columns (the encoding with fewer frequencies is a prefix). It computes no
    sine: a point that is not in the table raises :class:`LookupError`.

    Args:
        rows: ``(N, D)`` the points.
        values: ``(N, D (1 + 2 L_max))`` their encodings.
    """
    import torch

    keys = torch.as_tensor(np.asarray(rows, np.float64))
    table = torch.as_tensor(np.asarray(values, np.float32))
    D = keys.shape[1]
    L_max = (table.shape[1] // D - 1) // 2

    def positional_encoding(x, n_freqs, include_input=True):
        x = torch.as_tensor(x)
        L = int(n_freqs)
        if x.shape[-1] != D or not 0 <= L <= L_max:
            raise LookupError(f"the check's reference encoding holds (..., {D}) inputs and up to {L_max} frequencies; "
                              f"it was asked for shape {tuple(x.shape)} with n_freqs={n_freqs}")
        flat = x.detach().reshape(-1, D).to("cpu", torch.float64)
        dist, idx = torch.cdist(flat, keys).min(dim=1) if len(flat) else (torch.zeros(0), torch.zeros(0, dtype=int))
        if len(flat) and float(dist.max()) > 1e-4:
            raise LookupError("the check's reference encoding was asked for a point it does not hold: encode the "
                              "points pts and the directions viewdirs that forward receives, as they are")
        out = table[idx][:, (0 if include_input else D):D * (1 + 2 * L)]
        dtype = x.dtype if x.is_floating_point() else torch.float32
        return out.to(device=x.device, dtype=dtype).reshape(*x.shape[:-1], out.shape[-1])

    return positional_encoding


@contextlib.contextmanager
def _reference_encoding(NeRF, f):
    """While the check runs: the notebook's ``positional_encoding`` is the reference's table (restored after).

    Only where the class was defined in this process (the notebook, a test module); a class running in
    the grader's student process gets the table from the grader.
    """
    module = sys.modules.get(getattr(NeRF, "__module__", None) or "")
    local = module is not None and (module.__name__ == "__main__" or hasattr(module, "positional_encoding"))
    if not local or "enc_rows" not in f:
        yield
        return
    missing = object()
    saved = module.__dict__.get("positional_encoding", missing)
    module.positional_encoding = encoding_table(f["enc_rows"], f["enc_values"])
    try:
        yield
    finally:
        if saved is missing:
            del module.positional_encoding
        else:
            module.positional_encoding = saved


# --------------------------------------------------------------------------- layers and test weights


def config_kwargs(f, name: str) -> tuple[dict, dict]:
    """``(constructor kwargs, full configuration)`` of configuration ``name`` (the default one: no kwargs)."""
    vals = [int(v) for v in f[f"{name}_config"]]
    cfg = dict(zip(CONFIG_FIELDS, vals))
    cfg["skips"] = (cfg["skips"],)
    return ({} if name == "default" else dict(cfg)), cfg


def expected_layers(cfg: dict) -> list[tuple[int, int]]:
    """``[(in, out)]`` of the documented network's ``nn.Linear`` layers, in the docstring's order of definition."""
    W, enc, encd = cfg["width"], 3 * (1 + 2 * cfg["pos_freqs"]), 3 * (1 + 2 * cfg["dir_freqs"])
    out, n_in = [], enc
    for i in range(cfg["depth"]):
        out.append((n_in, W))
        n_in = W + (enc if i in cfg["skips"] else 0)
    return out + [(n_in, 1), (n_in, W), (W + encd, cfg["view_width"]), (cfg["view_width"], 3)]


def layer_table(model) -> list[tuple[int, int]]:
    """``[(in_features, out_features), ...]`` of the model's ``nn.Linear`` layers, in order of definition."""
    import torch.nn as nn

    return [(m.in_features, m.out_features) for m in model.modules() if isinstance(m, nn.Linear)]


def probe_weights(cfg: dict, seed: int, sigma_bias: float | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Deterministic test weights ``[(W (out, in), b (out,))]`` of the documented layers (:func:`expected_layers`).

    ``sigma_bias``: the density head's bias (the fixture stores one that makes about half of the raw
    densities positive, so that the ReLU matters).
    """
    g = np.random.default_rng(np.random.SeedSequence([int(seed), 7]))
    out = []
    for n_in, n_out in expected_layers(cfg):
        out.append(((g.standard_normal((n_out, n_in)) * 1.5 / math.sqrt(n_in)).astype(np.float32),
                    (g.standard_normal(n_out) * 0.1).astype(np.float32)))
    if sigma_bias is not None:
        out[cfg["depth"]] = (out[cfg["depth"]][0], np.full(1, sigma_bias, np.float32))
    return out


def copy_probe_weights(model, cfg: dict, seed: int, feature_pos: int, skip_h_first: bool, dirs_first: bool,
                       sigma_bias: float | None = None) -> bool:
    """Copy the test weights into ``model``'s linear layers, matched by role; False if the sizes differ.

    Layers are matched by their size, in order of definition, so the heads may come before or after the
    trunk. The feature layer has the trunk's size: ``feature_pos`` says which of the model's
    ``(width, width)`` layers it is (-1: the last, as documented). ``skip_h_first``: the skip layer's
    input is ``[h, γ(x)]``, ``dirs_first``: the view layer's input is ``[γ(d), feature]`` (their
    weights' columns are swapped to match).
    """
    import torch

    layers = _linear_params(model)
    ref = expected_layers(cfg)
    if layers is None or sorted(shp for shp, _, _ in layers) != sorted(ref):
        return False
    n, W = cfg["depth"], cfg["width"]
    square = [i for i, (shp, _, _) in enumerate(layers) if shp == (W, W)]
    feature_at = square[feature_pos] if square else None
    pool: dict = {}
    for k, shp in enumerate(ref):
        if k != n + 1:  # the feature layer is placed by feature_pos
            pool.setdefault(shp, []).append(k)
    weights = probe_weights(cfg, seed, sigma_bias)
    enc = 3 * (1 + 2 * cfg["pos_freqs"])
    skip_layers = {s + 1 for s in cfg["skips"]}
    with torch.no_grad():
        for i, (shp, weight, bias) in enumerate(layers):
            k = n + 1 if i == feature_at else pool[shp].pop(0)
            w, b = weights[k]
            if skip_h_first and k in skip_layers:
                w = np.concatenate([w[:, enc:], w[:, :enc]], axis=1)
            if dirs_first and k == n + 2:
                w = np.concatenate([w[:, W:], w[:, :W]], axis=1)
            weight.copy_(torch.as_tensor(w))
            bias.copy_(torch.as_tensor(b))
    return True


def _linear_params(model) -> list | None:
    """``[((in, out), weight, bias)]`` of the model's linear layers, from its parameters (in order of definition).

    Read from ``model.parameters()`` (weight and bias of each layer in turn), so that it works for a
    model that lives in another process too; None when the parameters are not those of its linear layers.
    """
    params = list(model.parameters())
    table = layer_table(model)
    if len(params) != 2 * len(table):
        return None
    out = []
    for k, (n_in, n_out) in enumerate(table):
        w, b = params[2 * k], params[2 * k + 1]
        if tuple(w.shape) != (n_out, n_in) or tuple(b.shape) != (n_out,):
            return None
        out.append(((n_in, n_out), w, b))
    return out


def _layer_hint(mine: list[tuple[int, int]], ref: list[tuple[int, int]], cfg: dict) -> tuple[str, bool, str | None]:
    """What the layer table shows: ``(text, whether the skip input is what is wrong, the mistake's key)``.

    A mistake is named only when the layers that differ from the documented ones are exactly the layers
    that mistake gives; otherwise the text lists the missing and unexpected layers.
    """
    cm, cr = Counter(mine), Counter(ref)
    missing, extra = cr - cm, cm - cr
    W, VW = cfg["width"], cfg["view_width"]
    enc, encd = 3 * (1 + 2 * cfg["pos_freqs"]), 3 * (1 + 2 * cfg["dir_freqs"])
    d = f"layers (in, out): missing {sorted(missing.elements())}, unexpected {sorted(extra.elements())}"
    skip_in = (W + enc, W)

    def exactly(miss: list, ext: list) -> bool:
        return missing == Counter(miss) and extra == Counter(ext)

    patterns = [
        ("no_skip", [skip_in], [(W, W)], True,
         f"no skip connection: after trunk layer {cfg['skips'][0]} concatenate the encoded input again, "
         f"h = torch.cat([γ(x), h], -1), so that the next layer takes {enc} + {W} inputs"),
        ("raw_skip", [skip_in], [(W + 3, W)], True,
         f"the skip concatenates the raw position x (3 values): concatenate the ENCODED position γ(x) ({enc} + {W} "
         "inputs)"),
        ("not_encoded", [(enc, W), skip_in], [(3, W), (W + 3, W)], False,
         f"the positions are not encoded: the first layer and the skip take γ(x) ({enc} inputs), not x (3)"),
        ("not_encoded_first", [(enc, W)], [(3, W)], False,
         f"the positions are not encoded: the first layer takes γ(x) ({enc} inputs), not x (3)"),
        ("view_unused", [(W + encd, VW)], [(W, VW)], False,
         f"the view direction is not used: the colour branch takes [feature, γ(d)] ({W} + {encd} inputs)"),
        ("view_raw", [(W + encd, VW)], [(W + 3, VW)], False,
         f"the colour branch takes the raw viewing direction (3 values): use its encoding γ(d) ({encd} values)"),
        ("view_in_trunk", [(enc, W), skip_in, (W + encd, VW)], [(enc + encd, W), (W + enc + encd, W), (W, VW)], False,
         "the viewing direction enters the trunk (its first layer takes [γ(x), γ(d)]): the density must not depend "
         "on the view; feed γ(d) only to the colour branch, [feature, γ(d)]"),
    ]
    for key, miss, ext, skip, text in patterns:
        if exactly(miss, ext):
            return text, skip, key
    if not missing and not extra and mine != ref:
        pos = [i for i, (n_in, _) in enumerate(mine) if n_in == W + enc]
        return (f"the skip input goes into layer {pos[0] if pos else '?'} of the trunk; with skips={cfg['skips']} the "
                f"output of layer {cfg['skips'][0]} (0-based) is concatenated with γ(x), so layer "
                f"{cfg['skips'][0] + 1} takes {enc} + {W} inputs"), True, "skip_position"
    if any(o == 4 for _, o in extra.elements()):
        return ("one head with 4 outputs: the density comes from the position branch (W -> 1) and the colour from the "
                f"view-dependent branch (-> 3); {d}"), False, None
    return d, False, None


def _outputs(c: Check, model, pts, dirs, lead, case: str):
    """``(rgb, sigma)`` as numpy arrays of the right shapes, or None (the failure recorded)."""
    import torch

    with torch.no_grad():
        out = c.call(model, pts, dirs, case=f"{case} forward")
    out = c.fields(out, case, ("rgb", "sigma"), "(rgb, sigma) from forward")
    if out is None:
        return None
    rgb, sigma = (as_float(v) for v in out)
    drop = f"drop the last axis (sigma[..., 0]) so that it is {lead}"
    if not (c.shape(rgb, (*lead, 3), f"{case}: rgb") & c.shape(sigma, lead, f"{case}: sigma", {(*lead, 1): drop})):
        return None
    return rgb, sigma


def _quiet_forward(model, pts, dirs, lead):
    """``(rgb, sigma)`` of a forward pass as numpy arrays, or None when it raises or has other shapes."""
    import torch

    try:
        with torch.no_grad():
            rgb, sigma = model(pts, dirs)
    except Exception:  # noqa: BLE001 - the first call reported it already
        return None
    rgb, sigma = as_float(rgb), as_float(sigma)
    if rgb is None or sigma is None or rgb.shape != (*lead, 3) or sigma.size != int(np.prod(lead)):
        return None
    return rgb, sigma.reshape(lead)


def _with_reference_weights(model, cfg, seed, pts, dirs, lead, ref_rgb, raw, bias):
    """The model's outputs with the test weights copied in, in the order of definition that fits best.

    Returns ``(rgb, sigma, trunk_ok)`` or None (the weights do not fit). ``trunk_ok``: sigma is some
    activation of the reference's raw density, so the trunk and its skip input compute what the reference's do.
    """
    acts = [lambda r: np.maximum(r, 0.0)] + [g for _, g in DENSITY_VARIANTS]
    square = sum(1 for shp in expected_layers(cfg) if shp == (cfg["width"], cfg["width"]))
    best = None
    for pos in [-1] + list(range(square - 1)):
        for swap in (False, True):
            if not copy_probe_weights(model, cfg, seed, pos, swap, False, bias):
                return None
            got = _quiet_forward(model, pts, dirs, lead)
            if got is None:
                continue
            trunk_ok = any(close(got[1], g(raw)) for g in acts)
            if best is None or (trunk_ok and not best[3]):
                best = (pos, swap, got, trunk_ok)
            if trunk_ok:
                break
        if best is not None and best[3]:
            break
    if best is None:
        return None
    pos, swap, (rgb, sigma), trunk_ok = best
    if trunk_ok and not close(rgb, ref_rgb) and copy_probe_weights(model, cfg, seed, pos, swap, True, bias):
        other = _quiet_forward(model, pts, dirs, lead)
        if other is not None and close(other[0], ref_rgb):
            rgb = other[0]
    return rgb, sigma, trunk_ok


def _own_init_gates(c: Check, model, rgb, sigma, pts, dirs, lead, case: str) -> None:
    """Range and view-dependence gates on the model's own initialisation (earn nothing, a failure costs)."""
    import torch

    c.gate(rgb.min() >= 0 and rgb.max() <= 1, f"{case}: rgb in [0, 1]",
           f"{case}: rgb ranges over [{rgb.min():.3g}, {rgb.max():.3g}]: no sigmoid on the RGB head")
    c.gate(sigma.min() >= 0, f"{case}: sigma >= 0",
           f"{case}: sigma has negative values (min {sigma.min():.3g}): the density must be non-negative, "
           "apply a ReLU to the density head", defining=RELU)
    other = _outputs(c, model, pts, torch.flip(dirs, dims=(0,)), lead, case)
    if other is not None:
        c.gate(close(other[1], sigma), f"{case}: sigma does not depend on the viewing direction",
               f"{case}: sigma changes with the viewing direction: the density head must branch off "
               "before the view direction is concatenated")
        c.gate(not np.array_equal(other[0], rgb), f"{case}: rgb depends on the viewing direction",
               f"{case}: rgb ignores viewdirs: concatenate γ(d) with the feature vector before the colour layer")


def _build(c: Check, NeRF, kw: dict):
    """``(case, model)``: the student's network built with ``kw`` (torch seeded), or :data:`FAILED` after a failure."""
    import torch

    case = "NeRF(" + ", ".join(f"{k}={v}" for k, v in kw.items()) + ")"
    torch.manual_seed(0)
    model = c.call(NeRF, case=case, **kw)
    if model is not FAILED and not isinstance(model, torch.nn.Module):
        c.fail(f"{case}: expected an nn.Module, got {type(model).__name__}")
        model = FAILED
    return case, model


def _check_config(c: Check, NeRF, f, name: str, pts, dirs, lead, seed: int) -> None:
    """The checks of one configuration: layer sizes, outputs, and the outputs with the reference's weights."""
    kw, cfg = config_kwargs(f, name)
    case, model = _build(c, NeRF, kw)
    own = None
    if model is not FAILED:
        ref_layers, mine = expected_layers(cfg), layer_table(model)
        hint, skip_mistake, key = _layer_hint(mine, ref_layers, cfg)  # a missing skip is named here
        c.gate(sorted(mine) == sorted(ref_layers), f"{case}: {len(ref_layers)} linear layers of the documented sizes",
               f"{case}: {hint}", defining=SKIP if skip_mistake else None, named=key)
        own = _outputs(c, model, pts, dirs, lead, case)
    if own is not None and name == "default":
        _own_init_gates(c, model, *own, pts, dirs, lead, case)
    ref_rgb, ref_sigma, raw = (f[f"{name}_{k}"].astype(float) for k in ("rgb", "sigma", "sigma_raw"))
    bias = float(f[f"{name}_sigma_bias"][0])
    res = None if own is None else _with_reference_weights(model, cfg, seed, pts, dirs, lead, ref_rgb, raw, bias)
    with_w = f"{case}: with the reference's weights"
    if res is None:
        why = ("its layers do not have the documented sizes (see above), so the reference's weights cannot be copied in"
               if own is not None else "the network could not be built (see above)" if model is FAILED else
               "its forward pass did not return rgb (..., 3) and sigma (...) as documented (see above)")
        for what, prop in (("the density's input (trunk and skip)", None), ("sigma", None), ("rgb", None)):
            c.fail(f"{with_w}, {what} cannot be compared: {why}", defining=prop)
        return
    rgb, sigma, trunk_ok = res
    no_relu = f.get(f"{name}_sigma_no_trunk_relu")
    trunk_hint = ("no ReLU after the trunk layers: h = torch.relu(layer(h)) after every trunk layer"
                  if no_relu is not None and close(sigma, no_relu.astype(float)) else
                  f"the density differs: check the ReLU after every trunk layer, the skip (γ(x) concatenated with "
                  f"the output of trunk layer {cfg['skips'][0]}) and that sigma is read off the last trunk layer")
    c.expect(trunk_ok, f"{with_w}, the trunk and its skip input compute the reference's features",
             f"{with_w}: {trunk_hint}", defining=SKIP if trunk_ok else None,
             named="no_trunk_relu" if trunk_hint.startswith("no ReLU") else None)
    act = next((why for why, g in DENSITY_VARIANTS if close(sigma, g(raw))), None)
    ok_sig = close(sigma, ref_sigma)
    c.expect(ok_sig, f"{with_w}, sigma = ReLU(density head) equals the reference's",
             f"{with_w}: " + (act or "sigma differs from the reference's (see the line above)"),
             defining=RELU if ok_sig or act is not None else None, named=act and act[:30])
    rgb_hint = _rgb_hint(f, name, rgb, trunk_ok)
    c.expect(close(rgb, ref_rgb), f"{with_w}, rgb equals the reference's", f"{with_w}: " + rgb_hint,
             named=rgb_hint[:30] if rgb_hint.startswith(("a ReLU", "rgb outside")) else None)


def _rgb_hint(f, name: str, rgb: np.ndarray, trunk_ok: bool) -> str:
    feat = f.get(f"{name}_rgb_feature_relu")
    if not trunk_ok:
        return "rgb differs as well (it is computed from the trunk's features)"
    if feat is not None and close(rgb, feat.astype(float)):
        return "a ReLU on the feature layer: the feature vector has no activation (only the view layer has a ReLU)"
    if rgb.min() < 0 or rgb.max() > 1:
        return "rgb outside [0, 1]: no sigmoid on the RGB head (put torch.sigmoid on it)"
    return ("rgb differs: the colour is sigmoid(rgb_head(relu(view_layer(torch.cat([feature(h), γ(d)], -1))))), "
            "with γ(d) the encoded viewing direction")


def _no_viewdirs_case(c: Check, NeRF, f, pts, dirs, lead) -> None:
    """``use_viewdirs=False`` (the smallest configuration): the colour must not depend on the viewing direction.

    A gate: a constant network satisfies it as well as a right one; ignoring the argument costs one check.
    """
    import torch

    kw, _ = config_kwargs(f, CONFIG_NAMES[-1])
    case, model = _build(c, NeRF, dict(kw, use_viewdirs=False))
    if model is FAILED:
        return
    own = _outputs(c, model, pts, dirs, lead, case)
    other = None if own is None else _quiet_forward(model, pts, torch.flip(dirs, dims=(0,)), lead)
    if other is None:
        return
    c.gate(close(other[0], own[0]), f"{case}: rgb does not depend on the viewing direction",
           f"{case}: rgb changes with the viewing direction although use_viewdirs=False: with use_viewdirs=False the "
           "colour comes from the trunk's features alone (the docstring: only the trunk, the density head and "
           "nn.Linear(., 3) on the trunk output, no view branch)")


def check_nerf_model(NeRF: Callable) -> None:
    """Check the student's ``NeRF`` class (notebook 07) by what it computes; prints one verdict per property."""
    import torch

    f = load_fixture(FIXTURE)
    pts, dirs = torch.as_tensor(f["pts"]), torch.as_tensor(f["dirs"])
    lead = tuple(f["pts"].shape[:-1])
    seed = int(f["weight_seed"][0])
    with Check("NeRF") as c, _reference_encoding(NeRF, f):
        for name in CONFIG_NAMES:
            _check_config(c, NeRF, f, name, pts, dirs, lead, seed)
        _no_viewdirs_case(c, NeRF, f, pts, dirs, lead)
        c.causes(NeRF, [
            (r"!(?s:use_viewdirs.*use_viewdirs)", "your class never reads use_viewdirs: with use_viewdirs=False, build no view branch and "
                              "put nn.Linear(., 3) on the trunk output"),
            (r"\babs\(", "torch.abs on the density: σ = torch.relu(raw), zero where the raw output is negative"),
            ((r"\b(?:clamp|clip)\(", r"!\bsigmoid\b"), "clamping the colour gives no gradient outside [0, 1]: the RGB head ends in "
                                    "torch.sigmoid"),
            (r"cat\(\s*\[?\s*(?:pts|x|h)\s*,\s*(?:viewdirs|dirs|d)\b",
             "the viewing direction joins only the colour branch, after the feature layer, never the trunk"),
        ])


# --------------------------------------------------------------------------- psnr


#: Wrong formulas of the PSNR of images in [0, 1]: (mistake, value as a function of the MSE).
PSNR_VARIANTS = (
    ("the sign is flipped: PSNR = -10 log10(mse) is positive for mse < 1", lambda m: 10 * math.log10(m)),
    ("a peak of 255: the kit's images are floats in [0, 1], so the peak is 1 and PSNR = -10 log10(mse)",
     lambda m: 10 * math.log10(255.0 ** 2 / m)),
    ("a peak of 255 and the sign flipped: the peak is 1 for images in [0, 1], PSNR = -10 log10(mse)",
     lambda m: -10 * math.log10(255.0 ** 2 / m)),
    ("the natural logarithm: PSNR = -10 log10(mse), with the base-10 logarithm", lambda m: -10 * math.log(m)),
    ("a factor 20 with the MSE: PSNR = -10 log10(mse) = -20 log10(rmse); the factor 20 goes with the RMSE",
     lambda m: -20 * math.log10(m)),
    ("the factor 10 is missing: PSNR = -10 log10(mse), in decibels", lambda m: -math.log10(m)),
    ("half the PSNR: -10 log10 of the RMSE; PSNR = -10 log10(mse) = -20 log10(rmse)",
     lambda m: -10 * math.log10(math.sqrt(m))),
)


def check_psnr(psnr: Callable) -> None:
    """Check ``psnr(mse) -> float``: peak signal-to-noise ratio in dB of images in [0, 1], -10 log10(mse)."""
    import torch

    f = load_fixture(FIXTURE)
    with Check("psnr") as c:
        outcomes = []
        for k, (mse, want) in enumerate(zip(f["psnr_mse"].astype(float), f["psnr_db"].astype(float))):
            case = f"mse number {k + 1} (a scalar tensor)"
            v = as_float(c.call(psnr, torch.tensor(mse, dtype=torch.float32), case=case))
            if v is None:
                continue
            if v.size != 1:
                c.fail(f"{case}: expected a single number, got shape {v.shape}")
                continue
            v = float(v.reshape(()))
            outcomes.append(Outcome(case, close(v, want), "PSNR = -10 log10(mse)",
                                    f"got {v:.3f} dB, expected {want:.3f} for mse = {mse:.4g}",
                                    {why for why, g in PSNR_VARIANTS if close(v, g(mse))},
                                    "PSNR = -10 log10(mse) for images in [0, 1] (peak 1)"))
        report_cases(c, outcomes, {why: why for why, _ in PSNR_VARIANTS})
        c.causes(psnr, [
            ((r"\blog\(", r"!\blog10\b"), "log is the natural logarithm: PSNR = -10 log10(mse)"),
            (r"\blog2\(", "log2 is the base-2 logarithm: PSNR = -10 log10(mse)"),
            (r"\b(?:0\.0\d*[1-9]|\d(?:\.\d+)?e-\d+)\b",
             "a small constant in your code (an epsilon?) changes a good model's PSNR (its MSE is 1e-3 or less): add nothing to the "
             "MSE, or 1e-10 at most"),
            (r"\b255\b", "255 is the peak of 8-bit images: the kit's images are floats in "
                                                   "[0, 1], peak 1"),
        ])

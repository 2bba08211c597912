"""Checks of notebook 06 (NeRF data and rays): get_rays, stratified sampling, query points, encoding.

Each ``check_*`` function runs the student's function on stored cases (fixture ``nerf_data``,
built from :mod:`course_lib.nerf.rays` and :mod:`course_lib.nerf.encoding` by
``python -m course_lib fixtures nerf_data``), compares with the stored reference results and with
properties, and names the likely mistake when something is off:

* ``get_rays``: meshgrid ij/xy transposition, OpenGL instead of OpenCV camera axes (y flipped,
  rays pointing backwards), the rotation transposed or missing, half-pixel offset (``W / 2``
  instead of ``cx``), normalized directions, ``rays_o`` not repeated per pixel.
* ``stratified_samples``: jitter in evaluation, no jitter in training, jitter larger than a bin,
  one jitter for all samples, ignoring the generator.
* ``query_points``: ``o + t d`` with the wrong broadcasting, ``o`` and ``d`` swapped.
* ``positional_encoding``: missing identity term, sin/cos order, missing (or extra) pi factor,
  wrong frequencies.

The helpers ``to_numpy`` and ``match_variant`` are shared with the other NeRF check modules.
The cases and the reference's results on them are stored arrays, made on the instructor's side
by :mod:`course_lib.instructor.cases.nerf_data`; this module imports no reference solution and ships
to students.
"""

from __future__ import annotations

import itertools
from typing import Callable

import numpy as np

from course_lib.checks.core import FAILED, Check, load_fixture

__all__ = [
    "check_get_rays",
    "check_stratified_samples",
    "check_query_points",
    "check_positional_encoding",
    "to_numpy",
    "match_variant",
    "encoding_variant",
]

FIXTURE = "nerf_data"


# --------------------------------------------------------------------------- shared helpers


def to_numpy(v) -> np.ndarray | None:
    """A float64 numpy array from a torch tensor, numpy array or nested list; None if impossible."""
    if v is FAILED or v is None:
        return None
    try:
        if hasattr(v, "detach"):
            v = v.detach().cpu().double().numpy()
        return np.asarray(v, dtype=float)
    except (TypeError, ValueError, RuntimeError):
        return None


def close(a, b, rtol: float = 1e-4, atol: float = 1e-5) -> bool:
    """Same shape and equal within tolerance (relative to b's scale)."""
    if a is None or b is None:
        return False
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.shape != b.shape or not np.isfinite(a).all():
        return False
    scale = max(1.0, float(np.abs(b).max()) if b.size else 1.0)
    return bool(np.allclose(a, b, rtol=rtol, atol=atol * scale))


def match_variant(value, variants: list[tuple[str, np.ndarray]], **tol) -> str | None:
    """The hint of the first variant that ``value`` equals (same shape, within tolerance), else None."""
    for hint, arr in variants:
        if arr is not None and close(value, arr, **tol):
            return hint
    return None


def _torch():
    import torch  # imported lazily: the check modules import without torch installed

    return torch


def as_tensor(a, dtype="float32"):
    """``a`` as a torch tensor of ``dtype`` (float32 by default), on the CPU."""
    torch = _torch()
    return torch.as_tensor(np.asarray(a), dtype=getattr(torch, dtype))


def _as_pair(out, c: Check, case: str, names=("rays_o", "rays_d")):
    if out is FAILED:
        return None
    if not isinstance(out, (tuple, list)) or len(out) != 2:
        c.fail(f"{case}: expected a tuple ({names[0]}, {names[1]}), got {type(out).__name__}")
        return None
    a, b = to_numpy(out[0]), to_numpy(out[1])
    if a is None or b is None:
        c.fail(f"{case}: {names[0]} and {names[1]} must be arrays (torch tensors)")
        return None
    return a, b


# --------------------------------------------------------------------------- fixtures


RAY_CASES = ("tiny", "orbit")


# --------------------------------------------------------------------------- get_rays


def _ray_variants(H, W, K, c2w, d_ref) -> list[tuple[str, np.ndarray]]:
    """Typical mistakes of get_rays, as the rays_d they produce (from the reference's rays_d)."""
    R = c2w[:3, :3]
    d_cam = d_ref @ R  # rows: R^T d, the reference directions in camera coordinates (z = 1)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    v = []
    flip = lambda s: (d_cam * np.array(s)) @ R.T  # noqa: E731
    v.append(("OpenGL camera axes (y up, z backwards): the kit's c2w is in OpenCV axes (x right, y down, "
              "z forward), so the camera-frame direction is ((u - cx) / fx, (v - cy) / fy, +1) with no sign flips", flip([1, -1, -1])))
    v.append(("rays point backwards: the camera looks along +z in the kit's OpenCV axes (not -z as in OpenGL)", flip([1, 1, -1])))
    v.append(("y is flipped: image rows grow downwards and so does the camera's y axis (OpenCV axes), "
              "use +(v - cy) / fy", flip([1, -1, 1])))
    v.append(("x is flipped: use +(u - cx) / fx", flip([-1, 1, 1])))
    v.append(("the rotation is transposed: rotate camera directions into the world with c2w[:3, :3] @ d "
              "(in row form d @ c2w[:3, :3].T)", d_cam @ R))
    v.append(("the directions are not rotated into the world: apply the rotation c2w[:3, :3]", d_cam))
    n = d_cam / np.linalg.norm(d_cam, axis=-1, keepdims=True)
    v.append(("the directions are normalized: the kit keeps d with z_cam = 1 so that z_vals are depths along "
              "the optical axis; do not normalize", n @ R.T))
    uu, vv = np.meshgrid(np.arange(W), np.arange(H), indexing="xy")
    for ox, oy, why in ((W / 2.0, H / 2.0, "W / 2 and H / 2"), (W / 2.0 - 0.5, H / 2.0 - 0.5, "(W - 1) / 2")):
        if np.isclose(ox, cx) and np.isclose(oy, cy):
            continue
        dc = np.stack([(uu - ox) / fx, (vv - oy) / fy, np.ones_like(uu, float)], axis=-1)
        v.append((f"the principal point is ignored ({why} used instead of K's cx, cy): use K[0, 2] and K[1, 2]", dc @ R.T))
    for s, where in ((0.5, "corners"), (-0.5, "corners")):
        dc = d_cam.copy()
        dc[..., 0] += s / fx
        dc[..., 1] += s / fy
        v.append((f"half-pixel offset: in the kit's convention the centre of pixel (0, 0) is at u = v = 0 "
                  f"(conventions.py), so use u = 0 ... W - 1 without +0.5", dc @ R.T))
    dc = np.stack([(uu - cx) / fy, (vv - cy) / fx, np.ones_like(uu, float)], axis=-1)
    v.append(("fx and fy are swapped: u goes with fx = K[0, 0], v with fy = K[1, 1]", dc @ R.T))
    return v


def check_get_rays(get_rays: Callable) -> None:
    """Check ``get_rays(H, W, K, c2w) -> (rays_o (H, W, 3), rays_d (H, W, 3))`` (notebook 06).

    Runs it on a tiny 3x4 camera and on an 6x8 camera on an orbit, compares with the reference,
    and names the likely mistake (meshgrid transposition, OpenGL axes, rotation, principal point).
    """
    f = load_fixture(FIXTURE)
    with Check("get_rays") as c:
        for name in RAY_CASES:
            H, W = (int(v) for v in f[f"rays_{name}_HW"])
            K, c2w = f[f"rays_{name}_K"].astype(float), f[f"rays_{name}_c2w"].astype(float)
            o_ref, d_ref = f[f"rays_{name}_o"].astype(float), f[f"rays_{name}_d"].astype(float)
            case = f"{H}x{W} camera ({name})"
            pair = _as_pair(c.call(get_rays, H, W, as_tensor(K), as_tensor(c2w), case=case), c, case)
            if pair is None:
                continue
            o, d = pair
            # rays_d: shape first, then values
            if d.shape == (W, H, 3) and close(np.swapaxes(d, 0, 1), d_ref):
                c.fail(f"{case}: rays_d has shape (W, H, 3) = {d.shape}: meshgrid ij/xy transposition; use "
                       "torch.meshgrid(u, v, indexing='xy') (or indexing='ij' with (v, u)) so that rows are image rows v")
                continue
            if d.shape == (H * W, 3):
                c.fail(f"{case}: rays_d has shape {d.shape}: return one ray per pixel as (H, W, 3) (reshape at the end)")
                continue
            if not c.shape(d, (H, W, 3), f"{case}: rays_d"):
                continue
            if close(d, d_ref):
                c.expect(True, f"{case}: rays_d matches the reference (one ray per pixel, OpenCV axes, z_cam = 1)", "")
            else:
                hint = match_variant(d, _ray_variants(H, W, K, c2w, d_ref))
                if hint is None:
                    d_cam = d @ c2w[:3, :3]
                    if np.all(d_cam[..., 2] < 0):
                        hint = "rays point backwards (z_cam < 0): the camera looks along +z in the kit's OpenCV axes"
                    else:
                        err = float(np.abs(d - d_ref).max())
                        hint = (f"rays_d differs from the reference (max error {err:.3g}): the camera-frame direction of "
                                "pixel (u, v) is ((u - cx) / fx, (v - cy) / fy, 1), rotated by c2w[:3, :3]")
                c.fail(f"{case}: {hint}")
            # rays_o
            if o.shape == (3,) or o.shape == (1, 1, 3):
                c.fail(f"{case}: rays_o has shape {o.shape}: repeat the camera centre for every pixel "
                       "(rays_o.expand(H, W, 3) or torch.broadcast_to)")
            elif c.shape(o, (H, W, 3), f"{case}: rays_o"):
                c.expect(close(o, o_ref), f"{case}: every ray starts at the camera centre c2w[:3, 3]",
                         f"{case}: rays_o is not the camera centre: it is the translation column c2w[:3, 3] "
                         "(the camera-to-world matrix maps the camera origin to its centre)")


# --------------------------------------------------------------------------- stratified sampling


def check_stratified_samples(stratified_samples: Callable) -> None:
    """Check ``stratified_samples(near, far, n_samples, n_rays, perturb, generator=None) -> z_vals (R, S)``.

    Evaluation (``perturb=False``) must give the reference's evenly spaced depths for every ray;
    training (``perturb=True``) one uniform sample inside each of the S bins, independent per ray
    and sample, reproducible with the given ``torch.Generator``.
    """
    torch = _torch()
    f = load_fixture(FIXTURE)
    near, far, S, R = (float(v) for v in f["strat_args"])
    S, R = int(S), int(R)
    z_ref = f["strat_z"].astype(float)
    # bins around the evaluation depths: edges at the midpoints, near and far at the ends
    mids = 0.5 * (z_ref[0, 1:] + z_ref[0, :-1])
    lower, upper = np.concatenate([[near], mids]), np.concatenate([mids, [far]])
    with Check("stratified_samples") as c:
        case = f"evaluation (perturb=False), near={near:g}, far={far:g}, {S} samples, {R} rays"
        z = to_numpy(c.call(stratified_samples, near, far, S, R, False, case=case))
        if z is not None and c.shape(z, (R, S), f"{case}: z_vals"):
            if close(z, z_ref):
                c.expect(True, f"{case}: the evenly spaced depths of the reference, the same for every ray", "")
            else:
                z2 = to_numpy(c.call(stratified_samples, near, far, S, R, False, case=case))
                inside = np.all((z >= lower - 1e-6) & (z <= upper + 1e-6))
                if z2 is not None and not close(z, z2):
                    c.fail(f"{case}: two calls give different depths: jitter in evaluation; perturb=False must give "
                           "fixed, evenly spaced depths (jitter only in training)")
                elif inside and not close(z, np.broadcast_to(z[:1], z.shape)):
                    c.fail(f"{case}: the depths differ between rays: jitter in evaluation (perturb=False must not jitter)")
                elif close(z, np.broadcast_to(np.linspace(near, far, S + 1)[:-1], z.shape)):
                    c.fail(f"{case}: the last depth is not far: use torch.linspace(near, far, n_samples)")
                else:
                    c.fail(f"{case}: z_vals are not the reference's evenly spaced depths from near to far "
                           f"(expected torch.linspace(near, far, n_samples) for every ray)")
        case = f"training (perturb=True), {S} samples, {R} rays"
        g1 = torch.Generator().manual_seed(0)
        zt = to_numpy(c.call(stratified_samples, near, far, S, R, True, generator=g1, case=case))
        if zt is not None and c.shape(zt, (R, S), f"{case}: z_vals"):
            c.gate(not close(zt, z_ref), f"{case}: the depths are jittered",
                     f"{case}: no jitter: with perturb=True draw one uniform sample inside each bin")
            inside = (zt >= lower - 1e-6) & (zt <= upper + 1e-6)
            c.expect(inside.all(), f"{case}: every sample lies in its own bin, so the depths are sorted",
                     f"{case}: {int((~inside).sum())} samples leave their bin: scale the uniform jitter by the bin "
                     "width (upper - lower), not by far - near")
            off = (zt - lower) / (upper - lower)
            varied_s = np.ptp(off, axis=1).min() > 1e-3
            varied_r = np.ptp(off, axis=0).min() > 1e-3
            c.expect(varied_s and varied_r, f"{case}: independent jitter for every ray and every sample",
                     f"{case}: the same jitter for every {'sample' if not varied_s else 'ray'}: draw a (n_rays, n_samples) "
                     "array of uniform numbers")
            zt2 = to_numpy(c.call(stratified_samples, near, far, S, R, True, generator=torch.Generator().manual_seed(0),
                                  case=case))
            if zt2 is not None:
                c.gate(close(zt, zt2), f"{case}: the same generator seed gives the same samples",
                         f"{case}: the same seed gave different samples: pass generator=generator to torch.rand")


# --------------------------------------------------------------------------- query points


def check_query_points(query_points: Callable) -> None:
    """Check ``query_points(rays_o (R, 3), rays_d (R, 3), z_vals (R, S)) -> pts (R, S, 3)``: o + t d."""
    f = load_fixture(FIXTURE)
    ro, rd, zv, ref = (f[k].astype(float) for k in ("query_o", "query_d", "query_z", "query_pts"))
    R, S = zv.shape
    with Check("query_points") as c:
        case = f"{R} rays, {S} samples"
        p = to_numpy(c.call(query_points, as_tensor(ro), as_tensor(rd), as_tensor(zv), case=case))
        if p is None:
            return
        if p.shape == (R, R, S) or (p.ndim == 3 and p.shape[-1] != 3):
            c.fail(f"{case}: pts has shape {p.shape}: add axes before broadcasting, "
                   "rays_o[:, None, :] + z_vals[..., None] * rays_d[:, None, :]")
            return
        if not c.shape(p, (R, S, 3), f"{case}: pts"):
            return
        variants = [
            ("rays_o and rays_d are swapped: the point at depth t is o + t d", rd[:, None] + zv[..., None] * ro[:, None]),
            ("the directions are normalized: use rays_d as given, so that t is the depth z_cam", ro[:, None] +
             zv[..., None] * (rd / np.linalg.norm(rd, axis=-1, keepdims=True))[:, None]),
            ("rays_o is missing: the point at depth t is o + t d", zv[..., None] * rd[:, None]),
        ]
        ok = close(p, ref)
        c.expect(ok, f"{case}: pts = o + t d matches the reference",
                 f"{case}: " + (match_variant(p, variants) or "pts differs from o + t d"))


# --------------------------------------------------------------------------- positional encoding


ORDERS = {
    "freq": "[x, sin(f0 x), cos(f0 x), sin(f1 x), cos(f1 x), ...] (sin and cos of each frequency side by side)",
    "freq_cos": "cos before sin for each frequency",
    "blocks": "all sines first, then all cosines",
    "coord": "grouped by coordinate (x0's frequencies, then x1's, ...)",
}
FREQS = {"pow2": "2^k for k = 0 ... L - 1", "pow2_from1": "2^k for k = 1 ... L", "linear": "k + 1 for k = 0 ... L - 1"}


def encoding_variant(x: np.ndarray, L: int, include_input: bool = True, pi: bool = True,
                     order: str = "freq", freqs: str = "pow2") -> np.ndarray:
    """One way of writing the positional encoding (the reference is one of them, the others are mistakes)."""
    x = np.asarray(x, float)
    k = np.arange(L, dtype=float)
    fr = {"pow2": 2.0 ** k, "pow2_from1": 2.0 ** (k + 1), "linear": k + 1.0}[freqs] * (np.pi if pi else 1.0)
    xf = x[..., None, :] * fr[:, None]  # (..., L, D)
    s, co = np.sin(xf), np.cos(xf)
    if order == "freq":
        parts = np.stack([s, co], axis=-2).reshape(*x.shape[:-1], -1)
    elif order == "freq_cos":
        parts = np.stack([co, s], axis=-2).reshape(*x.shape[:-1], -1)
    elif order == "blocks":
        parts = np.concatenate([s.reshape(*x.shape[:-1], -1), co.reshape(*x.shape[:-1], -1)], axis=-1)
    else:  # coord: for each coordinate, its sines and cosines
        parts = np.concatenate([np.swapaxes(s, -1, -2), np.swapaxes(co, -1, -2)], axis=-1).reshape(*x.shape[:-1], -1)
    return np.concatenate([x, parts], axis=-1) if include_input else parts


def _encoding_params(x, L, include_input, value) -> dict | None:
    """The (include_input, pi, order, freqs) of the variant equal to ``value``, or None."""
    for inc, pi, order, freqs in itertools.product((include_input, not include_input), (True, False), ORDERS, FREQS):
        if close(value, encoding_variant(x, L, inc, pi, order, freqs), rtol=1e-3, atol=2e-3):
            return {"include_input": inc, "pi": pi, "order": order, "freqs": freqs}
    return None


def _encoding_hint(mine: dict, ref: dict, include_input: bool) -> str:
    hints = []
    if mine["include_input"] != include_input:
        hints.append("missing identity term: the encoding starts with x itself, then the sines and cosines"
                     if include_input else "the identity term x should only be there with include_input=True")
    if mine["pi"] != ref["pi"]:
        hints.append("missing pi factor: use sin(2^k pi x) and cos(2^k pi x)" if ref["pi"]
                     else "no pi factor in the kit's encoding: use sin(2^k x), cos(2^k x)")
    if mine["freqs"] != ref["freqs"]:
        hints.append(f"wrong frequencies ({FREQS[mine['freqs']]}): use {FREQS[ref['freqs']]}")
    if mine["order"] != ref["order"]:
        hints.append(f"sin/cos order ({ORDERS[mine['order']]}): the kit's order is {ORDERS[ref['order']]}")
    return "; ".join(hints)


def check_positional_encoding(positional_encoding: Callable) -> None:
    """Check ``positional_encoding(x (..., D), n_freqs, include_input=True) -> (..., D (include_input + 2 L))``."""
    f = load_fixture(FIXTURE)
    x, dirs = f["enc_x"].astype(float), f["enc_dirs"].astype(float)
    cases = [
        ("positions, L=10", x, 10, True, f["enc_x_10"]),
        ("directions, L=4", dirs, 4, True, f["enc_dirs_4"]),
        ("include_input=False, L=3", x, 3, False, f["enc_x_3_noid"]),
        ("batch of shape (2, 3, 3), L=2", x.reshape(2, 3, 3), 2, True, f["enc_batch_2"]),
    ]
    ref_params = _encoding_params(x, 10, True, f["enc_x_10"].astype(float))
    with Check("positional_encoding") as c:
        for case, xin, L, inc, ref in cases:
            ref = ref.astype(float)
            out = to_numpy(c.call(positional_encoding, as_tensor(xin), L, include_input=inc, case=case))
            if out is None:
                continue
            D = xin.shape[-1]
            want = (*xin.shape[:-1], D * (int(inc) + 2 * L))
            if out.shape != want:
                hint = ""
                if inc and out.shape == (*xin.shape[:-1], 2 * L * D):
                    hint = ": missing identity term (the encoding starts with x itself)"
                elif not inc and out.shape == (*xin.shape[:-1], (1 + 2 * L) * D):
                    hint = ": with include_input=False leave out the identity term x"
                elif out.shape[:-1] != xin.shape[:-1]:
                    hint = ": keep the leading (batch) axes and concatenate along the last axis"
                c.fail(f"{case}: the encoding has shape {out.shape}, expected {want}{hint}")
                continue
            if close(out, ref, rtol=1e-3, atol=2e-3):  # float32 sin(2^9 pi x) is good to ~1e-4
                c.expect(True, f"{case}: shape {want} and values match the reference", "")
                continue
            mine = _encoding_params(xin, L, inc, out)
            if mine is not None and ref_params is not None:
                c.fail(f"{case}: {_encoding_hint(mine, ref_params, inc) or 'values differ from the reference'}")
            else:
                c.fail(f"{case}: the values differ from the reference (max error {float(np.abs(out - ref).max()):.3g}); "
                       "compare with the formula above: [x, sin(2^0 pi x), cos(2^0 pi x), ..., cos(2^(L-1) pi x)]")

"""Checks of notebook 06 (NeRF data and rays): get_rays, stratified sampling, query points, encoding.

Each ``check_*`` function runs the student's function on stored cases (fixture ``nerf_data``,
built from :mod:`course_lib.nerf.rays` and :mod:`course_lib.nerf.encoding` by
``python -m course_lib fixtures nerf_data``), compares with the stored reference results and with
properties, and names the likely mistake when something is off:

* ``get_rays``: meshgrid ij/xy transposition, OpenGL instead of OpenCV camera axes (y flipped,
  rays pointing backwards), the rotation transposed or missing, half-pixel offset (``W / 2``
  instead of ``cx``), normalized directions, ``rays_o`` not repeated per pixel.
* ``stratified_samples``: jitter in evaluation, no jitter in training, jitter larger than a bin,
  one jitter for all samples, ignoring the generator. Defining property (failing it costs at
  least half of the points): every training sample lies in its own bin, so the depths are sorted
  (the renderer's intervals t_{i+1} - t_i must be positive). The kit's bins (edges at the
  midpoints between the evaluation depths) and the paper's equal bins (width (far - near) / S) are
  both accepted.
* ``query_points``: ``o + t d`` with the wrong broadcasting (a broadcasting error is explained, not
  shown as torch's message alone), ``o`` and ``d`` swapped, the origin missing.
* ``positional_encoding``: missing identity term, sin/cos order, missing (or extra) pi factor,
  wrong frequencies.

The helpers ``to_numpy`` and ``match_variant`` are shared with the other NeRF check modules.
The cases, the reference's results on them and the results of the classic mistakes are stored
arrays, made on the instructor's side by :mod:`course_lib.instructor.cases.nerf_data` (the
mistakes by :mod:`course_lib.instructor.cases.nerf_variants`); this module computes no ray, sample
or encoding, imports no reference solution, and ships to students.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from course_lib.checks.core import FAILED, Check, declare_defining, load_fixture

__all__ = [
    "check_get_rays",
    "check_stratified_samples",
    "check_query_points",
    "check_positional_encoding",
    "to_numpy",
    "match_variant",
    "stored_variants",
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


def stored_variants(f: dict, prefix: str, hints: dict[str, str]) -> list[tuple[str, np.ndarray]]:
    """``[(hint, array)]`` of the mistakes stored under ``<prefix>__<label>`` whose label has a hint."""
    out = []
    for key in sorted(f):
        if key.startswith(prefix + "__"):
            label = key[len(prefix) + 2:]
            if label in hints:
                out.append((hints[label], f[key].astype(float)))
    return out


# --------------------------------------------------------------------------- fixtures


RAY_CASES = ("tiny", "orbit")

#: get_rays mistakes stored per camera (``rays_<case>_d__<label>``): label -> what to change.
RAY_HINTS = {
    "opengl": "OpenGL camera axes (y up, z backwards): the kit's c2w is in OpenCV axes (x right, y down, z forward), "
              "so the camera-frame direction is ((u - cx) / fx, (v - cy) / fy, +1) with no sign flips",
    "backwards": "rays point backwards: the camera looks along +z in the kit's OpenCV axes (not -z as in OpenGL)",
    "y_flip": "y is flipped: image rows grow downwards and so does the camera's y axis (OpenCV axes), use +(v - cy) / fy",
    "x_flip": "x is flipped: use +(u - cx) / fx",
    "transposed": "the rotation is transposed: rotate camera directions into the world with c2w[:3, :3] @ d "
                  "(in row form d @ c2w[:3, :3].T)",
    "not_rotated": "the directions are not rotated into the world: apply the rotation c2w[:3, :3]",
    "normalized": "the directions are normalized: the kit keeps d with z_cam = 1 so that z_vals are depths along "
                  "the optical axis; do not normalize",
    "centre_half": "the principal point is ignored (W / 2 and H / 2 used instead of K's cx, cy): use K[0, 2] and K[1, 2]",
    "centre_minus": "the principal point is ignored ((W - 1) / 2 used instead of K's cx, cy): use K[0, 2] and K[1, 2]",
    "half_plus": "half-pixel offset: in the kit's convention the centre of pixel (0, 0) is at u = v = 0 "
                 "(conventions.py), so use u = 0 ... W - 1 without +0.5",
    "half_minus": "half-pixel offset: in the kit's convention the centre of pixel (0, 0) is at u = v = 0 "
                  "(conventions.py), so use u = 0 ... W - 1 without -0.5",
    "f_swapped": "fx and fy are swapped: u goes with fx = K[0, 0], v with fy = K[1, 1]",
    "K_not_inverted": "K is applied instead of its inverse: the direction of pixel (u, v) is K^-1 (u, v, 1), "
                      "i.e. ((u - cx) / fx, (v - cy) / fy, 1)",
}


# --------------------------------------------------------------------------- get_rays


def _check_one_camera(c: Check, get_rays: Callable, f, name: str) -> None:
    H, W = (int(v) for v in f[f"rays_{name}_HW"])
    K, c2w = f[f"rays_{name}_K"].astype(float), f[f"rays_{name}_c2w"].astype(float)
    o_ref, d_ref = f[f"rays_{name}_o"].astype(float), f[f"rays_{name}_d"].astype(float)
    case = f"{H}x{W} camera ({name})"
    pair = _as_pair(c.call(get_rays, H, W, as_tensor(K), as_tensor(c2w), case=case), c, case)
    if pair is None:
        return
    o, d = pair
    if d.shape == (W, H, 3) and close(np.swapaxes(d, 0, 1), d_ref):
        c.fail(f"{case}: rays_d has shape (W, H, 3) = {d.shape}: meshgrid ij/xy transposition; use "
               "torch.meshgrid(u, v, indexing='xy') (or indexing='ij' with (v, u)) so that rows are image rows v",
               named="meshgrid")
        return
    if d.shape == (H * W, 3):
        c.fail(f"{case}: rays_d has shape {d.shape}: return one ray per pixel as (H, W, 3) (reshape at the end)")
        return
    if not c.shape(d, (H, W, 3), f"{case}: rays_d"):
        return
    if close(d, d_ref):
        c.expect(True, f"{case}: rays_d matches the reference (one ray per pixel, OpenCV axes, z_cam = 1)", "")
    else:
        hint = match_variant(d, stored_variants(f, f"rays_{name}_d", RAY_HINTS))
        named = hint and hint[:30]
        if hint is None:
            d_cam = d @ c2w[:3, :3]
            if np.all(d_cam[..., 2] < 0):
                hint = "rays point backwards (z_cam < 0): the camera looks along +z in the kit's OpenCV axes"
                named = "backwards"
            else:
                err = float(np.abs(d - d_ref).max())
                hint = (f"rays_d differs from the reference (max error {err:.3g}): the camera-frame direction of "
                        "pixel (u, v) is ((u - cx) / fx, (v - cy) / fy, 1), rotated by c2w[:3, :3]")
        c.fail(f"{case}: {hint}", named=named)
    if o.shape == (3,) or o.shape == (1, 1, 3):
        c.fail(f"{case}: rays_o has shape {o.shape}: repeat the camera centre for every pixel "
               "(rays_o.expand(H, W, 3) or torch.broadcast_to)")
    elif c.shape(o, (H, W, 3), f"{case}: rays_o"):
        c.expect(close(o, o_ref), f"{case}: every ray starts at the camera centre c2w[:3, 3]",
                 f"{case}: rays_o is not the camera centre: it is the translation column c2w[:3, 3] "
                 "(the camera-to-world matrix maps the camera origin to its centre)")


def check_get_rays(get_rays: Callable) -> None:
    """Check ``get_rays(H, W, K, c2w) -> (rays_o (H, W, 3), rays_d (H, W, 3))`` (notebook 06).

    Runs it on two cameras of the fixture (W != H, fx != fy, an off-centre principal point),
    compares with the reference, and names the likely mistake (meshgrid transposition, OpenGL
    axes, rotation, principal point).
    """
    f = load_fixture(FIXTURE)
    with Check("get_rays") as c:
        for name in RAY_CASES:
            _check_one_camera(c, get_rays, f, name)


# --------------------------------------------------------------------------- stratified sampling

BINS = "in their bins"
declare_defining("stratified_samples", {
    BINS: "every training sample lies in its own bin, so the depths are sorted: the renderer's intervals "
          "t_{i+1} - t_i must be positive",
})


def _bins(near: float, far: float, S: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The two accepted stratifications: ``{name: (lower (S,), upper (S,))}``."""
    z = near + (far - near) * np.arange(S) / (S - 1)
    mids = 0.5 * (z[1:] + z[:-1])
    edges = near + (far - near) * np.arange(S + 1) / S
    return {"kit": (np.concatenate([[near], mids]), np.concatenate([mids, [far]])),
            "paper": (edges[:-1], edges[1:])}


def _check_evaluation(c: Check, fn: Callable, near: float, far: float, S: int, R: int, z_ref: np.ndarray) -> None:
    case = f"evaluation (perturb=False), near={near:.3g}, far={far:.3g}, {S} samples, {R} rays"
    z = to_numpy(c.call(fn, near, far, S, R, False, case=case))
    if z is None or not c.shape(z, (R, S), f"evaluation (perturb=False), {S} samples, {R} rays: z_vals"):
        return
    if close(z, z_ref):
        c.expect(True, "evaluation (perturb=False): the evenly spaced depths of the reference, the same for every ray", "")
        return
    z2 = to_numpy(c.call(fn, near, far, S, R, False, case=case))
    named = "eval"
    lo, up = _bins(near, far, S)["kit"]
    inside = np.all((z >= lo - 1e-6) & (z <= up + 1e-6))
    step = (far - near) / S
    if z2 is not None and not close(z, z2):
        hint = "two calls give different depths: jitter in evaluation; perturb=False must give fixed, evenly " \
               "spaced depths (jitter only in training)"
    elif inside and not close(z, np.broadcast_to(z[:1], z.shape)):
        hint = "the depths differ between rays: jitter in evaluation (perturb=False must not jitter)"
    elif close(z, np.broadcast_to(near + step * np.arange(S), z.shape)):
        hint = "the last depth is not far: use torch.linspace(near, far, n_samples)"
    elif close(z, np.broadcast_to(near + step * (np.arange(S) + 0.5), z.shape)):
        hint = "the depths are the centres of S equal bins: in evaluation use torch.linspace(near, far, n_samples)"
    else:
        hint = "z_vals are not evenly spaced from near to far (expected torch.linspace(near, far, n_samples) for every ray)"
        named = None
    c.fail(f"{case}: {hint}", named=named and hint[:30])


def _bin_hint(zt: np.ndarray, near: float, far: float, S: int) -> str:
    lo, up = _bins(near, far, S)["kit"]
    z_even = near + (far - near) * np.arange(S) / (S - 1)
    out = int(np.sum((zt < lo - 1e-6) | (zt > up + 1e-6)))
    unsorted = bool(np.any(np.diff(zt, axis=1) < 0))
    rel = (zt - z_even) / (far - near)
    what = f"{out} samples leave their bin" + (" and the depths come out unsorted" if unsorted else "")
    if rel.min() > -1e-6 and rel.max() > 1.5 / S or rel.min() < -1.5 / S:
        why = "the jitter is scaled by far - near: scale the uniform numbers by the bin width (upper - lower)"
    elif zt.min() < near - 1e-6 or zt.max() > far + 1e-6:
        why = ("samples fall outside [near, far]: the first bin starts at near and the last ends at far (jitter "
               "z_i by +-half a bin only inside, with lower = [near, mids], upper = [mids, far])")
    else:
        why = ("draw z = lower + (upper - lower) * u with u uniform in [0, 1), lower = [near, mids], "
               "upper = [mids, far], mids the midpoints of the evaluation depths")
    return f"{what}: {why}"


def _check_training(c: Check, fn: Callable, near: float, far: float, S: int, R: int, seed: int, z_ref,
                    again: bool) -> None:
    """One training case; ``again``: call a second time with the same seed (reproducibility)."""
    import torch

    case = f"training (perturb=True), near={near:.3g}, far={far:.3g}, {S} samples, {R} rays"
    short = f"training (perturb=True), {S} samples, {R} rays"
    zt = to_numpy(c.call(fn, near, far, S, R, True, generator=torch.Generator().manual_seed(seed), case=case))
    if zt is None or not c.shape(zt, (R, S), f"{short}: z_vals"):
        return
    c.gate(not close(zt, z_ref), f"{short}: the depths are jittered",
           f"{case}: no jitter: with perturb=True draw one uniform sample inside each bin")
    fits = {k: np.all((zt >= lo - 1e-6) & (zt <= up + 1e-6)) for k, (lo, up) in _bins(near, far, S).items()}
    kind = next((k for k, ok in fits.items() if ok), None)
    bin_hint = _bin_hint(zt, near, far, S)
    c.expect(kind is not None, f"{short}: every sample lies in its own bin, so the depths are sorted",
             f"{case}: {bin_hint}", defining=BINS, named=None if "draw z = lower" in bin_hint else bin_hint[-40:])
    lo, up = _bins(near, far, S)[kind or "kit"]
    off = (zt - lo) / (up - lo)
    varied_s, varied_r = np.ptp(off, axis=1).min() > 1e-3, np.ptp(off, axis=0).min() > 1e-3
    c.expect(varied_s and varied_r, f"{short}: independent jitter for every ray and every sample",
             f"{case}: the same jitter for every {'sample' if not varied_s else 'ray'}: draw a (n_rays, n_samples) "
             "array of uniform numbers")
    if kind is not None:
        c.expect(off.min() < 0.25 and off.max() > 0.75, f"{short}: the jitter covers the whole bin",
                 f"{case}: the samples cover only [{off.min():.2f}, {off.max():.2f}] of their bins: draw u uniform "
                 "in [0, 1) and place the sample at lower + (upper - lower) * u")
    if not again:
        return
    zt2 = to_numpy(c.call(fn, near, far, S, R, True, generator=torch.Generator().manual_seed(seed), case=case))
    usable = zt2 is not None and np.shape(zt2) == np.shape(zt)  # an unusable second answer fails the gate too
    c.gate(usable and close(zt, zt2), f"{short}: the same generator seed gives the same samples",
           f"{case}: the same seed gave different samples: pass generator=generator to torch.rand" if usable else
           f"{case}: a second call with the same seed returned nothing usable (shape {np.shape(zt2)}, expected "
           f"{np.shape(zt)})", named="generator" if usable else None)


def check_stratified_samples(stratified_samples: Callable) -> None:
    """Check ``stratified_samples(near, far, n_samples, n_rays, perturb, generator=None) -> z_vals (R, S)``.

    Evaluation (``perturb=False``) must give the reference's evenly spaced depths for every ray;
    training (``perturb=True``) one uniform sample inside each of the S bins, independent per ray
    and sample, reproducible with the given ``torch.Generator`` (three cases of the fixture).
    """
    f = load_fixture(FIXTURE)
    with Check("stratified_samples") as c:
        near, far, S, R = (float(v) for v in f["strat_args"])
        _check_evaluation(c, stratified_samples, near, far, int(S), int(R), f["strat_z"].astype(float))
        for k, (near, far, S, R, seed) in enumerate(f["strat_train_args"]):
            S, R = int(S), int(R)
            _check_training(c, stratified_samples, float(near), float(far), S, R, int(seed),
                            f[f"strat_train_z_{k}"].astype(float), again=k == 0)


# --------------------------------------------------------------------------- query points

#: query_points mistakes stored per case (``query_<k>_pts__<label>``): label -> what to change.
QUERY_HINTS = {
    "swapped": "rays_o and rays_d are swapped: the point at depth t is o + t d",
    "normalized": "the directions are normalized: use rays_d as given, so that t is the depth z_cam",
    "no_origin": "rays_o is missing: the point at depth t is o + t d",
    "rays_on_samples": "the rays are broadcast along the samples axis (pts[r, s] uses ray s): give rays_o and rays_d "
                       "a samples axis, rays_o[:, None, :] + z_vals[..., None] * rays_d[:, None, :]",
    "no_depth_axis": "z_vals is used without a coordinate axis: z_vals[..., None] * rays_d[:, None, :]",
}
BROADCAST = ("size of tensor", "must match the size", "broadcast", "shape mismatch", "operands could not be")


def _query_call(c: Check, fn: Callable, args, case: str):
    """The student's pts, or None; a broadcasting error is explained, not only shown (one call per case)."""
    broadcast: list[Exception] = []

    def guarded(*a):
        try:
            return fn(*a)
        except Exception as exc:
            msg = str(exc).lower()
            if isinstance(exc, NotImplementedError) or not any(w in msg for w in BROADCAST):
                raise
            broadcast.append(exc)
            return np.zeros(0)  # a placeholder; the verdict below explains the error

    out = c.call(guarded, *args, case=case)
    if broadcast:
        exc = broadcast[0]
        c.fail(f"{case}: a broadcasting error ({type(exc).__name__}: {str(exc).splitlines()[0][:120]}): rays_o and "
               "rays_d are (R, 3), z_vals is (R, S); add axes so that they meet as (R, 1, 3) and (R, S, 1): "
               "rays_o[:, None, :] + z_vals[..., None] * rays_d[:, None, :]")
        return None
    return to_numpy(out)


def check_query_points(query_points: Callable) -> None:
    """Check ``query_points(rays_o (R, 3), rays_d (R, 3), z_vals (R, S)) -> pts (R, S, 3)``: o + t d."""
    f = load_fixture(FIXTURE)
    with Check("query_points") as c:
        for k in range(int(f["query_n"][0])):
            ro, rd, zv, ref = (f[f"query_{k}_{n}"].astype(float) for n in ("o", "d", "z", "pts"))
            R, S = zv.shape
            case = f"{R} rays, {S} samples"
            p = _query_call(c, query_points, (as_tensor(ro), as_tensor(rd), as_tensor(zv)), case)
            if p is None:
                continue
            if p.shape == (R, R, S) or (p.ndim == 3 and p.shape[-1] != 3):
                c.fail(f"{case}: pts has shape {p.shape}: add axes before broadcasting, "
                       "rays_o[:, None, :] + z_vals[..., None] * rays_d[:, None, :]")
                continue
            if not c.shape(p, (R, S, 3), f"{case}: pts"):
                continue
            hint = match_variant(p, stored_variants(f, f"query_{k}_pts", QUERY_HINTS))
            c.expect(close(p, ref), f"{case}: pts = o + t d matches the reference",
                     f"{case}: " + (hint or "pts differs from o + t d (pts[r, s] = rays_o[r] + z_vals[r, s] * rays_d[r])"),
                     named=hint and hint[:30])


# --------------------------------------------------------------------------- positional encoding

#: Encoding mistakes stored per case (``enc_<case>__<label>``): label -> what to change.
ENCODING_HINTS = {
    "no_identity": "missing identity term: the encoding starts with x itself, then the sines and cosines",
    "extra_identity": "the identity term x should only be there with include_input=True",
    "no_pi": "missing pi factor: use sin(2^k pi x) and cos(2^k pi x)",
    "cos_first": "sin/cos order (cos before sin for each frequency): the kit's order is "
                 "[x, sin(f0 x), cos(f0 x), sin(f1 x), cos(f1 x), ...]",
    "blocks": "sin/cos order (all sines first, then all cosines): the kit's order is "
              "[x, sin(f0 x), cos(f0 x), sin(f1 x), cos(f1 x), ...]",
    "coord": "sin/cos order (grouped by coordinate: x0's frequencies, then x1's, ...): for each frequency the kit "
             "puts the D sines, then the D cosines",
    "from1": "wrong frequencies (2^k for k = 1 ... L): use 2^k pi for k = 0 ... L - 1",
    "linear": "wrong frequencies (k + 1 for k = 0 ... L - 1): use the octaves 2^k pi for k = 0 ... L - 1",
    "half_angle": "wrong frequencies (2^(k-1) pi): use 2^k pi for k = 0 ... L - 1",
    "no_pi_blocks": "missing pi factor: use sin(2^k pi x) and cos(2^k pi x); sin/cos order (all sines first, "
                    "then all cosines): the kit's order is [x, sin(f0 x), cos(f0 x), ...]",
    "no_identity_no_pi": "missing identity term: the encoding starts with x itself; missing pi factor: use "
                         "sin(2^k pi x) and cos(2^k pi x)",
}
ENCODING_CASES = (("pos10", "positions, L={L}"), ("dir4", "directions, L={L}"), ("noid3", "include_input=False, L={L}"),
                  ("batch2", "a batch of shape {shape}, L={L}"))


def check_positional_encoding(positional_encoding: Callable) -> None:
    """Check ``positional_encoding(x (..., D), n_freqs, include_input=True) -> (..., D (include_input + 2 L))``."""
    f = load_fixture(FIXTURE)
    with Check("positional_encoding") as c:
        for key, label in ENCODING_CASES:
            xin, ref = f[f"enc_{key}_x"].astype(float), f[f"enc_{key}"].astype(float)
            L, inc = (int(v) for v in f[f"enc_{key}_args"])
            inc = bool(inc)
            case = label.format(L=L, shape=xin.shape)
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
                c.fail(f"{case}: the encoding has shape {out.shape}, expected {want}{hint}", named=hint[:30] or None)
                continue
            if close(out, ref, rtol=1e-3, atol=2e-3):  # float32 sin(2^9 pi x) is good to ~1e-4
                c.expect(True, f"{case}: shape {want} and values match the reference", "")
                continue
            hint = match_variant(out, stored_variants(f, f"enc_{key}", ENCODING_HINTS), rtol=1e-3, atol=2e-3)
            c.fail(f"{case}: " + (hint or f"the values differ from the reference (max error "
                                          f"{float(np.abs(out - ref).max()):.3g}); compare with the formula above: "
                                          "[x, sin(2^0 pi x), cos(2^0 pi x), ..., cos(2^(L-1) pi x)]"),
                   named=hint and hint[:30])

"""Checks of notebook 06 (NeRF data and rays): get_rays, stratified sampling, query points, encoding.

Cases (fixture ``nerf_data``, :mod:`course_lib.instructor.cases.nerf_data`, the mistakes' results by
:func:`course_lib.instructor.cases.nerf_data.encoding_variant`); what each check names:

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

The helpers ``close`` and ``matching`` are shared with the other NeRF check modules.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from course_lib.checks.core import Check, Outcome, as_float, close_rel, declare_defining, load_fixture, report_cases

__all__ = [
    "check_get_rays",
    "check_stratified_samples",
    "check_query_points",
    "check_positional_encoding",
    "close",
    "matching",
]

FIXTURE = "nerf_data"


# --------------------------------------------------------------------------- shared helpers


#: The NeRF checks' one tolerance, relative to the answer's scale: float32 results pass (float32 sin(2^9 pi x) is
#: good to ~1e-4), every named mistake is far beyond it.
NERF_RTOL = 1e-3


def close(a, b) -> bool:
    """The NeRF checks' one rule for "equal": :func:`~course_lib.checks.core.close_rel` within :data:`NERF_RTOL`
    (a number ``b`` stands for an array of ``a``'s shape)."""
    if a is None or b is None:
        return False
    return close_rel(a, np.full(np.shape(a), b) if np.ndim(b) == 0 else b, NERF_RTOL)


def matching(value, f: dict, prefix: str, hints: dict[str, str], suffix: str = "") -> list[str]:
    """The labels (keys of ``hints``) of the mistakes stored as ``<prefix>__<label><suffix>`` that ``value`` equals
    (:func:`close`), in the order of their keys."""
    labels = [(k, k[len(prefix) + 2:len(k) - len(suffix)]) for k in sorted(f)
              if k.startswith(prefix + "__") and k.endswith(suffix)]
    return [label for k, label in labels if label in hints and close(value, f[k].astype(float))]


def _torch():
    import torch  # imported lazily: the check modules import without torch installed

    return torch


def as_tensor(a, dtype="float32"):
    """``a`` as a torch tensor of ``dtype`` (float32 by default), on the CPU."""
    torch = _torch()
    return torch.as_tensor(np.asarray(a), dtype=getattr(torch, dtype))


def tensor_gate(c: Check, case: str, what: str, value, like) -> bool:
    """A gate: ``value`` is a torch tensor of the dtype of ``like`` (the kit's trainer and renderer, notebook 08,
    feed these results to torch code in float32: a numpy array or float64 crashes there)."""
    torch = _torch()
    ok = isinstance(value, torch.Tensor) and value.dtype == like.dtype
    got = (f"a {type(value).__name__}" if not isinstance(value, torch.Tensor) else f"a {value.dtype} tensor")
    return c.gate(ok, f"{case}: {what} is a {like.dtype} tensor, as its inputs",
                  f"{case}: {what} is {got}: return a torch tensor of the inputs' dtype ({like.dtype}); the kit's "
                  "trainer (notebook 08) calls your function with float32 tensors and computes in float32")


# --------------------------------------------------------------------------- fixtures


RAY_CASES = ("tiny", "orbit")

#: get_rays mistakes stored per camera (``rays_<case>_d__<label>``): label -> what to change.
RAY_HINTS = {
    "opengl": "OpenGL camera axes (y up, z backwards): the kit's c2w is in OpenCV axes (x right, y down, z forward), "
              "so the camera-frame direction is ((u - cx) / fx, (v - cy) / fy, +1) with no sign flips",
    "backwards": "rays point backwards: the camera looks along +z in the kit's OpenCV axes (not -z as in OpenGL)",
    "as_point": "the direction went through c2w as a point (rotation and translation): a direction only rotates, "
                "rays_d = d_cam @ c2w[:3, :3].T, without c2w[:3, 3] (which is rays_o)",
    "y_flip": "y is flipped: image rows grow downwards and so does the camera's y axis (OpenCV axes), use +(v - cy) / fy",
    "x_flip": "x is flipped: use +(u - cx) / fx",
    "transposed": "you rotated with the transpose: rotate camera directions into the world with c2w[:3, :3] @ d "
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


def _one_camera(c: Check, get_rays: Callable, f, name: str) -> Outcome | None:
    H, W = (int(v) for v in f[f"rays_{name}_HW"])
    K, c2w = f[f"rays_{name}_K"].astype(float), f[f"rays_{name}_c2w"].astype(float)
    case = f"{H}x{W} camera ({name})"
    K_t, c2w_t = as_tensor(K), as_tensor(c2w)  # the kit's trainer passes float32 tensors
    raw = c.fields(c.call(get_rays, H, W, K_t, c2w_t, case=case), case, ("rays_o", "rays_d"), "(rays_o, rays_d)")
    if raw is None:
        return None
    o, d = (as_float(v) for v in raw)
    if o is None or d is None:
        c.fail(f"{case}: rays_o and rays_d must be arrays (torch tensors)")
        return None
    tensor_gate(c, case, "rays_d", raw[1], K_t)
    d_ref = f[f"rays_{name}_d"].astype(float)
    if d.shape == (W, H, 3) and close(np.swapaxes(d, 0, 1), d_ref):
        c.fail(f"{case}: rays_d has shape (W, H, 3) = {d.shape}: you built the pixel grid with meshgrid's ij/xy "
               "transposed; use torch.meshgrid(u, v, indexing='xy') (or indexing='ij' with (v, u)) so that rows are "
               "image rows v", named="meshgrid")
        return None
    if not c.shape(d, (H, W, 3), f"{case}: rays_d", {(H * W, 3): "return one ray per pixel as (H, W, 3) (reshape at "
                                                                "the end)"}):
        return None
    labels = set(matching(d, f, f"rays_{name}_d", RAY_HINTS))
    R_, t_ = np.asarray(c2w, float)[:3, :3], np.asarray(c2w, float)[:3, 3]
    if not labels and close(((d - t_) @ R_)[..., 2], 1.0) and not close((d @ R_)[..., 2], 1.0):
        labels.add("as_point")  # minus the translation, every direction has z_cam = 1: the translation was added
    d_cam = d @ c2w[:3, :3]
    if not labels and np.all(d_cam[..., 2] < 0) and close(-d, d_ref * (d_cam[..., 2:] / -1.0)):
        labels.add("backwards")  # exactly the reference's rays reversed (up to length): nothing else explains it
    ok = close(d, d_ref)
    return Outcome(case, ok, "rays_d matches the reference (one ray per pixel, OpenCV axes, z_cam = 1)", keys=labels,
                   advice=f"rays_d differs from the reference (max error {float(np.abs(d - d_ref).max()):.3g}): the "
                   "camera-frame direction of pixel (u, v) is ((u - cx) / fx, (v - cy) / fy, 1), rotated by c2w[:3, :3]"
                   + ("" if ok else _direction_property(d, c2w)), data=(o, H, W, f[f"rays_{name}_o"].astype(float)))


def _origin_verdict(c: Check, r: Outcome) -> None:
    case, (o, H, W, o_ref) = r.case, r.data
    if o.shape == (3,) or o.shape == (1, 1, 3):
        c.fail(f"{case}: rays_o has shape {o.shape}: repeat the camera centre for every pixel "
               "(rays_o.expand(H, W, 3) or torch.broadcast_to)")
    elif c.shape(o, (H, W, 3), f"{case}: rays_o"):
        c.expect(close(o, o_ref), f"{case}: every ray starts at the camera centre c2w[:3, 3]",
                 f"{case}: rays_o is not the camera centre: it is the translation column c2w[:3, 3] "
                 "(the camera-to-world matrix maps the camera origin to its centre)")


def _direction_property(d, c2w) -> str:
    """What the camera-frame directions show (z_cam of every ray, the pixel centre's offset), as a property."""
    R_ = np.asarray(c2w, float)[:3, :3]
    d_cam = np.asarray(d, float) @ R_
    z = d_cam[..., 2]
    if close(z, z.flat[0]) and not close(z.flat[0], 1.0):
        return (f"; yours have z_cam = {z.flat[0]:.3g} for every ray (" +
                ("negative: the camera looks along +z in the kit's OpenCV axes" if z.flat[0] < 0 else
                 "the kit's directions have z_cam = 1, unnormalized") + ")")
    if not close(z, z.flat[0]):
        return "; yours do not have one z_cam for all rays (rotate the camera-frame directions by c2w[:3, :3] only)"
    u0 = d_cam[0, 0, :2]
    return f"; yours give the top-left pixel the camera-frame direction ({u0[0]:.3g}, {u0[1]:.3g}, 1)"


def check_get_rays(get_rays: Callable) -> None:
    """Check ``get_rays(H, W, K, c2w) -> (rays_o (H, W, 3), rays_d (H, W, 3))`` (notebook 06)."""
    f = load_fixture(FIXTURE)
    with Check("get_rays") as c:
        runs = [r for r in (_one_camera(c, get_rays, f, name) for name in RAY_CASES) if r is not None]
        report_cases(c, runs, RAY_HINTS, then=lambda r, _: _origin_verdict(c, r))


# --------------------------------------------------------------------------- stratified sampling

BINS = "in their bins"
declare_defining("stratified_samples", {
    BINS: "every training sample lies in its own bin, so the depths are sorted: the renderer's intervals "
          "t_{i+1} - t_i must be positive",
})


def _bins(near, far, S: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The two accepted stratifications: ``{name: (lower, upper)}``, ``(S,)`` for float bounds, ``(R, S)`` for
    ``(R,)`` bounds."""
    near, far = np.asarray(near, float)[..., None], np.asarray(far, float)[..., None]
    z = near + (far - near) * np.arange(S) / (S - 1)
    mids = 0.5 * (z[..., 1:] + z[..., :-1])
    edges = near + (far - near) * np.arange(S + 1) / S
    return {"kit": (np.concatenate([near + 0 * mids[..., :1], mids], -1), np.concatenate([mids, far + 0 * mids[..., :1]], -1)),
            "paper": (edges[..., :-1], edges[..., 1:])}


def _check_evaluation(c: Check, fn: Callable, near, far, S: int, R: int, z_ref: np.ndarray, case: str) -> None:
    short = case.split(", near=")[0]
    z = as_float(c.call(fn, near, far, S, R, False, case=case))
    if z is None or not c.shape(z, (R, S), f"{short}: z_vals"):
        return
    if close(z, z_ref):
        c.expect(True, f"{short}: the evenly spaced depths of the reference"
                 + (", the same for every ray" if np.ndim(near) == 0 else ", each ray between its own near and far"), "")
        return
    z2 = as_float(c.call(fn, near, far, S, R, False, case=case))
    lo, up = _bins(near, far, S)["kit"]
    inside = np.all((z >= lo - 1e-6) & (z <= up + 1e-6))
    near_a, far_a = np.broadcast_to(np.asarray(near, float), (R,))[:, None], np.broadcast_to(np.asarray(far, float), (R,))[:, None]
    step = (far_a - near_a) / S
    named = "eval"
    if z2 is not None and not close(z, z2):
        hint = "two calls give different depths: jitter in evaluation; perturb=False must give fixed, evenly " \
               "spaced depths (jitter only in training)"
    elif inside and np.ndim(near) == 0 and not close(z, np.broadcast_to(z[:1], z.shape)):
        hint = "the depths differ between rays: jitter in evaluation (perturb=False must not jitter)"
    elif close(z, near_a + step * np.arange(S)):
        hint = "the last depth is not far: use torch.linspace(near, far, n_samples)"
    elif close(z, near_a + step * (np.arange(S) + 0.5)):
        hint = "the depths are the centres of S equal bins: in evaluation use torch.linspace(near, far, n_samples)"
    else:
        hint = ("z_vals are not evenly spaced from near to far (expected torch.linspace(near, far, n_samples) for every "
                "ray, near and far of that ray)")
        named = None
    c.fail(f"{case}: {hint}", named=named and hint[:30])


def _bin_hint(zt: np.ndarray, near, far, S: int) -> tuple[str, str | None]:
    """What is wrong with training samples that leave their bins, and the mistake's key when the samples show it."""
    lo, up = _bins(near, far, S)["kit"]
    out = int(np.sum((zt < lo - 1e-6) | (zt > up + 1e-6)))
    unsorted = bool(np.any(np.diff(zt, axis=1) < 0))
    near_a = np.broadcast_to(np.asarray(near, float), (zt.shape[0],))[:, None]
    far_a = np.broadcast_to(np.asarray(far, float), (zt.shape[0],))[:, None]
    what = f"{out} samples leave their bin" + (" and the depths come out unsorted" if unsorted else
                                              " (the depths are sorted, but sample i is not inside bin i)")
    scaled = (zt - lo) / (far_a - near_a)  # the jitter in units of far - near
    if unsorted and scaled.min() > -1e-6 and scaled.max() < 1 + 1e-6 and (zt > far_a + 1e-6).any():
        return (f"{what}: your jitter is scaled by far - near (samples beyond far): scale the uniform numbers by the "
                "bin width (upper - lower)"), "jitter_far_near"
    z_even = near_a + (far_a - near_a) * np.arange(S) / (S - 1)
    span = float(np.ptp(zt - z_even, axis=1).max() / ((far_a - near_a) / (S - 1)).min())  # in bin widths
    if span > 1.5:
        return (f"{what}: your jitter spans {span:.1f} bin widths ({span / (S - 1):.0%} of far - near): a sample must "
                "stay in its bin, scale the uniform numbers by the bin width (upper - lower), not by far - near"), None
    if zt.min() < (near_a - 1e-6).min() or (zt > far_a + 1e-6).any():
        return (f"{what}; samples fall outside [near, far]: the first bin starts at near and the last ends at far "
                "(lower = [near, mids], upper = [mids, far])"), None
    return (f"{what}: draw z = lower + (upper - lower) * u with u uniform in [0, 1), lower = [near, mids], "
            "upper = [mids, far], mids the midpoints of the evaluation depths"), None


def _gen(seed: int):
    import torch

    return torch.Generator().manual_seed(int(seed))


def _check_training(c: Check, fn: Callable, near, far, S: int, R: int, seed: int, z_ref, again: bool,
                    case: str) -> None:
    """One training case; ``again``: the randomness (same seed, other seeds, torch's global generator untouched)."""
    import torch

    short = case.split(", near=")[0] if ", near=" in case else case
    zt = as_float(c.call(fn, near, far, S, R, True, generator=_gen(seed), case=case))
    if zt is None or not c.shape(zt, (R, S), f"{short}: z_vals"):
        return
    c.gate(not close(zt, z_ref), f"{short}: the depths are jittered",
           f"{case}: no jitter: with perturb=True draw one uniform sample inside each bin")
    fits = {k: np.all((zt >= lo - 1e-6) & (zt <= up + 1e-6)) for k, (lo, up) in _bins(near, far, S).items()}
    kind = next((k for k, ok in fits.items() if ok), None)
    bin_hint, key = _bin_hint(zt, near, far, S)
    c.expect(kind is not None, f"{short}: every sample lies in its own bin, so the depths are sorted",
             f"{case}: {bin_hint}", defining=BINS, named=key)
    lo, up = _bins(near, far, S)[kind or "kit"]
    off = (zt - lo) / (up - lo)
    varied_s, varied_r = np.ptp(off, axis=1).min() > 1e-3, np.ptp(off, axis=0).min() > 1e-3
    # the offsets inside the bins mean something only when the samples are in their bins (a constant is not jitter)
    c.expect(kind is not None and varied_s and varied_r, f"{short}: independent jitter for every ray and every sample",
             f"{case}: the same jitter for every {'sample' if not varied_s else 'ray'}: draw a (n_rays, n_samples) "
             "array of uniform numbers" if kind is not None else
             f"{case}: the jitter cannot be judged while the samples are not in their bins (see above)")
    if kind is not None:
        c.expect(off.min() < 0.25 and off.max() > 0.75, f"{short}: the jitter covers the whole bin",
                 f"{case}: the samples cover only [{off.min():.2f}, {off.max():.2f}] of their bins: draw u uniform "
                 "in [0, 1) and place the sample at lower + (upper - lower) * u")
    if not again:
        return
    saved = torch.get_rng_state()
    try:
        torch.manual_seed(20261124)
        before = torch.get_rng_state()
        zt2 = as_float(c.call(fn, near, far, S, R, True, generator=_gen(seed), case=case))
        touched = not torch.equal(torch.get_rng_state(), before)
    finally:
        torch.set_rng_state(saved)
    usable = zt2 is not None and np.shape(zt2) == np.shape(zt)  # an unusable second answer fails the gate too
    c.gate(usable and close(zt, zt2), f"{short}: the same generator seed gives the same samples",
           f"{case}: the same generator seed gave different samples: draw the uniform numbers from the generator "
           "argument, torch.rand(..., generator=generator)" if usable else
           f"{case}: a second call with the same seed returned nothing usable (shape {np.shape(zt2)}, expected "
           f"{np.shape(zt)})")
    c.gate(not touched, f"{short}: torch's global random state is left untouched",
           f"{case}: the call changed torch's global random state (torch.manual_seed or torch.rand without the "
           "generator): draw from the generator argument only")
    zt3 = as_float(c.call(fn, near, far, S, R, True, generator=_gen(seed + 1), case=case))
    c.gate(zt3 is not None and np.shape(zt3) == np.shape(zt) and not close(zt, zt3),
           f"{short}: another generator seed gives other samples",
           f"{case}: two generator seeds gave the same samples: draw the uniform numbers from the generator argument "
           "(not from a generator or seed of your own)")


def check_stratified_samples(stratified_samples: Callable) -> None:
    """Check ``stratified_samples(near, far, n_samples, n_rays, perturb, generator=None) -> z_vals (R, S)``.

    Evaluation (``perturb=False``) must give the reference's evenly spaced depths for every ray;
    training (``perturb=True``) one uniform sample inside each of the S bins, independent per ray
    and sample, drawn from the given ``torch.Generator`` (same seed, same samples; another seed,
    other samples; torch's global generator untouched). near and far come as floats and, as the
    kit's fast preset passes them (per-ray ray-box bounds), as ``(R,)`` float32 tensors.
    """
    import torch

    f = load_fixture(FIXTURE)
    with Check("stratified_samples") as c:
        near, far, S, R = (float(v) for v in f["strat_args"])
        S, R = int(S), int(R)
        _check_evaluation(c, stratified_samples, near, far, S, R, f["strat_z"].astype(float),
                          f"evaluation (perturb=False), near={near:.3g}, far={far:.3g}, {S} samples, {R} rays")
        for k, (near, far, S, R, seed) in enumerate(f["strat_train_args"]):
            S, R = int(S), int(R)
            _check_training(c, stratified_samples, float(near), float(far), S, R, int(seed),
                            f[f"strat_train_z_{k}"].astype(float), again=k == 0,
                            case=f"training (perturb=True), near={float(near):.3g}, far={float(far):.3g}, {S} samples, "
                                 f"{R} rays")
        if "strat_ray_near" in f:  # near and far per ray, as the kit's trainer passes them
            near_r, far_r = f["strat_ray_near"], f["strat_ray_far"]
            S, R, seed = int(f["strat_ray_S"]), len(near_r), int(f["strat_ray_seed"])
            tn, tf = torch.as_tensor(near_r, dtype=torch.float32), torch.as_tensor(far_r, dtype=torch.float32)
            label = f"{S} samples, {R} rays, near and far per ray ((R,) tensors)"
            _check_evaluation(c, stratified_samples, tn, tf, S, R, f["strat_ray_z"].astype(float),
                              f"evaluation (perturb=False), {label}")
            _check_training(c, stratified_samples, tn, tf, S, R, seed, f["strat_ray_z"].astype(float), again=False,
                            case=f"training (perturb=True), {label}")


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


def _broadcast_error(exc: Exception) -> str | None:
    """A broadcasting error of query_points, explained (not only shown as torch's message)."""
    if not any(w in str(exc).lower() for w in BROADCAST):
        return None
    return (f"a broadcasting error ({type(exc).__name__}: {str(exc).splitlines()[0][:120]}): rays_o and rays_d are "
            "(R, 3), z_vals is (R, S); add axes so that they meet as (R, 1, 3) and (R, S, 1): "
            "rays_o[:, None, :] + z_vals[..., None] * rays_d[:, None, :]")


def check_query_points(query_points: Callable) -> None:
    """Check ``query_points(rays_o (R, 3), rays_d (R, 3), z_vals (R, S)) -> pts (R, S, 3)``: o + t d."""
    f = load_fixture(FIXTURE)
    with Check("query_points") as c:
        outcomes = []
        for k in range(int(f["query_n"][0])):
            ro, rd, zv, ref = (f[f"query_{k}_{n}"].astype(float) for n in ("o", "d", "z", "pts"))
            R, S = zv.shape
            case = f"{R} rays, {S} samples"
            p = as_float(c.call_explained(query_points, as_tensor(ro), as_tensor(rd), as_tensor(zv), case=case,
                                          explain=_broadcast_error))
            if p is None:
                continue
            if p.shape == (R, R, S) or (p.ndim == 3 and p.shape[-1] != 3):
                c.fail(f"{case}: pts has shape {p.shape}: add axes before broadcasting, "
                       "rays_o[:, None, :] + z_vals[..., None] * rays_d[:, None, :]")
                continue
            if not c.shape(p, (R, S, 3), f"{case}: pts"):
                continue
            outcomes.append(Outcome(case, close(p, ref), "pts = o + t d matches the reference", "",
                                    set(matching(p, f, f"query_{k}_pts", QUERY_HINTS)),
                                    "pts differs from o + t d (pts[r, s] = rays_o[r] + z_vals[r, s] * rays_d[r])"))
        report_cases(c, outcomes, QUERY_HINTS)


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
ENCODING_HINTS["identity_last"] = ("you put the identity term x last: it goes first, [x, sin(2^0 pi x), cos(2^0 pi x), "
                                   "...]")
ENCODING_CASES = (("pos10", "positions, L={L}"), ("dir4", "directions, L={L}"), ("noid3", "include_input=False, L={L}"),
                  ("batch2", "a batch of shape {shape}, L={L}"))


def check_positional_encoding(positional_encoding: Callable) -> None:
    """Check ``positional_encoding(x (..., D), n_freqs, include_input=True) -> (..., D (include_input + 2 L))``.

    Called with float32 tensors, as the NeRF of notebook 07 calls it: the encoding must be a tensor of x's dtype.
    A stored mistake is named only when it explains every case the encoding fails.
    """
    f = load_fixture(FIXTURE)
    with Check("positional_encoding") as c:
        runs = []
        for key, label in ENCODING_CASES:
            xin, ref = f[f"enc_{key}_x"].astype(float), f[f"enc_{key}"].astype(float)
            L, inc = (int(v) for v in f[f"enc_{key}_args"])
            inc = bool(inc)
            case = label.format(L=L, shape=xin.shape)
            x_t = as_tensor(xin)
            raw = c.call(positional_encoding, x_t, L, include_input=inc, case=case)
            out = as_float(raw)
            if out is None:
                continue
            tensor_gate(c, case, "the encoding", raw, x_t)
            D = xin.shape[-1]
            want = (*xin.shape[:-1], D * (int(inc) + 2 * L))
            if out.shape != want:
                hint = ""
                if inc and out.shape == (*xin.shape[:-1], 2 * L * D):
                    hint = ": missing identity term (with include_input=True the encoding starts with x itself)"
                elif not inc and out.shape == (*xin.shape[:-1], (1 + 2 * L) * D):
                    hint = ": with include_input=False leave out the identity term x (you included it)"
                elif out.shape[:-1] != xin.shape[:-1]:
                    hint = ": keep the leading (batch) axes and concatenate along the last axis"
                c.fail(f"{case}: the encoding has shape {out.shape}, expected {want}{hint}")
                continue
            labels = set(matching(out, f, f"enc_{key}", ENCODING_HINTS))
            if inc and close(out[..., -D:], xin) and close(out[..., :-D], ref[..., D:]):
                labels.add("identity_last")
            ok = close(out, ref)
            runs.append(Outcome(case, ok, "shape and values match the reference", keys=labels, advice=(
                f"the values differ from the reference (max error {float(np.abs(out - ref).max()):.3g}); compare "
                "with the formula above: [x, sin(2^0 pi x), cos(2^0 pi x), ..., cos(2^(L-1) pi x)] (x only with "
                "include_input=True)")))
        report_cases(c, runs, ENCODING_HINTS)

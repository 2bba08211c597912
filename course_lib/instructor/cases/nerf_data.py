"""Cases of notebook 06 (rays, stratified samples, query points, positional encoding).

Built from :mod:`course_lib.nerf.rays` and :mod:`course_lib.nerf.encoding` (fixture ``nerf_data``);
the checks are in :mod:`course_lib.checks.nerf_data`. Every camera, depth range, point and
generator seed is drawn from seeded generators (salted for the hidden cases), and the results of the
classic mistakes on each case are stored next to the reference's
(:func:`encoding_variant`).
"""

from __future__ import annotations

import numpy as np

from course_lib.checks.nerf_data import ENCODING_CASES, FIXTURE, RAY_CASES, as_tensor
from course_lib.instructor.cases import builds, store
from course_lib.nerf import encoding, rays


def _look_at_c2w(center, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world (OpenCV axes) of a camera at ``center`` looking at ``target`` (world z up)."""
    center, target, up = (np.asarray(v, float) for v in (center, target, up))
    z = target - center
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    M = np.eye(4)
    M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = x, y, z, center
    return M


def _camera(g: np.random.Generator, H: int, W: int, f: float):
    """A camera with fx != fy, an off-centre principal point, looking at the origin from a random place."""
    K = np.array([[f * g.uniform(0.9, 1.1), 0.0, (W - 1) / 2 + g.uniform(0.2, 0.4) * g.choice([-1, 1])],
                  [0.0, f * g.uniform(1.15, 1.3), (H - 1) / 2 + g.uniform(0.2, 0.4) * g.choice([-1, 1])],
                  [0.0, 0.0, 1.0]])
    centre = g.normal(size=3)
    centre *= g.uniform(2.0, 4.0) / np.linalg.norm(centre)
    return K, _look_at_c2w(centre, g.normal(scale=0.3, size=3))


def _ray_mistakes(H, W, K, c2w, d_ref) -> dict[str, np.ndarray]:
    """The rays_d of the classic get_rays mistakes, from the reference's directions."""
    R = c2w[:3, :3]
    d_cam = d_ref @ R  # the reference directions in camera coordinates (z = 1)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    uu, vv = np.meshgrid(np.arange(W), np.arange(H), indexing="xy")
    flip = lambda s: (d_cam * np.array(s)) @ R.T  # noqa: E731
    cam = lambda u, v, fu, fv, ox, oy: np.stack([(u - ox) / fu, (v - oy) / fv, np.ones_like(u, float)], -1)  # noqa: E731
    pix = np.stack([uu, vv, np.ones_like(uu)], -1).astype(float)
    return {
        "opengl": flip([1, -1, -1]), "backwards": flip([1, 1, -1]), "y_flip": flip([1, -1, 1]), "x_flip": flip([-1, 1, 1]),
        "transposed": d_cam @ R, "not_rotated": d_cam,
        "normalized": (d_cam / np.linalg.norm(d_cam, axis=-1, keepdims=True)) @ R.T,
        "centre_half": cam(uu, vv, fx, fy, W / 2.0, H / 2.0) @ R.T,
        "centre_minus": cam(uu, vv, fx, fy, (W - 1) / 2.0, (H - 1) / 2.0) @ R.T,
        "half_plus": cam(uu + 0.5, vv + 0.5, fx, fy, cx, cy) @ R.T,
        "half_minus": cam(uu - 0.5, vv - 0.5, fx, fy, cx, cy) @ R.T,
        "f_swapped": cam(uu, vv, fy, fx, cx, cy) @ R.T,
        "K_not_inverted": (pix @ K.T) @ R.T,
    }


def _rays(out: dict, g: np.random.Generator) -> None:
    for name in RAY_CASES:
        H = int(g.integers(3, 6)) if name == "tiny" else int(g.integers(6, 9))
        W = H + int(g.integers(1, 4))
        K, c2w = _camera(g, H, W, 2.0 if name == "tiny" else 9.0)
        o, d = rays.get_rays(H, W, as_tensor(K), as_tensor(c2w))
        store(out, f"rays_{name}", HW=np.array([H, W]), K=K.astype(np.float32), c2w=c2w.astype(np.float32), o=o.numpy(),
              d=d.numpy())
        K32, c2w32 = out[f"rays_{name}_K"].astype(float), out[f"rays_{name}_c2w"].astype(float)
        for label, v in _ray_mistakes(H, W, K32, c2w32, d.numpy().astype(float)).items():
            out[f"rays_{name}_d__{label}"] = v.astype(np.float32)


def _strata(out: dict, g: np.random.Generator) -> None:
    import torch

    near = float(np.round(g.uniform(1.0, 3.0), 3))
    far = float(np.round(near + g.uniform(2.0, 5.0), 3))
    S, R = int(g.integers(12, 20)), int(g.integers(4, 8))
    out["strat_args"] = np.array([near, far, S, R])
    out["strat_z"] = rays.stratified_samples(near, far, S, R, perturb=False).numpy()
    train = []
    for k in range(3):
        near = float(np.round(g.uniform(0.5, 3.0), 3))
        far = float(np.round(near + g.uniform(1.0, 6.0), 3))
        S, R = int(g.integers(8, 24)), int(g.integers(5, 9))
        train.append([near, far, S, R, int(g.integers(1, 2**31))])
        out[f"strat_train_z_{k}"] = rays.stratified_samples(near, far, S, R, perturb=False).numpy()
    out["strat_train_args"] = np.array(train)
    # near and far per ray ((R,) tensors: the fast preset's ray-box bounds), as the kit's trainer passes them
    R, S = int(g.integers(5, 9)), int(g.integers(8, 16))
    near_r = np.round(g.uniform(0.5, 2.5, R), 3)
    far_r = np.round(near_r + g.uniform(0.5, 4.0, R), 3)
    out["strat_ray_near"], out["strat_ray_far"] = near_r.astype(np.float32), far_r.astype(np.float32)
    out["strat_ray_S"], out["strat_ray_seed"] = np.array(S), np.array(int(g.integers(1, 2**31)))
    out["strat_ray_z"] = rays.stratified_samples(torch.as_tensor(near_r, dtype=torch.float32),
                                                 torch.as_tensor(far_r, dtype=torch.float32), S, R,
                                                 perturb=False).numpy()


def _queries(out: dict, g: np.random.Generator) -> None:
    shapes = [(int(g.integers(3, 6)), int(g.integers(6, 9)))]
    n = int(g.integers(4, 7))
    shapes.append((n, n))  # R == S: a broadcast along the wrong axis gives no error, only wrong points
    out["query_n"] = np.array([len(shapes)])
    for k, (R, S) in enumerate(shapes):
        ro, rd = g.normal(size=(R, 3)), g.normal(size=(R, 3))
        zv = np.sort(g.uniform(1.0, 3.0, size=(R, S)), axis=1)
        ro, rd, zv = ro.astype(np.float32), rd.astype(np.float32), zv.astype(np.float32)
        out[f"query_{k}_o"], out[f"query_{k}_d"], out[f"query_{k}_z"] = ro, rd, zv
        out[f"query_{k}_pts"] = rays.query_points(as_tensor(ro), as_tensor(rd), as_tensor(zv)).numpy()
        o64, d64, z64 = ro.astype(float), rd.astype(float), zv.astype(float)
        mistakes = {
            "swapped": d64[:, None] + z64[..., None] * o64[:, None],
            "normalized": o64[:, None] + z64[..., None] * (d64 / np.linalg.norm(d64, axis=-1, keepdims=True))[:, None],
            "no_origin": z64[..., None] * d64[:, None],
        }
        if R == S:
            mistakes["rays_on_samples"] = o64[None, :] + z64[..., None] * d64[None, :]
        for label, v in mistakes.items():
            out[f"query_{k}_pts__{label}"] = v.astype(np.float32)


def _encodings(out: dict, g: np.random.Generator) -> None:
    x = g.uniform(-1.5, 1.5, size=(int(g.integers(5, 9)), 3)).astype(np.float32)
    dirs = g.normal(size=(int(g.integers(5, 9)), 3))
    dirs = (dirs / np.linalg.norm(dirs, axis=1, keepdims=True)).astype(np.float32)
    batch = g.uniform(-1.5, 1.5, size=(2, int(g.integers(2, 5)), 3)).astype(np.float32)
    inputs = {"pos10": (x, 10, True), "dir4": (dirs, 4, True), "noid3": (x, 3, False), "batch2": (batch, 2, True)}
    for key, _ in ENCODING_CASES:
        xin, L, inc = inputs[key]
        ref = encoding.positional_encoding(as_tensor(xin), L, include_input=inc).numpy()
        out[f"enc_{key}_x"], out[f"enc_{key}_args"], out[f"enc_{key}"] = xin, np.array([L, int(inc)]), ref
        for label, kw in ENCODING_VARIANTS.items():
            kw = dict({"include_input": inc}, **kw)
            if label == "extra_identity" and inc:
                continue
            out[f"enc_{key}__{label}"] = encoding_variant(xin, L, **kw).astype(np.float32)


@builds(FIXTURE)
def _build() -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    g = np.random.default_rng(6)
    _rays(out, g)
    _strata(out, g)
    _queries(out, g)
    _encodings(out, g)
    return out


# --------------------------------------------------------------------------- what the classic mistakes give
# (stored with the cases, keyed as the check module's sentences are: the shipped checks hold no implementation)


#: Encoding mistakes stored per case: label -> keyword arguments of :func:`encoding_variant`.
ENCODING_VARIANTS = {
    "no_identity": {"include_input": False},
    "extra_identity": {"include_input": True},
    "no_pi": {"pi": False},
    "cos_first": {"order": "freq_cos"},
    "blocks": {"order": "blocks"},
    "coord": {"order": "coord"},
    "from1": {"freqs": "pow2_from1"},
    "linear": {"freqs": "linear"},
    "no_pi_blocks": {"pi": False, "order": "blocks"},
    "no_identity_no_pi": {"include_input": False, "pi": False},
    "half_angle": {"freqs": "pow2_half"},
}


def encoding_variant(x: np.ndarray, L: int, include_input: bool = True, pi: bool = True,
                     order: str = "freq", freqs: str = "pow2") -> np.ndarray:
    """One way of writing the positional encoding of ``x (..., D)`` with ``L`` frequencies.

    order: "freq" (the kit's: sin and cos of each frequency side by side), "freq_cos" (cos first),
    "blocks" (all sines, then all cosines), "coord" (grouped by coordinate).
    freqs: "pow2" (2^k, k = 0..L-1), "pow2_from1" (k = 1..L), "linear" (k + 1), "pow2_half" (2^k / 2).
    """
    x = np.asarray(x, float)
    k = np.arange(L, dtype=float)
    fr = {"pow2": 2.0 ** k, "pow2_from1": 2.0 ** (k + 1), "linear": k + 1.0, "pow2_half": 2.0 ** (k - 1)}[freqs]
    xf = x[..., None, :] * (fr * (np.pi if pi else 1.0))[:, None]  # (..., L, D)
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

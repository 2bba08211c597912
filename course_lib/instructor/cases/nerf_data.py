"""Cases of notebook 06 (rays, stratified samples, query points, positional encoding).

Built from :mod:`course_lib.nerf.rays` and :mod:`course_lib.nerf.encoding` (fixture
``nerf_data``); the checks are in :mod:`course_lib.checks.nerf_data`.
"""

from __future__ import annotations

import numpy as np

from course_lib.checks.nerf_data import FIXTURE, as_tensor
from course_lib.instructor.cases import builds

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


@builds(FIXTURE)
def _build() -> dict[str, np.ndarray]:
    import torch

    from course_lib.nerf import encoding, rays

    out: dict[str, np.ndarray] = {}
    # get_rays: a tiny 3x4 camera with fx != fy and an off-centre principal point, and a
    # lego-like camera on an orbit (W != H so that a transposed grid shows in the shape).
    cams = {
        "tiny": (3, 4, [[2.0, 0.0, 1.3], [0.0, 2.5, 0.8], [0.0, 0.0, 1.0]], _look_at_c2w([1.0, -2.0, 0.5], [0.2, 0.3, 0.0])),
        "orbit": (6, 8, [[9.0, 0.0, 3.5], [0.0, 9.0, 2.5], [0.0, 0.0, 1.0]], _look_at_c2w([2.5, 3.0, 1.8], [0.0, 0.0, 0.0])),
    }
    for name, (H, W, K, c2w) in cams.items():
        o, d = rays.get_rays(H, W, as_tensor(K), as_tensor(c2w))
        out[f"rays_{name}_HW"] = np.array([H, W])
        out[f"rays_{name}_K"] = np.array(K, dtype=np.float32)
        out[f"rays_{name}_c2w"] = c2w.astype(np.float32)
        out[f"rays_{name}_o"] = o.numpy()
        out[f"rays_{name}_d"] = d.numpy()
    # stratified samples: evaluation depths (perturb=False)
    out["strat_args"] = np.array([2.0, 6.0, 16, 5])
    out["strat_z"] = rays.stratified_samples(2.0, 6.0, 16, 5, perturb=False).numpy()
    # query points
    g = np.random.default_rng(6)
    ro, rd = g.normal(size=(4, 3)), g.normal(size=(4, 3))
    zv = np.sort(g.uniform(1.0, 3.0, size=(4, 5)), axis=1)
    out["query_o"], out["query_d"], out["query_z"] = ro.astype(np.float32), rd.astype(np.float32), zv.astype(np.float32)
    out["query_pts"] = rays.query_points(as_tensor(ro), as_tensor(rd), as_tensor(zv)).numpy()
    # positional encoding: positions (L=10), directions (L=4), without identity, batched
    x = g.uniform(-1.5, 1.5, size=(6, 3)).astype(np.float32)
    dirs = g.normal(size=(6, 3))
    dirs = (dirs / np.linalg.norm(dirs, axis=1, keepdims=True)).astype(np.float32)
    out["enc_x"], out["enc_dirs"] = x, dirs
    out["enc_x_10"] = encoding.positional_encoding(as_tensor(x), 10).numpy()
    out["enc_dirs_4"] = encoding.positional_encoding(as_tensor(dirs), 4).numpy()
    out["enc_x_3_noid"] = encoding.positional_encoding(as_tensor(x), 3, include_input=False).numpy()
    out["enc_batch_2"] = encoding.positional_encoding(as_tensor(x.reshape(2, 3, 3)), 2).numpy()
    del torch
    return out

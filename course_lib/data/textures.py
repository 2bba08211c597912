"""Procedural textures of the kit's synthetic scenes: value noise, bricks, windows, signs, walls, roofs, ground.

Every texture is an ``(h, w, 3)`` float RGB image in [0, 1] drawn with the caller's ``rng``, at
``rho`` texels per metre (per unit); the building (:mod:`course_lib.data.building`) and the
excavator (:mod:`course_lib.data.excavator`) paint their surfaces with them.

Introduced in ``notebooks/01_fundamental_matrix.ipynb`` (the embedded scene).
"""

from __future__ import annotations

import string

import numpy as np

__all__ = ["value_noise", "blocks", "draw_window", "draw_sign", "wall_texture", "roof_texture", "ground_texture", "plain_texture"]


def value_noise(rng, h: int, w: int, cell_px: float, octaves: int = 3) -> np.ndarray:
    """Smooth multi-octave value noise in about [-1, 1], shape ``(h, w)`` float32."""
    import cv2

    out = np.zeros((h, w), np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        c = max(cell_px / 2**o, 1.0)
        gh, gw = int(np.ceil(h / c)) + 2, int(np.ceil(w / c)) + 2
        grid = rng.uniform(-1, 1, (gh, gw)).astype(np.float32)
        up = cv2.resize(grid, (int(gw * c), int(gh * c)), interpolation=cv2.INTER_CUBIC)
        out += amp * up[:h, :w]
        total += amp
        amp *= 0.5
    return out / total


def blocks(rng, h, w, rho, size_m, mortar_m, base, shade=0.18, mortar=(0.78, 0.76, 0.72), offset=0.5):
    """Running-bond blocks (stone, bricks, tiles, paving): ``(h, w, 3)`` float32 in [0, 1]."""
    bw, bh = size_m[0] * rho, size_m[1] * rho
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    row = np.floor(yy / bh).astype(int)
    xs = xx + (row % 2) * offset * bw
    col = np.floor(xs / bw).astype(int)
    nr, nc = row.max() + 2, col.max() + 2
    table = rng.normal(0.0, shade, (nr, nc, 1)).astype(np.float32)
    tint = rng.normal(0.0, shade * 0.3, (nr, nc, 3)).astype(np.float32)
    img = np.asarray(base, np.float32)[None, None, :] * (1.0 + table[row, col]) + tint[row, col] * 0.5
    fy, fx = yy / bh - np.floor(yy / bh), xs / bw - np.floor(xs / bw)
    m = mortar_m * rho
    joint = (fy * bh < m) | (fx * bw < m)
    img[joint] = np.asarray(mortar, np.float32)
    return img


def draw_window(img, x0, y0, w, h, rng, rho):
    """A framed window with a cross bar; glass with a sky reflection. Pixel box on ``img``."""
    import cv2

    f = max(int(0.07 * rho), 2)
    x0, y0, w, h = int(x0), int(y0), int(w), int(h)
    img[y0:y0 + h, x0:x0 + w] = (0.93, 0.92, 0.88)
    gy = np.linspace(0, 1, h - 2 * f, dtype=np.float32)[:, None, None]
    glass = (1 - gy) * np.array([0.35, 0.45, 0.58], np.float32) + gy * np.array([0.10, 0.13, 0.2], np.float32)
    glass = glass + 0.08 * value_noise(rng, h - 2 * f, w - 2 * f, 0.3 * rho, 2)[..., None]
    img[y0 + f:y0 + h - f, x0 + f:x0 + w - f] = glass
    cv2.rectangle(img, (x0 + w // 2 - f // 2, y0), (x0 + w // 2 + f // 2, y0 + h - 1), (0.93, 0.92, 0.88), -1)
    cv2.rectangle(img, (x0, y0 + int(h * 0.4) - f // 2), (x0 + w - 1, y0 + int(h * 0.4) + f // 2), (0.93, 0.92, 0.88), -1)
    cv2.rectangle(img, (x0 - f, y0 + h), (x0 + w + f, y0 + h + f), (0.6, 0.58, 0.55), -1)  # sill


def draw_sign(img, x0, y0, w, h, rng, rho, text=None):
    """A coloured sign (or poster) with random letters and shapes: strong, unique features."""
    import cv2

    x0, y0, w, h = int(x0), int(y0), int(w), int(h)
    bg = rng.uniform(0.15, 0.95, 3)
    img[y0:y0 + h, x0:x0 + w] = bg
    for _ in range(int(rng.integers(3, 7))):
        c = tuple(float(v) for v in rng.uniform(0, 1, 3))
        cx, cy = int(x0 + rng.uniform(0.1, 0.9) * w), int(y0 + rng.uniform(0.1, 0.9) * h)
        r = int(rng.uniform(0.08, 0.3) * min(w, h))
        if rng.random() < 0.5:
            cv2.circle(img, (cx, cy), r, c, -1)
        else:
            cv2.rectangle(img, (cx - r, cy - r // 2), (cx + r, cy + r // 2), c, -1)
    if text is None:
        text = "".join(rng.choice(list(string.ascii_uppercase + string.digits), int(rng.integers(3, 7))))
    scale = 0.5 * h / 30.0
    (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_DUPLEX, scale, 1)
    scale *= min(1.0, 0.9 * w / max(tw, 1))
    thick = max(1, int(scale * 2))
    (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_DUPLEX, scale, thick)
    ink = (0.05, 0.05, 0.05) if bg.mean() > 0.5 else (0.97, 0.97, 0.95)
    cv2.putText(img, text, (x0 + (w - tw) // 2, y0 + (h + th) // 2), cv2.FONT_HERSHEY_DUPLEX, scale, ink, thick, cv2.LINE_AA)


def wall_texture(rng, w_m, h_m, rho, windows=(), doors=(), signs=(), base=(0.62, 0.45, 0.36)):
    """Stone-block wall with windows/doors/signs given as (x, z, w, h) in metres (z from the bottom)."""
    h, w = int(np.ceil(h_m * rho)), int(np.ceil(w_m * rho))
    img = blocks(rng, h, w, rho, (0.42, 0.21), 0.025, base)
    img *= 1.0 + 0.22 * value_noise(rng, h, w, 1.2 * rho)[..., None]  # weathering
    img = np.ascontiguousarray(img)

    def box(x, z, bw, bh):  # metres (z up from the bottom edge) -> pixel box (x0, y0, w, h)
        return x * rho, (h_m - z - bh) * rho, bw * rho, bh * rho

    for win in windows:
        draw_window(img, *box(*win), rng, rho)
    for d in doors:
        x0, y0, dw, dh = (int(v) for v in box(*d))
        img[y0:y0 + dh, x0:x0 + dw] = (0.32, 0.2, 0.12)
        img[y0:y0 + dh, x0:x0 + dw] *= 1 + 0.15 * value_noise(rng, dh, dw, 0.2 * rho, 2)[..., None]
        k = max(int(0.06 * rho), 2)
        img[y0 + k:y0 + dh // 2 - k, x0 + k:x0 + dw - k] = (0.2, 0.25, 0.3)
    for s in signs:
        draw_sign(img, *box(*s[:4]), rng, rho, text=s[4] if len(s) > 4 else None)
    return np.clip(img, 0, 1)


def roof_texture(rng, w_m, h_m, rho):
    h, w = int(np.ceil(h_m * rho)), int(np.ceil(w_m * rho))
    img = blocks(rng, h, w, rho, (0.32, 0.22), 0.03, (0.55, 0.22, 0.15), shade=0.22, mortar=(0.25, 0.1, 0.08))
    img *= 1.0 + 0.25 * value_noise(rng, h, w, 1.5 * rho)[..., None]
    return np.clip(img, 0, 1)


def ground_texture(rng, w_m, h_m, rho, grass=True):
    h, w = int(np.ceil(h_m * rho)), int(np.ceil(w_m * rho))
    img = blocks(rng, h, w, rho, (0.6, 0.6), 0.03, (0.55, 0.55, 0.52), shade=0.15, mortar=(0.3, 0.3, 0.28), offset=0.0)
    img *= 1.0 + 0.2 * value_noise(rng, h, w, 0.8 * rho)[..., None]
    if grass:
        n = value_noise(rng, h, w, 3.0 * rho, 2)
        g = np.stack([0.25 + 0.1 * n, 0.45 + 0.12 * n, 0.18 + 0.05 * n], -1)
        g = g * (1 + 0.3 * value_noise(rng, h, w, 0.1 * rho, 2)[..., None])
        mask = np.clip((n - 0.15) * 6, 0, 1)[..., None]
        img = img * (1 - mask) + g * mask
    return np.clip(img, 0, 1).astype(np.float32)


def plain_texture(rng, w_m, h_m, rho, base, noise=0.25, cell_m=0.3):
    h, w = int(np.ceil(h_m * rho)), int(np.ceil(w_m * rho))
    img = np.ones((h, w, 3), np.float32) * np.asarray(base, np.float32)
    img *= 1.0 + noise * value_noise(rng, h, w, cell_m * rho, 3)[..., None]
    return np.clip(img, 0, 1)

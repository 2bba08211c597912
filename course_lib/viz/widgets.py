"""Interactive widgets (ipywidgets): move a slider, see the effect.

Each function returns an ``ipywidgets.VBox``; make it the last expression of a cell. The widgets
work live in JupyterLab and also when a notebook is executed headless (nbconvert/nbval): the
first picture is drawn at construction, and every slider change redraws by replacing the
``outputs`` of an ``ipywidgets.Output`` (or the bytes of an ``ipywidgets.Image``), which needs
no running front end. Results are cached per slider value, so moving back is instant.

API::

    ransac_threshold_widget(img1, img2, x1 (N,2), x2 (N,2), ransac_fn, rng_seed=0,
                            thresholds=(0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0),
                            value=1.0, max_lines=200) -> VBox
        ransac_fn(x1, x2, rng, threshold_px) -> result with .inliers (N,) bool (the student's
        ransac_fundamental; in the instructor's kit also course_lib.sfm.fundamental's). For each
        threshold RANSAC runs with a fresh numpy.random.default_rng(rng_seed) and the matches
        are redrawn (inliers green, outliers red) with the inlier count.
        children: (slider, label HTML, Output).

    ba_iterations_widget(states, K (3,3), image_size (W,H), costs=None, reference=None,
                         point_budget=5000, up=(0,-1,0), height=500) -> VBox
        states: list of (R_cw (M,3,3), t_cw (M,3), X (N,3)), one per bundle-adjustment
        iteration (e.g. collected with bundle_adjust(..., callback=...)); costs: one number per
        state (0.5 * sum of squared residuals). reference: optional (R_cw, t_cw, X) drawn in grey
        (e.g. the ground truth, already aligned). The 3-D scene of the chosen iteration is
        redrawn with fixed axes, so the motion of cameras and points is visible.
        children: (slider, label HTML, Output). With course_lib.sfm.bundle_adjustment:
            res = bundle_adjust(K, R_cw, t_cw, X, uv, keep_iterates=True)
            ba_iterations_widget(res.iterates, K, (W, H), res.cost_history)

    nerf_snapshot_slider(images, iterations=None, reference=None, width=None) -> VBox
        images: list of image paths (PNG/JPEG) or of (H,W,3) arrays (uint8 or float [0,1]),
        or an (N,H,W,3) array, one per training snapshot; iterations: N numbers for the label
        (default 0..N-1). reference: optional (H,W,3) ground-truth image shown beside.
        children: (slider, label HTML, HBox of Image widgets).

    novel_view_widget(render_fn, azimuth=(-180, 180, 15), elevation=(-30, 90, 10),
                      initial=(30.0, 30.0), width=None) -> VBox
        render_fn(azimuth_deg, elevation_deg) -> (H,W,3) image (uint8 or float [0,1], numpy or
        torch). Two sliders (min, max, step in degrees); the view is rendered when a slider is
        released. children: (HBox(azimuth slider, elevation slider), label HTML, Image).

Introduced in ``notebooks/01_fundamental_matrix.ipynb`` (RANSAC), ``05_bundle_adjustment``
(BA iterations) and ``08_nerf_rendering_and_training`` (snapshots, novel views).
"""

from __future__ import annotations

import base64
import io
import json
import time
from pathlib import Path

import ipywidgets as widgets
import numpy as np
import plotly.graph_objects as go
import plotly.io as pio

from course_lib.validate import KitInputError, camera_poses, intrinsics, matching_points
from course_lib.viz.figures import draw_matches
from course_lib.viz.scene3d import add_cameras, add_points, scene_figure, set_axis_box

__all__ = ["ransac_threshold_widget", "ba_iterations_widget", "nerf_snapshot_slider", "novel_view_widget"]


# ----------------------------------------------------------------------------- helpers
def _bundle(obj) -> dict:
    """A notebook ``display_data`` output for a matplotlib Figure or a plotly Figure."""
    if isinstance(obj, go.Figure):
        fig_json = json.loads(pio.to_json(obj, validate=False))
        data = {"application/vnd.plotly.v1+json": {**fig_json, "config": {"displaylogo": False}}, "text/plain": "<plotly figure>"}
    else:  # matplotlib Figure
        buf = io.BytesIO()
        obj.savefig(buf, format="png", bbox_inches="tight", dpi=obj.dpi)
        data = {"image/png": base64.b64encode(buf.getvalue()).decode("ascii"), "text/plain": "<Figure>"}
    return {"output_type": "display_data", "data": data, "metadata": {}}


def _show(out: widgets.Output, obj) -> None:
    out.outputs = (_bundle(obj),)


def _png(img) -> bytes:
    """PNG bytes of an image array (uint8 or float in [0, 1]; numpy or torch)."""
    import imageio.v3 as iio

    a = img
    if hasattr(a, "detach") and hasattr(a, "cpu"):
        a = a.detach().cpu().numpy()
    a = np.asarray(a)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (3, 4)):
        raise KitInputError(f"image has shape {a.shape}: expected (H, W, 3) (channels last)")
    if a.dtype != np.uint8:
        a = np.asarray(a, float)
        if np.nanmax(a, initial=0) <= 1.0 + 1e-3:
            a = a * 255.0
        a = np.clip(np.nan_to_num(a), 0, 255).round().astype(np.uint8)
    return iio.imwrite("<bytes>", a, extension=".png")


def _image_bytes(item) -> tuple[bytes, str]:
    if isinstance(item, (str, Path)):
        p = Path(item)
        if not p.exists():
            raise KitInputError(f"snapshot image not found: {p}")
        fmt = "jpeg" if p.suffix.lower() in (".jpg", ".jpeg") else "png"
        return p.read_bytes(), fmt
    return _png(item), "png"


def _label(text: str) -> widgets.HTML:
    return widgets.HTML(value=text)


# ----------------------------------------------------------------------------- RANSAC
def ransac_threshold_widget(
    img1,
    img2,
    x1,
    x2,
    ransac_fn,
    rng_seed: int = 0,
    thresholds=(0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0),
    value: float = 1.0,
    max_lines: int = 200,
) -> widgets.VBox:
    """A threshold slider that reruns RANSAC and redraws inliers (green) and outliers (red).

    Args:
        img1, img2: ``(H, W, 3)`` images.
        x1, x2: ``(N, 2)`` matching pixels.
        ransac_fn: ``ransac_fn(x1, x2, rng, threshold_px)`` returning an object with
            ``.inliers`` ``(N,)`` bool (and optionally ``.n_iters``).
        rng_seed: each run gets ``numpy.random.default_rng(rng_seed)`` (same threshold, same answer).
        thresholds: the slider's values, pixels.
        value: initial threshold (the nearest of ``thresholds``).
        max_lines: most match lines drawn.

    Returns:
        ``VBox(slider, label, output)``.
    """
    x1, x2 = matching_points(x1, x2, min_count=8, why="RANSAC")
    if not callable(ransac_fn):
        raise KitInputError("ransac_fn must be a function ransac_fn(x1, x2, rng, threshold_px) -> result with .inliers")
    options = [float(t) for t in thresholds]
    if not options:
        raise KitInputError("thresholds is empty")
    start = min(options, key=lambda t: abs(t - float(value)))
    slider = widgets.SelectionSlider(options=options, value=start, description="threshold [px]",
                                     continuous_update=False, style={"description_width": "initial"},
                                     layout=widgets.Layout(width="480px"))
    label = _label("")
    out = widgets.Output()
    cache: dict[float, tuple] = {}

    def run(t: float):
        if t not in cache:
            res = ransac_fn(x1, x2, np.random.default_rng(rng_seed), t)
            inl = np.asarray(getattr(res, "inliers", None))
            if inl.shape != (len(x1),):
                raise KitInputError(f"ransac_fn returned inliers of shape {inl.shape}: expected ({len(x1)},) bool")
            cache[t] = (inl.astype(bool), getattr(res, "n_iters", None))
        return cache[t]

    def redraw(change=None):
        t = float(slider.value)
        inl, n_iters = run(t)
        k = int(inl.sum())
        extra = f", {n_iters} iterations" if n_iters is not None else ""
        label.value = f"<b>threshold {t:g} px</b>: {k} / {len(x1)} inliers ({100 * k / len(x1):.0f} %){extra}"
        fig = draw_matches(img1, img2, x1, x2, inl, max_lines=max_lines, rng_seed=rng_seed,
                           title=f"threshold {t:g} px: {k} inliers (green), {len(x1) - k} outliers (red)")
        _show(out, fig)

    slider.observe(redraw, names="value")
    redraw()
    return widgets.VBox([slider, label, out])


# ----------------------------------------------------------------------------- BA
def _ba_state(k: int, st) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``states[k]`` of :func:`ba_iterations_widget` checked: ``(R_cw (M, 3, 3), t_cw (M, 3), X (N, 3))``."""
    if not isinstance(st, (tuple, list)) or len(st) != 3:
        raise KitInputError(f"states[{k}] must be a tuple (R_cw (M,3,3), t_cw (M,3), X (N,3))")
    R, t = camera_poses(st[0], st[1])
    X = np.asarray(st[2], float)
    if X.ndim != 2 or X.shape[1] != 3:
        raise KitInputError(f"states[{k}][2] (X) has shape {X.shape}: expected (N, 3)")
    return R, t, X


def _ba_axis_box(checked: list) -> tuple[np.ndarray, np.ndarray]:
    """Fixed axes over all states (a robust box of points and centres), so the scene does not jump: ``(lo, hi)``."""
    pts = np.concatenate([X[np.isfinite(X).all(1)] for _, _, X in checked])
    cen = np.concatenate([np.einsum("mji,mj->mi", R, -t) for R, t, _ in checked])
    lo, hi = cen.min(0), cen.max(0)
    if len(pts):
        lo = np.minimum(lo, np.percentile(pts, 1, axis=0))
        hi = np.maximum(hi, np.percentile(pts, 99, axis=0))
    pad = 0.08 * (hi - lo).max() + 1e-9
    lo, hi = lo - pad, hi + pad
    return lo, hi


def ba_iterations_widget(
    states,
    K,
    image_size,
    costs=None,
    reference=None,
    point_budget: int = 5000,
    up=(0.0, -1.0, 0.0),
    height: int = 500,
) -> widgets.VBox:
    """A slider over bundle-adjustment iterations redrawing the 3-D scene and the cost.

    Args:
        states: list of ``(R_cw (M, 3, 3), t_cw (M, 3), X (N, 3))``, one per iteration.
        K: ``(3, 3)`` intrinsics. image_size: ``(W, H)``.
        costs: optional list of one cost per state (shown in the label).
        reference: optional ``(R_cw, t_cw, X)`` drawn in grey in every view.
        point_budget: most points drawn per state (same fixed subset every time).
        up: world direction shown up. height: figure height in pixels.

    Returns:
        ``VBox(slider, label, output)``.
    """
    K = intrinsics(K)
    states = list(states)
    if not states:
        raise KitInputError("states is empty: pass one (R_cw, t_cw, X) per iteration")
    checked = [_ba_state(k, st) for k, st in enumerate(states)]
    if costs is not None:
        costs = [float(c) for c in costs]
        if len(costs) != len(states):
            raise KitInputError(f"costs has {len(costs)} entries for {len(states)} states")
    lo, hi = _ba_axis_box(checked)
    ext = hi - lo
    scale = 0.05 * float(np.linalg.norm(ext))
    slider = widgets.IntSlider(value=0, min=0, max=len(states) - 1, step=1, description="iteration",
                               continuous_update=False, layout=widgets.Layout(width="480px"))
    label = _label("")
    out = widgets.Output()

    def figure(k: int) -> go.Figure:
        R, t, X = checked[k]
        fig = scene_figure(title=f"bundle adjustment, iteration {k}", height=height, up=up)
        if reference is not None:
            add_points(fig, reference[2], name="reference points", max_points=point_budget, color="#aaaaaa",
                       legend_group="reference")
            add_cameras(fig, reference[0], reference[1], K, image_size, color="#888888", scale=scale,
                        legend_group="reference", show_names=False)
        add_points(fig, X, name="points", max_points=point_budget, color="#1f77b4", legend_group="estimate")
        add_cameras(fig, R, t, K, image_size, color="#d62728", scale=scale, legend_group="estimate", show_names=False)
        set_axis_box(fig, lo, hi)
        return fig

    def redraw(change=None):
        k = int(slider.value)
        txt = f"<b>iteration {k}</b> of {len(states) - 1}"
        if costs is not None:
            txt += f": cost {costs[k]:.6g}"
            if k > 0:
                txt += f" (start {costs[0]:.6g}, {100 * (1 - costs[k] / costs[0]) if costs[0] else 0:.1f} % lower)"
        label.value = txt
        _show(out, figure(k))

    slider.observe(redraw, names="value")
    redraw()
    return widgets.VBox([slider, label, out])


# ----------------------------------------------------------------------------- NeRF
def nerf_snapshot_slider(images, iterations=None, reference=None, width: int | None = None) -> widgets.VBox:
    """A slider over training snapshots (renders saved during NeRF training).

    Args:
        images: list of paths (PNG/JPEG) or ``(H, W, 3)`` arrays, or an ``(N, H, W, 3)`` array.
        iterations: N numbers shown in the label (default ``0 .. N-1``).
        reference: optional ``(H, W, 3)`` ground-truth image shown beside the snapshot.
        width: display width in pixels (default: the image's own).

    Returns:
        ``VBox(slider, label, HBox(snapshot Image[, reference Image]))``.
    """
    if hasattr(images, "shape") and len(images.shape) == 4:
        images = [images[i] for i in range(images.shape[0])]
    images = list(images)
    if not images:
        raise KitInputError("images is empty: pass one image (or path) per snapshot")
    if iterations is None:
        iterations = list(range(len(images)))
    iterations = list(iterations)
    if len(iterations) != len(images):
        raise KitInputError(f"iterations has {len(iterations)} entries for {len(images)} images")
    cache: dict[int, tuple[bytes, str]] = {}

    def get(k):
        if k not in cache:
            cache[k] = _image_bytes(images[k])
        return cache[k]

    layout = widgets.Layout(width=f"{int(width)}px") if width else widgets.Layout()
    b, fmt = get(len(images) - 1)
    view = widgets.Image(value=b, format=fmt, layout=layout)
    row = [view]
    if reference is not None:
        rb, rfmt = _image_bytes(reference)
        row.append(widgets.VBox([widgets.HTML("ground truth"), widgets.Image(value=rb, format=rfmt, layout=layout)]))
        row[0] = widgets.VBox([widgets.HTML("render"), view])
    slider = widgets.IntSlider(value=len(images) - 1, min=0, max=len(images) - 1, step=1, description="snapshot",
                               continuous_update=True, layout=widgets.Layout(width="480px"))
    label = _label("")

    def redraw(change=None):
        k = int(slider.value)
        b, fmt = get(k)
        view.format = fmt
        view.value = b
        label.value = f"<b>iteration {iterations[k]}</b> (snapshot {k + 1} of {len(images)})"

    slider.observe(redraw, names="value")
    redraw()
    return widgets.VBox([slider, label, widgets.HBox(row)])


def novel_view_widget(
    render_fn,
    azimuth=(-180.0, 180.0, 15.0),
    elevation=(-30.0, 90.0, 10.0),
    initial=(30.0, 30.0),
    width: int | None = None,
) -> widgets.VBox:
    """Azimuth/elevation sliders that render a novel view with ``render_fn``.

    Args:
        render_fn: ``render_fn(azimuth_deg, elevation_deg) -> (H, W, 3)`` image (uint8 or float
            in [0, 1], numpy or torch).
        azimuth: ``(min, max, step)`` in degrees. elevation: ``(min, max, step)`` in degrees.
        initial: ``(azimuth_deg, elevation_deg)`` rendered at construction.
        width: display width in pixels (default: the image's own).

    Returns:
        ``VBox(HBox(azimuth slider, elevation slider), label, Image)``.
    """
    if not callable(render_fn):
        raise KitInputError("render_fn must be a function render_fn(azimuth_deg, elevation_deg) -> (H, W, 3) image")
    a0, a1, da = (float(v) for v in azimuth)
    e0, e1, de = (float(v) for v in elevation)
    az = widgets.FloatSlider(value=float(np.clip(initial[0], a0, a1)), min=a0, max=a1, step=da, description="azimuth °",
                             continuous_update=False)
    el = widgets.FloatSlider(value=float(np.clip(initial[1], e0, e1)), min=e0, max=e1, step=de, description="elevation °",
                             continuous_update=False)
    label = _label("")
    view = widgets.Image(format="png", layout=widgets.Layout(width=f"{int(width)}px") if width else widgets.Layout())
    cache: dict[tuple[float, float], tuple[bytes, float]] = {}

    def redraw(change=None):
        key = (round(float(az.value), 6), round(float(el.value), 6))
        if key not in cache:
            t0 = time.perf_counter()
            img = render_fn(key[0], key[1])
            cache[key] = (_png(img), time.perf_counter() - t0)
            if len(cache) > 64:
                cache.pop(next(iter(cache)))
        b, dt = cache[key]
        view.value = b
        label.value = f"azimuth {key[0]:g}°, elevation {key[1]:g}° (rendered in {dt:.2f} s)"

    az.observe(redraw, names="value")
    el.observe(redraw, names="value")
    redraw()
    return widgets.VBox([widgets.HBox([az, el]), label, view])

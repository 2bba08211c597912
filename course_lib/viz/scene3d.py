"""Interactive 3-D scenes with plotly: cameras as frustums, point clouds, NeRF rays.

Every 3-D picture of the kit (SfM reconstructions, bundle adjustment before/after, NeRF camera
rigs and rays) is drawn here, so that all notebooks look alike and stay small. Show a figure by
making it the last expression of a cell (``fig``); importing :mod:`course_lib.viz` selects the
``plotly_mimetype`` renderer, which stores the figure in the notebook as JSON only (no plotly.js).
Use :func:`write_html` for a file that opens offline in a browser.

Conventions (see :mod:`course_lib.conventions`): poses are ``R_cw (3, 3)``, ``t_cw (3,)`` with
``x_cam = R_cw @ X + t_cw``; the camera centre is ``C = -R_cw.T @ t_cw``; camera axes are
OpenCV's (x right, y down, z forward). The SfM worlds of the kit are y-down too, so the 3-D view
puts world ``-y`` up by default (``up=(0, -1, 0)``). For NeRF scenes converted from Blender
(world z up) pass ``up=(0, 0, 1)``.

API (all arrays may be numpy arrays, lists or torch tensors; every function returns the figure)::

    scene_figure(cameras=None, points=None, title=None, point_budget=20000, height=600,
                 up=(0, -1, 0), camera_scale=None, name="scene", eye=None) -> go.Figure
        cameras: list of tuples (R_cw (3,3), t_cw (3,), K (3,3), (W, H)) or
                 (R_cw, t_cw, K, (W, H), name); drawn as one legend group `name + " cameras"`.
        points:  X (N,3) or a tuple (X (N,3), rgb (N,3) uint8 or None); NaN rows are dropped;
                 above `point_budget` points a fixed random subset is drawn.
        up: world direction shown up on screen; eye: optional (3,) viewpoint (plotly units).
        camera_scale: frustum depth in world units (default 5 % of the scene size).

    add_cameras(fig, R_cw (M,3,3), t_cw (M,3), K (3,3) or (M,3,3), image_size (W, H),
                names=None, color=None, scale=None, legend_group=None, images=None,
                show_names=None) -> go.Figure
        Frustum of camera i: apex at C_i, far rectangle = the image corners back-projected with K
        to depth `scale` (default 5 % of the scene size: points already in `fig` + camera
        centres), and a small triangle on the image's top edge pointing to image "up"
        (camera -y), so orientation is visible. Hovering the apex shows the name.
        `legend_group` (e.g. "before BA") makes one legend entry that toggles the group.
        `images`: optional list of M (H, W, 3) uint8 images drawn, coarsely, on the far plane.

    add_points(fig, X (N,3), rgb=None, name="points", max_points=20000, size=2, color=None,
               legend_group=None, rng_seed=0) -> go.Figure
        rgb: (N,3) uint8 (or floats in [0, 1]) per-point colours; else one `color`.

    add_rays(fig, rays_o (R,3), rays_d (R,3), samples=None (R,S,3), t_far=None,
             sample_values=None (R,S), name="rays", color=None, legend_group=None,
             max_rays=256, rng_seed=0) -> go.Figure
        Segments o -> o + t_far * d (default t_far: to the farthest sample, else 1, i.e. depth 1
        for the kit's rays whose d has z_cam = 1); samples as dots, coloured by `sample_values`
        (e.g. the NeRF weights) when given.

    camera_frustum(R_cw (3,3), t_cw (3,), K (3,3), image_size (W,H), scale) -> dict
        The geometry drawn for one camera, in world coordinates: "apex" (3,), "corners" (4,3)
        (image top-left, top-right, bottom-right, bottom-left), "up_triangle" (3,3) (the marker
        on the top edge), "up_tip" (3,) (its tip, towards camera -y).

    scene_size(X (N,3)) -> float     robust diameter (2nd..98th percentile box) of points.
    write_html(fig, path) -> Path    standalone HTML with plotly.js embedded (opens offline).
    set_axis_box(fig, lo (3,), hi (3,))   fix the 3-D axes to a box with equal scales.

Example::

    from course_lib.viz import scene_figure, add_cameras
    fig = scene_figure(points=(X, rgb), title="Reconstruction")
    add_cameras(fig, R_before, t_before, K, (W, H), legend_group="before BA", color="gray")
    add_cameras(fig, R_after, t_after, K, (W, H), legend_group="after BA", color="crimson")
    fig

Figures are deterministic (fixed trace uids, seeded subsampling, rounded coordinates stored as
float32), so re-running a notebook does not change its stored output. Size in the notebook:
about 20 bytes per drawn point (5 cameras + 5000 coloured points ~ 110 kB; 20000 points
~ 410 kB), so pass a smaller ``point_budget``/``max_points`` when a notebook has many scenes
(notebooks must stay < 2 MB). Introduced in
``notebooks/02_essential_matrix_and_pose.ipynb`` and used by every later notebook.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import plotly.graph_objects as go

from course_lib.validate import KitInputError, as_array, camera_poses, intrinsics, rotation

__all__ = [
    "scene_figure",
    "add_cameras",
    "add_points",
    "add_rays",
    "camera_frustum",
    "scene_size",
    "write_html",
    "set_axis_box",
    "PALETTE",
]

#: Colours given, in order, to legend groups that do not name their own colour.
PALETTE = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf")

_POINT_META = "course_lib:points"


# ----------------------------------------------------------------------------- input helpers
def _np(a, dtype=float) -> np.ndarray:
    """numpy array from numpy / list / torch tensor (without importing torch)."""
    return as_array(a, "the input", dtype)


def _rows(a, name: str, dim: int = 3) -> np.ndarray:
    """``(N, dim)`` float array; NaN allowed (the caller decides what to do with them)."""
    a = _np(a)
    if a.ndim != 2 or a.shape[1] != dim:
        hint = " (points are rows: transpose it?)" if a.ndim == 2 and a.shape[0] == dim else ""
        raise KitInputError(f"{name} has shape {tuple(a.shape)}: expected (N, {dim}){hint}")
    return a


def _image_size(image_size) -> tuple[int, int]:
    try:
        W, H = (int(v) for v in image_size)
    except (TypeError, ValueError):
        raise KitInputError(f"image_size must be (W, H) in pixels, got {image_size!r}") from None
    if W <= 0 or H <= 0:
        raise KitInputError(f"image_size must be positive (W, H), got {image_size!r}")
    return W, H


def _colour(rgb) -> str:
    r, g, b = (int(v) for v in rgb)
    return f"#{r:02x}{g:02x}{b:02x}"


def _slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", str(text).lower()).strip("-") or "x"


def _uid(fig: go.Figure, kind: str, group: str) -> str:
    """Deterministic, unique trace uid: position in the figure + kind + group."""
    return f"{len(fig.data)}-{kind}-{_slug(group)}"


def _group_colour(fig: go.Figure, group: str, color) -> str:
    if color is not None:
        return color
    groups = []
    for tr in fig.data:
        g = tr.legendgroup
        if g and g not in groups:
            groups.append(g)
    k = groups.index(group) if group in groups else len(groups)
    return PALETTE[k % len(PALETTE)]


def _decimals(size: float) -> int:
    """Decimals that keep about 1e-4 of the scene size (4 significant digits of the scene)."""
    size = float(size) if np.isfinite(size) and size > 0 else 1.0
    return int(max(0, min(10, -np.floor(np.log10(size * 1e-4)))))


def _line_lists(segments: list[np.ndarray], decimals: int) -> tuple[list, list, list]:
    """Polylines -> x, y, z lists with None between them (plotly's gap), rounded."""
    xs, ys, zs = [], [], []
    for seg in segments:
        seg = np.round(np.asarray(seg, float), decimals)
        if xs:
            xs.append(None)
            ys.append(None)
            zs.append(None)
        xs.extend(seg[:, 0].tolist())
        ys.extend(seg[:, 1].tolist())
        zs.extend(seg[:, 2].tolist())
    return xs, ys, zs


def _compact(a: np.ndarray, decimals: int) -> np.ndarray:
    """Round and store as float32 (plotly writes numpy float32 arrays as compact base64)."""
    return np.round(np.asarray(a, float), decimals).astype(np.float32)


# ----------------------------------------------------------------------------- geometry
def scene_size(X) -> float:
    """Robust diameter of a point set: the diagonal of its 2nd..98th-percentile box.

    Args:
        X: ``(N, 3)`` points (NaN rows ignored).

    Returns:
        The diameter (1.0 if there are fewer than 2 finite points or they coincide).
    """
    X = _rows(X, "X")
    X = X[np.isfinite(X).all(axis=1)]
    if len(X) < 2:
        return 1.0
    lo, hi = np.percentile(X, [2, 98], axis=0) if len(X) >= 50 else (X.min(0), X.max(0))
    d = float(np.linalg.norm(hi - lo))
    return d if d > 0 else 1.0


def camera_frustum(R_cw, t_cw, K, image_size, scale: float) -> dict:
    """World coordinates of the frustum drawn for one camera.

    Args:
        R_cw: ``(3, 3)`` rotation (camera from world).
        t_cw: ``(3,)`` translation, ``x_cam = R_cw @ X + t_cw``.
        K: ``(3, 3)`` intrinsics.
        image_size: ``(W, H)`` in pixels.
        scale: depth (camera z, world units) of the far rectangle.

    Returns:
        dict with ``"apex"`` ``(3,)`` = the centre ``C = -R_cw.T @ t_cw``; ``"corners"`` ``(4, 3)``,
        the image corners (top-left, top-right, bottom-right, bottom-left, i.e. pixels
        (-0.5, -0.5), (W-0.5, -0.5), (W-0.5, H-0.5), (-0.5, H-0.5)) back-projected to depth
        ``scale``; ``"up_triangle"`` ``(3, 3)``, a triangle standing on the top edge and pointing
        to image up (camera -y); ``"up_tip"`` ``(3,)`` its tip.
    """
    R = rotation(_np(R_cw), "R_cw", atol=1e-4)
    t = _np(t_cw).reshape(-1)
    if t.shape != (3,):
        raise KitInputError(f"t_cw has shape {t.shape}: expected (3,)")
    K = intrinsics(_np(K))
    W, H = _image_size(image_size)
    C = -R.T @ t
    Kinv = np.linalg.inv(K)
    uv = np.array(
        [
            [-0.5, -0.5],
            [W - 0.5, -0.5],
            [W - 0.5, H - 0.5],
            [-0.5, H - 0.5],
            # up marker: base on the top edge (middle 40 %), tip 25 % of H above it
            [0.3 * W - 0.5, -0.5],
            [0.7 * W - 0.5, -0.5],
            [0.5 * W - 0.5, -0.5 - 0.25 * H],
        ]
    )
    rays = np.c_[uv, np.ones(len(uv))] @ Kinv.T  # z_cam = 1
    x_cam = rays * (scale / rays[:, 2:3])
    X = (x_cam - t) @ R  # R^T (x_cam - t), row-wise
    return {"apex": C, "corners": X[:4], "up_triangle": X[4:7], "up_tip": X[6]}


def _existing_points(fig: go.Figure) -> np.ndarray:
    pts = []
    for tr in fig.data:
        if getattr(tr, "meta", None) == _POINT_META and tr.x is not None:
            pts.append(np.c_[_np(tr.x), _np(tr.y), _np(tr.z)])
    return np.concatenate(pts) if pts else np.zeros((0, 3))


def set_axis_box(fig: go.Figure, lo: np.ndarray, hi: np.ndarray) -> None:
    """Fix the 3-D axes to the box ``[lo, hi]`` (each ``(3,)``) with equal scales on all axes."""
    ext = hi - lo
    fig.update_layout(scene=dict(
        xaxis=dict(range=[float(lo[0]), float(hi[0])], autorange=False),
        yaxis=dict(range=[float(lo[1]), float(hi[1])], autorange=False),
        zaxis=dict(range=[float(lo[2]), float(hi[2])], autorange=False),
        aspectmode="manual",
        aspectratio=dict(x=float(ext[0] / ext.max()), y=float(ext[1] / ext.max()), z=float(ext[2] / ext.max())),
    ))


def _fit_view(fig: go.Figure) -> None:
    """Keep a few far-away points from shrinking the scene to a dot.

    With plotly's automatic ranges, one badly triangulated point 50 scene sizes away makes the
    reconstruction a speck in a corner (seen in the browser on the SfM ``scene.html``). When the
    points' full box is more than 3 times the diagonal of their 1st..99th-percentile box, the
    axes are set to that robust box together with the camera centres (5 % margin), keeping equal
    scales; points outside are clipped from the view (the legend still counts them). Scenes
    without such outliers keep plotly's automatic ranges.
    """
    X = _existing_points(fig)
    X = X[np.isfinite(X).all(axis=1)]
    if len(X) < 50:
        return
    lo, hi = np.percentile(X, [1, 99], axis=0)
    full = float(np.linalg.norm(X.max(0) - X.min(0)))
    if full <= 3.0 * max(float(np.linalg.norm(hi - lo)), 1e-12):
        return
    centres = [np.c_[_np(tr.x), _np(tr.y), _np(tr.z)] for tr in fig.data
               if isinstance(tr.uid, str) and "-centres-" in tr.uid and tr.x is not None]
    if centres:
        C = np.concatenate(centres)
        lo, hi = np.minimum(lo, C.min(0)), np.maximum(hi, C.max(0))
    pad = 0.05 * float((hi - lo).max()) + 1e-9
    lo, hi = lo - pad, hi + pad
    set_axis_box(fig, lo, hi)


# ----------------------------------------------------------------------------- figure
def _layout(fig: go.Figure, title, height, up, eye) -> None:
    axis = dict(showbackground=True, backgroundcolor="#f4f4f4", gridcolor="#dddddd", zerolinecolor="#bbbbbb")
    up = np.asarray(up, float).reshape(3)
    camera = dict(up=dict(x=float(up[0]), y=float(up[1]), z=float(up[2])))
    if eye is None and np.allclose(up, (0, -1, 0)):
        eye = (0.9, -0.9, -1.8)  # behind and above cameras that look along +z
    if eye is not None:
        camera["eye"] = dict(x=float(eye[0]), y=float(eye[1]), z=float(eye[2]))
    fig.update_layout(
        template="none",
        title=dict(text=title) if title else None,
        height=int(height),
        margin=dict(l=0, r=0, t=40 if title else 10, b=0),
        paper_bgcolor="white",
        font=dict(size=12),
        legend=dict(itemsizing="constant", x=0.0, y=1.0, bgcolor="rgba(255,255,255,0.7)"),
        uirevision="course_lib",
        scene=dict(
            aspectmode="data",
            xaxis=dict(title=dict(text="x"), **axis),
            yaxis=dict(title=dict(text="y"), **axis),
            zaxis=dict(title=dict(text="z"), **axis),
            camera=camera,
        ),
    )


def scene_figure(
    cameras=None,
    points=None,
    title: str | None = None,
    point_budget: int = 20000,
    height: int = 600,
    up=(0.0, -1.0, 0.0),
    camera_scale: float | None = None,
    name: str = "scene",
    eye=None,
) -> go.Figure:
    """A 3-D scene of cameras and points with equal axis scales.

    Args:
        cameras: list of ``(R_cw (3, 3), t_cw (3,), K (3, 3), (W, H))`` or
            ``(R_cw, t_cw, K, (W, H), name)`` tuples, drawn as frustums in one legend group
            ``f"{name} cameras"``; or None.
        points: ``X (N, 3)``, or ``(X, rgb)`` with ``rgb (N, 3)`` uint8 or None; NaN rows are
            dropped; or None.
        title: figure title.
        point_budget: at most this many points are drawn (a fixed random subset above it).
        height: figure height in pixels.
        up: world direction shown up on screen; ``(0, -1, 0)`` for the kit's y-down SfM worlds,
            ``(0, 0, 1)`` for NeRF/Blender scenes.
        camera_scale: frustum depth in world units (default 5 % of the scene size).
        name: legend label prefix.
        eye: optional ``(3,)`` viewpoint of the 3-D view (plotly's normalized scene units).

    Returns:
        ``plotly.graph_objects.Figure``; add more with :func:`add_cameras`, :func:`add_points`,
        :func:`add_rays`.
    """
    fig = go.Figure()
    _layout(fig, title, height, up, eye)
    if points is not None:
        if isinstance(points, (tuple, list)) and len(points) == 2 and np.ndim(points[0]) == 2:
            X, rgb = points
        else:
            X, rgb = points, None
        add_points(fig, X, rgb, name=f"{name} points", max_points=point_budget, legend_group=f"{name} points")
    if cameras:
        Rs, ts, Ks, names, size = [], [], [], [], None
        for i, cam in enumerate(cameras):
            if not isinstance(cam, (tuple, list)) or len(cam) not in (4, 5):
                raise KitInputError(
                    f"cameras[{i}] must be a tuple (R_cw, t_cw, K, (W, H)) or (R_cw, t_cw, K, (W, H), name); got {type(cam).__name__}"
                )
            Rs.append(_np(cam[0]))
            ts.append(_np(cam[1]).reshape(-1))
            Ks.append(_np(cam[2]))
            s = _image_size(cam[3])
            if size is not None and s != size:
                raise KitInputError(f"cameras[{i}] has image size {s} but cameras[0] has {size}: draw them with two add_cameras calls")
            size = s
            names.append(str(cam[4]) if len(cam) == 5 else f"camera {i}")
        add_cameras(fig, np.stack(Rs), np.stack(ts), np.stack(Ks), size, names=names, scale=camera_scale, legend_group=f"{name} cameras")
    return fig


def _palette_marker(col: np.ndarray) -> dict:
    """The marker colours of ``col (N, 3)`` uint8 as a palette and one index a point (or one colour)."""
    # palette + colour indices: ~1.3-2.7 bytes a point instead of a "#rrggbb" string each;
    # 5 bits a channel, fewer if that gives more than 512 distinct colours
    for bits in (5, 4, 3, 2):
        q = (col >> (8 - bits)).astype(np.int32)
        key = (q[:, 0] << (2 * bits)) + (q[:, 1] << bits) + q[:, 2]
        uniq, inv = np.unique(key, return_inverse=True)
        if len(uniq) <= 512:
            break
    m = (1 << bits) - 1
    pal = (np.stack([uniq >> (2 * bits), (uniq >> bits) & m, uniq & m], 1) * 255 + m // 2) // m
    if len(uniq) == 1:
        return {"color": _colour(pal[0])}
    n = len(uniq)
    return dict(color=inv.astype(np.uint16 if n > 255 else np.uint8), cmin=0, cmax=n - 1,
                colorscale=[[round(k / (n - 1), 6), _colour(p)] for k, p in enumerate(pal)], showscale=False)


def add_points(
    fig: go.Figure,
    X,
    rgb=None,
    name: str = "points",
    max_points: int | None = 20000,
    size: float = 2,
    color: str | None = None,
    legend_group: str | None = None,
    rng_seed: int = 0,
) -> go.Figure:
    """Add a point cloud (one trace).

    Args:
        fig: figure from :func:`scene_figure`.
        X: ``(N, 3)`` world points; rows with NaN/inf are dropped.
        rgb: ``(N, 3)`` uint8 colours (floats in [0, 1] are accepted) or None.
        name: legend label.
        max_points: above this many (finite) points, a subset of exactly ``max_points`` is drawn,
            chosen with ``numpy.random.default_rng(rng_seed)`` (deterministic); None = all.
        size: marker size in pixels.
        color: one colour for all points when ``rgb`` is None (default: the group's colour).
        legend_group: legend group to toggle with (default: ``name``).
        rng_seed: seed of the subsampling.

    Returns:
        ``fig`` (modified in place).
    """
    X = _rows(X, "X")
    group = legend_group or name
    col = None
    if rgb is not None:
        c = _np(rgb)
        if c.shape != X.shape:
            raise KitInputError(f"rgb has shape {tuple(c.shape)}: expected {X.shape} (one colour per point)")
        if np.issubdtype(np.asarray(rgb).dtype, np.floating) and np.nanmax(c, initial=0) <= 1.0:
            c = c * 255.0
        col = np.clip(np.nan_to_num(c), 0, 255).round().astype(np.uint8)
    keep = np.isfinite(X).all(axis=1)
    X = X[keep]
    col = col[keep] if col is not None else None
    if max_points is not None and len(X) > max_points:
        idx = np.sort(np.random.default_rng(rng_seed).choice(len(X), size=int(max_points), replace=False))
        X = X[idx]
        col = col[idx] if col is not None else None
    dec = _decimals(scene_size(X) if len(X) else 1.0)
    marker = dict(size=size)
    if col is not None:
        marker.update(_palette_marker(col))
    else:
        marker["color"] = _group_colour(fig, group, color)
    fig.add_trace(
        go.Scatter3d(
            x=_compact(X[:, 0], dec),
            y=_compact(X[:, 1], dec),
            z=_compact(X[:, 2], dec),
            mode="markers",
            marker=marker,
            name=f"{name} ({len(X)})",
            legendgroup=group,
            hoverinfo="skip" if len(X) > 5000 else "x+y+z",
            meta=_POINT_META,
            uid=_uid(fig, "points", group),
        )
    )
    _fit_view(fig)
    return fig


def add_cameras(
    fig: go.Figure,
    R_cw,
    t_cw,
    K,
    image_size,
    names=None,
    color: str | None = None,
    scale: float | None = None,
    legend_group: str | None = None,
    images=None,
    show_names: bool | None = None,
) -> go.Figure:
    """Add cameras as frustums with an "up" marker (one legend entry for all of them).

    Args:
        fig: figure from :func:`scene_figure`.
        R_cw: ``(M, 3, 3)`` rotations (a single ``(3, 3)`` is accepted).
        t_cw: ``(M, 3)`` translations, ``x_cam = R_cw[i] @ X + t_cw[i]``.
        K: ``(3, 3)`` shared intrinsics or ``(M, 3, 3)``.
        image_size: ``(W, H)`` in pixels.
        names: M labels shown on hover (and as text when ``show_names``); default "cam i".
        color: colour of this group (default: the next colour of :data:`PALETTE`).
        scale: depth of the far rectangle in world units (default: 5 % of the size of the scene
            made of the points already in ``fig`` and the camera centres).
        legend_group: legend entry, e.g. ``"before BA"``; clicking it toggles these cameras.
        images: optional list of M ``(H, W, 3)`` uint8 images painted (coarsely, 24 px wide)
            on the far rectangles; costs ~35 kB per camera in the notebook.
        show_names: write the names beside the apexes (default: when M <= 12).

    Returns:
        ``fig`` (modified in place).
    """
    R, t = camera_poses(R_cw, t_cw)
    M = R.shape[0]
    Ks = _camera_intrinsics(K, M)
    W, H = _image_size(image_size)
    names = [f"cam {i}" for i in range(M)] if names is None else [str(n) for n in names]
    if len(names) != M:
        raise KitInputError(f"names has {len(names)} entries for {M} cameras")
    group = legend_group or "cameras"
    col = _group_colour(fig, group, color)
    centres = np.einsum("mji,mj->mi", R, -t)  # C = -R^T t
    if scale is None:
        pts = np.concatenate([_existing_points(fig), centres])
        scale = 0.05 * scene_size(pts) if len(pts) >= 2 else 1.0
    scale = float(scale)
    if not np.isfinite(scale) or scale <= 0:
        raise KitInputError(f"scale must be a positive number of world units, got {scale}")
    dec = _decimals(max(scale * 20, 1e-9))
    frusta = [camera_frustum(R[i], t[i], Ks[i], (W, H), scale) for i in range(M)]
    _add_frustum_lines(fig, frusta, dec, col, group, f"{group} ({M})" if legend_group else f"cameras ({M})")
    _add_apexes(fig, frusta, names, dec, col, group, M <= 12 if show_names is None else show_names)
    if images is not None:
        if len(images) != M:
            raise KitInputError(f"images has {len(images)} entries for {M} cameras")
        for i, (img, f) in enumerate(zip(images, frusta)):
            _add_image_plane(fig, np.asarray(img), f["corners"], dec, group, f"{names[i]} image")
    _fit_view(fig)
    return fig


def _camera_intrinsics(K, M: int) -> list[np.ndarray]:
    """M checked ``(3, 3)`` intrinsics from one shared ``(3, 3)`` or ``(M, 3, 3)``."""
    Kn = _np(K)
    if Kn.shape == (3, 3):
        return [intrinsics(Kn)] * M
    if Kn.shape != (M, 3, 3):
        raise KitInputError(f"K has shape {tuple(Kn.shape)}: expected (3, 3) or ({M}, 3, 3)")
    return [intrinsics(k, f"K[{i}]") for i, k in enumerate(Kn)]


def _add_frustum_lines(fig, frusta: list[dict], dec: int, col: str, group: str, name: str) -> None:
    """One line trace: each frustum's far rectangle, its four edges to the apex and its "up" triangle."""
    segs = []
    for f in frusta:
        a, c = f["apex"], f["corners"]
        segs.append(np.stack([c[0], c[1], c[2], c[3], c[0]]))
        segs.extend(np.stack([a, c[k]]) for k in range(4))
        tri = f["up_triangle"]
        segs.append(np.stack([tri[0], tri[2], tri[1]]))
    xs, ys, zs = _line_lists(segs, dec)
    fig.add_trace(
        go.Scatter3d(
            x=xs,
            y=ys,
            z=zs,
            mode="lines",
            line=dict(color=col, width=3),
            name=name,
            legendgroup=group,
            hoverinfo="skip",
            uid=_uid(fig, "frustums", group),
        )
    )


def _add_apexes(fig, frusta: list[dict], names: list[str], dec: int, col: str, group: str, show_names: bool) -> None:
    """One marker trace at the camera centres, named on hover (and as text when ``show_names``)."""
    apex = np.round(np.stack([f["apex"] for f in frusta]), dec)
    fig.add_trace(
        go.Scatter3d(
            x=apex[:, 0].tolist(),
            y=apex[:, 1].tolist(),
            z=apex[:, 2].tolist(),
            mode="markers+text" if show_names else "markers",
            text=names if show_names else None,
            hovertext=names,
            hoverinfo="text",
            textposition="top center",
            textfont=dict(size=10, color=col),
            marker=dict(size=3, color=col),
            name=f"{group} centres",
            legendgroup=group,
            showlegend=False,
            uid=_uid(fig, "centres", group),
        )
    )


def _add_image_plane(fig, img: np.ndarray, corners: np.ndarray, dec: int, group: str, name: str) -> None:
    """Paint a coarse version of ``img`` on the quad ``corners`` (TL, TR, BR, BL) as a mesh."""
    if img.ndim != 3 or img.shape[2] < 3:
        raise KitInputError(f"each image must be (H, W, 3) RGB, got shape {img.shape}")
    img = img[..., :3]
    if img.dtype != np.uint8:
        img = np.clip(np.asarray(img, float) * (255.0 if np.nanmax(img) <= 1.0 else 1.0), 0, 255).astype(np.uint8)
    H, W = img.shape[:2]
    nx = min(24, W)
    ny = max(1, min(H, round(nx * H / W)))
    # box-average into ny x nx cells
    ys = np.linspace(0, H, ny + 1).astype(int)
    xs = np.linspace(0, W, nx + 1).astype(int)
    cells = np.array([[img[ys[r] : ys[r + 1], xs[c] : xs[c + 1]].reshape(-1, 3).mean(0) for c in range(nx)] for r in range(ny)])
    a, b = np.meshgrid(np.linspace(0, 1, nx + 1), np.linspace(0, 1, ny + 1))  # a along u, b along v
    tl, tr, br, bl = corners
    P = (1 - a)[..., None] * (1 - b)[..., None] * tl + a[..., None] * (1 - b)[..., None] * tr
    P = P + a[..., None] * b[..., None] * br + (1 - a)[..., None] * b[..., None] * bl
    P = np.round(P.reshape(-1, 3), dec)
    idx = np.arange((ny + 1) * (nx + 1)).reshape(ny + 1, nx + 1)
    v00, v01, v10, v11 = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    ii = np.r_[v00, v01]
    jj = np.r_[v01, v11]
    kk = np.r_[v10, v10]
    fc = [_colour(c) for c in cells.reshape(-1, 3).round().astype(int)] * 2
    fig.add_trace(
        go.Mesh3d(
            x=P[:, 0].tolist(),
            y=P[:, 1].tolist(),
            z=P[:, 2].tolist(),
            i=ii.tolist(),
            j=jj.tolist(),
            k=kk.tolist(),
            facecolor=fc,
            flatshading=True,
            lighting=dict(ambient=1.0, diffuse=0.0, specular=0.0),
            hoverinfo="skip",
            name=name,
            legendgroup=group,
            showlegend=False,
            uid=_uid(fig, "image", group),
        )
    )


def _ray_inputs(rays_o, rays_d, samples, sample_values):
    """:func:`add_rays`' inputs checked: ``o, d (R, 3)``, ``S (R, S, 3)`` or None, ``V (R, S)`` or None."""
    o = _np(rays_o)
    d = _np(rays_d)
    if o.ndim == 3:
        o = o.reshape(-1, 3)
    if d.ndim == 3:
        d = d.reshape(-1, 3)
    o = _rows(o, "rays_o")
    d = _rows(d, "rays_d")
    if o.shape != d.shape:
        raise KitInputError(f"rays_o has shape {o.shape} but rays_d has {d.shape}: one origin per direction")
    Rn = o.shape[0]
    S = None
    if samples is not None:
        S = _np(samples)
        if S.ndim != 3 or S.shape[0] != Rn or S.shape[2] != 3:
            raise KitInputError(f"samples has shape {tuple(S.shape)}: expected ({Rn}, S, 3)")
    V = None
    if sample_values is not None:
        if S is None:
            raise KitInputError("sample_values needs samples")
        V = _np(sample_values)
        if V.shape != S.shape[:2]:
            raise KitInputError(f"sample_values has shape {tuple(V.shape)}: expected {S.shape[:2]}")
    return o, d, S, V


def _add_samples(fig: go.Figure, S: np.ndarray, V, col: str, dec: int, name: str, group: str) -> None:
    """The sample points ``S (R, S, 3)`` of :func:`add_rays`, coloured by ``V (R, S)`` where given."""
    P = S.reshape(-1, 3)
    keep = np.isfinite(P).all(1)
    marker = dict(size=2, color=col)
    if V is not None:
        v = V.reshape(-1)[keep]
        marker = dict(size=2.5, color=_compact(v, 4), colorscale="Viridis", showscale=True,
                      colorbar=dict(thickness=10, len=0.5, title=dict(text="value")))
    P = P[keep]
    fig.add_trace(
        go.Scatter3d(
            x=_compact(P[:, 0], dec), y=_compact(P[:, 1], dec), z=_compact(P[:, 2], dec), mode="markers",
            marker=marker, name=f"{name} samples", legendgroup=group, showlegend=False,
            hoverinfo="skip", uid=_uid(fig, "samples", group),
        )
    )


def add_rays(
    fig: go.Figure,
    rays_o,
    rays_d,
    samples=None,
    t_far: float | None = None,
    sample_values=None,
    name: str = "rays",
    color: str | None = None,
    legend_group: str | None = None,
    max_rays: int | None = 256,
    rng_seed: int = 0,
) -> go.Figure:
    """Add rays (segments) and, optionally, their sample points (for the NeRF notebooks).

    Args:
        fig: figure from :func:`scene_figure` (NeRF scenes: ``up=(0, 0, 1)``).
        rays_o: ``(R, 3)`` origins (``(H, W, 3)`` is flattened).
        rays_d: ``(R, 3)`` directions (not necessarily unit).
        samples: optional ``(R, S, 3)`` sample points along the rays.
        t_far: each segment is ``o -> o + t_far * d``; default: up to the farthest sample, or 1.
        sample_values: optional ``(R, S)`` numbers colouring the samples (e.g. weights).
        name: legend label; legend_group: toggle group (default ``name``); color: line colour.
        max_rays: draw at most this many rays (a fixed random subset with ``rng_seed``).

    Returns:
        ``fig`` (modified in place).
    """
    o, d, S, V = _ray_inputs(rays_o, rays_d, samples, sample_values)
    Rn = o.shape[0]
    idx = np.arange(Rn)
    if max_rays is not None and Rn > max_rays:
        idx = np.sort(np.random.default_rng(rng_seed).choice(Rn, size=int(max_rays), replace=False))
    o, d = o[idx], d[idx]
    if S is not None:
        S = S[idx]
        V = V[idx] if V is not None else None
    if t_far is None:
        if S is not None:
            dd = np.maximum((d * d).sum(1), 1e-12)
            t_far_r = np.nanmax(((S - o[:, None]) * d[:, None]).sum(-1), axis=1) / dd
        else:
            t_far_r = np.ones(len(o))
    else:
        t_far_r = np.full(len(o), float(t_far))
    ends = o + t_far_r[:, None] * d
    group = legend_group or name
    col = _group_colour(fig, group, color)
    dec = _decimals(scene_size(np.concatenate([o, ends])))
    xs, ys, zs = _line_lists([np.stack([a, b]) for a, b in zip(o, ends)], dec)
    fig.add_trace(
        go.Scatter3d(
            x=xs, y=ys, z=zs, mode="lines", line=dict(color=col, width=2), name=f"{name} ({len(o)})",
            legendgroup=group, hoverinfo="skip", uid=_uid(fig, "rays", group),
        )
    )
    if S is not None:
        _add_samples(fig, S, V, col, dec, name, group)
    return fig


def write_html(fig: go.Figure, path) -> Path:
    """Write a standalone HTML file with plotly.js embedded (opens offline, ~5 MB).

    Args:
        fig: a plotly figure.
        path: output file (``.html``); parent folders are created.

    Returns:
        The path written.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.write_html(str(path), include_plotlyjs=True, full_html=True, auto_open=False, div_id="course-lib-figure")
    return path

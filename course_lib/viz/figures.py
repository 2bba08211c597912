"""2-D figures with matplotlib: matches, epipolar lines, errors, visibility, sparsity, training.

Every function returns a :class:`matplotlib.figure.Figure` and has no side effects: the figure is
*not* registered with ``pyplot``, so nothing is shown twice and nothing piles up in memory. In a
notebook make it the last expression of a cell (``draw_matches(...)``) or call
``display(fig)``; in a script call ``fig.savefig("out.png")``. Figures use one fixed style and a
small size (dpi 80) so the PNGs stored in notebooks stay small (photographs are drawn in grey by
default for the same reason, and so the coloured lines stand out).

Conventions (see :mod:`course_lib.conventions`): pixels ``(u, v)`` = (column, row), origin at the
top-left, image points are rows ``(N, 2)``; images are ``(H, W, 3)`` uint8 RGB or float in
[0, 1] (``(H, W)`` grey also works; torch tensors are accepted).

API::

    draw_matches(img1, img2, x1 (N,2), x2 (N,2), inliers=None (N,) bool, max_lines=200,
                 rng_seed=0, gray=True, title=None, figsize=None) -> Figure
        Images side by side, one line per match: inliers green, outliers red (all blue when
        `inliers` is None); at most `max_lines` lines, a fixed random subset (rng_seed).

    draw_epipolar_lines(img1, img2, F (3,3), x1 (N,2), x2 (N,2), n=10, rng_seed=0, gray=True,
                        title=None, figsize=None) -> Figure
        Convention x2h^T F x1h = 0. For n (fixed random) correspondences: in image 2 the lines
        F x1h with the points x2, in image 1 the lines F^T x2h with the points x1, one colour per
        correspondence.

    plot_reprojection_errors(errors_before (N,), errors_after=None (N',),
                             labels=("before", "after"), bins=40, max_px=None, title=None) -> Figure
        Histogram (left) and cumulative distribution (right) of pixel errors; the legend gives
        median and RMSE. NaN/inf entries are ignored. `errors_before` may also be a list of
        arrays (then `labels` has one label per array and `errors_after` is None).

    plot_visibility(V (T,M) bool, camera_names=None, sort_tracks=False, title=None) -> Figure
        Image with one column per camera (x axis: camera index or name) and one row per track /
        3-D point (y axis); dark = point seen in that camera. A bar chart below counts the
        observations per camera.

    plot_jacobian_sparsity(J (R,P) scipy.sparse or dense, col_splits=None, row_splits=None,
                           title=None, max_markers=200000) -> Figure
        Spy plot of the non-zeros (rows: residuals, columns: parameters). `col_splits` e.g.
        [6 * M] draws a line between the camera and the point parameters. Above `max_markers`
        non-zeros the pattern is drawn as a binned image instead of markers.

    plot_training_curves(history: dict, title=None) -> Figure
        history keys: "iterations" (or "iteration"/"step") (K,), "loss" (K,), optional "psnr"
        (K,), optional "test_psnr" (K',) with "test_iterations" (K',) (default: the last K'
        iterations). Left: loss (log scale); right: PSNR in dB (train, test).

    image_grid(images (N,H,W,3) or list of (H,W,3)/(H,W), titles=None, ncols=4, size=2.0,
               suptitle=None) -> Figure
        Images in a grid, axes off; `size` is the width of one cell in inches.

Introduced in ``notebooks/01_fundamental_matrix.ipynb`` (matches) and used by every notebook.
"""

from __future__ import annotations

import matplotlib as mpl
import numpy as np
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from course_lib.validate import KitInputError, matching_points

__all__ = [
    "STYLE",
    "KitFigure",
    "draw_matches",
    "draw_epipolar_lines",
    "plot_reprojection_errors",
    "plot_visibility",
    "plot_jacobian_sparsity",
    "plot_training_curves",
    "image_grid",
]

#: The fixed style of every figure of the kit (small PNGs, same look on every machine).
STYLE = {
    "figure.dpi": 80,
    "savefig.dpi": 80,
    "figure.facecolor": "white",
    "savefig.facecolor": "white",
    "font.size": 9,
    "axes.titlesize": 10,
    "axes.labelsize": 9,
    "legend.fontsize": 8,
    "xtick.labelsize": 8,
    "ytick.labelsize": 8,
    "axes.grid": False,
    "grid.alpha": 0.3,
    "lines.linewidth": 1.2,
    "image.interpolation": "nearest",
    "svg.hashsalt": "course_lib",
    "axes.prop_cycle": mpl.cycler(color=["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf"]),
}

INLIER_COLOUR = "#22b14c"
OUTLIER_COLOUR = "#e0201b"


class KitFigure(Figure):
    """A matplotlib Figure that shows itself as a PNG in Jupyter, even without pyplot.

    IPython draws a bare ``Figure`` only when the inline backend has been activated; this one
    carries its own ``_repr_png_`` (IPython prefers the backend's printer when there is one, so
    it is never shown twice).
    """

    def _repr_png_(self) -> bytes:
        import io

        buf = io.BytesIO()
        with mpl.rc_context(STYLE):
            self.savefig(buf, format="png", bbox_inches="tight", dpi=self.dpi)
        return buf.getvalue()


def _figure(figsize) -> Figure:
    with mpl.rc_context(STYLE):
        return KitFigure(figsize=figsize, dpi=STYLE["figure.dpi"], layout="constrained")


def _np(a, dtype=None) -> np.ndarray:
    if hasattr(a, "detach") and hasattr(a, "cpu"):
        a = a.detach().cpu().numpy()
    return np.asarray(a) if dtype is None else np.asarray(a, dtype=dtype)


def _image(img, name: str, gray: bool = False) -> np.ndarray:
    """(H, W, 3) float image in [0, 1] (grey replicated to 3 channels if gray)."""
    a = _np(img)
    if a.ndim == 3 and a.shape[0] in (1, 3) and a.shape[2] not in (1, 3, 4):
        raise KitInputError(f"{name} has shape {a.shape}: expected (H, W, 3) (channels last; use img.permute(1, 2, 0))")
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    if a.ndim != 3 or a.shape[2] not in (3, 4):
        raise KitInputError(f"{name} has shape {a.shape}: expected an (H, W, 3) RGB image or (H, W) grey")
    a = a[..., :3]
    if a.dtype == np.uint8:
        a = a.astype(np.float32) / 255.0
    else:
        a = a.astype(np.float32)
        if np.nanmax(a, initial=0) > 1.0 + 1e-3:
            a = a / 255.0
    a = np.clip(np.nan_to_num(a), 0.0, 1.0)
    if gray:
        g = a @ np.array([0.299, 0.587, 0.114], np.float32)
        a = np.repeat((0.25 + 0.75 * g)[..., None], 3, axis=2)  # lightened, so lines stand out
    return a


def _side_by_side(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, int]:
    H = max(a.shape[0], b.shape[0])
    canvas = np.ones((H, a.shape[1] + b.shape[1], 3), np.float32)
    canvas[: a.shape[0], : a.shape[1]] = a
    canvas[: b.shape[0], a.shape[1] :] = b
    return canvas, a.shape[1]


def _show_photo(ax, img: np.ndarray, width_px: float, gray: bool) -> None:
    """imshow a photo in its own pixel coordinates, pre-shrunk to about the drawn size.

    Shrinking by box-averaging (and, for grey, 32 levels) before matplotlib resamples keeps the
    stored PNG small; ``extent`` keeps the axes in the original pixel coordinates.
    """
    H, W = img.shape[:2]
    f = max(1, int(np.ceil(W / max(width_px, 1.0) - 0.25)))
    small = img
    if f > 1:
        small = img[: H // f * f, : W // f * f].reshape(H // f, f, W // f, f, 3).mean(axis=(1, 3))
    if gray:
        small = np.round(small * 31.0) / 31.0
    ax.imshow(small, interpolation="nearest" if f > 1 or gray else "antialiased",
              extent=(-0.5, (W // f) * f - 0.5, (H // f) * f - 0.5, -0.5))


def _subset(n: int, k: int, rng_seed: int) -> np.ndarray:
    if n <= k:
        return np.arange(n)
    return np.sort(np.random.default_rng(rng_seed).choice(n, size=k, replace=False))


def draw_matches(img1, img2, x1, x2, inliers=None, max_lines: int = 200, rng_seed: int = 0, gray: bool = True,
                 title: str | None = None, figsize=None) -> Figure:
    """Two images side by side with a line per correspondence.

    Args:
        img1, img2: ``(H, W, 3)`` images (uint8 or float in [0, 1]).
        x1, x2: ``(N, 2)`` pixels ``(u, v)``; row k of both is one match.
        inliers: optional ``(N,)`` bool; inliers are drawn green, outliers red.
        max_lines: at most this many lines (a fixed random subset); every match still gets a dot.
        rng_seed: seed of that subset.
        gray: draw the photos in (lightened) grey.
        title: default says how many matches/inliers there are.
        figsize: inches; default 9 wide.

    Returns:
        The Figure.
    """
    x1, x2 = matching_points(x1, x2)
    a, b = _image(img1, "img1", gray), _image(img2, "img2", gray)
    N = len(x1)
    if inliers is not None:
        inl = _np(inliers).astype(bool).reshape(-1)
        if inl.shape != (N,):
            raise KitInputError(f"inliers has shape {np.shape(inliers)}: expected ({N},) bool, one per match")
    canvas, off = _side_by_side(a, b)
    if figsize is None:
        figsize = (9.0, max(2.0, 9.0 * canvas.shape[0] / canvas.shape[1]) + 0.4)
    fig = _figure(figsize)
    with mpl.rc_context(STYLE):
        ax = fig.add_subplot()
        _show_photo(ax, canvas, figsize[0] * STYLE["figure.dpi"], gray)
        idx = _subset(N, max_lines, rng_seed)
        if inliers is None:
            colours = np.array(["#1f77b4"] * N)
        else:
            colours = np.where(inl, INLIER_COLOUR, OUTLIER_COLOUR)
        # outliers first, so the inliers are drawn on top
        order = idx[np.argsort(colours[idx] == INLIER_COLOUR, kind="stable")] if inliers is not None else idx
        segs = np.stack([x1[order], x2[order] + [off, 0.0]], axis=1)  # (L, 2 ends, 2)
        ax.add_collection(LineCollection(segs, colors=list(colours[order]), linewidths=0.7, alpha=0.8))
        ax.scatter(x1[:, 0], x1[:, 1], s=4, c=colours, linewidths=0)
        ax.scatter(x2[:, 0] + off, x2[:, 1], s=4, c=colours, linewidths=0)
        ax.set_xlim(-0.5, canvas.shape[1] - 0.5)
        ax.set_ylim(canvas.shape[0] - 0.5, -0.5)
        ax.set_axis_off()
        if title is None:
            title = f"{N} matches"
            if inliers is not None:
                title += f": {int(inl.sum())} inliers (green), {int(N - inl.sum())} outliers (red)"
            if N > max_lines:
                title += f"; {max_lines} lines drawn"
        ax.set_title(title)
    return fig


def _draw_line(ax, l: np.ndarray, W: int, H: int, colour) -> None:
    """Draw the line a u + b v + c = 0 across the image (clipped by the axes limits)."""
    a_, b_, c_ = l
    if abs(b_) >= abs(a_):
        u = np.array([-0.5, W - 0.5])
        v = -(a_ * u + c_) / b_
    else:
        v = np.array([-0.5, H - 0.5])
        u = -(b_ * v + c_) / a_
    ax.plot(u, v, "-", color=colour, lw=1.0)


def draw_epipolar_lines(img1, img2, F, x1, x2, n: int = 10, rng_seed: int = 0, gray: bool = True,
                        title: str | None = None, figsize=None) -> Figure:
    """Epipolar lines of a few correspondences in both images (``x2h^T F x1h = 0``).

    Args:
        img1, img2: ``(H, W, 3)`` images.
        F: ``(3, 3)`` fundamental matrix with ``x2h^T F x1h = 0``.
        x1, x2: ``(N, 2)`` corresponding pixels.
        n: how many correspondences to draw (a fixed random subset, ``rng_seed``).
        gray: draw the photos in grey. title, figsize: as usual.

    Returns:
        The Figure: left image 1 with the lines ``F^T x2h`` and the points ``x1``, right image 2
        with the lines ``F x1h`` and the points ``x2``. If F is right, each point lies on the line
        of its own colour.
    """
    x1, x2 = matching_points(x1, x2, min_count=1, why="drawing epipolar lines")
    F = _np(F, float)
    if F.shape != (3, 3) or not np.isfinite(F).all():
        raise KitInputError(f"F has shape {F.shape}: expected a finite (3, 3) fundamental matrix")
    a, b = _image(img1, "img1", gray), _image(img2, "img2", gray)
    idx = _subset(len(x1), n, rng_seed)
    h1 = np.c_[x1[idx], np.ones(len(idx))]
    h2 = np.c_[x2[idx], np.ones(len(idx))]
    l2 = h1 @ F.T  # F x1h, lines in image 2
    l1 = h2 @ F  # F^T x2h, lines in image 1
    if figsize is None:
        r = max(a.shape[0] / a.shape[1], b.shape[0] / b.shape[1])
        figsize = (9.0, max(2.0, 4.5 * r) + 0.5)
    fig = _figure(figsize)
    cmap = mpl.colormaps["tab10"]
    with mpl.rc_context(STYLE):
        axes = fig.subplots(1, 2)
        for ax, img, lines, pts, label in (
            (axes[0], a, l1, x1[idx], "image 1: lines $F^T x_2$, points $x_1$"),
            (axes[1], b, l2, x2[idx], "image 2: lines $F x_1$, points $x_2$"),
        ):
            H, W = img.shape[:2]
            _show_photo(ax, img, figsize[0] * STYLE["figure.dpi"] / 2, gray)
            for k in range(len(idx)):
                c = cmap(k % 10)
                _draw_line(ax, lines[k], W, H, c)
                ax.plot(pts[k, 0], pts[k, 1], "o", ms=5, mfc=c, mec="black", mew=0.6)
            ax.set_xlim(-0.5, W - 0.5)
            ax.set_ylim(H - 0.5, -0.5)
            ax.set_axis_off()
            ax.set_title(label)
        if title:
            fig.suptitle(title)
    return fig


def _errors(e, name: str) -> np.ndarray:
    e = _np(e, float).reshape(-1)
    return e[np.isfinite(e)]


def plot_reprojection_errors(errors_before, errors_after=None, labels=("before", "after"), bins: int = 40,
                             max_px: float | None = None, title: str | None = None) -> Figure:
    """Histogram and cumulative distribution of reprojection errors (pixels).

    Args:
        errors_before: ``(N,)`` errors in pixels (e.g. before bundle adjustment), or a list of
            such arrays (then ``errors_after`` must be None).
        errors_after: optional ``(N',)`` errors (e.g. after bundle adjustment).
        labels: one label per array.
        bins: histogram bins (shared by all arrays).
        max_px: right end of the x axis (default: the 99th percentile of all errors).
        title: figure title.

    Returns:
        The Figure (left: histogram, right: CDF); the legend gives each median and RMSE.
    """
    if isinstance(errors_before, (list, tuple)) and errors_after is None and len(errors_before) and np.ndim(errors_before[0]) >= 1:
        arrays = [_errors(e, f"errors[{i}]") for i, e in enumerate(errors_before)]
    else:
        arrays = [_errors(errors_before, "errors_before")]
        if errors_after is not None:
            arrays.append(_errors(errors_after, "errors_after"))
    labels = list(labels)[: len(arrays)]
    if len(labels) < len(arrays):
        labels += [f"set {i}" for i in range(len(labels), len(arrays))]
    if all(len(e) == 0 for e in arrays):
        raise KitInputError("no finite errors to plot")
    allv = np.concatenate(arrays)
    hi = float(max_px) if max_px is not None else float(np.percentile(allv, 99)) if len(allv) else 1.0
    hi = hi if hi > 0 else 1.0
    edges = np.linspace(0.0, hi, bins + 1)
    fig = _figure((8.0, 3.0))
    with mpl.rc_context(STYLE):
        ax1, ax2 = fig.subplots(1, 2)
        for k, (e, lab) in enumerate(zip(arrays, labels)):
            c = f"C{k}"
            if len(e) == 0:
                continue
            med, rmse = float(np.median(e)), float(np.sqrt(np.mean(e**2)))
            txt = f"{lab}: median {med:.2f} px, RMSE {rmse:.2f} px"
            ax1.hist(np.clip(e, 0, hi), bins=edges, histtype="stepfilled", alpha=0.35, color=c)
            ax1.hist(np.clip(e, 0, hi), bins=edges, histtype="step", color=c, label=txt)
            s = np.sort(e)
            ax2.plot(s, np.arange(1, len(s) + 1) / len(s), color=c, label=lab)
        ax1.set_xlabel("reprojection error [px]" + (f" (last bin: >= {hi:.2g})" if max_px is None else ""))
        ax1.set_ylabel("count")
        ax1.legend(loc="upper right")
        ax2.set_xlabel("reprojection error [px]")
        ax2.set_ylabel("fraction of observations <= error")
        ax2.set_xlim(0, hi)
        ax2.set_ylim(0, 1.01)
        ax2.grid(True)
        if title:
            fig.suptitle(title)
    return fig


def plot_visibility(V, camera_names=None, sort_tracks: bool = False, title: str | None = None) -> Figure:
    """The visibility matrix as an image: columns = cameras, rows = tracks (3-D points).

    Args:
        V: ``(T, M)`` bool, ``V[j, i]`` True if track/point j is seen in camera i.
        camera_names: optional M labels for the x axis.
        sort_tracks: order the rows by the first camera that sees them (shows the band structure
            of a sequence).
        title: default gives T, M and the mean track length.

    Returns:
        The Figure: the matrix (dark = seen) above a bar chart of observations per camera.
    """
    V = _np(V)
    if V.ndim != 2:
        raise KitInputError(f"V has shape {V.shape}: expected (T, M) bool, one row per track and one column per camera")
    V = V.astype(bool)
    T, M = V.shape
    if sort_tracks and T:
        first = np.where(V.any(1), V.argmax(1), M)
        V = V[np.lexsort((-V.sum(1), first))]
    fig = _figure((min(8.0, max(4.5, 2.5 + 0.35 * M)), 4.5))
    with mpl.rc_context(STYLE):
        gs = fig.add_gridspec(2, 1, height_ratios=[3, 1])
        ax = fig.add_subplot(gs[0])
        ax.imshow(V, aspect="auto", cmap="Greys", vmin=0, vmax=1, interpolation="nearest",
                  extent=(-0.5, M - 0.5, T - 0.5, -0.5))
        ax.set_ylabel(f"track / 3-D point j (T = {T})")
        ax.set_xticks([])
        if title is None:
            mean_len = float(V.sum(1).mean()) if T else 0.0
            title = f"visibility V[j, i]: {T} tracks x {M} cameras\nmean track length {mean_len:.2f} cameras"
        ax.set_title(title)
        axb = fig.add_subplot(gs[1], sharex=ax)
        axb.bar(np.arange(M), V.sum(0), color="#555555", width=0.8)
        axb.set_ylabel("points seen")
        axb.set_xlabel("camera i")
        ticks = np.arange(M) if M <= 30 else np.linspace(0, M - 1, 10).round().astype(int)
        axb.set_xticks(ticks)
        if camera_names is not None:
            names = [str(n) for n in camera_names]
            if len(names) != M:
                raise KitInputError(f"camera_names has {len(names)} entries for {M} cameras (columns of V)")
            axb.set_xticklabels([names[t] for t in ticks], rotation=90 if M > 8 else 0)
        axb.set_xlim(-0.5, M - 0.5)
    return fig


def plot_jacobian_sparsity(J, col_splits=None, row_splits=None, title: str | None = None, max_markers: int = 200000) -> Figure:
    """Spy plot of a (sparse) Jacobian: rows are residuals, columns are parameters.

    Args:
        J: ``(R, P)`` ``scipy.sparse`` matrix or dense array.
        col_splits: column indices where a vertical line is drawn, e.g. ``[6 * M]`` between the
            camera and the point parameters of bundle adjustment.
        row_splits: row indices for horizontal lines.
        title: default gives the shape, the number of non-zeros and the density.
        max_markers: above this many non-zeros the pattern is binned into an image.

    Returns:
        The Figure.
    """
    import scipy.sparse as sp

    if sp.issparse(J):
        A = sp.coo_matrix(J)
    else:
        d = _np(J, float)
        if d.ndim != 2:
            raise KitInputError(f"J has shape {d.shape}: expected a 2-D (residuals x parameters) matrix")
        A = sp.coo_matrix(d)
    A.sum_duplicates()
    nz = A.data != 0
    rows, cols = A.row[nz], A.col[nz]
    R, P = A.shape
    nnz = int(nz.sum())
    fig = _figure((6.0, 4.5))
    with mpl.rc_context(STYLE):
        ax = fig.add_subplot()
        if nnz <= max_markers:
            ms = float(np.clip(300.0 / max(R, P, 1), 0.3, 4.0))
            ax.plot(cols, rows, "s", ms=ms, color="black", mew=0, linestyle="none")
            ax.set_xlim(-0.5, P - 0.5)
            ax.set_ylim(R - 0.5, -0.5)
        else:
            nb_r, nb_c = min(R, 400), min(P, 400)
            img, _, _ = np.histogram2d(rows, cols, bins=[nb_r, nb_c], range=[[0, R], [0, P]])
            ax.imshow(img > 0, cmap="Greys", aspect="auto", extent=(-0.5, P - 0.5, R - 0.5, -0.5), interpolation="nearest")
        for c in col_splits or ():
            ax.axvline(c - 0.5, color="#d62728", lw=1)
        for r in row_splits or ():
            ax.axhline(r - 0.5, color="#d62728", lw=1)
        ax.set_aspect("auto")
        ax.set_xlabel(f"parameter (column), P = {P}")
        ax.set_ylabel(f"residual (row), R = {R}")
        ax.xaxis.set_label_position("top")
        ax.xaxis.tick_top()
        if title is None:
            dens = nnz / max(R * P, 1)
            title = f"Jacobian sparsity: {R} x {P}, {nnz} non-zeros ({100 * dens:.3g} %)"
        ax.set_title(title, pad=22)
    return fig


def plot_training_curves(history: dict, title: str | None = None) -> Figure:
    """Loss and PSNR against the iteration.

    Args:
        history: dict with ``"iterations"`` (or ``"iteration"``/``"step"``) ``(K,)``, ``"loss"``
            ``(K,)``, optional ``"psnr"`` ``(K,)`` (train, dB), optional ``"test_psnr"`` ``(K',)``
            with optional ``"test_iterations"`` ``(K',)`` (default: the last K' iterations).
        title: figure title.

    Returns:
        The Figure: loss (log scale) left, PSNR right (only the loss if there is no PSNR).
    """
    if not isinstance(history, dict):
        raise KitInputError(f"history must be a dict with 'iterations' and 'loss' (and 'psnr'), got {type(history).__name__}")
    key = next((k for k in ("iterations", "iteration", "step", "steps") if k in history), None)
    if "loss" not in history:
        raise KitInputError(f"history has keys {sorted(history)}: it needs 'loss' (and 'iterations')")
    loss = _np(history["loss"], float).reshape(-1)
    it = _np(history[key], float).reshape(-1) if key else np.arange(1, len(loss) + 1, dtype=float)
    if len(it) != len(loss):
        raise KitInputError(f"history['{key}'] has {len(it)} entries but history['loss'] has {len(loss)}")
    psnr = _np(history["psnr"], float).reshape(-1) if history.get("psnr") is not None else None
    test = _np(history["test_psnr"], float).reshape(-1) if history.get("test_psnr") is not None else None
    has_psnr = psnr is not None or test is not None
    fig = _figure((8.0, 3.0) if has_psnr else (4.5, 3.0))
    with mpl.rc_context(STYLE):
        axes = fig.subplots(1, 2 if has_psnr else 1)
        ax1 = axes[0] if has_psnr else axes
        ok = np.isfinite(loss) & (loss > 0)
        ax1.plot(it[ok], loss[ok], color="C0")
        ax1.set_yscale("log")
        ax1.set_xlabel("iteration")
        ax1.set_ylabel("loss (MSE)")
        ax1.grid(True, which="both")
        if has_psnr:
            ax2 = axes[1]
            if psnr is not None:
                if len(psnr) != len(it):
                    raise KitInputError(f"history['psnr'] has {len(psnr)} entries but there are {len(it)} iterations")
                ax2.plot(it, psnr, color="C0", label="train")
            if test is not None:
                tit = history.get("test_iterations")
                tit = _np(tit, float).reshape(-1) if tit is not None else it[len(it) - len(test):]
                if len(tit) != len(test):
                    raise KitInputError(f"history['test_iterations'] has {len(tit)} entries but 'test_psnr' has {len(test)}")
                ax2.plot(tit, test, "o-", color="C1", ms=3, label="test")
                ax2.annotate(f"{test[-1]:.2f} dB", (tit[-1], test[-1]), textcoords="offset points", xytext=(-30, 6), fontsize=8)
            ax2.set_xlabel("iteration")
            ax2.set_ylabel("PSNR [dB]")
            ax2.grid(True)
            ax2.legend(loc="lower right")
        if title:
            fig.suptitle(title)
    return fig


def image_grid(images, titles=None, ncols: int = 4, size: float = 2.0, suptitle: str | None = None) -> Figure:
    """Images in a grid (axes off).

    Args:
        images: ``(N, H, W, 3)`` array/tensor or a list of ``(H, W, 3)`` / ``(H, W)`` images
            (uint8 or float in [0, 1]; sizes may differ).
        titles: optional N titles.
        ncols: columns (fewer if there are fewer images).
        size: width of one cell in inches.
        suptitle: title over the grid.

    Returns:
        The Figure.
    """
    if hasattr(images, "shape") and len(getattr(images, "shape")) in (2, 3) and (len(images.shape) == 2 or images.shape[-1] in (3, 4)):
        images = [images]  # a single image
    imgs = [_image(im, f"images[{i}]") for i, im in enumerate(images)]
    if not imgs:
        raise KitInputError("images is empty: nothing to show")
    if titles is not None:
        titles = [str(t) for t in titles]
        if len(titles) != len(imgs):
            raise KitInputError(f"titles has {len(titles)} entries for {len(imgs)} images")
    n = len(imgs)
    ncols = max(1, min(int(ncols), n))
    nrows = (n + ncols - 1) // ncols
    aspect = max(im.shape[0] / im.shape[1] for im in imgs)
    fig = _figure((size * ncols, size * aspect * nrows + (0.3 * nrows if titles else 0) + (0.3 if suptitle else 0)))
    with mpl.rc_context(STYLE):
        axes = np.atleast_1d(fig.subplots(nrows, ncols)).reshape(-1)
        for k, ax in enumerate(axes):
            ax.set_axis_off()
            if k < n:
                ax.imshow(imgs[k], interpolation="antialiased")
                if titles is not None:
                    ax.set_title(titles[k], fontsize=8)
        if suptitle:
            fig.suptitle(suptitle)
    return fig

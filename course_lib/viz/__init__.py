"""Pictures: plotly 3-D scenes, matplotlib figures and ipywidgets (the one place for them).

* :mod:`course_lib.viz.scene3d` -- plotly 3-D: ``scene_figure``, ``add_cameras``, ``add_points``,
  ``add_rays``, ``camera_frustum``, ``write_html``.
* :mod:`course_lib.viz.figures` -- matplotlib 2-D (each returns a ``matplotlib.figure.Figure``):
  ``draw_matches``, ``draw_epipolar_lines``, ``plot_reprojection_errors``, ``plot_visibility``,
  ``plot_jacobian_sparsity``, ``plot_training_curves``, ``image_grid``.
* :mod:`course_lib.viz.widgets` -- ipywidgets (each returns a ``VBox``): ``ransac_threshold_widget``,
  ``ba_iterations_widget``, ``nerf_snapshot_slider``, ``novel_view_widget``.

Each module's docstring lists the exact signatures and shapes.

Importing this package makes ``"plotly_mimetype"`` plotly's default renderer: figures are
stored in the notebook as JSON only (no copy of plotly.js in every notebook, so notebook files
stay small); JupyterLab draws them natively. If you chose a renderer yourself with the
environment variable ``PLOTLY_RENDERER`` (e.g. ``PLOTLY_RENDERER=notebook_connected`` for the
classic notebook or a static HTML export), the kit leaves your choice alone.

The names are loaded on first use (``from course_lib.viz import draw_matches`` loads matplotlib,
not plotly nor ipywidgets), so that a command that writes one HTML page does not pay for the rest.
"""

from __future__ import annotations

import importlib
import os
import sys

if not os.environ.get("PLOTLY_RENDERER"):
    if "plotly.io._renderers" in sys.modules:
        import plotly.io as _pio

        _pio.renderers.default = "plotly_mimetype"
    else:  # plotly reads it when it first loads its renderers (which import nbformat, seconds)
        os.environ["PLOTLY_RENDERER"] = "plotly_mimetype"

#: public name -> the module that defines it
_HOME = {
    **dict.fromkeys(["scene_figure", "add_cameras", "add_points", "add_rays", "camera_frustum", "scene_size",
                     "write_html"], "course_lib.viz.scene3d"),
    **dict.fromkeys(["draw_matches", "draw_epipolar_lines", "plot_reprojection_errors", "plot_visibility",
                     "plot_jacobian_sparsity", "plot_training_curves", "image_grid"], "course_lib.viz.figures"),
    **dict.fromkeys(["ransac_threshold_widget", "ba_iterations_widget", "nerf_snapshot_slider",
                     "novel_view_widget"], "course_lib.viz.widgets"),
}
__all__ = list(_HOME)


def __getattr__(name: str):
    if name in _HOME:
        return getattr(importlib.import_module(_HOME[name]), name)
    raise AttributeError(f"module 'course_lib.viz' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_HOME))

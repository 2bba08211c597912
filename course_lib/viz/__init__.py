"""Pictures: plotly 3-D scenes, matplotlib figures and ipywidgets (the one place for them).

* :mod:`course_lib.viz.scene3d` -- plotly 3-D: ``scene_figure``, ``add_cameras``, ``add_points``,
  ``add_rays``, ``camera_frustum``, ``write_html``.
* :mod:`course_lib.viz.figures` -- matplotlib 2-D (each returns a ``matplotlib.figure.Figure``):
  ``draw_matches``, ``draw_epipolar_lines``, ``plot_reprojection_errors``, ``plot_visibility``,
  ``plot_jacobian_sparsity``, ``plot_training_curves``, ``image_grid``.
* :mod:`course_lib.viz.widgets` -- ipywidgets (each returns a ``VBox``): ``ransac_threshold_widget``,
  ``ba_iterations_widget``, ``nerf_snapshot_slider``, ``novel_view_widget``.

Each module's docstring lists the exact signatures and shapes.

Importing this package sets plotly's default renderer to ``"plotly_mimetype"``: figures are
stored in the notebook as JSON only (no copy of plotly.js in every notebook, so notebook files
stay small); JupyterLab draws them natively. If you chose a renderer yourself with the
environment variable ``PLOTLY_RENDERER`` (e.g. ``PLOTLY_RENDERER=notebook_connected`` for the
classic notebook or a static HTML export), the kit leaves your choice alone.
"""

from __future__ import annotations

import os

import plotly.io as _pio

if not os.environ.get("PLOTLY_RENDERER"):
    _pio.renderers.default = "plotly_mimetype"

from course_lib.viz.scene3d import (  # noqa: E402
    add_cameras,
    add_points,
    add_rays,
    camera_frustum,
    scene_figure,
    scene_size,
    write_html,
)

__all__ = [
    "scene_figure",
    "add_cameras",
    "add_points",
    "add_rays",
    "camera_frustum",
    "scene_size",
    "write_html",
]

from course_lib.viz.figures import (  # noqa: E402
    draw_epipolar_lines,
    draw_matches,
    image_grid,
    plot_jacobian_sparsity,
    plot_reprojection_errors,
    plot_training_curves,
    plot_visibility,
)

__all__ += [
    "draw_matches",
    "draw_epipolar_lines",
    "plot_reprojection_errors",
    "plot_visibility",
    "plot_jacobian_sparsity",
    "plot_training_curves",
    "image_grid",
]

from course_lib.viz.widgets import (  # noqa: E402
    ba_iterations_widget,
    nerf_snapshot_slider,
    novel_view_widget,
    ransac_threshold_widget,
)

__all__ += ["ransac_threshold_widget", "ba_iterations_widget", "nerf_snapshot_slider", "novel_view_widget"]

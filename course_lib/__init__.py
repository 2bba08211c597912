"""course_lib: the reference library of the SfM + NeRF course kit.

The notebooks in ``notebooks/`` teach one step each and call this library for everything that is
not the lesson, and for the reference solutions their checks compare against.

* :mod:`course_lib.conventions` - axes, pose direction, shapes, units (read it first).
* :mod:`course_lib.data` - P3 matching files, COLMAP text models, Blender NeRF data, synthetic scenes.
* :mod:`course_lib.sfm` - fundamental, essential, triangulation, pnp, visibility, bundle adjustment, pipeline.
* :mod:`course_lib.evaluate` - poses and points against ground truth (similarity alignment).
* :mod:`course_lib.nerf` - rays, encoding, model, render, train.
* :mod:`course_lib.viz` - plotly 3-D scenes, matplotlib figures, widgets.
* :mod:`course_lib.checks` - the checks behind every check cell; :mod:`course_lib.steps` - where each
  notebook starts (the reference result of the step before).
* :mod:`course_lib.instructor` - release, grading, the hidden cases (never shipped to students).

Command line: ``python -m course_lib --help``.
"""

__version__ = "0.1.0"

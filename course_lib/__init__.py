"""course_lib: the reference library of the SfM + NeRF course kit.

The notebooks in ``notebooks/`` teach one step each and call this library for everything that is
not the lesson, and for the reference solutions their checks compare against.

* :mod:`course_lib.conventions` - axes, pose direction, shapes, units (read it first).
* :mod:`course_lib.data` - P3 matching files, COLMAP text models, Blender NeRF data, synthetic scenes.
* :mod:`course_lib.sfm` - fundamental, essential, triangulation, pnp, visibility, bundle adjustment, pipeline.
* :mod:`course_lib.alignment` - poses and points against ground truth (similarity alignment).
* :mod:`course_lib.nerf` - rays, encoding, model, render, train.
* :mod:`course_lib.viz` - plotly 3-D scenes, matplotlib figures, widgets.
* :mod:`course_lib.checks` - the checks behind every check cell; :mod:`course_lib.starting_points` - where each
  notebook starts (the reference result of the step before).
* :mod:`course_lib.exercises` - the exercises, and how the kit's own code calls them;
  :mod:`course_lib.saved_solutions` - in the student kit, the student's own solutions (saved when their cell runs).
* :mod:`course_lib.instructor` - release, grading, the hidden cases (never shipped to students).

Command line: ``python -m course_lib --help``.
"""

__version__ = "0.1.0"


def _install_saving() -> None:
    """In a student kit's Jupyter kernel: running an exercise's cell saves it for later notebooks (:mod:`course_lib.saved_solutions`)."""
    try:
        from course_lib import saved_solutions  # deferred: `import course_lib` loads no submodule (start-up)

        saved_solutions.install()
    except Exception:  # noqa: BLE001 - importing the kit never fails because of it
        pass


_install_saving()

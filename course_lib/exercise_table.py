"""The table of the notebooks' exercises: for each, its notebook, its reference module, its result's fields and engines.

:mod:`course_lib.exercises` calls the exercises by this table and :mod:`course_lib.saved_solutions`
saves the student's own by it; a test keeps it equal to the notebooks.

Introduced in ``notebooks/05_bundle_adjustment.ipynb`` (the kit's pipeline runs on your functions).
"""

from __future__ import annotations

from dataclasses import dataclass

from course_lib.validate import KitInputError

__all__ = ["Exercise", "EXERCISES", "exercise_of"]


@dataclass(frozen=True)
class Exercise:
    """One exercise of a notebook.

    Attributes:
        name: the function (or class) the student writes, e.g. ``"get_rays"``.
        notebook: the notebook that teaches it, e.g. ``"06_nerf_data_and_rays.ipynb"``.
        module: the module of its reference solution in the instructor's kit (the student kit leaves
            the reference out, or ships a stand-in in its place); None where the reference is the
            notebook's own solution (``psnr``).
        fields: the names of the result's parts where the stub returns several things (a tuple in
            this order, or an object with these attributes); empty for a single value.
        engines: the kit's functions and classes that compute the exercise's result with the
            student's own functions (so the exercise's own code may not call them: the grader closes
            them in the process where it grades the exercise).
    """

    name: str
    notebook: str
    module: str | None
    fields: tuple[str, ...] = ()
    engines: tuple[str, ...] = ()


_NB = {
    "01": "01_fundamental_matrix.ipynb",
    "02": "02_essential_matrix_and_pose.ipynb",
    "03": "03_triangulation.ipynb",
    "04": "04_pnp.ipynb",
    "05": "05_bundle_adjustment.ipynb",
    "06": "06_nerf_data_and_rays.ipynb",
    "07": "07_nerf_model.ipynb",
    "08": "08_nerf_rendering_and_training.ipynb",
}

#: Every exercise of the kit, in notebook order (``tests/student/test_exercises.py`` keeps it equal to the notebooks).
EXERCISES: dict[str, Exercise] = {e.name: e for e in [
    Exercise("normalize_points", _NB["01"], "course_lib.sfm.fundamental", ("x_n", "T")),
    Exercise("eight_point", _NB["01"], "course_lib.sfm.fundamental"),
    Exercise("sampson_distance", _NB["01"], "course_lib.sfm.fundamental"),
    Exercise("ransac_fundamental", _NB["01"], "course_lib.sfm.fundamental", ("F", "inliers", "n_iters"),
             ("course_lib.sfm.tracks.verify_pair", "course_lib.sfm.tracks.ransac_every_pair")),
    Exercise("essential_from_fundamental", _NB["02"], "course_lib.sfm.essential"),
    Exercise("pose_candidates", _NB["02"], "course_lib.sfm.essential", ("R", "C")),
    Exercise("triangulate_linear", _NB["03"], "course_lib.sfm.triangulation"),
    Exercise("choose_pose", _NB["03"], "course_lib.sfm.triangulation", ("R_cw", "t_cw", "X", "in_front", "counts")),
    Exercise("triangulate_nonlinear", _NB["03"], "course_lib.sfm.triangulation"),
    Exercise("pnp_linear", _NB["04"], "course_lib.sfm.pnp", ("R_cw", "t_cw")),
    Exercise("pnp_ransac", _NB["04"], "course_lib.sfm.pnp", ("R_cw", "t_cw", "inliers", "n_iters")),
    Exercise("pnp_nonlinear", _NB["04"], "course_lib.sfm.pnp", ("R_cw", "t_cw")),
    Exercise("visibility_matrix", _NB["05"], "course_lib.sfm.visibility"),
    Exercise("reprojection_residuals", _NB["05"], "course_lib.sfm.bundle_adjustment", (),
             ("course_lib.sfm.lm.residuals", "course_lib.sfm.lm.PinholeCamera")),
    Exercise("jacobian_sparsity", _NB["05"], "course_lib.sfm.bundle_adjustment", (),
             ("course_lib.sfm.lm.jacobian", "course_lib.sfm.bundle_adjustment.reprojection_jacobian",
              "course_lib.sfm.bundle_adjustment._block_columns")),
    Exercise("bundle_adjust", _NB["05"], "course_lib.sfm.bundle_adjustment", ("R_cw", "t_cw", "X"),
             ("course_lib.sfm.bundle_adjustment.adjust", "course_lib.sfm.lm.solve")),
    Exercise("get_rays", _NB["06"], "course_lib.nerf.rays", ("rays_o", "rays_d"),
             ("course_lib.nerf.rays.camera_rays", "course_lib.nerf.scene.TrainingRays")),
    Exercise("stratified_samples", _NB["06"], "course_lib.nerf.rays"),
    Exercise("query_points", _NB["06"], "course_lib.nerf.rays"),
    Exercise("positional_encoding", _NB["06"], "course_lib.nerf.encoding"),
    Exercise("NeRF", _NB["07"], "course_lib.nerf.model"),
    Exercise("psnr", _NB["07"], None),  # a one-liner: no library function
    Exercise("volume_render", _NB["08"], "course_lib.nerf.render", (),
             ("course_lib.nerf.render.composite", "course_lib.nerf.inference.march_grid")),
]}


def exercise_of(name: str) -> Exercise:
    """The :class:`Exercise` called ``name``.

    Raises:
        KitInputError: no exercise has that name (the message lists them).
    """
    try:
        return EXERCISES[name]
    except KeyError:
        raise KitInputError(f"{name!r} is not an exercise of the kit; the exercises are: {', '.join(EXERCISES)}") from None

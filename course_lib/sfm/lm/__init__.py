"""Sparse Levenberg-Marquardt for bundle adjustment, with the Schur complement on the points.

This is the kit's ONE bundle adjuster: :func:`course_lib.sfm.bundle_adjustment.adjust`
(the lesson, 6 parameters per camera, ``K`` fixed) and ``python -m course_lib ba`` (the "Bundle
Adjustment in the Large" problems, 9 parameters per camera) both call :func:`solve`. What changes
between them is only the camera model, a small object with two methods (:class:`CameraModel`).

Problem
    Cameras ``c_i`` (``M x n`` parameters), points ``X_j`` (``N x 3``), observations ``k`` of point
    ``pt_idx[k]`` in camera ``cam_idx[k]`` at ``obs[k]``. Residual ``r_k = project(c_i, X_j) - obs_k``
    (2 numbers), cost ``0.5 sum_k rho(|r_k|^2)`` with ``rho(s) = s`` (least squares) or a robust
    loss (``"huber"``, ``"soft_l1"``, ``"cauchy"``, defined as in ``scipy.optimize.least_squares``).

Normal equations (one Gauss-Newton / LM step)
    With ``A_k = d r_k / d c_i`` (2 x n) and ``B_k = d r_k / d X_j`` (2 x 3), analytic, and robust
    weights ``w_k`` (IRLS: ``w_k = rho'(|r_k|^2)``)::

        [U + lam D_U     W      ] [dc]   [-g_c]     U_i = sum_{k in i} w A^T A  (n x n per camera)
        [W^T        V + lam D_V ] [dX] = [-g_X]     V_j = sum_{k in j} w B^T B  (3 x 3 per point)
                                                    W_ij = w A_k^T B_k,  g = J^T w r

    ``D = diag(J^T W J)`` (clamped to [1e-6, 1e32] as in Ceres): Marquardt's scale-invariant damping.

Schur complement (why BA scales)
    ``V`` is block diagonal (a point only touches itself), so it is inverted 3x3 block by 3x3 block
    in one batched numpy call, and the points are eliminated::

        S dc = -g_c + W V^-1 g_X,     S = U + lam D_U - W V^-1 W^T      (the reduced camera system, nM x nM)
        dX = -V^-1 (g_X + W^T dc)

    ``S`` has a non-zero ``n x n`` block (i, l) only when cameras i and l see a common point.
    Each such block is ONE matrix product over the points the two cameras share (``Y^T W`` with
    ``Y = V^-1 W^T`` of their observations stacked), so Python loops over camera pairs, never over
    points or observations. ``S`` is small (441 x 441 for the 49 Ladybug cameras) and solved densely
    by Cholesky; above ``dense_limit`` unknowns it is assembled sparse and solved with
    ``scipy.sparse.linalg.spsolve`` (SuperLU). Most of an iteration goes to ``W V^-1 W^T`` and the
    Jacobian's blocks, little to the factorization. BLAS is held to one thread meanwhile
    (:func:`course_lib.threads.single_threaded_blas`): its threads only cost time on products this small.

Damping strategy
    Nielsen's (the one in Ceres): the gain ratio ``rho = actual / predicted decrease``; a step is
    taken when ``rho > 1e-3``, then ``lam *= max(1/3, 1 - (2 rho - 1)^3)``; otherwise ``lam *= nu``,
    ``nu *= 2``; ``lam`` stays within ``[LAM_MIN, LAM_MAX]``. Stops when the relative decrease of
    the cost in a step is below ``ftol`` (Ceres' ``function_tolerance``), the step is below ``xtol``
    relative to the parameters, the gradient is below ``gtol``, or after ``max_iterations`` steps.

Gauge
    Reprojections do not change under a similarity of the world (7 degrees of freedom), so
    ``J^T J`` is singular along 7 directions. :func:`solve` takes masks of fixed parameters: the
    lesson's :func:`~course_lib.sfm.bundle_adjustment.adjust` fixes one camera and one
    translation coordinate of a second one; for BAL problems (like Ceres and the SciPy cookbook)
    nothing is fixed: the damping ``lam D`` makes every step well defined, the gauge drifts freely
    and harmlessly, and the cost (which is gauge-invariant) is what is compared.

Camera models
    :class:`PinholeCamera` (the lesson: rotation vector + t, 6 parameters, ``K`` fixed, the kit's
    OpenCV axes) and :class:`BALCamera` (rotation vector, t, f, k1, k2, 9 parameters, BAL's axes;
    see :mod:`course_lib.data.bal`). Both rotation parametrizations are the rotation vector
    ``r`` with ``R = exp([r]_x)`` and additive updates ``r + dr``; the derivative is
    ``d(R X)/dr = -[R X]_x R J_r(r)`` with ``J_r`` the right Jacobian of SO(3).

Introduced in ``notebooks/05_bundle_adjustment.ipynb`` ("How does this scale?").
"""

from course_lib.sfm.lm.cameras import (BALCamera, CameraModel, PinholeCamera, SimpleRadialCamera, right_jacobian_so3,
                                       rotvec_to_matrix)
from course_lib.sfm.lm.linear_solver import BlockStructure, NormalEquations, normal_equations, schur_solve
from course_lib.sfm.lm.problem import jacobian, reduced_camera_sparsity, residuals
from course_lib.sfm.lm.solver import LAM_MAX, LAM_MIN, LMResult, solve

__all__ = [
    "CameraModel",
    "PinholeCamera",
    "BALCamera",
    "SimpleRadialCamera",
    "rotvec_to_matrix",
    "right_jacobian_so3",
    "residuals",
    "jacobian",
    "BlockStructure",
    "NormalEquations",
    "normal_equations",
    "schur_solve",
    "reduced_camera_sparsity",
    "LMResult",
    "solve",
    "LAM_MIN",
    "LAM_MAX",
]

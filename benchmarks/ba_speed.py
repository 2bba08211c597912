"""Benchmark: the kit's bundle adjuster against the SciPy cookbook recipe and Ceres (pycolmap).

Solves ONE "Bundle Adjustment in the Large" problem (default: the course's Ladybug 49-7776) three
ways in the same run and prints a table of final cost, iterations, seconds and the ratio of
seconds to the kit's:

* ``kit``: :func:`course_lib.sfm.lm.solve` (analytic Jacobian, Schur complement on the points,
  dense Cholesky of the reduced camera system), ``ftol=1e-4``.
* ``scipy-cookbook``: the recipe of the SciPy cookbook's "Large-scale bundle adjustment in scipy"
  (https://scipy-cookbook.readthedocs.io/items/bundle_adjustment.html), written afresh here:
  ``least_squares(method="trf", x_scale="jac", ftol=1e-4)`` with the Jacobian by finite
  differences over the sparsity pattern ``jac_sparsity``.
* ``ceres (pycolmap)``: COLMAP's Ceres bundle adjuster through pycolmap, when installed (a
  benchmark dependency, not a kit requirement), with ``function_tolerance=1e-4``. The BAL problem
  is converted to COLMAP's conventions: camera axes x right, y down, z forward
  (``R_colmap = D R_bal``, ``t_colmap = D t_bal``, ``D = diag(1, -1, -1)``), pixels from the
  top-left corner (``u = cx + x``, ``v = cy - y``, with an artificial principal point ``(cx, cy)``
  held fixed), camera model ``RADIAL`` (f, cx, cy, k1, k2) = BAL's ``f (1 + k1 r^2 + k2 r^4)``.
  COLMAP's residual is zero for an observation whose point is behind its camera, so the table
  also gives every solver's cost over the observations in front of their camera at the start.

All costs are ``0.5 * sum(r**2)`` in BAL's pixel units, recomputed with the kit's BAL residual
from each solver's final parameters. Times are wall-clock seconds of the optimization only
(the file is read once, before); ``cpu s`` is the CPU time of the process over the same span
(all threads), a steadier number on a shared machine. Run::

    python benchmarks/ba_speed.py [PROBLEM_FILE] [--json OUT.json] [--skip-cookbook] [--skip-ceres]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

# One BLAS thread for everyone (override by setting it yourself): the cookbook's trf/lsmr makes
# thousands of small dense BLAS calls, and with OpenBLAS threads fighting over a busy 2-core
# machine it took 493 s instead of ~14 s. The kit holds BLAS to one thread itself; Ceres uses its
# own thread pool (--ceres-threads), not OpenBLAS.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from course_lib.data.bal import FLIP_YZ, BALProblem, load_bal  # noqa: E402
from course_lib.paths import course_data  # noqa: E402
from course_lib.sfm import lm  # noqa: E402

FTOL = 1e-4


# ---------------------------------------------------------------------------------------------
# The cost every solver is judged by
# ---------------------------------------------------------------------------------------------


def bal_costs(problem: BALProblem, cameras: np.ndarray, points: np.ndarray, in_front: np.ndarray) -> tuple[float, float]:
    """``0.5 * sum(r**2)`` over all observations and over those with ``in_front``."""
    r = lm.residuals(lm.BALCamera(), cameras, points, problem.cam_idx, problem.pt_idx, problem.obs)
    s = (r**2).sum(axis=1)
    return 0.5 * float(s.sum()), 0.5 * float(s[in_front].sum())


def depth_in_front(problem: BALProblem) -> np.ndarray:
    """``(n_obs,)`` bool: the point is in front of its camera (BAL: ``P.z < 0``)."""
    R = lm.rotvec_to_matrix(problem.camera_params[:, :3])[problem.cam_idx]
    P = np.einsum("kij,kj->ki", R, problem.points[problem.pt_idx]) + problem.camera_params[problem.cam_idx, 3:6]
    return P[:, 2] < 0


# ---------------------------------------------------------------------------------------------
# 1. the kit
# ---------------------------------------------------------------------------------------------


def run_kit(problem: BALProblem):
    c0 = time.process_time()
    res = lm.solve(
        lm.BALCamera(), problem.camera_params, problem.points, problem.cam_idx, problem.pt_idx, problem.obs, ftol=FTOL
    )
    return res.cameras, res.points, res.iterations, res.seconds, time.process_time() - c0


# ---------------------------------------------------------------------------------------------
# 2. the SciPy cookbook recipe (finite-difference Jacobian over a sparsity pattern, trf)
# ---------------------------------------------------------------------------------------------


def _cookbook_rotate(points, rot_vecs):
    """Rodrigues' formula, one rotation vector per point (as in the cookbook)."""
    theta = np.linalg.norm(rot_vecs, axis=1)[:, np.newaxis]
    with np.errstate(invalid="ignore"):
        v = rot_vecs / theta
        v = np.nan_to_num(v)
    dot = np.sum(points * v, axis=1)[:, np.newaxis]
    cos_theta = np.cos(theta)
    sin_theta = np.sin(theta)
    return cos_theta * points + sin_theta * np.cross(v, points) + dot * (1 - cos_theta) * v


def _cookbook_project(points, camera_params):
    points_proj = _cookbook_rotate(points, camera_params[:, :3])
    points_proj += camera_params[:, 3:6]
    points_proj = -points_proj[:, :2] / points_proj[:, 2, np.newaxis]
    f, k1, k2 = camera_params[:, 6], camera_params[:, 7], camera_params[:, 8]
    n = np.sum(points_proj**2, axis=1)
    r = 1 + k1 * n + k2 * n**2
    return points_proj * (r * f)[:, np.newaxis]


def _cookbook_fun(params, n_cameras, n_points, camera_indices, point_indices, points_2d):
    camera_params = params[: n_cameras * 9].reshape((n_cameras, 9))
    points_3d = params[n_cameras * 9 :].reshape((n_points, 3))
    points_proj = _cookbook_project(points_3d[point_indices], camera_params[camera_indices])
    return (points_proj - points_2d).ravel()


def _cookbook_sparsity(n_cameras, n_points, camera_indices, point_indices):
    m = camera_indices.size * 2
    n = n_cameras * 9 + n_points * 3
    A = sp.lil_matrix((m, n), dtype=int)
    i = np.arange(camera_indices.size)
    for s in range(9):
        A[2 * i, camera_indices * 9 + s] = 1
        A[2 * i + 1, camera_indices * 9 + s] = 1
    for s in range(3):
        A[2 * i, n_cameras * 9 + point_indices * 3 + s] = 1
        A[2 * i + 1, n_cameras * 9 + point_indices * 3 + s] = 1
    return A


def run_cookbook(problem: BALProblem):
    M, N = problem.n_cameras, problem.n_points
    x0 = np.hstack((problem.camera_params.ravel(), problem.points.ravel()))
    t0, c0 = time.perf_counter(), time.process_time()
    A = _cookbook_sparsity(M, N, problem.cam_idx, problem.pt_idx)
    res = least_squares(
        _cookbook_fun,
        x0,
        jac_sparsity=A,
        verbose=0,
        x_scale="jac",
        ftol=FTOL,
        method="trf",
        args=(M, N, problem.cam_idx, problem.pt_idx, problem.obs),
    )
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    return res.x[: 9 * M].reshape(M, 9), res.x[9 * M :].reshape(N, 3), int(res.njev), seconds, cpu


# ---------------------------------------------------------------------------------------------
# 3. Ceres through pycolmap
# ---------------------------------------------------------------------------------------------


def bal_to_colmap(problem: BALProblem, pycolmap):
    """A ``pycolmap.Reconstruction`` of the BAL problem (see the module docstring for the axes)."""
    rec = pycolmap.Reconstruction()
    half = float(np.ceil(np.abs(problem.obs).max())) + 1.0
    W = H = int(2 * half)
    cx = cy = half
    R_bal = lm.rotvec_to_matrix(problem.camera_params[:, :3])
    order = np.argsort(problem.cam_idx, kind="stable")
    starts = np.searchsorted(problem.cam_idx[order], np.arange(problem.n_cameras + 1))
    point2d_index = np.empty(problem.n_obs, dtype=np.int64)
    for i in range(problem.n_cameras):
        f, k1, k2 = problem.camera_params[i, 6:9]
        cam = pycolmap.Camera(model="RADIAL", width=W, height=H, params=[f, cx, cy, k1, k2], camera_id=i + 1)
        rec.add_camera_with_trivial_rig(cam)
        ks = order[starts[i] : starts[i + 1]]
        point2d_index[ks] = np.arange(len(ks))
        kp = np.stack([cx + problem.obs[ks, 0], cy - problem.obs[ks, 1]], axis=1)
        img = pycolmap.Image(name=f"bal_{i:05d}", keypoints=kp, camera_id=i + 1, image_id=i + 1)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(FLIP_YZ @ R_bal[i]), FLIP_YZ @ problem.camera_params[i, 3:6])
        rec.add_image_with_trivial_frame(img, pose)
    obs_of_point = np.argsort(problem.pt_idx, kind="stable")
    pstarts = np.searchsorted(problem.pt_idx[obs_of_point], np.arange(problem.n_points + 1))
    point_ids = np.empty(problem.n_points, dtype=np.int64)
    for j in range(problem.n_points):
        track = pycolmap.Track()
        for k in obs_of_point[pstarts[j] : pstarts[j + 1]]:
            track.add_element(int(problem.cam_idx[k]) + 1, int(point2d_index[k]))
        point_ids[j] = rec.add_point3D(problem.points[j], track)
    return rec, point_ids


def colmap_to_bal(rec, problem: BALProblem, point_ids) -> tuple[np.ndarray, np.ndarray]:
    from scipy.spatial.transform import Rotation

    cams = np.empty((problem.n_cameras, 9))
    for i in range(problem.n_cameras):
        pose = rec.image(i + 1).cam_from_world()
        M = pose.matrix()
        R_bal = FLIP_YZ @ M[:, :3]
        cams[i, :3] = Rotation.from_matrix(R_bal).as_rotvec()
        cams[i, 3:6] = FLIP_YZ @ M[:, 3]
        f, _, _, k1, k2 = rec.camera(i + 1).params
        cams[i, 6:9] = f, k1, k2
    pts = np.stack([rec.point3D(int(pid)).xyz for pid in point_ids])
    return cams, pts


def run_ceres(problem: BALProblem, pycolmap, num_threads: int = -1):
    rec, point_ids = bal_to_colmap(problem, pycolmap)
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = True
    options.refine_extra_params = True
    options.refine_principal_point = False
    options.print_summary = False
    so = options.ceres.solver_options
    so.function_tolerance = FTOL
    so.gradient_tolerance = 1e-10  # Ceres' defaults, so that function_tolerance decides, as for the others
    so.parameter_tolerance = 1e-8
    so.num_threads = num_threads
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        config.add_image(image_id)
    t0, c0 = time.perf_counter(), time.process_time()
    adjuster = pycolmap.create_default_bundle_adjuster(options, config, rec)
    summary = adjuster.solve()
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    iterations = -1
    try:
        cs = summary.ceres_summary
        iterations = int(cs.num_successful_steps) if hasattr(cs, "num_successful_steps") else -1
    except Exception:
        pass
    cams, pts = colmap_to_bal(rec, problem, point_ids)
    return cams, pts, iterations, seconds, cpu, summary


# ---------------------------------------------------------------------------------------------


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("problem", nargs="?", default=None, help="BAL file (default: course data 'bal-ladybug')")
    parser.add_argument("--json", type=Path, default=None, help="write the table as JSON")
    parser.add_argument("--skip-cookbook", action="store_true", help="leave out the SciPy cookbook recipe (the slow one)")
    parser.add_argument("--skip-ceres", action="store_true", help="leave out Ceres even when pycolmap is installed")
    parser.add_argument("--ceres-threads", type=int, default=-1, help="Ceres' num_threads (default -1: all cores)")
    args = parser.parse_args(argv)
    path = args.problem or course_data("bal-ladybug")
    if path is None:
        print("no problem file given and the course data 'bal-ladybug' is absent (set COURSE_DATA)", file=sys.stderr)
        return 2
    problem = load_bal(path)
    in_front = depth_in_front(problem)
    print(f"{problem}; {int((~in_front).sum())} observations behind their camera at the start")
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load average "
          f"{' '.join(f'{x:.1f}' for x in os.getloadavg())}; OPENBLAS_NUM_THREADS={os.environ['OPENBLAS_NUM_THREADS']}")
    init_all, init_front = bal_costs(problem, problem.camera_params, problem.points, in_front)
    rows = []

    def add(name, cams, pts, iterations, seconds, cpu_seconds):
        c_all, c_front = bal_costs(problem, cams, pts, in_front)
        rows.append(dict(solver=name, final_cost=c_all, final_cost_in_front=c_front, iterations=iterations,
                         seconds=seconds, cpu_seconds=cpu_seconds))
        print(f"  {name}: cost {c_all:.6e} (in front {c_front:.6e}), {iterations} iterations, {seconds:.2f} s "
              f"(cpu {cpu_seconds:.2f} s)", flush=True)

    add("kit (course_lib.sfm.lm)", *run_kit(problem))
    if not args.skip_cookbook:
        add("scipy cookbook (trf, FD jac)", *run_cookbook(problem))
    if not args.skip_ceres:
        try:
            import pycolmap
        except ImportError:
            pycolmap = None
            print("  ceres: pycolmap is not installed, skipped")
        if pycolmap is not None:
            *out, summary = run_ceres(problem, pycolmap, args.ceres_threads)
            add(f"ceres (pycolmap {pycolmap.__version__}, {args.ceres_threads} thr)", *out)
            try:
                print("   ", summary.ceres_summary.BriefReport())
            except Exception:
                pass

    kit_seconds = rows[0]["seconds"]
    print()
    print(f"initial cost {init_all:.4e} (all {problem.n_obs} observations), {init_front:.4e} (in front)")
    header = (f"| {'solver':32s} | {'final cost':>10s} | {'in front':>10s} | {'iter':>4s} | {'seconds':>7s} | "
              f"{'x kit':>6s} | {'cpu s':>7s} |")
    print(header)
    print("|" + "|".join("-" * (len(c)) for c in header.split("|")[1:-1]) + "|")
    for r in rows:
        r["ratio_to_kit"] = r["seconds"] / kit_seconds
        print(f"| {r['solver']:32s} | {r['final_cost']:10.4e} | {r['final_cost_in_front']:10.4e} | "
              f"{r['iterations']:4d} | {r['seconds']:7.2f} | {r['ratio_to_kit']:6.2f} | {r['cpu_seconds']:7.2f} |")
    if args.json:
        args.json.write_text(json.dumps(dict(problem=str(path), initial_cost=init_all, initial_cost_in_front=init_front,
                                             load_average=os.getloadavg(), rows=rows), indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

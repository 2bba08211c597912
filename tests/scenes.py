"""Synthetic scenes shared by several test modules."""

import numpy as np

from course_lib.conventions import compose_poses, invert_pose, world_to_camera
from course_lib.data.synthetic import make_scene


def relative_scene(noise_px=0.0, n_points=300, seed=0, outlier_fraction=0.0):
    """The synthetic scene re-expressed with camera 0 at R = I, t = 0 (the two-view frame)."""
    sc = make_scene(np.random.default_rng(seed), n_cameras=3, n_points=n_points, noise_px=noise_px,
                    outlier_fraction=outlier_fraction, dropout=0.0)
    R0w, t0w = sc.R_cw[0], sc.t_cw[0]
    R_w0, t_w0 = invert_pose(R0w, t0w)
    R_cw = np.stack([compose_poses(R, t, R_w0, t_w0)[0] for R, t in zip(sc.R_cw, sc.t_cw)])
    t_cw = np.stack([compose_poses(R, t, R_w0, t_w0)[1] for R, t in zip(sc.R_cw, sc.t_cw)])
    X = world_to_camera(R0w, t0w, sc.X)
    return sc, R_cw, t_cw, X

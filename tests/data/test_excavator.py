"""The held-out NeRF scene (course_lib.data.excavator): the grouped ray caster draws the same image as
the plain one, and every size of a data set is the largest one made smaller."""

import json

import numpy as np

from course_lib.data.blender import intrinsics_from_fov, load_blender
from course_lib.data.building import orbit_camera, render
from course_lib.data.excavator import CAMERA_ANGLE_X, build_excavator, make_excavator_datasets


def test_grouped_ray_casting_draws_the_same_image():
    surfaces, groups = build_excavator(np.random.default_rng(1))
    assert len(surfaces) > 150 and groups[-1][1] == len(surfaces)  # the groups cover every surface
    K = intrinsics_from_fov(48, 48, CAMERA_ANGLE_X)
    for az, el in ((0.3, 0.5), (3.5, 1.1)):
        M = orbit_camera(4.0, az, el)
        R_cw = M[:3, :3].T
        args = (surfaces, K, R_cw, -R_cw @ M[:3, 3], (48, 48))
        rgb, alpha = render(*args, supersample=1, background="transparent")
        rgb_g, alpha_g = render(*args, supersample=1, background="transparent", groups=groups)
        np.testing.assert_array_equal(alpha, alpha_g)
        np.testing.assert_allclose(rgb, rgb_g, atol=1e-12)
        assert 0.1 < alpha.mean() < 0.6  # the excavator fills a good part of the view, not all of it


def test_every_size_is_the_largest_made_smaller(tmp_path):
    folders = make_excavator_datasets(tmp_path, sizes=(16, 32), n_train=3, n_test=2)
    small, large = (load_blender(folders[s], "test", dtype="float32") for s in (16, 32))
    assert (small.W, large.W) == (16, 32) and len(small) == 2 and len(load_blender(folders[16], "train")) == 3
    np.testing.assert_allclose(small.c2w, large.c2w)
    shrunk = large.images.reshape(2, 16, 2, 16, 2, 3).mean(axis=(2, 4))
    assert np.abs(small.images - shrunk).mean() < 0.02  # area downscaling (of RGBA, then composited)
    info = json.loads((folders[16] / "scene.json").read_text())
    assert info["rendered_at"] == 32 and info["image_size"] == [16, 16]

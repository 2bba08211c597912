"""Rays through pixel centres, against a camera computed by hand; samples along rays."""

import numpy as np
import pytest
import torch

from course_lib.nerf.rays import get_rays, query_points, ray_box_intersection, stratified_samples
from course_lib.validate import KitInputError


def _camera(W=5, H=3, f=2.0):
    K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1.0]])
    # camera at C = (0, 0, -5) looking along world +z, x right, y down: identity rotation
    c2w = np.eye(4)
    c2w[:3, 3] = [0, 0, -5]
    return K, c2w


def test_centre_pixel_ray_is_optical_axis():
    K, c2w = _camera()
    rays_o, rays_d = get_rays(3, 5, K, c2w)
    assert rays_o.shape == (3, 5, 3) and rays_d.shape == (3, 5, 3)
    assert rays_d.dtype == torch.float32
    np.testing.assert_allclose(rays_d[1, 2].numpy(), [0, 0, 1])
    np.testing.assert_allclose(rays_o[0, 0].numpy(), [0, 0, -5])


def test_pixel_direction_by_hand():
    K, c2w = _camera()
    _, rays_d = get_rays(3, 5, K, c2w)
    # pixel u = 4 (last column), v = 0 (first row): ((4 - 2) / 2, (0 - 1) / 2, 1) = (1, -0.5, 1)
    np.testing.assert_allclose(rays_d[0, 4].numpy(), [1.0, -0.5, 1.0])
    # rows index v, columns index u ("xy" meshgrid): the top-left ray goes left and up
    np.testing.assert_allclose(rays_d[0, 0].numpy(), [-1.0, -0.5, 1.0])


def test_rotated_camera_and_z_is_depth():
    # camera at (4, 0, 0) looking at the origin: z_cam = -x_world, y_cam = -z_world (down), x_cam = -y_world
    c2w = np.eye(4)
    c2w[:3, :3] = np.column_stack([[0, -1, 0], [0, 0, -1], [-1, 0, 0]])
    c2w[:3, 3] = [4, 0, 0]
    K = np.array([[10.0, 0, 1], [0, 10.0, 1], [0, 0, 1]])
    rays_o, rays_d = get_rays(3, 3, K, torch.tensor(c2w, dtype=torch.float64))
    assert rays_d.dtype == torch.float64
    np.testing.assert_allclose(rays_d[1, 1].numpy(), [-1, 0, 0])
    # every ray's component along the optical axis is 1: the point at t has camera depth t
    z_axis = torch.tensor(c2w[:3, 2])
    np.testing.assert_allclose((rays_d @ z_axis).numpy(), 1.0)
    # the pixel below the centre (v = 2) looks down: world -z
    assert rays_d[2, 1, 2] < 0


def test_matches_projection():
    # project the 3-D point at t = 3 along a pixel's ray: it lands on that pixel
    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    c2w = np.eye(4)
    c2w[:3, :3] = Rotation.random(random_state=2).as_matrix()
    c2w[:3, 3] = rng.normal(size=3)
    K = np.array([[50.0, 0, 19.5], [0, 50.0, 14.5], [0, 0, 1]])
    rays_o, rays_d = get_rays(30, 40, K, torch.tensor(c2w))
    X = (rays_o + 3.0 * rays_d).numpy().reshape(-1, 3)
    w2c = np.linalg.inv(c2w)
    x = (X @ w2c[:3, :3].T + w2c[:3, 3]) @ K.T
    uv = x[:, :2] / x[:, 2:]
    vv, uu = np.mgrid[0:30, 0:40]
    np.testing.assert_allclose(uv, np.column_stack([uu.ravel(), vv.ravel()]), atol=1e-9)
    np.testing.assert_allclose(x[:, 2] / K[2, 2], 3.0)


def test_stratified_samples():
    z = stratified_samples(2.0, 6.0, 5, 4, perturb=False)
    assert z.shape == (4, 5)
    np.testing.assert_allclose(z[0].numpy(), [2, 3, 4, 5, 6])
    g = torch.Generator().manual_seed(0)
    zp = stratified_samples(2.0, 6.0, 5, 1000, perturb=True, generator=g)
    assert (zp >= 2).all() and (zp <= 6).all()
    assert (zp[:, 1:] >= zp[:, :-1]).all()
    # sample i stays in its bin [mid_{i-1}, mid_i]
    assert (zp[:, 1] >= 2.5).all() and (zp[:, 1] <= 3.5).all()
    g2 = torch.Generator().manual_seed(0)
    assert torch.equal(zp, stratified_samples(2.0, 6.0, 5, 1000, perturb=True, generator=g2))
    near = torch.tensor([1.0, 2.0])
    zr = stratified_samples(near, near + 1, 3, 2, perturb=False)
    np.testing.assert_allclose(zr.numpy(), [[1, 1.5, 2], [2, 2.5, 3]])
    with pytest.raises(KitInputError):
        stratified_samples(6.0, 2.0, 5, 1, perturb=False)


def test_query_points_and_box():
    o = torch.tensor([[0.0, 0, -5], [0, 0, -5]])
    d = torch.tensor([[0.0, 0, 1], [0, 1, 0]])
    z = torch.tensor([[1.0, 2.0], [3.0, 4.0]])
    pts = query_points(o, d, z)
    np.testing.assert_allclose(pts.numpy(), [[[0, 0, -4], [0, 0, -3]], [[0, 3, -5], [0, 4, -5]]])
    t0, t1 = ray_box_intersection(o, d, [-1, -1, -1], [1, 1, 1])
    np.testing.assert_allclose([t0[0].item(), t1[0].item()], [4, 6])
    assert t1[1] <= t0[1]  # misses the box
    with pytest.raises(KitInputError, match="flatten"):
        query_points(torch.zeros(2, 2, 3), torch.zeros(2, 2, 3), z)

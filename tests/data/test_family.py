"""The NeRF scene family (course_lib.data.family): each scene is its seed's, written as a valid Blender
scene whose poses (read back through the loader) see the object where the images show it."""

import json

import numpy as np
import pytest

from course_lib.data.blender import load_blender
from course_lib.data.building import cast_rays_grouped
from course_lib.data.family import FAMILY, build_family_scene, family_cameras, make_family_datasets
from course_lib.nerf.rays import camera_rays
from course_lib.validate import KitInputError


def _digest(surfaces, groups) -> tuple:
    return (len(surfaces), len(groups), float(sum(S.texture.sum() for S in surfaces)),
            float(sum(np.abs(S.origin).sum() + np.abs(S.a).sum() for S in surfaces)))


@pytest.mark.parametrize("name", list(FAMILY))
def test_a_scene_is_its_seeds(name):
    one = _digest(*build_family_scene(name, np.random.default_rng(5)))
    assert one == _digest(*build_family_scene(name, np.random.default_rng(5)))
    assert one != _digest(*build_family_scene(name, np.random.default_rng(6)))
    surfaces, groups = build_family_scene(name, np.random.default_rng(5))
    covered = np.zeros(len(surfaces), bool)
    for first, stop, _, _ in groups:
        covered[first:stop] = True
    assert covered.all()  # every surface is in a bounding sphere: the grouped caster sees all of them
    corners = np.array([S.origin + S.a + S.b for S in surfaces] + [S.origin for S in surfaces])
    assert np.abs(corners).max() < 1.25  # inside the box the cameras see


def test_cameras_look_at_the_origin_from_the_scene_radius():
    for name, scene in FAMILY.items():
        cams = family_cameras(name, np.random.default_rng(0), 6, 4)
        assert cams["train"].shape == (6, 4, 4) and cams["test"].shape == (4, 4, 4)
        C = cams["train"][:, :3, 3]
        np.testing.assert_allclose(np.linalg.norm(C, axis=1), scene.radius)
        axis = cams["train"][:, :3, 2]
        np.testing.assert_allclose(np.sum(axis * -C, axis=1) / scene.radius, 1.0, atol=1e-9)  # z looks at the origin


def test_every_scene_is_a_blender_scene_whose_poses_see_the_object(tmp_path):
    folders = make_family_datasets(tmp_path, sizes=(12, 24), n_train=3, n_test=2, seed=3)
    assert set(folders) == set(FAMILY)
    for name, by_size in folders.items():
        info = json.loads((by_size[12] / "scene.json").read_text())
        assert info["scene"] == name and info["rendered_at"] == 24 and info["image_size"] == [12, 12]
        assert len(load_blender(by_size[12], "train")) == 3
        white = load_blender(by_size[24], "test", white_background=True)
        black = load_blender(by_size[24], "test", white_background=False)
        assert (white.H, white.W, len(white)) == (24, 24, 2)
        alpha = 1.0 - (white.images - black.images).mean(axis=-1)  # (N, H, W): the stored coverage
        rng = np.random.default_rng(list(FAMILY).index(name) + 3)
        surfaces, groups = build_family_scene(name, rng)
        for i in range(len(white)):
            o, d = camera_rays(white.H, white.W, white.K, white.c2w[i])  # the loader's poses, the kit's rays
            o, d = o.reshape(-1, 3).double().numpy(), d.reshape(-1, 3).double().numpy()
            _, sid, _, _ = cast_rays_grouped(surfaces, groups, o[0], d)
            hit = (sid >= 0).reshape(white.H, white.W)
            a = alpha[i]
            sure = (a < 0.01) | (a > 0.99)  # pixels wholly on or off the object (its edges are partly covered)
            assert sure.mean() > 0.5
            agree = (hit == (a > 0.5))[sure].mean()
            assert agree > 0.97, f"{name} view {i}: the pose's pixel-centre rays agree with the image on {agree:.0%}"
            assert hit.any()  # the object is in view


def test_unknown_scene_is_named():
    with pytest.raises(KitInputError, match="bricks"):
        build_family_scene("teapot", np.random.default_rng(0))

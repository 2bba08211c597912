"""The Blender NeRF loader/writer: axes pinned by hand, the lego data, round trips, clear errors."""

import json

import numpy as np
import pytest

from course_lib.data.blender import (
    GL_FROM_CV,
    intrinsics_from_fov,
    load_blender,
    load_tiny_nerf_npz,
    write_blender,
)
from course_lib.paths import course_data
from course_lib.validate import KitInputError

LEGO = course_data("lego")
needs_lego = pytest.mark.skipif(LEGO is None, reason="course data nerf-lego-100 not on this machine (set COURSE_DATA)")


def _blender_camera_on_x_axis(d=4.0):
    """Blender/OpenGL c2w of a camera at (d, 0, 0) looking at the origin, world z up.

    OpenGL camera axes in the world: looks along -z_cam = -x_world -> z_cam = +x_world;
    y_cam (up) = +z_world; x_cam (right) = y_cam x z_cam = +y_world.
    """
    M = np.eye(4)
    M[:3, 0] = [0, 1, 0]
    M[:3, 1] = [0, 0, 1]
    M[:3, 2] = [1, 0, 0]
    M[:3, 3] = [d, 0, 0]
    return M


def _write_json(folder, split, frames, camera_angle_x=0.69):
    (folder / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": camera_angle_x, "frames": frames}))


def _tiny_scene(folder, split="train", n=1, size=(4, 6), c2w_gl=None):
    import cv2

    H, W = size
    (folder / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(n):
        rgba = np.zeros((H, W, 4), np.uint8)
        rgba[..., 0] = 255  # red, alpha 0 except one opaque pixel
        rgba[0, 0, 3] = 255
        cv2.imwrite(str(folder / "images" / f"v{i}.png"), cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
        M = _blender_camera_on_x_axis() if c2w_gl is None else c2w_gl
        frames.append({"file_path": f"./images/v{i}", "transform_matrix": M.tolist()})
    _write_json(folder, split, frames)
    return folder


def test_axes_pinned_by_hand(tmp_path):
    data = load_blender(_tiny_scene(tmp_path))
    c2w = data.c2w[0]
    np.testing.assert_allclose(c2w[:3, 3], [4, 0, 0])
    # OpenCV z (optical axis) points from the camera at +x towards the origin.
    np.testing.assert_allclose(c2w[:3, 2], [-1, 0, 0], atol=1e-12)
    # OpenCV y (image down) is world -z (world z is up in Blender).
    np.testing.assert_allclose(c2w[:3, 1], [0, 0, -1], atol=1e-12)
    # x (image right) unchanged, still a proper rotation.
    np.testing.assert_allclose(c2w[:3, 0], [0, 1, 0], atol=1e-12)
    assert np.linalg.det(c2w[:3, :3]) == pytest.approx(1.0)
    # The origin projects to the principal point, in front of the camera.
    X_cam = np.linalg.inv(c2w) @ np.array([0, 0, 0, 1.0])
    assert X_cam[2] == pytest.approx(4.0)
    uvw = data.K @ X_cam[:3]
    np.testing.assert_allclose(uvw[:2] / uvw[2], [data.K[0, 2], data.K[1, 2]])
    # A point above the origin (world +z) appears in the upper half of the image (smaller v).
    up = np.linalg.inv(c2w) @ np.array([0, 0, 1.0, 1])
    assert (data.K @ up[:3])[1] / up[2] < data.K[1, 2]


def test_compositing_white_and_black(tmp_path):
    folder = _tiny_scene(tmp_path)
    white = load_blender(folder).images[0]
    black = load_blender(folder, white_background=False).images[0]
    assert white.dtype == np.float32 and white.shape == (4, 6, 3)
    np.testing.assert_allclose(white[0, 0], [1, 0, 0])  # opaque red
    np.testing.assert_allclose(white[1, 1], [1, 1, 1])  # transparent -> white
    np.testing.assert_allclose(black[1, 1], [0, 0, 0])  # transparent -> black


def test_intrinsics_from_fov():
    K = intrinsics_from_fov(100, 100, 0.6911112070083618)
    assert K[0, 0] == pytest.approx(138.8889, abs=1e-3)
    assert K[0, 0] == K[1, 1]
    assert (K[0, 2], K[1, 2]) == (49.5, 49.5)


def test_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    N, H, W = 3, 5, 7
    c2w = np.tile(np.eye(4), (N, 1, 1))
    c2w[:, :3, :3] = Rotation.random(N, random_state=1).as_matrix()
    c2w[:, :3, 3] = rng.normal(size=(N, 3))
    images = rng.integers(0, 256, size=(N, H, W, 3), dtype=np.uint8)
    jpath = write_blender(tmp_path, "test", images, c2w, 0.8, names=["a", "b", "c"])
    meta = json.loads(jpath.read_text())
    assert meta["frames"][0]["file_path"] == "./images/a"
    # stored in OpenGL axes
    np.testing.assert_allclose(np.array(meta["frames"][1]["transform_matrix"]), c2w[1] @ GL_FROM_CV)
    back = load_blender(tmp_path, "test")
    assert back.names == ["a", "b", "c"] and (back.H, back.W) == (H, W)
    np.testing.assert_allclose(back.c2w, c2w, atol=1e-12)
    np.testing.assert_array_equal(np.round(back.images * 255).astype(np.uint8), images)
    assert back.camera_angle_x == pytest.approx(0.8)


def test_round_trip_rgba_and_downscale(tmp_path):
    images = np.zeros((1, 4, 4, 4), np.uint8)
    images[0, :2, :2] = [0, 0, 255, 255]  # opaque blue top-left quarter, the rest transparent
    write_blender(tmp_path, "train", images, np.eye(4)[None], 0.5)
    d = load_blender(tmp_path, downscale=2)
    assert (d.H, d.W) == (2, 2)
    np.testing.assert_allclose(d.images[0, 0, 0], [0, 0, 1], atol=1e-6)
    np.testing.assert_allclose(d.images[0, 1, 1], [1, 1, 1], atol=1e-6)
    assert d.K[0, 0] == pytest.approx(0.5 * intrinsics_from_fov(4, 4, 0.5)[0, 0])


def test_tiny_nerf_npz(tmp_path):
    poses = np.stack([_blender_camera_on_x_axis()] * 2)
    path = tmp_path / "tiny.npz"
    np.savez(path, images=np.zeros((2, 10, 10, 3), np.float32), poses=poses, focal=np.array(138.88887889922103 / 10))
    d = load_tiny_nerf_npz(path)
    assert d.images.shape == (2, 10, 10, 3) and len(d.names) == 2
    np.testing.assert_allclose(d.c2w[0][:3, 2], [-1, 0, 0], atol=1e-12)
    assert d.focal == pytest.approx(13.888887889922103)


def test_errors(tmp_path):
    with pytest.raises(KitInputError, match="not found"):
        load_blender(tmp_path / "nope")
    with pytest.raises(KitInputError, match="transforms_train.json"):
        load_blender(tmp_path)
    (tmp_path / "transforms_train.json").write_text("{not json")
    with pytest.raises(KitInputError, match="not valid JSON"):
        load_blender(tmp_path)
    _write_json(tmp_path, "train", [{"file_path": "./images/missing", "transform_matrix": np.eye(4).tolist()}])
    with pytest.raises(KitInputError, match="missing.png not found"):
        load_blender(tmp_path)
    _tiny_scene(tmp_path / "s")
    meta = json.loads((tmp_path / "s" / "transforms_train.json").read_text())
    meta["camera_angle_y"] = 0.3  # contradicts square pixels
    (tmp_path / "s" / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(KitInputError, match="square pixels"):
        load_blender(tmp_path / "s")
    bad = np.eye(4)
    bad[:3, :3] *= 2
    _tiny_scene(tmp_path / "t", c2w_gl=bad)
    with pytest.raises(KitInputError, match="not a rotation"):
        load_blender(tmp_path / "t")
    with pytest.raises(KitInputError, match="split"):
        load_blender(tmp_path / "t", split="training")
    with pytest.raises(KitInputError, match="expected"):
        write_blender(tmp_path / "w", "train", np.zeros((2, 4, 4), np.uint8), np.eye(4)[None], 0.5)


@needs_lego
def test_lego():
    train = load_blender(LEGO, "train")
    test = load_blender(LEGO, "test")
    assert len(train) == 90 and len(test) == 10
    assert train.images.shape == (90, 100, 100, 3) and train.images.dtype == np.float32
    assert 0.0 <= train.images.min() and train.images.max() <= 1.0
    assert train.focal == pytest.approx(138.889, abs=1e-3)
    assert train.names[0] == "r_0" and test.names[0] == "r_90"
    for d in (train, test):
        C = d.c2w[:, :3, 3]
        np.testing.assert_allclose(np.linalg.norm(C, axis=1), 4.03, atol=0.01)
        # Every optical axis (OpenCV z) passes close to the origin: the distance from the origin
        # to the line C + s z is small compared to the 4 m camera distance.
        z = d.c2w[:, :3, 2]
        s = -(C * z).sum(1)
        assert (s > 3.5).all(), "the origin must lie in front of every camera"
        miss = np.linalg.norm(C + s[:, None] * z, axis=1)
        assert miss.max() < 0.1
        # image down (OpenCV y) points roughly to world -z for these upright cameras
        assert (d.c2w[:, 2, 1] < 0).all()
    # corners are background -> white
    np.testing.assert_allclose(train.images[:, 0, 0], 1.0, atol=0.02)

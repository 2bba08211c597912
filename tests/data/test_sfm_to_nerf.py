"""`sfm-to-nerf`: a COLMAP text model + images -> NeRF Blender data set (course_lib.data.sfm_to_nerf)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from course_lib.__main__ import main
from course_lib.data import building
from course_lib.data.blender import intrinsics_from_fov, load_blender
from course_lib.data.colmap import write_colmap_text
from course_lib.data.sfm_to_nerf import normalization, resample_images, sfm_to_nerf
from course_lib.alignment import align_similarity
from course_lib.validate import KitInputError


def _write_model(folder, K, size, R_cw, t_cw, X, images):
    """A COLMAP text model of known cameras and points, with its images (P3 names 1.png ...)."""
    import cv2

    M = len(R_cw)
    names = [f"{i + 1}.png" for i in range(M)]
    uv = np.full((len(X), M, 2), np.nan)
    for i in range(M):
        xc = X @ R_cw[i].T + t_cw[i]
        uv[:, i] = (xc @ K.T)[:, :2] / (xc @ K.T)[:, 2:]
    write_colmap_text(folder / "colmap", K, size, names, R_cw, t_cw, np.ones(M, bool), X,
                      np.full((len(X), 3), 128, np.uint8), uv)
    for n, im in zip(names, images):
        cv2.imwrite(str(folder / n), im[:, :, ::-1])
    return names


@pytest.fixture(scope="module")
def known_scene(tmp_path_factory):
    """building.py's NeRF cameras (known c2w in the NeRF frame), moved into an arbitrary 'SfM' world."""
    folder = tmp_path_factory.mktemp("sfm")
    c2w_true = building.nerf_cameras(np.random.default_rng(7), 12)  # NeRF frame, OpenCV axes
    # an arbitrary similarity: X_sfm = s R X_nerf + t
    s, R, t = 3.7, Rotation.from_rotvec([0.3, -1.1, 0.4]).as_matrix(), np.array([5.0, -2.0, 11.0])
    R_cw = np.stack([(R @ c[:3, :3]).T for c in c2w_true])
    C = np.stack([s * R @ c[:3, 3] + t for c in c2w_true])
    t_cw = -np.einsum("mij,mj->mi", R_cw, C)
    X_nerf = np.random.default_rng(0).uniform(-0.8, 0.8, (300, 3))
    X = s * X_nerf @ R.T + t
    W, H = 64, 48
    K = np.array([[70.0, 0, 33.0], [0, 72.0, 22.5], [0, 0, 1]])  # off-centre, fx != fy: must be resampled
    imgs = [np.full((H, W, 3), 10 * i, np.uint8) for i in range(12)]
    _write_model(folder, K, (W, H), R_cw, t_cw, X, imgs)
    return folder, c2w_true, (s, R, t), K, X


def test_known_poses_and_round_trip(known_scene, tmp_path):
    folder, c2w_true, (s, R, t), K, X = known_scene
    summ = sfm_to_nerf(folder, folder, tmp_path / "nerf", size=32, test_every=4)
    tr, te = load_blender(tmp_path / "nerf", "train"), load_blender(tmp_path / "nerf", "test")
    assert len(tr) == 9 and len(te) == 3 and summ["test"] == ["3.png", "7.png", "11.png"]
    c2w = np.zeros((12, 4, 4))
    c2w[[i for i in range(12) if i % 4 != 2]] = tr.c2w
    c2w[[i for i in range(12) if i % 4 == 2]] = te.c2w
    # round trip against load_blender: exactly the stated similarity X_nerf = scale (X_sfm - center)
    frame_c, frame_s = np.array(summ["center"]), summ["scale"]
    R_cw_sfm = np.stack([(R @ c[:3, :3]).T for c in c2w_true])
    C_sfm = np.stack([s * R @ c[:3, 3] + t for c in c2w_true])
    np.testing.assert_allclose(c2w[:, :3, :3], np.transpose(R_cw_sfm, (0, 2, 1)), atol=1e-9)
    np.testing.assert_allclose(c2w[:, :3, 3], frame_s * (C_sfm - frame_c), atol=1e-9)
    # and the known NeRF-frame cameras come back up to a similarity (rotation R^T, scale)
    s2, R2, t2 = align_similarity(c2w[:, :3, 3], c2w_true[:, :3, 3])
    np.testing.assert_allclose(R2, R.T, atol=1e-9)
    np.testing.assert_allclose(s2 * frame_s * s, 1.0, rtol=1e-9)
    np.testing.assert_allclose(np.einsum("ij,mjk->mik", R2, c2w[:, :3, :3]), c2w_true[:, :3, :3], atol=1e-9)
    # the points' sphere is the unit sphere (95 % of the points inside)
    r = np.linalg.norm(frame_s * (X - frame_c), axis=1)
    assert np.percentile(r, 95) == pytest.approx(1.0)
    # Blender intrinsics: square pixels, centred; field of view from the mean focal length
    assert (tr.W, tr.H) == (32, 24)
    np.testing.assert_allclose(tr.K, intrinsics_from_fov(32, 24, summ["camera_angle_x"]))
    assert tr.K[0, 0] == pytest.approx(0.5 * (70 + 72) * 0.5)
    assert summ["near"] < min(summ["camera_distance"]) - 1 and summ["far"] > max(summ["camera_distance"]) + 1
    saved = json.loads((tmp_path / "nerf" / "sfm_to_nerf.json").read_text())
    assert saved["scale"] == summ["scale"]


def test_resample_moves_principal_point():
    """A pixel at the photo's principal point lands at the Blender image centre."""
    K = np.array([[100.0, 0, 70.0], [0, 100.0, 30.0], [0, 0, 1]])
    img = np.zeros((80, 120, 3), np.uint8)
    img[28:33, 68:73] = 255  # a blob centred on (70, 30)
    out, Kb, _ = resample_images([img], K, 120)
    v, u = np.nonzero(out[0, :, :, 0] > 128)
    assert abs(u.mean() - Kb[0, 2]) < 0.3 and abs(v.mean() - Kb[1, 2]) < 0.3


def test_cli_and_errors(known_scene, tmp_path, capsys):
    folder = known_scene[0]
    assert main(["sfm-to-nerf", str(folder), "--images", str(folder), "--out", str(tmp_path / "n"), "--size", "16"]) == 0
    assert "train it: python -m course_lib nerf train" in capsys.readouterr().out
    assert main(["sfm-to-nerf", str(tmp_path), "--images", str(folder), "--out", str(tmp_path / "m")]) == 2
    assert "no COLMAP text model" in capsys.readouterr().err
    with pytest.raises(KitInputError, match="cannot read the image"):
        sfm_to_nerf(folder, tmp_path, tmp_path / "o")
    with pytest.raises(KitInputError, match="too sparse"):
        normalization(np.zeros((2, 3)))


def test_orbit_cameras_look_at_the_origin():
    from course_lib.data.sfm_to_nerf import orbit_c2w

    for n, span in ((40, 360.0), (20, 180.0)):
        c2w = orbit_c2w(n, span_deg=span)
        C, z = c2w[:, :3, 3], c2w[:, :3, 2]
        assert c2w.shape == (n, 4, 4)
        np.testing.assert_allclose(np.linalg.norm(C, axis=1), building.NERF_RADIUS)
        np.testing.assert_allclose(np.einsum("mi,mi->m", z, -C / building.NERF_RADIUS), 1.0, atol=1e-12)  # z forward, at the origin
        np.testing.assert_allclose(np.linalg.det(c2w[:, :3, :3]), 1.0)
        assert (c2w[:, 2, 1] < 0).all()  # camera y (down in the image) points down in the z-up world


def test_a_simple_radial_model_is_undistorted_first(tmp_path):
    """A SIMPLE_RADIAL model: the photos are resampled onto the pinhole before the NeRF sees them."""
    import cv2

    from course_lib.data.camera import distort_pixels

    K = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    k1 = -0.15
    c2w = building.nerf_cameras(np.random.default_rng(1), 6)
    R_cw = np.stack([c[:3, :3].T for c in c2w])
    t_cw = -np.einsum("mij,mj->mi", R_cw, c2w[:, :3, 3])
    X = np.random.default_rng(0).uniform(-0.8, 0.8, (100, 3))
    img = np.zeros((48, 64, 3), np.uint8)
    d = distort_pixels(np.array([[58.0, 40.0]]), K, k1)[0]  # a corner dot as the distorted camera sees it
    img[int(round(d[1])), int(round(d[0]))] = 255
    names = [f"{i + 1}.png" for i in range(6)]
    uv = np.stack([(np.c_[X @ R_cw[i].T + t_cw[i]] @ K.T)[:, :2] / (X @ R_cw[i].T + t_cw[i])[:, 2:] for i in range(6)], 1)
    write_colmap_text(tmp_path / "colmap", K, (64, 48), names, R_cw, t_cw, np.ones(6, bool), X,
                      np.full((100, 3), 128, np.uint8), uv, camera_model="SIMPLE_RADIAL", k1=k1)
    for n in names:
        cv2.imwrite(str(tmp_path / n), img)
    summ = sfm_to_nerf(tmp_path, tmp_path, tmp_path / "nerf", size=64, test_every=0)
    assert summ["camera_model"] == "SIMPLE_RADIAL" and summ["undistorted_k1"] == k1
    out = load_blender(tmp_path / "nerf", "train").images[0]
    v, u = np.unravel_index(np.argmax(out.sum(axis=2)), out.shape[:2])
    assert abs(u - 58) <= 1 and abs(v - 40) <= 1  # where the pinhole sees the dot

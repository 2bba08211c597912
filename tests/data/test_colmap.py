"""COLMAP text models (course_lib.data.colmap): round trip, pixel convention, pycolmap cross-check."""

import numpy as np
import pytest

from course_lib.conventions import project
from course_lib.data.colmap import read_colmap_text, write_colmap_text
from course_lib.data.synthetic import make_scene
from course_lib.validate import KitInputError


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    rng = np.random.default_rng(3)
    sc = make_scene(rng, n_cameras=5, n_points=80, noise_px=0.3, outlier_fraction=0.0)
    X = sc.X.copy()
    X[[3, 10]] = np.nan  # not triangulated
    registered = np.array([True, True, False, True, True])
    rgb = rng.integers(0, 256, (80, 3)).astype(np.uint8)
    names = [f"{i + 1}.png" for i in range(5)]
    R = sc.R_cw.copy()
    t = sc.t_cw.copy()
    R[2] = np.nan  # unregistered images may hold NaN poses
    t[2] = np.nan
    folder = tmp_path_factory.mktemp("colmap")
    write_colmap_text(folder, sc.K, (800, 600), names, R, t, registered, X, rgb, sc.uv)
    return dict(folder=folder, sc=sc, X=X, registered=registered, rgb=rgb, names=names)


def test_files_written(model):
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        assert (model["folder"] / name).is_file()
    cam = [ln for ln in (model["folder"] / "cameras.txt").read_text().splitlines() if not ln.startswith("#")]
    assert cam[0].startswith("1 PINHOLE 800 600 ")


def test_round_trip(model):
    m = read_colmap_text(model["folder"])
    sc, reg = model["sc"], model["registered"]
    assert m.image_names == ["1.png", "2.png", "4.png", "5.png"]
    np.testing.assert_array_equal(m.image_ids, [1, 2, 4, 5])
    np.testing.assert_allclose(m.K, sc.K, atol=1e-12)
    assert m.image_size == (800, 600)
    np.testing.assert_allclose(m.R_cw, sc.R_cw[reg], atol=1e-12)
    np.testing.assert_allclose(m.t_cw, sc.t_cw[reg], atol=1e-12)
    has_X = np.isfinite(model["X"]).all(axis=1)
    np.testing.assert_allclose(m.X, model["X"][has_X])
    np.testing.assert_array_equal(m.rgb, model["rgb"][has_X])
    np.testing.assert_array_equal(m.point_ids, np.arange(1, has_X.sum() + 1))
    uv = sc.uv[has_X][:, reg]
    np.testing.assert_array_equal(np.isnan(m.uv), np.isnan(uv))
    np.testing.assert_allclose(m.uv[np.isfinite(uv)], uv[np.isfinite(uv)], atol=1e-9)
    # ERROR is the mean reprojection error of the point over its track
    j = int(np.flatnonzero(np.isfinite(m.uv[:, 0, 0]) & np.isfinite(m.uv[:, 1, 0]))[0])
    e = [np.linalg.norm(project(m.K, m.R_cw[i], m.t_cw[i], m.X[j : j + 1])[0] - m.uv[j, i]) for i in range(4) if np.isfinite(m.uv[j, i, 0])]
    assert abs(m.error[j] - np.mean(e)) < 1e-9


def test_pycolmap_reads_the_model(model):
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap (environment.txt) is needed for the COLMAP cross-check")
    rec = pycolmap.Reconstruction(str(model["folder"]))
    sc, reg = model["sc"], model["registered"]
    assert rec.num_reg_images() == 4
    assert rec.num_points3D() == int(np.isfinite(model["X"]).all(axis=1).sum())
    for i in np.flatnonzero(reg):
        img = rec.images[int(i) + 1]
        assert img.name == model["names"][i]
        pose = img.cam_from_world() if callable(img.cam_from_world) else img.cam_from_world
        np.testing.assert_allclose(pose.rotation.matrix(), sc.R_cw[i], atol=1e-10)
        np.testing.assert_allclose(pose.translation, sc.t_cw[i], atol=1e-10)
    p = rec.points3D[1]
    np.testing.assert_allclose(p.xyz, model["X"][0])
    # pycolmap's own projection agrees with the kit's after the 0.5 px shift of the pixel convention
    cam = rec.cameras[1]
    img = rec.images[1]
    pose = img.cam_from_world() if callable(img.cam_from_world) else img.cam_from_world
    xc = pose * model["X"][0]
    uv_colmap = cam.img_from_cam(xc[None, :] / xc[2])[0] if xc.ndim == 1 else None
    uv_kit = project(sc.K, sc.R_cw[0], sc.t_cw[0], model["X"][:1])[0]
    np.testing.assert_allclose(uv_colmap, uv_kit + 0.5, atol=1e-9)
    # and its mean reprojection error (recomputed) equals the kit's
    rec.update_point_3d_errors()
    m = read_colmap_text(model["folder"])
    assert abs(rec.compute_mean_reprojection_error() - m.error.mean()) < 1e-6


def test_bad_inputs(tmp_path, model):
    sc = model["sc"]
    args = dict(K=sc.K, image_size=(800, 600), image_names=model["names"], R_cw=sc.R_cw, t_cw=sc.t_cw,
                registered=model["registered"], X=sc.X, rgb=model["rgb"], observations=sc.uv)
    with pytest.raises(KitInputError, match="registered has shape"):
        write_colmap_text(tmp_path, **{**args, "registered": np.ones(3, bool)})
    with pytest.raises(KitInputError, match="observations has shape"):
        write_colmap_text(tmp_path, **{**args, "observations": sc.uv[:, :2]})
    with pytest.raises(KitInputError, match="not invertible"):
        write_colmap_text(tmp_path, **{**args, "K": np.diag([0.0, 0.0, 1.0])})
    with pytest.raises(KitInputError, match="not found"):
        read_colmap_text(tmp_path / "nothing")
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "cameras.txt").write_text("1 OPENCV 800 600 1 2 3 4 0 0 0 0\n")
    (tmp_path / "m" / "images.txt").write_text("")
    (tmp_path / "m" / "points3D.txt").write_text("")
    with pytest.raises(KitInputError, match="PINHOLE"):
        read_colmap_text(tmp_path / "m")


def test_simple_radial_writes_the_photos_own_pixels_and_reads_back(tmp_path):
    from course_lib.data.camera import distort_pixels

    rng = np.random.default_rng(4)
    sc = make_scene(rng, n_cameras=3, n_points=40, noise_px=0.0, outlier_fraction=0.0)
    K = sc.K.copy()
    K[0, 1], K[1, 1] = 0.0, K[0, 0]
    names = [f"{i + 1}.png" for i in range(3)]
    write_colmap_text(tmp_path, K, (800, 600), names, sc.R_cw, sc.t_cw, np.ones(3, bool), sc.X,
                      np.zeros((40, 3), np.uint8), sc.uv, camera_model="SIMPLE_RADIAL", k1=-0.04)
    cam = [ln for ln in (tmp_path / "cameras.txt").read_text().splitlines() if not ln.startswith("#")][0].split()
    assert cam[1] == "SIMPLE_RADIAL" and float(cam[4]) == K[0, 0] and float(cam[7]) == -0.04
    m = read_colmap_text(tmp_path)
    assert m.camera_model == "SIMPLE_RADIAL" and m.k1 == -0.04
    np.testing.assert_allclose(m.K, K, atol=1e-12)
    has = np.isfinite(m.uv)
    np.testing.assert_allclose(m.uv[has], distort_pixels(sc.uv, K, -0.04)[has], atol=1e-9)
    with pytest.raises(KitInputError, match="PINHOLE or SIMPLE_RADIAL"):
        write_colmap_text(tmp_path, K, (800, 600), names, sc.R_cw, sc.t_cw, np.ones(3, bool), sc.X,
                          np.zeros((40, 3), np.uint8), sc.uv, camera_model="OPENCV")
    (tmp_path / "cameras.txt").write_text("1 OPENCV 800 600 500 500 400 300 0.1 0.01 0 0\n")
    with pytest.raises(KitInputError, match="undistort the images first"):
        read_colmap_text(tmp_path)

"""`match`: photos with known K -> P3 folder (course_lib.data.cli_match)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from course_lib.__main__ import main
from course_lib.data import building
from course_lib.data.cli_match import list_images, match_folder, scale_intrinsics
from course_lib.data.p3 import read_p3
from course_lib.validate import KitInputError


@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    """4 small renders of the building (400x300) with their true cameras, as P3-numbered PNGs + a noise file."""
    import cv2

    folder = tmp_path_factory.mktemp("photos")
    rng = np.random.default_rng(3)
    surfaces = building.build_scene(rng, ground="large", rho=40.0)
    R_cw, t_cw = building.sfm_cameras(np.random.default_rng(1), 4)
    K = building.WPI_LIKE_K.copy()
    K = scale_intrinsics(K, building.SFM_IMAGE_SIZE, (400, 300))
    for i in range(4):
        rgb, _ = building.render(surfaces, K, R_cw[i], t_cw[i], (400, 300), supersample=1)
        cv2.imwrite(str(folder / f"{i + 1}.png"), np.round(rgb[:, :, ::-1] * 255).astype(np.uint8))
    np.savetxt(folder / "calibration.txt", K)
    (folder / "notes.txt").write_text("not an image")
    cv2.imwrite(str(folder / "thumbnail.jpg"), np.zeros((10, 10, 3), np.uint8))  # ignored: not P3-numbered
    return folder, K, R_cw, t_cw


def test_match_writes_p3_with_true_epipolar_geometry(photos, tmp_path):
    folder, K, R_cw, t_cw = photos
    rep = match_folder(folder, folder / "calibration.txt", tmp_path / "p3")
    assert [im["source"] for im in rep["images"]] == ["1.png", "2.png", "3.png", "4.png"]
    d = read_p3(tmp_path / "p3")
    assert d.n_images == 4 and d.image_size == (400, 300)
    np.testing.assert_allclose(d.K, K, atol=1e-9)
    assert d.n_tracks > 200
    for (i, j), pm in d.matches.items():
        e = building.epipolar_errors(K, R_cw[i], t_cw[i], R_cw[j], t_cw[j], pm.x1, pm.x2)
        assert len(pm) >= 15
        assert np.median(e) < 0.3, (i, j, np.median(e))
        # each pair was verified at 2 px; the files also list the pairs that tracks imply (i-k-j), a few of them wrong
        assert np.mean(e < 2.5) > 0.9, (i, j)


def test_downscale_scales_K_and_matches(photos, tmp_path):
    folder, K, R_cw, t_cw = photos
    rep = match_folder(folder, K, tmp_path / "p3", downscale=2.0)
    d = read_p3(tmp_path / "p3")
    assert d.image_size == (200, 150) and rep["image_size"] == [200, 150]
    K2 = scale_intrinsics(K, (400, 300), (200, 150))
    np.testing.assert_allclose(d.K, K2)
    assert K2[0, 0] == pytest.approx(K[0, 0] / 2) and K2[0, 2] == pytest.approx((K[0, 2] + 0.5) / 2 - 0.5)
    pm = d.pair(0, 1)
    e = building.epipolar_errors(K2, R_cw[0], t_cw[0], R_cw[1], t_cw[1], pm.x1, pm.x2)
    assert np.median(e) < 0.3


def test_cli_and_bad_inputs(photos, tmp_path, capsys):
    import cv2

    folder, K, _, _ = photos
    assert main(["match", str(folder), "--K", str(folder / "calibration.txt"), "--out", str(tmp_path / "cli"), "--no-verify"]) == 0
    assert "matched 4 images" in capsys.readouterr().out
    # all images in name order when none is P3-numbered
    other = tmp_path / "own"
    other.mkdir()
    for k, n in enumerate(["IMG_10.jpg", "IMG_2.JPG", "IMG_1.png"]):
        cv2.imwrite(str(other / n), cv2.imread(str(folder / f"{k + 1}.png")))
    assert [p.name for p in list_images(other)] == ["IMG_1.png", "IMG_2.JPG", "IMG_10.jpg"]

    cases = {
        "one": (["1.png"], "at least 2"),
        "sizes": (["1.png", "2.png"], "one camera at one size"),
        "broken": (["1.png", "2.png"], "cannot read the image"),
        "twice": (["1.png", "2.png"], "keep one file per number"),
    }
    for name, (files, msg) in cases.items():
        d = tmp_path / name
        d.mkdir()
        for f in files:
            (d / f).write_bytes((folder / f).read_bytes())
        if name == "sizes":
            cv2.imwrite(str(d / "2.png"), np.zeros((20, 30, 3), np.uint8))
        if name == "twice":
            (d / "2.jpg").write_bytes((folder / "2.png").read_bytes())
        if name == "broken":
            (d / "2.png").write_bytes(b"not a png")
        with pytest.raises(KitInputError, match=msg):
            match_folder(d, K, tmp_path / f"out_{name}")
    bad_k = tmp_path / "badK.txt"
    bad_k.write_text("1 0 2\n0 1\n")
    with pytest.raises(KitInputError, match="9 entries"):
        match_folder(folder, bad_k, tmp_path / "o1")
    with pytest.raises(KitInputError, match="not found"):
        match_folder(folder, tmp_path / "missing.txt", tmp_path / "o2")
    with pytest.raises(KitInputError, match="downscale"):
        match_folder(folder, K, tmp_path / "o3", downscale=0.5)
    # the CLI turns them into one line and exit status 2
    assert main(["match", str(tmp_path / "one"), "--K", str(folder / "calibration.txt"), "--out", str(tmp_path / "o4")]) == 2
    assert "error:" in capsys.readouterr().err


def test_photos_are_copied_and_the_verification_is_carried(photos, tmp_path):
    folder, K, _, _ = photos
    rep = match_folder(folder, folder / "calibration.txt", tmp_path / "p3")
    for i in range(1, 5):
        assert (tmp_path / "p3" / f"{i}.png").read_bytes() == (folder / f"{i}.png").read_bytes()  # copied, not re-encoded
    d = read_p3(tmp_path / "p3")
    assert d.camera is None  # K from a calibration file: held fixed by sfm
    assert d.two_view is not None and set(d.two_view) == {tuple(int(v) - 1 for v in k.split("-"))
                                                          for k, v in rep["pairs"].items() if v["verified"] >= 15}
    assert rep["pair_selection"] == "exhaustive" and rep["pairs_matched"] == 6
    assert d.stats["inconsistent_components"] == 0  # the tracks are written consistent (join_tracks)
    match_folder(folder, K, tmp_path / "p3", downscale=2.0, verify=False)
    assert not (tmp_path / "p3" / "two_view_geometries.json").exists()
    assert read_p3(tmp_path / "p3").image_size == (200, 150)
    seq = match_folder(folder, K, tmp_path / "seq", pairs="sequential")
    assert seq["pairs_matched"] == 6 and seq["pair_selection"] == "sequential"


def test_without_K_the_camera_comes_from_EXIF_and_sfm_refines_it(photos, tmp_path, capsys):
    import io

    from PIL import Image

    folder, K, _, _ = photos
    own = tmp_path / "phone"
    own.mkdir()
    f35 = round(K[0, 0] * 43.2666 / np.hypot(400, 300))
    for i in range(4):
        img = Image.open(folder / f"{i + 1}.png")
        ex = Image.Exif()
        ex[0x010F], ex[0x0110] = "Maker", "Phone"
        ex.get_ifd(0x8769)[0xA405] = f35
        buf = io.BytesIO()
        img.save(buf, "JPEG", quality=95, exif=ex.tobytes())
        (own / f"IMG_{i + 1:04d}.JPG").write_bytes(buf.getvalue())
    assert main(["match", str(own), "--out", str(tmp_path / "p3"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "camera: f = " in out and "FocalLengthIn35mmFilm" in out and "sfm refines f and k1" in out
    d = read_p3(tmp_path / "p3")
    assert d.camera.refine and d.camera.model == "SIMPLE_RADIAL" and d.camera.camera == "Maker Phone"
    assert abs(d.K[0, 0] / K[0, 0] - 1) < 0.03  # the rounded 35 mm equivalent
    assert (tmp_path / "p3" / "1.jpg").read_bytes() == (own / "IMG_0001.JPG").read_bytes()


def test_identical_photos_are_named(photos, tmp_path, capsys):
    folder, K, _, _ = photos
    twin = tmp_path / "twin"
    twin.mkdir()
    for i in range(1, 5):
        (twin / f"{i}.png").write_bytes((folder / f"{i}.png").read_bytes())
    (twin / "5.png").write_bytes((folder / "4.png").read_bytes())
    assert main(["match", str(twin), "--K", str(folder / "calibration.txt"), "--out", str(tmp_path / "p3"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "identical or near-identical photos (no baseline): 4.png, 5.png" in out
    rep = json.loads((tmp_path / "p3" / "match_report.json").read_text())
    assert rep["identical_photos"] == [["4.png", "5.png"]]

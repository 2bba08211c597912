"""`match`: photos with known K -> P3 folder (course_lib.data.match_cli)."""

from __future__ import annotations

import numpy as np
import pytest

from course_lib.__main__ import main
from course_lib.data import building
from course_lib.data.match_cli import list_images, match_folder, scale_intrinsics
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
        "gap": (["1.png", "3.png"], "without gaps"),
    }
    for name, (files, msg) in cases.items():
        d = tmp_path / name
        d.mkdir()
        for f in files:
            (d / f).write_bytes((folder / f).read_bytes())
        if name == "sizes":
            cv2.imwrite(str(d / "2.png"), np.zeros((20, 30, 3), np.uint8))
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

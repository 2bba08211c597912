"""`match` on photos of any names (course_lib.data.cli_match.find_images), the names kept through `sfm` and `sfm-to-nerf`."""

from __future__ import annotations

import json

import numpy as np
import pytest

from course_lib.__main__ import main
from course_lib.data import building
from course_lib.data.cli_match import find_images, scale_intrinsics
from course_lib.data.colmap import read_colmap_text
from course_lib.data.p3 import SOURCE_NAMES_FILE, read_p3
from course_lib.validate import KitInputError


def _touch(folder, names):
    """Empty files (find_images reads names only)."""
    for n in names:
        p = folder / n
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(b"")
    return folder


@pytest.mark.parametrize("files, order, ignored", [
    # numbered from 0 (video frames, many data sets)
    (["0002.jpg", "0000.jpg", "0010.jpg", "0001.jpg"], ["0000.jpg", "0001.jpg", "0002.jpg", "0010.jpg"], []),
    # numbered from 1 with gaps; an image without a number beside them is ignored (and named)
    (["3.png", "1.png", "10.png", "thumb.jpg", "matching1.txt"], ["1.png", "3.png", "10.png"], ["thumb.jpg"]),
    # a course P3 folder: as it is
    (["2.png", "1.png", "3.png", "calibration.txt", "matching1.txt"], ["1.png", "2.png", "3.png"], []),
    # prefixes, natural order (2 before 10)
    (["frame_0010.png", "frame_0002.png", "frame_0001.png"], ["frame_0001.png", "frame_0002.png", "frame_0010.png"], []),
    (["IMG_1234.JPG", "IMG_998.JPG", "IMG_1300.JPG"], ["IMG_998.JPG", "IMG_1234.JPG", "IMG_1300.JPG"], []),
    # mixed case of names and suffixes
    (["img_2.PNG", "IMG_10.jpg", "Img_1.JpEg", "IMG_3.TIFF"], ["Img_1.JpEg", "img_2.PNG", "IMG_3.TIFF", "IMG_10.jpg"], []),
])
def test_order_and_names(tmp_path, files, order, ignored):
    found = find_images(_touch(tmp_path, files))
    assert found.names == order
    assert [p.name for p in found.paths] == order
    assert found.ignored == ignored


def test_subfolders_when_asked(tmp_path):
    _touch(tmp_path, ["b/IMG_1.jpg", "a/IMG_10.jpg", "a/IMG_2.jpg", "top.png", ".hidden/x.png", "out/1.png"])
    found = find_images(tmp_path, recursive=True, exclude=tmp_path / "out")
    assert found.names == ["a/IMG_2.jpg", "a/IMG_10.jpg", "b/IMG_1.jpg", "top.png"]
    with pytest.raises(KitInputError, match=r"subfolders hold 4 image\(s\) \(a, b, out\): pass --recursive"):
        find_images(_touch(tmp_path / "only_sub", ["a/IMG_1.jpg", "a/IMG_2.jpg", "b/c.png", "out/1.png"]))


@pytest.mark.parametrize("files, message", [
    (["1.png", "1.jpg", "2.png"], r"image number\(s\) occur in two files \(1.jpg, 1.png\).*keep one file per number"),
    (["01.png", "1.png", "2.png"], r"\(01.png, 1.png\)"),
    (["IMG_1.HEIC", "IMG_2.heic", "IMG_3.jpg"], r"holds 1 image\(s\).*: IMG_3.jpg; matching needs at least 2.*2 .heic file\(s\) "
                                                r"\(HEIC/HEIF \(iPhone\): export or convert them to JPEG\)"),
    (["notes.txt"], r"holds 0 image\(s\)"),
])
def test_refusals_say_what_is_wrong_and_what_to_do(tmp_path, files, message):
    with pytest.raises(KitInputError, match=message):
        find_images(_touch(tmp_path, files))


def test_missing_folder(tmp_path):
    with pytest.raises(KitInputError, match="image folder not found"):
        find_images(tmp_path / "nope")


@pytest.fixture(scope="module")
def named_photos(tmp_path_factory):
    """4 renders of the building (320x240) under camera-style names in two subfolders, with their true K."""
    import cv2

    folder = tmp_path_factory.mktemp("named")
    surfaces = building.build_scene(np.random.default_rng(3), ground="large", rho=40.0)
    R_cw, t_cw = building.sfm_cameras(np.random.default_rng(1), 4)
    K = scale_intrinsics(building.WPI_LIKE_K.copy(), building.SFM_IMAGE_SIZE, (320, 240))
    names = ["day1/IMG_0998.JPG", "day1/IMG_1002.jpg", "day2/img_7.png", "day2/IMG_10.PNG"]
    for i, n in enumerate(names):
        rgb, _ = building.render(surfaces, K, R_cw[i], t_cw[i], (320, 240), supersample=1)
        (folder / n).parent.mkdir(exist_ok=True)
        cv2.imwrite(str(folder / n), np.round(rgb[:, :, ::-1] * 255).astype(np.uint8))
    np.savetxt(folder / "calibration.txt", K)
    return folder, names


def test_names_are_kept_through_sfm_and_sfm_to_nerf(named_photos, tmp_path, capsys):
    folder, names = named_photos
    p3 = tmp_path / "p3"
    assert main(["match", str(folder), "--recursive", "--K", str(folder / "calibration.txt"), "--out", str(p3), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "read 4 photos: all images in the folder and its subfolders, in natural name order (day1/IMG_0998.JPG ... day2/IMG_10.PNG)" in out
    order = ["day1/IMG_0998.JPG", "day1/IMG_1002.jpg", "day2/img_7.png", "day2/IMG_10.PNG"]
    d = read_p3(p3)
    assert d.image_names == ["1.jpg", "2.jpg", "3.png", "4.png"] and d.photo_names == order
    assert [r["source"] for r in json.loads((p3 / SOURCE_NAMES_FILE).read_text())] == order

    assert main(["sfm", str(p3), "--out", str(tmp_path / "sfm"), "--quiet"]) == 0
    model = read_colmap_text(tmp_path / "sfm" / "colmap")
    assert sorted(model.image_names) == sorted(order)
    report = json.loads((tmp_path / "sfm" / "report.json").read_text())
    assert sorted(report["final"]["registered"]) == sorted(order)
    assert set(report["initial_pair"]["names"]) <= set(order)
    html = (tmp_path / "sfm" / "scene.html").read_text()
    assert all(n.replace("/", "\\u002f") in html for n in order)  # plotly's JSON escapes "/"
    # sfm-to-nerf finds the photos in the P3 folder under their P3 names
    assert main(["sfm-to-nerf", str(tmp_path / "sfm"), "--images", str(p3), "--out", str(tmp_path / "nerf"), "--size", "32",
                 "--test-every", "0"]) == 0
    frames = json.loads((tmp_path / "nerf" / "transforms_train.json").read_text())["frames"]
    assert sorted(f["file_path"] for f in frames) == sorted(f"./images/r_{n.rsplit('.', 1)[0].replace('/', '_')}" for n in order)


def test_source_names_file_must_list_the_images(named_photos, tmp_path):
    folder, _ = named_photos
    p3 = tmp_path / "p3"
    main(["match", str(folder / "day1"), "--K", str(folder / "calibration.txt"), "--out", str(p3), "--quiet", "--no-verify"])
    assert read_p3(p3).photo_names == ["IMG_0998.JPG", "IMG_1002.jpg"]
    (p3 / SOURCE_NAMES_FILE).write_text(json.dumps([{"p3_name": "1.jpg", "source": "a.jpg"}]))
    with pytest.raises(KitInputError, match=r"names 1 images but the folder has 2 \(2.jpg not among them\): delete source_names.json"):
        read_p3(p3)

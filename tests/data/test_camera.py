"""Cameras without a calibration file (course_lib.data.camera): EXIF, the guess, SIMPLE_RADIAL."""

import io

import numpy as np
import pytest

from course_lib.data.camera import (
    DIAGONAL_35MM,
    FOCAL_GUESS_FACTOR,
    CameraPrior,
    camera_prior,
    distort,
    distort_pixels,
    exif_focal_px,
    read_camera,
    undistort,
    undistort_image,
    undistort_pixels,
    write_camera,
)
from course_lib.validate import KitInputError


def _jpeg(path, size=(640, 480), exif=None):
    from PIL import Image

    ex = Image.Exif()
    sub = ex.get_ifd(0x8769)
    for tag, val in (exif or {}).items():
        (sub if tag >= 0x8000 else ex)[tag] = val
    img = Image.fromarray(np.random.default_rng(0).integers(0, 255, (size[1], size[0], 3), dtype=np.uint8))
    buf = io.BytesIO()
    img.save(buf, "JPEG", exif=ex.tobytes())
    path.write_bytes(buf.getvalue())
    return path


class TestExif:
    def test_focal_length_and_sensor_resolution(self, tmp_path):
        # a 4.8 mm wide sensor imaged at 4000 px (833.33 px/mm), 4.25 mm lens; the photo downsized to 640 px
        p = _jpeg(tmp_path / "a.jpg", exif={0x010F: "Maker", 0x0110: "Phone", 0x920A: (425, 100), 0xA20E: (4000 * 10, 48),
                                            0xA210: 4, 0xA002: 4000, 0xA003: 3000})
        f, how, cam = exif_focal_px(p, (640, 480))
        assert f == pytest.approx(4.25 * 4000 / 4.8 * 640 / 4000) and "FocalPlaneXResolution" in how and cam == "Maker Phone"

    def test_35mm_equivalent_over_the_diagonal(self, tmp_path):
        p = _jpeg(tmp_path / "b.jpg", exif={0xA405: 28})
        f, how, _ = exif_focal_px(p, (640, 480))
        assert f == pytest.approx(28 / DIAGONAL_35MM * 800.0) and "FocalLengthIn35mmFilm 28" in how

    def test_no_exif(self, tmp_path):
        assert exif_focal_px(_jpeg(tmp_path / "c.jpg"), (640, 480))[0] is None
        assert exif_focal_px(tmp_path / "missing.jpg", (640, 480))[0] is None


def test_camera_prior_from_exif_or_the_guess_and_one_zoom_only(tmp_path):
    a = [_jpeg(tmp_path / f"{k}.jpg", exif={0xA405: 28}) for k in range(3)]
    prior = camera_prior(a + [_jpeg(tmp_path / "noexif.jpg")], (640, 480))
    assert prior.model == "SIMPLE_RADIAL" and prior.refine
    assert prior.K[0, 0] == pytest.approx(28 / DIAGONAL_35MM * 800) and "3 of 4 photos" in prior.source
    np.testing.assert_allclose(prior.K[:2, 2], [319.5, 239.5])
    guess = camera_prior([_jpeg(tmp_path / "g.jpg")], (640, 480))
    assert guess.K[0, 0] == FOCAL_GUESS_FACTOR * 640 and guess.source.startswith("guess")
    with pytest.raises(KitInputError, match="several cameras or zoom settings"):
        camera_prior(a + [_jpeg(tmp_path / "tele.jpg", exif={0xA405: 77})], (640, 480))


def test_the_camera_file_round_trip(tmp_path):
    prior = CameraPrior(np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]), "SIMPLE_RADIAL", 0.0, "guess", True, "X")
    write_camera(tmp_path, prior)
    back = read_camera(tmp_path)
    np.testing.assert_allclose(back.K, prior.K)
    assert (back.model, back.refine, back.camera) == ("SIMPLE_RADIAL", True, "X")
    assert read_camera(tmp_path / "none") is None
    (tmp_path / "camera.json").write_text('{"model": "OPENCV", "K": [[1,0,0],[0,1,0],[0,0,1]]}')
    with pytest.raises(KitInputError, match="PINHOLE and SIMPLE_RADIAL"):
        read_camera(tmp_path)


def test_simple_radial_distortion_and_its_inverse():
    rng = np.random.default_rng(0)
    x = rng.uniform(-0.6, 0.6, (100, 2))
    for k1 in (-0.1, 0.0, 0.08):
        np.testing.assert_allclose(undistort(distort(x, k1), k1), x, atol=1e-10)
    np.testing.assert_allclose(distort(np.array([[0.5, 0.0]]), -0.1), [[0.5 * (1 - 0.1 * 0.25), 0.0]])
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    uv = rng.uniform(0, 640, (50, 2))
    np.testing.assert_allclose(undistort_pixels(distort_pixels(uv, K, -0.05), K, -0.05), uv, atol=1e-8)
    nan = np.array([[np.nan, np.nan]])
    assert np.isnan(undistort_pixels(nan, K, -0.05)).all()


def test_undistort_image_moves_a_dot_where_the_pinhole_sees_it():
    K = np.array([[300.0, 0, 159.5], [0, 300, 119.5], [0, 0, 1]])
    img = np.zeros((240, 320), np.float32)
    d = distort_pixels(np.array([[280.0, 200.0]]), K, -0.1)[0]  # a pinhole pixel seen by the distorted camera at d
    img[int(round(d[1])) - 1:int(round(d[1])) + 2, int(round(d[0])) - 1:int(round(d[0])) + 2] = 1.0
    out = undistort_image(img, K, -0.1)
    v, u = np.unravel_index(np.argmax(out), out.shape)
    assert abs(u - 280) <= 1.5 and abs(v - 200) <= 1.5
    np.testing.assert_array_equal(undistort_image(img, K, 0.0), img)

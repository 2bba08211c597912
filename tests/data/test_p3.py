"""Tests of the P3 matching-format reader and writer (course_lib.data.p3)."""

from __future__ import annotations

import numpy as np
import pytest

from course_lib.data.p3 import read_calibration, read_p3, write_p3
from course_lib.paths import course_data
from course_lib.validate import KitInputError

WPI = course_data("wpi")
UPENN = course_data("upenn")

# SOURCES.md: unique correspondences per pair (1-based ids)
WPI_UNIQUE = {(1, 2): 636, (1, 3): 299, (1, 4): 339, (1, 5): 202, (2, 3): 505,
              (2, 4): 556, (2, 5): 290, (3, 4): 1102, (3, 5): 621, (4, 5): 570}
UPENN_UNIQUE = {(1, 2): 1319, (1, 3): 572, (1, 4): 443, (2, 3): 1704, (2, 4): 827, (3, 4): 1609,
                (3, 5): 916, (3, 6): 429, (4, 5): 1640, (4, 6): 890, (5, 6): 1290}

K_TEXT = "500 0 320\n0 500 240\n0 0 1\n"


def make_folder(tmp_path, files: dict[str, str], calib: str | None = K_TEXT, crlf: bool = False):
    """A P3 folder with the given matching files (name -> text) and no images."""
    for name, text in files.items():
        if crlf:
            text = text.replace("\n", "\r\n")
        (tmp_path / name).write_bytes(text.encode())
    if calib is not None:
        (tmp_path / "calibration.txt").write_bytes(calib.encode())
    return tmp_path


def check_consistent(d):
    """Every track id of a correspondence points to a track with exactly those pixels."""
    for (i, j), pm in d.matches.items():
        m = pm.track_ids >= 0
        np.testing.assert_allclose(d.track_uv[pm.track_ids[m], i], pm.x1[m])
        np.testing.assert_allclose(d.track_uv[pm.track_ids[m], j], pm.x2[m])


# ---------------------------------------------------------------- real data


@pytest.mark.skipif(WPI is None, reason="WPI course data not present (set COURSE_DATA or ../shared/data)")
def test_wpi_counts_and_K():
    d = read_p3(WPI)
    assert d.image_names == [f"{i}.png" for i in range(1, 6)]
    assert d.n_images == 5
    got = {(i + 1, j + 1): len(pm) for (i, j), pm in d.matches.items()}
    assert got == WPI_UNIQUE
    np.testing.assert_allclose(d.K, [[531.122155322710, 0, 407.192550839899],
                                     [0, 531.541737503901, 313.308715048366], [0, 0, 1]])
    assert d.image_size == (800, 600)
    img = d.image(0)
    assert img.shape == (600, 800, 3) and img.dtype == np.uint8
    assert d.track_uv.shape[1:] == (5, 2) and d.track_rgb.shape == (d.n_tracks, 3)
    assert d.stats["duplicate_correspondences"] == sum(
        r - u for r, u in zip([672, 308, 352, 206, 533, 585, 301, 1183, 656, 597], WPI_UNIQUE.values()))
    check_consistent(d)
    # every track has at most one observation per image and at least two in all
    assert ((~np.isnan(d.track_uv[..., 0])).sum(1) >= 2).all()


@pytest.mark.skipif(UPENN is None, reason="UPenn course data not present (set COURSE_DATA or ../shared/data)")
def test_upenn_counts_and_K():
    d = read_p3(UPENN)
    assert d.image_names == [f"{i}.jpg" for i in range(1, 7)]
    got = {(i + 1, j + 1): len(pm) for (i, j), pm in d.matches.items()}
    assert got == UPENN_UNIQUE
    for i, j in [(1, 5), (1, 6), (2, 5), (2, 6)]:
        assert (i - 1, j - 1) not in d.matches
        assert len(d.pair(i - 1, j - 1)) == 0
    np.testing.assert_allclose(d.K, [[568.996140852, 0, 643.21055941], [0, 568.988362396, 477.982801038], [0, 0, 1]])
    assert d.stats["rows"] == 2002 + 2261 + 2412 + 2291 + 1365
    check_consistent(d)


# ---------------------------------------------------------------- calibration


@pytest.mark.parametrize("text", [
    "531.1 0 407.2\r\n0 531.5 313.3\r\n0 0 1",  # WPI: CRLF, no final newline
    "K = [531.1 0 407.2;\r\n     0 531.5 313.3;\r\n     0 0 1]",  # UPenn: MATLAB syntax
    "K = [531.1 0 407.2; 0 531.5 313.3; 0 0 1]\n",
    "531.1, 0, 407.2\n0, 531.5, 313.3\n0, 0, 1\n",
])
def test_calibration_formats(tmp_path, text):
    p = tmp_path / "calibration.txt"
    p.write_bytes(text.encode())
    np.testing.assert_allclose(read_calibration(p), [[531.1, 0, 407.2], [0, 531.5, 313.3], [0, 0, 1]])
    np.testing.assert_allclose(read_calibration(tmp_path), read_calibration(p))


@pytest.mark.parametrize("text, words", [
    ("1 0 2\n0 1 3\n", "found 6 numbers"),
    ("1 0 2\n0 1 x\n0 0 1", "'x'"),
    ("0 0 2\n0 0 3\n0 0 1", "not invertible"),
    ("1 0 nan\n0 1 3\n0 0 1", "NaN"),
])
def test_calibration_malformed(tmp_path, text, words):
    p = tmp_path / "calibration.txt"
    p.write_text(text)
    with pytest.raises(KitInputError, match="calibration.txt") as e:
        read_calibration(p)
    assert words in str(e.value)


def test_calibration_missing(tmp_path):
    with pytest.raises(KitInputError, match="calibration file not found"):
        read_calibration(tmp_path / "calibration.txt")


# ---------------------------------------------------------------- quirks of the matching files


def test_crlf_trailing_spaces_header_not_row_count(tmp_path):
    m1 = ("nFeatures: 3930\n"  # WPI: number of detected features, not of rows
          "2 255 0 0 10.5 20.5 2 11.5 21.5 \n"
          "\n"
          "3 0 255 0 30 40 2 31 41 3 32 42 \n")
    m2 = "nFeatures: 1\n2 0 0 255 31 41 3 33 43 "  # no final newline; same feature 31,41 as above
    d = read_p3(make_folder(tmp_path, {"matching1.txt": m1, "matching2.txt": m2}, crlf=True), require_images=False)
    assert d.n_images == 3 and d.image_names == ["1.png", "2.png", "3.png"]
    assert {k: len(v) for k, v in d.matches.items()} == {(0, 1): 2, (0, 2): 1, (1, 2): 1}
    np.testing.assert_allclose(d.matches[(0, 1)].x1, [[10.5, 20.5], [30, 40]])
    np.testing.assert_allclose(d.matches[(0, 1)].x2, [[11.5, 21.5], [31, 41]])
    assert d.matches[(0, 1)].rgb.tolist() == [[255, 0, 0], [0, 255, 0]]
    # two tracks: {1:(10.5,20.5), 2:(11.5,21.5)} and {1:(30,40), 2:(31,41), 3:(32,42)}
    # the row of matching2 says (31,41) in 2 <-> (33,43) in 3, conflicting with (32,42): see below
    assert d.stats["rows"] == 3


def test_tracks_joined_across_files(tmp_path):
    m1 = "nFeatures: 1\n2 10 20 30 1 2 2 3 4 \n"
    m2 = "nFeatures: 1\n2 40 50 60 3 4 3 5 6 \n"
    d = read_p3(make_folder(tmp_path, {"matching1.txt": m1, "matching2.txt": m2}), require_images=False)
    assert d.n_tracks == 1
    np.testing.assert_allclose(d.track_uv[0], [[1, 2], [3, 4], [5, 6]])
    assert d.track_rgb[0].tolist() == [10, 20, 30]  # colour of the row of the first image
    assert d.matches[(0, 1)].track_ids.tolist() == [0]
    assert d.matches[(1, 2)].track_ids.tolist() == [0]
    assert (0, 2) not in d.matches


def test_duplicates_and_same_feature_on_several_rows(tmp_path):
    m1 = ("nFeatures: 4\n"
          "3 1 2 3 10 10 2 11 11 3 12 12 \n"
          "2 1 2 3 10 10 3 12 12 \n"  # duplicate of (1,3) from the row above (UPenn style)
          "2 1 2 3 10 10 2 11 11 \n"  # duplicate of (1,2)
          "2 9 9 9 50 50 3 52 52 \n")
    d = read_p3(make_folder(tmp_path, {"matching1.txt": m1}), require_images=False)
    assert {k: len(v) for k, v in d.matches.items()} == {(0, 1): 1, (0, 2): 2}
    assert d.stats["duplicate_correspondences"] == 2 and d.stats["unique_correspondences"] == 3
    assert d.n_tracks == 2
    np.testing.assert_allclose(d.track_uv[0], [[10, 10], [11, 11], [12, 12]])
    check_consistent(d)


def test_inconsistent_component_rule(tmp_path):
    # feature A=(10,10) of image 1 matched to B=(11,11) and to B'=(90,90) in image 2 (WPI-style
    # one-to-many); B is also matched to C=(12,12) in image 3, so B has 2 correspondences, B' only 1.
    m1 = ("nFeatures: 2\n"
          "3 1 2 3 10 10 2 11 11 3 12 12 \n"
          "2 1 2 3 10 10 2 90 90 \n")
    m2 = "nFeatures: 1\n2 4 5 6 11 11 3 12 12 \n"
    d = read_p3(make_folder(tmp_path, {"matching1.txt": m1, "matching2.txt": m2}), require_images=False)
    assert d.stats["inconsistent_components"] == 1 and d.stats["dropped_observations"] == 1
    assert d.n_tracks == 1
    np.testing.assert_allclose(d.track_uv[0], [[10, 10], [11, 11], [12, 12]])
    pm = d.matches[(0, 1)]
    assert len(pm) == 2 and pm.track_ids.tolist() == [0, -1]  # A-B' kept as a match, not in the track
    check_consistent(d)


def test_inconsistent_tie_drops_both(tmp_path):
    m1 = "nFeatures: 2\n2 1 2 3 10 10 2 11 11 \n2 1 2 3 10 10 2 90 90 \n"
    d = read_p3(make_folder(tmp_path, {"matching1.txt": m1}), require_images=False)
    assert d.n_tracks == 0 and d.stats["dropped_observations"] == 3
    assert d.matches[(0, 1)].track_ids.tolist() == [-1, -1]


def test_images_names_and_lazy_loading(tmp_path):
    import cv2

    make_folder(tmp_path, {"matching1.txt": "nFeatures: 1\n2 1 2 3 1 2 2 3 4 \n"})
    img = np.zeros((6, 8, 3), np.uint8)
    img[..., 0] = 200  # red in RGB
    cv2.imwrite(str(tmp_path / "1.jpg"), img[:, :, ::-1])
    with pytest.raises(KitInputError, match=r"2\.png/\.jpg are missing|2\.png/\.jpg.*missing"):
        read_p3(tmp_path)
    d = read_p3(tmp_path, require_images=False)
    assert d.image_names == ["1.jpg", "2.png"]
    with pytest.raises(KitInputError, match="not found"):
        d.image(1)
    cv2.imwrite(str(tmp_path / "2.png"), img[:, :, ::-1])
    d = read_p3(tmp_path)
    assert d.image_size == (8, 6)
    assert d.image(1)[0, 0].tolist() == [200, 0, 0]  # RGB, not BGR


# ---------------------------------------------------------------- malformed input


@pytest.mark.parametrize("m1, words", [
    ("nFeatures: 2\n2 1 2 3 1 2 2 3 4 \n3 1 2 3 1 2 2 3 4 \n",
     "matching1.txt line 3: expected 5 + 3*(k-1) = 11 numbers after k=3, found 8 — is the file truncated?"),
    ("nFeatures: 1\n2 1 2 3 1 2 2 3 4 3 5 6 \n", "line 2: expected 5 + 3*(k-1) = 8 numbers after k=2, found 11"),
    ("nFeatures: 1\n2 1 2 3 nan 2 2 3 4 \n", "line 2: value 'nan' is not finite"),
    ("nFeatures: 1\n2 1 2 3 1 2 2 3 abc \n", "line 2: 'abc' is not a number"),
    ("nFeatures: 1\n2 1 2 3 1 2 0 3 4 \n", "line 2: image id 0 out of range"),
    ("nFeatures: 1\n2 1 2 3 1 2 1 3 4 \n", "line 2: image id 1 matches image 1 with itself"),
    ("nFeatures: 1\n2 1 2 3 1 2 2.5 3 4 \n", "line 2: image id 2.5 is not an integer"),
    ("nFeatures: 1\n0 1 2 3 1 2 \n", "line 2: k = 0"),
    ("nFeatures: 1\n2 1 2 300 1 2 2 3 4 \n", "line 2: colour"),
])
def test_malformed_rows(tmp_path, m1, words):
    make_folder(tmp_path, {"matching1.txt": m1})
    with pytest.raises(KitInputError) as e:
        read_p3(tmp_path, require_images=False)
    assert words in str(e.value)


def test_truncated_row_message_exact(tmp_path):
    rows = ["nFeatures: 60"] + ["2 1 2 3 1 2 3 5 6 "] * 55 + ["3 1 2 3 1 2 3 5 6"]
    make_folder(tmp_path, {"matching2.txt": "\n".join(rows)})
    with pytest.raises(KitInputError) as e:
        read_p3(tmp_path, require_images=False)
    assert str(e.value) == "matching2.txt line 57: expected 5 + 3*(k-1) = 11 numbers after k=3, found 8 — is the file truncated?"


def test_missing_calibration_empty_and_missing_folder(tmp_path):
    with pytest.raises(KitInputError, match="P3 folder not found"):
        read_p3(tmp_path / "nope")
    with pytest.raises(KitInputError, match="no matching.*files"):
        read_p3(tmp_path)
    make_folder(tmp_path, {"matching1.txt": "nFeatures: 1\n2 1 2 3 1 2 2 3 4 \n"}, calib=None)
    with pytest.raises(KitInputError, match="calibration file not found"):
        read_p3(tmp_path)


def test_matching0_is_rejected(tmp_path):
    make_folder(tmp_path, {"matching0.txt": "nFeatures: 1\n2 1 2 3 1 2 2 3 4 \n"})
    with pytest.raises(KitInputError, match="1-based"):
        read_p3(tmp_path, require_images=False)


# ---------------------------------------------------------------- writer


def test_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    T, M = 40, 4
    uv = rng.uniform(0, 100, (T, M, 2)).round(6)
    seen = rng.random((T, M)) < 0.7
    seen[:, :2] |= seen.sum(1, keepdims=True) < 2  # at least two observations
    uv[~seen] = np.nan
    order = np.argsort(seen.argmax(1), kind="stable")  # read_p3 orders tracks by their first image
    uv, seen = uv[order], seen[order]
    rgb = rng.integers(0, 256, (T, 3)).astype(np.uint8)
    K = np.array([[500.0, 0, 320.5], [0, 501.25, 240.125], [0, 0, 1]])
    images = [rng.integers(0, 256, (6, 8, 3)).astype(np.uint8) for _ in range(M)]
    names = [f"{i + 1}.png" for i in range(M)]
    out = write_p3(tmp_path / "p3", names, K, uv, rgb, images=images)
    d = read_p3(out)
    np.testing.assert_allclose(d.K, K)
    assert d.image_names == names and d.n_tracks == T
    np.testing.assert_allclose(d.track_uv, uv, atol=1e-6)
    assert (d.track_rgb == rgb).all()
    assert (d.image(2) == images[2]).all()  # PNG is lossless
    for (i, j), pm in d.matches.items():
        both = seen[:, i] & seen[:, j]
        assert len(pm) == both.sum()
        assert sorted(pm.track_ids.tolist()) == np.flatnonzero(both).tolist()
    # format details: nFeatures = rows, trailing space, LF only
    raw = (out / "matching1.txt").read_bytes()
    assert b"\r" not in raw
    lines = raw.decode().splitlines()
    assert lines[0] == f"nFeatures: {len(lines) - 1}"
    assert all(line.endswith(" ") for line in lines[1:])
    # writing without images: read back with require_images=False
    d2 = read_p3(write_p3(tmp_path / "noimg", names, K, uv, rgb), require_images=False)
    np.testing.assert_allclose(d2.track_uv, uv, atol=1e-6)


def test_writer_rejects_bad_input(tmp_path):
    K = np.eye(3)
    with pytest.raises(KitInputError, match=r"expected \(T, 2, 2\)"):
        write_p3(tmp_path, ["1.png", "2.png"], K, np.zeros((3, 3, 2)), np.zeros((3, 3), np.uint8))
    with pytest.raises(KitInputError, match="P3 folders name image"):
        write_p3(tmp_path, ["a.png", "b.png"], K, np.zeros((3, 2, 2)), np.zeros((3, 3), np.uint8))


def test_tracks_from_pairs_matches_reader_rule():
    from course_lib.data.match_graph import tracks_from_pairs

    pairs = {(0, 1): ([[10, 10], [10, 10]], [[11, 11], [90, 90]]), (1, 2): ([[11, 11]], [[12, 12]])}
    track_uv, ids, stats = tracks_from_pairs(3, pairs)
    np.testing.assert_allclose(track_uv, [[[10, 10], [11, 11], [12, 12]]])
    assert ids[(0, 1)].tolist() == [0, -1] and ids[(1, 2)].tolist() == [0]
    assert stats == {"inconsistent_components": 1, "dropped_observations": 1}
    with pytest.raises(KitInputError, match="not a pair"):
        tracks_from_pairs(2, {(0, 0): ([[1, 1]], [[2, 2]])})


def test_union_find_roots_and_groups():
    from course_lib.data.match_graph import UnionFind

    uf = UnionFind(5)
    assert uf.union(3, 1) and uf.union(1, 4)
    assert uf.find(4) == uf.find(3) == 1  # the root is the smallest node
    assert uf.find(2) == 2 and uf.add() == 5
    g = UnionFind(4, groups=[0, 1, 0, 1])  # nodes of the same group never share a set
    assert g.union(0, 1)
    assert not g.union(1, 2)  # the set {0, 1} already holds group 0
    assert g.union(2, 3) and g.find(3) == 2 and g.find(1) == 0

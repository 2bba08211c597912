"""BAL loader (course_lib.data.bal): a hand-written file, compressed files, bad files, conventions."""

import bz2

import numpy as np
import pytest

from course_lib import conventions
from course_lib.data import bal
from course_lib.paths import course_data
from course_lib.sfm import lm
from course_lib.validate import KitInputError

# 2 cameras, 3 points, 4 observations, written by hand
TINY = """2 3 4
0 0     -3.326500e+02 2.620900e+02
1 0     -1.997600e+02 1.667000e+02
0 1     1.0 2.0
1 2     -5 6e1
0.1
-0.2
0.3
1
2
-3
500
1e-7
-2e-13
0
0
0
0
0
-10
400
0
0
1
2
3
4
5
6
-7
8.5
9
"""


def write(tmp_path, text, name="p.txt"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_tiny_file(tmp_path):
    prob = bal.load_bal(write(tmp_path, TINY))
    assert (prob.n_cameras, prob.n_points, prob.n_obs) == (2, 3, 4)
    assert prob.cam_idx.tolist() == [0, 1, 0, 1] and prob.pt_idx.tolist() == [0, 0, 1, 2]
    assert prob.cam_idx.dtype == np.int64
    np.testing.assert_allclose(prob.obs[0], [-332.65, 262.09])
    np.testing.assert_allclose(prob.obs[3], [-5.0, 60.0])
    np.testing.assert_allclose(prob.camera_params[0], [0.1, -0.2, 0.3, 1, 2, -3, 500, 1e-7, -2e-13])
    np.testing.assert_allclose(prob.camera_params[1], [0, 0, 0, 0, 0, -10, 400, 0, 0])
    np.testing.assert_allclose(prob.points, [[1, 2, 3], [4, 5, 6], [-7, 8.5, 9]])
    assert "2 cameras, 3 points, 4 observations" in repr(prob)


@pytest.mark.parametrize("suffix", [".txt.bz2", ".txt"])
def test_write_read_round_trip(tmp_path, suffix):
    prob = bal.load_bal(write(tmp_path, TINY))
    out = bal.write_bal(tmp_path / f"copy{suffix}", prob)
    if suffix.endswith(".bz2"):
        assert out.read_bytes()[:3] == b"BZh"
    again = bal.load_bal(out)
    for name in ("camera_params", "points", "obs"):
        np.testing.assert_allclose(getattr(again, name), getattr(prob, name), rtol=1e-10)
    assert again.cam_idx.tolist() == prob.cam_idx.tolist()


def test_bz2_is_read(tmp_path):
    p = tmp_path / "p.txt.bz2"
    p.write_bytes(bz2.compress(TINY.encode()))
    assert bal.load_bal(p).n_obs == 4


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "no header"),
        ("2 3\n", "no header"),
        ("2 x 4\n" + "0 " * 40, "three integers"),
        ("0 3 4\n", "must be positive"),
        (TINY.rsplit("\n", 3)[0] + "\n", "truncated"),  # the last two point coordinates are missing
        ("\n".join(TINY.split("\n")[:3]) + "\n", "ends in the observations"),
        (TINY + "1 2\n", "more numbers"),
        (TINY.replace("1 2     -5 6e1", "1 2     -5 abc"), "'abc'"),
        (TINY.replace("1 2     -5 6e1", "2 2     -5 6e1"), "names camera 2"),
        (TINY.replace("1 2     -5 6e1", "1 3     -5 6e1"), "names point 3"),
        (TINY.replace("0 1     1.0 2.0", "0.5 1     1.0 2.0"), "non-integer"),
        (TINY.replace("500\n", "nan\n"), "NaN"),
    ],
)
def test_bad_files_fail_clearly(tmp_path, text, message):
    with pytest.raises(KitInputError, match=message):
        bal.load_bal(write(tmp_path, text))


def test_missing_and_damaged_files(tmp_path):
    with pytest.raises(KitInputError, match="not found"):
        bal.load_bal(tmp_path / "nope.txt.bz2")
    p = tmp_path / "cut.txt.bz2"
    p.write_bytes(bz2.compress(TINY.encode() * 50)[:60])
    with pytest.raises(KitInputError, match="damaged or truncated"):
        bal.load_bal(p)
    q = tmp_path / "binary.txt"
    q.write_bytes(b"\xff\xfe\x00binary")
    with pytest.raises(KitInputError, match="non-text"):
        bal.load_bal(q)


def test_opencv_conversion_matches_the_kit_projection():
    """With k1 = k2 = 0, BAL's model is the kit's pinhole after flipping y and z (module docstring)."""
    rng = np.random.default_rng(0)
    cams = np.hstack([rng.normal(0, 0.3, (3, 3)), rng.normal(0, 1, (3, 3)), np.full((3, 1), 700.0), np.zeros((3, 2))])
    cams[:, 5] -= 20.0  # points near the origin are in front (BAL: P.z < 0)
    X = rng.normal(0, 1, (10, 3))
    R_cw, t_cw, fk = bal.bal_to_opencv(cams)
    cx, cy = 320.0, 240.0
    for i in range(3):
        np.testing.assert_allclose(np.linalg.det(R_cw[i]), 1.0)
        K = np.array([[fk[i, 0], 0, cx], [0, fk[i, 0], cy], [0, 0, 1]])
        uv = conventions.project(K, R_cw[i], t_cw[i], X)
        assert (conventions.world_to_camera(R_cw[i], t_cw[i], X)[:, 2] > 0).all()  # in front, z forward
        xy = lm.BALCamera().project(cams, X, np.full(10, i))
        np.testing.assert_allclose(uv, np.stack([cx + xy[:, 0], cy - xy[:, 1]], axis=1), atol=1e-9)


def test_ladybug_loads():
    path = course_data("bal-ladybug")
    if path is None:
        pytest.skip("course data 'bal-ladybug' is not on this machine (set COURSE_DATA)")
    prob = bal.load_bal(path)
    assert (prob.n_cameras, prob.n_points, prob.n_obs) == (49, 7776, 31843)
    r = lm.residuals(lm.BALCamera(), prob.camera_params, prob.points, prob.cam_idx, prob.pt_idx, prob.obs)
    assert 0.5 * (r**2).sum() == pytest.approx(8.5091e5, rel=1e-4)  # the SciPy cookbook's initial cost

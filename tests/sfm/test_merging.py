"""Two models made one (course_lib.sfm.merging): the similarity between their frames, one carried into the other."""

import numpy as np
from scipy.spatial.transform import Rotation

from course_lib.sfm.merging import carry, similarity_ransac


def _similarity(rng):
    return 2.5, Rotation.from_rotvec(rng.normal(0, 0.5, 3)).as_matrix(), rng.normal(0, 3, 3)


def test_the_similarity_is_found_among_wrong_points():
    rng = np.random.default_rng(0)
    s, R, T = _similarity(rng)
    X = rng.uniform(-5, 5, (300, 3))
    Y = s * X @ R.T + T
    wrong = rng.random(300) < 0.4  # look-alike tracks: the two models put these points elsewhere
    Y[wrong] += rng.normal(0, 2.0, (wrong.sum(), 3))

    def agrees(s_, R_, T_, rows):
        return np.linalg.norm(s_ * X[rows] @ R_.T + T_ - Y[rows], axis=1) < 0.05

    (s_, R_, T_), inl = similarity_ransac(X, Y, agrees, np.random.default_rng(1))
    assert np.array_equal(inl, ~wrong)
    assert abs(s_ - s) < 1e-9 and np.allclose(R_, R, atol=1e-9) and np.allclose(T_, T, atol=1e-9)
    nothing = similarity_ransac(X, Y, lambda *a: np.zeros(len(X[a[3]]), bool), np.random.default_rng(1))
    assert nothing is None


def _state(rng, registered, points, M=4, T=6):
    R = np.full((M, 3, 3), np.nan)
    t = np.full((M, 3), np.nan)
    for i in registered:
        R[i] = Rotation.from_rotvec(rng.normal(0, 0.2, 3)).as_matrix()
        t[i] = rng.normal(0, 1, 3)
    X = np.full((T, 3), np.nan)
    X[points] = rng.normal(0, 1, (len(points), 3))
    reg = np.zeros(M, bool)
    reg[registered] = True
    return {"registered": reg, "R": R, "t": t, "X": X, "candidate": rng.random((T, M)) < 0.5, "ref": registered[0]}


def test_carry_brings_what_the_base_lacks_and_keeps_what_it_has():
    """Cameras and points carried by the similarity project the same pixels as before; the base's own stay as they are."""
    rng = np.random.default_rng(2)
    base = _state(rng, [0, 1], [0, 1, 2])
    other = _state(rng, [1, 2, 3], [2, 3, 4])
    s, R, T = _similarity(rng)
    merged, images, points = carry(base, other, s, R, T)
    assert images.tolist() == [2, 3] and points.tolist() == [3, 4] and merged["ref"] == 0
    assert merged["registered"].tolist() == [True, True, True, True]
    np.testing.assert_array_equal(merged["R"][:2], base["R"][:2])
    np.testing.assert_array_equal(merged["X"][:3], base["X"][:3])
    np.testing.assert_array_equal(merged["candidate"][:, 2:], other["candidate"][:, 2:])
    for i in (2, 3):  # the same pixel through the carried camera and point as through the other model's
        for j in (3, 4):
            a = other["R"][i] @ other["X"][j] + other["t"][i]
            b = merged["R"][i] @ merged["X"][j] + merged["t"][i]
            np.testing.assert_allclose(a[:2] / a[2], b[:2] / b[2], atol=1e-9)

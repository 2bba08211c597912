"""Verified tracks (course_lib.sfm.tracks), the feature-swap scene generator and the camera alignment."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from course_lib.data.synthetic import make_scene, write_scene_p3
from course_lib.alignment import align_cameras, pose_errors
from course_lib.sfm.fundamental import eight_point, eight_point_batch, sampson_distance
from course_lib.sfm.tracks import join_tracks, ransac_every_pair, verified_tracks, verify_pair
from course_lib.validate import KitInputError


def _p(*xy):
    return np.array(xy, float).reshape(-1, 2)


def test_join_tracks_chains_matches_across_pairs():
    # feature a of image 0 -- b of image 1 -- c of image 2: one track of three observations
    edges = [(0, 1, _p(10, 10), _p(20, 20), None), (1, 2, _p(20, 20), _p(30, 30), None)]
    tr = join_tracks(3, edges)
    assert tr.uv.shape == (1, 3, 2) and tr.stats["refused_edges"] == 0
    np.testing.assert_array_equal(tr.uv[0], [[10, 10], [20, 20], [30, 30]])


def test_join_tracks_splits_at_the_conflicting_link():
    """Two true tracks P = (p0, p1, p2) and Q = (q0, q1, q2), and one wrong match p1 -- q2.

    Raw union-find would make one component with two features in images 1 and 2 (the P3 reader
    then drops the conflicting observations). Joined in order of trust, the wrong link comes last
    and is refused: both tracks come back whole.
    """
    p = [_p(100, 100), _p(110, 100), _p(120, 100)]
    q = [_p(300, 200), _p(310, 200), _p(320, 200)]
    edges = [
        (0, 1, np.vstack([p[0], q[0]]), np.vstack([p[1], q[1]]), np.array([[255, 0, 0], [0, 0, 255]])),
        (1, 2, np.vstack([p[1], q[1]]), np.vstack([p[2], q[2]]), None),
        (0, 2, np.vstack([p[0], q[0]]), np.vstack([p[2], q[2]]), None),
        (1, 2, p[1], q[2], None),  # the wrong match, least trusted
    ]
    tr = join_tracks(3, edges)
    assert tr.stats["refused_edges"] == 1
    assert tr.uv.shape == (2, 3, 2)
    got = sorted(tuple(map(tuple, t)) for t in tr.uv)
    want = sorted(tuple(map(tuple, np.vstack(x))) for x in (p, q))
    assert got == want
    assert {tuple(c) for c in tr.rgb} == {(255, 0, 0), (0, 0, 255)}


def test_join_tracks_split_keeps_both_pieces_of_a_chain():
    # a chain a0 - a1 - b0' where b0' is a second feature of image 0: the last link is refused,
    # and b0' -- b2 still forms its own track
    edges = [(0, 1, _p(1, 1), _p(2, 2), None), (1, 2, _p(2, 2), _p(3, 3), None),
             (0, 2, _p(5, 5), _p(6, 6), None), (2, 0, _p(3, 3), _p(5, 5), None)]
    tr = join_tracks(3, edges)
    assert tr.stats["refused_edges"] == 1 and len(tr.uv) == 2
    assert (np.isfinite(tr.uv[..., 0]).sum(axis=1) == [3, 2]).all()


def test_join_tracks_bad_pair():
    with pytest.raises(KitInputError, match="two different images"):
        join_tracks(2, [(0, 0, _p(1, 1), _p(2, 2), None)])


def test_eight_point_batch_equals_the_textbook_one():
    rng = np.random.default_rng(1)
    x1, x2 = rng.uniform(0, 800, (20, 8, 2)), rng.uniform(0, 600, (20, 8, 2))
    F, ok = eight_point_batch(x1, x2)
    assert ok.all()
    for b in range(20):
        np.testing.assert_allclose(eight_point(x1[b], x2[b]), F[b], atol=1e-9)  # same sign convention too
    x1[3, :, 1] = 2.0 * x1[3, :, 0]  # all on a line: degenerate
    x1[3, :, 0] = x1[3, 0, 0]
    assert not eight_point_batch(x1, x2)[1][3]


def test_verify_pair_finds_the_inliers():
    sc = make_scene(np.random.default_rng(2), n_cameras=3, n_points=300, noise_px=0.5, outlier_fraction=0.25)
    x1, x2, inlier, _ = sc.pair(0, 2)
    v = verify_pair(x1, x2, np.random.default_rng(0), threshold_px=2.0)
    assert v.F is not None and v.n_iters >= 8
    recall = (v.inliers & inlier).sum() / inlier.sum()
    wrong = (v.inliers & ~inlier).sum() / max((~inlier).sum(), 1)
    assert recall > 0.97 and wrong < 0.05, (recall, wrong)
    np.testing.assert_allclose(v.sampson, sampson_distance(v.F, x1, x2), rtol=1e-9)
    few = verify_pair(x1[:7], x2[:7], np.random.default_rng(0))
    assert few.F is None and "at least 8" in few.note


def test_verify_pair_bailout_gives_the_same_answer():
    """The preemptive test only skips models that cannot beat the best: same inliers, same samples."""
    sc = make_scene(np.random.default_rng(8), n_cameras=3, n_points=400, noise_px=1.0, outlier_fraction=0.3)
    for i, j in ((0, 1), (0, 2), (1, 2)):
        x1, x2, _, _ = sc.pair(i, j)
        off = verify_pair(x1, x2, np.random.default_rng(0), threshold_px=2.0, bailout=0)
        on = verify_pair(x1, x2, np.random.default_rng(0), threshold_px=2.0, bailout=64)
        assert on.n_iters == off.n_iters
        np.testing.assert_array_equal(on.inliers, off.inliers)
        np.testing.assert_array_equal(on.F, off.F)


def test_swap_outliers_are_real_features_of_other_points():
    sc = make_scene(np.random.default_rng(8), n_cameras=4, n_points=100, outlier_fraction=0.2, outlier_kind="swap")
    good = sc.visible & ~sc.outlier
    assert sc.outlier.any()
    for j, i in zip(*np.nonzero(sc.outlier)):
        donors = np.flatnonzero(good[:, i] & (np.abs(sc.uv[:, i] - sc.uv[j, i]).max(axis=1) == 0))
        assert len(donors) and j not in donors
    with pytest.raises(ValueError, match="outlier_kind"):
        make_scene(np.random.default_rng(0), outlier_kind="wrong")


def test_verified_tracks_of_a_feature_swap_scene(tmp_path):
    sc = make_scene(np.random.default_rng(8), n_cameras=8, n_points=400, noise_px=1.0, outlier_fraction=0.3, outlier_kind="swap")
    data, keep = write_scene_p3(sc, tmp_path)
    assert data.n_tracks < 10  # the raw tracks chain everything together
    tr = verified_tracks(data, ransac_every_pair(data.matches, np.random.default_rng(0), 2.0))
    assert 0.9 * keep.sum() <= len(tr.uv) <= 1.1 * keep.sum()
    assert tr.stats["refused_edges"] > 0
    # every track holds at most one feature per image by construction; most observations are correct
    good = sc.visible & ~sc.outlier
    correct = 0
    n_obs = int(np.isfinite(tr.uv[..., 0]).sum())
    for t in range(len(tr.uv)):
        owners = [np.flatnonzero(good[:, i] & (np.abs(sc.uv[:, i] - tr.uv[t, i]).max(axis=1) < 1e-5)) for i in
                  np.flatnonzero(np.isfinite(tr.uv[t, :, 0]))]
        ids = [o[0] for o in owners if len(o)]
        if ids:
            correct += np.bincount(ids).max()
    assert correct >= 0.95 * n_obs, (correct, n_obs)


def test_align_cameras_recovers_a_similarity_of_a_collinear_path():
    from scipy.spatial.transform import Rotation

    sc = make_scene(np.random.default_rng(0), n_cameras=6)
    R_cw, t_cw = sc.R_cw.copy(), sc.t_cw.copy()
    C = np.stack([-R.T @ t for R, t in zip(R_cw, t_cw)])
    C[:, 1:] = C[0, 1:]  # all centres on one line: a centre-only alignment is undetermined
    t_cw = np.stack([-R @ c for R, c in zip(R_cw, C)])
    Ra = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    s, ta = 2.5, np.array([1.0, 2.0, 3.0])
    R2 = R_cw @ Ra.T  # world' = s Ra X + ta
    t2 = np.stack([s * t - R @ ta for R, t in zip(R2, t_cw)])
    s_, R_, t_ = align_cameras(R2, t2, R_cw, t_cw)
    np.testing.assert_allclose(R_, Ra.T, atol=1e-9)
    np.testing.assert_allclose(s_, 1 / s, rtol=1e-9)
    pe = pose_errors(R2, t2, R_cw, t_cw)
    assert pe.rotation_deg.max() < 1e-5 and pe.center.max() < 1e-9


# --- the calibrated check: pairs of look-alike texture that only F fits ---------------------------------------


def _fundamental(K1, K2, R, t):
    """``F = K2⁻ᵀ [t]ₓ R K1⁻¹`` (unit norm)."""
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.linalg.inv(K2).T @ tx @ R @ np.linalg.inv(K1)
    return F / np.linalg.norm(F)


def _look_alike_matches(x1, x2, F, rng, px=1.0):
    """Wrong matches between two images' real features ``x1 (N1, 2)``, ``x2 (N2, 2)``: each feature of image 1 paired
    with an unused feature of image 2 within ``px`` of its epipolar line of ``F`` (as repeated texture slides along
    the lines of the F that RANSAC finds): ``(rows of x1, rows of x2)``."""
    from course_lib.data.two_view import epipolar_distances

    used, a, b = set(), [], []
    for k in rng.permutation(len(x1)):
        d = epipolar_distances(F, np.repeat(x1[k:k + 1], len(x2), axis=0), x2)
        for m in np.flatnonzero(d < px):
            if m not in used:
                used.add(m)
                a.append(k)
                b.append(m)
                break
    return np.array(a, int), np.array(b, int)


def look_alike_ring(tmp_path, seed=0, n_cameras=12):
    """A ring of views around an object whose opposite sides look alike: the P3 folder as ``match`` writes it.

    The right pairs (neighbours on the ring) carry their true F. Every pair of views more than 120
    degrees apart -- which share no point -- gets the wrong matches of repeated texture: real
    features of both photos that a generic F (not the geometry of two calibrated cameras) pairs
    along its epipolar lines, 30 or more of them, carried as verified. Returns ``(scene, P3Data,
    wrong pairs)``.
    """
    from course_lib.data.p3 import PairMatches
    from course_lib.data.scenes import cylinder_points, observe, ring_cameras
    from course_lib.data.synthetic import WPI_LIKE_K

    rng = np.random.default_rng(seed)
    R, t = ring_cameras(rng, n_cameras)
    X, normal = cylinder_points(rng, 900)
    sc = observe(rng, WPI_LIKE_K, R, t, X, normal, noise_px=0.5, dropout=0.1)
    data, keep = write_scene_p3(sc, tmp_path)
    K = sc.K
    data.two_view = {}
    for (i, j) in data.matches:
        Rij = R[j] @ R[i].T
        data.two_view[(i, j)] = _fundamental(K, K, Rij, t[j] - Rij @ t[i])
    K_other = K.copy()
    K_other[0, 0] *= 1.2
    K_other[1, 1] *= 0.5
    K_other[:2, 2] += (60.0, -40.0)
    wrong = []
    for i in range(n_cameras):
        for j in range(i + 1, n_cameras):
            gap = min(j - i, n_cameras - (j - i)) * 360.0 / n_cameras
            if gap <= 120.0:
                continue
            x1 = sc.uv[keep][:, i][np.isfinite(sc.uv[keep][:, i, 0])]
            x2 = sc.uv[keep][:, j][np.isfinite(sc.uv[keep][:, j, 0])]
            # the F of another camera (other focal lengths in u and v, another centre): no E of the camera's K fits it
            Rw = Rotation.from_rotvec([0.0, np.radians(rng.uniform(-20, 20)), 0.0]).as_matrix()
            Fw = _fundamental(K, K_other, Rw, np.array([*rng.normal(0, 0.3, 2), 1.0]))
            a, b = _look_alike_matches(x1, x2, Fw, rng)
            assert len(a) >= 30, len(a)
            data.matches[(i, j)] = PairMatches(x1[a], x2[b], np.full((len(a), 3), 128, np.uint8), np.full(len(a), -1))
            data.two_view[(i, j)] = Fw
            wrong.append((i, j))
    return sc, data, wrong


def test_calibrated_check_tells_look_alike_pairs_from_right_ones(tmp_path):
    from course_lib.sfm.tracks import calibrated_check

    sc, data, wrong = look_alike_ring(tmp_path)
    right = [k for k in data.matches if k not in wrong and len(data.matches[k]) >= 30]
    for key in right:
        pm = data.matches[key]
        inl, share = calibrated_check(pm.x1, pm.x2, sc.K, 2.0, 0)
        assert share >= 0.95 and inl.shape == (len(pm),), (key, share)
    for key in wrong:
        pm = data.matches[key]
        _, share = calibrated_check(pm.x1, pm.x2, sc.K, 2.0, 0)
        assert share < 0.85, (key, share)
    assert calibrated_check(np.zeros((4, 2)), np.zeros((4, 2)), sc.K, 2.0, 0)[1] == 0.0


def test_look_alike_pairs_give_no_tracks_and_the_ring_is_right(tmp_path):
    """Without the check the look-alike pairs join tracks of opposite sides of the object; with it each is
    named, and the model of the ring has the true poses."""
    from course_lib.sfm.pipeline import run_sfm

    sc, data, wrong = look_alike_ring(tmp_path)
    rec = run_sfm(data, np.random.default_rng(0))
    notes = {tuple(p["pair"]): p.get("note", "") for p in rec.report["pairs"]}
    assert all(notes[k].startswith("the five-point E explains") and "repeated texture" in notes[k] for k in wrong)
    assert "checked by the five-point E" in rec.report["verification"]
    assert rec.n_registered == sc.n_cameras
    r = rec.registered
    assert pose_errors(rec.R_cw[r], rec.t_cw[r], sc.R_cw[r], sc.t_cw[r]).rotation_deg.max() < 0.5
    off = run_sfm(data, np.random.default_rng(0), min_e_f_inlier_ratio=0.0)  # the look-alike pairs feed tracks
    assert sum(1 for p in off.report["pairs"] if tuple(p["pair"]) in wrong and "note" not in p) == len(wrong)

"""The incremental SfM pipeline (course_lib.sfm.pipeline) on a synthetic scene, the embedded scene and the course data.

Targets (measured here, see the module docstring of course_lib.sfm.pipeline):
* embedded scene: all 6 images, rotation error <= 0.1 deg per camera and centre error <= 1 % of
  the scene size after a similarity alignment (course_lib.alignment.pose_errors);
* WPI Unity Hall: 5/5 images, >= 600 points, mean reprojection error <= 0.7 px;
* UPenn Levine Hall: 6/6 images, >= 1400 points, mean reprojection error <= 1.0 px.
The course data tests are skipped (with the reason) where /work/shared/data is absent.
"""

import json

import numpy as np
import pytest

from course_lib.data.building import load_ground_truth
from course_lib.data.p3 import read_p3
from course_lib.data.synthetic import make_scene, write_scene_p3
from course_lib.paths import EMBEDDED_SFM, course_data
from course_lib.alignment import pose_errors
from course_lib.sfm.pipeline import Reconstruction, run_sfm
from course_lib.validate import KitInputError


def _check_consistent(rec: Reconstruction):
    """Properties every reconstruction has: shapes, NaN where unregistered, errors that match."""
    M, T = len(rec.image_names), len(rec.X)
    assert rec.R_cw.shape == (M, 3, 3) and rec.t_cw.shape == (M, 3) and rec.inlier.shape == (T, M)
    assert np.isnan(rec.R_cw[~rec.registered]).all()
    for i in np.flatnonzero(rec.registered):
        np.testing.assert_allclose(rec.R_cw[i] @ rec.R_cw[i].T, np.eye(3), atol=1e-9)
        assert np.linalg.det(rec.R_cw[i]) > 0
    has_X = np.isfinite(rec.X).all(axis=1)
    assert not rec.inlier[~has_X].any() and not rec.inlier[:, ~rec.registered].any()
    assert (rec.inlier[has_X].sum(axis=1) >= 2).all()
    E = rec.reprojection_errors()
    assert np.isfinite(E[rec.inlier]).all() and np.isnan(E[~rec.inlier]).all()
    json.dumps(rec.report)  # JSON-serializable
    f = rec.report["final"]
    assert f["points"] == rec.n_points and f["registered_images"] == rec.n_registered
    assert abs(f["mean_reprojection_error_px"] - np.mean(E[rec.inlier])) < 1e-3


def _wrong_observations(sc, rec) -> tuple[int, int]:
    """(wrong, total) inlier observations of ``rec``: a wrong one is not a correct observation of its track's point.

    The owner of a pixel in image i is the scene point whose correct (not outlier) observation it
    is (the files hold the pixels to 6 decimals); a track's point is the owner of most of its
    inlier observations.
    """
    good = sc.visible & ~sc.outlier
    wrong = total = 0
    for t in np.flatnonzero(np.isfinite(rec.X).all(axis=1)):
        owners = []
        for i in np.flatnonzero(rec.inlier[t]):
            j = np.flatnonzero(good[:, i] & (np.abs(sc.uv[:, i] - rec.track_uv[t, i]).max(axis=1) < 1e-5))
            owners.append(int(j[0]) if len(j) else -1)
        vals, counts = np.unique(owners, return_counts=True)
        major = vals[np.argmax(counts)]
        wrong += sum(o != major or o < 0 for o in owners)
        total += len(owners)
    return wrong, total


def _synthetic_run(tmp_path_factory, **scene):
    sc = make_scene(np.random.default_rng(scene.pop("seed")), n_points=400, **scene)
    data, keep = write_scene_p3(sc, tmp_path_factory.mktemp("p3"))
    return sc, data, run_sfm(data, np.random.default_rng(0))


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    return _synthetic_run(tmp_path_factory, seed=5, n_cameras=5, noise_px=0.5, outlier_fraction=0.1)


def test_synthetic_scene(synthetic):
    sc, data, rec = synthetic
    _check_consistent(rec)
    assert rec.n_registered == 5
    assert rec.image_size == (800, 600) or rec.image_size[0] <= 800  # no images: size from the pixels
    pe = pose_errors(rec.R_cw, rec.t_cw, sc.R_cw, sc.t_cw)
    assert pe.rotation_deg.max() < 0.2, pe.rotation_deg
    assert pe.center.max() < 0.01 * sc.scene_size, pe.center
    # nearly every point comes back (those seen in 2+ images), and outlier observations (random
    # pixels) do not survive, except the rare one that falls by chance near the epipolar line of
    # a two-view track (then the point fits it)
    assert rec.n_points >= 0.95 * (sc.visible.sum(axis=1) >= 2).sum()
    wrong, total = _wrong_observations(sc, rec)
    assert wrong <= 0.01 * total, (wrong, total)
    # the final error is the noise level (0.5 px per coordinate -> ~0.6 px mean distance, less after the fit)
    assert 0.3 < rec.report["final"]["mean_reprojection_error_px"] < 0.7
    stages = rec.report["stages"]
    assert stages[0]["stage"] == "initial pair" and stages[-1]["stage"] == "final"
    assert all("reprojection_after_ba" in s for s in stages if s.get("registered", True))


@pytest.mark.parametrize("n_cameras, fraction, seed", [(8, 0.3, 8), (5, 0.1, 5), (12, 0.2, 12)])
def test_feature_swap_outliers(tmp_path_factory, n_cameras, fraction, seed):
    """Wrong matches that are real features of other points (issue 11: 8 cameras, 30 % failed with
    "x1 has shape (0, 2)" after the raw tracks had merged into one): every image registers."""
    sc, data, rec = _synthetic_run(tmp_path_factory, seed=seed, n_cameras=n_cameras, noise_px=1.0 if n_cameras == 8 else 0.5,
                                   outlier_fraction=fraction, outlier_kind="swap")
    if n_cameras == 8:
        assert data.n_tracks < 10  # the raw tracks of the reader: chained into a handful
    _check_consistent(rec)
    assert rec.n_registered == n_cameras
    assert rec.report["tracks"]["refused_links"] > 0
    assert rec.n_points >= 0.9 * (sc.visible.sum(axis=1) >= 2).sum()
    wrong, total = _wrong_observations(sc, rec)
    assert wrong <= 0.01 * total, (wrong, total)
    pe = pose_errors(rec.R_cw, rec.t_cw, sc.R_cw, sc.t_cw)
    assert pe.rotation_deg.mean() < 0.2, pe.rotation_deg


@pytest.fixture(scope="module")
def embedded():
    data = read_p3(EMBEDDED_SFM)
    return data, run_sfm(data, np.random.default_rng(0))


def test_embedded_scene_matches_the_ground_truth(embedded):
    data, rec = embedded
    _check_consistent(rec)
    K, names, R_true, t_true = load_ground_truth(EMBEDDED_SFM)
    assert names == rec.image_names
    assert rec.n_registered == len(names)
    gt = json.loads((EMBEDDED_SFM / "ground_truth.json").read_text())
    pe = pose_errors(rec.R_cw, rec.t_cw, R_true, t_true)
    assert pe.rotation_deg.max() <= 0.1, pe.rotation_deg
    assert pe.center.max() <= 0.01 * gt["scene_size"], pe.center
    assert rec.report["final"]["mean_reprojection_error_px"] < 0.5


def test_before_bundle_adjustment_and_final_only(embedded):
    data, full = embedded
    none = run_sfm(data, np.random.default_rng(0), bundle_adjustment="none")
    _check_consistent(none)
    assert none.n_registered == full.n_registered
    assert "reprojection_after_ba" not in none.report["stages"][-1]
    final = run_sfm(data, np.random.default_rng(0), bundle_adjustment="final")
    _check_consistent(final)
    assert final.report["final"]["mean_reprojection_error_px"] < none.report["final"]["mean_reprojection_error_px"]


def _course_run(name):
    folder = course_data(name)
    if folder is None:
        pytest.skip(f"course data {name!r} not found (set COURSE_DATA or put it at ../shared/data); target not checked")
    data = read_p3(folder)
    return run_sfm(data, np.random.default_rng(0))


def test_wpi_unity_hall_targets():
    rec = _course_run("wpi")
    _check_consistent(rec)
    f = rec.report["final"]
    assert f["registered_images"] == 5
    assert f["points"] >= 600
    assert f["mean_reprojection_error_px"] <= 0.7


def test_upenn_levine_hall_targets():
    rec = _course_run("upenn")
    _check_consistent(rec)
    f = rec.report["final"]
    assert f["registered_images"] == 6  # images 5 and 6 only come in by PnP
    assert f["points"] >= 1400
    assert f["mean_reprojection_error_px"] <= 1.0
    order = [s["image"] for s in rec.report["stages"] if s["stage"] == "register"]
    assert 4 in order and 5 in order


def test_bad_inputs(embedded):
    data, _ = embedded
    with pytest.raises(KitInputError, match="rng must be"):
        run_sfm(data, 0)
    with pytest.raises(KitInputError, match="bundle_adjustment="):
        run_sfm(data, np.random.default_rng(0), bundle_adjustment="sometimes")
    with pytest.raises(KitInputError, match="has no attribute"):
        run_sfm(object(), np.random.default_rng(0))


# --- degenerate input: named in the report (or in the error), never a traceback -------------------


def _observe(K, R_cw, t_cw, X, seed, noise=0.5, W=800, H=600):
    """A SyntheticScene of given cameras and points (no outliers, every point in view observed)."""
    from course_lib.conventions import project, world_to_camera
    from course_lib.data.synthetic import SyntheticScene

    M = len(R_cw)
    uv = np.full((len(X), M, 2), np.nan)
    for i in range(M):
        x = project(K, R_cw[i], t_cw[i], X)
        z = world_to_camera(R_cw[i], t_cw[i], X)[:, 2]
        ok = (z > 0) & (x[:, 0] >= 0) & (x[:, 0] <= W - 1) & (x[:, 1] >= 0) & (x[:, 1] <= H - 1)
        uv[ok, i] = x[ok]
    noisy = uv + np.random.default_rng(seed).normal(0.0, noise, uv.shape)
    return SyntheticScene(K, R_cw, t_cw, X, noisy, uv, np.zeros(uv.shape[:2], bool), (W, H), noise)


@pytest.fixture(scope="module")
def base_scene():
    return make_scene(np.random.default_rng(3), n_cameras=5, n_points=300, outlier_fraction=0.0)


def _pure_rotation_cameras(sc):
    """The scene's cameras plus a 6th one at the centre of camera 3, turned by 4 degrees."""
    from scipy.spatial.transform import Rotation

    R6 = Rotation.from_euler("y", 4, degrees=True).as_matrix() @ sc.R_cw[2]
    C3 = -sc.R_cw[2].T @ sc.t_cw[2]
    return np.concatenate([sc.R_cw, R6[None]]), np.concatenate([sc.t_cw, (-R6 @ C3)[None]])


def test_pure_rotation_pair_is_named_and_the_rest_reconstructed(base_scene, tmp_path):
    R, t = _pure_rotation_cameras(base_scene)
    data, _ = write_scene_p3(_observe(base_scene.K, R, t, base_scene.X, 4), tmp_path)
    rec = run_sfm(data, np.random.default_rng(0))
    _check_consistent(rec)
    deg = rec.report["degenerate_pairs"]
    assert [(d["names"], d["kind"]) for d in deg] == [(["3.png", "6.png"], "pure rotation")]
    assert sorted(rec.report["initial_pair"]["images"]) != [2, 5]
    assert rec.n_registered == 6  # the turned camera still comes in by PnP
    pe = pose_errors(rec.R_cw, rec.t_cw, R, t)
    assert pe.rotation_deg.max() < 0.2


def test_only_a_pure_rotation_pair_is_a_named_error(base_scene, tmp_path):
    R, t = _pure_rotation_cameras(base_scene)
    data, _ = write_scene_p3(_observe(base_scene.K, R[[2, 5]], t[[2, 5]], base_scene.X, 4), tmp_path)
    with pytest.raises(KitInputError, match=r"1.png-2.png: pure rotation .*different positions"):
        run_sfm(data, np.random.default_rng(0))


def test_planar_scene_is_a_named_error(base_scene, tmp_path):
    X = base_scene.X.copy()
    X[:, 2] = 10.0  # every point on the plane z = 10
    data, _ = write_scene_p3(_observe(base_scene.K, base_scene.R_cw, base_scene.t_cw, X, 4), tmp_path)
    with pytest.raises(KitInputError, match=r"1.png-2.png: planar \(a homography explains"):
        run_sfm(data, np.random.default_rng(0))


def test_a_facade_with_structure_off_it_starts_after_the_other_pairs(base_scene, tmp_path):
    """85 % of the points on one plane (a facade), the rest off it (balconies): every pair is "mostly planar"; the
    five-point pose is not degenerate for a plane and the points off it pick the right one of its two poses."""
    X = base_scene.X.copy()
    on_plane = np.random.default_rng(1).random(len(X)) < 0.85
    X[on_plane, 2] = 10.0
    data, _ = write_scene_p3(_observe(base_scene.K, base_scene.R_cw, base_scene.t_cw, X, 4), tmp_path)
    rec = run_sfm(data, np.random.default_rng(0))
    _check_consistent(rec)
    assert {d["kind"] for d in rec.report["degenerate_pairs"]} == {"mostly planar"}
    assert rec.n_registered == 5
    assert pose_errors(rec.R_cw, rec.t_cw, base_scene.R_cw, base_scene.t_cw).rotation_deg.max() < 0.2


@pytest.mark.parametrize("n_seen, reason", [
    (18, "too few 2D-3D matches: 18 of its features see triangulated points, PnP needs 20"),
    (10, "no verified matches with any other image"),
])
def test_image_with_too_few_matches_is_left_out_by_name(base_scene, tmp_path, n_seen, reason):
    sc = _observe(base_scene.K, base_scene.R_cw, base_scene.t_cw, base_scene.X, 4)
    seen = np.flatnonzero(np.isfinite(sc.uv[:, 4, 0]))
    sc.uv[seen[n_seen:], 4] = np.nan  # image 5 sees only n_seen points
    data, _ = write_scene_p3(sc, tmp_path)
    rec = run_sfm(data, np.random.default_rng(0), structure_less_fallback=False)  # PnP alone
    _check_consistent(rec)
    assert rec.n_registered == 4
    assert [d["name"] for d in rec.report["left_out"]] == ["5.png"]
    assert rec.report["left_out"][0]["reason"].startswith(reason)
    assert rec.report["final"]["left_out"] == {"5.png": rec.report["left_out"][0]["reason"]}


def test_an_image_that_sees_too_few_points_for_pnp_registers_from_its_matches(base_scene, tmp_path):
    """18 points seen by image 5 (PnP needs 20), each also seen by several registered images: its matches with them
    give its pose without 3-D points (COLMAP's structure-less fallback), as right as the others'."""
    sc = _observe(base_scene.K, base_scene.R_cw, base_scene.t_cw, base_scene.X, 4)
    seen = np.flatnonzero(np.isfinite(sc.uv[:, 4, 0]))
    sc.uv[seen[18:], 4] = np.nan
    data, _ = write_scene_p3(sc, tmp_path)
    rec = run_sfm(data, np.random.default_rng(0))
    _check_consistent(rec)
    assert rec.n_registered == 5 and rec.report["left_out"] == []
    (stage,) = [st for st in rec.report["stages"] if st.get("image") == 4 and st.get("registered")]
    assert len(stage["structure_less"]) >= 2 and stage["pnp_inliers"] >= 20
    err = pose_errors(rec.R_cw, rec.t_cw, base_scene.R_cw, base_scene.t_cw).rotation_deg
    assert err[:4].max() < 0.2 and err[4] < 0.5  # 18 points at 0.5 px of noise: 0.24 deg


def test_identical_photos_are_a_named_error(base_scene, tmp_path):
    sc = _observe(base_scene.K, base_scene.R_cw[[2, 2]], base_scene.t_cw[[2, 2]], base_scene.X, 4, noise=0.2)
    data, _ = write_scene_p3(sc, tmp_path)
    with pytest.raises(KitInputError, match=r"1.png-2.png: identical or near-identical photos \(no baseline"):
        run_sfm(data, np.random.default_rng(0))


# --- registration that scales: local BAs between BAs of the whole model ----------------------------


def test_local_bundle_adjustments_between_global_ones(tmp_path):
    sc = make_scene(np.random.default_rng(8), n_cameras=14, n_points=500, noise_px=0.5, outlier_fraction=0.05)
    data, _ = write_scene_p3(sc, tmp_path)
    rec = run_sfm(data, np.random.default_rng(0))
    _check_consistent(rec)
    kinds = [s["ba"]["kind"] for s in rec.report["stages"] if s["stage"] == "register" and s.get("registered")]
    assert rec.n_registered == 14 and kinds[:4] == ["global"] * 4 and "local" in kinds[4:]
    n, last = 6, 6  # a BA of the whole model when it has grown by ba_images_ratio since the last one
    for kind in kinds[4:]:
        n += 1
        assert kind == ("global" if n >= 1.1 * last else "local")
        last = n if kind == "global" else last
    local = next(s["ba"] for s in rec.report["stages"] if s.get("ba", {}).get("kind") == "local")
    assert len(local["images"]) <= 6 and "held fixed" in local["gauge"]
    every = run_sfm(data, np.random.default_rng(0), ba_images_ratio=1.0)
    err = lambda r: pose_errors(r.R_cw, r.t_cw, sc.R_cw, sc.t_cw).rotation_deg.mean()  # noqa: E731
    assert err(rec) < 0.1 and err(rec) <= 1.5 * err(every)


# --- cameras without a calibration file: the focal length and k1 refined ----------------------------


def _uncalibrated(tmp_path, f_factor: float, k1: float, seed: int = 9):
    """A 10-view scene seen by a SIMPLE_RADIAL camera; the P3 folder carries a prior f that is off by f_factor."""
    from course_lib.data.camera import CameraPrior, distort_pixels, write_camera

    sc = make_scene(np.random.default_rng(seed), n_cameras=10, n_points=600, noise_px=0.5, outlier_fraction=0.05)
    K = sc.K.copy()
    K[0, 0] = K[1, 1] = 0.5 * (K[0, 0] + K[1, 1])
    K[0, 1] = 0.0
    sc.K = K
    sc.uv = distort_pixels(sc.uv, K, k1)  # the noise stays where it was: small
    data, _ = write_scene_p3(sc, tmp_path / "p3")
    prior = K.copy()
    prior[0, 0] = prior[1, 1] = f_factor * K[0, 0]
    (tmp_path / "p3" / "calibration.txt").write_text("\n".join(" ".join(map(str, r)) for r in prior))
    write_camera(tmp_path / "p3", CameraPrior(prior, "SIMPLE_RADIAL", 0.0, "test", True))
    return sc, read_p3(tmp_path / "p3", require_images=False)


def test_a_wrong_focal_length_is_refined_to_the_true_one(tmp_path):
    sc, data = _uncalibrated(tmp_path, 1.12, 0.0)
    assert data.camera.refine
    rec = run_sfm(data, np.random.default_rng(0))
    assert rec.camera_model == "SIMPLE_RADIAL" and rec.n_registered == 10
    assert abs(rec.K[0, 0] / sc.K[0, 0] - 1) < 0.01 and abs(rec.k1) < 0.01
    cam = rec.report["camera"]
    assert cam["model"] == "SIMPLE_RADIAL" and cam["prior_focal_px"] == pytest.approx(1.12 * sc.K[0, 0], rel=1e-6)
    assert cam["refinements"] and all(r["accepted"] for r in cam["refinements"])
    err = pose_errors(rec.R_cw, rec.t_cw, sc.R_cw, sc.t_cw).rotation_deg.mean()
    held = run_sfm(data, np.random.default_rng(0), refine_intrinsics=False)  # the wrong f, held: far worse
    (tmp_path / "p3" / "calibration.txt").write_text("\n".join(" ".join(map(str, r)) for r in sc.K))
    true_k = run_sfm(read_p3(tmp_path / "p3", require_images=False), np.random.default_rng(0), refine_intrinsics=False)
    true_k_err = pose_errors(true_k.R_cw, true_k.t_cw, sc.R_cw, sc.t_cw).rotation_deg.mean()
    held_err = pose_errors(held.R_cw, held.t_cw, sc.R_cw, sc.t_cw).rotation_deg.mean()
    assert held.camera_model == "PINHOLE" and held_err > 2 * err
    assert err <= 1.5 * true_k_err, (err, true_k_err)


def test_radial_distortion_is_refined(tmp_path):
    sc, data = _uncalibrated(tmp_path, 0.95, -0.06, seed=10)
    rec = run_sfm(data, np.random.default_rng(0))
    assert rec.n_registered == 10
    assert abs(rec.K[0, 0] / sc.K[0, 0] - 1) < 0.01 and abs(rec.k1 + 0.06) < 0.01
    assert rec.error_stats()["median"] < 0.7
    assert pose_errors(rec.R_cw, rec.t_cw, sc.R_cw, sc.t_cw).rotation_deg.mean() < 0.1
    # the COLMAP text model says SIMPLE_RADIAL and holds the photos' own pixels
    from course_lib.data.colmap import read_colmap_text

    rec.write_colmap(tmp_path / "model")
    back = read_colmap_text(tmp_path / "model")
    assert back.camera_model == "SIMPLE_RADIAL" and back.k1 == pytest.approx(rec.k1)
    np.testing.assert_allclose(back.K, rec.K, atol=1e-9)


def test_the_pipeline_runs_on_functions_that_return_what_their_stubs_document(monkeypatch):
    """The student kit: the mapper and the pair verification call the exercises, which may return tuples
    (the stubs allow a tuple or a dataclass); the embedded scene is reconstructed as with the references."""
    from course_lib import exercises
    from course_lib.sfm import bundle_adjustment, essential, fundamental, initial_pair, pnp, tracks, triangulation

    def as_tuple(fn, *fields):
        def student(*args, **kwargs):
            res = fn(*args, **kwargs)
            return tuple(getattr(res, f) for f in fields)
        return student

    mine = {
        "ransac_fundamental": as_tuple(fundamental.ransac_fundamental, "F", "inliers", "n_iters"),
        "sampson_distance": lambda F, x1, x2: list(fundamental.sampson_distance(F, x1, x2)),
        "eight_point": fundamental.eight_point,
        "essential_from_fundamental": essential.essential_from_fundamental,
        "pose_candidates": essential.pose_candidates,
        "choose_pose": as_tuple(triangulation.choose_pose, "R_cw", "t_cw", "X", "in_front", "counts"),
        "triangulate_linear": triangulation.triangulate_linear,
        "triangulate_nonlinear": triangulation.triangulate_nonlinear,
        "pnp_ransac": as_tuple(pnp.pnp_ransac, "R_cw", "t_cw", "inliers", "n_iters"),
        "pnp_nonlinear": pnp.pnp_nonlinear,
        "reprojection_residuals": bundle_adjustment.reprojection_residuals,
        "jacobian_sparsity": lambda *a: bundle_adjustment.jacobian_sparsity(*a).toarray(),  # a dense pattern is allowed
    }
    for name, fn in mine.items():
        monkeypatch.setitem(exercises._IMPLEMENTATIONS, name, fn)
    monkeypatch.setattr(tracks, "ransac", None)  # the student kit has no batched reference RANSAC
    monkeypatch.setattr(initial_pair, "sampson_distance_batch", None)  # nor notebook 01's batched Sampson distance
    rec = run_sfm(read_p3(EMBEDDED_SFM), np.random.default_rng(0))
    _check_consistent(rec)
    _, names, R_gt, t_gt = load_ground_truth(EMBEDDED_SFM)
    assert rec.registered.all()
    assert pose_errors(rec.R_cw, rec.t_cw, R_gt, t_gt).rotation_deg.max() < 0.1


def test_a_carried_verification_is_refit_by_the_exercises_in_the_student_kit(monkeypatch):
    """``match``'s F carried into the P3 folder: the refit on its inliers by the exercises (student kit) keeps
    the same inliers as the reference's batched refit."""
    from course_lib.sfm import tracks

    data = read_p3(EMBEDDED_SFM)
    pm = data.matches[(0, 1)]
    F = tracks.verify_pair(pm.x1, pm.x2, np.random.default_rng(0), 2.0).F
    ref = tracks.from_carried_geometry(pm.x1, pm.x2, F, 2.0)
    monkeypatch.setattr(tracks, "eight_point_batch", None)
    kit = tracks.from_carried_geometry(pm.x1, pm.x2, F, 2.0)
    assert ref.n_inliers > 50 and np.array_equal(kit.inliers, ref.inliers)
    np.testing.assert_allclose(kit.sampson, ref.sampson, rtol=1e-6, atol=1e-9)

"""The incremental mapper (course_lib.sfm.mapper): its stages, its options, several models, and the hard scenes.

The hard scenes (course_lib.data.scenes) are what students' own photo sets look like: views in
groups with weak links, texture-poor views, near-duplicate (pure-rotation) views. On each, the kit
must not crash, must register at least as many images as COLMAP given the very same matches
(pycolmap, as benchmarks/sfm_vs_colmap.py runs it), with a mean rotation error within 1.2x
COLMAP's (where COLMAP registers three or more images; with two the alignment says nothing).
"""

import importlib.util
import json

import numpy as np
import pytest

from course_lib.__main__ import main
from course_lib.data.scenes import grouped_ring_scene, near_duplicate_scene, texture_poor_ring_scene
from course_lib.data.synthetic import make_scene, write_scene_p3
from course_lib.alignment import pose_errors
from course_lib.paths import REPO_ROOT
from course_lib.sfm.mapper import IncrementalMapper, MapperOptions, spread_score
from course_lib.sfm.pipeline import run_sfm
from course_lib.sfm.tracks import verified_pairs_and_tracks
from course_lib.validate import KitInputError


def _benchmark():
    spec = importlib.util.spec_from_file_location("sfm_vs_colmap", REPO_ROOT / "benchmarks" / "sfm_vs_colmap.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _rotation_error(R_cw, t_cw, registered, sc) -> float:
    r = np.asarray(registered, bool)
    return float(pose_errors(R_cw[r], t_cw[r], sc.R_cw[r], sc.t_cw[r]).rotation_deg.mean())


# --- options and stages ---------------------------------------------------------------------------------


def test_options_by_object_or_keyword_and_unknown_names():
    assert MapperOptions.from_keywords(MapperOptions(min_pnp_inliers=30), max_reproj_px=3.0).min_pnp_inliers == 30
    with pytest.raises(KitInputError, match=r"unknown SfM option\(s\) \['min_inliers'\]"):
        MapperOptions.from_keywords(min_inliers=5)
    with pytest.raises(KitInputError, match="bundle_adjustment="):
        MapperOptions.from_keywords(bundle_adjustment="sometimes")


def test_spread_score_prefers_points_spread_over_the_image():
    rng = np.random.default_rng(0)
    spread = rng.uniform([0, 0], [800, 600], (40, 2))
    corner = rng.uniform([0, 0], [100, 75], (60, 2))
    assert spread_score(spread, (800, 600)) > spread_score(corner, (800, 600))
    assert spread_score(np.zeros((0, 2)), (800, 600)) == 0


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    sc = make_scene(np.random.default_rng(3), n_cameras=5, n_points=300, outlier_fraction=0.05)
    data, _ = write_scene_p3(sc, tmp_path_factory.mktemp("p3"))
    return sc, data


def _mapper(data, **options):
    opts = MapperOptions.from_keywords(**options)
    report = {}
    pairs, tracks = verified_pairs_and_tracks(data, np.random.default_rng(0), opts.f_threshold_px, opts.min_pair_matches, report)
    return IncrementalMapper(data, pairs, tracks.uv, data.K, (800, 600), opts, np.random.default_rng(0)), tracks


def test_stages_by_name_build_the_model(small_scene):
    sc, data = small_scene
    mapper, tracks = _mapper(data)
    first = next(mapper.find_initial_pair())
    assert mapper.initialize(first) and mapper.registered.sum() == 2 and mapper.has_X.sum() >= 20
    while (ranked := mapper.next_images()):
        info, why = mapper.register_next_image(ranked[0][0])
        assert info is not None, why
        assert mapper.triangulate_image(ranked[0][0]) >= 0
        mapper.adjust_bundle("huber", 1.0, 10)
        mapper.filter_points()
    assert mapper.retriangulate()["points_new"] >= 0
    mapper.finish()
    rec = mapper.end_model(tracks.rgb)
    assert rec.n_registered == 5 and mapper.used.all()
    assert _rotation_error(rec.R_cw, rec.t_cw, rec.registered, sc) < 0.2


def test_growth_bundle_adjustments_are_short_and_the_final_one_is_not(small_scene):
    """The BA policy of MapperOptions: at most ba_max_iterations during the growth, final_ba_max_iterations at the end."""
    sc, data = small_scene
    rec = run_sfm(data, np.random.default_rng(0), ba_max_iterations=3, final_ba_max_iterations=1)
    grow = [st["ba"]["iterations"] for st in rec.report["stages"] if st["stage"] != "final" and "ba" in st]
    final = next(st for st in rec.report["stages"] if st["stage"] == "final")
    assert len(grow) == 4 and max(grow) == 3  # the initial pair and 3 registrations, each followed by a BA
    assert final["ba"]["iterations"] == 1
    default = run_sfm(data, np.random.default_rng(0))
    assert default.n_registered == 5 and _rotation_error(default.R_cw, default.t_cw, default.registered, sc) < 0.2


def test_a_pair_that_triangulates_nothing_is_dropped_without_bundle_adjustment(small_scene, monkeypatch):
    """Seed 0 of the issue's ring: the chosen pair kept no point and BA was called on nothing (exit 2)."""
    _, data = small_scene
    mapper, _ = _mapper(data, min_angle_deg=60.0)  # no point of any pair is seen under 60 degrees
    calls = []
    monkeypatch.setattr("course_lib.sfm.mapper_ba.adjust", lambda *a, **k: calls.append(1))
    pair = mapper.score_pair(0, 1)
    assert not mapper.initialize(pair)
    assert calls == [] and not mapper.registered.any()
    assert mapper.failed_starts == {(0, 1): 0}
    assert mapper.adjust_bundle("huber", 1.0, 10) == {"skipped": "no points to adjust"}
    with pytest.raises(KitInputError, match=r"no image pair can start the reconstruction: .* kept fewer than 20 points"):
        run_sfm(data, np.random.default_rng(0), min_angle_deg=60.0)


def test_only_degenerate_pairs_is_one_clear_line_and_exit_2(tmp_path, capsys):
    import cv2

    sc = near_duplicate_scene(np.random.default_rng(0), twins=(2,))
    keep = np.zeros(sc.n_cameras, bool)
    keep[[2, 6]] = True  # a view and its twin, turned on the spot: nothing else
    sc.uv[:, ~keep] = np.nan
    from course_lib.data.synthetic import SyntheticScene

    two = SyntheticScene(sc.K, sc.R_cw[keep], sc.t_cw[keep], sc.X, sc.uv[:, keep], sc.uv_true[:, keep], sc.outlier[:, keep],
                         sc.image_size, sc.noise_px)
    write_scene_p3(two, tmp_path)
    for name in ("1.png", "2.png"):
        cv2.imwrite(str(tmp_path / name), np.full((600, 800, 3), 128, np.uint8))
    assert main(["sfm", str(tmp_path), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "1.png-2.png: pure rotation" in err[0] and "different positions" in err[0]



def test_a_pose_that_explains_a_small_share_of_the_matches_is_refused(small_scene):
    """COLMAP's abs_pose_min_inlier_ratio: a pose that explains only a small share of an image's 2D-3D matches was
    found among look-alike texture. Here 70 right matches among 200 (the rest random pixels): registered at the
    default share (25 %), refused at 50 % with the reason (PnP alone: its matches with the registered images would
    register it without points, register_from_pairs)."""
    _, data = small_scene
    mapper, _ = _mapper(data, structure_less_fallback=False)
    assert mapper.initialize(mapper.score_pair(0, 1))
    for i in (2, 3):
        assert mapper.add_image(i)[0] is not None
    js = np.flatnonzero(mapper.has_X & mapper.candidate[:, 4])
    assert len(js) >= 200
    mapper.candidate[js[200:], 4] = False
    wrong = js[70:200]
    mapper.uv[wrong, 4] = np.random.default_rng(1).uniform([0, 0], [800, 600], (len(wrong), 2))
    state = mapper.state()
    mapper.use_options(MapperOptions.from_keywords(mapper.opts, min_pnp_inlier_ratio=0.5))
    numbers, why = mapper.register_next_image(4)
    assert numbers is None and why.startswith("too small a share of PnP inliers:") and "of 200 2D-3D matches" in why
    assert "need 50%" in why and not mapper.registered[4]
    mapper.use_options(MapperOptions.from_keywords(mapper.opts, min_pnp_inlier_ratio=0.25))
    numbers, why = mapper.register_next_image(4)
    assert why is None and 60 <= numbers["pnp_inliers"] <= 75 and numbers["correspondences"] == 200
    assert (state["candidate"] | ~mapper.candidate).all()  # only the outliers lost their flag


def _grow_from(mapper, a, b, images):
    """A model started from pair (a, b) and grown by ``images`` in that order (each must register)."""
    assert mapper.initialize(mapper.score_pair(a, b))
    for i in images:
        numbers, why = mapper.add_image(i)
        assert numbers is not None, why
    mapper.finish()


@pytest.fixture(scope="module")
def six_views(tmp_path_factory):
    sc = make_scene(np.random.default_rng(5), n_cameras=6, n_points=400, outlier_fraction=0.05)
    data, _ = write_scene_p3(sc, tmp_path_factory.mktemp("p3"))
    return sc, data


def test_a_later_model_that_shares_images_is_merged_into_the_earlier_one(six_views):
    """Two models with their own frames and scales (0, 1, 2, 3 and 4, 5, 3): one similarity on their common points
    carries the smaller (later) one into the larger's frame; all six cameras end up right, the gauge is the larger's."""
    sc, data = six_views
    mapper, _ = _mapper(data)
    _grow_from(mapper, 0, 1, [2, 3])
    earlier = mapper.state()
    mapper.begin_model()
    _grow_from(mapper, 4, 5, [3])
    numbers, why = mapper.merge(earlier)
    assert why is None and numbers["shared_images"] == 1 and numbers["images_added"] == [4, 5]
    assert numbers["inliers"] >= 0.8 * numbers["common_points"] and numbers["ba"]["kind"] == "global"
    assert mapper.registered.all() and mapper.ref == 0
    np.testing.assert_allclose(mapper.R[0], np.eye(3), atol=1e-9)  # the earlier (larger) model's gauge
    assert _rotation_error(mapper.R, mapper.t, mapper.registered, sc) < 0.2
    assert np.nanmedian(mapper.errors()) < 1.0


def test_a_later_model_that_outgrew_the_earlier_one_keeps_its_own_frame(six_views):
    """The later model (4, 5, 3, 2, 1) has grown past the earlier one (0, 1, 2): the earlier one's image 0 comes into
    the later one's frame, and the later model keeps its poses where both have one."""
    sc, data = six_views
    mapper, _ = _mapper(data)
    _grow_from(mapper, 0, 1, [2])
    earlier = mapper.state()
    mapper.begin_model()
    _grow_from(mapper, 4, 5, [3, 2, 1])
    before = mapper.state()
    numbers, why = mapper.merge(earlier)
    assert why is None and numbers["shared_images"] == 2 and numbers["images_added"] == [0]
    assert mapper.registered.all() and mapper.ref == 4
    np.testing.assert_allclose(mapper.R[4], np.eye(3), atol=1e-9)  # the later (larger) model's gauge
    assert _rotation_error(mapper.R, mapper.t, mapper.registered, sc) < 0.2
    assert _rotation_error(before["R"], before["t"], before["registered"], sc) < 0.2


def test_a_model_whose_points_disagree_is_not_merged(six_views):
    _, data = six_views
    mapper, _ = _mapper(data)
    _grow_from(mapper, 0, 1, [2, 3])
    earlier = mapper.state()
    earlier["X"] = earlier["X"][np.random.default_rng(0).permutation(len(earlier["X"]))]  # points on the wrong tracks
    mapper.begin_model()
    _grow_from(mapper, 4, 5, [3, 2])
    before = mapper.state()
    numbers, why = mapper.merge(earlier)
    assert numbers is None and "common points onto the earlier model" in why
    assert (mapper.registered == before["registered"]).all() and np.array_equal(mapper.X, before["X"], equal_nan=True)
    mapper.begin_model()
    numbers, why = mapper.merge(earlier)
    assert numbers is None and why == "0 shared images, need 1"


def test_run_sfm_merges_a_model_that_grows_into_an_earlier_one(six_views, monkeypatch):
    """The controller's side: the first model is stopped at four images (the others fail to register once), the
    second starts from the two images left, grows over the first (six images, the larger) and the first is merged
    into it: one model of six, both reports in it."""
    sc, data = six_views
    real = IncrementalMapper.register_next_image

    def first_model_stops_at_four(self, i):
        if not self.used.any() and self.registered.sum() >= 4:
            return None, "held out by the test"
        return real(self, i)

    monkeypatch.setattr(IncrementalMapper, "register_next_image", first_model_stops_at_four)
    rec = run_sfm(data, np.random.default_rng(0))
    assert rec.n_registered == 6 and rec.others == [] and [m["registered_images"] for m in rec.report["models"]] == [6]
    merges = [st for st in rec.report["stages"] if st["stage"] == "merge"]
    assert len(merges) == 1 and merges[0]["images_added"] == [] and merges[0]["shared_images"] == 4
    assert any(st.get("model") == "merged" and st["stage"] == "initial pair" for st in rec.report["stages"])
    assert rec.report["left_out"] == [] and "merge" in rec.report["seconds"]
    assert _rotation_error(rec.R_cw, rec.t_cw, rec.registered, sc) < 0.2


# --- the hard scenes against COLMAP on the same matches --------------------------------------------------


def _kit_and_colmap(sc, tmp_path):
    pytest.importorskip("pycolmap", reason="pycolmap (environment.txt) is needed for the COLMAP cross-check")
    bench = _benchmark()
    data, _ = write_scene_p3(sc, tmp_path / "p3")
    (tmp_path / "colmap").mkdir()
    col = bench.run_colmap(data, sc.image_size, tmp_path / "colmap")
    rec = run_sfm(data, np.random.default_rng(0))
    _ = json.dumps(rec.report)
    return data, rec, col


def _at_least_colmap(rec, col, sc):
    assert rec.n_registered >= col["registered"].sum(), (rec.n_registered, col["registered"].sum())
    kit_rot = _rotation_error(rec.R_cw, rec.t_cw, rec.registered, sc)
    if col["registered"].sum() >= 3:
        col_rot = _rotation_error(col["R_cw"], col["t_cw"], col["registered"], sc)
        assert kit_rot <= 1.2 * col_rot, (kit_rot, col_rot)
    assert kit_rot < 0.5, kit_rot


def test_grouped_ring_two_models(tmp_path):
    """The issue's ring: 13 well-linked views and 3 weakly linked ones whose pairs are the strongest."""
    sc = grouped_ring_scene(np.random.default_rng(0))
    data, rec, col = _kit_and_colmap(sc, tmp_path)
    _at_least_colmap(rec, col, sc)
    assert rec.n_registered == 13 and [m["registered_images"] for m in rec.report["models"]] == [13, 3]
    (other,) = rec.others
    assert other.report["final"]["registered"] == ["14.png", "15.png", "16.png"]
    assert _rotation_error(other.R_cw, other.t_cw, other.registered, sc) < 0.5
    assert {d["name"]: d["reason"] for d in rec.report["left_out"]}["14.png"].startswith("in model 2 (colmap-1/)")
    assert other.report["left_out"][0]["reason"].startswith("in model 1 (colmap/)")


def test_texture_poor_ring(tmp_path):
    sc = texture_poor_ring_scene(np.random.default_rng(0))
    data, rec, col = _kit_and_colmap(sc, tmp_path)
    _at_least_colmap(rec, col, sc)
    start = rec.report["initial_pair"]
    # texture-poor: the model starts from a pair at (or, relaxed as COLMAP does, under) min_pair_inliers
    assert start.get("relaxed") or start["ransac_inliers"] <= MapperOptions().min_pair_inliers


def test_near_duplicate_views(tmp_path):
    sc = near_duplicate_scene(np.random.default_rng(0))
    data, rec, col = _kit_and_colmap(sc, tmp_path)
    _at_least_colmap(rec, col, sc)
    assert rec.n_registered == sc.n_cameras
    kinds = {tuple(d["names"]): d["kind"] for d in rec.report["degenerate_pairs"]}
    assert kinds == {("2.png", "7.png"): "pure rotation", ("4.png", "8.png"): "pure rotation", ("5.png", "9.png"): "pure rotation"}


def test_cli_writes_every_model(tmp_path, capsys):
    import cv2

    sc = grouped_ring_scene(np.random.default_rng(0))
    write_scene_p3(sc, tmp_path / "p3")
    for i in range(sc.n_cameras):
        cv2.imwrite(str(tmp_path / "p3" / f"{i + 1}.png"), np.full((600, 800, 3), 128, np.uint8))
    out = tmp_path / "out"
    assert main(["sfm", str(tmp_path / "p3"), "--out", str(out), "--quiet"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "13/16 images registered" in lines[0] and lines[0].endswith("2 models: 13 + 3 images")
    assert lines[1].startswith("model 2 (colmap-1/): 3 images (14.png, 15.png, 16.png)")
    report = json.loads((out / "report.json").read_text())
    assert [m["folder"] for m in report["models"]] == ["colmap", "colmap-1"]
    assert report["totals"]["registered_images_all_models"] == 16 and len(report["others"]) == 1
    for folder in ("colmap", "colmap-1"):
        assert (out / folder / "images.txt").is_file()
    assert "model 2 points" in (out / "scene.html").read_text()

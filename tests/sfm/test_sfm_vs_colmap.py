"""The kit's SfM pipeline against COLMAP (pycolmap) on the same P3 matches (benchmarks/sfm_vs_colmap.py).

Speed is measured by the benchmark, not here; this checks that both register the same images and
agree on the cameras, and that the benchmark runs end to end.
"""

import importlib.util

import numpy as np
import pytest

from course_lib.data.synthetic import make_scene, write_scene_p3
from course_lib.paths import REPO_ROOT
from course_lib.alignment import pose_errors

pytest.importorskip("pycolmap", reason="pycolmap (environment.txt) is needed for the COLMAP cross-check")


def _benchmark():
    spec = importlib.util.spec_from_file_location("sfm_vs_colmap", REPO_ROOT / "benchmarks" / "sfm_vs_colmap.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_kit_and_colmap_agree_on_a_feature_swap_scene(tmp_path):
    bench = _benchmark()
    sc = make_scene(np.random.default_rng(5), n_cameras=5, n_points=400, noise_px=0.5, outlier_fraction=0.1, outlier_kind="swap")
    data, _ = write_scene_p3(sc, tmp_path / "p3")
    (tmp_path / "colmap").mkdir()
    col = bench.run_colmap(data, sc.image_size, tmp_path / "colmap")
    kit = bench.run_kit(data)
    assert col["registered"].all() and kit["registered"].all()
    # both close to the truth, and to each other
    for res in (col, kit):
        assert pose_errors(res["R_cw"], res["t_cw"], sc.R_cw, sc.t_cw).rotation_deg.max() < 0.3
    assert pose_errors(kit["R_cw"], kit["t_cw"], col["R_cw"], col["t_cw"]).rotation_deg.max() < 0.3
    assert kit["points"] >= 0.9 * col["points"]


def test_benchmark_runs(capsys, tmp_path):
    bench = _benchmark()
    sc = make_scene(np.random.default_rng(1), n_cameras=4, n_points=200, noise_px=0.5, outlier_fraction=0.1)
    write_scene_p3(sc, tmp_path / "p3")
    assert bench.main(["--scenes", "none", "--p3", str(tmp_path / "p3"), "--json", str(tmp_path / "rows.json")]) == 0
    out = capsys.readouterr().out
    assert "p3" in out and "colmap" in out and "kit" in out
    assert (tmp_path / "rows.json").is_file()

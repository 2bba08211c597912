"""``python -m course_lib sfm``: outputs (COLMAP model, report.json, scene.html) and one-line errors on bad input."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from course_lib.__main__ import main
from course_lib.data.colmap import read_colmap_text
from course_lib.paths import EMBEDDED_SFM


@pytest.fixture(scope="module")
def run_embedded(tmp_path_factory):
    out = tmp_path_factory.mktemp("sfm_out")
    rc = main(["sfm", "--out", str(out), "--seed", "0", "--quiet"])
    return rc, out


def test_writes_the_three_outputs(run_embedded, capsys):
    rc, out = run_embedded
    assert rc == 0
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        assert (out / "colmap" / name).is_file()
    report = json.loads((out / "report.json").read_text())
    assert report["totals"]["registered_images"] == 6
    assert report["final"]["points"] == report["totals"]["points"] > 500
    assert {"pairs", "initial_pair", "stages", "final", "seconds", "totals"} <= set(report)
    html = (out / "scene.html").read_text()
    assert "<html" in html and "plotly" in html.lower()
    assert len(html) > 1_000_000  # plotly.js is embedded: the page opens offline


def test_model_reads_back(run_embedded):
    _, out = run_embedded
    m = read_colmap_text(out / "colmap")
    report = json.loads((out / "report.json").read_text())
    assert len(m.image_names) == 6 and len(m.X) == report["final"]["points"]
    assert abs(m.error.mean() - report["final"]["mean_reprojection_error_px"]) < 0.2  # per-point vs per-observation mean


def test_pycolmap_reads_the_model(run_embedded):
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap (environment.txt) is needed for the COLMAP cross-check")
    _, out = run_embedded
    rec = pycolmap.Reconstruction(str(out / "colmap"))
    m = read_colmap_text(out / "colmap")
    assert rec.num_reg_images() == 6 and rec.num_points3D() == len(m.X)
    for k, iid in enumerate(m.image_ids):
        img = rec.images[int(iid)]
        pose = img.cam_from_world() if callable(img.cam_from_world) else img.cam_from_world
        np.testing.assert_allclose(pose.rotation.matrix(), m.R_cw[k], atol=1e-9)
        np.testing.assert_allclose(pose.translation, m.t_cw[k], atol=1e-9)
    rec.update_point_3d_errors()
    assert abs(rec.compute_mean_reprojection_error() - m.error.mean()) < 1e-6


def _copy_embedded(tmp_path):
    dst = tmp_path / "scene"
    shutil.copytree(EMBEDDED_SFM, dst)
    return dst


def _error_line(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    return err[0]


def test_missing_folder(tmp_path, capsys):
    assert main(["sfm", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")]) == 2
    assert "not found" in _error_line(capsys)


def test_truncated_matching_file(tmp_path, capsys):
    d = _copy_embedded(tmp_path)
    text = (d / "matching2.txt").read_text()
    (d / "matching2.txt").write_text(text[: len(text) // 2].rsplit(" ", 3)[0])  # cut in the middle of a row
    assert main(["sfm", str(d), "--out", str(tmp_path / "o")]) == 2
    assert "matching2.txt" in _error_line(capsys)


def test_missing_image(tmp_path, capsys):
    d = _copy_embedded(tmp_path)
    (d / "3.jpg").unlink()
    assert main(["sfm", str(d), "--out", str(tmp_path / "o")]) == 2
    assert "3.png/.jpg" in _error_line(capsys) or "3.jpg" in capsys.readouterr().err


def test_non_invertible_K(tmp_path, capsys):
    d = _copy_embedded(tmp_path)
    (d / "calibration.txt").write_text("0 0 400\n0 0 300\n0 0 1\n")
    assert main(["sfm", str(d), "--out", str(tmp_path / "o")]) == 2
    assert "not invertible" in _error_line(capsys)


def test_out_is_a_file(tmp_path, capsys):
    f = tmp_path / "taken.txt"
    f.write_text("x")
    assert main(["sfm", "--out", str(f), "--quiet"]) == 2
    assert "is a file, not a folder" in _error_line(capsys)


def test_left_out_image_is_printed_by_name(tmp_path, capsys):
    from course_lib.data.synthetic import make_scene, write_scene_p3

    sc = make_scene(np.random.default_rng(3), n_cameras=5, n_points=300, outlier_fraction=0.0)
    seen = np.flatnonzero(np.isfinite(sc.uv[:, 4, 0]))
    sc.uv[seen[10:], 4] = np.nan  # image 5 shares only 10 points with the others
    write_scene_p3(sc, tmp_path / "p3")
    import cv2

    for i in range(5):  # the command reads P3 folders with their images
        cv2.imwrite(str(tmp_path / "p3" / f"{i + 1}.png"), np.full((600, 800, 3), 128, np.uint8))
    assert main(["sfm", str(tmp_path / "p3"), "--out", str(tmp_path / "o"), "--quiet", "--no-html"]) == 0
    out = capsys.readouterr().out
    assert "4/5 images registered" in out and "left out: 5.png: no verified matches" in out
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    assert report["left_out"][0]["name"] == "5.png"


# --- the command line imports only what the command needs -------------------------------------------

def _modules_after(argv: list[str]) -> set[str]:
    """The names in ``sys.modules`` after ``python -m course_lib ARGV`` has run, in a fresh process."""
    code = ("import sys, runpy; sys.argv = ['course_lib'] + sys.argv[1:]\n"
            "try:\n    runpy.run_module('course_lib', run_name='__main__')\n"
            "except SystemExit:\n    pass\n"
            "print('MODULES', ' '.join(sorted(sys.modules)))")
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(root)}
    out = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, cwd=root, env=env,
                         check=True).stdout
    line = next(ln for ln in out.splitlines() if ln.startswith("MODULES "))
    return set(line.split()[1:])


@pytest.mark.parametrize("argv", [["--help"], ["sfm", "--help"], ["match", "--help"]])
def test_help_imports_no_torch_nor_nbformat(argv):
    mods = _modules_after(argv)
    heavy = {m for m in mods if m.split(".")[0] in {"torch", "nbformat", "jsonschema", "plotly"}}
    assert not heavy, f"python -m course_lib {' '.join(argv)} imported {sorted(heavy)[:5]}"


def test_sfm_imports_neither_torch_nor_nbformat(tmp_path):
    mods = _modules_after(["sfm", "--out", str(tmp_path / "o"), "--quiet"])  # scene.html included: plotly, not its renderers
    assert "course_lib.sfm.pipeline" in mods
    heavy = {m for m in mods if m.split(".")[0] in {"torch", "nbformat", "jsonschema"}}
    assert not heavy, f"python -m course_lib sfm imported {sorted(heavy)[:5]}"


def test_any_mapper_option_from_the_command_line(tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["sfm", "--out", str(out), "--quiet", "--no-html", "--option", "min_pnp_inliers=25",
                 "--option", "ba_images_ratio=1.2", "--option", "final_max_reproj_px=none"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["options"]["ba_images_ratio"] == 1.2 and report["options"]["final_max_reproj_px"] is None
    for bad, msg in [("min_pnp=3", "no such option"), ("min_pnp_inliers=three", "expected an integer"),
                     ("multiple_models=maybe", "true or false"), ("min_pnp_inliers", "expected KEY=VALUE"),
                     ("initial_pair=1", "two integers")]:
        assert main(["sfm", "--out", str(tmp_path / "x"), "--quiet", "--option", bad]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and msg in err[0], (bad, err)


def test_a_rerun_leaves_no_model_of_the_earlier_run(tmp_path, capsys):
    """An earlier run into the same --out wrote colmap-1/ (two models): a run with one model removes it, and keeps a
    colmap-N folder that holds anything the kit did not write."""
    out = tmp_path / "o"
    for k in (1, 2):
        (out / f"colmap-{k}").mkdir(parents=True)
        for name in ("cameras.txt", "images.txt", "points3D.txt"):
            (out / f"colmap-{k}" / name).write_text("# an earlier run\n")
    (out / "colmap-2" / "notes.md").write_text("mine\n")
    assert main(["sfm", "--out", str(out), "--quiet", "--no-html"]) == 0
    assert (out / "colmap" / "images.txt").is_file() and not (out / "colmap-1").exists()
    assert (out / "colmap-2" / "notes.md").read_text() == "mine\n"

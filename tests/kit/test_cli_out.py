"""Issue 14: an existing file given as a command's output gets one line that says what to do (exit 2).

One case per command whose output handling this file pins (``nerf train/render`` and ``sfm`` are
tested with their own commands): ``match --out``, ``sfm-to-nerf --out``, ``make-data --out``,
``ba --json``, ``grade --json/--markdown`` and ``release OUT_DIR``. Each fails before any work is
done, with ``error: ...`` on one line and no traceback.
"""

from __future__ import annotations

import pytest

from course_lib.__main__ import main
from course_lib.paths import EMBEDDED_SFM


def run(argv: list[str], capsys) -> tuple[int, str]:
    rc = main(argv)
    err = capsys.readouterr().err.strip()
    return rc, err


@pytest.fixture
def a_file(tmp_path):
    f = tmp_path / "existing.txt"
    f.write_text("not a folder")
    return f


def assert_one_line(rc: int, err: str, *phrases: str) -> None:
    assert rc == 2, err
    assert err.startswith("error: ") and "\n" not in err and "Traceback" not in err, err
    for p in phrases:
        assert p in err, err


def test_match_out_existing_file(a_file, capsys):
    rc, err = run(["match", str(EMBEDDED_SFM), "--K", str(EMBEDDED_SFM / "calibration.txt"), "--out", str(a_file)],
                  capsys)
    assert_one_line(rc, err, f"--out {a_file}", "is a file, not a folder", "give a folder path")
    assert a_file.read_text() == "not a folder"


def test_match_out_under_a_file(a_file, capsys):
    rc, err = run(["match", str(EMBEDDED_SFM), "--K", str(EMBEDDED_SFM / "calibration.txt"), "--out",
                   str(a_file / "p3")], capsys)
    assert_one_line(rc, err, "is a file, not a folder")


def test_sfm_to_nerf_out_existing_file(a_file, tmp_path, capsys):
    rc, err = run(["sfm-to-nerf", str(tmp_path), "--images", str(EMBEDDED_SFM), "--out", str(a_file)], capsys)
    assert_one_line(rc, err, f"--out {a_file}", "is a file, not a folder")


def test_make_data_out_existing_file(a_file, capsys):
    rc, err = run(["make-data", "--which", "sfm", "--out", str(a_file)], capsys)
    assert_one_line(rc, err, f"--out {a_file}", "is a file, not a folder")


def test_ba_json_is_a_folder_or_under_a_file(a_file, tmp_path, capsys):
    rc, err = run(["ba", str(tmp_path / "problem.txt"), "--json", str(tmp_path)], capsys)
    assert_one_line(rc, err, f"--json {tmp_path} is a folder", "ba.json")
    rc, err = run(["ba", str(tmp_path / "problem.txt"), "--json", str(a_file / "ba.json")], capsys)
    assert_one_line(rc, err, "--json", "is a file, not a folder")


def test_grade_report_paths_are_checked_before_grading(a_file, tmp_path, capsys):
    rc, err = run(["grade", str(tmp_path), "--json", str(a_file / "report.json")], capsys)
    assert_one_line(rc, err, "--json", "is a file, not a folder")
    rc, err = run(["grade", str(tmp_path), "--markdown", str(tmp_path)], capsys)
    assert_one_line(rc, err, f"--markdown {tmp_path} is a folder", "feedback.md")


def test_release_into_an_existing_file(a_file, capsys):
    rc = main(["release", str(a_file)])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and err.startswith("error: ") and "is a file, not a folder" in err and "Traceback" not in err, err
    assert a_file.read_text() == "not a folder"

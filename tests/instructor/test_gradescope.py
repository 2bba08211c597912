"""Gradescope: the autograder package, and ``run_autograder`` in a fresh folder laid out as Gradescope lays it out.

The package is unzipped into ``ROOT/source`` (Gradescope's ``/autograder/source``), a submission put in
``ROOT/submission``, and the package's own ``run_autograder`` run (``AUTOGRADER_ROOT`` stands in for
``/autograder``, and the test's Python for the one ``setup.sh`` installs): it must write ``ROOT/results/results.json``
in Gradescope's format, for a complete submission and for one that attacks (it imports the reference, and tries to
read the instructor's kit that lies beside it in the container into its feedback).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import nbformat
import pytest

from course_lib.__main__ import main
from tests.instructor.test_grade import NB01, solved, write_submission

OPTIONS = ["--notebooks", "01", "--no-nbval", "--timeout", "20", "--hidden-seed", "11"]


@pytest.fixture(scope="module")
def package(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("gradescope") / "autograder.zip"
    assert main(["gradescope", "--package", str(path), *OPTIONS]) == 0
    return path


def run_autograder(package: Path, root: Path, notebooks: dict) -> dict:
    (root / "source").mkdir(parents=True)
    subprocess.run(["unzip", "-q", str(package), "-d", str(root / "source")], check=True)
    write_submission(root / "submission", notebooks)
    (root / "results").mkdir()
    env = {**os.environ, "AUTOGRADER_ROOT": str(root), "AUTOGRADER_PYTHON": sys.executable}
    done = subprocess.run([str(root / "source" / "run_autograder")], env=env, capture_output=True, text=True,
                          timeout=900)
    assert done.returncode == 0, done.stdout + done.stderr
    return json.loads((root / "results" / "results.json").read_text())


@pytest.mark.fails_closed  # no grading
def test_the_package_holds_setup_run_autograder_and_the_kit(package):
    import zipfile

    with zipfile.ZipFile(package) as z:
        names = set(z.namelist())
        assert {"setup.sh", "run_autograder", "kit/environment.txt", "kit/course_lib/__main__.py"} <= names
        assert all((z.getinfo(n).external_attr >> 16) & 0o111 for n in ("setup.sh", "run_autograder"))
        assert "--notebooks 01 --hidden-seed 11 --timeout 20.0 --no-nbval" in z.read("run_autograder").decode()
        for script in ("setup.sh", "run_autograder"):
            assert subprocess.run(["bash", "-n"], input=z.read(script)).returncode == 0


def test_results_of_a_complete_submission(package, tmp_path):
    results = run_autograder(package, tmp_path / "autograder", {NB01: solved()[NB01]})
    print(json.dumps(results, indent=1)[:3000])  # pytest -s: the results.json
    tests = {t["name"]: t for t in results["tests"]}
    assert results["score"] == sum(t["score"] for t in results["tests"]) == 0.9 * sum(t["max_score"] for t in
                                                                                       results["tests"])
    assert "01_fundamental_matrix.ipynb: eight_point" in tests and all(t["visibility"] == "visible" for t in tests.values())
    assert results["output_format"] == "md" and "# Grading feedback" in results["output"]


def test_results_of_an_attacking_submission(package, tmp_path):
    root = tmp_path / "autograder"
    kit_file = root / "source" / "kit" / "course_lib" / "sfm" / "fundamental.py"
    nbs = solved(bodies={"eight_point": "return ref_eight_point(x1, x2)",
                         "normalize_points": f"raise RuntimeError(np.fromfile({str(kit_file)!r}, dtype=np.uint8)"
                                             ".tobytes().decode()[:3000])"})
    nbs[NB01].cells.insert(2, nbformat.v4.new_code_cell("from course_lib.sfm.fundamental import eight_point as "
                                                        "ref_eight_point"))
    results = run_autograder(package, root, nbs)
    print(json.dumps(results, indent=1)[:3000])  # pytest -s: the results.json
    tests = {t["name"].split(": ")[1]: t for t in results["tests"]}
    assert tests["eight_point"]["score"] == 0 and "reference solution" in tests["eight_point"]["output"]
    assert tests["normalize_points"]["score"] == 0 and "No such file" in tests["normalize_points"]["output"]
    reference = kit_file.read_text()
    leaked = [ln for ln in reference.splitlines() if len(ln.strip()) > 30 and ln.strip() in json.dumps(results)]
    assert not leaked, leaked
    assert results["score"] < 0.9 * sum(t["max_score"] for t in results["tests"])

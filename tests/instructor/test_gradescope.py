"""Gradescope: the autograder package, and ``run_autograder`` in a fresh folder laid out as Gradescope lays it out.

The package is unzipped into ``ROOT/source`` (Gradescope's ``/autograder/source``, closed to others as ``setup.sh``
leaves it), a submission put in ``ROOT/submission``, and the package's own ``run_autograder`` run
(``AUTOGRADER_ROOT`` stands in for ``/autograder``, and a Python of the test's for the one ``setup.sh`` installs):
it must write ``ROOT/results/results.json`` in Gradescope's format, for a complete submission and for one that
attacks (it imports the reference, and tries to read the instructor's kit that lies beside it into its feedback):
with bubblewrap (``COURSE_GRADER_CONTAINER=0``) and in container mode, the package's default.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
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


def run_autograder(package: Path, root: Path, notebooks: dict, python: str = sys.executable, **env) -> dict:
    (root / "source").mkdir(parents=True)
    subprocess.run(["unzip", "-q", str(package), "-d", str(root / "source")], check=True)
    os.chmod(root / "source", 0o700)  # as setup.sh leaves it: the kit closed to the student's uid
    write_submission(root / "submission", notebooks)
    (root / "results").mkdir()
    env = {**os.environ, "AUTOGRADER_ROOT": str(root), "AUTOGRADER_PYTHON": python, **env}
    cgroup = env.pop("cgroup", None)
    done = subprocess.run([str(root / "source" / "run_autograder")], env=env, capture_output=True, text=True,
                          timeout=900, preexec_fn=cgroup.enter if cgroup is not None else None)
    assert done.returncode == 0, done.stdout + done.stderr
    return json.loads((root / "results" / "results.json").read_text())


@pytest.mark.fails_closed  # no grading
def test_the_package_holds_setup_run_autograder_and_the_kit(package):
    import zipfile

    with zipfile.ZipFile(package) as z:
        names = set(z.namelist())
        assert {"setup.sh", "run_autograder", "kit/environment.txt", "kit/course_lib/__main__.py"} <= names
        assert all((z.getinfo(n).external_attr >> 16) & 0o111 for n in ("setup.sh", "run_autograder"))
        run = z.read("run_autograder").decode()
        assert "--notebooks 01 --hidden-seed 11 --timeout 20.0 --no-nbval" in run
        assert 'COURSE_GRADER_CONTAINER="${COURSE_GRADER_CONTAINER-1}"' in run  # container mode unless chosen off
        assert "chmod -R go-rwx /autograder/source" in z.read("setup.sh").decode()
        for script in ("setup.sh", "run_autograder"):
            assert subprocess.run(["bash", "-n"], input=z.read(script)).returncode == 0


@pytest.mark.slow  # the grader on a whole submission: pytest -m "not slow" leaves it out
def test_results_of_a_complete_submission(package, tmp_path):
    results = run_autograder(package, tmp_path / "autograder", {NB01: solved()[NB01]}, COURSE_GRADER_CONTAINER="0")
    print(json.dumps(results, indent=1)[:3000])  # pytest -s: the results.json
    tests = {t["name"]: t for t in results["tests"]}
    assert results["score"] == sum(t["score"] for t in results["tests"]) == 0.9 * sum(t["max_score"] for t in
                                                                                       results["tests"])
    assert "01_fundamental_matrix.ipynb: eight_point" in tests and all(t["visibility"] == "visible" for t in tests.values())
    assert results["output_format"] == "md" and "# Grading feedback" in results["output"]


def attacking(root: Path) -> tuple[dict, Path]:
    """Notebook 01 that imports the reference, and reads the instructor's kit beside it into its exception."""
    kit_file = root / "source" / "kit" / "course_lib" / "sfm" / "fundamental.py"
    nbs = solved(bodies={"eight_point": "return ref_eight_point(x1, x2)",
                         "normalize_points": f"raise RuntimeError(np.fromfile({str(kit_file)!r}, dtype=np.uint8)"
                                             ".tobytes().decode()[:3000])"})
    nbs[NB01].cells.insert(2, nbformat.v4.new_code_cell("from course_lib.sfm.fundamental import eight_point as "
                                                        "ref_eight_point"))
    return nbs, kit_file


@pytest.mark.slow  # the grader on a whole submission: pytest -m "not slow" leaves it out
def test_results_of_an_attacking_submission(package, tmp_path):
    root = tmp_path / "autograder"
    nbs, kit_file = attacking(root)
    results = run_autograder(package, root, nbs, COURSE_GRADER_CONTAINER="0")  # bubblewrap
    print(json.dumps(results, indent=1)[:3000])  # pytest -s: the results.json
    assert_attack_fails(results, kit_file, "No such file")  # the sandbox does not show the kit


def assert_attack_fails(results: dict, kit_file: Path, why: str) -> None:
    tests = {t["name"].split(": ")[1]: t for t in results["tests"]}
    assert tests["eight_point"]["score"] == 0  # the reference is not in the student's process
    assert "No module named 'course_lib.sfm.fundamental'" in tests["eight_point"]["output"], tests["eight_point"]
    assert tests["normalize_points"]["score"] == 0 and why in tests["normalize_points"]["output"]
    reference = kit_file.read_text()
    leaked = [ln for ln in reference.splitlines() if len(ln.strip()) > 30 and ln.strip() in json.dumps(results)]
    assert not leaked, leaked
    assert results["score"] < 0.9 * sum(t["max_score"] for t in results["tests"])


@pytest.mark.slow  # the grader on a whole submission: pytest -m "not slow" leaves it out
def test_results_of_an_attacking_submission_in_container_mode(package, tmp_path):
    """Container mode (COURSE_GRADER_CONTAINER=1), where bubblewrap is not used: the grader as root, the Python of a
    virtual environment of the system's Python (which all may run, as in a container), a cgroup with a memory
    limit standing in for the container's. The kit beside the submission is closed to the student's uid."""
    from course_lib.instructor.cgroups import Cgroup
    from tests.instructor.template_runner import fresh_venv

    if os.getuid() != 0 or not os.access("/usr/bin/python3", os.X_OK):
        pytest.skip("container mode: the grader runs as root, with a Python all may run")
    limit = Cgroup.create(16 << 30, 4096)
    if limit is None:
        pytest.skip("no cgroup can be made here to stand in for the container's memory limit")
    base = Path(tempfile.mkdtemp(prefix="course-container-test-"))
    os.chmod(base, 0o755)
    try:
        venv = fresh_venv(base / "venv", Path(sysconfig.get_paths()["purelib"]), python="/usr/bin/python3")
        root = tmp_path / "autograder"
        nbs, kit_file = attacking(root)
        results = run_autograder(package, root, nbs, python=str(venv / "bin" / "python"), cgroup=limit)
    finally:
        limit.close()
        shutil.rmtree(base)
    print(json.dumps(results, indent=1)[:3000])  # pytest -s: the results.json
    assert "container mode" in results["output"]
    assert_attack_fails(results, kit_file, "Permission denied")
    tests = {t["name"].split(": ")[1]: t for t in results["tests"]}
    assert tests["sampson_distance"]["score"] == 9  # honest code is graded as everywhere
    reference = kit_file.read_text()
    assert not [ln for ln in reference.splitlines() if len(ln.strip()) > 30 and ln.strip() in json.dumps(results)]

"""The stored fixtures are current: rebuilt from the reference, they equal the committed files.

CI machines differ in their CPU (AVX-512 or not), and OpenBLAS picks its kernels by CPU: the SVD's
signs and a diverging solver's end point can change with them. The second test rebuilds the
SfM fixtures on another kernel set (``OPENBLAS_CORETYPE``), as another machine would.
"""

import os
import subprocess
import sys

import pytest

from course_lib.instructor.cli_fixtures import build_fixtures
from course_lib.paths import REPO_ROOT


def test_fixtures_are_current():
    """Rebuild every fixture from the reference and compare with the committed files."""
    diffs = build_fixtures(write=False)
    assert diffs, "no case builders registered"
    stale = {k: v for k, v in diffs.items() if v}
    assert not stale, f"stale fixtures (run: python -m course_lib fixtures): {stale}"


@pytest.mark.parametrize("core", ["Haswell", "Sandybridge"])
def test_fixtures_are_the_same_on_another_cpu(core):
    """The numpy/scipy fixtures rebuilt with OpenBLAS's kernels for another CPU equal the committed files."""
    names = ["fundamental", "essential", "triangulation_step", "triangulation", "pnp", "bundle_adjustment"]
    env = dict(os.environ, OPENBLAS_CORETYPE=core)
    res = subprocess.run([sys.executable, "-m", "course_lib", "fixtures", "--check", *names], cwd=REPO_ROOT, env=env,
                         capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, f"fixtures differ with OPENBLAS_CORETYPE={core}:\n{res.stdout}{res.stderr[-2000:]}"

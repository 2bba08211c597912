"""The checks ship to students: they import no reference solution and run without one.

``course_lib.checks`` never imports ``course_lib.sfm``, ``course_lib.nerf`` or the instructor
package, not even inside a function; the step inputs of the embedded scene (``course_lib.starting_points``)
read stored fixtures. Both are tested statically (imports) and by running every check and every
step input in a process where those packages cannot be imported.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

import course_lib.checks

CHECKS_DIR = Path(course_lib.checks.__file__).parent
FORBIDDEN = ("course_lib.sfm", "course_lib.nerf", "course_lib.instructor")


def _imports(path: Path) -> list[tuple[int, str]]:
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            out += [(node.lineno, f"{node.module}.{a.name}") for a in node.names]
    return out


@pytest.mark.parametrize("path", sorted(CHECKS_DIR.glob("*.py")), ids=lambda p: p.name)
def test_checks_import_no_reference(path):
    bad = [(line, mod) for line, mod in _imports(path) if mod.startswith(FORBIDDEN)]
    assert not bad, f"{path.name} imports {bad}: the checks ship to students and hold no reference"


BLOCKED_RUN = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.startswith(%r):
            raise ModuleNotFoundError(name, name=name)
sys.meta_path.insert(0, Block())
import importlib, pkgutil
import course_lib.checks, course_lib.starting_points as starting_points
def todo(*a, **k):
    raise NotImplementedError
for m in pkgutil.iter_modules(course_lib.checks.__path__):
    mod = importlib.import_module("course_lib.checks." + m.name)
    for name in sorted(dir(mod)):
        if name.startswith("check_"):
            getattr(mod, name)(todo)
print("two_view_step", starting_points.two_view_step().F.shape)
for f in (starting_points.triangulation_input, starting_points.pnp_input, starting_points.bundle_adjustment_input):
    print(f.__name__, sorted(f()))
"""


def test_checks_and_step_inputs_run_without_the_reference():
    code = BLOCKED_RUN % (FORBIDDEN,)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "Traceback" not in out.stdout, out.stdout
    assert out.stdout.count("not implemented yet") >= 23, out.stdout
    assert "two_view_step (3, 3)" in out.stdout
    for name in ("triangulation_input", "pnp_input", "bundle_adjustment_input"):
        assert f"{name} [" in out.stdout

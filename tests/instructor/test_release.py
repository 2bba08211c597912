"""The student release: stubs instead of solutions, no reference solutions, byte-identical, validated."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import nbformat
import pytest

from course_lib.instructor.notebooks import NOTEBOOKS_DIR, ReleaseError, kit_specs, marker_regions
from course_lib.instructor.release import stub_source, verify_release, write_release
from course_lib.paths import REPO_ROOT


@pytest.fixture(scope="module")
def kit(tmp_path_factory):
    from course_lib.__main__ import main

    out = tmp_path_factory.mktemp("kit") / "student-kit"
    assert main(["release", str(out)]) == 0  # the CLI, in this process
    return out, json.loads((out / "RELEASE_MANIFEST.json").read_text())


def _tree(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_releasing_twice_gives_identical_files(kit):
    out, _ = kit
    before = _tree(out)
    (out / "notebooks" / "stray.txt").write_text("x")
    write_release(out)  # over the earlier release: replaced by identical files, the stray file gone
    assert _tree(out) == before


def test_notebooks_have_stubs_and_keep_checks_and_verdicts(kit):
    out, manifest = kit
    for spec in kit_specs():
        if spec.name in manifest["left_out_notebooks"]:
            assert not spec.exercises and not (out / "notebooks" / spec.name).exists()
            continue
        inst = nbformat.read(NOTEBOOKS_DIR / spec.name, as_version=4)
        stud = nbformat.read(out / "notebooks" / spec.name, as_version=4)
        assert len(inst.cells) == len(stud.cells)
        text = json.dumps(stud)
        assert "BEGIN SOLUTION" not in text and "END SOLUTION" not in text
        for e in spec.exercises:
            ex, chk = stud.cells[e.cell], stud.cells[e.check_cell]
            assert "raise NotImplementedError" in ex.source and f"{e.name}" in ex.source and '"""' in ex.source
            assert ex.outputs == [] and ex.execution_count is None
            assert chk.source == e.check_source  # check cell and its reference verdict kept
            assert "".join(o.get("text", "") for o in chk.outputs) == e.verdict
            body = ex.source.split('"""')[-1]  # the code after the docstring
            assert "course_lib.sfm" not in body and "course_lib.nerf" not in body and "reference" not in body
        for a, b in zip(inst.cells, stud.cells):
            if a.cell_type == "markdown":
                assert a.source == b.source
            assert "execution" not in b.metadata
    assert {nb["name"] for nb in manifest["notebooks"]} | set(manifest["left_out_notebooks"]) == {
        p.name for p in NOTEBOOKS_DIR.glob("*.ipynb")}


def test_hints_are_kept_in_the_stub():
    src = "def f(x):\n    \"\"\"Doc.\"\"\"\n    # BEGIN SOLUTION\n    # HINT: use np.mean\n    return x.mean()\n    # END SOLUTION\n"
    out = stub_source(src)
    assert "# HINT: use np.mean" in out and "return x.mean()" not in out and "raise NotImplementedError" in out
    assert out.startswith("def f(x):\n    \"\"\"Doc.\"\"\"\n")


def test_reference_solutions_are_left_out_or_redacted(kit):
    out, manifest = kit
    for mod in ("course_lib.sfm.fundamental", "course_lib.sfm.essential", "course_lib.sfm.triangulation",
                "course_lib.sfm.pnp"):
        assert mod in manifest["omitted_modules"]
        assert not (out / (mod.replace(".", "/") + ".py")).exists()
    assert not (out / "course_lib/instructor").exists(), "the instructor package never ships"
    assert (out / "course_lib/checks/core.py").exists() and (out / "course_lib/steps.py").exists()
    for mod, names in manifest["redacted"].items():
        src = (out / (mod.replace(".", "/") + ".py")).read_text()
        for n in names:
            assert f"def {n}(" not in src and f"class {n}(" not in src
            assert f"{n} = _kit_stand_in(" in src
    # every exercise with a reference in course_lib is covered by one of the two
    for spec in kit_specs():
        for e in spec.exercises:
            if e.reference:
                mod, attr = e.reference.split(":")
                assert mod in manifest["omitted_modules"] or attr in manifest["redacted"].get(mod, []), e
    assert (out / "data/fixtures/fundamental.npz").exists() and (out / "README.md").exists()
    assert manifest["files"]["data/fixtures/fundamental.npz"]


def test_released_library_imports_without_the_solutions(kit):
    out, _ = kit
    code = (
        "import importlib, pkgutil, course_lib\n"
        "assert course_lib.__file__.startswith(%r), course_lib.__file__\n"
        "for m in pkgutil.walk_packages(course_lib.__path__, 'course_lib.'):\n"
        "    importlib.import_module(m.name)\n"
        "try:\n    import course_lib.sfm.fundamental\nexcept ImportError:\n    pass\n"
        "else:\n    raise SystemExit('the reference solution is importable')\n"
        "from course_lib.checks.fundamental import check_eight_point\nfrom course_lib.steps import two_view_step\n"
        "assert two_view_step().F.shape == (3, 3)\n"
        "from course_lib.nerf.render import volume_render\n"
        "try:\n    volume_render(None, None, None, None)\nexcept NotImplementedError as e:\n"
        "    assert '08_nerf_rendering_and_training.ipynb' in str(e)\n"
        "import __main__\n__main__.volume_render = lambda *a: 'mine'\n"
        "assert volume_render(1, 2, 3, 4) == 'mine'\n" % str(out)
    )
    env = dict(os.environ, PYTHONPATH=str(out))
    res = subprocess.run([sys.executable, "-c", code], cwd=out, env=env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]


def test_released_notebooks_run_in_the_kit(kit):
    """Notebooks 01 and 02 (the others: python -m course_lib release OUT --verify)."""
    out, _ = kit
    problems = verify_release(out, only=["01", "02"])
    assert set(problems) == {"01_fundamental_matrix.ipynb", "02_essential_matrix_and_pose.ipynb"}
    assert all(v == [] for v in problems.values()), problems


def _notebook(tmp_path: Path, name: str, source: str) -> Path:
    d = tmp_path / "nbs"
    d.mkdir(exist_ok=True)
    nb = nbformat.v4.new_notebook()
    nb.cells = [
        nbformat.v4.new_code_cell("from course_lib.checks.fundamental import check_eight_point"),
        nbformat.v4.new_code_cell(source),
        nbformat.v4.new_code_cell("# NBVAL_CHECK_OUTPUT\ncheck_eight_point(eight_point)",
                                  outputs=[nbformat.v4.new_output("stream", name="stdout", text="eight_point\n")]),
    ]
    nbformat.write(nb, d / name)
    return d


@pytest.mark.parametrize("source, phrase", [
    ("def eight_point(x1, x2):\n    # BEGIN SOLUTION\n    return 1\n", "has no '# END SOLUTION'"),
    ("def eight_point(x1, x2):\n    return 1\n    # END SOLUTION\n", "without a '# BEGIN SOLUTION'"),
    ("def eight_point(x1, x2):\n    # BEGIN SOLUTION\n    # BEGIN SOLUTION\n    return 1\n    # END SOLUTION\n",
     "before the '# END SOLUTION'"),
    ("def eight_point(x1, x2):\n    return 1\n", "missing solution markers"),
])
def test_bad_markers_stop_the_release_with_the_notebook_named(tmp_path, source, phrase):
    d = _notebook(tmp_path, "09_broken.ipynb", source)
    with pytest.raises(ReleaseError) as err:
        write_release(tmp_path / "out", notebooks_dir=d)
    assert "09_broken.ipynb" in str(err.value) and phrase in str(err.value)
    assert not (tmp_path / "out").exists()
    res = subprocess.run([sys.executable, "-m", "course_lib", "release", str(tmp_path / "out"), "--notebooks-dir", str(d)],
                         cwd=REPO_ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 1 and "09_broken.ipynb" in res.stderr and "Traceback" not in res.stderr


def test_marker_regions():
    assert marker_regions("a\n# BEGIN SOLUTION\nb\n# END SOLUTION\n", "x") == [(1, 3)]
    with pytest.raises(ReleaseError):
        marker_regions("# END SOLUTION\n", "x")

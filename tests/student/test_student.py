"""A student's solutions travel with the student: saved when the exercise's cell runs, found by later notebooks.

The cells run in a real IPython shell (as in Jupyter, where IPython keeps every cell's source); a
fresh shell then plays the later notebook. One test runs two notebooks in two Jupyter kernels.
"""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

from course_lib import saved_solutions
from course_lib.exercises import EXERCISES


@pytest.fixture
def shell(tmp_path, monkeypatch):
    """An IPython shell whose exercise cells save to ``tmp_path / "solutions"`` (restores ``__main__`` after)."""
    from IPython.core.interactiveshell import InteractiveShell

    monkeypatch.setenv("COURSE_LIB_SOLUTIONS", str(tmp_path / "solutions"))
    main = sys.modules["__main__"]
    saved_solutions._LOADED.clear()
    sh = InteractiveShell.instance()
    assert saved_solutions.install(sh)
    yield sh
    InteractiveShell.clear_instance()
    sys.modules["__main__"] = main
    saved_solutions._LOADED.clear()


def run(sh, source: str):
    res = sh.run_cell(source, store_history=True)  # as a Jupyter kernel runs a cell
    assert res.success, res.error_in_exec or res.error_before_exec
    return res


def fresh_notebook(sh):
    """The next notebook: a new shell namespace, nothing of the earlier cells left."""
    sh.reset(new_session=True)
    for name in list(sys.modules):
        if name.startswith("_course_lib_saved_"):
            del sys.modules[name]
    saved_solutions._LOADED.clear()


def test_running_the_cell_saves_the_function_with_its_helpers_imports_and_constants(shell, tmp_path):
    run(shell, "import numpy as np\nfrom scipy.spatial.transform import Rotation as Rot\nSCALE = 2.0\nNAMES = ('a', 'b')")
    run(shell, "def _centroid(x):\n    return x.mean(axis=0)")
    run(shell, "def normalize_points(x):\n    \"\"\"Mine.\"\"\"\n    c = _centroid(x)\n"
               "    s = SCALE / np.mean(np.linalg.norm(x - c, axis=1)) / np.sqrt(2) * np.sqrt(2) ** 1\n"
               "    T = np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1.0]])\n"
               "    assert Rot is not None and NAMES\n"
               "    return s * (x - c), T")
    saved = (tmp_path / "solutions" / "normalize_points.py").read_text()
    assert "notebooks/01_fundamental_matrix.ipynb" in saved
    for line in ("import numpy as np", "from scipy.spatial.transform._rotation import Rotation as Rot",
                 "SCALE = 2.0", "NAMES = ('a', 'b')", "def _centroid(x):", "def normalize_points(x):"):
        assert line in saved, line
    fresh_notebook(shell)
    run(shell, "import numpy as np\nfrom course_lib.exercises import call\n"
               "x = np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 2.0]])\nxn, T = call('normalize_points', x)")
    xn, T, x = shell.user_ns["xn"], shell.user_ns["T"], shell.user_ns["x"]
    assert "normalize_points" not in shell.user_ns  # the kit found the saved one
    assert np.allclose(xn, (T @ np.c_[x, np.ones(3)].T).T[:, :2])


def test_a_stub_is_not_saved_and_the_stand_in_names_the_notebook_to_finish(shell, tmp_path):
    run(shell, 'def get_rays(H, W, K, c2w):\n    """doc"""\n    # YOUR CODE HERE\n    raise NotImplementedError("your code here")')
    assert not (tmp_path / "solutions").exists() or not list((tmp_path / "solutions").iterdir())
    fresh_notebook(shell)
    stand_in = saved_solutions.stand_in("get_rays", EXERCISES["get_rays"].notebook)
    with pytest.raises(NotImplementedError, match=r"get_rays is an exercise of notebooks/06_nerf_data_and_rays.ipynb"
                                                  r".*run its cell .*get_rays\.py"):
        stand_in(2, 2, None, None)
    # in the notebook that teaches it, the stub is the student's function: the message says to finish it
    run(shell, 'def get_rays(H, W, K, c2w):\n    raise NotImplementedError("your code here")')
    with pytest.raises(NotImplementedError, match=r"your get_rays .* is not written yet"):
        stand_in(2, 2, None, None)


def test_only_the_cell_that_defines_the_exercise_saves_it_never_the_kits_fallback(shell, tmp_path, capsys):
    """Notebook 02 defines an OpenCV triangulate_linear inside ``except ImportError`` where the release lacks the
    reference: that is the kit's code, not the student's, so nothing is saved and no note blames the student."""
    run(shell, "try:\n    from course_lib.not_here import triangulate_linear\nexcept ImportError:\n"
               "    import cv2\n\n    def triangulate_linear(P1, P2, x1, x2):\n"
               "        Xh = cv2.triangulatePoints(P1, P2, x1.T, x2.T).T\n        return Xh[:, :3] / Xh[:, 3:]\n"
               "X = 1")
    run(shell, "Y = 2  # a later cell of the notebook")
    assert not (tmp_path / "solutions" / "triangulate_linear.py").exists()
    assert "triangulate_linear" not in capsys.readouterr().out
    run(shell, "import numpy as np\n\ndef triangulate_linear(P1, P2, x1, x2):\n    return np.zeros((len(x1), 3))")
    assert "def triangulate_linear" in (tmp_path / "solutions" / "triangulate_linear.py").read_text()
    assert capsys.readouterr().out == ""


def test_classes_dataclasses_and_the_kits_stand_ins_travel(shell, tmp_path):
    run(shell, "from dataclasses import dataclass\nimport numpy as np\n\n@dataclass\nclass RansacResult:\n"
               "    F: np.ndarray\n    inliers: np.ndarray\n    n_iters: int")
    run(shell, "def ransac_fundamental(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):\n"
               "    return RansacResult(np.eye(3), np.ones(len(x1), bool), 1)")
    run(shell, "import torch\nfrom torch import nn\nfrom course_lib.nerf.encoding import positional_encoding\n\n"
               "class NeRF(nn.Module):\n    def __init__(self, depth=8, width=256, skips=(4,), pos_freqs=10, dir_freqs=4,"
               " use_viewdirs=True, view_width=128):\n        super().__init__()\n        self.lin = nn.Linear(3, 4)\n"
               "        self.encode = positional_encoding\n\n"
               "    def forward(self, pts, viewdirs):\n        out = self.lin(pts)\n"
               "        return torch.sigmoid(out[..., :3]), torch.relu(out[..., 3])")
    nerf = (tmp_path / "solutions" / "NeRF.py").read_text()
    assert "from course_lib.nerf.encoding import positional_encoding" in nerf  # the kit's stand-in, by name
    fresh_notebook(shell)
    res = saved_solutions.find_student_solution("ransac_fundamental")(np.zeros((9, 2)), np.zeros((9, 2)), None)
    assert res.n_iters == 1 and res.inliers.all()
    import torch

    model = saved_solutions.find_student_solution("NeRF")(depth=2)
    rgb, sigma = model(torch.zeros(5, 3), torch.zeros(5, 3))
    assert tuple(rgb.shape) == (5, 3) and tuple(sigma.shape) == (5,)


def test_what_cannot_travel_is_named_and_the_notebooks_own_function_comes_first(shell, tmp_path, capsys):
    run(shell, "import numpy as np\nTABLE = np.arange(4.0)\ndef sampson_distance(F, x1, x2):\n"
               "    return np.abs(TABLE[:len(x1)])")
    assert "without: TABLE (a ndarray of the notebook)" in capsys.readouterr().out
    assert "# Not saved" in (tmp_path / "solutions" / "sampson_distance.py").read_text()
    run(shell, "def sampson_distance(F, x1, x2):\n    return 'the notebook'")
    assert saved_solutions.find_student_solution("sampson_distance")(None, [], []) == "the notebook"
    fresh_notebook(shell)
    assert saved_solutions.find_student_solution("sampson_distance")(None, [], []) == "the notebook"  # saved again


def test_a_saved_solution_that_does_not_load_says_which_file_to_renew(tmp_path, monkeypatch):
    monkeypatch.setenv("COURSE_LIB_SOLUTIONS", str(tmp_path))
    saved_solutions._LOADED.clear()
    (tmp_path / "eight_point.py").write_text("import not_a_module_anywhere\n")
    with pytest.raises(RuntimeError, match=r"your saved eight_point .*eight_point\.py.* does not load: "
                                           r"ModuleNotFoundError.*Run its cell"):
        saved_solutions.load_saved_solution("eight_point")
    assert saved_solutions.load_saved_solution("pnp_linear") is None


def test_the_instructors_kit_saves_nothing_and_the_grader_can_turn_saving_off(monkeypatch, tmp_path):
    monkeypatch.delenv("COURSE_LIB_SOLUTIONS", raising=False)
    assert not saved_solutions.is_student_kit() and saved_solutions.solutions_dir() is None
    assert not saved_solutions.install(object())
    monkeypatch.setenv("COURSE_LIB_SOLUTIONS", str(tmp_path))  # the grader's folder of stand-ins: read, never written
    monkeypatch.setenv("COURSE_LIB_SAVE_SOLUTIONS", "0")
    assert not saved_solutions.install(object())


def test_two_notebooks_in_two_kernels(tmp_path):
    """The first notebook's exercise cell saves get_rays; a fresh kernel's trainer helper uses it."""
    import nbformat
    from nbclient import NotebookClient

    sol = tmp_path / "solutions"
    env = {"COURSE_LIB_SOLUTIONS": str(sol)}
    first = ["import torch\n\nimport course_lib",
             "def get_rays(H, W, K, c2w):\n"
             "    u, v = torch.meshgrid(torch.arange(W, dtype=K.dtype), torch.arange(H, dtype=K.dtype), indexing='xy')\n"
             "    d = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1) @ c2w[:3, :3].T\n"
             "    return c2w[:3, 3].expand(d.shape), d"]
    second = ["import numpy as np\nfrom course_lib.nerf.rays import camera_rays\n"
              "o, d = camera_rays(3, 4, np.diag([2.0, 2.0, 1.0]), np.eye(4))  # numpy float64: converted for get_rays\n"
              "print(tuple(d.shape), d.dtype)"]
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        for cells in (first, second):
            nb = nbformat.v4.new_notebook(cells=[nbformat.v4.new_code_cell(c) for c in cells])
            NotebookClient(nb, kernel_name="python3", timeout=120, resources={"metadata": {"path": str(tmp_path)}}).execute()
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k)
            else:
                os.environ[k] = v
    assert (sol / "get_rays.py").exists()
    assert nb.cells[0].outputs[0]["text"].strip() == "(3, 4, 3) torch.float32"

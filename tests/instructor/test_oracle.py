"""Each exercise graded on its own (issue 19, item 2): the earlier exercises it calls answer by their reference.

* Through the real grader: a submission whose earlier exercise is wrong (``normalize_points``
  without centring, ``triangulate_linear`` with u and v swapped, ``pnp_linear`` without making R
  orthonormal, notebook 07's copy of ``positional_encoding`` without π) but whose later exercises
  are right loses points only on the earlier exercise.
* The call-back, in a sandboxed student process: junk arguments raise the reference's error in the
  student's code (the grader and its worker go on); a call the reference cannot take (another
  signature, a value that cannot be sent) and a class go to the student's own; an argument too
  large is refused there; an exercise that calls back without end is stopped at the cap; the
  exercise itself is never answered; the call-backs' time is the exercise's (one clock: an exercise
  that makes the reference work longer than its budget is stopped at its budget), and a reference
  that runs too long, or returns too much, is stopped.
* Which earlier steps an exercise's code calls, from its extracted code (:func:`earlier_steps`).
"""

from __future__ import annotations

import ast
import textwrap
from pathlib import Path

import nbformat
import numpy as np
import pytest

from course_lib.instructor import oracle as oracle_mod
from course_lib.instructor.grade import HIDDEN_SHARE, grade_submission, prepare_hidden
from course_lib.instructor.notebooks import NOTEBOOKS_DIR, kit_specs, python_source
from course_lib.instructor.oracle import Oracle, earlier_steps
from course_lib.instructor.remote import RemoteFunction
from course_lib.instructor.sandbox import wire
from course_lib.instructor.settings import Isolation, student_library
from course_lib.instructor.student_process import StudentProcess, StudentProcessEnded
from tests.instructor.honest import honest_submission

NOTEBOOKS = ["01", "03", "04", "07"]
SEED = 19

#: An earlier exercise written wrong, as a student would; every later exercise of its notebook calls it.
WRONG = {
    "normalize_points": """
        def normalize_points(x):
            s = np.sqrt(2) / np.linalg.norm(x - x.mean(0), axis=1).mean()
            return x * s, np.diag([s, s, 1.0])  # the centroid is not removed
    """,
    "triangulate_linear": """
        def triangulate_linear(P1, P2, x1, x2):
            out = []
            for a, b in zip(x1, x2):  # u and v swapped
                A = np.stack([a[0] * P1[2] - P1[1], a[1] * P1[2] - P1[0], b[0] * P2[2] - P2[1], b[1] * P2[2] - P2[0]])
                Xh = np.linalg.svd(A)[2][-1]
                out.append(Xh[:3] / Xh[3])
            return np.array(out)
    """,
    "pnp_linear": """
        def pnp_linear(X, x, K):
            xn = np.column_stack([x, np.ones(len(x))]) @ np.linalg.inv(K).T
            rows = []
            for Xi, (u, v, _) in zip(np.column_stack([X, np.ones(len(X))]), xn):
                rows.append(np.concatenate([Xi, np.zeros(4), -u * Xi]))
                rows.append(np.concatenate([np.zeros(4), Xi, -v * Xi]))
            P = np.linalg.svd(np.array(rows))[2][-1].reshape(3, 4)
            if np.linalg.det(P[:, :3]) < 0:
                P = -P
            s = np.cbrt(np.linalg.det(P[:, :3]))
            return P[:, :3] / s, P[:, 3] / s  # R is not made orthonormal
    """,
    "positional_encoding": """
        def positional_encoding(x, n_freqs, include_input=True):
            freqs = 2.0 ** torch.arange(n_freqs, dtype=x.dtype)
            xb = x[..., None, :] * freqs[:, None]  # no factor pi, and sin and cos not interleaved per frequency
            parts = [x] if include_input else []
            return torch.cat(parts + [torch.sin(xb).flatten(-2), torch.cos(xb).flatten(-2)], -1)
    """,
}
#: Where each wrong function goes: its exercise's notebook, or the notebook that calls it (notebook 07 imports
#: notebook 06's positional_encoding, as saved when its cell ran there; a student may define one in 07 instead,
#: and notebook 06 is not graded here).
WHERE = {"positional_encoding": "07_nerf_model.ipynb"}


def _binds(node: ast.stmt, name: str) -> bool:
    if isinstance(node, (ast.Import, ast.ImportFrom)):
        return any((a.asname or a.name).split(".")[0] == name for a in node.names)
    return getattr(node, "name", None) == name


def put_def(path, name: str, code: str) -> None:
    """Replace the top-level def (or import) of ``name`` in the notebook at ``path`` by ``code`` (the student's edit)."""
    nb = nbformat.read(path, as_version=4)
    for cell in nb.cells:
        if cell.cell_type != "code":
            continue
        tree = ast.parse(python_source(cell.source))
        node = next((n for n in tree.body if _binds(n, name)), None)
        if node is not None:
            lines = cell.source.splitlines()
            cell.source = "\n".join(lines[:node.lineno - 1] + textwrap.dedent(code).strip("\n").splitlines()
                                    + lines[node.end_lineno:]) + "\n"
            nbformat.write(nb, path)
            return
    raise AssertionError(f"no def of {name} in {path}")


@pytest.fixture(scope="module")
def hidden(tmp_path_factory):
    return prepare_hidden(kit_specs(NOTEBOOKS_DIR, only=NOTEBOOKS), SEED, tmp_path_factory.mktemp("hidden"))


@pytest.mark.slow  # the grader on a chain of notebooks: pytest -m "not slow" leaves it out
def test_a_wrong_earlier_exercise_costs_points_once(tmp_path, hidden):
    sub, _ = honest_submission(tmp_path / "sub", notebooks=NOTEBOOKS)
    nb_of = {e.name: s.name for s in kit_specs(NOTEBOOKS_DIR, only=NOTEBOOKS) for e in s.exercises}
    for name, code in WRONG.items():
        put_def(sub / "notebooks" / WHERE.get(name, nb_of.get(name, "")), name, code)
    report = grade_submission(sub, notebooks=NOTEBOOKS, hidden=hidden, run_nbval=False)
    points = {g["name"]: g["points"] for g in report["exercises"]}
    full = {g["name"]: round(g["max_points"] * HIDDEN_SHARE, 2) for g in report["exercises"]}
    for name in set(WRONG) & set(points):
        assert points[name] < full[name], (name, points[name])
    later = {n: (p, next(g["feedback"] for g in report["exercises"] if g["name"] == n))
             for n, p in points.items() if n not in WRONG and p < full[n]}
    assert not later, later  # eight_point, ransac_fundamental, choose_pose, pnp_ransac, NeRF, ... all full


# ------------------------------------------------------------------ the call-back in a student process


def readable_library(folder: Path) -> Path:
    """The student release in ``folder``, readable by the student's uid (as the grader makes its own)."""
    import os

    os.chmod(folder, 0o755)
    return student_library(folder)


@pytest.fixture(scope="module")
def iso(tmp_path_factory):
    return Isolation.for_grading(readable_library(tmp_path_factory.mktemp("student-kit")),
                                 [tmp_path_factory.mktemp("grader-secret")], NOTEBOOKS_DIR)


STEPS = {"normalize_points": "course_lib.sfm.fundamental:normalize_points",
         "Model": "course_lib.nerf.model:NeRF"}  # an earlier step that is a class stays the student's
CODE = """
import numpy as np


def normalize_points(x):
    return x, np.eye(3)  # wrong: the grader answers with the reference instead


class Model:
    pass


def eight_point(x1, x2=None, how="plain"):
    if how == "plain":
        return normalize_points(x1)
    if how == "junk":
        return normalize_points("junk")
    if how == "keyword":
        return normalize_points(x=x1)
    if how == "function":
        return normalize_points(lambda: 0)[1]
    if how == "class":
        return isinstance(Model, type) and Model.__module__ == "__main__"
    if how == "other interface":
        return normalize_points(x1, centre=False)
    if how == "huge":
        return normalize_points(np.zeros((5_000_000, 2)))
    if how == "again":
        for _ in range(10**6):
            normalize_points(x1)
    if how == "itself":
        wire = normalize_points.__globals__  # the stub's module: the wire format, the grader's pipes
        wire["write_frame"](wire["REP_FD"], {"event": "oracle", "name": "eight_point", "args": {"$": "tuple", "v": []},
                                             "kwargs": {"$": "dict", "k": [], "v": []}})
        return wire["read_frame"](wire["REQ_FD"])[0]
"""


def student(iso, budget=60.0):
    return StudentProcess(iso, CODE, "eight_point", None, budget, oracle=Oracle("eight_point", STEPS))


def test_the_stub_answers_with_the_reference_and_junk_raises_in_the_students_code(iso):
    from course_lib.sfm.fundamental import normalize_points

    x = np.random.default_rng(0).normal(size=(12, 2)) * 50 + 300
    with student(iso) as proc:
        f = RemoteFunction(proc, "eight_point")
        xn, T = f(x)
        assert np.allclose(xn, normalize_points(x)[0]) and np.allclose(T, normalize_points(x)[1])
        with pytest.raises(ValueError, match="raised by the grader's reference normalize_points"):
            f(x, how="junk")
        with pytest.raises(ValueError, match="KitInputError: x has 8 points that are all identical .* the grader's"):
            f(np.ones((8, 2)))  # the reference's own error, as a ValueError (the builtin it derives from)
        assert np.array_equal(f(x, how="function"), np.eye(3))  # not sendable: the student's own answers
        with pytest.raises(TypeError, match="unexpected keyword argument 'centre'"):
            f(x, how="other interface")  # not the reference's signature: the student's own answers (and raises)
        assert np.allclose(f(x, how="keyword")[0], normalize_points(x)[0])  # the grader and its worker go on
        assert f(x, how="class") is True
        reply = f(x, how="itself")  # a forged request for the exercise itself is refused
        assert reply["ok"] is False and "answers no call of 'eight_point'" in reply["message"]
        assert proc.oracle.calls == 6 and not proc.ended  # the function never left the process


def test_a_huge_argument_is_refused_in_the_students_process(iso):
    with student(iso) as proc:
        with pytest.raises(ValueError, match="MiB of arguments"):
            RemoteFunction(proc, "eight_point")(np.zeros((8, 2)), how="huge")
        assert proc.oracle.calls == 0 and not proc.ended


def test_endless_call_backs_are_stopped_at_the_cap(iso, monkeypatch):
    monkeypatch.setattr(oracle_mod, "MAX_CALLS", 300)  # the real cap (50 000) the same way, 170 times slower
    with student(iso) as proc:
        with pytest.raises(StudentProcessEnded, match="more than 300 times"):
            RemoteFunction(proc, "eight_point")(np.random.default_rng(2).normal(size=(8, 2)), how="again")
        assert proc.event == "limit" and proc.oracle.calls == 300


def test_call_backs_count_on_the_exercises_clock(tmp_path):
    """Reference RANSAC runs without end, all on call-backs: the exercise is stopped at its budget of 1 s (one
    clock: the reference's time on the student's call-backs is the exercise's), however fast the machine, and
    the feedback says how long it really took."""
    code = ("import numpy as np\n"
            "def ransac_fundamental(x1, x2, rng, threshold_px=1.0, confidence=0.999, max_iters=2000):\n"
            "    raise NotImplementedError\n"
            "def pnp_ransac(x1, x2):\n"
            "    k = 0\n"
            "    while True:  # only call-backs: the time is the reference's\n"
            "        ransac_fundamental(x1, x2, np.random.default_rng(k), threshold_px=1e-9, max_iters=2000)\n"
            "        k += 1\n")
    steps = {"ransac_fundamental": "course_lib.sfm.fundamental:ransac_fundamental"}
    x1 = np.random.default_rng(3).normal(size=(60, 2)) * 100
    iso = Isolation.for_grading(readable_library(tmp_path), [], NOTEBOOKS_DIR)
    with StudentProcess(iso, code, "pnp_ransac", None, 1.0, oracle=Oracle("pnp_ransac", steps)) as proc:
        with pytest.raises(StudentProcessEnded, match=r"stopped after \d+\.\d s"):
            RemoteFunction(proc, "pnp_ransac")(x1, x1[::-1] + 1.0)
        assert proc.event == "timeout"


def test_the_workers_time_is_bounded_and_a_result_too_large_is_refused():
    steps = {"ransac_fundamental": "course_lib.sfm.fundamental:ransac_fundamental",
             "positional_encoding": "course_lib.nerf.encoding:positional_encoding"}
    orc = Oracle("pnp_ransac", steps)
    try:
        def request(name, *args, **kwargs):
            arrays: list = []
            head = {"name": name, "args": wire.encode(args, arrays), "kwargs": wire.encode(kwargs, arrays)}
            return orc.answer(head, arrays, 1.0)

        x = np.random.default_rng(1).normal(size=(2000, 2))
        reply, _ = request("ransac_fundamental", x, x + 1e3, np.random.default_rng(0), threshold_px=1e-9,
                           confidence=0.999999, max_iters=10**9)
        assert reply["type"] == "TimeoutError", reply  # an endless RANSAC, stopped at its 1 s
        torch = pytest.importorskip("torch")
        reply, _ = request("positional_encoding", torch.zeros(300_000, 3), 20)
        assert not reply["ok"] and ("MiB" in reply["message"] or reply["type"] == "TimeoutError"), reply
    finally:
        orc.close()


def test_a_forged_generator_state_is_a_clear_error_not_a_crash_of_the_worker():
    """Issue 40, item 7: an MT19937 state with its position far outside 0..624 (numpy reads ``key[pos]`` unchecked:
    the worker used to segfault), a short key, a PCG64 state past 2^128: each answered with a TypeError that says
    what is wrong, and the same worker still answers the next, honest call."""
    orc = Oracle("ransac_fundamental", {"eight_point": "course_lib.sfm.fundamental:eight_point",
                                         "ransac_fundamental": "course_lib.sfm.fundamental:ransac_fundamental"})
    x = np.random.default_rng(1).normal(size=(20, 2))
    try:
        def request(state):
            arrays: list = []
            head = {"name": "ransac_fundamental", "args": wire.encode((x, x + 1.0), arrays),
                    "kwargs": {"$": "dict", "k": ["rng"], "v": [{"$": "rng", "s": wire.encode(state, arrays)}]}}
            return orc.answer(head, arrays, 30.0)[0]

        mt = np.random.MT19937(0).state
        for state, what in ((dict(mt, state=dict(mt["state"], pos=2**40)), "pos: 1099511627776, not an integer in"),
                            (dict(mt, state=dict(mt["state"], key=mt["state"]["key"][:5])), "uint32 (5,), not uint32"),
                            (dict(np.random.PCG64(0).state, state={"state": 2**130, "inc": 1}), "PCG64.state.state")):
            reply = request(state)
            assert reply["type"] == "TypeError" and "malformed generator state" in reply["message"], reply
            assert what in reply["message"], reply
        pid = orc.pid
        reply = request(np.random.MT19937(3).state)
        assert "malformed" not in str(reply) and orc.pid == pid, reply  # the same worker answers (the reference)
    finally:
        orc.close()


def test_the_earlier_steps_come_from_the_extracted_code():
    kit = [(e.name, e.reference) for s in kit_specs(NOTEBOOKS_DIR) for e in s.exercises]
    code = ("import numpy as np\nfrom course_lib.nerf.encoding import positional_encoding\n"
            "def eight_point(x1, x2):\n    return normalize_points(x1)\n"
            "def normalize_points(x):\n    return x\n"
            "def pnp_linear(X, x, K):\n    pass\n")
    assert earlier_steps(code, "eight_point", kit) == {"normalize_points": "course_lib.sfm.fundamental:normalize_points"}
    assert set(earlier_steps(code, "NeRF", kit)) == {"normalize_points", "eight_point", "pnp_linear",
                                                      "positional_encoding"}
    assert earlier_steps(code, "normalize_points", kit) == {}  # never itself, never a later exercise
    assert earlier_steps("def psnr(:", "psnr", kit) == {}

"""The student kit holds no implementation of any exercise, in any module.

Every function and class that the student release of ``course_lib`` defines (public or private,
in the checks, the step inputs, the loaders, the figures, the redacted modules...) is tried as
every exercise whose arguments it accepts (keyword arguments it does not know are passed by
position), through the exercise's own check on the public cases.
None may earn half of the exercise's points: pasted into an exercise cell, it would otherwise be a
working answer that the student did not write.
"""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys

import nbformat
import pytest

from course_lib.instructor.notebooks import NOTEBOOKS_DIR, kit_specs, python_source
from course_lib.instructor.release import write_release

#: Minutes, not seconds (every function of the student kit tried as every exercise): left out of the quick
#: subset (pytest -m "not slow").
pytestmark = pytest.mark.slow

#: Exercises for which a function of the student kit still passes (issue 18, item 3); each is fixed by
#: moving that function to the instructor side (or making the check's yardstick something else).
STILL_SHIPPED = {
}

TRY_ALL = r"""
import contextlib, importlib, inspect, io, json, os, pkgutil, signal, sys, time
import course_lib
from course_lib.checks import core

exercises = json.loads(sys.argv[1])
objs = {}
for m in pkgutil.walk_packages(course_lib.__path__, "course_lib."):
    try:
        mod = importlib.import_module(m.name)
    except Exception:
        continue
    for name, obj in vars(mod).items():
        if (inspect.isfunction(obj) or inspect.isclass(obj)) and getattr(obj, "__module__", "") == m.name:
            if getattr(obj, "__kit_stand_in__", False):
                continue
            objs[f"{m.name}.{name}"] = obj

def adapt(obj):
    # obj as a drop-in: called as the check calls the exercise, or with the keyword values passed by position
    if inspect.isclass(obj):
        return obj

    def call(*args, **kwargs):
        try:
            return obj(*args, **kwargs)
        except TypeError:
            return obj(*args, *kwargs.values())

    return call

def accepts(obj, n_args, is_class):
    if is_class != inspect.isclass(obj):
        return False
    if is_class:
        import torch
        return issubclass(obj, torch.nn.Module)
    try:
        inspect.signature(obj).bind(*range(n_args))
        return True
    except (TypeError, ValueError):
        return False

LIMIT = 10.0  # seconds for one candidate on one exercise, killed after (a long C call ignores SIGALRM)


def start(obj, todo):
    # the checks of the exercises ``todo`` ([(name, check)], in order) on ``obj`` in a forked child that writes one
    # score a line: a candidate that loops, blows up or hangs in C code costs LIMIT seconds per exercise at most, and
    # nothing it changes reaches another candidate (one child per candidate: a fork of this process, which holds the
    # whole kit, costs more than most tries)
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(r)
        for name, check in todo:
            s = 0.0
            try:
                core.RESULTS.pop(name, None)
                with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
                    check(adapt(obj))
            except BaseException:
                pass
            try:
                res = core.RESULTS.get(name)
                s = core.score(res) if res is not None else 0.0
            except BaseException:
                s = 0.0
            os.write(w, (repr(float(s)) + "\n").encode())
        os._exit(0)
    os.close(w)
    os.set_blocking(r, False)
    return pid, r


def take_scores(job, final):
    # the scores the child wrote so far, each for the next exercise of its list; a line resets the child's clock.
    # ``final`` (the child ended or was killed): the exercise it was on when it stopped scores 0
    while True:
        try:
            chunk = os.read(job["r"], 65536)
        except BlockingIOError:
            chunk = None
        if not chunk:
            break
        job["buf"] += chunk
    *lines, job["buf"] = job["buf"].split(b"\n")
    for line in lines:
        name, _ = job["todo"].pop(0)
        try:
            s = float(line)
        except ValueError:
            s = 0.0
        scored.append((name, s, job["qual"]))
        job["end"] = time.monotonic() + LIMIT
    if final:
        os.close(job["r"])
        if job["todo"]:
            job["todo"].pop(0)


candidates = {}  # candidate's name -> (candidate, [(exercise, check)]): every exercise whose arguments it accepts
for ex in exercises:
    check = getattr(importlib.import_module(ex["check_module"]), ex["check_function"])
    for qual, obj in objs.items():
        if accepts(obj, ex["n_args"], ex["is_class"]):
            candidates.setdefault(qual, (obj, []))[1].append((ex["name"], check))
jobs = [(qual, obj, todo) for qual, (obj, todo) in candidates.items()]
best = {ex["name"]: (0.0, None) for ex in exercises}
scored = []
running = {}  # one child per candidate, as many at once as there are cores
while jobs or running:
    while jobs and len(running) < (os.cpu_count() or 1):
        qual, obj, todo = jobs.pop(0)
        pid, r = start(obj, todo)
        running[pid] = {"r": r, "buf": b"", "end": time.monotonic() + LIMIT, "qual": qual, "obj": obj, "todo": todo}
    for pid, job in list(running.items()):
        ended = os.waitpid(pid, os.WNOHANG)[0]
        if not ended and time.monotonic() >= job["end"]:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            ended = True
        take_scores(job, final=bool(ended))
        if ended:
            del running[pid]
            if job["todo"]:  # it ended or hung on one exercise: the rest in a fresh child
                jobs.insert(0, (job["qual"], job["obj"], job["todo"]))
    time.sleep(0.005)
for name, s, qual in scored:
    if s > best[name][0]:
        best[name] = (s, qual)
print(json.dumps(best))
"""


def _exercises() -> list[dict]:
    """Every exercise with its check and the number of required positional arguments of its def."""
    out = []
    for spec in kit_specs():
        nb = nbformat.read(NOTEBOOKS_DIR / spec.name, as_version=4)
        for e in spec.exercises:
            node = next(n for n in ast.parse(python_source(nb.cells[e.cell].source)).body
                        if getattr(n, "name", None) == e.name)
            is_class = isinstance(node, ast.ClassDef)
            n_args = 0 if is_class else len(node.args.posonlyargs + node.args.args) - len(node.args.defaults)
            out.append({"name": e.name, "check_module": e.check_module, "check_function": e.check_function,
                        "n_args": n_args, "is_class": is_class})
    return out


EXERCISES = _exercises()


@pytest.fixture(scope="module")
def best(tmp_path_factory):
    kit = tmp_path_factory.mktemp("kit") / "student-kit"
    write_release(kit)
    env = dict(os.environ, PYTHONPATH=str(kit), COURSE_LIB_QUICK="1", MPLBACKEND="Agg")
    res = subprocess.run([sys.executable, "-c", TRY_ALL, json.dumps(EXERCISES)], cwd=kit, env=env,
                         capture_output=True, text=True, timeout=1200)
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("exercise", [pytest.param(e["name"], marks=pytest.mark.xfail(
    reason="a function of the student kit still passes this exercise", strict=True))
    if e["name"] in STILL_SHIPPED else e["name"] for e in EXERCISES])
def test_no_function_of_the_student_kit_passes_an_exercise(exercise, best):
    score, where = best[exercise]
    assert score < 0.5, f"{where} (in the student kit) earns {score:.0%} of {exercise}'s checks"

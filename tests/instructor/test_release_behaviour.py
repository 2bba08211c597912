"""Nothing the student kit ships solves an exercise, checked by behaviour (issue 33, item 3).

Every callable of the student release's ``course_lib`` -- module functions, classes, their static,
class and instance methods (instances built from the case's own values) -- is called on each
exercise's public inputs, with simple adapters: the arguments in any order (and any subset the
callable takes), as numpy or as torch, and for the bundle adjuster's layout also the cameras and
points apart. Every array in what comes back (the result, its items, values, attributes; transposed
or reshaped to the answer's shape) is compared with the reference answer. None may reproduce it.

The kit's engines that build on exercises (``sfm.lm``'s ``PinholeCamera``/``residuals``/``solve``,
``bundle_adjustment.adjust``, ``nerf.scene.TrainingRays``, ``nerf.inference.march_grid``,
``nerf.render.composite``) call the student's own functions (:mod:`course_lib.exercises`): with no
saved solution here they stop with ``NotImplementedError`` and reproduce nothing.
"""

from __future__ import annotations

import json
import os
import pickle
import subprocess
import sys

import numpy as np
import pytest
import torch

from course_lib.data.synthetic import make_scene
from course_lib.instructor.release import write_release

#: Minutes, not seconds: left out of the quick subset (pytest -m "not slow").
pytestmark = pytest.mark.slow

BEHAVIOUR = r'''
import contextlib, importlib, inspect, io, itertools, json, os, pickle, pkgutil, signal, sys, time, types, warnings

# No callable may start a process: everything that would is refused before the kit is imported (the probe
# runs as one process; RLIMIT_NPROC does not bind root, so the entry points themselves are closed).
class NoProcesses(OSError):  # an OSError, as a failed exec is: callers that handle one handle this
    pass


def _refuse(*_a, **_k):
    raise NoProcesses("the behaviour probe refuses to start processes")


import subprocess, multiprocessing, pty  # noqa: E401
for _name in ("fork", "forkpty", "system", "popen", "posix_spawn", "posix_spawnp", "spawnv", "spawnve", "spawnvp",
              "spawnvpe", "execv", "execve", "execvp", "execvpe", "execl", "execle", "execlp", "execlpe"):
    if hasattr(os, _name):
        setattr(os, _name, _refuse)
subprocess.Popen.__init__ = _refuse
multiprocessing.Process.start = _refuse
pty.fork = _refuse
try:
    import resource
    resource.setrlimit(resource.RLIMIT_NPROC, (64, 64))
except (ImportError, ValueError, OSError):
    pass

import numpy as np, scipy.sparse as sp, torch
import course_lib
TOTAL_SECONDS = float(sys.argv[3])
FIRST_HIT = sys.argv[4] == "first"  # a case's search stops at its first hit (the search's own test: is it found?)
T_START = time.perf_counter()

warnings.filterwarnings("ignore")
cases = pickle.load(open(sys.argv[1], "rb"))
MAX_SELECTIONS = int(sys.argv[2])

callables, classes, unimported = [], [], []
MAIN_PID = os.getpid()
for m in pkgutil.walk_packages(course_lib.__path__, "course_lib."):
    if m.name.startswith("course_lib.instructor") or m.name == "course_lib.__main__":
        continue  # never shipped (the instructor's kit), or the command line (it runs whole commands)
    try:
        mod = importlib.import_module(m.name)
    except Exception as exc:
        unimported.append(f"{m.name}: {type(exc).__name__}: {exc}")
        continue
    for name, obj in vars(mod).items():
        if getattr(obj, "__kit_stand_in__", False) or getattr(obj, "__module__", None) != m.name:
            continue
        if inspect.isfunction(obj):
            if name in ("main", "run") and "cli" in m.name:  # command-line entry points: whole commands
                continue
            callables.append((f"{m.name}.{name}", obj))
        elif inspect.isclass(obj):
            classes.append((f"{m.name}.{name}", obj))
            callables.append((f"{m.name}.{name}", obj))
            for attr, v in vars(obj).items():
                if isinstance(v, (staticmethod, classmethod)):
                    callables.append((f"{m.name}.{name}.{attr}", getattr(obj, attr)))


class Timeout(BaseException):
    pass


#: the alarm stops a call only while one runs: Python runs the handler at its next bytecode, so a SIGALRM that arrives
#: at the end of a long C call can surface after the call returned and the timer was cleared; then it is dropped
ARMED = [False]


def alarm(*_):
    if ARMED[0]:
        raise Timeout()


signal.signal(signal.SIGALRM, alarm)


#: a call may take this long; a callable that spends more on one exercise is not tried further (an exercise's
#: answer takes milliseconds on these inputs: the slow ones draw, wait for input or measure the CPU; they are
#: listed in the result)
CALL_SECONDS, CALLABLE_SECONDS = 0.25, 0.25


def attempt(fn, args):
    try:
        ARMED[0] = True
        signal.setitimer(signal.ITIMER_REAL, CALL_SECONDS)
        try:
            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
                return True, fn(*args)
        finally:  # a Timeout raised here (the alarm came as the call ended) is the call's, caught below
            ARMED[0] = False
            signal.setitimer(signal.ITIMER_REAL, 0)
    except (Exception, Timeout, KeyboardInterrupt):  # KeyboardInterrupt: nerf.train's Ctrl-C handler called twice
        return False, None
    finally:
        if os.getpid() != MAIN_PID:  # a callable that forks: its child leaves at once
            os._exit(0)


def as_numpy(v):
    if isinstance(v, torch.Tensor):
        return v.detach().cpu().numpy()
    if sp.issparse(v):
        return v
    if isinstance(v, (np.ndarray, float, int, np.floating, np.integer, bool, np.bool_)):
        return np.asarray(v)
    return None


def as_torch(v):
    if isinstance(v, np.ndarray) and v.dtype.kind in "fiub":
        return torch.as_tensor(v.astype(np.float32) if v.dtype.kind == "f" else v)
    return v


def as_plain(v):
    return v.detach().cpu().numpy().astype(float) if isinstance(v, torch.Tensor) and v.is_floating_point() else (
        v.detach().cpu().numpy() if isinstance(v, torch.Tensor) else v)


def parts(out, depth=0):
    """Every array in a result: itself, its items, dict values, attributes (two levels)."""
    a = as_numpy(out)
    if a is not None:
        yield a
    if depth >= 2:
        return
    if isinstance(out, dict):
        items = list(out.values())
    elif isinstance(out, (tuple, list)) and len(out) <= 50:
        items = list(out)
    elif hasattr(out, "__dict__") and not isinstance(out, (types.ModuleType, type, torch.nn.Module)):
        items = [v for v in vars(out).values() if not callable(v)]
    else:
        items = []
    for it in items:
        yield from parts(it, depth + 1)


def same(got, want, kind, tol):
    if kind == "pattern":
        try:
            g = sp.csr_matrix(got) if not sp.issparse(got) else got.tocsr()
        except Exception:
            return False
        if g.shape != want.shape:
            return False
        g = g.copy()
        g.eliminate_zeros()
        return (g != 0).toarray().tolist() == (want != 0).tolist()
    if sp.issparse(got):
        return False
    got = np.asarray(got)
    if got.dtype.kind not in "fiub" or got.size != want.size or got.size == 0:
        return False
    shaped = [got.reshape(want.shape)]
    if got.ndim == 2 and got.shape != want.shape:
        shaped.append(got.T.reshape(want.shape))
    for g in shaped:
        g = g.astype(float)
        if not np.isfinite(g).all():
            continue
        if kind == "close" and np.allclose(g, want, atol=tol, rtol=tol):
            return True
        if kind == "mask" and np.array_equal(g.astype(bool), want.astype(bool)):
            return True
        if kind == "projective":
            c = abs(float((g.ravel() @ want.ravel()) / (np.linalg.norm(g) * np.linalg.norm(want) + 1e-300)))
            if c > 1 - tol:
                return True
        if kind == "rotation_set":
            if all(min(np.abs(g[i] - want[j]).max() for i in range(len(g))) < tol for j in range(len(want))):
                return True
    return False


def reproduces(out, case):
    found = list(parts(out))
    if case.get("ba"):  # the bundle adjuster's answer: cameras and points at the minimum of the reprojection error
        K, uv, best = case["ba"]["K"], case["ba"]["uv"], case["ba"]["rms"]
        R = [a for a in found if a.shape == case["ba"]["R_shape"]]
        t = [a for a in found if a.shape == case["ba"]["t_shape"]]
        X = [a for a in found if a.shape == case["ba"]["X_shape"]]
        for Ri, ti, Xi in itertools.product(R, t, X):
            xc = np.einsum("mij,nj->nmi", Ri.astype(float), Xi.astype(float)) + ti[None].astype(float)
            p = xc @ K.T
            e = p[..., :2] / p[..., 2:] - uv
            rms = float(np.sqrt(np.nanmean(np.sum(e ** 2, axis=-1))))
            if rms <= 1.02 * best:
                return True
        return False
    for keys in case["keys"]:
        if all(any(same(a, case["expected"][k][0], case["expected"][k][1], case["expected"][k][2]) for a in found)
               for k in keys):
            return True
    return False


def forms(values, torch_first):
    plain = [as_plain(v) for v in values]
    t = [as_torch(v) for v in plain]
    return [t, plain] if torch_first else [plain, t]


def arity(fn):
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return None
    req = tot = 0
    for p in sig.parameters.values():
        if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD):
            tot += 1
            req += p.default is p.empty
        elif p.kind == p.VAR_POSITIONAL:
            tot = 99
    return req, tot


found, calls, slow, incomplete = {}, 0, set(), []
for name, case in cases.items():
    if time.perf_counter() - T_START > TOTAL_SECONDS:
        incomplete.append(name)
        continue
    pool = case["pool"]
    hits = []
    # instances of the kit's classes built from nothing or from one value of the case: their methods are tried too
    bound = []
    for qual, cls in classes:
        if issubclass(cls, BaseException):
            continue
        for ctor_args in [()] + [(v,) for v in pool]:
            for form in forms(ctor_args, case["torch"]):
                ok, inst = attempt(cls, form)
                if ok and inst is not None:
                    for attr in dir(type(inst)):
                        if attr.startswith("__"):
                            continue
                        v = getattr(type(inst), attr, None)
                        if inspect.isfunction(v):
                            bound.append((f"{qual}(...).{attr}", getattr(inst, attr)))
                    break
    for qual, fn in callables + bound:
        ar = arity(fn)
        if ar is None or qual in slow:
            continue
        req, tot = ar
        spent, hit = 0.0, None
        selections = itertools.chain.from_iterable(
            itertools.islice(itertools.permutations(range(len(pool)), k), MAX_SELECTIONS)
            for k in range(max(req, 1), min(tot, len(pool), req + 1) + 1))
        for idx in selections:
            for form in forms([pool[i] for i in idx], case["torch"]):
                calls += 1
                start = time.perf_counter()
                ok, out = attempt(fn, form)
                spent += time.perf_counter() - start
                if ok and out is not None and reproduces(out, case):
                    hit = f"{qual}{tuple(case['names'][i] for i in idx)}"
                    break
            if hit or spent > CALLABLE_SECONDS:
                break
        if hit:
            hits.append(hit)
            if FIRST_HIT:
                break
        elif spent > CALLABLE_SECONDS:
            slow.add(qual)
    found[name] = hits
print(json.dumps({"found": found, "calls": calls, "slow": sorted(slow), "incomplete": incomplete,
                  "unimported": unimported}))
'''


def _ref(name):
    from course_lib.exercises import implementation

    return implementation(name)


def _case(names, values, expected, keys, torch_first=False, **extra):
    return {"names": names, "pool": values, "expected": expected, "keys": keys, "torch": torch_first, **extra}


def public_cases() -> dict:
    """Each exercise's public inputs (the kit's synthetic scenes) and the reference answer, per component.

    ``expected``: ``{component: (array, comparison, tolerance)}``; ``keys``: the sets of components that
    together are the answer (a callable that returns all of one set reproduces the exercise).
    """
    from scipy.spatial.transform import Rotation

    from course_lib.conventions import projection_matrix
    from course_lib.sfm.bundle_adjustment import pack_params
    from course_lib.sfm.visibility import observation_list

    rng = np.random.default_rng(3)
    sc = make_scene(rng, n_cameras=3, n_points=60, noise_px=0.3, outlier_fraction=0.0, dropout=0.0)
    K = sc.K
    both = np.isfinite(sc.uv[:, 0]).all(1) & np.isfinite(sc.uv[:, 1]).all(1)
    x1, x2, X = sc.uv[both, 0], sc.uv[both, 1], sc.X[both]
    out = make_scene(np.random.default_rng(4), n_cameras=2, n_points=120, noise_px=0.3, outlier_fraction=0.25,
                     dropout=0.0)
    ok = np.isfinite(out.uv).all(axis=(1, 2))
    o1, o2, oX = out.uv[ok, 0], out.uv[ok, 1], out.X[ok]
    cases = {}
    c = lambda name, *a, **k: cases.__setitem__(name, _case(*a, **k))  # noqa: E731

    xn, T = _ref("normalize_points")(x1)
    c("normalize_points", ["x"], [x1], {"x_n": (xn, "close", 1e-6), "T": (T, "close", 1e-6)}, [["x_n"], ["T"]])
    F = _ref("eight_point")(x1, x2)
    c("eight_point", ["x1", "x2"], [x1, x2], {"F": (F, "projective", 1e-6)}, [["F"]])
    d = _ref("sampson_distance")(F, x1, x2)
    c("sampson_distance", ["F", "x1", "x2"], [F, x1, x2], {"d": (d, "close", 1e-6)}, [["d"]])
    rr = _ref("ransac_fundamental")(o1, o2, np.random.default_rng(0), 1.0)
    c("ransac_fundamental", ["x1", "x2", "rng", "threshold_px"], [o1, o2, np.random.default_rng(0), 1.0],
      {"F": (rr.F, "projective", 1e-4), "inliers": (np.asarray(rr.inliers), "mask", 0)}, [["F"], ["inliers"]])
    E = _ref("essential_from_fundamental")(F, K)
    c("essential_from_fundamental", ["F", "K"], [F, K], {"E": (E, "projective", 1e-6)}, [["E"]])
    R4, C4 = _ref("pose_candidates")(E)
    c("pose_candidates", ["E"], [E], {"R": (R4, "rotation_set", 1e-6)}, [["R"]])
    P1, P2 = projection_matrix(K, sc.R_cw[0], sc.t_cw[0]), projection_matrix(K, sc.R_cw[1], sc.t_cw[1])
    Xl = _ref("triangulate_linear")(P1, P2, x1, x2)
    c("triangulate_linear", ["P1", "P2", "x1", "x2"], [P1, P2, x1, x2], {"X": (Xl, "close", 1e-6)}, [["X"]])
    ch = _ref("choose_pose")(R4, C4, K, x1, x2)
    c("choose_pose", ["R", "C", "K", "x1", "x2"], [R4, C4, K, x1, x2],
      {"R_cw": (ch.R_cw, "close", 1e-6), "t_cw": (ch.t_cw, "close", 1e-6)}, [["R_cw", "t_cw"]])
    X0 = X + np.random.default_rng(5).normal(0, 0.05, X.shape)
    uvv = sc.uv[both]
    Xn = _ref("triangulate_nonlinear")(K, sc.R_cw, sc.t_cw, uvv, X0)
    c("triangulate_nonlinear", ["K", "R_cws", "t_cws", "uv", "X0"], [K, sc.R_cw, sc.t_cw, uvv, X0],
      {"X": (Xn, "close", 1e-5)}, [["X"]])
    R, t = _ref("pnp_linear")(X, x2, K)
    c("pnp_linear", ["X", "x", "K"], [X, x2, K], {"R_cw": (R, "close", 1e-6), "t_cw": (t, "close", 1e-6)},
      [["R_cw", "t_cw"]])
    pr = _ref("pnp_ransac")(oX, o2, K, np.random.default_rng(0), 2.0)
    c("pnp_ransac", ["X", "x", "K", "rng", "threshold_px"], [oX, o2, K, np.random.default_rng(0), 2.0],
      {"R_cw": (pr.R_cw, "close", 1e-3), "t_cw": (pr.t_cw, "close", 1e-3)}, [["R_cw", "t_cw"]])
    R0 = Rotation.from_rotvec(Rotation.from_matrix(sc.R_cw[1]).as_rotvec() + 0.01).as_matrix()
    t0 = sc.t_cw[1] + 0.05
    R, t = _ref("pnp_nonlinear")(X, x2, K, R0, t0)
    c("pnp_nonlinear", ["X", "x", "K", "R_cw", "t_cw"], [X, x2, K, R0, t0],
      {"R_cw": (R, "close", 1e-5), "t_cw": (t, "close", 1e-5)}, [["R_cw", "t_cw"]])
    uv = make_scene(np.random.default_rng(6), n_cameras=3, n_points=50, noise_px=0.3, outlier_fraction=0.0).uv
    V = _ref("visibility_matrix")(uv)
    c("visibility_matrix", ["track_uv"], [uv], {"V": (np.asarray(V), "mask", 0)}, [["V"]])
    ba = make_scene(np.random.default_rng(7), n_cameras=3, n_points=40, noise_px=0.5, outlier_fraction=0.0)
    keep = np.isfinite(ba.uv).all(-1).sum(1) >= 2
    buv, bX = ba.uv[keep], ba.X[keep]
    obs = observation_list(buv)
    M, N = len(ba.R_cw), len(bX)
    params = pack_params(ba.R_cw, ba.t_cw, bX)
    r = _ref("reprojection_residuals")(params, M, N, obs.camera_idx, obs.point_idx, obs.uv, ba.K)
    cams, pts = params[:6 * M].reshape(M, 6), params[6 * M:].reshape(N, 3)
    c("reprojection_residuals", ["params", "M", "N", "camera_idx", "point_idx", "uv", "K", "cameras", "points"],
      [params, M, N, obs.camera_idx, obs.point_idx, obs.uv, ba.K, cams, pts], {"r": (r, "close", 1e-6)}, [["r"]])
    S = _ref("jacobian_sparsity")(M, N, obs.camera_idx, obs.point_idx)
    c("jacobian_sparsity", ["M", "N", "camera_idx", "point_idx", "6"], [M, N, obs.camera_idx, obs.point_idx, 6],
      {"S": (S.toarray() != 0, "pattern", 0)}, [["S"]])
    Rb = np.stack([Rotation.from_rotvec(Rotation.from_matrix(Ri).as_rotvec() + 0.01).as_matrix() for Ri in ba.R_cw])
    tb, Xb = ba.t_cw + 0.02, bX + 0.02
    res = _ref("bundle_adjust")(ba.K, Rb, tb, Xb, buv)
    e = res.final_errors
    c("bundle_adjust", ["K", "R_cw", "t_cw", "X", "uv", "cameras", "points", "camera_idx", "point_idx", "uv_obs"],
      [ba.K, Rb, tb, Xb, buv, pack_params(Rb, tb, Xb)[:6 * M].reshape(M, 6), Xb, obs.camera_idx, obs.point_idx,
       obs.uv], {}, [], ba={"K": ba.K, "uv": buv, "rms": float(np.sqrt(np.mean(e ** 2))), "R_shape": (M, 3, 3),
                            "t_shape": (M, 3), "X_shape": (N, 3)})
    # NeRF (notebooks 06-08): float32 tensors, as the stubs document
    H, W = 6, 5
    Kt = torch.tensor([[4.0, 0, 2.0], [0, 4.0, 2.5], [0, 0, 1]])
    c2w = torch.eye(4)
    c2w[:3, :3] = torch.as_tensor(Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix(), dtype=torch.float32)
    c2w[:3, 3] = torch.tensor([0.5, -1.0, 2.0])
    o, dd = _ref("get_rays")(H, W, Kt, c2w)
    c("get_rays", ["H", "W", "K", "c2w"], [H, W, Kt, c2w], {"rays_d": (dd.numpy(), "close", 1e-5)}, [["rays_d"]],
      torch_first=True)
    z = _ref("stratified_samples")(2.0, 6.0, 9, 4, False)
    c("stratified_samples", ["near", "far", "n_samples", "n_rays", "perturb"], [2.0, 6.0, 9, 4, False],
      {"z": (z.numpy(), "close", 1e-6)}, [["z"]], torch_first=True)
    ro, rd = o.reshape(-1, 3)[:4], dd.reshape(-1, 3)[:4]
    zz = 2.0 + torch.rand(4, 9, generator=torch.Generator().manual_seed(0)).sort(-1).values * 4
    pts3 = _ref("query_points")(ro, rd, zz)
    c("query_points", ["rays_o", "rays_d", "z_vals"], [ro, rd, zz], {"pts": (pts3.numpy(), "close", 1e-6)}, [["pts"]],
      torch_first=True)
    xe = torch.rand(7, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1
    enc = _ref("positional_encoding")(xe, 4)
    c("positional_encoding", ["x", "n_freqs"], [xe, 4], {"enc": (enc.numpy(), "close", 1e-5)}, [["enc"]],
      torch_first=True)
    mse = torch.tensor(0.0123)
    c("psnr", ["mse"], [mse], {"psnr": (np.asarray(-10 * np.log10(0.0123)), "close", 1e-5)}, [["psnr"]],
      torch_first=True)
    g = torch.Generator().manual_seed(2)
    rgb, sigma = torch.rand(4, 9, 3, generator=g), 3 * torch.rand(4, 9, generator=g)
    vr = _ref("volume_render")(rgb, sigma, zz, rd)
    c("volume_render", ["rgb", "sigma", "z_vals", "rays_d"], [rgb, sigma, zz, rd],
      {"rgb_map": (vr["rgb_map"].numpy(), "close", 1e-5), "weights": (vr["weights"].numpy(), "close", 1e-5)},
      [["rgb_map"], ["weights"]], torch_first=True)
    return cases


#: the probe's hard limits: wall clock of the search (then it stops and says which exercises it did not try),
#: of the process, and its address space
SEARCH_SECONDS, PROCESS_SECONDS, ADDRESS_SPACE = 300, 420, 8 << 30


def _limits():  # in the probe process, before it starts: no memory blow-up, no process tree
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE, ADDRESS_SPACE))
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    # bounded on its own too: a probe whose test was stopped (Ctrl-C, a killed pytest) must not run on
    resource.setrlimit(resource.RLIMIT_CPU, (PROCESS_SECONDS, PROCESS_SECONDS + 10))
    try:  # and it dies with the test's process (Linux: PR_SET_PDEATHSIG)
        import ctypes
        import signal

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))
    except (OSError, AttributeError):
        pass


def _run(kit, cases, tmp_path, max_selections=48, first_hit=False) -> dict:
    import signal

    path = tmp_path / "cases.pkl"
    path.write_bytes(pickle.dumps(cases))
    env = dict(os.environ, PYTHONPATH=str(kit), MPLBACKEND="Agg", COURSE_LIB_QUICK="1", OMP_NUM_THREADS="1",
               COURSE_LIB_SOLUTIONS=str(tmp_path / "no-solutions"))
    proc = subprocess.Popen([sys.executable, "-c", BEHAVIOUR, str(path), str(max_selections), str(SEARCH_SECONDS),
                             "first" if first_hit else "all"],
                            cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_limits, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=PROCESS_SECONDS)
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # the probe's own session: nothing it started outlives it
        except ProcessLookupError:
            pass
    assert proc.returncode == 0, err[-3000:]
    res = json.loads(out.strip().splitlines()[-1])
    assert res["incomplete"] == [], f"the search ran out of time before {res['incomplete']}"
    assert res["unimported"] == [], res["unimported"]  # every module of the kit is searched
    return res


@pytest.fixture(scope="module")
def cases():
    return public_cases()


@pytest.fixture(scope="module")
def behaviour(cases, tmp_path_factory):
    kit = tmp_path_factory.mktemp("kit") / "student-kit"
    write_release(kit)
    return _run(kit, cases, tmp_path_factory.mktemp("behaviour"))


def test_the_cases_cover_every_exercise_but_the_nerf_class(cases):
    from course_lib.exercises import EXERCISES

    assert set(cases) == set(EXERCISES) - {"NeRF"}  # the class: tests/instructor/test_kit_holds_no_solution.py


def test_nothing_shipped_reproduces_an_exercise(behaviour):
    found = {k: v for k, v in behaviour["found"].items() if v}
    print(f"{behaviour['calls']} calls of the kit's callables on the exercises' public inputs")
    assert found == {}, found


def test_the_search_finds_an_engine_that_answers(cases, tmp_path):
    """The instructor's library (the references and the engines before issue 33) is found out."""
    from course_lib.paths import REPO_ROOT

    res = _run(REPO_ROOT, {k: cases[k] for k in ("reprojection_residuals", "jacobian_sparsity", "get_rays",
                                                 "essential_from_fundamental")}, tmp_path, max_selections=40,
               first_hit=True)
    for name, hits in res["found"].items():
        assert hits, f"the reference of {name} in the instructor's kit was not found"

"""The separation of grading (issue 14): the wire format and the student's process, without the notebooks.

* The wire format carries data only (JSON + ``np.save`` arrays read with ``allow_pickle=False``):
  every kind of value the checks exchange survives a round trip with its type; an object array
  is refused; a numpy generator continues the same stream on the other side.
* A :class:`~course_lib.instructor.student_process.StudentProcess` imports the student release's
  ``course_lib`` (the reference solutions are not there), sees neither the instructor's kit nor
  the grader's secret folders (bubblewrap's sandbox, checked before the student's code runs),
  cannot write outside its temporary folder or reach the network, and answers by handle for an
  ``nn.Module``, whose forward pass uses the parameters the grader sets.
* Fail closed: without bubblewrap, or where it cannot make a sandbox, or where the sandbox it makes
  does not check out, no code of the student's runs; ``insecure`` runs without one and says so.
"""

from __future__ import annotations

import collections
import dataclasses
import io
import os

import numpy as np
import pytest

from course_lib.instructor.remote import RemoteFunction
from course_lib.instructor.sandbox import jail, wire
from course_lib.instructor.settings import Isolation, student_library
from course_lib.instructor.student_process import StudentProcess, StudentProcessEnded
from course_lib.paths import REPO_ROOT
from course_lib.instructor.notebooks import NOTEBOOKS_DIR


@dataclasses.dataclass
class Result:
    F: np.ndarray
    n_iters: int


Pose = collections.namedtuple("Pose", "R_cw t_cw")


def round_trip(value):
    arrays: list = []
    tree = wire.encode(value, arrays)
    head, arrs = wire.unpack(wire.pack({"v": tree}, arrays))
    return wire.decode(head["v"], arrs)


@pytest.mark.parametrize("value", [
    3, -2**70, 2.5, float("inf"), 1 - 2j, "text", None, False, (1, [2.0, "x"]), {"a": 1, (2, 3): None},
    np.arange(6.0).reshape(2, 3), np.array(7.0), np.float32(1.5), np.array([True, False]),
    Pose(np.eye(3), np.zeros(3)), Result(np.ones((3, 3)), 12),
])
def test_round_trip_keeps_values_and_types(value):
    out = round_trip(value)
    assert type(out).__name__ == type(value).__name__
    if isinstance(value, np.ndarray) or isinstance(value, np.generic):
        assert out.dtype == value.dtype and np.shape(out) == np.shape(value) and np.array_equal(out, value)
    elif isinstance(value, Result):
        assert np.array_equal(out.F, value.F) and out.n_iters == 12
    elif isinstance(value, Pose):
        assert out._fields == ("R_cw", "t_cw") and np.array_equal(out.R_cw, value.R_cw)
    elif isinstance(value, float) or isinstance(value, complex) or value is None or isinstance(value, (int, str)):
        assert out == value
    else:
        assert repr(out) == repr(value)


def test_tensors_sparse_and_generators_round_trip():
    torch = pytest.importorskip("torch")
    import scipy.sparse as sp

    t = round_trip(torch.arange(4.0).requires_grad_(True))
    assert isinstance(t, torch.Tensor) and t.requires_grad and t.tolist() == [0, 1, 2, 3]
    m = round_trip(sp.csr_matrix(np.eye(3)))
    assert sp.issparse(m) and m.format == "csr" and np.array_equal(m.toarray(), np.eye(3))
    g = np.random.default_rng(5)
    g2 = round_trip(g)
    assert np.array_equal(g.integers(0, 10**6, 5), g2.integers(0, 10**6, 5))
    tg = torch.Generator().manual_seed(3)
    tg2 = round_trip(tg)
    assert torch.equal(torch.rand(3, generator=tg), torch.rand(3, generator=tg2))


def test_object_arrays_and_pickles_are_refused():
    with pytest.raises(wire.WireError, match="dtype=object"):
        wire.encode(np.array([object()]), [])
    with pytest.raises(wire.WireError, match="cannot be sent"):
        wire.encode(object(), [])
    buf = io.BytesIO()
    np.save(buf, np.array([{"a": 1}], dtype=object), allow_pickle=True)  # a pickle inside an .npy
    raw = buf.getvalue()
    import json
    import struct

    head = json.dumps({"v": {"$": "nd", "a": 0}}).encode()
    msg = struct.pack("<II", len(head), 1) + head + struct.pack("<Q", len(raw)) + raw
    with pytest.raises(wire.WireError, match="Python objects"):
        wire.unpack(msg)


@pytest.fixture(scope="module")
def iso(tmp_path_factory):
    lib = student_library(tmp_path_factory.mktemp("student-kit"))
    os.chmod(lib, 0o755)  # the student's uid reads it (the grader's own student library is made so)
    secret = tmp_path_factory.mktemp("grader-secret")
    (secret / "answers.txt").write_text("42")
    return Isolation.for_grading(lib, [secret], NOTEBOOKS_DIR)


PROBE = """
import os, socket

def probe(secret_file, outside_file):
    out = {}
    for key, path in (("reference", os.path.join(%r, "course_lib", "sfm", "fundamental.py")), ("secret", secret_file)):
        try:
            open(path).read()
            out[key] = "read"
        except OSError as exc:
            out[key] = type(exc).__name__
    try:
        with open(outside_file, "w") as f:
            f.write("x")
        out["write outside"] = "written"
    except OSError as exc:
        out["write outside"] = str(exc)
    with open("mine.txt", "w") as f:
        out["write own folder"] = f.write("ok")
    try:
        socket.create_connection(("1.1.1.1", 53), timeout=2)
        out["network"] = "connected"
    except OSError as exc:
        out["network"] = type(exc).__name__
    try:
        import course_lib.sfm.fundamental  # noqa: F401
        out["import reference"] = "imported"
    except ImportError as exc:
        out["import reference"] = type(exc).__name__
    import course_lib
    out["course_lib"] = course_lib.__file__
    out["processes"] = len([d for d in os.listdir("/proc") if d.isdigit()])
    return out
""" % str(REPO_ROOT)


def test_the_student_process_sees_only_the_release_and_its_folder(iso, tmp_path):
    outside = tmp_path / "outside.txt"
    with StudentProcess(iso, PROBE, "probe", None, 60) as proc:
        box = proc.sandbox
        out = RemoteFunction(proc, "probe")(str(iso.hide[0] / "answers.txt"), str(outside))
    assert out["course_lib"].startswith(str(iso.library)), out
    assert out["import reference"] == "ModuleNotFoundError"
    assert out["write own folder"] == 2
    assert box["namespaces"] and box["read_only"] and box["tool"] == "bubblewrap", box
    assert out["reference"] == out["secret"] == "FileNotFoundError", out
    assert ("No such file" in out["write outside"] or "Read-only" in out["write outside"]) and not outside.exists(), out
    assert out["network"] != "connected" and out["processes"] <= 2, out


def test_exceptions_exit_and_time_limit(iso):
    code = ("import os, time\n"
            "def f(kind):\n"
            "    if kind == 'raise':\n        raise KeyError('k')\n"
            "    if kind == 'exit':\n        os._exit(3)\n"
            "    while True:\n        time.sleep(0.01)\n")
    with StudentProcess(iso, code, "f", None, 30) as proc:
        with pytest.raises(KeyError, match="line 4 of your exercise code"):
            RemoteFunction(proc, "f")("raise")
        with pytest.raises(StudentProcessEnded, match=r"your function ended the process with os._exit\(3\)"):
            RemoteFunction(proc, "f")("exit")
        with pytest.raises(StudentProcessEnded):  # every later call fails at once
            RemoteFunction(proc, "f")("raise")
    with StudentProcess(iso, code, "f", None, 3) as proc:
        with pytest.raises(StudentProcessEnded, match=r"stopped after \d+\.\d s.*limit of one exercise is 3 s"):
            RemoteFunction(proc, "f")("loop")
        assert proc.event == "timeout"


def test_a_module_stays_in_the_student_process_and_uses_the_graders_parameters(iso):
    torch = pytest.importorskip("torch")
    code = ("import torch\n"
            "class Net(torch.nn.Module):\n"
            "    def __init__(self, width=4):\n"
            "        super().__init__()\n"
            "        self.a = torch.nn.Linear(3, width)\n"
            "        self.b = torch.nn.Linear(width, 1)\n"
            "    def forward(self, x):\n"
            "        return self.b(torch.relu(self.a(x)))[..., 0]\n")
    with StudentProcess(iso, code, "Net", None, 60, torch=True) as proc:
        torch.manual_seed(0)
        net = RemoteFunction(proc, "Net")(width=5)
        assert isinstance(net, torch.nn.Module) and type(net).__name__ == "Net"
        layers = [(m.in_features, m.out_features) for m in net.modules() if isinstance(m, torch.nn.Linear)]
        assert layers == [(3, 5), (5, 1)] and sum(p.numel() for p in net.parameters()) == 3 * 5 + 5 + 5 + 1
        local = torch.nn.Sequential(torch.nn.Linear(3, 5), torch.nn.ReLU(), torch.nn.Linear(5, 1))
        with torch.no_grad():
            for p, q in zip(net.parameters(), local.parameters()):
                p.copy_(torch.randn_like(p))
                q.copy_(p)
            x = torch.randn(7, 3)
            assert torch.allclose(net(x), local(x)[..., 0], atol=1e-6)


def test_insecure_runs_without_a_sandbox_and_says_so(iso):
    plain = Isolation(iso.library, iso.hide, iso.keep, insecure=True)
    code = "import course_lib\ndef where():\n    return course_lib.__file__\n"
    with StudentProcess(plain, code, "where", None, 30) as proc:
        assert proc.sandbox["namespaces"] is False and "--insecure" in proc.sandbox["note"]
        assert RemoteFunction(proc, "where")().startswith(str(iso.library))


def test_nothing_of_the_student_survives_its_process(iso):
    """A student's process that leaves its process group (setsid) and forks a looping child is still gone at the end."""
    code = ("import os, time\n"
            "def f():\n"
            "    os.setsid()\n"
            "    if os.fork() == 0:\n"
            "        while True:\n            pass\n"
            "    while True:\n        time.sleep(0.1)\n")
    proc = StudentProcess(iso, code, "f", None, 3)
    namespace = f"pid:[{proc.started.info['pid-namespace']}]"
    with pytest.raises(StudentProcessEnded, match="stopped after 3"):
        RemoteFunction(proc, "f")()
    proc.close()
    import time

    time.sleep(0.5)
    left = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            dead = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[0] == "Z"  # a zombie holds nothing
            if os.readlink(f"/proc/{pid}/ns/pid") == namespace and not dead:
                left.append(pid)
        except OSError:
            pass
    assert not left, f"processes of the student still running: {left}"


# ------------------------------------------------------------------ issue 18: a submission is data, an allow-listed view


def test_a_submission_is_copied_as_regular_files_only(tmp_path):
    from course_lib.instructor.submission import copy_submission

    sub, other = tmp_path / "sub", tmp_path / "other"
    (sub / "notebooks").mkdir(parents=True)
    other.mkdir()
    (other / "secret.txt").write_text("another student's")
    (sub / "notebooks" / "a.ipynb").write_text("{}")
    (sub / "notebooks" / "inside.ipynb").symlink_to("a.ipynb")
    (sub / "notebooks" / "outside.txt").symlink_to(other / "secret.txt")
    (sub / "loop").symlink_to(sub)  # a cycle
    (sub / "up").symlink_to("..")
    (sub / "broken").symlink_to("nowhere")
    os.mkfifo(sub / "notebooks" / "fifo.ipynb")
    (sub / "big.bin").write_bytes(b"x" * 2000)
    out = copy_submission(sub, tmp_path / "copy", max_file_bytes=1000)
    files = sorted(str(p.relative_to(out.root)) for p in out.root.rglob("*"))
    assert files == ["notebooks", "notebooks/a.ipynb", "notebooks/inside.ipynb"], files
    assert not any(p.is_symlink() for p in out.root.rglob("*"))
    assert (out.root / "notebooks" / "inside.ipynb").read_text() == "{}"
    refused = " | ".join(out.refused)
    for what in ("notebooks/outside.txt: a symbolic link to a place outside", "loop: a link to a folder already copied",
                 "up: a symbolic link to a place outside", "broken: a broken symbolic link",
                 "notebooks/fifo.ipynb: not a regular file", "big.bin: 2000 bytes"):
        assert what in refused, refused


def test_long_paths_and_odd_names_are_left_out_and_reported(tmp_path):
    """Issue 40, item 5: sixteen nested folders of 253-character names (the copy's path would pass the system's 4096),
    names with control characters or bytes that are not text: left out with a reason, never an exception."""
    from course_lib.instructor.submission import MAX_PATH_BYTES, copy_submission

    sub = tmp_path / "sub"
    (sub / "notebooks").mkdir(parents=True)
    (sub / "notebooks" / "a.ipynb").write_text("{}")
    fd = os.open(sub, os.O_RDONLY)
    for k in range(16):  # made relative to each folder: the whole path is past what the system takes
        os.mkdir(chr(97 + k) * 253, dir_fd=fd)
        fd, old = os.open(chr(97 + k) * 253, os.O_RDONLY, dir_fd=fd), fd
        os.close(old)
    os.close(os.open("x.py", os.O_WRONLY | os.O_CREAT, dir_fd=fd))
    os.close(fd)
    (sub / "new\nline.md").write_text("x")
    with open(os.fsencode(sub) + b"/bad\xff\xfename.txt", "w") as f:
        f.write("x")
    out = copy_submission(sub, tmp_path / ("c" * 200) / "copy")
    files = sorted(str(p.relative_to(out.root)) for p in out.root.rglob("*"))
    assert "notebooks/a.ipynb" in files and not any(f.endswith("x.py") or "name" in f for f in files), files
    refused = " | ".join(out.refused)
    assert f"a path longer than {MAX_PATH_BYTES} bytes" in refused, refused
    assert refused.count("a name with bytes that are not text or with control characters") == 2, refused


def test_malformed_replies_are_refused_before_anything_is_allocated():
    import json
    import struct

    def message(head: dict, records: list[bytes]) -> bytes:
        h = json.dumps(head).encode()
        return struct.pack("<II", len(h), len(records)) + h + b"".join(struct.pack("<Q", len(r)) + r for r in records)

    buf = io.BytesIO()
    np.save(buf, np.zeros(4))
    npy = buf.getvalue()
    lying = npy.replace(b"(4,)", b"(400000000000,)".ljust(4))  # a header that claims 3 TB
    for records, phrase in (([lying[:len(npy)]], "size differs|not a .npy|malformed"),
                            ([b"PK\x03\x04" + b"\0" * 60], "not a .npy record"),
                            ([npy[:-8]], "size differs")):
        with pytest.raises((wire.WireError, ValueError), match=phrase):
            wire.unpack(message({"v": {"$": "nd", "a": 0}}, records))
    with pytest.raises(wire.WireError):
        wire.unpack(struct.pack("<II", 10, 1 << 30) + b"{}")  # more records than bytes


VIEW = """
import os

def view():
    status = dict(line.split(":", 1) for line in open("/proc/self/status").read().splitlines() if ":" in line)
    try:
        os.mkdir("/usr/lib/x")
        write = "written"
    except OSError as exc:
        write = type(exc).__name__
    return {"root": sorted(os.listdir("/")), "cap": status["CapEff"].strip(), "uid": os.getuid(), "write": write,
            "pids": sorted(int(p) for p in os.listdir("/proc") if p.isdigit())}
"""


def test_the_student_process_sees_an_allow_list_without_privileges(iso):
    with StudentProcess(iso, VIEW, "view", None, 60) as proc:
        box = proc.sandbox
        out = RemoteFunction(proc, "view")()
    allowed = {p.strip("/").split("/")[0] for p in iso.read_only()} | {"dev", "proc", "tmp", "grader"}
    assert set(out["root"]) <= allowed, set(out["root"]) - allowed
    assert out["cap"] == "0000000000000000" and out["uid"] != 0 and out["write"] in ("OSError", "PermissionError")
    assert max(out["pids"]) <= 3, out["pids"]
    assert "IPC" in box["namespaces list"] and box["capabilities"].startswith("none"), box
    assert "memory" in box and "processes" in box and "disk" in box, box
    if os.getuid() == 0:  # never the grading user
        from course_lib.instructor.settings import STUDENT_UID

        assert out["uid"] == STUDENT_UID and box["uid"].startswith(str(STUDENT_UID)), (out["uid"], box)


def test_a_reply_larger_than_any_exercise_returns_ends_only_that_process(iso):
    code = ("import os, stat\n"
            "def f():\n"
            "    for name in os.listdir('/proc/self/fd'):\n"
            "        fd = int(name)\n"
            "        try:\n"
            "            if stat.S_ISFIFO(os.fstat(fd).st_mode):\n"
            "                os.write(fd, (2**31 - 9).to_bytes(8, 'little') + b'x' * 1000)\n"
            "        except OSError:\n"
            "            pass\n"
            "    return 1\n")
    with StudentProcess(iso, code, "f", None, 30) as proc:
        with pytest.raises(StudentProcessEnded, match="more than any exercise returns"):
            RemoteFunction(proc, "f")()


# ------------------------------------------------------------------ issue 33: fail closed, replies bounded before anything is built


def test_a_sandbox_report_that_says_nothing_is_refused_on_every_count(iso):
    """verify() names everything an empty (or forged) report lacks: no grading on a sandbox it cannot confirm."""
    missing = " | ".join(jail.verify({}, {}, seccomp=True))
    for what in ("namespace of its own", "capabilities left", "no_new_privs", "no seccomp filter", "root is writable",
                 "network devices"):
        assert what in missing, (what, missing)
    line = jail.refusal("the sandbox is not isolated: " + missing, jail.REPORT)
    assert "\n" not in line and line.startswith("refusing to run the students' code:") and "--insecure" in line


def test_wire_floods_are_refused_before_anything_is_built():
    import json
    import struct

    def message(head: bytes, n_arrays: int = 0, records: bytes = b"") -> bytes:
        return struct.pack("<II", len(head), n_arrays) + head + records

    with pytest.raises(wire.WireError, match="more than 200000 values"):
        wire.unpack(message(b"[" + b"0," * 250_000 + b"0]"))
    with pytest.raises(wire.WireError, match="array count"):
        wire.unpack(message(b"{}", wire.MAX_ARRAYS + 1, b"\0" * 8 * (wire.MAX_ARRAYS + 1)))
    with pytest.raises(wire.WireError, match="nested too deeply|malformed"):
        wire.unpack(message(b"[" * 100_000 + b"]" * 100_000))
    tree = {"$": "tuple", "v": [{"$": "sparse", "shape": [2 ** 17, 2 ** 17], "a": 0, "fmt": "coo"},
                                {"$": "module", "h": 1, "params": [], "linear": [[8, 8, True]]}]}
    kinds = sorted((d[0], d[1]) for d in wire.declared(tree))
    assert kinds == [("module", "value[1]"), ("sparse", "value[0]")], kinds
    with pytest.raises(wire.WireError, match="sends no weight"):
        wire.check_module_tree(tree["v"][1], [])
    assert wire.check_module_tree({"params": [["w", 0], ["b", 1]], "linear": [[3, 2, True]]},
                                  [np.zeros((2, 3)), np.zeros(2)]) == [(3, 2, True)]
    assert json.dumps(tree)  # (the tree itself is plain data)


def test_a_sparse_reply_far_larger_than_the_expected_answer_is_not_built(iso):
    code = ("import scipy.sparse as sp\n"
            "def f(n, transposed=False):\n"
            "    return sp.coo_matrix(([1.0], ([0], [0])), shape=(3, n) if transposed else (n, n))\n")
    import scipy.sparse as sp

    with StudentProcess(iso, code, "f", None, 30) as proc:
        f = RemoteFunction(proc, "f", reference=lambda n, transposed=False: sp.eye(n, 3, format="csr"))
        assert f(5, transposed=True).shape == (3, 5)  # another shape, small: the check names the mistake
        with pytest.raises(ValueError, match=r"sparse matrix of shape \(131072, 131072\).*did not build it"):
            f(2 ** 17)
        with pytest.raises(ValueError, match="did not build it"):  # no reference: the plain bound
            RemoteFunction(proc, "f")(2 ** 17)
        assert not proc.ended

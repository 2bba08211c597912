"""The process that runs a student's code during grading: the sandbox, the wire format, the server.

This file is run as a *script* by the grader (``python -S -E sandbox.py ...``), never imported by
the student's code, and needs nothing but the standard library (numpy and torch are imported only
when the student's code or the data need them). The grader imports it too, for :func:`encode`,
:func:`decode`, :func:`write_frame` and :func:`read_frame`.

Two commands:

``child.py serve CONFIG.json``
    Enter the sandbox (below), put ``CONFIG["path"]`` (the student release's library) first on
    ``sys.path``, run the student's extracted exercise code in a fresh ``__main__`` module, then
    answer calls from the grader on file descriptors 3 (requests) and 4 (replies): each request
    names a function or an object handle and carries its arguments as data; each reply carries the
    result as data, or the exception the student's code raised. Objects that are not data (an
    ``nn.Module``) stay here and are answered by handle. The earlier exercises named in
    ``CONFIG["oracle"]`` are rebound, after the student's code ran, to :func:`oracle_stub`s: while a
    call runs, a stub sends its arguments to the grader (an ``oracle`` event on the reply pipe) and
    waits for the answer on the request pipe (:mod:`course_lib.instructor.oracle`).

``child.py exec CONFIG.json -- PROGRAM ARGS...``
    Enter the sandbox and ``execv`` a program (nbval of the student's notebook). The sandbox's
    report goes to the grader's file ``report_fd``; after the program ended, the launcher (outside
    the PID namespace, unseen by the program) copies the file ``collect`` out to ``collect_fd``.

The sandbox (``CONFIG["sandbox"]``), entered before any student code runs:

* resource limits are set by the grader in ``preexec_fn`` (CPU seconds, address space, file size,
  number of processes), which also moves the process into a cgroup of its own where the grader can
  make one (totals of memory and processes for the whole tree: :mod:`course_lib.instructor.cgroups`);
* where the kernel allows unprivileged user namespaces: new user, mount, network, PID and IPC
  namespaces (no network: only a loopback device; System V IPC objects end with the sandbox); the
  process is not root inside. A **fresh root** is built from bind mounts of an allow-list
  (``root["read_only"]``: the Python installation, the student release, system libraries; folders
  in ``root["hide"]`` inside them covered by empty folders), a few device files, a /proc of the new
  PID namespace, and one size-limited tmpfs for everything writable (the working folder, filled with
  a copy of ``root["seed"]``, /tmp and /dev/shm); then ``pivot_root`` and the host's root is
  detached. Every capability is dropped and ``no_new_privs`` set, so the mounts cannot be undone.
  Without user namespaces only the resource limits and the import path apply (the working copy is
  then made on the host's disk); :func:`enter_sandbox` reports what was enforced, and ``serve``
  sends that report as its first frame, before any of the student's code runs.

The wire format never unpickles: a frame is a JSON header plus numpy arrays written with
``np.save`` and read back as ``.npy`` records of numeric dtypes whose size is checked against their
header before anything is allocated (:func:`unpack`); a reply is at most :data:`MAX_REPLY` bytes. Values: None, bool, int, float,
complex, str, tuple, list, dict, namedtuple, dataclass-like records (their public attributes),
numpy arrays and scalars, scipy sparse matrices, torch tensors, numpy and torch random
generators (their state).
"""

from __future__ import annotations

import io
import json
import os
import struct
import sys

MAX_REQUEST = 1 << 31  # bytes of one message from the grader (the hidden inputs)
#: Bytes of one reply from the student's process: what an exercise can honestly return (the largest honest reply
#: of the kit's exercises, a NeRF model's parameters or a rendered image, is a few MiB; see benchmarks/grade_speed.py).
MAX_REPLY = 64 << 20
_JSON_LIMIT = 16 << 20

# ---------------------------------------------------------------------------------------------
# Wire format
# ---------------------------------------------------------------------------------------------


class WireError(Exception):
    """A message that cannot be encoded or decoded."""


def _np():
    import numpy as np

    return np


def _torch():
    return sys.modules.get("torch")


def _ident(name: str, default: str = "Result") -> str:
    name = str(name)
    return name if name.isidentifier() and not name.startswith("__") and len(name) < 80 else default


def encode(obj, arrays: list, callbacks: list | None = None, handles: dict | None = None, depth: int = 0):
    """``obj`` as a JSON-able tree; arrays are appended to ``arrays`` and referred to by index.

    ``callbacks`` (grader side): callables in the arguments are sent as numbered callbacks.
    ``handles`` (student side): ``nn.Module`` results stay in this process, sent as a handle.
    """
    if depth > 50:
        raise WireError("the value is nested more than 50 levels deep")
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, int):
        return obj if type(obj) is int else int(obj)
    if isinstance(obj, float):
        return {"$": "float", "v": repr(float(obj))}
    if isinstance(obj, complex):
        return {"$": "complex", "re": repr(obj.real), "im": repr(obj.imag)}
    np = sys.modules.get("numpy")
    torch = _torch()
    if np is not None:
        if isinstance(obj, np.ndarray) or isinstance(obj, np.generic):
            arr = np.asarray(obj)
            if arr.dtype.hasobject:
                raise WireError("an array of Python objects (dtype=object) cannot be sent; use a numeric array")
            arrays.append(np.asarray(arr))
            return {"$": "nd" if isinstance(obj, np.ndarray) else "npscalar", "a": len(arrays) - 1}
        if isinstance(obj, np.random.Generator):
            return {"$": "rng", "s": encode(obj.bit_generator.state, arrays, depth=depth + 1)}
    if torch is not None:
        if isinstance(obj, torch.Tensor):
            t = obj.detach().cpu()
            if t.dtype == torch.bfloat16:
                t = t.float()
            arrays.append(np.asarray(t.numpy()))
            return {"$": "torch", "a": len(arrays) - 1, "grad": bool(obj.requires_grad)}
        if isinstance(obj, torch.Generator):
            arrays.append(obj.get_state().numpy().copy())
            return {"$": "tgen", "a": len(arrays) - 1}
        if handles is not None and isinstance(obj, torch.nn.Module):
            return _module_handle(obj, arrays, handles)
    sparse = sys.modules.get("scipy.sparse")
    if sparse is not None and sparse.issparse(obj):
        coo = obj.tocoo()
        for a in (coo.row, coo.col, coo.data):
            arrays.append(np.asarray(a))
        return {"$": "sparse", "fmt": _ident(obj.format, "coo"), "shape": [int(n) for n in coo.shape],
                "array": not isinstance(obj, sparse.spmatrix), "a": len(arrays) - 3}
    if isinstance(obj, tuple) and hasattr(obj, "_fields"):
        return {"$": "ntuple", "n": _ident(type(obj).__name__), "f": [_ident(f, "field") for f in obj._fields],
                "v": [encode(v, arrays, callbacks, handles, depth + 1) for v in obj]}
    if isinstance(obj, (tuple, list)):
        return {"$": "tuple" if isinstance(obj, tuple) else "list",
                "v": [encode(v, arrays, callbacks, handles, depth + 1) for v in obj]}
    if isinstance(obj, dict):
        return {"$": "dict", "k": [encode(k, arrays, callbacks, handles, depth + 1) for k in obj],
                "v": [encode(v, arrays, callbacks, handles, depth + 1) for v in obj.values()]}
    if callbacks is not None and callable(obj) and not isinstance(obj, type):
        callbacks.append(obj)
        return {"$": "cb", "i": len(callbacks) - 1}
    fields = getattr(obj, "__dataclass_fields__", None)
    attrs = {k: getattr(obj, k) for k in fields} if isinstance(fields, dict) and not isinstance(obj, type) else None
    if attrs is None and type(obj).__module__ == "__main__" and isinstance(getattr(obj, "__dict__", None), dict) \
            and not isinstance(obj, type) and not callable(obj):  # a plain class of the student's own notebook
        attrs = {k: v for k, v in vars(obj).items() if not k.startswith("_")}
    if attrs is not None:
        return {"$": "record", "n": _ident(type(obj).__name__),
                "f": {_ident(k, "field"): encode(v, arrays, callbacks, handles, depth + 1) for k, v in attrs.items()}}
    raise WireError(f"a value of type {type(obj).__name__} cannot be sent between your code and the grader "
                    "(use numbers, arrays, tensors, tuples, lists, dicts or a dataclass of them)")


class Record:
    """A dataclass-like result received from the student's process (its public attributes)."""

    def __init__(self, **fields):
        self.__dict__.update(fields)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({', '.join(f'{k}=...' for k in self.__dict__)})"


_TYPES: dict = {}


def _record_type(name: str):
    if len(_TYPES) > 4096:  # a reply cannot grow the grader by naming new types
        _TYPES.clear()
    if ("record", name) not in _TYPES:
        _TYPES[("record", name)] = type(name, (Record,), {})
    return _TYPES[("record", name)]


def _ntuple_type(name: str, fields: tuple):
    import collections

    key = ("ntuple", name, fields)
    if len(fields) > 64 or len(_TYPES) > 4096:
        return None  # a plain tuple
    if key not in _TYPES:
        try:
            _TYPES[key] = collections.namedtuple(name, fields)
        except ValueError:
            _TYPES[key] = None
    return _TYPES[key]


def decode(tree, arrays: list, callback=None, module_proxy=None):
    """The value of an :func:`encode` tree (``callback(i)``: a stand-in for callback ``i``)."""
    if tree is None or isinstance(tree, (bool, int, str)):
        return tree
    if isinstance(tree, list):
        raise WireError("malformed message")
    kind = tree.get("$")
    sub = lambda v: decode(v, arrays, callback, module_proxy)  # noqa: E731
    if kind == "float":
        return float(tree["v"])
    if kind == "complex":
        return complex(float(tree["re"]), float(tree["im"]))
    if kind in ("nd", "npscalar"):
        a = arrays[int(tree["a"])]
        return a if kind == "nd" else a[()]
    if kind == "torch":
        import torch

        t = torch.from_numpy(arrays[int(tree["a"])].copy())
        return t.requires_grad_(True) if tree.get("grad") and t.is_floating_point() else t
    if kind == "rng":
        np = _np()
        state = sub(tree["s"])
        bg = getattr(np.random, _ident(state.get("bit_generator", "PCG64"), "PCG64"), None)
        if bg is None or not isinstance(bg, type) or not issubclass(bg, np.random.BitGenerator):
            raise WireError("unknown bit generator")
        gen = bg()
        gen.state = state
        return np.random.Generator(gen)
    if kind == "tgen":
        import torch

        g = torch.Generator()
        g.set_state(torch.from_numpy(arrays[int(tree["a"])].copy()))
        return g
    if kind == "ntuple":
        t = _ntuple_type(_ident(tree["n"]), tuple(_ident(f, "field") for f in tree["f"]))
        vals = [sub(v) for v in tree["v"]]
        return t(*vals) if t is not None and len(vals) == len(t._fields) else tuple(vals)
    if kind == "tuple":
        return tuple(sub(v) for v in tree["v"])
    if kind == "list":
        return [sub(v) for v in tree["v"]]
    if kind == "dict":
        return {sub(k): sub(v) for k, v in zip(tree["k"], tree["v"])}
    if kind == "record":
        return _record_type(_ident(tree["n"]))(**{_ident(k, "field"): sub(v) for k, v in tree["f"].items()})
    if kind == "sparse":
        import scipy.sparse as sp

        k = int(tree["a"])
        row, col, data = arrays[k], arrays[k + 1], arrays[k + 2]
        shape = tuple(int(n) for n in tree["shape"])
        m = (sp.coo_array if tree.get("array") else sp.coo_matrix)((data, (row, col)), shape=shape)
        fmt = _ident(tree.get("fmt", "coo"), "coo")
        return m.asformat(fmt) if fmt in ("csr", "csc", "coo", "lil", "dok", "bsr", "dia") else m
    if kind == "cb":
        if callback is None:
            raise WireError("a callback where none is expected")
        return callback(int(tree["i"]))
    if kind == "module":
        if module_proxy is None:
            raise WireError("an object handle where none is expected")
        return module_proxy(tree, arrays)
    raise WireError(f"unknown value kind {kind!r}")


def _module_handle(module, arrays: list, handles: dict) -> dict:
    """A student's ``nn.Module``: it stays here; the grader gets its parameters and linear layers."""
    import torch

    h = len(handles) + 1
    handles[h] = module
    params = []
    for name, p in module.named_parameters():
        arrays.append(p.detach().cpu().numpy().copy())
        params.append([name, len(arrays) - 1])
    layers = [[int(m.in_features), int(m.out_features), m.bias is not None] for m in module.modules()
              if isinstance(m, torch.nn.Linear)]
    return {"$": "module", "h": h, "n": _ident(type(module).__name__, "Module"), "params": params, "linear": layers}


def pack(header: dict, arrays: list) -> bytes:
    np = sys.modules.get("numpy")
    head = json.dumps(header, allow_nan=True).encode()
    parts = [struct.pack("<II", len(head), len(arrays)), head]
    for a in arrays:
        buf = io.BytesIO()
        np.save(buf, a, allow_pickle=False)
        b = buf.getvalue()
        parts += [struct.pack("<Q", len(b)), b]
    return b"".join(parts)


def _load_npy(data) -> object:
    """One ``.npy`` record as a numpy array: numeric and boolean dtypes only, its size checked against its header.

    A ``.npz`` archive, a pickle, an object array or a header that claims more data than was sent is refused
    (:class:`WireError`) before anything is allocated.
    """
    np = _np()
    fmt = np.lib.format
    fp = io.BytesIO(data)
    if bytes(data[:6]) != b"\x93NUMPY":
        raise WireError("malformed message (an array that is not a .npy record)")
    version = fmt.read_magic(fp)
    read_header = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
    shape, fortran, dtype = read_header(fp)
    if dtype.hasobject or dtype.kind not in "biufcSUMmV":
        raise WireError("malformed message (an array of Python objects)")
    count = 1
    for n in shape:
        count *= int(n)
    start = fp.tell()
    if count * dtype.itemsize != len(data) - start:
        raise WireError("malformed message (an array whose size differs from its header)")
    flat = np.frombuffer(bytearray(data[start:]), dtype=dtype, count=count)
    return flat.reshape(shape, order="F" if fortran else "C")


def unpack(data) -> tuple[dict, list]:
    """The header and arrays of one message; :class:`WireError` (or ``ValueError``) for anything malformed."""
    if len(data) < 8:
        raise WireError("malformed message")
    n_head, n_arr = struct.unpack_from("<II", data, 0)
    if n_head > min(_JSON_LIMIT, len(data) - 8) or n_arr > (len(data) - 8 - n_head) // 8:
        raise WireError("malformed message")
    pos = 8
    header = json.loads(bytes(data[pos:pos + n_head]).decode())
    pos += n_head
    arrays = []
    for _ in range(n_arr):
        (n,) = struct.unpack_from("<Q", data, pos)
        pos += 8
        if n > len(data) - pos:
            raise WireError("malformed message (an array longer than the message)")
        arrays.append(_load_npy(memoryview(data)[pos:pos + n]))
        pos += n
    if not isinstance(header, dict):
        raise WireError("malformed message")
    return header, arrays


def write_frame(fd: int, header: dict, arrays: list = ()) -> None:
    data = pack(header, list(arrays))
    view = memoryview(struct.pack("<Q", len(data)) + data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


def _read_exact(fd: int, n: int) -> bytes:
    chunks, left = [], n
    while left:
        b = os.read(fd, min(left, 1 << 24))
        if not b:
            raise EOFError("the other side closed the connection")
        chunks.append(b)
        left -= len(b)
    return b"".join(chunks)


def read_frame(fd: int, limit: int = MAX_REQUEST) -> tuple[dict, list]:
    """The next message on ``fd`` (at most ``limit`` bytes)."""
    (n,) = struct.unpack("<Q", _read_exact(fd, 8))
    if n > limit:
        raise WireError(f"a message of {n} bytes is larger than the limit ({limit} bytes)")
    return unpack(_read_exact(fd, n))


# ---------------------------------------------------------------------------------------------
# The sandbox
# ---------------------------------------------------------------------------------------------

CLONE_NEWNS, CLONE_NEWUSER, CLONE_NEWNET, CLONE_NEWPID = 0x00020000, 0x10000000, 0x40000000, 0x20000000
CLONE_NEWIPC = 0x08000000
MNT_DETACH = 2
PR_SET_NO_NEW_PRIVS, PR_CAPBSET_DROP = 38, 24
SYS_PIVOT_ROOT = {"x86_64": 155, "aarch64": 41}.get(os.uname().machine, 155)
MS_RDONLY, MS_NOSUID, MS_NODEV, MS_BIND, MS_REC, MS_PRIVATE = 1, 2, 4, 4096, 16384, 1 << 18
MS_REMOUNT = 32
AT_FDCWD, AT_RECURSIVE = -100, 0x8000
MOUNT_ATTR_RDONLY = 0x1
SYS_MOUNT_SETATTR = 442  # x86_64 and aarch64 (generic syscall table)


def _libc():
    import ctypes
    import ctypes.util

    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    return ctypes, libc


def _check(ctypes, rc: int, what: str) -> None:
    if rc != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"{what}: {os.strerror(err)}")


def _mount(ctypes, libc, src, dst, fstype, flags, data=None):
    _check(ctypes, libc.mount(None if src is None else src.encode(), dst.encode(),
                              None if fstype is None else fstype.encode(), ctypes.c_ulong(flags),
                              None if data is None else data.encode()), f"mount {dst}")


def _setattr(ctypes, libc, path: str, set_ro: bool, recursive: bool) -> None:
    class MountAttr(ctypes.Structure):
        _fields_ = [("attr_set", ctypes.c_uint64), ("attr_clr", ctypes.c_uint64),
                    ("propagation", ctypes.c_uint64), ("userns_fd", ctypes.c_uint64)]

    attr = MountAttr(MOUNT_ATTR_RDONLY if set_ro else 0, 0 if set_ro else MOUNT_ATTR_RDONLY, 0, 0)
    rc = libc.syscall(ctypes.c_long(SYS_MOUNT_SETATTR), ctypes.c_int(AT_FDCWD), path.encode(),
                      ctypes.c_uint(AT_RECURSIVE if recursive else 0), ctypes.byref(attr),
                      ctypes.c_size_t(ctypes.sizeof(attr)))
    _check(ctypes, rc, f"mount_setattr {path}")


def enter_sandbox(cfg: dict, collect=None) -> dict:
    """Enter the namespaces and the file system view described in ``cfg``; returns what was enforced.

    ``collect`` (the ``exec`` command): called in the waiting launcher after the sandboxed program ended,
    to copy its results out of the sandbox's own file system.
    """
    done = {"namespaces": False, "network": "not isolated", "ipc": "shared with the host", "file system":
            "the grading user's (only the import path and the working copy are set)", "read_only": False,
            "disk": "per file only (RLIMIT_FSIZE)", "note": ""}
    if not cfg.get("namespaces", True) or not sys.platform.startswith("linux"):
        done["note"] = "namespaces not requested" if sys.platform.startswith("linux") else "not Linux"
        return done
    try:
        ctypes, libc = _libc()
        uid, gid = os.getuid(), os.getgid()
        _check(ctypes, libc.unshare(CLONE_NEWUSER | CLONE_NEWNS | CLONE_NEWNET | CLONE_NEWPID | CLONE_NEWIPC), "unshare")
    except OSError as exc:
        done["note"] = f"no user namespaces here ({exc.strerror if hasattr(exc, 'strerror') else exc})"
        return done
    inner = uid or 1000  # never root inside: no capabilities survive an exec, setuid programs stay plain
    try:
        for name, text in (("setgroups", "deny"), ("uid_map", f"{inner} {uid} 1"), ("gid_map", f"{gid or 1000} {gid} 1")):
            with open(f"/proc/self/{name}", "w") as f:
                f.write(text)
    except OSError as exc:
        done["note"] = f"the user namespace could not be set up ({exc})"
        return done
    done.update(namespaces=True, network="none: a new network namespace with only the loopback device",
                ipc="its own IPC namespace (System V shared memory ends with the sandbox)")
    _loopback_up()
    _become_pid_one(collect)
    try:
        _fresh_root(ctypes, libc, cfg, done)
    except OSError as exc:  # the student's code must not run with the host's files in view
        raise SystemExit(f"the sandbox's file system could not be set up: {exc}") from None
    _drop_privileges(ctypes, libc, done)
    return done


def _fresh_root(ctypes, libc, cfg: dict, done: dict) -> None:
    """A new root of bind mounts: the allow-listed folders read-only, a size-limited tmpfs for what may be written.

    ``cfg["root"]``: ``stage`` (an empty folder of the grader's, to build the root in), ``read_only`` (paths
    shown read-only at their own place), ``hide`` (folders inside those covered by an empty folder),
    ``work`` (the working folder's path) and ``seed`` (a folder whose files are copied into it), ``disk_bytes``.
    """
    import shutil

    spec = cfg["root"]
    stage = spec["stage"]
    root, rw = os.path.join(stage, "root"), os.path.join(stage, "rw")
    _mount(ctypes, libc, None, "/", None, MS_REC | MS_PRIVATE)
    for d in (root, rw):
        os.makedirs(d, exist_ok=True)
    _mount(ctypes, libc, "tmpfs", root, "tmpfs", MS_NOSUID | MS_NODEV, "size=4m,mode=755")
    disk = int(spec.get("disk_bytes", 1 << 30))
    _mount(ctypes, libc, "tmpfs", rw, "tmpfs", MS_NOSUID | MS_NODEV, f"size={disk},mode=755")
    writable = _writable_area(ctypes, libc, root, rw, {"tmp": "/tmp", "shm": "/dev/shm"})
    bound: list[str] = []
    for p in sorted(spec.get("read_only", []), key=len):  # folders before what is inside them
        _bind_at_own_path(ctypes, libc, root, p, bound)
    writable += _writable_area(ctypes, libc, root, rw, {"work": spec["work"]})
    if spec.get("seed"):  # regular files only: the grader's copy of the submission
        shutil.copytree(spec["seed"], os.path.join(rw, "work"), dirs_exist_ok=True, symlinks=False)
    for h in spec.get("hide", []):
        if os.path.isdir(os.path.join(root, h.lstrip("/"))):
            _mount(ctypes, libc, "tmpfs", os.path.join(root, h.lstrip("/")), "tmpfs", MS_NOSUID | MS_NODEV,
                   "size=16k,mode=755")
    _devices(ctypes, libc, root)
    try:  # a /proc of the new PID namespace: other processes (and their views of the files) are not visible
        os.makedirs(os.path.join(root, "proc"), exist_ok=True)
        _mount(ctypes, libc, "proc", os.path.join(root, "proc"), "proc", MS_NOSUID | MS_NODEV | 8)
        done["proc"] = "own PID namespace"
    except OSError as exc:
        done["proc"] = f"no /proc ({exc.strerror})"
    _setattr(ctypes, libc, root, True, True)
    for w in writable:
        _setattr(ctypes, libc, w, False, False)
    os.chdir(root)
    _check(ctypes, libc.syscall(ctypes.c_long(SYS_PIVOT_ROOT), b".", b"."), "pivot_root")
    _check(ctypes, libc.umount2(b".", ctypes.c_int(MNT_DETACH)), "umount the host's root")
    os.chdir("/")
    done.update({"file system": "a fresh root: the Python installation, the student release and system "
                                "libraries read-only; the working copy, /tmp and /dev/shm writable",
                 "read_only": True, "disk": f"{disk} bytes in all (a tmpfs for everything writable)"})


def _bind_at_own_path(ctypes, libc, root: str, path: str, bound: list[str]) -> None:
    """Show host ``path`` (a folder or a file) read-only at the same place under ``root``; links on the way are kept.

    ``bound``: the host paths bound so far (a path inside one of them is already in view).
    """
    parts = [p for p in path.split("/") if p]
    host = "/"
    for k, part in enumerate(parts):
        host = os.path.join(host, part)
        if any(host == b or host.startswith(b.rstrip("/") + "/") for b in bound):
            return
        inside = os.path.join(root, host.lstrip("/"))
        if os.path.islink(host):
            if not os.path.lexists(inside):
                os.symlink(os.readlink(host), inside)
            target = os.path.realpath(host)
            rest = "/".join(parts[k + 1:])
            _bind_at_own_path(ctypes, libc, root, os.path.join(target, rest) if rest else target, bound)
            return
        if k < len(parts) - 1:
            os.makedirs(inside, exist_ok=True)
    if not os.path.exists(host):
        return
    inside = os.path.join(root, host.lstrip("/"))
    if os.path.isdir(host):
        os.makedirs(inside, exist_ok=True)
    elif not os.path.exists(inside):
        os.close(os.open(inside, os.O_CREAT | os.O_WRONLY, 0o644))
    _mount(ctypes, libc, host, inside, None, MS_BIND | MS_REC)
    bound.append(host)


def _writable_area(ctypes, libc, root: str, rw: str, targets: dict[str, str]) -> list[str]:
    """Folders of the one size-limited tmpfs ``rw`` bound at ``targets`` (name -> path in the sandbox)."""
    out = []
    for name, target in targets.items():
        src = os.path.join(rw, name)
        os.makedirs(src, exist_ok=True)
        os.chmod(src, 0o755 if name == "work" else 0o1777)
        inside = os.path.join(root, target.lstrip("/"))
        os.makedirs(inside, exist_ok=True)
        _mount(ctypes, libc, src, inside, None, MS_BIND)
        out.append(inside)
    return out


def _devices(ctypes, libc, root: str) -> None:
    """/dev with the harmless devices only (bound from the host: a user namespace cannot create device files)."""
    dev = os.path.join(root, "dev")
    os.makedirs(dev, exist_ok=True)
    for name in ("null", "zero", "full", "random", "urandom"):
        if os.path.exists(f"/dev/{name}"):
            open(os.path.join(dev, name), "a").close()
            _mount(ctypes, libc, f"/dev/{name}", os.path.join(dev, name), None, MS_BIND)
    for name, target in (("fd", "/proc/self/fd"), ("stdin", "/proc/self/fd/0"), ("stdout", "/proc/self/fd/1"),
                         ("stderr", "/proc/self/fd/2")):
        os.symlink(target, os.path.join(dev, name))


def _drop_privileges(ctypes, libc, done: dict) -> None:
    """No capabilities left (not even in the sandbox's own namespaces) and none to gain: the mounts stay as they are."""
    try:
        _check(ctypes, libc.prctl(PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0), "prctl(NO_NEW_PRIVS)")
        for cap in range(64):
            if libc.prctl(PR_CAPBSET_DROP, cap, 0, 0, 0) != 0:
                break

        class Header(ctypes.Structure):
            _fields_ = [("version", ctypes.c_uint32), ("pid", ctypes.c_int)]

        data = (ctypes.c_uint32 * 6)()
        _check(ctypes, libc.capset(ctypes.byref(Header(0x20080522, 0)), data), "capset")
        done["capabilities"] = "none"
    except OSError as exc:
        done["capabilities"] = f"kept ({exc})"


def _loopback_up() -> None:
    """Bring up ``lo`` in the new network namespace (Jupyter kernels talk to nbval over 127.0.0.1)."""
    import fcntl
    import socket

    SIOCGIFFLAGS, SIOCSIFFLAGS, IFF_UP = 0x8913, 0x8914, 0x1
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            flags = struct.unpack("16sH", fcntl.ioctl(s, SIOCGIFFLAGS, struct.pack("16sH", b"lo", 0))[:18])[1]
            fcntl.ioctl(s, SIOCSIFFLAGS, struct.pack("16sH", b"lo", flags | IFF_UP) + b"\0" * 22)
    except OSError:
        pass


def _become_pid_one(collect=None) -> None:
    """Fork into the new PID namespace: the child goes on as its process 1, this process waits and exits with it.

    The waiting process stays outside the PID namespace (the student's code cannot see or signal it) and,
    after the child ended (and with it every process of the namespace), runs ``collect``.
    """
    pid = os.fork()
    if pid == 0:
        try:  # if the waiting parent is killed, so is this process (and with it the namespace)
            ctypes, libc = _libc()
            libc.prctl(1, 9)  # PR_SET_PDEATHSIG, SIGKILL
        except (OSError, AttributeError):
            pass
        return
    for fd in (REQ_FD, REP_FD) if REQ_FD >= 0 else ():
        try:
            os.close(fd)
        except OSError:
            pass
    while True:
        try:
            _, status = os.waitpid(pid, 0)
            break
        except ChildProcessError:
            os._exit(1)
        except InterruptedError:
            continue
    if collect is not None:
        try:
            collect()
        except Exception:  # noqa: BLE001 - the grader reads what was collected, or reports none
            pass
    if os.WIFSIGNALED(status):
        os._exit(128 + os.WTERMSIG(status))
    os._exit(os.WEXITSTATUS(status))


def _seed_work(cfg: dict, done: dict) -> None:
    """Without a fresh root, the working copy is made on the host's disk (with it, inside the sandbox's tmpfs)."""
    import shutil

    spec = cfg.get("root") or {}
    if spec.get("seed") and not done.get("read_only"):
        shutil.copytree(spec["seed"], spec["work"], dirs_exist_ok=True, symlinks=False)


def _copy_out(path: str, fd: int, limit: int = 16 << 20) -> None:
    """Copy (at most ``limit`` bytes of) the file ``path`` of the sandbox into the grader's open file ``fd``."""
    with open(path, "rb") as f:
        data = f.read(limit)
    os.write(fd, data)


# ---------------------------------------------------------------------------------------------
# Serving the student's code
# ---------------------------------------------------------------------------------------------

REQ_FD, REP_FD = -1, -1  # set from the configuration


def _trace_line(exc: BaseException) -> str:
    import traceback

    for fr in reversed(traceback.extract_tb(exc.__traceback__)):
        if fr.filename == "<your notebook>":
            return f" (line {fr.lineno} of your exercise code)"
    return ""


def _exc_reply(exc: BaseException) -> dict:
    return {"ok": False, "type": _ident(type(exc).__name__, "Exception"),
            "builtin": type(exc).__module__ == "builtins", "message": str(exc)[:2000], "where": _trace_line(exc)}


def _guard_exit(fd: int) -> None:
    """``os._exit`` says who ended the process before it ends it (a process the student's code forked ends quietly:
    it is not the process the grader talks to)."""
    import posix

    real = posix._exit
    me = os.getpid()

    def _exit(code=0):
        try:
            if os.getpid() == me:
                write_frame(fd, {"event": "exit", "how": "os._exit", "code": int(code) if isinstance(code, int) else 1})
        finally:
            real(code)

    os._exit = posix._exit = _exit


def serve(cfg: dict) -> None:
    import types

    global REQ_FD, REP_FD
    REQ_FD, REP_FD = int(cfg["req_fd"]), int(cfg["rep_fd"])
    done = enter_sandbox(cfg.get("sandbox", {}))
    _seed_work(cfg.get("sandbox", {}), done)
    os.chdir(cfg["cwd"])
    sys.path[:] = [cfg["path"]] + [p for p in cfg["sys_path"] if p]
    for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[k] = "1"
    import numpy  # noqa: F401 - the wire format needs it

    if cfg.get("torch"):
        import torch

        torch.set_num_threads(1)
    # ready: the exercise's time starts now (the imports above are the kit's, not the student's)
    write_frame(REP_FD, {"event": "sandbox", "sandbox": done})  # before any code of the student's runs
    req, rep = REQ_FD, REP_FD
    _guard_exit(rep)
    log = open(os.path.join(cfg["cwd"], ".grader-output.txt"), "w")  # the student's prints go here
    os.dup2(log.fileno(), 1)
    os.dup2(log.fileno(), 2)
    module = types.ModuleType("__main__")
    module.__file__ = os.path.join(cfg["cwd"], "exercise.py")
    sys.modules["__main__"] = module
    handles: dict = {}
    try:
        exec(compile(cfg["code"], "<your notebook>", "exec"), module.__dict__)  # noqa: S102 - sandboxed
        target = module.__dict__.get(cfg["name"])
        for step in cfg.get("oracle", ()):  # the earlier exercises it calls: answered by the grader from now on
            if step in module.__dict__ and step != cfg["name"] and not isinstance(module.__dict__[step], type):
                module.__dict__[step] = oracle_stub(step, cfg["name"], module.__dict__[step])
        hello = {"ok": True, "found": target is not None, "callable": callable(target)}
    except BaseException as exc:  # noqa: BLE001 - reported to the grader
        target, hello = None, _exc_reply(exc)
    write_frame(rep, hello)
    while True:
        try:
            msg, arrays = read_frame(req)
        except EOFError:
            break
        if msg.get("op") == "bye":
            break
        calls: list = []
        try:
            def recorder(i):
                def cb(*args, **kwargs):
                    calls.append((i, args, kwargs))

                return cb

            args = decode(msg["args"], arrays, recorder)
            kwargs = decode(msg["kwargs"], arrays, recorder)
            gens = _generators(args, kwargs)
            _set_rng(msg.get("rng"), arrays)
            fn = target if msg.get("h") is None else handles[int(msg["h"])]
            if msg.get("h") is not None and msg.get("params"):
                _load_params(fn, msg["params"], arrays)
            grad = _grad_mode(msg.get("grad", True))
            with grad:
                value = fn(*args, **kwargs)
            out: list = []
            tree = encode(value, out, handles=handles)
            cb_tree = encode([[i, list(a), k] for i, a, k in calls], out)
            reply = {"ok": True, "value": tree, "callbacks": cb_tree, "rng": _get_rng(out),
                     "gens": [[where, encode(g, out)] for where, g in gens]}
        except BaseException as exc:  # noqa: BLE001 - the student's exception, as data
            out, reply = [], _exc_reply(exc)
            if isinstance(exc, WireError):
                reply["wire"] = True
        write_frame(rep, reply, out)


def _generators(args, kwargs) -> list:
    """``[[where, generator]]``: the random generators among the call's arguments (``where``: ``["a", i]`` or
    ``["k", name]``); their states after the call go back with the reply, so that, as in a notebook, the caller's
    generator has advanced by what the student's function drew from it."""
    np, torch = _np(), _torch()
    kinds = tuple(k for k in (getattr(np.random, "Generator", None), getattr(torch, "Generator", None)) if k)
    out = [[["a", i], a] for i, a in enumerate(args) if isinstance(a, kinds)]
    return out + [[["k", k], v] for k, v in kwargs.items() if isinstance(v, kinds)]


def oracle_stub(step: str, exercise: str, own):
    """A plain function in place of the student's earlier exercise ``step`` while ``exercise`` is graded.

    It holds no reference code: it sends its arguments to the grader as data and returns the grader's
    answer (the reference's result, :mod:`course_lib.instructor.oracle`), or raises the reference's error.
    A call the reference cannot answer (arguments that do not fit its signature, or values that cannot
    be sent) goes to the student's ``own`` function, as in the notebook.
    """

    def stub(*args, **kwargs):
        out: list = []
        try:
            head = {"event": "oracle", "name": step, "args": encode(tuple(args), out),
                    "kwargs": encode(dict(kwargs), out)}
        except WireError:
            return own(*args, **kwargs)
        size = sum(a.nbytes for a in out)
        if size > MAX_REPLY:
            raise ValueError(f"{step} was called with {size >> 20} MiB of arguments: while {exercise} is graded, "
                             f"the grader answers {step} for at most {MAX_REPLY >> 20} MiB")
        write_frame(REP_FD, head, out)
        reply, arrays = read_frame(REQ_FD)
        if reply.get("ok"):
            return decode(reply.get("value"), arrays)
        if reply.get("unbound"):
            return own(*args, **kwargs)
        raise _oracle_error(reply, step, exercise)

    stub.__name__ = stub.__qualname__ = step
    stub.__doc__ = f"{step}, answered by the grader with the reference's result while {exercise} is graded."
    return stub


def _oracle_error(reply: dict, step: str, exercise: str) -> Exception:
    """The reference's exception, as the student's code sees it (a builtin type where it was one)."""
    import builtins

    name = _ident(reply.get("type", "RuntimeError"), "RuntimeError")
    cls = getattr(builtins, name, None) if reply.get("builtin") else None
    msg = (f"{reply.get('message', '')} (raised by the grader's reference {step}, which answers for your {step} "
           f"while {exercise} is graded)")
    if not (isinstance(cls, type) and issubclass(cls, Exception)) or cls is StopIteration:
        cls, msg = RuntimeError, f"{name}: {msg}"
    try:
        return cls(msg)
    except Exception:  # noqa: BLE001 - exception types with other constructors
        return RuntimeError(f"{name}: {msg}")


def _grad_mode(enabled: bool):
    import contextlib

    torch = _torch()
    return torch.set_grad_enabled(bool(enabled)) if torch is not None else contextlib.nullcontext()


def _load_params(module, params: list, arrays: list) -> None:
    import torch

    mine = dict(module.named_parameters())
    with torch.no_grad():
        for name, k in params:
            if name in mine:
                mine[name].copy_(torch.from_numpy(arrays[int(k)]))


def _set_rng(state, arrays) -> None:
    if not state:
        return
    np = _np()
    if state.get("np") is not None:
        np.random.set_state(tuple(decode(state["np"], arrays)))
    torch = _torch()
    if torch is not None and state.get("torch") is not None:
        torch.set_rng_state(decode(state["torch"], arrays))


def _get_rng(arrays: list) -> dict:
    np = _np()
    out = {"np": encode(list(np.random.get_state()), arrays)}
    torch = _torch()
    if torch is not None:
        out["torch"] = encode(torch.get_rng_state(), arrays)
    return out


def main(argv: list[str]) -> int:
    if len(argv) >= 2 and argv[0] == "serve":
        with open(argv[1]) as f:
            cfg = json.load(f)
        serve(cfg)
        return 0
    if len(argv) >= 4 and argv[0] == "exec" and argv[2] == "--":
        with open(argv[1]) as f:
            cfg = json.load(f)
        out_fds = [int(fd) for fd in (cfg.get("report_fd"), cfg.get("collect_fd")) if fd is not None]
        collect = None
        if cfg.get("collect") and cfg.get("collect_fd") is not None:
            collect = lambda: _copy_out(cfg["collect"], int(cfg["collect_fd"]))  # noqa: E731
        done = enter_sandbox(cfg.get("sandbox", {}), collect)
        _seed_work(cfg.get("sandbox", {}), done)
        if cfg.get("report_fd") is not None:
            os.write(int(cfg["report_fd"]), json.dumps(done).encode())
        for fd in out_fds:  # the program (and the student's notebook) never hold the grader's files
            os.close(fd)
        os.chdir(cfg["cwd"])
        os.execve(argv[3], argv[3:], dict(os.environ))
    print("usage: child.py serve CONFIG.json | child.py exec CONFIG.json -- PROGRAM ARGS...", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

"""The wire format between the grader and a student's process: frames of JSON and ``.npy`` records, never pickle.

This module is used on both sides: imported by the grader (``course_lib.instructor.sandbox.wire``)
and copied next to :mod:`server` into the sandbox, where it is imported as a top-level ``wire``
module by a ``python -S -E -B`` that has only the standard library (numpy and torch are imported
only when the data need them).

A frame is an 8-byte length, then a message: two 4-byte counts (header bytes, arrays), a JSON
header, and the arrays, each an 8-byte length and an ``np.save`` record. Reading is bounded by
construction:

* a message is at most ``limit`` bytes (:data:`MAX_REPLY` for a student's reply), read as it
  arrives, never allocated ahead of what arrived;
* the JSON header is at most ``header_limit`` bytes (:data:`MAX_HEADER`), its tree at most
  :data:`MAX_NODES` values (:func:`unpack` counts them before anything is decoded), and a message at most
  :data:`MAX_ARRAYS` arrays;
* an array is a ``.npy`` record of a numeric dtype whose size equals what its header declares
  (:func:`unpack`; a pickle, an ``.npz`` archive or a record that claims more than was sent is
  refused before anything is allocated);
* what a value only *declares* (the shape of a sparse matrix, the layers of a remote module) is
  listed by :func:`declared` so that the grader can check it against the expected answer before it
  builds anything (:mod:`course_lib.instructor.student_process`).

Values: None, bool, int, float, complex, str, tuple, list, dict, namedtuple, dataclass-like records
(their public attributes), numpy arrays and scalars, scipy sparse matrices, torch tensors, numpy and
torch random generators (their state), and (student side) an ``nn.Module`` as a handle.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import select
import struct
import sys
import time

__all__ = ["WireError", "Record", "encode", "decode", "declared", "pack", "unpack", "write_frame", "read_frame",
           "ready", "read_exact", "read_until_closed", "global_rng", "set_global_rng", "builtin_exception",
           "MAX_REQUEST", "MAX_REPORT", "MAX_REPLY", "MAX_HEADER", "MAX_NODES", "MAX_ARRAYS", "MAX_SPARSE_CELLS",
           "ident", "lazy_numpy", "close_fds", "close_inherited"]

MAX_REQUEST = 1 << 31  # bytes of one message from the grader (the hidden inputs)
#: Bytes of one reply from the student's process: what an exercise can honestly return (the largest honest reply
#: of the kit's exercises, a NeRF model's parameters or a rendered image, is a few MiB; see benchmarks/grade_speed.py).
MAX_REPLY = 64 << 20
#: Bytes of a message's JSON header (the largest honest one, a model handle with its parameter names or a list of
#: a few thousand numbers, is a few KiB).
MAX_HEADER = 4 << 20
#: Values in one message's JSON tree (each list item, dict key and value counts one).
MAX_NODES = 200_000
#: Arrays in one reply (a NeRF model's parameters and the random states are a few dozen).
MAX_ARRAYS = 65_536
#: Cells (rows x columns) of a sparse matrix whose shape no expected answer vouches for (a 2^12 x 2^12 pattern).
MAX_SPARSE_CELLS = 1 << 24
#: Parameters of a remote module (a NeRF MLP has about 20).
MAX_PARAMS = 4096
#: Bytes of nbval's junit report of one notebook.
MAX_REPORT = 16 << 20


class WireError(Exception):
    """A message that cannot be encoded or decoded."""


def close_fds(fds) -> None:
    """Close each of ``fds`` (a pipe's end); one that is closed already is no error."""
    for fd in fds:
        with contextlib.suppress(OSError):
            os.close(fd)


def close_inherited(*keep: int) -> None:
    """Close every file descriptor above 2 but ``keep``: a worker forked from the grader holds no pipe of the grader's
    other work (nbval's, another exercise's). Without ``/proc`` they stay open."""
    with contextlib.suppress(OSError):
        close_fds(fd for fd in [int(f) for f in os.listdir("/proc/self/fd")] if fd > 2 and fd not in keep)


def lazy_numpy():
    """numpy, imported on first use (a process that only relays messages never loads it)."""
    import numpy as np

    return np


def ident(name, default: str = "Result") -> str:
    """``name`` if it is a short public identifier, else ``default`` (names in a message are data)."""
    name = str(name)[:100]
    return name if name.isidentifier() and not name.startswith("__") and len(name) < 80 else default


def builtin_exception(reply: dict) -> type | None:
    """The builtin exception type an exception's reply names (``type``, with ``builtin`` set), or None: only a subclass
    of ``Exception`` other than ``StopIteration`` (names in a message are data)."""
    import builtins

    cls = getattr(builtins, ident(reply.get("type", "Exception"), "Exception"), None) if reply.get("builtin") else None
    return cls if isinstance(cls, type) and issubclass(cls, Exception) and cls is not StopIteration else None


def global_rng(arrays: list) -> dict:
    """The global numpy (and, where torch is loaded, torch) random states, encoded: they go with every call and come
    back with its reply, so that, as in a notebook, a function that seeds or draws from them changes its caller's."""
    out = {"np": encode(list(lazy_numpy().random.get_state()), arrays)}
    torch = sys.modules.get("torch")  # where this process imported it (the wire never imports it)
    if torch is not None:
        out["torch"] = encode(torch.get_rng_state(), arrays)
    return out


def set_global_rng(state, arrays: list) -> None:
    """Set the global random states that :func:`global_rng` encoded (those ``state`` holds)."""
    if not isinstance(state, dict):
        return
    if state.get("np") is not None:
        lazy_numpy().random.set_state(tuple(decode(state["np"], arrays)))
    torch = sys.modules.get("torch")
    if torch is not None and state.get("torch") is not None:
        torch.set_rng_state(decode(state["torch"], arrays))


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
    torch = sys.modules.get("torch")
    if np is not None:
        if isinstance(obj, (np.ndarray, np.generic)):
            arr = np.asarray(obj)
            if arr.dtype.hasobject:
                raise WireError("an array of Python objects (dtype=object) cannot be sent; use a numeric array")
            arrays.append(arr)
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
        return {"$": "sparse", "fmt": ident(obj.format, "coo"), "shape": [int(n) for n in coo.shape],
                "array": not isinstance(obj, sparse.spmatrix), "a": len(arrays) - 3}
    if isinstance(obj, tuple) and hasattr(obj, "_fields"):
        return {"$": "ntuple", "n": ident(type(obj).__name__), "f": [ident(f, "field") for f in obj._fields],
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
        return {"$": "record", "n": ident(type(obj).__name__),
                "f": {ident(k, "field"): encode(v, arrays, callbacks, handles, depth + 1) for k, v in attrs.items()}}
    raise WireError(f"a value of type {type(obj).__name__} cannot be sent between your code and the grader "
                    "(use numbers, arrays, tensors, tuples, lists, dicts or a dataclass of them)")


class Record:
    """A dataclass-like result received from the student's process (its public attributes)."""

    def __init__(self, **fields):
        self.__dict__.update(fields)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({', '.join(f'{k}=...' for k in self.__dict__)})"


_TYPES: dict = {}


def _made_type(name: str, fields: tuple | None = None):
    """The :class:`Record` subclass ``name`` (``fields`` None), or the namedtuple ``name`` of ``fields`` (None where it
    cannot be one: the value is then a plain tuple); made once, and at most 4096 of them (a reply cannot grow the
    grader by naming new types)."""
    import collections

    if fields is not None and len(fields) > 64:
        return None
    if len(_TYPES) > 4096:
        _TYPES.clear()
    if (name, fields) not in _TYPES:
        try:
            _TYPES[name, fields] = type(name, (Record,), {}) if fields is None else collections.namedtuple(name, fields)
        except ValueError:
            _TYPES[name, fields] = None
    return _TYPES[name, fields]


def _array(arrays: list, k) -> object:
    if type(k) is not int or not 0 <= k < len(arrays):
        raise WireError("malformed message (an array index out of range)")
    return arrays[k]


#: Integer fields of a numpy bit generator's state whose range is narrower than the generator's word: MT19937's
#: position in its key (0..624: numpy reads ``key[pos]`` unchecked, and a larger one crashes the process), Philox's
#: position in its buffer (0..4), the cached 32 bits of every generator. Any other integer field: 0 <= value < 2^128.
_STATE_RANGES = {"pos": 624, "buffer_pos": 4, "has_uint32": 1, "uinteger": (1 << 32) - 1}


def _checked_state(state, template, where: str):
    """``state`` (a numpy bit generator's state from a message) if it has exactly the form of ``template`` (a fresh
    generator's state of the same kind): the same keys, every array of the same dtype and shape (MT19937's key: 624
    uint32), every integer in its range (:data:`_STATE_RANGES`); else :class:`WireError` naming what is wrong."""
    np = lazy_numpy()
    if isinstance(template, dict):
        if not isinstance(state, dict) or set(state) != set(template):
            raise WireError(f"malformed generator state ({where}: the fields "
                            f"{sorted(map(str, state)) if isinstance(state, dict) else type(state).__name__}, "
                            f"not {sorted(template)})")
        return {k: _checked_state(state[k], template[k], f"{where}.{k}") for k in template}
    if isinstance(template, np.ndarray):
        if not isinstance(state, np.ndarray) or state.dtype != template.dtype or state.shape != template.shape:
            got = f"{state.dtype} {state.shape}" if isinstance(state, np.ndarray) else type(state).__name__
            raise WireError(f"malformed generator state ({where}: {got}, not {template.dtype} {template.shape})")
        return state.copy()
    if isinstance(template, str):
        if state != template:
            raise WireError(f"malformed generator state ({where}: {str(state)[:40]!r}, not {template!r})")
        return state
    if isinstance(template, int) and not isinstance(template, bool):
        top = _STATE_RANGES.get(where.rsplit(".", 1)[-1], (1 << 128) - 1)
        if type(state) is not int or not 0 <= state <= top:
            raise WireError(f"malformed generator state ({where}: {str(state)[:40]}, not an integer in 0..{top})")
        return state
    raise WireError(f"malformed generator state ({where})")


def decode(tree, arrays: list, callback=None, module_proxy=None):
    """The value of an :func:`encode` tree (``callback(i)``: a stand-in for callback ``i``)."""
    if tree is None or isinstance(tree, (bool, int, str)):
        return tree
    if not isinstance(tree, dict):
        raise WireError("malformed message")
    kind = tree.get("$")
    sub = lambda v: decode(v, arrays, callback, module_proxy)  # noqa: E731
    if kind == "float":
        return float(str(tree["v"])[:40])
    if kind == "complex":
        return complex(float(str(tree["re"])[:40]), float(str(tree["im"])[:40]))
    if kind in ("nd", "npscalar"):
        a = _array(arrays, tree.get("a"))
        return a if kind == "nd" else a[()]
    if kind == "torch":
        import torch

        t = torch.from_numpy(_array(arrays, tree.get("a")).copy())
        return t.requires_grad_(True) if tree.get("grad") and t.is_floating_point() else t
    if kind in ("rng", "tgen"):
        return _generator(kind, tree, arrays, sub)
    if kind == "ntuple":
        t = _made_type(ident(tree["n"]), tuple(ident(f, "field") for f in _items(tree["f"])))
        vals = [sub(v) for v in _items(tree["v"])]
        return t(*vals) if t is not None and len(vals) == len(t._fields) else tuple(vals)
    if kind == "tuple":
        return tuple(sub(v) for v in _items(tree["v"]))
    if kind == "list":
        return [sub(v) for v in _items(tree["v"])]
    if kind == "dict":
        return {sub(k): sub(v) for k, v in zip(_items(tree["k"]), _items(tree["v"]))}
    if kind == "record":
        if not isinstance(tree["f"], dict):
            raise WireError("malformed record")
        return _made_type(ident(tree["n"]))(**{ident(k, "field"): sub(v) for k, v in tree["f"].items()})
    if kind == "sparse":
        return _sparse(tree, arrays)
    if kind == "cb":
        if callback is None:
            raise WireError("a callback where none is expected")
        return callback(int(tree["i"]))
    if kind == "module":
        if module_proxy is None:
            raise WireError("an object handle where none is expected")
        return module_proxy(tree, arrays)
    raise WireError(f"unknown value kind {str(kind)[:40]!r}")


def _generator(kind: str, tree: dict, arrays: list, sub):
    """A numpy (``"rng"``) or torch (``"tgen"``) generator from its checked state."""
    np = lazy_numpy()
    if kind == "rng":
        state = sub(tree["s"])
        if not isinstance(state, dict):
            raise WireError("malformed generator state")
        bg = getattr(np.random, ident(state.get("bit_generator", "PCG64"), "PCG64"), None)
        if bg is None or not isinstance(bg, type) or not issubclass(bg, np.random.BitGenerator):
            raise WireError("unknown bit generator")
        gen = bg()
        gen.state = _checked_state(state, gen.state, bg.__name__)
        return np.random.Generator(gen)
    import torch

    g = torch.Generator()
    a = _array(arrays, tree.get("a"))
    if a.dtype != np.uint8 or a.shape != tuple(g.get_state().shape):
        raise WireError(f"malformed torch generator state (an array of {a.dtype} {a.shape}; a torch.Generator's "
                        f"state is uint8 {tuple(g.get_state().shape)})")
    try:
        g.set_state(torch.from_numpy(a.copy()))
    except (RuntimeError, ValueError) as exc:
        raise WireError(f"malformed torch generator state ({str(exc)[:200]})") from None
    return g


def _sparse(tree: dict, arrays: list):
    """A scipy sparse matrix (or array) from its checked COO parts."""
    import scipy.sparse as sp

    k = tree.get("a")
    row, col, data = (_array(arrays, k + i if type(k) is int else None) for i in range(3))
    shape = _sparse_shape(tree)
    if not (len(row) == len(col) == len(data)):
        raise WireError("malformed sparse matrix (its index and value arrays differ in length)")
    if len(row) and (row.min() < 0 or col.min() < 0 or row.max() >= shape[0] or col.max() >= shape[1]):
        raise WireError("malformed sparse matrix (an index outside its shape)")
    m = (sp.coo_array if tree.get("array") else sp.coo_matrix)((data, (row, col)), shape=shape)
    fmt = ident(tree.get("fmt", "coo"), "coo")
    return m.asformat(fmt) if fmt in ("csr", "csc", "coo", "lil", "dok", "bsr") else m


def _items(v) -> list:
    if not isinstance(v, list):
        raise WireError("malformed message (a list expected)")
    return v


def _sparse_shape(tree: dict) -> tuple[int, int]:
    shape = tree.get("shape")
    if not (isinstance(shape, list) and len(shape) == 2 and all(type(n) is int and 0 <= n < 2**62 for n in shape)):
        raise WireError("malformed sparse matrix (its shape is not two sizes)")
    return shape[0], shape[1]


def declared(tree) -> list[tuple]:
    """What a tree declares without sending it, before anything is built.

    Returns ``("sparse", path, (rows, cols))`` for every sparse matrix and ``("module", path, layers, shapes)``
    for every remote module (``layers``: its ``[in, out, bias]`` list; ``shapes``: the shapes of the parameters
    it sends), ``path`` saying where in the value it is (``"value[1]"``). Malformed entries raise
    :class:`WireError`. (:func:`unpack` bounded the tree's size before.)
    """
    out: list[tuple] = []
    stack = [(tree, "value")]
    while stack:
        node, path = stack.pop()
        if not isinstance(node, dict):
            if isinstance(node, list):
                raise WireError("malformed message")
            continue
        kind = node.get("$")
        if kind == "sparse":
            out.append(("sparse", path, _sparse_shape(node)))
        elif kind == "module":
            out.append(("module", path, node.get("linear"), node.get("params")))
        elif kind in ("tuple", "list", "ntuple"):
            stack += [(v, f"{path}[{i}]") for i, v in enumerate(_items(node.get("v")))]
        elif kind == "dict":
            stack += [(v, f"{path}[{i}]") for i, v in enumerate(_items(node.get("v")))]
            stack += [(v, f"{path}.key{i}") for i, v in enumerate(_items(node.get("k")))]
        elif kind == "record":
            f = node.get("f")
            if not isinstance(f, dict):
                raise WireError("malformed record")
            stack += [(v, f"{path}.{ident(k, 'field')}") for k, v in f.items()]
        elif kind == "rng":
            stack.append((node.get("s"), path))
    return out


def check_module_tree(tree: dict, arrays: list) -> list[tuple[int, int, bool]]:
    """The linear layers a remote module declares, checked against the parameters it sent (before any is built).

    A layer must have the shape of a weight it sent (``(out, in)``), with at most one layer per weight, and the
    module at most :data:`MAX_PARAMS` parameters; else :class:`WireError`.
    """
    params, linear = tree.get("params"), tree.get("linear")
    if not isinstance(params, list) or not isinstance(linear, list) or len(params) > MAX_PARAMS:
        raise WireError(f"malformed module (more than {MAX_PARAMS} parameters, or no lists)")
    shapes: dict[tuple, int] = {}
    for p in params:
        if not (isinstance(p, list) and len(p) == 2 and isinstance(p[0], str)):
            raise WireError("malformed module parameter")
        shape = tuple(_array(arrays, p[1]).shape)
        shapes[shape] = shapes.get(shape, 0) + 1
    out = []
    for layer in linear:
        if not (isinstance(layer, list) and len(layer) == 3 and all(type(n) is int for n in layer[:2])):
            raise WireError("malformed module layer")
        i, o, b = int(layer[0]), int(layer[1]), bool(layer[2])
        if shapes.get((o, i), 0) <= 0:
            raise WireError(f"the module declares a {i} -> {o} linear layer but sends no weight of that shape")
        shapes[(o, i)] -= 1
        out.append((i, o, b))
    return out


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
    return {"$": "module", "h": h, "n": ident(type(module).__name__, "Module"), "params": params, "linear": layers}


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
    np = lazy_numpy()
    fmt = np.lib.format
    fp = io.BytesIO(data)
    if bytes(data[:6]) != b"\x93NUMPY":
        raise WireError("malformed message (an array that is not a .npy record)")
    version = fmt.read_magic(fp)
    read_header = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
    shape, fortran, dtype = read_header(fp)
    if dtype.hasobject or dtype.kind not in "biufcSUMmV":
        raise WireError("malformed message (an array of Python objects)")
    count = math.prod(int(n) for n in shape)
    start = fp.tell()
    if count * dtype.itemsize != len(data) - start:
        raise WireError("malformed message (an array whose size differs from its header)")
    flat = np.frombuffer(bytearray(data[start:]), dtype=dtype, count=count)
    return flat.reshape(shape, order="F" if fortran else "C")


def _count_nodes(tree, limit: int) -> None:
    """:class:`WireError` when the JSON tree holds more than ``limit`` values (counted without recursion)."""
    stack, seen = [tree], 0
    while stack:
        node = stack.pop()
        seen += 1
        if seen > limit:
            raise WireError(f"malformed message (more than {limit} values)")
        if isinstance(node, dict):
            stack.extend(node.values())
        elif isinstance(node, list):
            stack.extend(node)


def unpack(data, header_limit: int = MAX_HEADER, max_nodes: int = MAX_NODES,
           max_arrays: int = MAX_ARRAYS) -> tuple[dict, list]:
    """The header and arrays of one message; :class:`WireError` (or ``ValueError``) for anything malformed."""
    if len(data) < 8:
        raise WireError("malformed message")
    n_head, n_arr = struct.unpack_from("<II", data, 0)
    if n_head > min(header_limit, len(data) - 8) or n_arr > min(max_arrays, (len(data) - 8 - n_head) // 8):
        raise WireError("malformed message (a header or an array count larger than the message allows)")
    pos = 8
    try:
        header = json.loads(bytes(data[pos:pos + n_head]).decode())
    except RecursionError:
        raise WireError("malformed message (a header nested too deeply)") from None
    _count_nodes(header, max_nodes)
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


def ready(fd: int, deadline: float | None, write: bool = False) -> bool:
    """Whether ``fd`` can be read (``write``: written) before ``deadline`` (``time.monotonic()``; None: no deadline)."""
    if deadline is None:
        return True
    left = deadline - time.monotonic()
    return left > 0 and bool(select.select([] if write else [fd], [fd] if write else [], [], left)[int(write)])


def write_frame(fd: int, header: dict, arrays: list = (), deadline: float | None = None) -> None:
    """Send one message on ``fd``; ``TimeoutError`` when ``deadline`` (``time.monotonic()``) passes before it is
    sent."""
    data = pack(header, list(arrays))
    view = memoryview(struct.pack("<Q", len(data)) + data)
    while view:
        if not ready(fd, deadline, write=True):
            raise TimeoutError
        view = view[os.write(fd, view[: 1 << 16]):]


def read_exact(fd: int, n: int, deadline: float | None = None) -> bytearray:
    """``n`` bytes of ``fd``, read as they arrive (never allocated ahead of them); ``EOFError`` when the other side
    closed first, ``TimeoutError`` when ``deadline`` (``time.monotonic()``) passed first."""
    buf = bytearray()
    while len(buf) < n:
        if not ready(fd, deadline):
            raise TimeoutError
        b = os.read(fd, min(n - len(buf), 1 << 20))
        if not b:
            raise EOFError("the other side closed the connection")
        buf += b
    return buf


def read_until_closed(fd: int, limit: int, deadline: float | None = None) -> tuple[bytes, bool]:
    """What arrives on ``fd`` until the other side closes it (``complete``) or ``deadline``; at most ``limit`` bytes
    kept (the rest is read and dropped)."""
    got, size = [], 0
    while True:
        if not ready(fd, deadline):
            return b"".join(got), False
        b = os.read(fd, 1 << 16)
        if not b:
            return b"".join(got), True
        if size < limit:
            got.append(b[:limit - size])
            size += len(b)


def read_frame(fd: int, limit: int = MAX_REQUEST, deadline: float | None = None,
               trusted: bool = False) -> tuple[dict, list]:
    """The next message on ``fd``, read as it arrives: at most ``limit`` bytes (else :class:`WireError`), before
    ``deadline`` (``time.monotonic()``; else ``TimeoutError``); ``EOFError`` when the other side closed. Its header is
    bounded as :func:`unpack`'s defaults say, unless ``trusted`` (the grader's requests: ``limit`` bounds all)."""
    (n,) = struct.unpack("<Q", read_exact(fd, 8, deadline))
    if n > limit:
        raise WireError(f"a message of {n} bytes, more than the limit ({limit} bytes)")
    data = read_exact(fd, n, deadline)
    return unpack(data, 1 << 30, 1 << 30, 1 << 30) if trusted else unpack(data)

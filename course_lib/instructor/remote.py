"""The student's function and ``nn.Module`` as the grader's check sees them: proxies whose calls go to the student's process.

The check function of an exercise receives a :class:`RemoteFunction` in place of the student's
function: each call is sent, as data, to the :class:`~course_lib.instructor.student_process.StudentProcess`
that holds the student's code, and the decoded result comes back. An ``nn.Module`` the student's
class builds stays in that process; the grader gets a stand-in (:func:`remote_module`) with the module's
parameters and linear layers, whose forward pass sends the (possibly replaced) parameters and the
inputs back to the student's process.
"""

from __future__ import annotations

import copy
import functools

from course_lib.instructor.sandbox import wire

__all__ = ["RemoteFunction", "remote_module"]


class RemoteFunction:
    """The student's function (or class) as the check sees it: each call goes to the student's process.

    Args:
        proc: the student's process (:class:`~course_lib.instructor.student_process.StudentProcess`).
        name: the exercise.
        reference: the reference of the exercise (or None): the expected answer of a call whose reply declares
            what it does not send (:meth:`~course_lib.instructor.student_process.StudentProcess.call`).

    Attributes:
        calls: calls made; ``not_implemented``: calls that raised ``NotImplementedError`` (an untouched stub).
    """

    def __init__(self, proc, name: str, reference=None):
        self._proc, self._reference = proc, reference
        self.__name__ = self.__qualname__ = name
        self.calls = self.not_implemented = 0

    def __call__(self, *args, **kwargs):
        self.calls += 1
        ref = self._reference
        expect = (lambda: ref(*_copies(args), **_copies(kwargs))) if ref is not None else None
        try:
            return self._proc.call(args, kwargs, expect=expect)
        except NotImplementedError:
            self.not_implemented += 1
            raise

    def __repr__(self) -> str:
        return f"<your {self.__name__}, running in its own process>"


def _copies(value):
    """Arrays copied (the reference must not change the check's inputs)."""
    try:
        return copy.deepcopy(value)
    except Exception:  # noqa: BLE001 - a value that cannot be copied is passed as it is
        return value


def remote_module(proc, tree: dict, arrays: list):
    """The ``torch.nn.Module`` that stands for a student's module (a ``"module"`` handle of :func:`wire.encode`),
    its declared layers checked against the weights it sent before anything is built."""
    layers = wire.check_module_tree(tree, arrays)
    sub = type(wire.ident(tree.get("n", "Module"), "Module"), (_remote_module_class(),), {})
    return sub(proc, tree, arrays, layers)


@functools.cache
def _remote_module_class():
    import torch  # deferred: torch, only for a student's nn.Module (the SfM exercises never load it)

    class _Remote(torch.nn.Module):
        """A student's ``nn.Module`` living in the student's process: its parameters and linear layers are mirrored here;
        ``forward`` sends the current parameters and the inputs there and returns the result."""

        def __init__(self, proc, tree: dict, arrays: list, layers: list):
            super().__init__()
            names, mirror = [], []
            for name, k in tree["params"]:
                names.append(str(name)[:200])
                mirror.append(torch.nn.Parameter(torch.from_numpy(arrays[int(k)].copy())))
            linear = [torch.nn.Linear(i, o, bias=b, device="meta") for i, o, b in layers]
            object.__setattr__(self, "_r", {"proc": proc, "h": int(tree["h"]), "names": names, "mirror": mirror,
                                            "linear": linear})

        def parameters(self, recurse: bool = True):
            yield from self._r["mirror"]

        def named_parameters(self, prefix: str = "", recurse: bool = True, remove_duplicate: bool = True):
            for n, p in zip(self._r["names"], self._r["mirror"]):
                yield (f"{prefix}.{n}" if prefix else n), p

        def modules(self):
            yield self
            yield from self._r["linear"]

        def named_modules(self, memo=None, prefix: str = "", remove_duplicate: bool = True):
            yield prefix, self
            for i, m in enumerate(self._r["linear"]):
                yield f"{prefix}.linear{i}" if prefix else f"linear{i}", m

        def forward(self, *args, **kwargs):
            r = self._r
            params = [(n, p.detach().cpu().numpy()) for n, p in zip(r["names"], r["mirror"])]
            return r["proc"].call(args, kwargs, handle=r["h"], params=params)

        def extra_repr(self) -> str:
            return "running in the student's process"

    return _Remote

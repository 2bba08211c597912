"""Where a NeRF trains and renders: the CPU, an NVIDIA GPU (CUDA) or an Apple GPU (MPS).

One helper, used by ``nerf train --device``, ``nerf render --device``, :func:`course_lib.nerf.train.train`
and notebooks 07-10 (``DEVICE = pick_device()`` in their first cell)::

    pick_device()          # "auto": CUDA if there is one, else MPS (Apple silicon), else the CPU
    pick_device("cpu")     # always works
    pick_device("cuda")    # KitInputError with what to do where there is no CUDA GPU

Everything else follows the device of the tensors (``rays_o`` and the model's parameters).
:func:`render_chunk` says how many rays one forward pass of an image render takes on a device:
a CPU renders in small cache-friendly chunks, a GPU in chunks sized to its free memory, so that
snapshots and evaluations cost little beside training.

Introduced in ``notebooks/07_nerf_model.ipynb``.
"""

from __future__ import annotations

import torch

from course_lib.validate import KitInputError

__all__ = ["DEVICE_CHOICES", "available_devices", "pick_device", "device_name", "render_chunk"]

#: what ``--device`` accepts
DEVICE_CHOICES = ("auto", "cpu", "cuda", "mps")

#: rays per render chunk on a CPU (a larger chunk is not faster there and needs more memory)
CPU_CHUNK = 4096


def _mps_available() -> bool:
    mps = getattr(torch.backends, "mps", None)
    return bool(mps is not None and mps.is_available())


def available_devices() -> list[str]:
    """The device kinds this machine offers, best first, e.g. ``["cuda", "cpu"]`` (the CPU is always there)."""
    found = []
    if torch.cuda.is_available():
        found.append("cuda")
    if _mps_available():
        found.append("mps")
    return found + ["cpu"]


def pick_device(request: str | torch.device | None = "auto") -> torch.device:
    """The torch device for ``request``: ``"auto"`` (or None) picks CUDA, then MPS, then the CPU.

    Args:
        request: ``"auto"``, ``"cpu"``, ``"cuda"``, ``"cuda:1"``, ``"mps"`` or a ``torch.device``.

    Returns:
        ``torch.device`` (``cuda:0`` rather than ``cuda``, so that it prints which GPU).

    Raises:
        KitInputError: an unknown name, or a GPU that this machine (or this build of PyTorch) lacks;
            the message says what to do instead.

    Introduced in ``notebooks/07_nerf_model.ipynb``.
    """
    if request is None:
        request = "auto"
    if isinstance(request, torch.device):
        request = str(request)
    if not isinstance(request, str):
        raise KitInputError(f"device {request!r}: expected one of {', '.join(DEVICE_CHOICES)}")
    name = request.strip().lower()
    kind = name.split(":")[0]
    if kind not in DEVICE_CHOICES:
        raise KitInputError(f"device {request!r}: expected one of {', '.join(DEVICE_CHOICES)} (e.g. cuda:0)")
    if kind == "auto":
        kind = available_devices()[0]
        name = kind
    if kind == "cuda":
        if not torch.cuda.is_available():
            why = ("this PyTorch is a CPU-only build (torch.version.cuda is None): install a CUDA build of PyTorch "
                   "(https://pytorch.org/get-started/locally/)" if torch.version.cuda is None
                   else "PyTorch finds no NVIDIA GPU or driver (check nvidia-smi)")
            raise KitInputError(f"device {request!r}: no CUDA GPU here -- {why}; or use --device auto "
                                f"(available here: {', '.join(available_devices())})")
        index = int(name.split(":")[1]) if ":" in name else torch.cuda.current_device()
        if not 0 <= index < torch.cuda.device_count():
            raise KitInputError(f"device {request!r}: this machine has {torch.cuda.device_count()} CUDA GPU(s), "
                                f"numbered 0 to {torch.cuda.device_count() - 1}")
        return torch.device("cuda", index)
    if kind == "mps":
        if not _mps_available():
            raise KitInputError(f"device {request!r}: no Apple GPU (MPS) here -- it needs a Mac with Apple silicon "
                                f"and PyTorch >= 1.12; or use --device auto (available here: {', '.join(available_devices())})")
        return torch.device("mps")
    if ":" in name and name != "cpu:0":
        raise KitInputError(f"device {request!r}: the CPU has no index; use cpu")
    return torch.device("cpu")


def device_name(device: torch.device | str) -> str:
    """A human-readable name: ``"cpu (2 threads)"``, ``"cuda:0 (NVIDIA H100 80GB HBM3)"``, ``"mps (Apple GPU)"``."""
    device = torch.device(device)
    if device.type == "cuda":
        return f"{device} ({torch.cuda.get_device_name(device)})"
    if device.type == "mps":
        return "mps (Apple GPU)"
    return f"cpu ({torch.get_num_threads()} threads)"


def render_chunk(device: torch.device | str, samples_per_ray: int = 64, bytes_per_sample: int = 4096,
                 memory_fraction: float = 0.25) -> int:
    """Rays per forward pass when rendering whole images without gradients on ``device``.

    A CPU gains nothing from larger chunks than a few thousand rays (:data:`CPU_CHUNK`). A GPU is
    fed chunks sized to a quarter of its free memory (``bytes_per_sample`` is a generous bound on
    what one sample holds at once in the paper's 256-wide MLP), a power of two between 4096 and
    2^20 rays; MPS gets 65536.

    Args:
        device: where the render runs.
        samples_per_ray: coarse + fine samples of every ray.
        bytes_per_sample: memory one sample needs during the forward pass.
        memory_fraction: share of the free GPU memory a chunk may take.

    Returns:
        rays per chunk (int).
    """
    device = torch.device(device)
    if device.type == "cuda":
        free, _total = torch.cuda.mem_get_info(device)
        rays = int(memory_fraction * free / (max(samples_per_ray, 1) * bytes_per_sample))
        chunk = 4096
        while chunk * 2 <= min(rays, 1 << 20):
            chunk *= 2
        return chunk
    if device.type == "mps":
        return 65536
    return CPU_CHUNK

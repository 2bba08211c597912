"""Input checks at the public boundary, with messages a student can act on.

Every public function of the kit calls these on its inputs, so that a wrong shape, a NaN or a
singular K fails at once with a sentence that says what to fix, e.g.::

    x1 has shape (7, 2): the 8-point algorithm needs at least 8 correspondences

and never with a traceback deep inside numpy.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["KitInputError", "points", "matching_points", "intrinsics", "rotation", "vector3", "matrix3x3", "as_array", "camera_poses", "generator", "positive", "probability",
           "count", "choice", "existing_path", "file_in", "output_dir"]


class KitInputError(ValueError):
    """Raised for bad input to a kit function; the message says what is wrong and what to do."""


def _shape(a) -> str:
    return str(tuple(np.shape(a)))


def points(x, name: str, dim: int, min_count: int = 0, why: str = "") -> np.ndarray:
    """Check and return a float ``(N, dim)`` array of points.

    Args:
        x: array-like of shape ``(N, dim)``.
        name: the argument's name, for the message.
        dim: 2 for image points, 3 for world points.
        min_count: the fewest rows the caller can work with.
        why: what needs ``min_count`` rows ("the 8-point algorithm"), for the message.

    Raises:
        KitInputError: wrong shape, too few rows, or non-finite values.
    """
    try:
        a = np.asarray(x, dtype=float)
    except (TypeError, ValueError) as exc:
        raise KitInputError(f"{name} must be a numeric array of shape (N, {dim}); got {type(x).__name__} ({exc})") from None
    if a.ndim != 2 or a.shape[1] != dim:
        hint = " (points are rows: transpose it?)" if a.ndim == 2 and a.shape[0] == dim else ""
        raise KitInputError(f"{name} has shape {_shape(a)}: expected (N, {dim}){hint}")
    if a.shape[0] < min_count:
        need = f"{why} needs" if why else "this needs"
        raise KitInputError(
            f"{name} has shape {_shape(a)}: {need} at least {min_count} "
            f"{'correspondences' if dim == 2 else 'points'}"
        )
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        rows = np.flatnonzero(bad)[:5].tolist()
        raise KitInputError(f"{name} has {int(bad.sum())} row(s) with NaN or inf (first rows {rows}): drop or fix them first")
    return a


def matching_points(x1, x2, min_count: int = 0, why: str = "", names=("x1", "x2"), dims=(2, 2)):
    """Check two arrays of corresponding points: each valid and with the same number of rows."""
    a = points(x1, names[0], dims[0], min_count, why)
    b = points(x2, names[1], dims[1], min_count, why)
    if a.shape[0] != b.shape[0]:
        raise KitInputError(
            f"{names[0]} has {a.shape[0]} rows but {names[1]} has {b.shape[0]}: row k of both must be the same correspondence"
        )
    return a, b


def intrinsics(K, name: str = "K") -> np.ndarray:
    """Check and return a ``(3, 3)`` float intrinsic matrix that is finite and invertible."""
    try:
        K = np.asarray(K, dtype=float)
    except (TypeError, ValueError):
        raise KitInputError(f"{name} must be a 3x3 numeric matrix, got {type(K).__name__}") from None
    if K.shape != (3, 3):
        raise KitInputError(f"{name} has shape {_shape(K)}: expected the (3, 3) intrinsic matrix")
    if not np.isfinite(K).all():
        raise KitInputError(f"{name} contains NaN or inf: check the calibration file")
    if abs(np.linalg.det(K)) < 1e-12 or K[0, 0] == 0 or K[1, 1] == 0:
        raise KitInputError(f"{name} is not invertible (focal lengths {K[0, 0]:g}, {K[1, 1]:g}): check the calibration file")
    if not np.allclose(K[2], [0, 0, 1]):
        raise KitInputError(f"{name} must have last row [0, 0, 1], got {K[2].tolist()}")
    return K


def rotation(R, name: str = "R", atol: float = 1e-6) -> np.ndarray:
    """Check and return a ``(3, 3)`` rotation matrix (orthonormal, det = +1)."""
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3):
        raise KitInputError(f"{name} has shape {_shape(R)}: expected (3, 3)")
    if not np.isfinite(R).all():
        raise KitInputError(f"{name} contains NaN or inf")
    if not np.allclose(R @ R.T, np.eye(3), atol=atol):
        raise KitInputError(f"{name} is not orthonormal (R Rᵀ ≠ I): orthogonalize it with an SVD")
    if np.linalg.det(R) < 0:
        raise KitInputError(f"{name} has det = -1: it is a reflection, not a rotation (flip its sign)")
    return R


def vector3(t, name: str = "t") -> np.ndarray:
    """Check and return a finite vector of shape ``(3,)`` (``(3, 1)`` is accepted and flattened)."""
    t = np.asarray(t, dtype=float)
    if t.size != 3:
        raise KitInputError(f"{name} has shape {_shape(t)}: expected (3,)")
    if not np.isfinite(t).all():
        raise KitInputError(f"{name} contains NaN or inf")
    return t.reshape(3)


def matrix3x3(M, name: str, what: str) -> np.ndarray:
    """Check and return a finite, non-zero ``(3, 3)`` float matrix (``what``: "fundamental matrix", ...)."""
    try:
        M = np.asarray(M, dtype=float)
    except (TypeError, ValueError):
        raise KitInputError(f"{name} must be a numeric (3, 3) matrix, got {type(M).__name__}") from None
    if M.shape != (3, 3):
        raise KitInputError(f"{name} has shape {M.shape}: expected the (3, 3) {what}")
    if not np.isfinite(M).all():
        raise KitInputError(f"{name} contains NaN or inf")
    if not np.abs(M).max() > 0:
        raise KitInputError(f"{name} is all zeros: it is not a valid {what}")
    return M


def camera_poses(R_cw, t_cw, atol: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    """Check and return the poses of ``M`` cameras as float arrays ``R_cw (M, 3, 3)``, ``t_cw (M, 3)``.

    One camera may be given as ``R_cw (3, 3)``, ``t_cw (3,)``; ``t_cw (M, 3, 1)`` is accepted; torch
    tensors are read without importing torch.

    Raises:
        KitInputError: wrong shapes, a matrix that is not a rotation, or a non-finite translation.
    """
    R, t = (as_array(a, name) for a, name in ((R_cw, "R_cw"), (t_cw, "t_cw")))
    if R.shape == (3, 3):
        R = R[None]
    if t.shape in ((3,), (3, 1)) and R.shape[0] == 1:
        t = t.reshape(1, 3)
    if R.ndim != 3 or R.shape[1:] != (3, 3):
        raise KitInputError(f"R_cw has shape {_shape(R)}: expected (M, 3, 3) (one rotation per camera)")
    if t.ndim == 3 and t.shape[1:] == (3, 1):
        t = t[..., 0]
    if t.shape != (R.shape[0], 3):
        raise KitInputError(f"t_cw has shape {_shape(t)}: expected ({R.shape[0]}, 3) to match R_cw {_shape(R)}")
    for i, Ri in enumerate(R):
        rotation(Ri, name=f"R_cw[{i}]", atol=atol)
    if not np.isfinite(t).all():
        raise KitInputError("t_cw contains NaN or inf")
    return R, t


def as_array(a, name: str = "the input", dtype=float) -> np.ndarray:
    """Numpy array from numpy / list / torch tensor (without importing torch)."""
    if hasattr(a, "detach") and hasattr(a, "cpu"):
        a = a.detach().cpu().numpy()
    try:
        return np.asarray(a, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise KitInputError(f"{name} must be a numeric array, got {type(a).__name__} ({exc})") from None


def generator(rng, name: str = "rng") -> np.random.Generator:
    """Check that ``rng`` is a ``numpy.random.Generator`` (every stochastic function takes one)."""
    if not isinstance(rng, np.random.Generator):
        raise KitInputError(
            f"{name} must be a numpy.random.Generator (e.g. np.random.default_rng(0)), got {type(rng).__name__}"
        )
    return rng


def positive(x, name: str, what: str = "a positive number") -> float:
    """Check and return a finite number ``> 0`` (``what`` names it in the message: "a positive number of pixels")."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise KitInputError(f"{name}={x!r}: expected {what}") from None
    if not (np.isfinite(v) and v > 0):
        raise KitInputError(f"{name}={x}: expected {what}")
    return v


def probability(p, name: str = "confidence") -> float:
    """Check and return a probability strictly between 0 and 1."""
    try:
        v = float(p)
    except (TypeError, ValueError):
        v = float("nan")
    if not 0.0 < v < 1.0:
        raise KitInputError(f"{name}={p}: expected a probability strictly between 0 and 1")
    return v


def count(n, name: str, minimum: int = 0) -> int:
    """Check and return a whole number ``>= minimum`` (an iteration count, a size)."""
    try:
        v = int(n)
    except (TypeError, ValueError):
        raise KitInputError(f"{name}={n!r}: expected a whole number >= {minimum}") from None
    if v < minimum:
        raise KitInputError(f"{name}={n}: expected at least {minimum}")
    return v


def choice(value, name: str, options: dict):
    """Check that ``value`` is one of ``options`` (``{value: what it means}``), with all of them in the message."""
    if value not in options:
        listed = ", ".join(f"{k!r} ({v})" for k, v in options.items())
        raise KitInputError(f"{name}={value!r}: expected one of {listed}")
    return value


def existing_path(path, what: str) -> Path:
    """Return ``Path(path)`` if it exists, else raise with a message that names what was expected."""
    p = Path(path)
    if not p.exists():
        raise KitInputError(f"{what} not found: {p} (check the path; it is resolved from {Path.cwd()})")
    return p


def file_in(path, name: str, missing: str) -> Path:
    """``Path(path)``, or ``path / name`` where ``path`` is a folder; the file must exist.

    Raises:
        KitInputError: there is no such file; the message is ``missing`` with ``{path}`` filled in.
    """
    p = Path(path)
    if p.is_dir():
        p = p / name
    if not p.is_file():
        raise KitInputError(missing.format(path=p))
    return p


def output_dir(path, option: str = "--out") -> Path:
    """Create (if needed) and return the output folder ``path`` of a command.

    Every command that writes a folder calls this first, so that a wrong ``--out`` gets one line
    that says what to do, and nothing is half-written.

    Raises:
        KitInputError: ``path`` is an existing file, or lies under one, or cannot be created.
    """
    p = Path(path)
    for q in (p, *p.parents):
        if q.exists() and not q.is_dir():
            raise KitInputError(f"{option} {p}: {q} is a file, not a folder; give a folder path "
                                "(a new one, or one the command wrote before)")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise KitInputError(f"{option} {p}: cannot create the folder ({exc.strerror}); choose a folder you can write to") from None
    return p

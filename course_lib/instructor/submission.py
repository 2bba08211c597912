"""A submission is data: it is copied into the grader's scratch space as regular files and folders only.

The grader never reads, runs, writes or deletes anything through a path of the submission itself:
:func:`copy_submission` walks the student's folder without following links and writes a fresh
copy of it; everything after (reading the notebooks, the hidden checks' working folders, nbval)
works on that copy. What the copy refuses is reported to the student:

* a symbolic link is followed only when its real path stays inside the submission and points to
  a regular file or folder (then the *content* is copied, as a file or folder of its own); a link
  out of the submission (to another student's folder, to the instructor's kit, to ``/``) is left
  out, and so is a link cycle;
* devices, FIFOs and sockets are left out (reading a FIFO would block the grader);
* files larger than ``max_file_bytes``, more than ``max_files`` entries, folders deeper than
  ``max_depth``, paths longer than :data:`MAX_PATH_BYTES` and more than ``max_total_bytes`` in all are
  left out, and so are names that are not text (undecodable bytes, control characters);
* whatever else cannot be copied (a name the grader's file system refuses) is left out, never an error:
  every submission gets a report.
"""

from __future__ import annotations

import errno
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["SubmissionCopy", "copy_submission", "SKIP_NAMES", "MAX_PATH_BYTES"]

#: Folders and files of a working copy that are not part of a submission.
SKIP_NAMES = {".git", "__pycache__", ".ipynb_checkpoints", ".venv", "outputs", ".pytest_cache"}
#: Bytes of a path inside the submission (the kit's longest is under 100; the system's limit is 4096 for the whole
#: path, the grader's scratch folder and the sandbox's working folder included).
MAX_PATH_BYTES = 1024


@dataclass
class SubmissionCopy:
    """The grader's copy of a submission and what was left out of it.

    Attributes:
        root: the copy (regular files and folders only).
        refused: ``"path: why"`` for every entry that was not copied (relative to the submission).
        files: regular files copied.
        bytes: bytes copied.
    """

    root: Path
    refused: list[str] = field(default_factory=list)
    files: int = 0
    bytes: int = 0


@dataclass
class _Walk:
    src_real: str
    out: SubmissionCopy
    max_file_bytes: int
    max_total_bytes: int
    max_files: int
    max_depth: int
    seen_dirs: set = field(default_factory=set)


def copy_submission(src: Path, dst: Path, *, max_file_bytes: int = 256 << 20, max_total_bytes: int = 1 << 30,
                    max_files: int = 20000, max_depth: int = 20) -> SubmissionCopy:
    """Copy the submission folder ``src`` into the new folder ``dst`` as regular files and folders only.

    Args:
        src: the student's folder (the instructor's argument; what is inside it is the student's).
        dst: a folder that does not exist yet, in the grader's scratch space.

    Returns:
        The copy and the list of entries left out, each with the reason.
    """
    src_real = os.path.realpath(src)
    if not os.path.isdir(src_real):
        raise NotADirectoryError(f"{src} is not a folder")
    dst = Path(dst)
    dst.mkdir(parents=True)
    walk = _Walk(src_real, SubmissionCopy(dst), max_file_bytes, max_total_bytes, max_files, max_depth)
    walk.seen_dirs.add(src_real)
    _copy_dir(walk, src_real, dst, "", 0)
    return walk.out


def _copy_dir(walk: _Walk, src: str, dst: Path, rel: str, depth: int) -> None:
    if depth > walk.max_depth:
        walk.out.refused.append(f"{rel}: folders nested more than {walk.max_depth} deep")
        return
    try:
        entries = sorted(os.scandir(src), key=lambda e: e.name)
    except OSError as exc:
        walk.out.refused.append(f"{rel or '.'}: cannot be listed ({exc.strerror})")
        return
    for entry in entries:
        if entry.name in SKIP_NAMES or entry.name.endswith(".egg-info"):
            continue
        name, path = entry.name, f"{rel}{entry.name}"
        if not name.isprintable() or any(0xDC80 <= ord(c) <= 0xDCFF for c in name):
            walk.out.refused.append(f"{rel}{name.encode('utf-8', 'backslashreplace').decode('ascii', 'replace')[:80]}"
                                    ": a name with bytes that are not text or with control characters (left out)")
            continue
        if len(path.encode("utf-8")) > MAX_PATH_BYTES:
            walk.out.refused.append(f"{path[:120]}...: a path longer than {MAX_PATH_BYTES} bytes (left out)")
            continue
        try:
            _copy_entry(walk, entry.path, dst / name, path, depth)
        except OSError as exc:  # a name or path the grader's file system refuses: left out, reported
            walk.out.refused.append(f"{path[:200]}: cannot be copied ({exc.strerror or exc}; left out)")


def _copy_entry(walk: _Walk, path: str, dst: Path, rel: str, depth: int) -> None:
    """Copy one entry: a folder, a regular file, or a link whose real path stays inside the submission."""
    try:
        st = os.lstat(path)
    except OSError as exc:
        walk.out.refused.append(f"{rel}: cannot be read ({exc.strerror})")
        return
    linked = stat.S_ISLNK(st.st_mode)
    if linked:
        real = os.path.realpath(path)
        if real != walk.src_real and not real.startswith(walk.src_real.rstrip("/") + "/"):
            walk.out.refused.append(f"{rel}: a symbolic link to a place outside the submission (left out)")
            return
        try:
            st = os.stat(real)
        except OSError:
            walk.out.refused.append(f"{rel}: a broken symbolic link (left out)")
            return
        path = real
    if stat.S_ISDIR(st.st_mode):
        real = os.path.realpath(path)
        if linked and real in walk.seen_dirs:
            walk.out.refused.append(f"{rel}: a link to a folder already copied (a cycle; left out)")
            return
        walk.seen_dirs.add(real)
        dst.mkdir()
        _copy_dir(walk, path, dst, rel + "/", depth + 1)
    elif stat.S_ISREG(st.st_mode):
        _copy_file(walk, path, dst, rel, st.st_size)
    else:
        walk.out.refused.append(f"{rel}: not a regular file (a device, FIFO or socket; left out)")


def _copy_file(walk: _Walk, path: str, dst: Path, rel: str, size: int) -> None:
    out = walk.out
    if out.files >= walk.max_files:
        out.refused.append(f"{rel}: more than {walk.max_files} files in the submission (left out)")
        return
    if size > walk.max_file_bytes or out.bytes + size > walk.max_total_bytes:
        out.refused.append(f"{rel}: {size} bytes, over the limit of the submission's size (left out)")
        return
    try:  # O_NOFOLLOW | O_NONBLOCK: a file swapped for a link or a FIFO since lstat is refused, not followed
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        why = "changed while it was copied" if exc.errno in (errno.ELOOP, errno.ENXIO) else exc.strerror
        out.refused.append(f"{rel}: cannot be read ({why})")
        return
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            out.refused.append(f"{rel}: not a regular file (left out)")
            return
        with open(fd, "rb", closefd=False) as f, open(dst, "xb") as g:
            left = walk.max_file_bytes + 1
            while left > 0 and (chunk := f.read(min(left, 1 << 20))):
                g.write(chunk)
                left -= len(chunk)
                out.bytes += len(chunk)
        out.files += 1
    finally:
        os.close(fd)

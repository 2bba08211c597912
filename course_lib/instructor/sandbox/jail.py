"""The jail of a student's process: bubblewrap around :mod:`server`, checked before any of the student's code runs.

The grader never writes namespace code of its own: `bubblewrap <https://github.com/containers/bubblewrap>`_
(``bwrap``, what Flatpak builds on; Debian/Ubuntu package ``bubblewrap``) makes the sandbox
(:func:`command`):

* new user, mount, PID, IPC, network (only a loopback device), UTS and cgroup namespaces
  (``--unshare-all --unshare-user``), and no further user namespace inside (``--disable-userns``);
* a fresh root that shows only an allow-list, read-only (:meth:`Isolation.read_only`: the Python
  installation, the student release, system libraries; a hidden folder inside one of them covered by
  an empty read-only folder), the server's own folder read-only at ``/grader``, the grader's copy of
  the submission read-only at ``/submission``; a ``/proc`` of its own PID namespace, a minimal
  ``/dev``; the root itself remounted read-only;
* what it may write: a size-limited tmpfs at ``/tmp`` (its working folder, ``/tmp/work``, is filled
  there from ``/submission``) and a small one at ``/dev/shm``;
* ``--cap-drop ALL`` (no capability left, none to gain: ``no_new_privs``), ``--die-with-parent``
  (nothing of it outlives the grader's process that started it), ``--new-session`` (no terminal
  to inject input into), and on x86_64 a seccomp filter (:func:`seccomp_filter`) that refuses the
  system calls no exercise needs (ptrace, other processes' memory, keyrings, bpf, perf, io_uring,
  mounts, module loading...).

What bubblewrap lacks, the kit keeps: the totals of a process tree (:mod:`course_lib.instructor.cgroups`),
the per-process limits, running as a separate uid when the grader is root (:data:`STUDENT_UID`; the
grader drops to it before it starts ``bwrap``, which then needs unprivileged user namespaces), and
the wire protocol (:mod:`wire`).

**Fail closed.** ``bwrap`` fails when it cannot make the sandbox. And whatever it reports, the
grader checks the sandbox itself before the student's code runs (:func:`verify`): :mod:`server`
reports what it observes (:func:`server.facts`: its namespaces, capabilities, ``no_new_privs``,
writable mounts, the hidden folders it can see, its network interfaces) and waits for the
grader's ``go``; ``bwrap --info-fd`` tells the grader the sandbox's process on the host, whose uid
and namespaces the grader reads from ``/proc``. Anything missing ends the grading with one line
(:class:`IsolationError`) that says what is missing and how to enable it. At its end a sandbox is
killed as a whole (:func:`kill_tree`: the launcher, its process group and the PID namespace). ``--insecure`` (a trusted
local run) skips the sandbox, and the report says so.
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import shutil
import signal
import stat
import struct
import sys
import tempfile
import time
from pathlib import Path

from course_lib.instructor.sandbox import server, wire
from course_lib.instructor.settings import STUDENT_UID, site_allow_list
from course_lib.validate import KitInputError

__all__ = ["IsolationError", "closed_to", "command", "install_server", "verify", "privileges_left", "read_info",
           "seccomp_filter", "preexec", "sandboxed", "refusal", "STUDENT_UID", "HOW_TO_ENABLE", "INSTALL", "REPORT",
           "REFUSAL", "WORK", "SEED", "kill_tree"]

#: The working folder of a student's process inside the sandbox, and where the grader's copy of the submission is.
WORK = "/tmp/work"
SEED = "/submission"
SERVER = "/grader"
#: Mount points a sandboxed process may write to (its tmpfs, /proc of its own PID namespace, the device files).
WRITABLE = {"/tmp", "/dev/shm", "/proc", "/dev/pts", "/dev/null", "/dev/zero", "/dev/full", "/dev/random",
            "/dev/urandom", "/dev/tty"}
SHM_BYTES = 64 << 20
INSTALL = "install bubblewrap (apt-get install bubblewrap)"
HOW_TO_ENABLE = ("allow unprivileged user namespaces for bwrap (sysctl kernel.unprivileged_userns_clone=1; on Ubuntu "
                 "24.04 kernel.apparmor_restrict_unprivileged_userns=0; in Docker a seccomp profile that allows "
                 "unshare and no AppArmor confinement of the container)")
REPORT = "the sandbox did not come out as the grader makes it (a bwrap the grader does not know?)"
#: How every refusal starts (``grade-class`` grades a submission refused while others ran again, alone).
REFUSAL = "refusing to run the students' code"


class IsolationError(KitInputError):
    """The grader cannot verify that a student's code would run isolated: it refuses to run it (one line)."""


def refusal(what: str, how: str = HOW_TO_ENABLE) -> str:
    """The one line of a refusal: what is missing, how to enable it, and the way out for a trusted run."""
    return f"{REFUSAL}: {what}; {how}, or pass --insecure for a trusted local run"


def private_folder(prefix: str, parent: Path | None = None) -> Path:
    """A new folder that only the grader and the student's uid can enter (``rwxr-x---`` root and the student's group
    when the grader is root, else ``rwx------``): a student's code, its configuration and its copy of the submission
    are never readable by anyone else on the machine. Made inside ``parent`` (the run's folder, removed by the grader
    at the end however the process that made this one ended) when given."""
    folder = Path(tempfile.mkdtemp(prefix=prefix, dir=parent))
    if os.getuid() == 0:
        os.chown(folder, 0, STUDENT_UID)
        os.chmod(folder, 0o750)
    return folder


def install_server(folder: Path, config: dict) -> Path:
    """Write :mod:`server`, :mod:`wire` and ``config.json`` into ``folder`` (shown read-only at ``/grader``)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    here = Path(__file__).resolve().parent
    for name in ("server.py", "wire.py"):
        shutil.copyfile(here / name, folder / name)
        os.chmod(folder / name, 0o644)
    (folder / "config.json").write_text(json.dumps(config))
    os.chmod(folder / "config.json", 0o644)
    os.chmod(folder, 0o755)
    return folder


def closed_to(path: str, uid: int, gid: int) -> str | None:
    """The first folder on the way to ``path`` (its real path) that user ``uid`` (group ``gid``, no other group)
    cannot enter, or ``path`` itself where it cannot read it; None where it can reach and read ``path``."""
    parts = [p for p in os.path.realpath(path).split("/") if p]
    here = "/"
    for k in range(len(parts) + 1):
        try:
            st = os.stat(here)
        except OSError:
            return here
        last = k == len(parts)
        need = (stat.S_IRUSR if not stat.S_ISDIR(st.st_mode) else stat.S_IRUSR | stat.S_IXUSR) if last else stat.S_IXUSR
        shift = 0 if st.st_uid == uid else (3 if st.st_gid == gid else 6)
        if (st.st_mode << shift) & need != need:
            return here
        if not last:
            here = os.path.join(here, parts[k])
    return None


def _binds(paths: list[str], staged: dict[str, str]) -> list[str]:
    """``--ro-bind`` (or ``--symlink``, for a link) of each host path at the same place; parents before children.

    ``staged``: host paths the student's uid cannot reach, and the reachable folder where :func:`preexec` shows them.
    """
    args: list[str] = []
    bound: list[str] = []
    for p in sorted(paths, key=len):
        if any(p == b or p.startswith(b.rstrip("/") + "/") for b in bound):
            continue
        if os.path.islink(p):
            args += ["--symlink", os.readlink(p), p]
        else:
            args += ["--ro-bind", staged.get(p, p), p]
        bound.append(p)
    return args


def staging(paths: list[str], stage_root: Path) -> dict[str, str]:
    """For a grader that runs as root: the allow-listed paths the student's uid cannot reach (a Python installed under
    ``/root``), each with a folder of ``stage_root`` where :func:`preexec` shows it to the student's uid alone."""
    out = {}
    for k, p in enumerate(sorted(paths, key=len)):
        if os.path.islink(p) or closed_to(p, STUDENT_UID, STUDENT_UID) is None:
            continue
        dst = Path(stage_root) / str(k)
        if os.path.isdir(p):
            dst.mkdir(parents=True, exist_ok=True)
        else:
            dst.parent.mkdir(parents=True, exist_ok=True)
            dst.touch()
        out[p] = str(dst)
    if out:
        os.chmod(stage_root, 0o755)
    return out


def command(iso, mode: str, server_dir: Path, seed: Path | None, info_fd: int, seccomp_fd: int | None,
            staged: dict[str, str] | None = None) -> list[str]:
    """The ``bwrap`` command line that runs ``server.py MODE /grader/config.json`` in the sandbox of ``iso``.

    Args:
        iso: the run's :class:`~course_lib.instructor.settings.Isolation`.
        mode: ``"serve"`` (an exercise) or ``"exec"`` (nbval of a notebook).
        server_dir: the folder written by :func:`install_server`.
        seed: the grader's copy of the submission (shown read-only at ``/submission``), or None.
        info_fd: the descriptor ``bwrap`` writes the sandbox's host pid and namespaces to.
        seccomp_fd: a descriptor holding :func:`seccomp_filter`'s program, or None.
        staged: :func:`staging`'s folders (a grader that runs as root).
    """
    disk = int(iso.limits.disk_bytes) + (seed_bytes(seed) if seed is not None else 0)
    args = [shutil.which("bwrap") or "bwrap", "--unshare-all", "--unshare-user", "--disable-userns",
            "--die-with-parent", "--new-session", "--cap-drop", "ALL", "--hostname", "sandbox",
            "--size", str(disk), "--tmpfs", "/tmp"]
    args += _binds(iso.read_only(), staged or {})
    # what of each site-packages folder is not the student's dependencies, and each hidden folder inside a shown one:
    # an empty read-only file or folder in its place
    for p in site_hidden(iso.read_only()) + iso.covered():
        args += ["--ro-bind", "/dev/null", p] if os.path.isfile(p) and not os.path.islink(p) else \
            ["--size", "4096", "--tmpfs", p, "--remount-ro", p]
    args += ["--ro-bind", str(server_dir), SERVER]
    if seed is not None:
        args += ["--ro-bind", str(seed), SEED]
    args += ["--proc", "/proc", "--dev", "/dev", "--size", str(SHM_BYTES), "--tmpfs", "/dev/shm",
             "--remount-ro", "/dev", "--remount-ro", "/", "--info-fd", str(info_fd), "--chdir", "/tmp"]
    if seccomp_fd is not None:
        args += ["--seccomp", str(seccomp_fd)]
    return args + ["--", sys.executable, "-S", "-E", "-B", f"{SERVER}/server.py", mode, f"{SERVER}/config.json"]


def site_hidden(shown: list[str]) -> list[str]:
    """What of the site-packages folders inside ``shown`` a student's process must not see: every entry that is not on
    :func:`~course_lib.instructor.settings.site_allow_list` (the kit's own distribution, its editable finder, a copy
    of ``course_lib`` put there by hand), or the whole folder where nothing of it is allowed. Covering the few entries
    left out costs a mount each, where binding the few hundred allowed ones would cost a second per sandbox."""
    out = []
    for site, allowed in site_allow_list().items():
        if not any(site == r or site.startswith(r.rstrip("/") + "/") for r in shown):
            continue
        if not allowed:
            out.append(site)
            continue
        keep = set(allowed)
        try:
            out += [os.path.join(site, e) for e in sorted(os.listdir(site)) if e not in keep]
        except OSError:
            out.append(site)
    return out


def seed_bytes(seed: Path) -> int:
    """What the copy of ``seed`` (the grader's copy of a submission) takes in a tmpfs: every file in whole pages,
    plus 1 MiB. The sandbox's ``/tmp`` is this plus ``Limits.disk_bytes``, so that every submission the grader copied
    fits in its working folder and the student's code still has ``disk_bytes`` to write."""
    total = 1 << 20
    for folder, _, files in os.walk(seed):
        for f in files:
            with contextlib.suppress(OSError):
                total += -(-os.lstat(os.path.join(folder, f)).st_size // 4096) * 4096
    return total


def sandboxed(iso, mode: str, server_dir: Path, seed: Path | None, stage_dir: Path):
    """Everything needed to start ``server.py MODE`` in a sandbox, refused (:class:`IsolationError`) without
    bubblewrap, and when the student's uid would be the grading user's.

    Returns:
        ``(argv, fds, info_r, staged, filtered)``: the command line (:func:`command`), the descriptors the process
        must inherit (the caller closes them once it started), the read end of bwrap's report, the staged folders,
        and whether a seccomp filter is applied.
    """
    if shutil.which("bwrap") is None:
        raise IsolationError(refusal("bubblewrap (bwrap) is not installed", INSTALL))
    if os.getuid() == 0 and STUDENT_UID == 0:
        raise IsolationError(refusal("COURSE_GRADER_STUDENT_UID is 0, the grading user's uid",
                                     "set it to an unprivileged uid (default 65534)"))
    info_r, info_w = os.pipe()
    seccomp = None
    program = seccomp_filter()
    if program is not None:
        seccomp, w = os.pipe()
        os.write(w, program)
        os.close(w)
    staged = staging(iso.read_only(), stage_dir) if os.getuid() == 0 else {}
    argv = command(iso, mode, server_dir, seed, info_w, seccomp, staged)
    return argv, [info_w] + ([seccomp] if seccomp is not None else []), info_r, staged, seccomp is not None


def preexec(limits, cpu_seconds: float | None, cgroup, as_student: bool, staged: dict[str, str] | None = None):
    """The ``preexec_fn`` of a sandboxed process: enter ``cgroup``, set the limits, and (root only) show the
    ``staged`` paths and drop to the student's uid, in that order (entering a cgroup needs the grader's rights).

    The one thing done here that bubblewrap cannot do: a grader that runs as root starts ``bwrap`` as the student's
    uid, which cannot reach a Python installed under ``/root``; so this process (still root, about to become the
    launcher) makes a private mount namespace of its own, binds each such folder at a reachable place there
    (:func:`staging`), and only then drops to the student's uid and starts ``bwrap``, which shows the folder
    read-only at its own path. Nothing of it is visible outside this one launcher.
    """

    def run() -> None:
        if cgroup is not None:
            cgroup.enter()
        limits.apply(cpu_seconds)
        if as_student:
            if staged:
                _show_staged(staged)
            os.setgroups([])
            os.setgid(STUDENT_UID)
            os.setuid(STUDENT_UID)

    return run


def launch_failure(exc: BaseException, staged: dict[str, str]) -> str:
    """What failed when the launcher of a sandbox could not even start (its ``preexec_fn`` raised)."""
    if staged:
        err = _unshare_errno()
        why = f"unshare(CLONE_NEWNS): {os.strerror(err)}" if err else str(exc)
        return (f"the launcher could not make the private mount namespace that shows {', '.join(sorted(staged))} to "
                f"the student's uid ({why})")
    return f"the sandbox's launcher could not start ({exc})"


def _unshare_errno() -> int:
    """The errno of ``unshare(CLONE_NEWNS)`` in a throw-away child (0: it works), to say why a launcher failed."""
    pid = os.fork()
    if pid == 0:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        os._exit(0 if libc.unshare(0x00020000) == 0 else min(ctypes.get_errno(), 255) or 255)
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status) if os.WIFEXITED(status) else 255


def _show_staged(staged: dict[str, str]) -> None:
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    CLONE_NEWNS, MS_BIND, MS_REC, MS_PRIVATE = 0x00020000, 4096, 16384, 1 << 18
    if libc.unshare(CLONE_NEWNS) != 0 or libc.mount(None, b"/", None, ctypes.c_ulong(MS_REC | MS_PRIVATE), None) != 0:
        raise OSError(ctypes.get_errno(), "a private mount namespace for the launcher")
    for src, dst in staged.items():
        if libc.mount(src.encode(), dst.encode(), None, ctypes.c_ulong(MS_BIND | MS_REC), None) != 0:
            raise OSError(ctypes.get_errno(), f"bind {src}")


# ---------------------------------------------------------------------------------------------
# Checking the sandbox before the student's code runs
# ---------------------------------------------------------------------------------------------


def read_info(fd: int, deadline: float) -> dict:
    """``bwrap --info-fd``'s JSON (the sandbox's host pid and namespaces); ``{}`` when bwrap wrote none in time."""
    data = b""
    while len(data) < 1 << 16 and wire.ready(fd, deadline):
        b = os.read(fd, 4096)
        if not b:
            break
        data += b
        try:
            return json.loads(data.decode())
        except ValueError:
            continue
    return {}


def privileges_left(facts: dict, caps: tuple[str, ...], seccomp: bool) -> list[str]:
    """What a process's report (``facts["status"]``) says it kept of its privileges: any of the capability sets
    ``caps``, no ``no_new_privs``, and (``seccomp``) no filter."""
    status = facts.get("status") or {}
    left = [k for k in caps if status.get(k) != "0000000000000000"]
    missing = [f"capabilities left ({', '.join(left)})"] if left else []
    if status.get("NoNewPrivs") != "1":
        missing.append("no_new_privs is not set")
    if seccomp and status.get("Seccomp") != "2":
        missing.append("no seccomp filter")
    return missing


def verify(facts: dict, info: dict, seccomp: bool) -> list[str]:
    """What is missing from a sandbox, from the server's ``facts`` and ``bwrap``'s ``info`` (empty: isolated).

    Checked: new user, mount, PID, network and IPC namespaces (also against ``bwrap``'s own report); no
    capability and ``no_new_privs``; the seccomp filter where one was given; a read-only root with only the
    sandbox's own tmpfs, ``/proc`` and devices writable; none of the hidden folders in view; no network device
    but the loopback; and, when the grader is root, a process on the host that runs as :data:`STUDENT_UID`.
    """
    missing = []
    own, ns = server.namespaces(), facts.get("ns") or {}
    same = [n for n in ("user", "mnt", "pid", "net", "ipc") if not ns.get(n) or ns.get(n) == own.get(n)]
    if same:
        missing.append(f"no {', '.join(same)} namespace of its own")
    for n in ("mnt", "pid", "net", "ipc"):
        want = info.get(f"{n}-namespace")
        if want is not None and ns.get(n) != f"{n}:[{want}]":
            missing.append(f"its {n} namespace is not the one bwrap made")
    missing += privileges_left(facts, ("CapEff", "CapPrm", "CapBnd", "CapAmb"), seccomp)
    if not facts.get("root_read_only"):
        missing.append("its root is writable")
    extra = [w for w in facts.get("writable", []) if w not in WRITABLE]
    if extra:
        missing.append(f"writable mounts besides its tmpfs ({', '.join(extra[:5])})")
    if facts.get("visible"):
        missing.append(f"it can see {', '.join(facts['visible'][:3])}")
    if facts.get("unreadable"):
        missing.append(f"the student release {facts['unreadable'][0]} is not readable by the student's uid "
                       "(make it and its folders readable by all: chmod a+rX)")
    if set(facts.get("net") or ["?"]) - {"lo"}:
        missing.append(f"network devices ({', '.join(facts.get('net') or ['unknown'])})")
    pid = info.get("child-pid")
    status = server.proc_lines(f"/proc/{pid}/status") if isinstance(pid, int) else None
    uids = None
    with contextlib.suppress(ValueError):  # a Uid: line that is not numbers reads as unreadable, as no line does
        uids = next(([int(x) for x in ln.split()[1:5]] for ln in status or [] if ln.startswith("Uid:")), None)
    if os.getuid() == 0:  # (a STUDENT_UID of 0 is refused before the sandbox is made: sandboxed)
        if uids is None:
            missing.append("its process on the host cannot be read (bwrap --info-fd)")
        elif set(uids) != {STUDENT_UID}:
            missing.append(f"it runs as uid {uids[0]}, not as the student's uid {STUDENT_UID}")
    elif uids is not None and set(uids) != {os.getuid()}:
        missing.append(f"it runs as uid {uids[0]}")
    return missing


def describe(iso, seccomp: bool) -> dict:
    """What confined a verified sandbox (:func:`verify`), for the report (``isolation``)."""
    return {"tool": "bubblewrap", "namespaces": True, "read_only": True,
            "namespaces list": "user, mount, PID, IPC, network (loopback only), UTS, cgroup",
            "file system": "a fresh root: the Python installation, the student release and system libraries "
                           "read-only; its /tmp (the working copy) and /dev/shm writable",
            "disk": f"{int(iso.limits.disk_bytes)} bytes (its /tmp, past its working copy) + {SHM_BYTES} bytes "
                    "(/dev/shm)",
            "capabilities": "none (no_new_privs)", "seccomp": "filter" if seccomp else "none on this architecture",
            "uid": (f"{STUDENT_UID} (the grader runs as root)" if os.getuid() == 0 else
                    f"{os.getuid()}, the grading user's, in a user namespace of its own with nothing of that user's "
                    "in view")}


# ---------------------------------------------------------------------------------------------
# The seccomp filter (x86_64)
# ---------------------------------------------------------------------------------------------

#: System calls no exercise, notebook or Jupyter kernel needs; refused with EPERM (x86_64 numbers).
DENIED_X86_64 = {
    "ptrace": 101, "syslog": 103, "pivot_root": 155, "adjtimex": 159, "chroot": 161, "acct": 163,
    "settimeofday": 164, "mount": 165, "umount2": 166, "swapon": 167, "swapoff": 168, "reboot": 169, "iopl": 172,
    "ioperm": 173, "init_module": 175, "delete_module": 176, "quotactl": 179, "clock_settime": 227,
    "kexec_load": 246, "add_key": 248, "request_key": 249, "keyctl": 250, "unshare": 272, "perf_event_open": 298,
    "name_to_handle_at": 303, "open_by_handle_at": 304, "setns": 308, "process_vm_readv": 310,
    "process_vm_writev": 311, "finit_module": 313, "kexec_file_load": 320, "bpf": 321, "userfaultfd": 323,
    "io_uring_setup": 425, "io_uring_enter": 426, "io_uring_register": 427, "open_tree": 428, "move_mount": 429,
    "fsopen": 430, "fsconfig": 431, "fsmount": 432, "fspick": 433, "mount_setattr": 442,
}
_AUDIT_ARCH_X86_64 = 0xC000003E
_X32_BIT = 0x40000000
_RET_ALLOW, _RET_EPERM, _RET_KILL = 0x7FFF0000, 0x00050000 | 1, 0x80000000


def seccomp_filter() -> bytes | None:
    """A classic BPF program for ``bwrap --seccomp``: EPERM for :data:`DENIED_X86_64` and the x32 ABI, kill for
    another architecture; None where the machine is not x86_64 (there the namespaces and the dropped capabilities
    alone refuse what these calls could do)."""
    if platform.machine() != "x86_64":
        return None
    ld_nr, ld_arch = (0x20, 0, 0, 0), (0x20, 0, 0, 4)  # BPF_LD | BPF_W | BPF_ABS
    denied = sorted(DENIED_X86_64.values())
    prog = [ld_arch, (0x15, 1, 0, _AUDIT_ARCH_X86_64), (0x06, 0, 0, _RET_KILL), ld_nr]
    n_tests = 1 + len(denied)  # the x32 test, then one per call; after them: allow, deny
    prog.append((0x35, n_tests, 0, _X32_BIT))  # BPF_JMP | BPF_JGE | BPF_K: x32 calls -> deny
    for k, nr in enumerate(denied):
        prog.append((0x15, n_tests - 1 - k, 0, nr))  # BPF_JMP | BPF_JEQ | BPF_K -> deny
    prog += [(0x06, 0, 0, _RET_ALLOW), (0x06, 0, 0, _RET_EPERM)]
    return b"".join(struct.pack("<HBBI", *ins) for ins in prog)


def kill_tree(pid: int) -> None:
    """SIGKILL a sandbox launcher (bwrap), its process group and its direct children.

    The launcher's child is process 1 of the sandbox's PID namespace: when it dies, Linux kills
    every process in that namespace, including those that left the process group (``setsid``).
    It is killed first, and the launcher (which reaps it and then exits) is given a moment before it
    is killed too, so that no zombie is left to the host's init.
    """
    try:
        kids = [int(k) for t in os.listdir(f"/proc/{pid}/task")
                for k in open(f"/proc/{pid}/task/{t}/children").read().split()]
    except OSError:
        kids = []
    for k in kids:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(k, signal.SIGKILL)
    for _ in range(50 if kids else 0):  # the launcher reaps its child and exits on its own
        try:
            with open(f"/proc/{pid}/stat") as f:
                if f.read().rsplit(")", 1)[1].split()[0] == "Z":
                    break
        except OSError:
            break
        time.sleep(0.01)
    for kill, target in ((os.killpg, pid), (os.kill, pid)):
        with contextlib.suppress(ProcessLookupError, PermissionError):
            kill(target, signal.SIGKILL)

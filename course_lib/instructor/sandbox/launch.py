"""Starting a student's process in the run's isolation mode, and checking it before any of the student's code runs.

A grading run has one mode (:func:`mode_of`), and this module is the one place that tells them apart:

* ``bubblewrap`` (the default): :mod:`jail` makes the sandbox around :mod:`server` and reports it through
  ``--info-fd``; the process works in the sandbox's own tmpfs (:data:`jail.WORK`);
* ``container`` (``COURSE_GRADER_CONTAINER=1``): :mod:`container` confines the process itself as it starts;
* ``insecure`` (``--insecure``, a trusted local run): the plain server, as the grading user; the report says so.

:func:`start` starts ``server.py serve`` (an exercise) or ``server.py exec`` (nbval of a notebook) in the mode;
where the mode cannot start it, it refuses (:class:`~jail.IsolationError`, one line). :func:`check` compares what
the server reports of itself with what the mode must give, and refuses where anything is missing (fail closed).
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from course_lib.instructor.sandbox import container, jail, wire
from course_lib.instructor.settings import START_SECONDS

__all__ = ["BUBBLEWRAP", "CONTAINER", "INSECURE", "Started", "mode_of", "paths", "env", "start", "check",
           "refuse_start"]

BUBBLEWRAP, CONTAINER, INSECURE = "bubblewrap", "container", "insecure"


def mode_of(iso) -> str:
    """The isolation mode of a grading run's :class:`~course_lib.instructor.settings.Isolation`."""
    if iso.insecure:
        return INSECURE
    return CONTAINER if container.enabled() else BUBBLEWRAP


def paths(iso, folder: Path, seed: Path | None) -> tuple[str, str | None]:
    """The process's working folder and where it finds the grader's copy of the submission, as the process sees
    them: inside bubblewrap's view, else on the host (``folder``: the process's private folder)."""
    if mode_of(iso) == BUBBLEWRAP:
        return jail.WORK, jail.SEED if seed is not None else None
    return str(Path(folder) / "work"), str(seed) if seed is not None else None


def env(home: str | Path, **more: str) -> dict:
    """The environment of a student's process: no variable of the grader's but the locale, one thread per math
    library, no bytecode, matplotlib without a display, the kit's quick mode; ``HOME`` and ``more`` on top."""
    out = {k: v for k, v in os.environ.items() if k in ("PATH", "LANG", "LC_ALL", "TZ")}
    out.update(HOME=str(home), TMPDIR="/tmp", OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1",
               PYTHONDONTWRITEBYTECODE="1", MPLBACKEND="Agg", COURSE_LIB_QUICK="1")
    out.update(more)
    return out


@dataclass
class Started:
    """A started student's process and what its mode reported of it.

    Attributes:
        proc: the launcher (``bwrap``, or the server itself).
        mode: :data:`BUBBLEWRAP`, :data:`CONTAINER` or :data:`INSECURE`.
        info: ``bwrap --info-fd``'s report (the sandbox's host pid and namespaces); ``{}`` in the other modes, and
            where bwrap wrote none in time.
        filtered: whether bubblewrap applied the seccomp filter.
    """

    proc: subprocess.Popen
    mode: str
    info: dict = field(default_factory=dict)
    filtered: bool = False


def start(iso, kind: str, cfg: dict, folder: Path, seed: Path | None, cgroup, cpu_seconds: float, environ: dict,
          fds: list[int], stderr=subprocess.DEVNULL) -> Started:
    """Start ``server.py KIND`` (``"serve"`` or ``"exec"``) with configuration ``cfg`` in the run's mode.

    Args:
        iso: the run's :class:`~course_lib.instructor.settings.Isolation`.
        folder: the process's private folder (:func:`jail.private_folder`): the server's files, the staged folders.
        seed: the grader's copy of the submission (shown read-only to the process), or None.
        cgroup: the cgroup the process enters (None: the caller's own).
        cpu_seconds: the process's CPU time limit.
        environ: its environment (:func:`env`).
        fds: the descriptors it inherits besides the mode's own; closed here, whether it started or not.
        stderr: where its standard error goes.

    Raises:
        IsolationError: the mode cannot start a confined process here (nothing of the student's ran).
    """
    mode = mode_of(iso)
    cfg = dict(cfg, hide=[str(h) for h in iso.hide], keep=[str(k) for k in iso.keep], library=str(iso.library),
               own_pid_namespace=mode == BUBBLEWRAP)
    info_r, staged, filtered, more = None, {}, False, []
    try:
        server_dir = jail.install_server(Path(folder) / "grader", cfg)
        if mode == BUBBLEWRAP:
            argv, more, info_r, staged, filtered = jail.sandboxed(iso, kind, server_dir, seed, Path(folder) / "stage")
            preexec = jail.preexec(iso.limits, cpu_seconds, cgroup, as_student=os.getuid() == 0, staged=staged)
        else:
            argv = [sys.executable, "-S", "-E", "-B", str(server_dir / "server.py"), kind,
                    str(server_dir / "config.json")]
            if mode == CONTAINER:
                container.check(cgroup)
                preexec = container.preexec(iso.limits, cpu_seconds, cgroup, Path(cfg["cwd"]))
            else:
                preexec = jail.preexec(iso.limits, cpu_seconds, cgroup, as_student=False)
        try:
            proc = subprocess.Popen(argv, cwd=folder, env=environ, stdin=subprocess.DEVNULL,
                                    stdout=subprocess.DEVNULL, stderr=stderr, pass_fds=fds + more,
                                    start_new_session=True, preexec_fn=preexec)
        except (OSError, subprocess.SubprocessError) as exc:  # the launcher could not even start (preexec_fn)
            if mode == INSECURE:
                raise
            raise jail.IsolationError(jail.refusal(jail.launch_failure(exc, staged))) from None
    except BaseException:
        wire.close_fds([info_r] if info_r is not None else [])
        raise
    finally:  # the process holds its own copies now
        wire.close_fds(fds + more)
    started = Started(proc, mode, filtered=filtered)
    if info_r is not None:
        started.info = jail.read_info(info_r, time.monotonic() + START_SECONDS)
        os.close(info_r)
    return started


def check(started: Started, iso, facts: dict, cgroup, what: str = "the sandbox") -> dict:
    """What confines a started process, for the report, once what it reports of itself (``facts``,
    :func:`server.facts`) is checked against its mode (with the totals of ``cgroup``).

    Raises:
        IsolationError: something the mode must give is missing (the process is killed first).
    """
    if started.mode == INSECURE:
        box = {"tool": "none (--insecure)", "namespaces": False, "read_only": False,
               "note": "--insecure: the student's code ran without a sandbox, as the grading user"}
        return dict(box, **iso.limits.totals(cgroup))
    boxed = started.mode == BUBBLEWRAP
    missing = jail.verify(facts, started.info, started.filtered) if boxed else container.verify(facts)
    if missing:
        jail.kill_tree(started.proc.pid)
        raise jail.IsolationError(jail.refusal(f"{what} is not isolated: " + "; ".join(missing), jail.REPORT))
    box = jail.describe(iso, started.filtered) if boxed else container.describe(cgroup)
    return dict(box, **iso.limits.totals(cgroup))


def refuse_start(started: Started, stderr_text: str = "", what: str = "the sandbox") -> jail.IsolationError:
    """The refusal when a process did not report before its start's time ran out or it ended: bubblewrap could not
    make ``what`` (its own words from ``stderr_text`` where it said any). The process is killed."""
    with contextlib.suppress(subprocess.TimeoutExpired):
        started.proc.wait(timeout=2)
    jail.kill_tree(started.proc.pid)
    lines = [ln.strip() for ln in stderr_text.splitlines() if ln.strip()]
    said = [ln for ln in lines if ln.startswith("bwrap:")] or lines[-1:]
    why = said[0] if said else f"bwrap ended with exit code {started.proc.poll()}"
    return jail.IsolationError(jail.refusal(f"bubblewrap could not make {what} ({why[:300]})"))

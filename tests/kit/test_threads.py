"""course_lib.threads: the one place that sets BLAS and torch threads."""

import os

import numpy as np

from course_lib import threads


def _has_threadpoolctl():
    try:
        import threadpoolctl  # noqa: F401
    except ImportError:
        return False
    return True


def test_blas_threads_are_restored():
    np.linalg.svd(np.eye(3))  # numpy's OpenBLAS is loaded
    controls = threads.blas_thread_controls()
    before = [get() for get, _ in controls]
    with threads.single_threaded_blas():
        if controls and not _has_threadpoolctl():
            assert all(get() == 1 for get, _ in controls)
    assert [get() for get, _ in controls] == before


def test_set_blas_threads():
    controls = threads.blas_thread_controls()
    before = [get() for get, _ in controls]
    try:
        threads.set_blas_threads(1)
        assert all(get() == 1 for get, _ in controls)
    finally:
        for (_, set_), n in zip(controls, before):
            set_(int(n))


def test_set_torch_threads():
    import torch

    old = torch.get_num_threads()
    try:
        assert threads.set_torch_threads(1) == 1
        assert threads.set_torch_threads(0) == 1  # 0: unchanged
        assert 1 <= threads.set_torch_threads(-1) <= (os.cpu_count() or 1)
    finally:
        torch.set_num_threads(old)


def test_cores_in_use_sees_a_busy_core():
    import subprocess
    import sys

    spin = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        busy = threads.cores_in_use(0.5)
    finally:
        spin.kill()
        spin.wait()
    assert 0.5 <= busy <= (os.cpu_count() or 1) + 0.1  # one spinning process: at least about one core


def test_auto_torch_threads_honour_omp_num_threads(monkeypatch):
    """"auto" takes the number the caller set in OMP_NUM_THREADS (the suite's workers: one each), busy or idle."""
    import torch

    old = torch.get_num_threads()
    monkeypatch.setattr(threads, "cores_in_use", lambda *a, **k: 0.0)  # an idle machine: auto alone would take all
    try:
        monkeypatch.setenv("OMP_NUM_THREADS", "1")
        assert threads.set_torch_threads(-1) == 1
        monkeypatch.delenv("OMP_NUM_THREADS")
        assert threads.set_torch_threads(-1) == (os.cpu_count() or 1)
    finally:
        torch.set_num_threads(old)

"""Executors: serial, a local process pool and a Dask cluster give the same merge."""

import platform
import subprocess
import sys

import numpy as np
import pytest

import gridmerge
from gridmerge.errors import GridMergeError
from gridmerge.parallel import DaskExecutor, ProcessExecutor, SerialExecutor, executor_for


def _square(x):
    return x * x


def test_executors_keep_the_items_order():
    items = list(range(7))
    with SerialExecutor() as s:
        assert s.map(_square, items) == [x * x for x in items]
    with ProcessExecutor(2) as p:
        assert p.map(_square, items) == [x * x for x in items] and p.workers == 2
        assert p.map(_square, []) == []


def test_executor_for_picks_what_the_command_line_asks():
    assert isinstance(executor_for(), SerialExecutor)
    assert isinstance(executor_for(1), SerialExecutor)
    with executor_for(2) as ex:
        assert isinstance(ex, ProcessExecutor)
    with pytest.raises(GridMergeError):
        executor_for(0)


def test_unreachable_scheduler_is_one_clear_error():
    pytest.importorskip("distributed")
    with pytest.raises(GridMergeError, match="Dask scheduler"):
        DaskExecutor("tcp://127.0.0.1:9", timeout=1)


@pytest.fixture(scope="module")
def fleet3():
    from gridmerge.bench.fleet import simulate_fleet

    return simulate_fleet(3, seed=0, shape=(400, 560)).maps


@pytest.fixture(scope="module")
def serial_merge(fleet3):
    return gridmerge.merge(fleet3, rng=3)


def _same(a, b):
    assert a.success and b.success
    assert a.names == b.names and a.unplaced == b.unplaced
    for s, t in zip(a.transforms, b.transforms):
        assert (s is None) == (t is None)
        if s is not None:
            np.testing.assert_array_equal(s.params, t.params)
    np.testing.assert_array_equal(np.nan_to_num(a.grid.data, nan=-1), np.nan_to_num(b.grid.data, nan=-1))
    assert [(p.i, p.j, p.success, p.confidence) for p in a.pairs] == [(p.i, p.j, p.success, p.confidence) for p in b.pairs]


def test_process_pool_merge_equals_serial(fleet3, serial_merge):
    with ProcessExecutor(2) as ex:
        _same(serial_merge, gridmerge.merge(fleet3, rng=3, executor=ex))


def test_dask_local_cluster_merge_equals_serial(fleet3, serial_merge):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        with DaskExecutor(cluster.scheduler_address) as ex:
            assert ex.workers == 2
            _same(serial_merge, gridmerge.merge(fleet3, rng=3, executor=ex))


def test_opencv_threads_split_restores_the_count_after_nested_and_concurrent_holders(monkeypatch):
    import threading

    import cv2

    from gridmerge.parallel import opencv_threads_split

    before = cv2.getNumThreads()
    monkeypatch.setattr("os.cpu_count", lambda: 8)
    cv2.setNumThreads(8)
    try:
        inside, go, done = [], threading.Event(), threading.Event()

        def other():
            with opencv_threads_split(2):
                inside.append(cv2.getNumThreads())
                go.set()
                done.wait(5)

        with opencv_threads_split(2):
            assert cv2.getNumThreads() == 4  # half the cores
            with opencv_threads_split(4):  # nested: the first holder's count stands
                assert cv2.getNumThreads() == 4
            worker = threading.Thread(target=other)
            worker.start()
            assert go.wait(5)
        # The first holder left while the other still holds: not restored yet.
        assert cv2.getNumThreads() == 4 and inside == [4]
        done.set()
        worker.join(5)
        assert cv2.getNumThreads() == 8  # the last one out restores it
        cv2.setNumThreads(1)
        with opencv_threads_split(2):
            assert cv2.getNumThreads() == 1  # never more than OpenCV had
        assert cv2.getNumThreads() == 1
    finally:
        cv2.setNumThreads(before)


_KEPT = """
import os, sys
import numpy as np
from gridmerge.parallel import keep_freed_memory
applied = keep_freed_memory() if sys.argv[1] == "keep" else False
def resident_mb():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
x = np.ones(2_500_000)  # 20 MB
before = resident_mb()
del x
print(applied, before - resident_mb())
"""


@pytest.mark.skipif(sys.platform != "linux" or platform.libc_ver()[0] != "glibc", reason="glibc's mallopt")
def test_keep_freed_memory_keeps_a_freed_large_block_for_the_next():
    # In a process of its own: it changes how the whole process allocates. By default
    # glibc returns a freed 20 MB block to the system (the next one is fresh memory);
    # kept, the process still holds it.
    runs = {}
    for mode in ("default", "keep"):
        out = subprocess.run([sys.executable, "-c", _KEPT, mode], capture_output=True, text=True, check=True).stdout
        applied, released = out.split()
        runs[mode] = (applied == "True", float(released))
    assert runs["keep"][0] and not runs["default"][0]
    assert runs["default"][1] > 15.0
    assert runs["keep"][1] < 5.0


def test_keep_freed_memory_changes_nothing_without_glibc(monkeypatch):
    import ctypes

    from gridmerge.parallel import keep_freed_memory

    monkeypatch.setattr(platform, "libc_ver", lambda *a, **k: ("musl", "1.2"))
    assert keep_freed_memory() is False
    monkeypatch.setattr(platform, "libc_ver", lambda *a, **k: ("glibc", "2.36"))
    monkeypatch.setattr(platform, "system", lambda: "Linux")

    def missing(*args, **kwargs):
        raise OSError("no C library")

    monkeypatch.setattr(ctypes, "CDLL", missing)
    assert keep_freed_memory() is False

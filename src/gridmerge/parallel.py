"""Running independent jobs (pairwise alignments, feature extraction) in parallel.

One small interface, :class:`Executor`: ``executor.map(fn, items)`` returns
``[fn(item) for item in items]``, in order. Three implementations:

* :class:`SerialExecutor`: in this process, one after the other (the default);
* :class:`ProcessExecutor`: a local pool of worker processes (``--workers N``);
* :class:`DaskExecutor`: the workers of a Dask distributed cluster (``--scheduler
  tcp://host:8786``), or of a ``distributed.Client`` you already have.

The results do not depend on the executor: every job carries its own seed
(:func:`gridmerge.merge` derives one per map pair), so serial and parallel runs give the
same numbers. ``fn`` and the items must be picklable for the parallel executors
(module-level functions, maps and :class:`~gridmerge.features.Features` are).

Examples
--------
>>> from gridmerge.parallel import executor_for
>>> with executor_for() as ex:          # serial
...     ex.map(abs, [-1, 2, -3])
[1, 2, 3]
"""

from __future__ import annotations

import multiprocessing
import os
import threading
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from typing import Any, Callable, Iterable, Protocol, Sequence, runtime_checkable

from .errors import GridMergeError

__all__ = ["Executor", "SerialExecutor", "ProcessExecutor", "DaskExecutor", "executor_for", "opencv_threads_split",
           "keep_freed_memory"]


@runtime_checkable
class Executor(Protocol):
    """Runs ``fn`` on every item; results in the items' order."""

    #: How many jobs run at once (1 for serial).
    workers: int

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> list: ...

    def close(self) -> None: ...


class _Closing:
    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:  # pragma: no cover - overridden where there is something to close
        pass


class SerialExecutor(_Closing):
    """Runs the jobs one after the other in this process."""

    workers = 1

    def map(self, fn: Callable[[Any], Any], items: Iterable[Any]) -> list:
        return [fn(item) for item in items]

    def __repr__(self) -> str:
        return "SerialExecutor()"


class ProcessExecutor(_Closing):
    """A local pool of ``workers`` processes (started once, reused by every ``map``).

    Parameters
    ----------
    workers : int, optional
        Number of processes; default ``os.cpu_count()``.
    start_method : {"spawn", "forkserver", "fork"}
        How workers start. ``"spawn"`` (default) is safe with OpenCV's threads; workers
        import gridmerge once, which costs about a second, and run OpenCV single-threaded
        (the pool is the parallelism). As with any spawned pool, the main program must be
        importable (a script or module, guarded by ``if __name__ == "__main__":``).
    """

    def __init__(self, workers: int | None = None, start_method: str = "spawn"):
        n = (os.cpu_count() or 1) if workers is None else int(workers)
        if n < 1:
            raise GridMergeError(f"workers must be at least 1, got {workers}")
        self.workers = n
        self._pool = ProcessPoolExecutor(
            max_workers=n, mp_context=multiprocessing.get_context(start_method), initializer=_one_opencv_thread
        )

    def map(self, fn: Callable[[Any], Any], items: Iterable[Any]) -> list:
        items = list(items)
        if not items:
            return []
        return list(self._pool.map(fn, items))

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __repr__(self) -> str:
        return f"ProcessExecutor(workers={self.workers})"


def _one_opencv_thread() -> None:
    """In a pool worker: OpenCV's own threads would only compete with the other workers."""
    import cv2

    cv2.setNumThreads(1)


#: Guards OpenCV's thread count while :func:`opencv_threads_split` holds it.
_SPLIT_LOCK = threading.Lock()
#: ``[holders, OpenCV's thread count before the first one]``.
_SPLIT_STATE: list = [0, None]


@contextmanager
def opencv_threads_split(ways: int = 2):
    """OpenCV's threads cut to a ``ways``-th of the cores (at least one, never more than
    it had) while the block runs: for code that runs ``ways`` threads of its own, each
    calling OpenCV (``align`` finds both maps' features at once, and its judge's helper
    thread makes the refinement's fields while the keypoints are matched). OpenCV's
    parallel loops, one per core in each of those threads, would otherwise wait for cores
    the other threads hold: on two cores the 1585 x 1585 speed pair took 0.53-0.54 s
    with them and 0.50 s with one OpenCV thread each. Results do not depend on it.

    OpenCV's thread count is one setting for the whole process: the first of nested or
    concurrent holders sets it, the last one out restores it.
    """
    import cv2

    cores = os.cpu_count() or 1
    with _SPLIT_LOCK:
        if _SPLIT_STATE[0] == 0:
            _SPLIT_STATE[1] = cv2.getNumThreads()
            cv2.setNumThreads(max(1, min(_SPLIT_STATE[1], cores // max(1, int(ways)))))
        _SPLIT_STATE[0] += 1
    try:
        yield
    finally:
        with _SPLIT_LOCK:
            _SPLIT_STATE[0] -= 1
            if _SPLIT_STATE[0] == 0:
                cv2.setNumThreads(_SPLIT_STATE[1])


#: glibc's ``mallopt`` parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3


def keep_freed_memory(mmap_threshold_mb: int = 32, trim_threshold_mb: int = 512) -> bool:
    """Ask the C library's allocator to keep large freed blocks for reuse, for a process
    that aligns many maps (a fleet merge, ``gridmerge bench``, a long-running node).

    One alignment of two 1585 x 1585 maps touches about 180 MB of memory the process
    has not used before (SIFT's pyramids, the refinement's fields, the scorer's tables).
    By default glibc hands blocks of that size back to the system when they are freed,
    so every alignment pays again for fresh pages (about 0.06-0.09 s of its 0.6 s on
    this project's 2-core machine). With blocks of up to ``mmap_threshold_mb`` taken from
    the heap, and up to ``trim_threshold_mb`` of free heap kept, the next alignment
    reuses them: 0.49-0.50 s. The price is that memory: the process's resident size stays
    up to ``trim_threshold_mb`` above what it uses. It changes the whole process, which
    is why the library never calls it on its own; gridmerge's command line does, for
    itself. The same as setting ``MALLOC_MMAP_THRESHOLD_`` and ``MALLOC_TRIM_THRESHOLD_``
    in the environment before the process starts.

    Returns whether it applied (glibc only; ``False`` elsewhere, changing nothing).
    """
    import ctypes
    import ctypes.util
    import platform

    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return False
    mallopt = getattr(libc, "mallopt", None)
    if mallopt is None:
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    mb = 1024 * 1024
    return (mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold_mb) * mb) == 1
            and mallopt(_M_TRIM_THRESHOLD, int(trim_threshold_mb) * mb) == 1)


class DaskExecutor(_Closing):
    """The workers of a Dask distributed cluster.

    Parameters
    ----------
    address : str, optional
        The scheduler's address (``tcp://host:8786``). Ignored when ``client`` is given.
    client : distributed.Client, optional
        A client you already have (it is not closed by :meth:`close`).
    timeout : float
        Seconds to wait for the scheduler when connecting.

    Raises
    ------
    GridMergeError
        When ``dask.distributed`` is not installed (``pip install gridmerge[dask]``) or the
        scheduler cannot be reached.
    """

    def __init__(self, address: str | None = None, *, client=None, timeout: float = 10.0):
        try:
            from distributed import Client
        except ImportError:  # pragma: no cover - dask is in the dev extra
            raise GridMergeError("a Dask scheduler needs dask.distributed: pip install 'gridmerge[dask]'") from None
        if client is None:
            if not address:
                raise GridMergeError("DaskExecutor needs a scheduler address or a client")
            try:
                client = Client(address, timeout=timeout)
            except (OSError, TimeoutError) as exc:
                raise GridMergeError(f"cannot reach the Dask scheduler at {address}: {exc}") from None
            self._own = True
        else:
            self._own = False
        self.client = client
        self.workers = max(1, sum(w.get("nthreads", 1) for w in client.scheduler_info().get("workers", {}).values()))

    def map(self, fn: Callable[[Any], Any], items: Iterable[Any]) -> list:
        items = list(items)
        if not items:
            return []
        # pure=False: equal items (e.g. one map aligned twice) are still separate jobs.
        futures = self.client.map(fn, items, pure=False)
        return self.client.gather(futures)

    def close(self) -> None:
        if self._own:
            self.client.close()

    def __repr__(self) -> str:
        return f"DaskExecutor({self.client.scheduler.address!r})"


def executor_for(workers: int | None = None, scheduler: str | None = None) -> SerialExecutor | ProcessExecutor | DaskExecutor:
    """The executor asked for on the command line.

    ``scheduler`` (a Dask address) wins; then ``workers`` > 1 gives a process pool;
    otherwise serial. Use it as a context manager so that pools are shut down.
    """
    if scheduler:
        return DaskExecutor(scheduler)
    if workers is not None and int(workers) > 1:
        return ProcessExecutor(int(workers))
    if workers is not None and int(workers) < 1:
        raise GridMergeError(f"workers must be at least 1, got {workers}")
    return SerialExecutor()

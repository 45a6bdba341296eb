"""Speed and memory of align and merge, from 500 x 500 to 4000 x 4000 cells.

Run with ``python -m pytest benchmarks --benchmark-only`` (needs pytest-benchmark; not part
of the normal test run). See ``benchmarks/README.md`` for the targets.

Each pair: a procedural building of ``size x size`` cells (``samples.building``); robot a
scans it from viewpoints in its left 70 %, robot b from viewpoints in its right 70 %
(``samples.explore``, 7.5 m range, one viewpoint per 8000 free cells), and b's map is turned by 30 degrees about its centre
(nearest-neighbour warp, same canvas). Both maps are ``size x size``. Pairs are generated
once and kept in pytest's cache (``.pytest_cache``); ``--cache-clear`` regenerates them.

Every benchmark stores in ``extra_info``: the peak memory of one call (tracemalloc, MB:
numpy and Python allocations, not OpenCV's native ones), the process's max RSS (MB),
whether the call aligned and its corner error (px), the target time, and for the default
method its median time over the ``orb`` baseline's on the same pair.
Set ``GRIDMERGE_BENCH_STRICT=1`` to turn the targets into assertions.
"""

from __future__ import annotations

import inspect
import math
import os
import sys
import time
import tracemalloc

import numpy as np
import pytest

pytest.importorskip("pytest_benchmark")

import gridmerge  # noqa: E402
from gridmerge import OccupancyGrid, samples  # noqa: E402
from gridmerge.align import METHODS  # noqa: E402
from gridmerge.transforms import corner_error  # noqa: E402

SIZES = (500, 1000, 1585, 2000, 4000)
#: The default method of gridmerge.align.
DEFAULT = inspect.signature(gridmerge.align).parameters["method"].default
BASELINE = "orb"
#: Median seconds the default method must stay under, by size (README targets).
TARGET_S = {1585: 0.5, 4000: 3.0}
MEMORY_TARGET_MB = 1024.0
BASELINE_FACTOR = 2.0
STRICT = os.environ.get("GRIDMERGE_BENCH_STRICT", "") not in ("", "0")
_GENERATOR_VERSION = 2

#: Median align times measured in this session: (method, size) -> seconds.
_MEDIANS: dict = {}


def _rounds(size: int) -> int:
    return 5 if size <= 1000 else 3 if size <= 2000 else 2


def _make_pair(size: int, seed: int = 0):
    world = samples.building(seed, (size, size))
    rng = np.random.default_rng([seed, size])
    cols = np.broadcast_to(np.arange(size)[None, :], (size, size))
    free = int(world.free().sum())
    n = max(8, free // 8000)
    va = samples.random_viewpoints(world, n, rng=rng, region=cols < 0.7 * size, clearance=5.0)
    vb = samples.random_viewpoints(world, n, rng=rng, region=cols > 0.3 * size, clearance=5.0)
    a = samples.explore(world, va, max_range_px=150)
    b_world = samples.explore(world, vb, max_range_px=150)
    c = (size - 1) / 2.0
    t = math.radians(30.0)
    rot = np.array([[math.cos(t), -math.sin(t), 0.0], [math.sin(t), math.cos(t), 0.0], [0.0, 0.0, 1.0]])
    shift = np.array([[1.0, 0.0, c], [0.0, 1.0, c], [0.0, 0.0, 1.0]])
    truth = shift @ rot @ np.linalg.inv(shift)  # b pixels -> a pixels (= world pixels)
    b = samples.warp(b_world, truth[:2], (size, size), interpolation="nearest")
    return a.data, b.data, truth


@pytest.fixture(scope="session")
def pairs(request):
    """``pairs(size) -> (a, b, truth)``, generated once and cached on disk."""
    cache = getattr(request.config, "cache", None)  # None with -p no:cacheprovider
    cache_dir = None if cache is None else cache.mkdir("gridmerge-speed")
    made: dict = {}

    def get(size: int):
        if size not in made:
            f = None if cache_dir is None else cache_dir / f"pair-v{_GENERATOR_VERSION}-{size}.npz"
            if f is not None and f.is_file():
                z = np.load(f)
                a, b, truth = z["a"], z["b"], z["truth"]
            else:
                a, b, truth = _make_pair(size)
                if f is not None:
                    np.savez_compressed(f, a=a, b=b, truth=truth)
            made[size] = (OccupancyGrid(a, name=f"a{size}"), OccupancyGrid(b, name=f"b{size}"), truth)
        return made[size]

    return get


def _max_rss_mb():
    try:
        import resource
    except ImportError:  # pragma: no cover - Windows
        return None
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / (1024.0 * 1024.0) if sys.platform == "darwin" else rss / 1024.0


def _peak_mb(fn):
    """(result, tracemalloc peak in MB) of one call."""
    tracemalloc.start()
    try:
        out = fn()
        peak = tracemalloc.get_traced_memory()[1] / 1e6
    finally:
        tracemalloc.stop()
    return out, peak


def _methods():
    names = [BASELINE, DEFAULT] if BASELINE in METHODS else [DEFAULT]
    return list(dict.fromkeys(names))


@pytest.mark.parametrize("size", SIZES)
@pytest.mark.parametrize("method", _methods())
def test_align(benchmark, pairs, size, method):
    a, b, truth = pairs(size)
    benchmark.group = f"align {size}x{size}"
    result, peak = _peak_mb(lambda: gridmerge.align(a, b, method=method, rng=0))
    t0 = time.perf_counter()
    benchmark.pedantic(gridmerge.align, args=(a, b), kwargs={"method": method, "rng": 0}, rounds=_rounds(size), iterations=1)
    median = benchmark.stats.stats.median if benchmark.stats is not None else time.perf_counter() - t0
    _MEDIANS[(method, size)] = median
    info = benchmark.extra_info
    info["cells"] = 2 * size * size
    info["peak_mb"] = round(peak, 1)
    info["max_rss_mb"] = _max_rss_mb()
    info["aligned"] = bool(result.success)
    info["corner_error_px"] = None if result.transform is None else round(corner_error(result.transform, truth, b.shape), 3)
    if method == DEFAULT:
        info["target_s"] = TARGET_S.get(size)
        base = _MEDIANS.get((BASELINE, size))
        info["vs_orb"] = None if not base else round(median / base, 2)
        if STRICT:
            assert peak < MEMORY_TARGET_MB
            if size in TARGET_S:
                assert median < TARGET_S[size], f"{median:.2f} s >= {TARGET_S[size]} s"
            if base:
                assert median <= BASELINE_FACTOR * base, f"{median:.2f} s > {BASELINE_FACTOR} x {base:.2f} s of {BASELINE}"


@pytest.mark.parametrize("size", SIZES)
def test_merge(benchmark, pairs, size):
    a, b, truth = pairs(size)
    benchmark.group = f"merge {size}x{size}"
    result, peak = _peak_mb(lambda: gridmerge.merge([a, b], rng=0))
    benchmark.pedantic(gridmerge.merge, args=([a, b],), kwargs={"rng": 0}, rounds=_rounds(size), iterations=1)
    info = benchmark.extra_info
    info["cells"] = 2 * size * size
    info["peak_mb"] = round(peak, 1)
    info["max_rss_mb"] = _max_rss_mb()
    info["merged"] = bool(result.success)
    info["merged_shape"] = None if result.grid is None else list(result.grid.shape)
    if STRICT:
        assert peak < MEMORY_TARGET_MB

"""Descriptor matching (the paper's section III.B), as plain functions.

Every function takes two ``(N, D)`` and ``(M, D)`` descriptor arrays and returns
``(dists, idxs)``: ``(K,)`` float distances and ``(K, 2)`` int index pairs
``(i in desc1, j in desc2)``, sorted by ``i``.

Float descriptors (SIFT) are compared by Euclidean distance with FLANN's randomized
kd-trees (``method="flann"``: approximate, 76-90 % of the nearest neighbours of the
benchmark's 1585 x 1585 to 4000 x 4000 pairs' SIFT descriptors right) or exhaustively
(``"brute"``: every pair, by a matrix product; exact). Binary descriptors (ORB) use
Hamming distance, exhaustively.

Examples
--------
>>> import numpy as np
>>> rng = np.random.default_rng(0)
>>> d1 = rng.random((50, 128), dtype=np.float32)
>>> d2 = d1[::-1] + 0.01
>>> dists, idxs = match_snn(d1, d2, ratio=0.8)
>>> bool((idxs[:, 1] == 49 - idxs[:, 0]).all()), len(idxs)
(True, 50)
"""

from __future__ import annotations

from contextlib import nullcontext

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

__all__ = ["knn", "match_nn", "match_snn", "match_mnn", "match_smnn"]

_FLANN_INDEX_KDTREE = 1
#: Distances of at most this many pairs of descriptors are held at once.
_BLOCK_PAIRS = 4_000_000


def _empty():
    return np.zeros(0, dtype=float), np.zeros((0, 2), dtype=int)


def _as_descriptors(d, binary: bool) -> np.ndarray:
    arr = np.asarray(d)
    if arr.ndim != 2:
        raise ValueError(f"descriptors must be a 2-D array, got shape {arr.shape}")
    return np.ascontiguousarray(arr, dtype=np.uint8 if binary else np.float32)


def knn(
    desc1, desc2, k: int = 2, *, method: str = "flann", binary: bool | None = None, trees: int = 4, checks: int = 128, seed: int = 0,
    threads: int | None = None,
):
    """The ``k`` nearest neighbours in ``desc2`` of each row of ``desc1``.

    ``method``: ``"flann"`` (approximate) or ``"brute"`` (every pair). The exhaustive
    search breaks ties between equally near descriptors by index, the lower first; its
    distances are exact for integer-valued descriptors such as OpenCV's SIFT (whatever
    the machine's matrix product). FLANN's randomized kd-trees draw from OpenCV's
    global random generator, which is seeded with ``seed`` just before the index is
    built, so results are repeatable.

    ``threads``: at most this many BLAS threads for the exhaustive search's matrix
    product (``None``: the BLAS library's own choice, usually one per core). Give 1
    when another thread of the caller keeps the other cores busy: a BLAS thread per core
    then waits for cores it cannot have (on two cores, with the other one busy, the
    product of 3322 x 2709 SIFT descriptors took 0.06 s on two threads, 0.03 s on one).
    The result does not depend on it.

    Returns
    -------
    dists : (N, k) float array
        Distances (Euclidean, or Hamming for binary descriptors); ``inf`` where fewer
        than ``k`` neighbours exist.
    idxs : (N, k) int array
        Indices into ``desc2``; ``-1`` where missing.
    """
    if binary is None:
        binary = np.asarray(desc1).dtype == np.uint8
    d1 = _as_descriptors(desc1, binary)
    d2 = _as_descriptors(desc2, binary)
    n = d1.shape[0]
    dists = np.full((n, k), np.inf)
    idxs = np.full((n, k), -1, dtype=int)
    if n == 0 or d2.shape[0] == 0:
        return dists, idxs
    if d1.shape[1] != d2.shape[1]:
        raise ValueError(f"descriptor sizes differ: {d1.shape[1]} and {d2.shape[1]}")
    if method not in ("flann", "brute"):
        raise ValueError(f"unknown matching method {method!r} (use 'flann' or 'brute')")
    kk = min(k, d2.shape[0])
    if not binary and method == "brute":
        limit = nullcontext() if threads is None else threadpool_limits(limits=max(1, int(threads)), user_api="blas")
        with limit:
            dists[:, :kk], idxs[:, :kk] = _exhaustive(d1, d2, kk)
        return dists, idxs
    if not binary:
        # FLANN's index, built from OpenCV's seeded generator and searched directly: what
        # FlannBasedMatcher.knnMatch does, without a Python object per match (the same
        # neighbours and distances; 0.01 s less for the 1585 x 1585 speed pair). It gives
        # squared distances.
        cv2.setRNGSeed(int(seed))
        index = cv2.flann_Index(d2, {"algorithm": _FLANN_INDEX_KDTREE, "trees": int(trees)})
        found, sq = index.knnSearch(d1, kk, params={"checks": int(checks)})
        found = np.asarray(found, dtype=int).reshape(n, kk)
        ok = found >= 0
        idxs[:, :kk] = np.where(ok, found, -1)
        # The square root in float32, as OpenCV's matches carry it.
        root = np.sqrt(np.maximum(np.asarray(sq, dtype=np.float32).reshape(n, kk), 0.0)).astype(float)
        dists[:, :kk] = np.where(ok, root, np.inf)
        return dists, idxs
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    for row in matcher.knnMatch(d1, d2, k=kk):
        for c, m in enumerate(row):
            dists[m.queryIdx, c] = m.distance
            idxs[m.queryIdx, c] = m.trainIdx
    return dists, idxs


def _exhaustive(d1: np.ndarray, d2: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """``(N, k)`` Euclidean distances and indices of the ``k`` nearest rows of ``d2`` to
    each row of ``d1`` (float arrays), comparing every pair; ties go to the lower index.
    Squared distances ``|x|^2 + |y|^2 - 2 x.y`` by blocks of rows: in float32 when every
    sum is an integer below 2**24 (exact, as for SIFT's integer-valued descriptors),
    in float64 otherwise."""
    exact = all(bool(np.all(d == np.round(d))) for d in (d1, d2))
    top = max(float(np.abs(d1).max(initial=0.0)), float(np.abs(d2).max(initial=0.0)))
    # Every term and partial sum is within 2 * D * top^2 for non-negative descriptors
    # (the -2 x.y term), 4 * D * top^2 otherwise.
    spread = 2 if min(float(d1.min(initial=0.0)), float(d2.min(initial=0.0))) >= 0 else 4
    dtype = np.float32 if exact and spread * d1.shape[1] * top * top < 2**24 else np.float64
    a, b = d1.astype(dtype), d2.astype(dtype)
    na, nb = (a * a).sum(axis=1), (b * b).sum(axis=1)
    n = a.shape[0]
    dists = np.empty((n, k))
    idxs = np.empty((n, k), dtype=int)
    rows = max(1, _BLOCK_PAIRS // max(1, b.shape[0]))
    for s in range(0, n, rows):
        sq = a[s : s + rows] @ b.T
        sq *= -2
        sq += na[s : s + rows, None]
        sq += nb[None, :]
        r = np.arange(sq.shape[0])
        for c in range(k):
            j = np.argmin(sq, axis=1)  # the first of equal minima: the lower index
            dists[s : s + rows, c] = sq[r, j]
            idxs[s : s + rows, c] = j
            sq[r, j] = np.inf
    return np.sqrt(np.maximum(dists, 0.0)), idxs


def match_nn(desc1, desc2, **kwargs):
    """Nearest neighbour of each descriptor of ``desc1`` in ``desc2`` (the paper's rule)."""
    dists, idxs = knn(desc1, desc2, 1, **kwargs)
    ok = idxs[:, 0] >= 0
    i = np.nonzero(ok)[0]
    return dists[ok, 0], np.stack([i, idxs[ok, 0]], axis=1)


def match_snn(desc1, desc2, ratio: float = 0.8, **kwargs):
    """Nearest neighbours that pass Lowe's ratio test ``d1 < ratio * d2``."""
    dists, idxs = knn(desc1, desc2, 2, **kwargs)
    if len(dists) == 0:
        return _empty()
    ok = (idxs[:, 0] >= 0) & (dists[:, 0] < ratio * dists[:, 1])
    i = np.nonzero(ok)[0]
    return dists[ok, 0], np.stack([i, idxs[ok, 0]], axis=1)


def _mutual(dists, pairs, desc1, desc2, kwargs):
    if len(pairs) == 0:
        return dists, pairs
    _, back = knn(desc2, desc1, 1, **kwargs)
    keep = back[pairs[:, 1], 0] == pairs[:, 0]
    return dists[keep], pairs[keep]


def match_mnn(desc1, desc2, **kwargs):
    """Mutual nearest neighbours: ``j`` is ``i``'s nearest and ``i`` is ``j``'s nearest."""
    dists, pairs = match_nn(desc1, desc2, **kwargs)
    return _mutual(dists, pairs, desc1, desc2, kwargs)


def match_smnn(desc1, desc2, ratio: float = 0.8, **kwargs):
    """Ratio test and mutual check together."""
    dists, pairs = match_snn(desc1, desc2, ratio, **kwargs)
    return _mutual(dists, pairs, desc1, desc2, kwargs)

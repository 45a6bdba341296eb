"""Descriptor matching (the paper's section III.B), as plain functions.

Every function takes two ``(N, D)`` and ``(M, D)`` descriptor arrays and returns
``(dists, idxs)``: ``(K,)`` float distances and ``(K, 2)`` int index pairs
``(i in desc1, j in desc2)``, sorted by ``i``.

Float descriptors (SIFT) are compared by Euclidean distance with FLANN's randomized
kd-trees (``method="flann"``, approximate and fast) or exhaustively (``"brute"``). Binary
descriptors (ORB) use Hamming distance, exhaustively.

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

import cv2
import numpy as np

__all__ = ["knn", "match_nn", "match_snn", "match_mnn", "match_smnn"]

_FLANN_INDEX_KDTREE = 1


def _empty():
    return np.zeros(0, dtype=float), np.zeros((0, 2), dtype=int)


def _as_descriptors(d, binary: bool) -> np.ndarray:
    arr = np.asarray(d)
    if arr.ndim != 2:
        raise ValueError(f"descriptors must be a 2-D array, got shape {arr.shape}")
    return np.ascontiguousarray(arr, dtype=np.uint8 if binary else np.float32)


def knn(
    desc1, desc2, k: int = 2, *, method: str = "flann", binary: bool | None = None, trees: int = 4, checks: int = 128, seed: int = 0
):
    """The ``k`` nearest neighbours in ``desc2`` of each row of ``desc1``.

    FLANN's randomized kd-trees draw from OpenCV's global random generator, which is
    seeded with ``seed`` just before the index is built, so results are repeatable.

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
    if binary:
        matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    elif method == "flann":
        matcher = cv2.FlannBasedMatcher({"algorithm": _FLANN_INDEX_KDTREE, "trees": int(trees)}, {"checks": int(checks)})
    elif method == "brute":
        matcher = cv2.BFMatcher(cv2.NORM_L2)
    else:
        raise ValueError(f"unknown matching method {method!r} (use 'flann' or 'brute')")
    kk = min(k, d2.shape[0])
    if method == "flann" and not binary:
        cv2.setRNGSeed(int(seed))
    for row in matcher.knnMatch(d1, d2, k=kk):
        for c, m in enumerate(row):
            dists[m.queryIdx, c] = m.distance
            idxs[m.queryIdx, c] = m.trainIdx
    return dists, idxs


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

"""Warping maps into a common frame and fusing their cells (the paper's section III.D).

Fusion rules, cell by cell, for cells known in several maps (a cell that only one map
knows keeps that map's value; a cell no map knows stays unknown):

* ``"average"``: the paper's eq. (9), the mean of the known values;
* ``"logodds"``: Bayesian fusion of independent evidence, the sum of the log-odds
  (probabilities clipped to ``[0.001, 0.999]`` so that certain cells stay finite);
* ``"max"``: the largest occupancy, as m-explore's ``multirobot_map_merge`` does.

Examples
--------
>>> import numpy as np
>>> a = np.array([[0.0, 1.0, np.nan, np.nan]])
>>> b = np.array([[1.0, 1.0, 0.2, np.nan]])
>>> fuse_values([a, b], "average").tolist()
[[0.5, 1.0, 0.20000000298023224, nan]]
>>> fuse_values([a, b], "max").tolist()
[[1.0, 1.0, 0.20000000298023224, nan]]
"""

from __future__ import annotations

from typing import Iterable, Sequence

import cv2
import numpy as np

__all__ = ["FUSION_RULES", "warp_values", "fuse_values"]

FUSION_RULES = ("average", "logodds", "max")
_LOGODDS_CLIP = 1e-3


def _cell_permutation(matrix) -> tuple[np.ndarray, np.ndarray] | None:
    """``(A, t)`` when the ``(2, 3)`` affine ``matrix`` moves the cell grid onto itself
    (a quarter turn or mirroring, ``A`` with one entry of +-1 in each row and column, and
    a whole-cell shift ``t``); ``None`` otherwise."""
    m = np.asarray(matrix, dtype=float)
    m = m[:2] if m.shape == (3, 3) else m
    if m.shape != (2, 3) or not np.isfinite(m).all() or not np.array_equal(m, np.rint(m)):
        return None
    a, t = m[:, :2], m[:, 2]
    if not (np.abs(a).sum(axis=0) == 1).all() or not (np.abs(a).sum(axis=1) == 1).all():
        return None
    return a, t


def reindexed(data: np.ndarray, inverse, out_shape: Sequence[int], fill=np.nan) -> np.ndarray | None:
    """``out(p) = data(inverse @ p)`` for ``inverse`` (output pixels ``(x, y)`` -> ``data``'s
    pixels) that moves the cell grid onto itself: quarter turns, mirrorings and
    whole-cell shifts, which every interpolation carries cell for cell. The cells are
    copied (exactly, whatever OpenCV's interpolation does with round-off); ``fill`` off
    ``data``. ``None`` for any other transform.

    Examples
    --------
    >>> import numpy as np
    >>> d = np.arange(6.0).reshape(2, 3)
    >>> reindexed(d, [[0, 1, 0], [-1, 0, 1]], (3, 2)).tolist()  # out(x, y) = d(y, 1 - x)
    [[3.0, 0.0], [4.0, 1.0], [5.0, 2.0]]
    >>> reindexed(d, [[1, 0, 2], [0, 1, 0]], (2, 2), fill=-1.0).tolist()  # out(x) = d(x + 2)
    [[2.0, -1.0], [5.0, -1.0]]
    >>> reindexed(d, [[1, 0, 0.5], [0, 1, 0]], (2, 3)) is None
    True
    """
    found = _cell_permutation(inverse)
    return None if found is None else _copy_cells(np.asarray(data), *found, out_shape, fill)


def _copy_cells(src: np.ndarray, a: np.ndarray, t: np.ndarray, out_shape: Sequence[int], fill) -> np.ndarray:
    """:func:`reindexed` for ``inverse = [a | t]`` already found to move the cell grid
    onto itself (:func:`_cell_permutation`)."""
    h, w = int(out_shape[0]), int(out_shape[1])
    out = np.full((h, w), fill, dtype=src.dtype)
    if a[0, 0] == 0:
        # x_in = a01 y + t0, y_in = a10 x + t1: out[y, x] = data.T[x_in, y_in].
        src, rs, rt, cs, ct = src.T, int(a[0, 1]), int(t[0]), int(a[1, 0]), int(t[1])
    else:
        rs, rt, cs, ct = int(a[1, 1]), int(t[1]), int(a[0, 0]), int(t[0])

    def span(step: int, shift: int, n_out: int, n_in: int) -> tuple[int, int]:
        # The outputs i with 0 <= step * i + shift < n_in.
        lo, hi = (-shift, n_in - shift) if step > 0 else (shift - n_in + 1, shift + 1)
        return max(0, lo), max(max(0, lo), min(n_out, hi))

    y0, y1 = span(rs, rt, h, src.shape[0])
    x0, x1 = span(cs, ct, w, src.shape[1])
    if y0 < y1 and x0 < x1:
        rows = rs * np.arange(y0, y1) + rt
        cols = cs * np.arange(x0, x1) + ct
        out[y0:y1, x0:x1] = src[rows[:, None], cols[None, :]]
    return out


def warp_values(
    data: np.ndarray,
    matrix: np.ndarray,
    out_shape: Sequence[int],
    *,
    interpolation: str = "linear",
) -> np.ndarray:
    """Warp a ``(H, W)`` occupancy array (``NaN`` = unknown) into another pixel frame.

    Parameters
    ----------
    data : (H, W) float array
        Probabilities with ``NaN`` for unknown cells.
    matrix : (2, 3) or (3, 3) float array
        Maps ``data``'s pixels ``(x, y)`` to the output's pixels.
    out_shape : (H', W')
        Shape of the output.
    interpolation : {"linear", "nearest"}
        ``"linear"`` interpolates values and the known mask separately, so unknown cells
        never bleed into known ones: an output cell is known when at least half of its
        interpolation weight falls on known cells. A transform that moves the cell grid
        onto itself (quarter turns, mirrorings, whole-cell shifts) copies the cells
        exactly, with either (:func:`reindexed`).

    Returns
    -------
    (H', W') float32 array
        ``NaN`` where unknown or outside ``data``.
    """
    m = np.asarray(matrix, dtype=float)
    m = m[:2] if m.shape == (3, 3) else m
    h, w = int(out_shape[0]), int(out_shape[1])
    src = np.asarray(data, dtype=np.float32)
    if interpolation not in ("linear", "nearest"):
        raise ValueError(f"unknown interpolation {interpolation!r} (use 'linear' or 'nearest')")
    grid_move = _cell_permutation(m)
    if grid_move is not None:  # cell for cell: copied, not interpolated
        a, t = grid_move
        moved = _copy_cells(src, a.T, -a.T @ t, (h, w), np.nan)  # the inverse of [a | t]
        return np.clip(moved, 0.0, 1.0, out=moved)
    known = (~np.isnan(src)).astype(np.float32)
    vals = np.nan_to_num(src, nan=0.0)
    flag = cv2.INTER_NEAREST if interpolation == "nearest" else cv2.INTER_LINEAR
    kw = dict(flags=flag, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    wk = cv2.warpAffine(known, m, (w, h), **kw)
    wv = cv2.warpAffine(vals * known, m, (w, h), **kw)
    # In place: the output is canvas-sized, and merged canvases are the largest arrays
    # gridmerge makes.
    ok = wk >= 0.5 - 1e-6
    np.divide(wv, wk, out=wv, where=ok)
    np.clip(wv, 0.0, 1.0, out=wv)
    wv[~ok] = np.nan
    return wv


def fuse_values(layers: Iterable[np.ndarray], rule: str = "average") -> np.ndarray:
    """Fuse equally shaped occupancy arrays (``NaN`` = unknown) cell by cell.

    Parameters
    ----------
    layers : iterable of (H, W) float arrays
        Consumed one at a time: a generator that warps each map as it is needed keeps
        one layer in memory, not all of them.
    rule : {"average", "logodds", "max"}

    Returns
    -------
    (H, W) float32 array
        ``NaN`` where no layer knows the cell.
    """
    if rule not in FUSION_RULES:
        raise ValueError(f"unknown fusion rule {rule!r} (use one of {', '.join(FUSION_RULES)})")
    total = count = extra = None
    for layer in layers:
        v = np.asarray(layer, dtype=np.float32)
        if total is None:
            total = np.zeros(v.shape, np.float32)  # sum of the known values
            count = np.zeros(v.shape, np.uint16)  # layers knowing each cell
            if rule == "max":
                extra = np.full(v.shape, -np.inf, np.float32)
            elif rule == "logodds":
                extra = np.zeros(v.shape, np.float32)  # sum of the log-odds
        elif v.shape != total.shape:
            raise ValueError(f"layers of different shapes: {total.shape} and {v.shape}")
        known = ~np.isnan(v)
        count += known
        np.add(total, v, out=total, where=known)
        if rule == "max":
            np.fmax(extra, v, out=extra)  # fmax ignores NaN
        elif rule == "logodds":
            p = np.clip(np.where(known, v, np.float32(0.5)), _LOGODDS_CLIP, 1.0 - _LOGODDS_CLIP)
            extra += np.log(p / (1.0 - p))
    if total is None:
        raise ValueError("nothing to fuse")
    # The result is computed in place, in arrays made here (the canvas may be large).
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        if rule == "average":
            out = np.divide(total, count, out=total)
        elif rule == "max":
            out = extra
        else:
            out = np.negative(extra, out=extra)
            np.exp(out, out=out)
            out += 1.0
            np.reciprocal(out, out=out)
            # A cell known to one map only keeps that map's value exactly.
            single = count == 1
            out[single] = total[single]
    out[count == 0] = np.nan
    return out

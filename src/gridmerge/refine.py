"""Sub-pixel refinement of a similarity transform against the maps themselves.

Keypoint positions are only as precise as the detector; the cells of the two maps hold
far more evidence. :func:`refine_direct` minimises, by Gauss-Newton with Huber weights,
the difference between smoothed occupancy fields of the two maps over the cells both
know, coarse to fine (the smoothing shrinks from ``sigmas[0]`` to ``sigmas[-1]``). Only
cells near structure (where the smoothed field has a gradient) take part, so the vast
free areas of a map cost nothing. Each step is damped (Levenberg-Marquardt) until it
lowers the Huber cost of the cells both poses put on a's known area and stays within
``max_shift`` of the start: plain steps from a start 7-15 px off could run thousands of
pixels away on noisy maps.

The smoothed field is a normalised convolution, ``G * (p k) / G * k`` with ``k`` the known
mask, so unknown cells never pull walls towards them.

Every level's fields cover whole maps and are shared through ``cache`` by all the
candidates refined on one pair (and can be computed ahead: :func:`prepare_fields`); of
map b only the cells near structure and their values are kept.

Maps of more than :data:`LARGE_CELLS` cells are refined coarse to fine in resolution as
well, so that time and memory stay bounded: levels smoothed by at least
:data:`COARSE_SIGMA` of a's pixels run on both maps reduced by 2 (a Gaussian prefilter,
then every other cell; the smoothing, not the cells, limits those levels' precision), and
the finest level runs at full resolution with b's cells judged block by block from a
pool that the candidates share, and a's field computed on the box they reach only.
Nothing is drawn at random: where b has more cells than a level uses, an evenly spread
subset is taken, so a refinement does not depend on the ones made before it.
Smaller maps run every level at full resolution, exactly as the refinement was first
written (the reduced levels converge to slightly different poses on real maps that bend,
which changes borderline decisions).
"""

from __future__ import annotations

import copy
import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from .grid import OccupancyGrid
from .transforms import SimilarityTransform
from .verify import _strided_cells

__all__ = ["refine_direct", "RefineReport", "prepare_fields", "WallICP", "wall_search", "chamfer_polish"]


@dataclass(frozen=True)
class RefineReport:
    """What :func:`refine_direct` did.

    Attributes
    ----------
    accepted : bool
        Whether the refined transform replaced the initial one.
    iterations : int
        Gauss-Newton steps taken over all levels.
    points : int
        Cells of map b used at the finest level.
    shift_px : float
        Largest displacement of b's corners between initial and refined transforms.
    rms_before, rms_after : float
        Robust RMS of field differences at the finest level.
    """

    accepted: bool
    iterations: int
    points: int
    shift_px: float
    rms_before: float
    rms_after: float


#: Maps of more cells than this are refined coarse to fine in resolution (smaller ones
#: at full resolution throughout, whose whole-map fields are cheap enough).
LARGE_CELLS = 6_000_000
#: On large maps, levels smoothed by at least this many of a's pixels run at half resolution.
COARSE_SIGMA = 1.5


def _auto_factors(sigmas, large: bool) -> tuple[int, ...]:
    return tuple(2 if large and s >= COARSE_SIGMA else 1 for s in sigmas)


def _planes(grid: OccupancyGrid, box, factor: int):
    """``(known, known * value)`` of ``grid``'s ``box`` as float32, reduced by ``factor``:
    smoothed by a Gaussian of :func:`_prefilter` cells, then every ``factor``-th cell
    of every ``factor``-th row (reduced cell ``(x, y)`` is cell ``(factor x, factor y)``).
    A Gaussian, unlike block means, looks the same from every direction: the reduced
    fields of two maps turned against each other still match. Large boxes are reduced
    in bands of rows, so that no full-resolution copy of them is ever made."""
    x0, y0, x1, y1 = box
    if factor <= 1:
        return _raw_planes(grid.data[y0:y1, x0:x1])
    s = _prefilter(factor)
    reach = (int(round(s * 8 + 1)) | 1) // 2  # GaussianBlur's kernel radius
    h, w = y1 - y0, x1 - x0
    rows = -(-h // factor)
    k_out = np.empty((rows, -(-w // factor)), np.float32)
    v_out = np.empty_like(k_out)
    band = max(1, (1 << 21) // max(1, w * factor))  # reduced rows per band
    for r0 in range(0, rows, band):
        r1 = min(rows, r0 + band)
        lo, hi = r0 * factor, min(h, (r1 - 1) * factor + 1)  # full rows kept
        a0, a1 = max(0, lo - reach), min(h, hi + reach)  # ... and those the blur reaches
        k, v = _raw_planes(grid.data[y0 + a0 : y0 + a1, x0:x1])
        # Cut edges get their true neighbours; the map's own edges are reflected as
        # GaussianBlur reflects them on the whole map.
        k = cv2.GaussianBlur(k, (0, 0), s)[lo - a0 : hi - a0 : factor, ::factor]
        v = cv2.GaussianBlur(v, (0, 0), s)[lo - a0 : hi - a0 : factor, ::factor]
        k_out[r0:r1], v_out[r0:r1] = k, v
    return k_out, v_out


def _raw_planes(data: np.ndarray):
    v = data.astype(np.float32)
    k = (~np.isnan(v)).astype(np.float32)
    cv2.patchNaNs(v, 0.0)
    return k, v


def _prefilter(factor: int) -> float:
    """Smoothing (cells) before keeping every ``factor``-th cell (1 for 2, as a Gaussian pyramid)."""
    return 0.5 * factor


def _normalised(k: np.ndarray, v: np.ndarray, sigma: float):
    """The normalised convolution and the smoothed known mask (float32)."""
    sk = cv2.GaussianBlur(k, (0, 0), sigma)
    f = cv2.GaussianBlur(v, (0, 0), sigma)
    np.divide(f, np.maximum(sk, 1e-6), out=f)
    np.copyto(f, 0.0, where=sk <= 1e-3)
    return f, sk


def _gradient(f: np.ndarray, dx: int, dy: int, dst: np.ndarray | None = None) -> np.ndarray:
    """The x (``dx=1``) or y (``dy=1``) derivative of ``f`` per cell (float32)."""
    return cv2.Sobel(f, cv2.CV_32F, dx, dy, dst=dst, ksize=3, scale=1.0 / 8.0)


def _smoothed(k: np.ndarray, v: np.ndarray, sigma: float):
    """The normalised convolution, its gradient and the smoothed known mask (float32)."""
    f, sk = _normalised(k, v, sigma)
    return f, _gradient(f, 1, 0), _gradient(f, 0, 1), sk


def _level_sigma(sigma: float, factor: int) -> float:
    """Smoothing in reduced cells that, after :func:`_planes`' prefilter, totals ``sigma`` cells."""
    if factor <= 1:
        return sigma
    pre = _prefilter(factor)
    return math.sqrt(max(sigma * sigma - pre * pre, 0.25 * factor * factor)) / factor


def _a_field(grid: OccupancyGrid, box, factor: int, sigma: float, planes=None) -> np.ndarray:
    """Field, x and y gradients and smoothed known mask of ``box``: one ``(H, W, 4)``
    float32 image, interleaved so that one bilinear lookup reads all four at a point.
    ``planes``: :func:`_planes` of that box, when already computed."""
    k, v = planes if planes is not None else _planes(grid, box, factor)
    f, sk = _normalised(k, v, _level_sigma(sigma, factor))
    del k, v  # (made here, they go; a caller's stay)
    # Written a plane at a time: the four planes and the image at once would hold twice a
    # large map's box (114 MB more at the peak of the 4000 x 4000 speed pair).
    out = np.empty(f.shape + (4,), np.float32)
    cv2.mixChannels([sk], [out], [0, 3])
    del sk
    cv2.mixChannels([f], [out], [0, 0])
    g = _gradient(f, 1, 0)
    cv2.mixChannels([g], [out], [0, 1])
    cv2.mixChannels([_gradient(f, 0, 1, dst=g)], [out], [0, 2])
    return out


def _b_points(grid: OccupancyGrid, box, factor: int, sigma: float, planes=None):
    """Cells of b near structure (reduced coordinates of ``box``) and their field values.
    ``planes``: :func:`_planes` of the box, when already computed."""
    k, v = planes if planes is not None else _planes(grid, box, factor)
    f, gx, gy, sk = _smoothed(k, v, _level_sigma(sigma, factor))
    # Structure: a field changing by 0.01 per cell, or per smoothing width when wider (a
    # thin wall blurred over many cells, as a finer map's at a's coarse levels, changes by
    # less than 0.01 per cell).
    near = cv2.bitwise_and(cv2.compare(sk, 0.9, cv2.CMP_GT), cv2.compare(cv2.magnitude(gx, gy), 0.01 / max(1.0, sigma), cv2.CMP_GT))
    xy = cv2.findNonZero(cv2.bitwise_and(near, cv2.compare(k, 0.5, cv2.CMP_GT)))  # row by row, as np.nonzero
    xy = np.zeros((0, 2), np.intp) if xy is None else xy.reshape(-1, 2).astype(np.intp)
    xs, ys = xy[:, 0], xy[:, 1]
    return xs, ys, f[ys, xs].astype(np.float64)


def _scaling(f: float, offset=(0.0, 0.0)) -> np.ndarray:
    """Reduced pixels of a box at ``offset`` -> full pixels: ``x = f x' + offset``."""
    return np.array([[f, 0.0, offset[0]], [0.0, f, offset[1]], [0.0, 0.0, 1.0]])


_REMAP_MAX = 32767


def _cached(cache: dict | None, key, compute):
    if cache is None:
        return compute()
    if key not in cache:
        cache[key] = compute()
    return cache[key]


def _sample(img: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """``(N, C)`` bilinear values of ``img`` (``(H, W, C)``) at ``(N, 2)`` points (0 outside)."""
    n = len(xy)
    # remap wants maps shaped like an image of fewer than 32767 rows: fold the points.
    width = 1024
    rows = max(1, -(-n // width))
    m = np.full((rows * width, 2), -10.0, dtype=np.float32)
    m[:n] = xy
    out = cv2.remap(img, m.reshape(rows, width, 2), None, interpolation=cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    return out.reshape(rows * width, -1)[:n]


def _corner_shift(t0: np.ndarray, t1: np.ndarray, shape) -> float:
    h, w = shape
    c = np.array([[0.0, 0.0, 1.0], [w - 1.0, 0.0, 1.0], [w - 1.0, h - 1.0, 1.0], [0.0, h - 1.0, 1.0]])
    d = (c @ t0.T)[:, :2] - (c @ t1.T)[:, :2]
    return float(np.hypot(d[:, 0], d[:, 1]).max())


def _whole(grid: OccupancyGrid):
    return (0, 0, grid.width, grid.height)


def _box_of(points: np.ndarray, grow: float, shape):
    """Integer bounding box ``(x0, y0, x1, y1)`` of ``points`` grown by ``grow``, clipped."""
    h, w = shape
    lo = np.floor(points.min(0) - grow)
    hi = np.ceil(points.max(0) + grow) + 1
    x0, y0 = int(max(0, lo[0])), int(max(0, lo[1]))
    x1, y1 = int(min(w, hi[0])), int(min(h, hi[1]))
    return (x0, y0, max(x0, x1), max(y0, y1))


def _on_known(grid: OccupancyGrid, xy: np.ndarray) -> np.ndarray:
    """Which of the ``(N, 2)`` float points ``(x, y)`` lie on ``grid``'s known cells (the
    nearest cell)."""
    p = np.rint(xy).astype(np.int64)
    h, w = grid.shape
    on = (p[:, 0] >= 0) & (p[:, 0] < w) & (p[:, 1] >= 0) & (p[:, 1] < h)
    on[on] = grid.known[p[on, 1], p[on, 0]]
    return on


def _gaussian_taps(sigma: float) -> np.ndarray:
    """The kernel ``cv2.GaussianBlur`` uses on float images for ``sigma``."""
    ksize = int(round(sigma * 4 * 2 + 1)) | 1
    return cv2.getGaussianKernel(ksize, sigma, cv2.CV_64F).ravel()


def _block_fields(data: np.ndarray, bx: np.ndarray, by: np.ndarray, c: int, sigma: float):
    """What :func:`_smoothed` gives at full resolution, computed for the ``c x c`` blocks
    of cells at block coordinates ``(bx, by)`` (cells ``x = c bx + j``, ``y = c by + i``)
    from each block's neighbourhood of ``data`` (NaN unknown) only.

    Returns ``(x, y, field, gx, gy, smoothed known, known)``, one value per cell. Blocks
    closer to the border than the kernel's reach are left out.
    """
    taps = _gaussian_taps(sigma).astype(np.float32)
    r = len(taps) // 2
    reach = r + 1  # the gradient needs the field one cell around
    h, w = data.shape
    keep = (c * bx - reach >= 0) & (c * bx + c - 1 + reach < w) & (c * by - reach >= 0) & (c * by + c - 1 + reach < h)
    bx, by = bx[keep], by[keep]
    side = c + 2 * reach  # the window of a block
    outs = c + 2  # smoothed values at offsets -1 .. c from the block's first cell
    m = np.zeros((side, outs), np.float32)
    for o in range(outs):
        m[o : o + 2 * r + 1, o] = taps
    d = np.arange(side)
    offsets = (d[:, None] * w + d[None, :]).reshape(-1)
    flat = data.reshape(-1)
    wts = np.array([1.0, 2.0, 1.0], np.float32) / 8.0
    sub = np.arange(c)
    res = []
    for s0 in range(0, len(bx), 4096):  # bounded memory
        x0 = c * bx[s0 : s0 + 4096] - reach
        y0 = c * by[s0 : s0 + 4096] - reach
        k = len(x0)
        win = flat.take((y0 * w + x0)[:, None] + offsets[None, :]).astype(np.float32, copy=False)
        known = ~np.isnan(win)
        both = np.stack([known.astype(np.float32), np.where(known, win, np.float32(0.0))])  # (2, k, side^2)
        # Separable smoothing, rows then columns, each one matrix product.
        t = (both.reshape(2 * k * side, side) @ m).reshape(2, k, side, outs).transpose(0, 1, 3, 2)
        sm = (t.reshape(2 * k * outs, side) @ m).reshape(2, k, outs, outs).transpose(0, 1, 3, 2)  # [., ., y, x]
        sk, sv = sm[0], sm[1]
        f = np.where(sk > 1e-3, sv / np.maximum(sk, 1e-6), np.float32(0.0))
        kn = known.reshape(k, side, side)
        for i in range(c):
            for j in range(c):
                gx = (f[:, i : i + 3, j + 2] - f[:, i : i + 3, j]) @ wts
                gy = (f[:, i + 2, j : j + 3] - f[:, i, j : j + 3]) @ wts
                res.append((x0 + reach + j, y0 + reach + i, f[:, i + 1, j + 1], gx, gy, sk[:, i + 1, j + 1], kn[:, reach + i, reach + j]))
    if not res:
        z = np.zeros(0, np.float32)
        e = np.zeros(0, np.int64)
        return e, e, z, z, z, z, np.zeros(0, bool)
    return tuple(np.concatenate(col) for col in zip(*res))


def _landing(a: OccupancyGrid, params: np.ndarray, x: np.ndarray, y: np.ndarray, t: np.ndarray):
    """The cells ``(x, y)`` of b (and their values ``t``) that ``params`` puts on a's known cells."""
    ha, wa = a.shape
    q = np.rint(np.stack([x, y], axis=1) @ params[:2, :2].T + params[:2, 2])
    ok = (q[:, 0] >= 0) & (q[:, 0] < wa) & (q[:, 1] >= 0) & (q[:, 1] < ha)
    idx = np.flatnonzero(ok)
    ok[idx] = ~np.isnan(a.data[q[idx, 1].astype(np.int64), q[idx, 0].astype(np.int64)])
    return x[ok], y[ok], t[ok]



#: Blocks of b judged at once at full resolution (a fixed size, so that the pool of judged
#: cells does not depend on which candidate asked first).
_POOL_CHUNK = 2048


def _fine_points(a: OccupancyGrid, b: OccupancyGrid, params: np.ndarray, coarse_cells, coarse: int, sigma: float, max_points: int, pool: dict):
    """Up to ``max_points`` full-resolution cells of b near structure (as
    :func:`_b_points` would select them) that land on a's known cells under ``params``,
    and their field values.

    The blocks of the structure found at reduced resolution (``coarse_cells``, reduced
    by ``coarse``) are judged at full resolution a chunk at a time, in an order spread
    over the whole map (:func:`_spread_order`), until enough cells land; ``pool`` keeps
    what was judged, for the next candidate. No random draw: a candidate gets the same
    cells whichever candidates came before it.
    """
    cx, cy = coarse_cells
    if "order" not in pool:
        pool.update(order=_spread_order(len(cx)), next=0, chunks=[])
    kept_x, kept_y, kept_t = [], [], []
    count, i = 0, 0
    while count < max_points:
        if i == len(pool["chunks"]):
            if pool["next"] >= len(pool["order"]):
                break
            blocks = np.sort(pool["order"][pool["next"] : pool["next"] + _POOL_CHUNK])
            pool["next"] += _POOL_CHUNK
            x, y, f, gx, gy, sk, known = _block_fields(b.data, cx[blocks], cy[blocks], coarse, sigma)
            good = (sk > 0.9) & (gx * gx + gy * gy > 1e-4) & known
            pool["chunks"].append((x[good], y[good], f[good].astype(np.float64)))
        x, y, t = _landing(a, params, *pool["chunks"][i])
        i += 1
        kept_x.append(x)
        kept_y.append(y)
        kept_t.append(t)
        count += len(x)
    if not kept_x:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    x, y, t = (np.concatenate(c) for c in (kept_x, kept_y, kept_t))
    if len(x) > max_points:
        pick = _evenly(len(x), max_points)
        x, y, t = x[pick], y[pick], t[pick]
    return x, y, t


def _evenly(n: int, k: int) -> np.ndarray:
    """``k`` of the indices ``0 .. n - 1`` (``k <= n``), evenly spread and increasing."""
    return (np.arange(k, dtype=np.int64) * n) // k


def _spread_order(n: int) -> np.ndarray:
    """A permutation of ``0 .. n - 1`` whose every prefix is spread over the whole range
    (the golden-ratio sequence): the first blocks of b judged lie all over the map."""
    return np.argsort((np.arange(n) * 0.6180339887498949) % 1.0, kind="stable")


def _b_level(sigma_a: float, factor_a: int, scale: float) -> tuple[float, int]:
    """b's smoothing and reduction for a level smoothed by ``sigma_a`` of a's cells and
    reduced by ``factor_a``, at ``scale`` (a's cells per b cell)."""
    # Clamped: an extreme scale would make the blur enormous (and slow) for nothing.
    sigma_b = min(max(0.5, sigma_a / max(scale, 1e-6)), 8.0 * sigma_a)
    sigma_b = round(sigma_b * 50) / 50  # 2 % steps, so that nearby scales share a field
    fb = max(1, int(round(factor_a / max(scale, 1e-6)))) if factor_a > 1 else 1
    return sigma_b, fb


#: Key of ``cache``'s dict of a large map's planes, kept only while :func:`prepare_fields`
#: makes every level (they are not worth their memory afterwards).
_PASSING = "passing planes"


def _cached_planes(grid: OccupancyGrid, cache, which: str, factor: int):
    key = (which + " planes", factor)
    if grid.data.size > LARGE_CELLS:  # each level needs them once, but levels share them
        return _cached(cache.get(_PASSING) if cache is not None else None, key, lambda: _planes(grid, _whole(grid), factor))
    return _cached(cache, key, lambda: _planes(grid, _whole(grid), factor))


def _level_field(a: OccupancyGrid, cache, sigma: float, factor: int):
    """a's whole-map field of a level (cached)."""
    return _cached(cache, ("a", sigma, factor), lambda: _a_field(a, _whole(a), factor, sigma, planes=_cached_planes(a, cache, "a", factor)))


def _level_points(b: OccupancyGrid, cache, sigma: float, factor: int):
    """b's cells near structure at a level, and their field values (cached)."""
    return _cached(cache, ("b", sigma, factor), lambda: _b_points(b, _whole(b), factor, sigma, planes=_cached_planes(b, cache, "b", factor)))


#: Levenberg-Marquardt damping of a first try (next to the unit diagonal of the scaled
#: normal equations: nearly a plain Gauss-Newton step) and tries per step.
_LM_START = 1e-4
_LM_TRIES = 8


def _robust_cost(r: np.ndarray, keep: np.ndarray, huber: float, params: np.ndarray, prior) -> float:
    """The cost a refinement step must not raise: the Huber losses of the residuals
    ``r[keep]`` (what the weighted steps minimise), plus the scale prior's
    ``strength / 2 (s - s0)^2`` when ``prior = (strength, s0)``."""
    a = np.abs(r[keep])
    loss = np.where(a <= huber, 0.5 * a * a, huber * a - 0.5 * huber * huber)
    total = float(loss.sum())
    if prior is not None:
        total += 0.5 * prior[0] * (math.hypot(params[0, 0], params[1, 0]) - prior[1]) ** 2
    return total


#: Where :func:`refine_direct`'s cache keeps b's fields for ``reference="finer"``.
_FINER_CACHE = ("finer reference",)


def _b_is_the_field(a: OccupancyGrid, b: OccupancyGrid, reference: str) -> bool:
    """Whether ``reference`` (``"a"`` or ``"finer"``) makes b's field the last level's:
    b's cells smaller than a's, with ``"finer"``."""
    if reference not in ("a", "finer"):
        raise ValueError(f"unknown reference {reference!r} (use 'a' or 'finer')")
    return reference == "finer" and b.resolution < a.resolution * (1.0 - 1e-9)


def prepare_fields(a: OccupancyGrid, b: OccupancyGrid, cache: dict, *, scale: float = 1.0, sigmas=(3.0, 1.5, 1.0),
                   reference: str = "a") -> dict:
    """Fill ``cache`` with the fields :func:`refine_direct` will need (with the same
    ``cache``, ``sigmas`` and ``reference``) for transforms of about ``scale``, so that
    they can be computed ahead, e.g. in a thread while candidates are being found.
    Returns ``cache``."""
    if _b_is_the_field(a, b, reference):
        # The levels but the last as usual, the last with b's field (_refine_finer_last).
        prepare_fields(a, b, cache, scale=scale, sigmas=tuple(sigmas)[:-1])
        prepare_fields(b, a, cache.setdefault(_FINER_CACHE, {}), scale=1.0 / scale, sigmas=tuple(sigmas)[-1:])
        return cache
    if max(*a.shape, *b.shape) >= _REMAP_MAX:
        return cache
    sigmas = tuple(float(s) for s in sigmas)
    large = max(a.data.size, b.data.size) > LARGE_CELLS
    cache[_PASSING] = {}  # a large map's reduced planes, made once for all the levels
    try:
        for sigma_a, fa in zip(sigmas, _auto_factors(sigmas, large)):
            sigma_b, fb = _b_level(sigma_a, fa, scale)
            if fa == 1 and fb == 1 and large:
                _level_points(b, cache, sigma_b, 2)
            else:
                _level_field(a, cache, sigma_a, fa)
                _level_points(b, cache, sigma_b, fb)
    finally:
        del cache[_PASSING]
    return cache


def refine_direct(
    a: OccupancyGrid,
    b: OccupancyGrid,
    initial: SimilarityTransform,
    *,
    sigmas=(3.0, 1.5, 1.0),
    iterations: int = 10,
    max_points: int = 20000,
    max_shift: float = 12.0,
    cache: dict | None = None,
    factors=None,
    scale_prior: tuple[float, float] | None = None,
    reference: str = "a",
) -> tuple[SimilarityTransform, RefineReport]:
    """Refine ``initial`` (b pixels -> a pixels) against the cells of both maps.

    Parameters
    ----------
    a, b : OccupancyGrid
    initial : SimilarityTransform
        A transform already close to the truth (within about ``sigmas[0]`` pixels).
    sigmas : sequence of float
        Smoothing (in a's pixels) of each level, coarse to fine.
    iterations : int
        Gauss-Newton steps per level at most.
    max_points : int
        Cells of b used per level at most: beyond that, a subset evenly spread over
        them (about every k-th, row by row). No random draw: a transform's refinement
        does not depend on what was refined before it, and below
        :data:`LARGE_CELLS` every transform is fitted to the same cells.
    max_shift : float
        How far (a's pixels) b's corners may move. A refinement that would lead farther
        (whose last step was held back by this bound) is refused.
    cache : dict, optional
        Smoothed fields from earlier calls on the same two maps (pass the same dict to
        refine several candidates cheaply).
    factors : sequence of int, optional
        Resolution reduction of each level (in a's cells; b's is chosen to match at the
        transform's scale). Default: all 1 (full resolution), except on maps of more than
        :data:`LARGE_CELLS` cells: 2 for levels smoothed by at least :data:`COARSE_SIGMA`
        pixels.
    scale_prior : (float, float), optional
        ``(scale, strength)``: pull the scale towards ``scale`` (e.g. the maps' resolution
        ratio) with ``strength`` times the information the cells give on the scale.
    reference : {"a", "finer"}
        The map whose smoothed field the other map's cells are fitted to at the last
        level: ``"a"``, or ``"finer"``, the map of smaller cells (by the maps'
        ``resolution``; ``a`` when they are equal). The fit is not symmetric where the
        cells differ in size: a coarse map's field steps about half a coarse cell ahead of its
        walls, and the fine map's cells fitted to it place the walls, and so the scale,
        off by a fraction of a cell. Where b is the finer map, ``"finer"`` runs the
        levels but the last as usual (from a rough start the coarse field's wide steps
        draw the fine cells in more surely) and the last one the other way round, a's
        cells fitted to b's field smoothed by ``sigmas[-1]`` of b's cells, inverted;
        ``cache`` then also holds b's field (apart from a's), ``max_shift`` and the
        report's ``shift_px`` stay in a's pixels, and its RMS values are the last
        level's, from the other levels' result. On simulated pairs whose cells differ
        1.15-2 times, refined without the scale prior from the truth or from starts a few
        pixels off, the coarse field left the poses 0.56 and 0.85 px from the truth
        (medians), the finer one 0.31 and 0.48 px (docs/benchmarks.md, twenty-sixth
        session).

    Returns
    -------
    transform : SimilarityTransform
        The refined transform, or ``initial`` when refinement was not accepted.
    report : RefineReport
        ``rms_before`` and ``rms_after`` are measured at the last level.
    """
    if _b_is_the_field(a, b, reference):
        return _refine_finer_last(a, b, initial, sigmas=tuple(float(s) for s in sigmas), iterations=iterations,
                                  max_points=max_points, max_shift=max_shift, cache=cache, factors=factors,
                                  scale_prior=scale_prior)
    if max(*a.shape, *b.shape) >= _REMAP_MAX:
        # OpenCV's remap cannot sample images this long; keep the initial estimate.
        return initial, RefineReport(False, 0, 0, 0.0, math.nan, math.nan)
    sigmas = tuple(float(s) for s in sigmas)
    large = max(a.data.size, b.data.size) > LARGE_CELLS
    factors = _auto_factors(sigmas, large) if factors is None else tuple(max(1, int(f)) for f in factors)
    if len(factors) != len(sigmas):
        raise ValueError("factors and sigmas must have the same length")
    p = initial.params.copy()
    steps = 0
    npts = 0
    huber = 0.1
    pinned = False
    rms_before = rms_after = math.nan
    for level, (sigma_a, fa) in enumerate(zip(sigmas, factors)):
        last = level == len(sigmas) - 1
        sigma_b, fb = _b_level(sigma_a, fa, math.hypot(p[0, 0], p[1, 0]))
        b_box = _whole(b)
        if fa == 1 and fb == 1 and large:
            # Full resolution on a huge map: b's cells near structure, found at half
            # resolution, judged block by block from a pool the candidates share, and a's
            # field on the box they can reach only.
            cand = _level_points(b, cache, sigma_b, 2)
            pool = _cached(cache, ("b pool", sigma_b, 2), dict)
            xs, ys, target = _fine_points(a, b, p, cand[:2], 2, sigma_b, max_points, pool)
            if len(xs) < 20:
                continue  # nothing to fit at this smoothing: the next level may have
            q = np.stack([xs, ys], axis=1) @ p[:2, :2].T + p[:2, 2]
            a_box = _box_of(q, max_shift + 4.0 * sigma_a + 4.0, a.shape)
            field = _a_field(a, a_box, 1, sigma_a)
        else:
            # Whole-map fields (at full or reduced resolution), shared by every candidate.
            a_box = _whole(a)
            field = _level_field(a, cache, sigma_a, fa)
            xs, ys, target = _level_points(b, cache, sigma_b, fb)
            if len(xs) < 20:
                continue  # nothing to fit at this smoothing: the next level may have
            if len(xs) > max_points:
                pick = _evenly(len(xs), max_points)
                xs, ys, target = xs[pick], ys[pick], target[pick]
        pts = np.stack([xs, ys], axis=1).astype(np.float64)
        pts_x, pts_y = pts[:, 0].copy(), pts[:, 1].copy()
        npts = len(pts)
        # This level's pixels: reduced pixels of a's and b's boxes.
        to_a = np.linalg.inv(_scaling(fa, a_box[:2]))
        from_b = _scaling(fb, b_box[:2])
        shape_b = (b.shape[0] / fb, b.shape[1] / fb)

        def residuals(params):
            """``(gradients, r, valid)`` at the cells moved by ``params``: the field's
            ``(N, 2)`` gradients, the residuals and where a's smoothed known mask holds."""
            at = _sample(field, pts @ params[:2, :2].T + params[:2, 2])
            return at[:, 1:3], at[:, 0].astype(np.float64) - target, at[:, 3] > 0.9

        def robust_rms(r, valid):
            if not valid.any():
                return math.inf
            rv = np.abs(r[valid])
            return float(np.sqrt(np.mean(np.minimum(rv, 3 * huber) ** 2)))

        def to_level(m):
            return to_a @ m @ from_b

        def from_level(m):
            return np.linalg.inv(to_a) @ m @ np.linalg.inv(from_b)

        q_params = to_level(p)
        # The prior's scale in this level's (reduced) pixels.
        s_level = None if scale_prior is None else scale_prior[0] * math.hypot(*to_level(np.eye(3))[:2, 0])
        if last:
            _, r0, v0 = residuals(to_level(initial.params))
            rms_before = robust_rms(r0, v0)
        current = residuals(q_params)
        for _ in range(iterations):
            grad, r, valid = current
            if valid.sum() < 20:
                break
            g = grad[valid]
            gx, gy = g[:, 0].astype(np.float64), g[:, 1].astype(np.float64)
            rv = r[valid]
            px, py = pts_x[valid], pts_y[valid]
            # Parameters (sa, sb, tx, ty) of [[sa, -sb, tx], [sb, sa, ty]].
            j = np.stack([gx * px + gy * py, -gx * py + gy * px, gx, gy], axis=1)
            absr = np.abs(rv)
            w = np.where(absr <= huber, 1.0, huber / np.maximum(absr, 1e-12))
            # Column scaling keeps the normal equations well conditioned.
            norm = np.sqrt((j**2 * w[:, None]).sum(0)) + 1e-12
            jn = j / norm
            h = (jn.T * w) @ jn
            g = (jn.T * w) @ rv
            prior = None
            if s_level is not None:
                sa0, sb0 = q_params[0, 0], q_params[1, 0]
                s_now = math.hypot(sa0, sb0)
                jp = np.array([sa0 / s_now, sb0 / s_now, 0.0, 0.0])
                info = float(((j @ jp) ** 2 * w).sum())  # the cells' information on the scale
                jpn = jp / norm
                h = h + scale_prior[1] * info * np.outer(jpn, jpn)
                g = g + scale_prior[1] * info * jpn * (s_now - s_level)
                prior = (scale_prior[1] * info, s_level)
            # Levenberg-Marquardt: a Gauss-Newton step, damped until it lowers the robust
            # cost (an undamped step on a field far from the truth can run away).
            new = None
            lam = _LM_START
            pinned = False  # held back by max_shift: the refinement leads farther away
            for _try in range(_LM_TRIES):
                try:
                    delta = -np.linalg.solve(h + (lam + 1e-9) * np.eye(4), g) / norm
                except np.linalg.LinAlgError:
                    break
                sa, sb = q_params[0, 0] + delta[0], q_params[1, 0] + delta[1]
                trial = np.array([[sa, -sb, q_params[0, 2] + delta[2]], [sb, sa, q_params[1, 2] + delta[3]], [0.0, 0.0, 1.0]])
                # A step beyond what may be accepted in the end (the scale collapsing, all
                # cells landing on one spot of a, lowers the cost too) is too long.
                if _corner_shift(initial.params, from_level(trial), b.shape) > max_shift:
                    pinned = True
                    lam *= 8.0
                    continue
                tried = residuals(trial)
                both = valid & tried[2]  # compared on the cells both poses put on a's known area
                if _robust_cost(tried[1], both, huber, trial, prior) <= _robust_cost(r, both, huber, q_params, prior):
                    new, current = trial, tried  # the next step starts from these residuals
                    break
                lam *= 8.0
            if new is None:
                break
            steps += 1
            moved = _corner_shift(q_params, new, shape_b)
            q_params = new
            if moved < 1e-3:
                break
        p = from_level(q_params)
        if last:
            rms_after = robust_rms(current[1], current[2])  # ``current``: at ``q_params``
    shift = _corner_shift(initial.params, p, b.shape)
    accepted = bool(
        np.isfinite(p).all()
        and shift <= max_shift
        and not pinned
        and math.isfinite(rms_after)
        and (not math.isfinite(rms_before) or rms_after <= rms_before + 1e-9)
    )
    report = RefineReport(accepted, steps, npts, shift, rms_before, rms_after)
    if not accepted:
        return initial, report
    # Exactly a similarity again (the level changes of frame add rounding).
    sa, sb = (p[0, 0] + p[1, 1]) / 2.0, (p[1, 0] - p[0, 1]) / 2.0
    p = np.array([[sa, -sb, p[0, 2]], [sb, sa, p[1, 2]], [0.0, 0.0, 1.0]])
    return SimilarityTransform(p), report


def _refine_finer_last(a, b, initial, *, sigmas, iterations, max_points, max_shift, cache, factors, scale_prior):
    """:func:`refine_direct` with ``reference="finer"`` where b's cells are smaller than
    a's: the levels but the last fit b's cells to a's field, as usual (from a rough
    start, the coarse field's wide steps draw the fine cells in more surely than the
    other way round); the last level fits a's cells to b's field, smoothed by
    ``sigmas[-1]`` of b's cells, and is inverted."""
    px = a.resolution / b.resolution  # b's pixels per a's pixel
    first, r1 = initial, None
    if len(sigmas) > 1:
        first, r1 = refine_direct(a, b, initial, sigmas=sigmas[:-1], iterations=iterations, max_points=max_points,
                                  max_shift=max_shift, cache=cache, scale_prior=scale_prior,
                                  factors=None if factors is None else tuple(factors)[:-1])
    inner = None if cache is None else cache.setdefault(_FINER_CACHE, {})
    swapped, r2 = refine_direct(b, a, SimilarityTransform(first.params).inverse, sigmas=sigmas[-1:], iterations=iterations,
                                max_points=max_points, max_shift=max_shift * px, cache=inner,
                                factors=None if factors is None else tuple(factors)[-1:],
                                scale_prior=None if scale_prior is None else (1.0 / scale_prior[0], scale_prior[1]))
    out = swapped.inverse if r2.accepted else first
    shift = _corner_shift(initial.params, out.params, b.shape)
    if shift > max_shift:  # the last level led too far: the coarse levels' result stands
        out = first
        shift = _corner_shift(initial.params, out.params, b.shape)
    accepted = out is not initial and bool(r2.accepted or (r1 is not None and r1.accepted))
    steps = r2.iterations + (0 if r1 is None else r1.iterations)
    report = RefineReport(accepted, steps, r2.points, shift, r2.rms_before, r2.rms_after)
    return (out if accepted else initial), report


class WallICP:
    """Iterative closest point on the walls of two maps: the last, precise step of a pose.

    :func:`refine_direct` matches smoothed occupancy, whose optimum on noisy maps with
    thin walls (spurious and missed hits, a resolution change) can lie a few pixels from
    where the walls themselves coincide; at 2-3 px off, walls 1-2 cells thick no longer
    agree. ICP pairs each wall cell of one map with the nearest wall cell of the other
    (both ways, within a radius that shrinks to the verification's tolerance) and fits a
    similarity to the pairs, so it converges where walls lie on walls.

    With ``facing`` (the default), a wall cell knows which way it faces: towards the
    free cells the robot saw it from (the gradient of the map's free cells, blurred by
    :data:`FACING_SIGMA`), or nowhere in particular when free space lies on both sides
    or none (a thin wall seen from both rooms, a lone hit). Two cells pair only when
    they do not face opposite ways: a wall seen from the corridor in one map is not the
    wall of the next room seen from inside in the other, however near it lies. And each
    step fits the pairs point to plane (the distance along the target cell's facing
    direction; both axes for pairs that face nowhere), so that pairs slide along a wall
    instead of pulling the pose towards where the wall cells happen to be sampled (their
    distance along the wall counts a tenth): a pose 2-3 px off along a wall that
    point-to-point pairs held there reaches the truth. A step that the pairs do not
    determine ends the polish with the pose as it was. ``facing=False`` is plain
    point-to-point ICP.

    The nearest wall cell of every cell of both maps is found once (a distance transform
    with labels, kept as 2-byte offsets within :data:`WALL_ICP_REACH`), and so are the
    blurred free cells (1 byte per cell), so polishing many poses of one pair costs little.

    Parameters
    ----------
    a, b : OccupancyGrid
    radii : sequence of float
        Pairing radius (a's pixels) of each round, large to small.
    max_points : int
        Wall cells used per map at most (an even stride).
    facing : bool
        Pair only cells that do not face opposite ways, and fit point to plane.

    Examples
    --------
    >>> from gridmerge import samples
    >>> from gridmerge.transforms import SimilarityTransform, corner_error
    >>> a, b, truth = samples.robot_pair(0, scale=1.0, rotation_deg=40)
    >>> start = SimilarityTransform(translation=(3, -2)) @ SimilarityTransform(truth)
    >>> polished = WallICP(a, b).polish(start)
    >>> corner_error(polished, truth, b.shape) < 1.0
    True
    """

    def __init__(self, a: OccupancyGrid, b: OccupancyGrid, *, radii=(4.0, 3.0, 2.0, 2.0), max_points: int = 20000,
                 facing: bool = True):
        self.radii = tuple(float(r) for r in radii)
        self.facing = bool(facing)
        self._maps = []
        for g in (a, b):
            walls = g.occupied()
            if not walls.any():
                self._maps.append(None)
                continue
            cells = _strided_cells(walls, max_points)
            free = _blurred_free(g) if self.facing else None
            self._maps.append((_nearest_walls(walls, WALL_ICP_REACH), cells, free, None if free is None else _facing(free, cells)))

    def swapped(self) -> "WallICP":
        """The same ICP with the maps' roles swapped (``WallICP(b, a)``), sharing their
        nearest-wall tables."""
        other = copy.copy(self)
        other._maps = self._maps[::-1]
        return other

    def thinned(self, max_points: int) -> WallICP:
        """The same ICP on at most ``max_points`` wall cells of each map (an even spread of
        its own), sharing the nearest-wall tables: cheaper polishes of many candidates."""
        maps = []
        for entry in self._maps:
            if entry is None or len(entry[1]) <= max_points:
                maps.append(entry)
                continue
            nearest, cells, free, facing = entry
            keep = _evenly(len(cells), int(max_points))
            maps.append((nearest, cells[keep], free, None if facing is None else facing[keep]))
        if all(x is y for x, y in zip(maps, self._maps)):
            return self
        other = copy.copy(self)
        other._maps = maps
        return other

    def _pairs(self, which: int, points: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
        """``(keep, nearest)``: which ``points`` (pixels of map ``which``) lie within
        ``radius`` of one of its walls, and that wall cell."""
        offsets = self._maps[which][0]
        h, w = offsets.shape[:2]
        p = np.rint(points).astype(np.int64)
        keep = (p[:, 0] >= 0) & (p[:, 0] < w) & (p[:, 1] >= 0) & (p[:, 1] < h)
        o = offsets[p[keep, 1], p[keep, 0]].astype(np.int64)
        found = o[:, 0] != _NO_WALL
        near = np.zeros(len(o), bool)
        near[found] = _chamfer_norms()[np.abs(o[found, 1]), np.abs(o[found, 0])] <= radius
        out = np.zeros_like(points)
        idx = np.flatnonzero(keep)[near]
        out[idx] = p[idx] + o[near]
        keep[keep] = near
        return keep, out

    def polish(self, t: SimilarityTransform, *, rounds: int = 3, min_pairs: int = 20, keep_scale: bool = True) -> SimilarityTransform:
        """``t`` (b pixels -> a pixels) moved to where the walls coincide; ``t`` itself
        when either map has no walls, too few walls pair up, or (``facing``) a step is
        not determined by its pairs."""
        if self._maps[0] is None or self._maps[1] is None:
            return t
        pa, pb = self._maps[0][1], self._maps[1][1]
        m = np.asarray(t.params, dtype=float)
        scale = math.sqrt(abs(float(np.linalg.det(m[:2, :2])))) or 1.0
        for radius in self.radii:
            for _ in range(rounds):
                inv = np.linalg.inv(m)
                k1, q1 = self._pairs(0, pb @ m[:2, :2].T + m[:2, 2], radius)
                k2, q2 = self._pairs(1, pa @ inv[:2, :2].T + inv[:2, 2], radius * math.sqrt(abs(float(np.linalg.det(inv[:2, :2])))))
                if self.facing:
                    src, dst, normals = self._faced(m, (k1, q1), (k2, q2))
                    if len(src) < min_pairs:
                        return t
                    m = _plane_step(m, src, dst, normals, keep_scale=keep_scale)
                    if m is None:
                        return t
                    continue
                src = np.vstack([pb[k1], q2[k2]])
                dst = np.vstack([q1[k1], pa[k2]])
                if len(src) < min_pairs:
                    return t
                fit = SimilarityTransform.from_estimate(src, dst)
                if not fit:
                    return t
                m = np.asarray(fit.params, dtype=float)
                if keep_scale:
                    # The best rotation at a fixed scale is the free fit's; the
                    # translation then maps the centroids onto each other.
                    r = m[:2, :2] * (scale / math.hypot(m[0, 0], m[1, 0]))
                    m = np.array([[r[0, 0], r[0, 1], 0.0], [r[1, 0], r[1, 1], 0.0], [0.0, 0.0, 1.0]])
                    m[:2, 2] = dst.mean(axis=0) - r @ src.mean(axis=0)
        return SimilarityTransform(m)

    def _faced(self, m: np.ndarray, forward, backward):
        """The pairs of one round whose cells do not face opposite ways: ``(src, dst,
        normals)``, b's pixels, a's pixels and the direction (a's frame) along which each
        pair's distance counts: the target wall cell's facing (a's cell for b's cells
        sent into a; b's cell, turned into a, for a's cells sent into b), the other
        cell's when the target faces nowhere, zero when neither faces anywhere."""
        (k1, q1), (k2, q2) = forward, backward
        _, pa, free_a, na_cells = self._maps[0]
        _, pb, free_b, nb_cells = self._maps[1]
        turn = m[:2, :2] / (math.sqrt(abs(float(np.linalg.det(m[:2, :2])))) or 1.0)
        # b's cells sent into a, paired with a's nearest walls (the targets).
        tgt1 = _facing(free_a, q1[k1])
        own1 = nb_cells[k1] @ turn.T
        # a's cells sent into b, paired with b's nearest walls (the targets).
        tgt2 = _facing(free_b, q2[k2]) @ turn.T
        own2 = na_cells[k2]
        tgt = np.vstack([tgt1, tgt2])
        own = np.vstack([own1, own2])
        same = _same_face(tgt, own)
        normals = np.where((np.abs(tgt).sum(1) > 0)[:, None], tgt, own)[same]
        src = np.vstack([pb[k1], q2[k2]])[same]
        dst = np.vstack([q1[k1], pa[k2]])[same]
        return src, dst, normals


#: Blur (cells) of a map's free cells whose gradient tells which way a wall cell faces.
FACING_SIGMA = 1.5
#: Least gradient (of free cells blurred to 0..255, across two cells) for a wall cell to
#: face somewhere; a step from unknown or wall to free gives about 130.
_FACING_MIN = 24


def _blurred_free(grid: OccupancyGrid) -> np.ndarray:
    """``(H, W)`` uint8: the map's free cells (255) blurred by :data:`FACING_SIGMA`."""
    free = grid.free().astype(np.uint8) * np.uint8(255)
    return cv2.GaussianBlur(free, (0, 0), FACING_SIGMA)


def _facing(free: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """``(N, 2)`` unit ``(x, y)`` directions in which the ``(N, 2)`` integer cells face
    (up the gradient of the blurred free cells ``free``), zero where that gradient is
    below :data:`_FACING_MIN` (free on both sides, or on neither)."""
    h, w = free.shape
    c = np.rint(cells).astype(np.int64).reshape(-1, 2)
    x, y = c[:, 0], c[:, 1]
    xl, xr = np.clip(x - 1, 0, w - 1), np.clip(x + 1, 0, w - 1)
    yu, yd = np.clip(y - 1, 0, h - 1), np.clip(y + 1, 0, h - 1)
    g = np.stack([free[y, xr].astype(np.float64) - free[y, xl], free[yd, x].astype(np.float64) - free[yu, x]], axis=1)
    norm = np.hypot(g[:, 0], g[:, 1])
    out = np.zeros_like(g)
    strong = norm >= _FACING_MIN
    out[strong] = g[strong] / norm[strong, None]
    return out


def _same_face(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Which rows of the ``(N, 2)`` directions ``u`` and ``v`` do not point opposite ways
    (a zero direction agrees with any)."""
    return (u * v).sum(axis=1) >= 0.0


def _plane_step(m: np.ndarray, src: np.ndarray, dst: np.ndarray, normals: np.ndarray, *, keep_scale: bool = True):
    """``m`` (``(3, 3)``, b -> a pixels) after one point-to-plane step on the pairs
    ``src`` (b) -> ``dst`` (a), each counting its distance along its ``(N, 2)`` normal
    (a's frame) and, weighed by :data:`_TANGENT_WEIGHT`, along the wall; a zero normal
    counts both axes fully. ``None`` when the pairs do not determine the step (all at
    one spot).

    The step is a similarity about the centroid of the moved points, linearised in its
    rotation (and scale, unless ``keep_scale``), solved by least squares, then applied
    exactly. The small weight along the walls keeps a step that the normals alone hold
    weakly (walls seen facing two or three ways only, in a small part of the maps) from
    sliding: on the 96 simulated positives of seeds 0-1, polished from the truth and
    from 2.5 px off, normals alone left 3.1 % of the poses more than 2 px off (one
    47 px), with a tenth along the walls 2.1 % (none beyond 7 px), point to point 8.0 %;
    on seeds 2-3 the tenth changed nothing that far off (4.5 %; point to point 10.1 %)."""
    p = src @ m[:2, :2].T + m[:2, 2]
    e = dst - p
    centre = p.mean(axis=0)
    d = p - centre
    nx, ny = normals[:, 0], normals[:, 1]
    faced = (nx != 0) | (ny != 0)
    # Each pair weighs its 2-d distance by W = a I + b n n^T: a tenth along the wall plus
    # all of it across (a = 0.1, b = 0.9, n unit), or both axes alike (a = 1, b = 0). With
    # J the pair's motion per parameter (rotation: d turned a quarter; x; y; scale: d),
    # the normal equations sum a J^T J + b (J^T n)(J^T n)^T and a J^T e + b (J^T n)(n . e).
    a = np.where(faced, _TANGENT_WEIGHT, 1.0)
    b = np.where(faced, 1.0 - _TANGENT_WEIGHT, 0.0)
    dx, dy = d[:, 0], d[:, 1]
    one, zero = np.ones_like(dx), np.zeros_like(dx)
    cols = [np.stack([-dy, dx]), np.stack([one, zero]), np.stack([zero, one])]  # (2, N) each
    if not keep_scale:
        cols.append(np.stack([dx, dy]))
    jn = np.stack([c[0] * nx + c[1] * ny for c in cols])  # (k, N): J^T n
    k = len(cols)
    h = np.empty((k, k))
    for i in range(k):
        for j in range(i, k):
            h[i, j] = h[j, i] = (a * (cols[i] * cols[j]).sum(axis=0) + b * jn[i] * jn[j]).sum()
    ne = nx * e[:, 0] + ny * e[:, 1]
    g = np.array([(a * (c[0] * e[:, 0] + c[1] * e[:, 1]) + b * jn[i] * ne).sum() for i, c in enumerate(cols)])
    diag = np.diag(h)
    if not (diag > 1e-18).all():
        return None
    norm = np.sqrt(diag)
    hn = h / np.outer(norm, norm)
    eig = np.linalg.eigvalsh(hn)
    if eig[0] < 1e-9 * eig[-1]:
        return None
    x = np.linalg.solve(hn, g / norm) / norm
    theta, tx, ty = x[0], x[1], x[2]
    grow = 1.0 + (x[3] if not keep_scale else 0.0)
    c, s = math.cos(theta) * grow, math.sin(theta) * grow
    step = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    step[:2, 2] = centre + np.array([tx, ty]) - step[:2, :2] @ centre
    return step @ m


#: Weight (squared distances) of a facing pair's distance along its wall in
#: :func:`_plane_step`, against 1 across it.
_TANGENT_WEIGHT = 0.1


#: How far (pixels) :class:`WallICP` looks for a map's nearest wall: its pairing radii in
#: b's pixels at scales down to 1/8.
WALL_ICP_REACH = 32
_NO_WALL = -128
#: OpenCV's 5 x 5 chamfer mask for ``DIST_L2``: steps (1, 0), (1, 1) and (2, 1).
_CHAMFER_STEPS = ((1, 0, 1.0), (1, 1, 1.4), (2, 1, 2.1969))


@functools.cache
def _chamfer_norms() -> np.ndarray:
    """``[|dy|, |dx|]`` -> the distance ``cv2.distanceTransform`` (``DIST_L2``, mask 5)
    gives between two cells that far apart, for offsets up to :data:`WALL_ICP_REACH`: the
    cheapest path of the mask's steps (float32 sums, as OpenCV's). Made once, when first
    needed."""
    n = WALL_ICP_REACH + 1
    cost = np.full((n, n), np.inf, np.float32)
    cost[0, 0] = 0.0
    steps = [(dy, dx, np.float32(c)) for a, b, c in _CHAMFER_STEPS for dy, dx in {(a, b), (b, a)}]
    # Every step moves away from the origin (dx + dy grows), so one pass in order of
    # dx + dy finds each cheapest path.
    for total in range(1, 2 * n - 1):
        for y in range(max(0, total - n + 1), min(n, total + 1)):
            x = total - y
            best = np.float32(np.inf)
            for dy, dx, c in steps:
                if y - dy >= 0 and x - dx >= 0:
                    best = min(best, np.float32(cost[y - dy, x - dx] + c))
            cost[y, x] = best
    cost.flags.writeable = False  # shared by every caller
    return cost


#: Distance (a's pixels) from a wall beyond which a wall cell no longer pulls
#: :func:`chamfer_polish`'s pose, and the Huber threshold of its cost.
CHAMFER_REACH = 3.0
CHAMFER_HUBER = 0.5


def _bilinear(field: np.ndarray, xy: np.ndarray, outside: float) -> np.ndarray:
    """``field`` at the ``(N, 2)`` float points ``(x, y)``, bilinear; ``outside`` where a
    point's four cells are not all in the field. Exact fractions, unlike :func:`_sample`
    (``cv2.remap`` rounds them to 1/32 of a cell): a Gauss-Newton polish to a fraction of a
    cell compares costs that differ by less."""
    out = np.full(len(xy), float(outside))
    if not len(xy):
        return out
    h, w = field.shape
    x0 = np.floor(xy[:, 0])
    y0 = np.floor(xy[:, 1])
    ok = (x0 >= 0) & (y0 >= 0) & (x0 + 1 < w) & (y0 + 1 < h)
    fx, fy = xy[ok, 0] - x0[ok], xy[ok, 1] - y0[ok]
    xi, yi = x0[ok].astype(np.intp), y0[ok].astype(np.intp)
    out[ok] = ((field[yi, xi] * (1 - fx) + field[yi, xi + 1] * fx) * (1 - fy)
               + (field[yi + 1, xi] * (1 - fx) + field[yi + 1, xi + 1] * fx) * fy)
    return out


def _wall_field(walls: np.ndarray, points: np.ndarray, margin: float):
    """``(field, gx, gy, corner)``: the distance (cells) to the nearest of ``walls``, and
    its gradient, on the box of ``walls``'s cells that ``points`` (``(N, 2)`` float
    ``(x, y)``) reach grown by ``margin``; ``corner`` is the box's ``(x, y)`` in the map.
    Walls beyond the box are not seen: the box's margin must exceed the distances that
    count."""
    x0, y0, x1, y1 = _box_of(points, math.ceil(margin), walls.shape)
    box = walls[y0:y1, x0:x1]
    if not box.any():
        return None
    field = cv2.distanceTransform((~box).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    gx = cv2.Sobel(field, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(field, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    return field, gx, gy, np.array([x0, y0], dtype=float)


def chamfer_polish(a: OccupancyGrid, b: OccupancyGrid, t: SimilarityTransform, *, reach: float = CHAMFER_REACH,
                   huber: float = CHAMFER_HUBER, iterations: int = 30, max_points: int = 20000,
                   min_cells: int = 10) -> SimilarityTransform:
    """``t`` (b pixels -> a pixels) moved, at its scale, to where the two maps' walls lie
    nearest each other to a fraction of a cell: the least (Huber) sum of the distances
    from each map's wall cells to the other's nearest wall, bilinear on the distance
    transforms.

    Every wall cell of b that ``t`` puts on a's known cells counts its distance to a's
    walls, and every wall cell of a that ``t`` puts on b's known cells its distance (in a's
    pixels) to b's walls, the two sides weighing alike; cells more than ``reach`` cells
    from the other map's walls do not count. Gauss-Newton steps on the turn and shift,
    each halved until the cost falls, stop when it no longer does.

    :class:`WallICP` pairs each wall cell with the nearest wall *cell*, whose grid the
    pose then snaps towards; a distance field varies smoothly between cells, so the
    optimum lies where walls coincide rather than where their cells do.

    Parameters
    ----------
    a, b : OccupancyGrid
    t : SimilarityTransform
        The start, b's pixels to a's; its scale is kept.
    reach, huber : float
        Distances (a's cells) beyond which a wall cell no longer counts, and from which
        it counts linearly.
    iterations : int
        Gauss-Newton steps at most.
    max_points : int
        Wall cells of each map at most (an even stride).
    min_cells : int
        Wall cells of each map that must count; fewer leave ``t`` as it is.

    Returns
    -------
    SimilarityTransform
        The polished pose; ``t`` itself when either map has too few walls in the overlap
        or no step lowers the cost.

    Examples
    --------
    >>> from gridmerge import samples
    >>> from gridmerge.transforms import SimilarityTransform, corner_error
    >>> a, b, truth = samples.robot_pair(0, scale=1.0, rotation_deg=40)
    >>> start = SimilarityTransform(translation=(1.5, -1)) @ SimilarityTransform(truth)
    >>> polished = chamfer_polish(a, b, start)
    >>> corner_error(polished, truth, b.shape) < 0.5
    True
    """
    m = np.asarray(t.params, dtype=float)
    scale = math.sqrt(abs(float(np.linalg.det(m[:2, :2])))) or 1.0
    walls_a, walls_b = a.occupied(), b.occupied()
    pa, pb = _strided_cells(walls_a, max_points), _strided_cells(walls_b, max_points)
    if len(pa) < min_cells or len(pb) < min_cells:
        return t

    inv = np.linalg.inv(m)
    sent_b = pb @ m[:2, :2].T + m[:2, 2]
    sent_a = pa @ inv[:2, :2].T + inv[:2, 2]
    on_b, on_a = _on_known(a, sent_b), _on_known(b, sent_a)
    pb, pa = pb[on_b], pa[on_a]  # b's walls on a's known cells, a's walls on b's
    if len(pa) < min_cells or len(pb) < min_cells:
        return t
    # The pose moves a few cells at most: fields on the boxes the cells reach, grown.
    margin = reach + 8.0
    fa = _wall_field(walls_a, sent_b[on_b], margin)
    fb = _wall_field(walls_b, sent_a[on_a], margin / scale)
    if fa is None or fb is None:
        return t
    far = 1e6
    wa, wb = 1.0 / len(pb), 1.0 / len(pa)

    def pose(p: np.ndarray) -> np.ndarray:
        c, s = scale * math.cos(p[0]), scale * math.sin(p[0])
        return np.array([[c, -s, p[1]], [s, c, p[2]], [0.0, 0.0, 1.0]])

    def residuals(p: np.ndarray):
        mm = pose(p)
        q = pb @ mm[:2, :2].T + mm[:2, 2] - fa[3]  # b's walls in a's box
        r1 = _bilinear(fa[0], q, far)
        mi = np.linalg.inv(mm)
        u = pa @ mi[:2, :2].T + mi[:2, 2] - fb[3]  # a's walls in b's box
        r2 = _bilinear(fb[0], u, far) * scale
        return q, r1, u, r2

    def cost(r1: np.ndarray, r2: np.ndarray) -> float:
        def side(r):
            r = np.minimum(np.abs(r), reach)
            return float(np.where(r <= huber, 0.5 * r * r, huber * (r - 0.5 * huber)).mean())
        return side(r1) + side(r2)

    p = np.array([math.atan2(m[1, 0], m[0, 0]), m[0, 2], m[1, 2]])
    q, r1, u, r2 = residuals(p)
    now = cost(r1, r2)
    moved = False
    for _ in range(iterations):
        th = p[0]
        c, s = scale * math.cos(th), scale * math.sin(th)
        # b's cells sent into a: d(q)/d(turn) = scale R'(turn) x.
        g1x, g1y = _bilinear(fa[1], q, 0.0), _bilinear(fa[2], q, 0.0)
        dqx, dqy = -s * pb[:, 0] - c * pb[:, 1], c * pb[:, 0] - s * pb[:, 1]
        j1 = np.column_stack([g1x * dqx + g1y * dqy, g1x, g1y])
        # a's cells sent into b: u = R(-turn) (x - shift) / scale.
        g2x, g2y = _bilinear(fb[1], u, 0.0) * scale, _bilinear(fb[2], u, 0.0) * scale
        ct, st = math.cos(th), math.sin(th)
        dx, dy = pa[:, 0] - p[1], pa[:, 1] - p[2]
        j2 = np.column_stack([g2x * (-st * dx + ct * dy) / scale + g2y * (-ct * dx - st * dy) / scale,
                              g2x * (-ct / scale) + g2y * (st / scale),
                              g2x * (-st / scale) + g2y * (-ct / scale)])
        r = np.concatenate([r1, r2])
        jac = np.vstack([j1, j2])
        ar = np.abs(r)
        weight = (np.concatenate([np.full(len(r1), wa), np.full(len(r2), wb)])
                  * np.where(ar <= huber, 1.0, huber / np.maximum(ar, 1e-12)) * (ar < reach))
        hess = (jac * weight[:, None]).T @ jac + np.diag([1e-2 * scale * scale, 1e-6, 1e-6])
        try:
            step = -np.linalg.solve(hess, (jac * weight[:, None]).T @ r)
        except np.linalg.LinAlgError:
            break
        for _halving in range(6):
            trial = residuals(p + step)
            after = cost(trial[1], trial[3])
            if after < now:
                break
            step = step / 2.0
        else:
            break
        p = p + step
        q, r1, u, r2 = trial
        now = after
        moved = True
        if abs(step[0]) < 1e-6 and abs(step[1]) < 1e-3 and abs(step[2]) < 1e-3:
            break
    return SimilarityTransform(pose(p)) if moved else t


def wall_search(a: OccupancyGrid, b: OccupancyGrid, t: SimilarityTransform, *, degrees: float = 2.0,
                step_deg: float = 0.25, reach: int = 20, tolerance: float = 2.0, max_points: int = 1500,
                keep: int = 6, scales=(1.0,)) -> list[SimilarityTransform]:
    """Poses near ``t`` (b pixels -> a pixels) where b's walls land on a's: the start of
    :meth:`WallICP.polish` when ``t`` lies beyond its reach of the truth.

    ICP pairs each wall cell with the nearest one of the other map, a few pixels away at
    most; from a pose 10-20 px or a degree off, on walls that run in two directions, it
    stays where it started. This search turns b's wall cells that ``t`` puts on a's known
    cells (an evenly spread ``max_points`` of them) about their centroid by every angle
    within ``degrees`` (steps of ``step_deg``) and, for each, shifts them by every whole
    pixel within ``reach`` in x and y, counting the cells that land within ``tolerance``
    of one of a's walls. Nothing is drawn at random.

    Parameters
    ----------
    a, b : OccupancyGrid
    t : SimilarityTransform
        The pose to search around (b pixels -> a pixels); its scale is kept.
    degrees, step_deg : float
        Largest turn either way, and the step between turns.
    reach : int
        Largest shift along each axis, a's pixels.
    tolerance : float
        Distance (a's pixels) within which a moved wall cell counts as on a wall.
    max_points : int
        b's wall cells moved at most.
    keep : int
        Poses returned at most.
    scales : sequence of float
        Factors of ``t``'s scale to search at (about the same centroid), each with every
        turn and shift.

    Returns
    -------
    list of SimilarityTransform
        Up to ``keep`` poses, the most wall cells landed first (the three best shifts of
        each turn; a pose within 0.6 degrees and 3 px of a better one is left out).
        Empty when fewer than 10 of b's wall cells land on a's known cells.

    Examples
    --------
    >>> from gridmerge import samples
    >>> from gridmerge.transforms import SimilarityTransform, corner_error
    >>> a, b, truth = samples.robot_pair(0, scale=1.0, rotation_deg=40)
    >>> start = SimilarityTransform(rotation=0.02, translation=(12, -9)) @ SimilarityTransform(truth)
    >>> best = wall_search(a, b, start)[0]
    >>> corner_error(best, truth, b.shape) < 3.0
    True
    """
    m = np.asarray(t.params, dtype=float)
    a_walls = a.occupied()
    pts = _strided_cells(b.occupied(), 1 << 40)
    if len(pts) == 0 or not a_walls.any():
        return []
    moved = pts @ m[:2, :2].T + m[:2, 2]
    moved = moved[_on_known(a, moved)]
    if len(moved) < 10:
        return []
    moved = moved[_evenly(len(moved), max_points)] if len(moved) > max_points else moved
    centre = moved.mean(axis=0)
    # The box of a that the turned and shifted cells can reach (and the walls within
    # tolerance of it): a's cells within tolerance of a wall there, padded so that every
    # cell has a place to land, as one flat byte array looked up by index.
    stretch = max(abs(float(f) - 1.0) for f in scales)
    swing = float(np.abs(moved - centre).max()) * (math.radians(abs(degrees)) + stretch) * 1.5 + 2.0
    grow = math.ceil(reach + swing + tolerance) + 1
    x0, y0, x1, y1 = _box_of(moved, grow, a.shape)
    near = cv2.distanceTransform((~a_walls[y0:y1, x0:x1]).astype(np.uint8), cv2.DIST_L2, 3) <= tolerance
    pad = int(reach) + 2
    hb, wb = near.shape
    wp = wb + 2 * pad
    flat = np.zeros((hb + 2 * pad, wp), np.uint8)
    flat[pad : pad + hb, pad : pad + wb] = near
    flat = flat.ravel()
    moved -= (x0, y0)
    centre = centre - (x0, y0)
    h, w = hb, wb
    d = np.arange(-int(reach), int(reach) + 1)
    offsets = (d[:, None] * wp + d[None, :]).ravel()  # row-major: (dy, dx)
    found = []
    turns = np.arange(-degrees, degrees + step_deg / 2, step_deg)
    for factor, deg in [(float(f), float(e)) for f in scales for e in turns]:
        rot = SimilarityTransform(rotation=math.radians(deg), scale=factor).params[:2, :2]
        p = np.rint((moved - centre) @ rot.T + centre).astype(np.int64)
        inside = (p[:, 0] >= -2) & (p[:, 0] < w + 2) & (p[:, 1] >= -2) & (p[:, 1] < h + 2)
        base = (p[inside, 1] + pad) * wp + p[inside, 0] + pad
        counts = flat.take(base[None, :] + offsets[:, None]).sum(axis=1, dtype=np.int64)
        for k in np.argsort(-counts, kind="stable")[:3]:
            dy, dx = divmod(int(k), len(d))
            found.append((-int(counts[k]), factor, deg, int(d[dx]), int(d[dy])))
    found.sort()
    picked = []
    for _, factor, deg, dx, dy in found:
        if any(f == factor and abs(deg - e) < 0.6 and abs(dx - x) <= 3 and abs(dy - y) <= 3 for f, e, x, y in picked):
            continue
        picked.append((factor, deg, dx, dy))
        if len(picked) >= keep:
            break
    out = []
    for factor, deg, dx, dy in picked:
        turn = SimilarityTransform(rotation=math.radians(deg), scale=factor).params
        step = np.eye(3)
        step[:2, :2] = turn[:2, :2]
        step[:2, 2] = centre + (dx, dy) - turn[:2, :2] @ centre
        step[:2, 2] += (x0, y0) - step[:2, :2] @ (x0, y0)  # back from the box to a's pixels
        out.append(SimilarityTransform(step @ m))
    return out


def _nearest_walls(walls: np.ndarray, reach: int, rows: int | None = None) -> np.ndarray:
    """``(H, W, 2)`` int8 ``(dx, dy)`` from each cell to its nearest wall cell (by a
    distance transform with labels), ``_NO_WALL`` where none lies within ``reach``.

    Two bytes per cell, computed in blocks of rows with ``reach`` rows of margin: the
    transform's float distance and integer label per cell, for a whole 4000 x 4000 map,
    were 128 MB per map."""
    h, w = walls.shape
    out = np.full((h, w, 2), _NO_WALL, np.int8)
    rows = max(1, (1 << 21) // max(1, w)) if rows is None else int(rows)
    cols = np.arange(w)[None, :]
    for y0 in range(0, h, rows):
        y1 = min(h, y0 + rows)
        ya, yb = max(0, y0 - reach), min(h, y1 + reach)
        sub = walls[ya:yb]
        ys, xs = np.nonzero(sub)
        if len(xs) == 0:
            continue
        dist, labels = cv2.distanceTransformWithLabels((~sub).astype(np.uint8), cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
        nx = np.zeros(int(labels.max()) + 1, np.int64)
        ny = np.zeros_like(nx)
        nx[labels[ys, xs]] = xs
        ny[labels[ys, xs]] = ys
        lab = labels[y0 - ya : y1 - ya]
        dx = nx[lab] - cols
        dy = ny[lab] - np.arange(y0 - ya, y1 - ya)[:, None]
        ok = (dist[y0 - ya : y1 - ya] <= reach) & (np.abs(dx) <= reach) & (np.abs(dy) <= reach)
        out[y0:y1, :, 0] = np.where(ok, dx, _NO_WALL)
        out[y0:y1, :, 1] = np.where(ok, dy, 0)
    return out


"""Sub-pixel refinement of a similarity transform against the maps themselves.

Keypoint positions are only as precise as the detector; the cells of the two maps hold
far more evidence. :func:`refine_direct` minimises, by Gauss-Newton with Huber weights,
the difference between smoothed occupancy fields of the two maps over the cells both
know, coarse to fine (the smoothing shrinks from ``sigmas[0]`` to ``sigmas[-1]``). Only
cells near structure (where the smoothed field has a gradient) take part, so the vast
free areas of a map cost nothing.

The smoothed field is a normalised convolution, ``G * (p k) / G * k`` with ``k`` the known
mask, so unknown cells never pull walls towards them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from .grid import OccupancyGrid
from .transforms import SimilarityTransform

__all__ = ["refine_direct", "RefineReport"]


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


def _field(grid: OccupancyGrid, sigma: float):
    known = grid.known.astype(np.float32)
    vals = np.nan_to_num(grid.data, nan=0.0).astype(np.float32) * known
    sk = cv2.GaussianBlur(known, (0, 0), sigma)
    sv = cv2.GaussianBlur(vals, (0, 0), sigma)
    with np.errstate(invalid="ignore", divide="ignore"):
        f = np.where(sk > 1e-3, sv / np.maximum(sk, 1e-6), 0.0).astype(np.float32)
    gx = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 8.0)
    gy = cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / 8.0)
    return f, gx, gy, sk


_REMAP_MAX = 32767


def _cached(cache: dict | None, key, compute):
    if cache is None:
        return compute()
    if key not in cache:
        cache[key] = compute()
    return cache[key]


def _sample(img: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear values of ``img`` at ``(N, 2)`` points (0 outside)."""
    n = len(xy)
    # remap wants maps shaped like an image of fewer than 32767 rows: fold the points.
    width = 1024
    rows = max(1, -(-n // width))
    mx = np.full(rows * width, -10.0, dtype=np.float32)
    my = np.full(rows * width, -10.0, dtype=np.float32)
    mx[:n], my[:n] = xy[:, 0], xy[:, 1]
    out = cv2.remap(
        img, mx.reshape(rows, width), my.reshape(rows, width), interpolation=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT, borderValue=0.0,
    )
    return out.reshape(-1)[:n]


def _corner_shift(t0: np.ndarray, t1: np.ndarray, shape) -> float:
    h, w = shape
    c = np.array([[0.0, 0.0, 1.0], [w - 1.0, 0.0, 1.0], [w - 1.0, h - 1.0, 1.0], [0.0, h - 1.0, 1.0]])
    d = (c @ t0.T)[:, :2] - (c @ t1.T)[:, :2]
    return float(np.hypot(d[:, 0], d[:, 1]).max())


def refine_direct(
    a: OccupancyGrid,
    b: OccupancyGrid,
    initial: SimilarityTransform,
    *,
    sigmas=(3.0, 1.5, 1.0),
    iterations: int = 10,
    max_points: int = 20000,
    max_shift: float = 12.0,
    rng=0,
    cache: dict | None = None,
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
        Cells of b sampled per level at most (a seeded random subset beyond that).
    max_shift : float
        A refinement that moves b's corners farther than this (a's pixels) is refused.
    rng : int or numpy.random.Generator
        Seed of the subsampling.
    cache : dict, optional
        Smoothed fields from earlier calls on the same two maps (pass the same dict to
        refine several candidates cheaply).

    Returns
    -------
    transform : SimilarityTransform
        The refined transform, or ``initial`` when refinement was not accepted.
    report : RefineReport
    """
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    if max(*a.shape, *b.shape) >= _REMAP_MAX:
        # OpenCV's remap cannot sample images this long; keep the initial estimate.
        return initial, RefineReport(False, 0, 0, 0.0, math.nan, math.nan)
    p = initial.params.copy()
    steps = 0
    npts = 0
    huber = 0.1
    rms_before = rms_after = math.nan
    for level, sigma_a in enumerate(sigmas):
        scale = math.hypot(p[0, 0], p[1, 0])
        # Clamped: an extreme scale would make the blur enormous (and slow) for nothing.
        sigma_b = min(max(0.5, sigma_a / max(scale, 1e-6)), 8.0 * sigma_a)
        sigma_b = round(sigma_b * 50) / 50  # 2 % steps, so that nearby scales share a field
        fa, gxa, gya, ka = _cached(cache, ("a", sigma_a), lambda: _field(a, sigma_a))
        fb, gxb, gyb, kb = _cached(cache, ("b", sigma_b), lambda: _field(b, sigma_b))
        gmag = np.hypot(gxb, gyb)
        ys, xs = np.nonzero((kb > 0.9) & (gmag > 0.01) & b.known)
        if len(xs) < 20:
            break
        if len(xs) > max_points:
            pick = np.sort(gen.choice(len(xs), max_points, replace=False))
            xs, ys = xs[pick], ys[pick]
        pts = np.stack([xs, ys], axis=1).astype(np.float64)
        target = fb[ys, xs].astype(np.float64)
        npts = len(pts)

        def residuals(params):
            q = pts @ params[:2, :2].T + params[:2, 2]
            valid = _sample(ka, q) > 0.9
            r = _sample(fa, q).astype(np.float64) - target
            return q, r, valid

        def robust_rms(r, valid):
            if not valid.any():
                return math.inf
            rv = np.abs(r[valid])
            return float(np.sqrt(np.mean(np.minimum(rv, 3 * huber) ** 2)))

        if level == len(sigmas) - 1:
            _, r0, v0 = residuals(initial.params)
            rms_before = robust_rms(r0, v0)
        for _ in range(iterations):
            q, r, valid = residuals(p)
            if valid.sum() < 20:
                break
            gx = _sample(gxa, q).astype(np.float64)[valid]
            gy = _sample(gya, q).astype(np.float64)[valid]
            rv = r[valid]
            px, py = pts[valid, 0], pts[valid, 1]
            # Parameters (sa, sb, tx, ty) of [[sa, -sb, tx], [sb, sa, ty]].
            j = np.stack([gx * px + gy * py, -gx * py + gy * px, gx, gy], axis=1)
            absr = np.abs(rv)
            w = np.where(absr <= huber, 1.0, huber / np.maximum(absr, 1e-12))
            # Column scaling keeps the normal equations well conditioned.
            norm = np.sqrt((j**2 * w[:, None]).sum(0)) + 1e-12
            jn = j / norm
            h = (jn.T * w) @ jn
            g = (jn.T * w) @ rv
            try:
                delta = -np.linalg.solve(h + 1e-9 * np.eye(4), g) / norm
            except np.linalg.LinAlgError:
                break
            sa, sb = p[0, 0] + delta[0], p[1, 0] + delta[1]
            new = np.array([[sa, -sb, p[0, 2] + delta[2]], [sb, sa, p[1, 2] + delta[3]], [0.0, 0.0, 1.0]])
            steps += 1
            moved = _corner_shift(p, new, b.shape)
            p = new
            if moved < 1e-3:
                break
        if level == len(sigmas) - 1:
            _, r1, v1 = residuals(p)
            rms_after = robust_rms(r1, v1)
    shift = _corner_shift(initial.params, p, b.shape)
    accepted = bool(
        np.isfinite(p).all()
        and shift <= max_shift
        and math.isfinite(rms_after)
        and (not math.isfinite(rms_before) or rms_after <= rms_before + 1e-9)
    )
    report = RefineReport(accepted, steps, npts, shift, rms_before, rms_after)
    if not accepted:
        return initial, report
    return SimilarityTransform(p), report

"""Global alignment hypotheses from the maps' structure, without keypoints.

Keypoints fail on real maps whose walls are fragmentary and whose corridors repeat; the
walls themselves still carry the alignment. Two global cues, in the spirit of Carpin's
spectral map merging:

* **rotation**: the histogram of wall directions (gradient orientations near occupied
  cells, modulo 180 degrees) of each map; the circular cross-correlation of the two
  histograms peaks at the rotation between the maps, up to 180 degrees (both are tried);
* **translation**: for each candidate rotation (and scale), the cross-correlation of the two
  maps' smoothed wall images, computed with FFTs at a coarse resolution; its highest peaks
  are candidate translations. Walls count positively and free space slightly negatively,
  so walls crossing the other map's free space are penalised.

The result is a ranked list of similarity transforms, to be refined and verified against
the maps (:mod:`gridmerge.refine`, :mod:`gridmerge.verify`).

Examples
--------
>>> from gridmerge import samples
>>> from gridmerge.transforms import corner_error
>>> a, b, truth = samples.robot_pair(0, scale=1.0, rotation_deg=40)
>>> best = correlation_hypotheses(a, b)[0]
>>> corner_error(best.transform, truth, b.shape) < 10
True
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from .grid import OccupancyGrid
from .transforms import SimilarityTransform

__all__ = ["CorrelationHypothesis", "direction_histogram", "rotation_candidates", "correlation_hypotheses"]


@dataclass(frozen=True)
class CorrelationHypothesis:
    """A transform proposed by correlation.

    Attributes
    ----------
    transform : SimilarityTransform
        b's pixels -> a's pixels.
    score : float
        The correlation peak (comparable between hypotheses of one pair only).
    rotation_deg, scale : float
        The rotation and scale tried.
    """

    transform: SimilarityTransform
    score: float
    rotation_deg: float
    scale: float


def direction_histogram(grid: OccupancyGrid, bins: int = 180, smooth: float = 1.5) -> np.ndarray:
    """``(bins,)`` unit-norm histogram of wall directions modulo 180 degrees.

    Gradient orientations of the smoothed occupancy, weighted by gradient magnitude, within
    two cells of an occupied cell (so that the edge of the explored area does not count),
    circularly smoothed by ``smooth`` bins.
    """
    occ = cv2.GaussianBlur(np.nan_to_num(grid.data, nan=0.5).astype(np.float32), (0, 0), 1.5)
    gx = cv2.Sobel(occ, cv2.CV_32F, 1, 0)
    gy = cv2.Sobel(occ, cv2.CV_32F, 0, 1)
    near = cv2.dilate(grid.occupied().astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    # Cells away from walls weigh nothing: only those near walls are looked at.
    gx, gy = gx[near], gy[near]
    weight = np.sqrt(gx * gx + gy * gy)
    angle = np.degrees(np.arctan2(gy, gx)) % 180.0
    hist, _ = np.histogram(angle, bins=bins, range=(0.0, 180.0), weights=weight)
    hist = hist.astype(float)
    if smooth > 0:
        half = int(math.ceil(3 * smooth))
        k = np.exp(-0.5 * (np.arange(-half, half + 1) / smooth) ** 2)
        hist = np.convolve(np.concatenate([hist[-half:], hist, hist[:half]]), k, "valid")
    norm = np.linalg.norm(hist)
    return hist / norm if norm > 0 else hist


def rotation_candidates(a: OccupancyGrid, b: OccupancyGrid, n: int = 4, min_separation_deg: float = 5.0) -> list[float]:
    """Up to ``n`` rotations (degrees, modulo 180) that align b's wall directions with a's.

    The peaks of the circular cross-correlation of the two direction histograms, best
    first; a rotation ``theta`` here also stands for ``theta + 180``.
    """
    ha, hb = direction_histogram(a), direction_histogram(b)
    bins = len(ha)
    if not ha.any() or not hb.any():
        return []
    cc = np.real(np.fft.ifft(np.fft.fft(ha) * np.conj(np.fft.fft(hb))))
    step = 180.0 / bins
    sep = max(1, int(round(min_separation_deg / step)))
    peaks: list[int] = []
    for k in np.argsort(-cc, kind="stable"):
        if all(min(abs(k - p), bins - abs(k - p)) > sep for p in peaks):
            peaks.append(int(k))
        if len(peaks) >= n:
            break
    return [p * step for p in peaks]


def _signed_walls(grid: OccupancyGrid, factor: float, free_weight: float, sigma: float) -> np.ndarray:
    walls = grid.occupied().astype(np.float32)
    free = grid.free().astype(np.float32)
    if factor < 1.0:
        # Walls are thin: grow them to the coarse cell size first, so that a coarse cell
        # crossed by a wall counts as wall however thin the wall is.
        k = int(math.ceil(1.0 / factor))
        if k > 1:
            walls = cv2.dilate(walls, np.ones((k, k), np.uint8))
        size = (max(1, round(walls.shape[1] * factor)), max(1, round(walls.shape[0] * factor)))
        walls = cv2.resize(walls, size, interpolation=cv2.INTER_AREA)
        free = cv2.resize(free, size, interpolation=cv2.INTER_AREA)
    return cv2.GaussianBlur(walls - free_weight * free, (0, 0), sigma)


def _peaks(a_img: np.ndarray, b_img: np.ndarray, n: int, suppress: int, spectra: dict | None = None):
    """``n`` best ``(dx, dy, value)``: shifts of b's image onto a's by cross-correlation.

    ``spectra`` keeps a's transforms by padded size, for many b images against one a.
    """
    h = cv2.getOptimalDFTSize(a_img.shape[0] + b_img.shape[0])
    w = cv2.getOptimalDFTSize(a_img.shape[1] + b_img.shape[1])
    if spectra is None:
        fa = np.fft.rfft2(a_img, (h, w))
    else:
        if (h, w) not in spectra:
            spectra[(h, w)] = np.fft.rfft2(a_img, (h, w))
        fa = spectra[(h, w)]
    fb = np.fft.rfft2(b_img, (h, w))
    c = np.fft.irfft2(fa * np.conj(fb), (h, w))  # c[dy, dx] = sum a[y + dy, x + dx] b[y, x]
    out = []
    for _ in range(n):
        y, x = np.unravel_index(int(np.argmax(c)), c.shape)
        value = float(c[y, x])
        if not math.isfinite(value):
            break
        out.append((x - w if x > w // 2 else x, y - h if y > h // 2 else y, value))
        c[max(0, y - suppress) : y + suppress + 1, max(0, x - suppress) : x + suppress + 1] = -np.inf
    return out


def correlation_hypotheses(
    a: OccupancyGrid,
    b: OccupancyGrid,
    *,
    scales: Sequence[float] = (1.0,),
    rotations: Sequence[float] | None = None,
    n_rotations: int = 4,
    fine_deg: Sequence[float] = (-1.0, 0.0, 1.0),
    peaks: int = 3,
    size: int = 200,
    free_weight: float = 0.25,
    sigma: float = 1.0,
    max_hypotheses: int = 20,
) -> list[CorrelationHypothesis]:
    """Candidate transforms b -> a from wall directions and wall-image correlation.

    Parameters
    ----------
    a, b : OccupancyGrid
        Best cropped to their known cells (as :func:`gridmerge.align` does).
    scales : sequence of float
        Scales (a's pixels per b's pixel) to try; 1 for maps of one resolution.
    rotations : sequence of float, optional
        Rotations (degrees, modulo 180) to try instead of :func:`rotation_candidates`.
    n_rotations : int
        Rotation candidates from the direction histograms.
    fine_deg : sequence of float
        Offsets (degrees) tried around each rotation candidate.
    peaks : int
        Correlation peaks kept per rotation and scale.
    size : int
        Longest side (cells) of the coarse images correlated.
    free_weight : float
        Weight of free space (negative) against walls (positive) in the correlated images.
    sigma : float
        Smoothing of the coarse images, in coarse cells.
    max_hypotheses : int

    Returns
    -------
    list of CorrelationHypothesis
        Best first.
    """
    if rotations is None:
        rotations = rotation_candidates(a, b, n_rotations)
    if not rotations or not a.occupied().any() or not b.occupied().any():
        return []
    factor = min(1.0, size / max(max(a.shape), max(b.shape) * max(scales)))
    a_img = _signed_walls(a, factor, free_weight, sigma)
    spectra: dict = {}
    out: list[CorrelationHypothesis] = []
    hb, wb = b.shape
    corners = np.array([[0.0, 0.0], [wb, 0.0], [wb, hb], [0.0, hb]])
    coarse = np.diag([factor, factor, 1.0])
    for s in scales:
        b_img = _signed_walls(b, min(1.0, factor * s), free_weight, sigma)
        fb = b_img.shape[1] / wb  # b's coarse cells per b pixel
        for base in rotations:
            for half_turn in (0.0, 180.0):
                for d in fine_deg:
                    theta = math.radians(base + half_turn + d)
                    rot = SimilarityTransform(rotation=theta, scale=s)
                    # b's pixels -> rotated, scaled and coarse, shifted to positive coordinates.
                    placed = coarse @ rot.params
                    c = corners @ placed[:2, :2].T
                    lo, hi = c.min(0), c.max(0)
                    place = np.array([[1.0, 0.0, -lo[0]], [0.0, 1.0, -lo[1]], [0.0, 0.0, 1.0]]) @ placed
                    from_coarse_b = np.diag([1.0 / fb, 1.0 / fb, 1.0])
                    m = place @ from_coarse_b
                    shape = (int(math.ceil(hi[0] - lo[0])) + 1, int(math.ceil(hi[1] - lo[1])) + 1)
                    warped = cv2.warpAffine(b_img, m[:2], shape, flags=cv2.INTER_LINEAR)
                    for dx, dy, value in _peaks(a_img, warped, peaks, suppress=4, spectra=spectra):
                        shift = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])
                        full = np.linalg.inv(coarse) @ shift @ place
                        out.append(CorrelationHypothesis(SimilarityTransform(full), value, math.degrees(theta) % 360.0, s))
    out.sort(key=lambda h: -h.score)
    return out[:max_hypotheses]

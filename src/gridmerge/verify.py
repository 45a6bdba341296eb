"""Judging an alignment by the maps themselves.

Feature matches can agree on a wrong transform (repeated corridors, symmetric rooms), so
every alignment is checked against the cells of both maps, in map a's frame:

* Birk & Carpin's **acceptance index** ``agr / (agr + dis)`` over the cells both maps
  know, where ``agr`` counts cells that both call occupied or both call free, and ``dis``
  cells that one calls occupied and the other free;
* **wall agreement**: the share of each map's occupied cells in the overlap that lie
  within ``tolerance`` cells of an occupied cell of the other map (symmetric mean). Free
  space dominates real maps, so the acceptance index alone stays high for many wrong
  merges; walls are where maps of different places disagree;
* the **overlap**: how many cells both maps know, and what fraction of the smaller map
  that is.

Examples
--------
>>> import numpy as np
>>> from gridmerge.grid import OccupancyGrid
>>> from gridmerge.transforms import SimilarityTransform
>>> d = np.zeros((50, 50)); d[10, :] = 1.0; d[:, 30] = 1.0
>>> v = verify(OccupancyGrid(d), OccupancyGrid(d), SimilarityTransform())
>>> v.acceptance_index, v.wall_agreement
(1.0, 1.0)
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from .fuse import warp_values
from .grid import FREE_THRESHOLD, OCCUPIED_THRESHOLD, OccupancyGrid
from .transforms import AffineTransform

__all__ = ["Verification", "verify", "acceptance_index", "WallScorer", "QuickScore", "despeckle"]


@dataclass(frozen=True)
class Verification:
    """Agreement of two aligned maps.

    Attributes
    ----------
    acceptance_index : float
        ``agr / (agr + dis)``; ``nan`` without overlap.
    agreement, disagreement : int
        Birk & Carpin's counts.
    wall_agreement : float
        Symmetric share of occupied overlap cells within ``tolerance`` of the other map's
        walls; ``nan`` when the overlap holds no wall.
    overlap_cells : int
        Cells of a's frame known in both maps.
    overlap_fraction : float
        ``overlap_cells`` over the known cells of the smaller map (in a's cells).
    """

    acceptance_index: float
    agreement: int
    disagreement: int
    wall_agreement: float
    overlap_cells: int
    overlap_fraction: float

    def to_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in asdict(self).items()}


def acceptance_index(p: np.ndarray, q: np.ndarray, *, occupied: float = OCCUPIED_THRESHOLD, free: float = FREE_THRESHOLD):
    """Birk & Carpin's acceptance index of two equally shaped occupancy arrays.

    Returns ``(index, agreement, disagreement)``; the index is ``nan`` when no cell is
    known as free or occupied in both.
    """
    with np.errstate(invalid="ignore"):
        po, pf = p > occupied, p < free
        qo, qf = q > occupied, q < free
    agr = int(np.count_nonzero(po & qo) + np.count_nonzero(pf & qf))
    dis = int(np.count_nonzero(po & qf) + np.count_nonzero(pf & qo))
    index = agr / (agr + dis) if agr + dis else math.nan
    return index, agr, dis


def despeckle(grid: OccupancyGrid) -> OccupancyGrid:
    """``grid`` with isolated occupied cells (no occupied 8-neighbour) made free.

    Single spurious hits are scattered over the free space of real and simulated maps;
    they are not walls, and judging an alignment by them only adds noise. Returns ``grid``
    itself when there is none.
    """
    occ = grid.occupied().astype(np.uint8)
    if not occ.any():
        return grid
    neighbours = cv2.filter2D(occ, cv2.CV_16S, np.ones((3, 3), np.float32), borderType=cv2.BORDER_CONSTANT) - occ
    isolated = (occ == 1) & (neighbours == 0)
    if not isolated.any():
        return grid
    data = grid.data.copy()
    data[isolated] = 0.0
    return grid.replace(data=data)


def _near(mask: np.ndarray, tolerance: float) -> np.ndarray:
    """Cells within ``tolerance`` cells of a True cell of ``mask``."""
    if not mask.any():
        return np.zeros_like(mask)
    dist = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 3)
    return dist <= tolerance


def verify(a: OccupancyGrid, b: OccupancyGrid, transform: AffineTransform, *, tolerance: float = 2.0) -> Verification:
    """Score how well ``b``, moved by ``transform`` (b pixels -> a pixels), agrees with ``a``.

    Parameters
    ----------
    a, b : OccupancyGrid
    transform : AffineTransform
    tolerance : float
        Distance (a's cells) within which two walls count as the same wall.
    """
    warped = warp_values(b.data, transform.params, a.shape, interpolation="nearest")
    both = a.known & ~np.isnan(warped)
    overlap = int(np.count_nonzero(both))
    pa = np.where(both, a.data, np.nan)
    pb = np.where(both, warped, np.nan)
    index, agr, dis = acceptance_index(pa, pb)
    with np.errstate(invalid="ignore"):
        wa = pa > OCCUPIED_THRESHOLD
        wb = pb > OCCUPIED_THRESHOLD
    shares = []
    if wa.any() and wb.any():
        shares.append(np.count_nonzero(wa & _near(wb, tolerance)) / np.count_nonzero(wa))
        shares.append(np.count_nonzero(wb & _near(wa, tolerance)) / np.count_nonzero(wb))
    elif wa.any() or wb.any():
        shares.append(0.0)
    wall = float(np.mean(shares)) if shares else math.nan
    scale2 = abs(float(np.linalg.det(transform.params[:2, :2])))
    known_b_in_a = np.count_nonzero(b.known) * scale2
    smaller = min(float(np.count_nonzero(a.known)), known_b_in_a)
    fraction = overlap / smaller if smaller > 0 else 0.0
    return Verification(index, agr, dis, wall, overlap, min(1.0, fraction))


@dataclass(frozen=True)
class QuickScore:
    """:class:`WallScorer`'s verdict on one transform.

    Attributes
    ----------
    wall_agreement : float
        Symmetric share of wall cells landing within the tolerance of the other map's walls,
        among those landing on the other map's known cells (0 when none do).
    overlap : float
        Share of b's known cells that land on a's known cells.
    walls_compared : int
        Wall cells that landed on known cells of the other map (both directions).
    consistency : float
        Symmetric share, among wall cells landing near the other map's walls or on its free
        space away from walls, of those near walls: walls seen from different sides or
        missing in one map do not lower it, walls across the other map's rooms do.
    """

    wall_agreement: float
    overlap: float
    walls_compared: int
    consistency: float = 0.0


class WallScorer:
    """Fast, repeated wall agreement of many candidate transforms between two maps.

    Distance transforms of both maps' walls are computed once; each candidate then only
    moves (a sample of) the wall cells of each map into the other and looks distances up,
    so dozens of candidates cost less than one full :func:`verify`.

    Parameters
    ----------
    a, b : OccupancyGrid
    tolerance : float
        Distance, in a's cells, within which walls coincide.
    max_points : int
        Wall cells sampled per map at most (an even stride, so results are repeatable).
    """

    def __init__(self, a: OccupancyGrid, b: OccupancyGrid, *, tolerance: float = 2.0, max_points: int = 20000):
        self.tolerance = float(tolerance)
        self._maps = []
        self._free = []
        for g in (a, b):
            walls = g.occupied()
            self._free.append(g.free())
            dist = cv2.distanceTransform((~walls).astype(np.uint8), cv2.DIST_L2, 3) if walls.any() else np.full(g.shape, np.inf, np.float32)
            ys, xs = np.nonzero(walls)
            step = max(1, len(xs) // max_points)
            ky, kx = np.nonzero(g.known)
            kstep = max(1, len(kx) // max_points)
            self._maps.append(
                (
                    g.known,
                    dist,
                    np.stack([xs[::step], ys[::step]], 1).astype(float),
                    np.stack([kx[::kstep], ky[::kstep]], 1).astype(float),
                )
            )

    @staticmethod
    def _lookup(points: np.ndarray, known: np.ndarray, dist: np.ndarray, tol: float, free: np.ndarray | None = None):
        h, w = known.shape
        p = np.rint(points).astype(np.int64)
        inside = (p[:, 0] >= 0) & (p[:, 0] < w) & (p[:, 1] >= 0) & (p[:, 1] < h)
        p = p[inside]
        on_known = known[p[:, 1], p[:, 0]]
        d = dist[p[:, 1], p[:, 0]]
        near = d[on_known] <= tol
        if free is None:
            return int(on_known.sum()), int(near.sum())
        conflict = int(np.count_nonzero(free[p[:, 1], p[:, 0]] & (d > tol)))
        return int(on_known.sum()), int(near.sum()), conflict

    def __call__(self, transform: AffineTransform) -> QuickScore:
        (ka, da, wa, pa), (kb, db, wb, pb) = self._maps
        inv = np.linalg.inv(transform.params)
        scale = math.sqrt(abs(float(np.linalg.det(transform.params[:2, :2])))) or 1.0
        fa, fb = self._free
        n_ab, good_ab, bad_ab = self._lookup(wb @ transform.params[:2, :2].T + transform.params[:2, 2], ka, da, self.tolerance, fa)
        n_ba, good_ba, bad_ba = self._lookup(wa @ inv[:2, :2].T + inv[:2, 2], kb, db, self.tolerance / scale, fb)
        shares = [g / n for g, n in ((good_ab, n_ab), (good_ba, n_ba)) if n > 0]
        wall = float(np.mean(shares)) if shares else 0.0
        cons = [g / (g + c) for g, c in ((good_ab, bad_ab), (good_ba, bad_ba)) if g + c > 0]
        consistency = float(np.mean(cons)) if cons else 0.0
        landed, _ = self._lookup(pb @ transform.params[:2, :2].T + transform.params[:2, 2], ka, np.zeros_like(da), 0.0)
        overlap = landed / len(pb) if len(pb) else 0.0
        return QuickScore(wall, overlap, n_ab + n_ba, consistency)

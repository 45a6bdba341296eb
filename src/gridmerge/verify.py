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

__all__ = ["Verification", "verify", "acceptance_index"]


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

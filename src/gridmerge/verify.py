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

import copy
import functools
import math
from dataclasses import asdict, dataclass, replace

import cv2
import numpy as np

from .grid import FREE_THRESHOLD, OCCUPIED_THRESHOLD, OccupancyGrid
from .transforms import AffineTransform

__all__ = ["Verification", "verify", "acceptance_index", "WallScorer", "QuickScore", "despeckle", "chance_wall_agreement",
           "Slide", "slide", "Crossing", "crossing"]


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
    walls_a, walls_b : int or None
        Occupied cells of a, and of b moved into a's cells, in the overlap: what
        ``wall_agreement``'s two shares are taken of (``None`` in results saved before
        they were recorded).
    matched_a, matched_b : int or None
        Of those, the cells within ``tolerance`` of the other map's walls: the wall
        agreement is the mean of ``matched_a / walls_a`` and ``matched_b / walls_b``
        (``None`` in results saved before they were recorded).
    """

    acceptance_index: float
    agreement: int
    disagreement: int
    wall_agreement: float
    overlap_cells: int
    overlap_fraction: float
    walls_a: int | None = None
    walls_b: int | None = None
    matched_a: int | None = None
    matched_b: int | None = None

    def to_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in asdict(self).items()}

    def wall_counts(self, names: tuple[str, str] | None = None) -> str:
        """Each map's wall cells in the overlap and how many lie on the other's walls, in
        words ("18 of 18 and 21 of 28 wall cells"; with ``names``, "18 of A's 18 and 21 of
        B's 28 wall cells"); "" when they were not counted or the overlap holds no wall.

        Examples
        --------
        >>> v = Verification(1.0, 100, 0, 0.88, 500, 0.3, walls_a=18, walls_b=28, matched_a=18, matched_b=21)
        >>> v.wall_counts(), v.wall_counts(("A", "B"))
        ('18 of 18 and 21 of 28 wall cells', "18 of A's 18 and 21 of B's 28 wall cells")
        """
        if self.walls_a is None or self.walls_b is None or not math.isfinite(self.wall_agreement):
            return ""
        na, nb = ("", "") if names is None else (f"{names[0]}'s ", f"{names[1]}'s ")
        return f"{self.matched_a} of {na}{self.walls_a} and {self.matched_b} of {nb}{self.walls_b} wall cells"

    def swapped(self) -> "Verification":
        """The same verification with the two maps' roles exchanged (the per-map counts
        swapped; the shared counts and shares are symmetric already)."""
        return replace(self, walls_a=self.walls_b, walls_b=self.walls_a, matched_a=self.matched_b, matched_b=self.matched_a)


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
    """``grid`` with isolated occupied cells (no occupied 8-neighbour) made unknown.

    Single hits are scattered over the free space of real and simulated maps. Some are
    noise, but many are walls seen sparsely (far from the robot, at a grazing angle):
    neither is a wall to judge an alignment by. Made unknown, they count for nothing;
    made free (as until the fifty-fourth session), a sparse true wall became free space
    where the other map has its wall, and the true pose agreed less than one a few
    cells off (docs/benchmarks.md, fifty-third and fifty-fourth sessions). Returns
    ``grid`` itself when there is none.
    """
    occ = grid.occupied().view(np.uint8)
    if not occ.any():
        return grid
    # Occupied cells in each 3 x 3 block (at most 9: bytes suffice); 1 means alone.
    block = cv2.boxFilter(occ, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
    isolated = (block == 1) & (occ == 1)
    if not isolated.any():
        return grid
    data = grid.data.copy()
    data[isolated] = np.nan
    if data.dtype != np.float32:
        return grid.replace(data=data)
    # The values are the grid's own, some made unknown: valid as they are, so no second
    # validation pass over a possibly huge map.
    data.flags.writeable = False
    out = copy.copy(grid)
    object.__setattr__(out, "data", data)
    return out


#: Above this tolerance (cells) :func:`_near` takes the distance transform, whose cost
#: does not grow with it (at 4000 x 4000 cells the two cost the same near 10 cells).
_DILATE_MAX = 8.0


@functools.lru_cache(maxsize=32)
def _near_kernel(tolerance: float) -> np.ndarray:
    """The offsets whose distance, as ``cv2.distanceTransform(DIST_L2, 3)`` measures it,
    is at most ``tolerance``: a ``(2r + 1, 2r + 1)`` uint8 kernel centred on offset 0
    (read off that transform of a single cell)."""
    # The transform's distance is at least 0.955 times the larger coordinate.
    r = int(math.floor(tolerance / 0.95)) + 1
    one = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    one[r, r] = 0
    kernel = (cv2.distanceTransform(one, cv2.DIST_L2, 3) <= tolerance).astype(np.uint8)
    rows = np.flatnonzero(kernel.any(axis=1))
    k = r - int(rows[0]) if len(rows) else 0  # the kernel is symmetric: trim its empty border
    kernel = np.ascontiguousarray(kernel[r - k : r + k + 1, r - k : r + k + 1])
    kernel.flags.writeable = False
    return kernel


def _near(mask: np.ndarray, tolerance: float) -> np.ndarray:
    """Cells within ``tolerance`` cells of a True cell of ``mask`` (``(H, W)`` bool).

    The distance is ``cv2.distanceTransform``'s (``DIST_L2``, 3 x 3 mask); for small
    tolerances the same cells are found by a dilation with the offsets it puts within
    ``tolerance`` (a few times cheaper on large maps).
    """
    if not mask.any():
        return np.zeros_like(mask)
    tolerance = float(tolerance)
    if 0.0 <= tolerance <= _DILATE_MAX:
        m = np.ascontiguousarray(mask, dtype=bool)
        near = cv2.dilate(m.view(np.uint8), _near_kernel(tolerance), borderType=cv2.BORDER_CONSTANT, borderValue=0)
        return near.view(bool)
    dist = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 3)
    return dist <= tolerance


def chance_wall_agreement(grid: OccupancyGrid, tolerance: float = 2.0) -> float:
    """The share of ``grid``'s known cells within ``tolerance`` cells of one of its
    occupied cells (0 when it knows none).

    About what the other map's walls would agree with on this map's side (the wall
    agreement's share for this map) for a pose laid anywhere on it: real maps' walls are
    thin lines through free space (0.1 to 0.45 at 3 cells), noise or a map whose free
    and occupied values are swapped is walls everywhere (near 1), and there the wall
    agreement cannot tell a right pose from any other.

    Examples
    --------
    >>> import numpy as np
    >>> from gridmerge.grid import OccupancyGrid
    >>> room = np.zeros((100, 100)); room[[0, -1], :] = 1.0; room[:, [0, -1]] = 1.0
    >>> round(chance_wall_agreement(OccupancyGrid(room), 3.0), 2)
    0.15
    >>> noise = np.random.default_rng(0).integers(0, 2, (100, 100)).astype(float)
    >>> round(chance_wall_agreement(OccupancyGrid(noise), 3.0), 2)
    1.0
    """
    known = grid.known
    n = int(np.count_nonzero(known))
    walls = grid.occupied()
    if n == 0 or not walls.any():
        return 0.0
    return float(np.count_nonzero(_near(walls, tolerance) & known)) / n


def _footprint(params: np.ndarray, shape_b, shape_a) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)``: the box of a's pixels that b's image (``shape_b``) can cover
    when moved by ``params`` (b pixels -> a pixels), clipped to a (``shape_a``)."""
    hb, wb = shape_b
    ha, wa = shape_a
    c = np.array([[-0.5, -0.5], [wb - 0.5, -0.5], [wb - 0.5, hb - 0.5], [-0.5, hb - 0.5]])
    q = c @ np.asarray(params, dtype=float)[:2, :2].T + np.asarray(params, dtype=float)[:2, 2]
    if not np.isfinite(q).all():
        return 0, 0, wa, ha
    lo = np.floor(q.min(0)) - 2
    hi = np.ceil(q.max(0)) + 3
    x0, y0 = int(min(max(lo[0], 0), wa)), int(min(max(lo[1], 0), ha))
    x1, y1 = int(min(max(hi[0], x0), wa)), int(min(max(hi[1], y0), ha))
    return x0, y0, x1, y1


def _warp_nearest(data: np.ndarray, matrix: np.ndarray, shape) -> np.ndarray:
    """``warp_values(data, matrix, shape, interpolation="nearest")``, in one warp: the
    nearest cell's value is copied as it is, NaN (unknown) included."""
    h, w = int(shape[0]), int(shape[1])
    if h == 0 or w == 0:
        return np.full((h, w), np.nan, np.float32)
    src = np.asarray(data, dtype=np.float32)
    return cv2.warpAffine(
        src, np.asarray(matrix, dtype=float)[:2], (w, h), flags=cv2.INTER_NEAREST,
        borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"),
    )


def _overlap_box(a: OccupancyGrid, b: OccupancyGrid, transform: AffineTransform):
    """``(sub, warped)``: ``(h, w)`` float arrays over the box of a's pixels that b's
    image covers when moved by ``transform`` (b pixels -> a pixels): a's cells there, and
    b's moved into them (nearest neighbour, NaN where b does not know)."""
    # Only the part of a that b's image covers can overlap: work on that box.
    x0, y0, x1, y1 = _footprint(transform.params, b.shape, a.shape)
    shifted = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]]) @ transform.params
    sub = a.data[y0:y1, x0:x1]
    return sub, _warp_nearest(b.data, shifted, sub.shape)


def _overlap_cells(a: OccupancyGrid, b: OccupancyGrid, transform: AffineTransform):
    """``(both, a_occupied, a_free, b_occupied, b_free)``: ``(h, w)`` bool masks over the
    box of :func:`_overlap_box`: the cells both maps know, and each map's occupied and
    free cells among them (b's moved into a's cells, nearest neighbour)."""
    sub, warped = _overlap_box(a, b, transform)
    both = ~np.isnan(sub) & ~np.isnan(warped)
    with np.errstate(invalid="ignore"):
        ao, af = (sub > OCCUPIED_THRESHOLD) & both, (sub < FREE_THRESHOLD) & both
        bo, bf = (warped > OCCUPIED_THRESHOLD) & both, (warped < FREE_THRESHOLD) & both
    return both, ao, af, bo, bf


def verify(a: OccupancyGrid, b: OccupancyGrid, transform: AffineTransform, *, tolerance: float = 2.0) -> Verification:
    """Score how well ``b``, moved by ``transform`` (b pixels -> a pixels), agrees with ``a``.

    Parameters
    ----------
    a, b : OccupancyGrid
    transform : AffineTransform
    tolerance : float
        Distance (a's cells) within which two walls count as the same wall.
    """
    both, ao, af, bo, bf = _overlap_cells(a, b, transform)
    overlap = int(np.count_nonzero(both))
    agr = int(np.count_nonzero(ao & bo) + np.count_nonzero(af & bf))
    dis = int(np.count_nonzero(ao & bf) + np.count_nonzero(af & bo))
    index = agr / (agr + dis) if agr + dis else math.nan
    na, nb = int(np.count_nonzero(ao)), int(np.count_nonzero(bo))
    ma = mb = 0
    if na and nb:
        ma = int(np.count_nonzero(ao & _near(bo, tolerance)))
        mb = int(np.count_nonzero(bo & _near(ao, tolerance)))
    wall = (ma / na + mb / nb) / 2 if na and nb else 0.0 if na or nb else math.nan
    scale2 = abs(float(np.linalg.det(transform.params[:2, :2])))
    known_b_in_a = np.count_nonzero(b.known) * scale2
    smaller = min(float(np.count_nonzero(a.known)), known_b_in_a)
    fraction = overlap / smaller if smaller > 0 else 0.0
    return Verification(index, agr, dis, wall, overlap, min(1.0, fraction), na, nb, ma, mb)


@dataclass(frozen=True)
class Slide:
    """How firmly the maps' walls pin a pose along its weakest direction (:func:`slide`).

    Attributes
    ----------
    direction : (2,) float array
        Unit vector ``(x, y)`` in a's pixels: the direction along which the walls the two
        maps share run (the weaker axis of their orientation tensor).
    distance : float
        How far (a's pixels) b was slid that way, each way.
    kept : float
        The lower of the two slid poses' wall agreement over the pose's own (0 when the
        pose's walls do not agree at all): near 1, the walls that hold the pose hold it
        as well slid along that line.
    """

    direction: np.ndarray
    distance: float
    kept: float


def _wall_axis(mask: np.ndarray) -> np.ndarray | None:
    """The unit ``(x, y)`` direction along which the walls of ``mask`` (``(H, W)`` bool)
    mostly run: the eigenvector of the smaller eigenvalue of the summed, per-cell
    normalised gradient tensor of the smoothed mask; ``None`` without walls."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if not len(rows):
        return None
    pad = 8  # beyond the blur's and the gradient's reach
    mask = np.pad(mask[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1], pad)
    m = cv2.GaussianBlur(mask.view(np.uint8).astype(np.float32), (0, 0), 1.5)
    gx = cv2.Sobel(m, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(m, cv2.CV_32F, 0, 1, ksize=3)
    near = _near(mask, 2.0)
    gx, gy = gx[near].astype(float), gy[near].astype(float)
    norm = gx * gx + gy * gy
    keep = norm > 1e-12
    if not keep.any():
        return None
    gx, gy, norm = gx[keep], gy[keep], norm[keep]
    tensor = np.array([[np.sum(gx * gx / norm), np.sum(gx * gy / norm)],
                       [np.sum(gx * gy / norm), np.sum(gy * gy / norm)]])
    _, vectors = np.linalg.eigh(tensor)
    return vectors[:, 0]


def slide(a: OccupancyGrid, b: OccupancyGrid, transform: AffineTransform, *, tolerance: float = 2.0,
          fraction: float = 0.15, verification: Verification | None = None) -> Slide | None:
    """Slide ``b``, moved by ``transform`` (b pixels -> a pixels), along the walls the two
    maps share, ``fraction`` of the overlap's size (the square root of its cells) each
    way, and measure how much of its wall agreement it keeps.

    A pose the maps fix drops on both sides: its walls cross, or its rooms' walls close
    on the other map's free space. A pose held by one straight wall, or a corridor, with
    the rest of b on a's unknown cells agrees as well slid along it: the maps do not say
    where along that line b lies, and a fit of two different places looks like that.

    ``verification``: ``verify(a, b, transform, tolerance=tolerance)`` when already
    known. Returns ``None`` when the pose shares no agreeing wall.

    Examples
    --------
    >>> import numpy as np
    >>> from gridmerge.grid import OccupancyGrid
    >>> from gridmerge.transforms import SimilarityTransform
    >>> d = np.full((80, 80), np.nan); d[20:60, 10:70] = 0.0; d[40, 10:70] = 1.0
    >>> line = OccupancyGrid(d)  # one wall through a band of free space
    >>> round(slide(line, line, SimilarityTransform()).kept, 2)
    1.0
    >>> d = np.full((80, 80), np.nan); d[15:65, 15:65] = 0.0
    >>> d[15:65, [15, 64]] = 1.0; d[[15, 64], 15:65] = 1.0
    >>> room = OccupancyGrid(d)  # a closed room: slid, its walls across the slide part
    >>> round(slide(room, room, SimilarityTransform()).kept, 2)
    0.67
    """
    base = verification if verification is not None else verify(a, b, transform, tolerance=tolerance)
    if not (math.isfinite(base.wall_agreement) and base.wall_agreement > 0 and base.overlap_cells):
        return None
    _, ao, _, bo, _ = _overlap_cells(a, b, transform)
    shared = (ao & _near(bo, tolerance)) | (bo & _near(ao, tolerance))
    axis = _wall_axis(shared)
    if axis is None:
        return None
    distance = float(fraction) * math.sqrt(base.overlap_cells)
    kept = []
    for sign in (1.0, -1.0):
        move = np.eye(3)
        move[:2, 2] = sign * distance * axis
        v = verify(a, b, AffineTransform(move @ transform.params), tolerance=tolerance)
        kept.append(v.wall_agreement / base.wall_agreement if math.isfinite(v.wall_agreement) else 0.0)
    return Slide(axis, distance, float(min(kept)))


@dataclass(frozen=True)
class Crossing:
    """How many of the overlap's walls lie deep inside the other map's free space
    (:func:`crossing`).

    Attributes
    ----------
    walls : int
        Occupied cells of both maps where both know the cell (counted in the finer map's
        cells, the other moved into them).
    deep : int or None
        Of those, the cells farther than ``depth`` cells from anything but the
        other map's free space (its walls, its unknown): walls across the other map's
        rooms, not beside its walls.
    share : float
        ``deep / walls`` (NaN without walls, or when ``deep`` was not counted).
    """

    walls: int
    deep: int | None
    share: float


def crossing(a: OccupancyGrid, b: OccupancyGrid, transform: AffineTransform, *, depth: float = 5.0,
             max_walls: int | None = None) -> Crossing:
    """Count the overlap's walls that cross the other map's open space, ``b`` moved by
    ``transform`` (b pixels -> a pixels).

    A wall of one map inside the other's free space contradicts the pose. Near the other
    map's walls, that is what bent maps and thick walls do; deeper than ``depth`` cells
    from any of its walls or unknown cells, the other map saw through the place where
    this wall stands. Real maps of one building have some such walls (furniture
    moved, doors open, glass); maps of two places laid room on room have many.

    It is counted in the cells of the map with the finer cells (a's when the transform
    does not shrink b, b's otherwise), the other moved into them: both ways round give
    the same, and ``depth`` is that map's cells. With ``max_walls``, an overlap holding
    that many wall cells or more is not searched for deep ones (``deep`` is ``None``,
    ``share`` NaN): on large maps that search costs most.

    Examples
    --------
    >>> import numpy as np
    >>> from gridmerge.grid import OccupancyGrid
    >>> from gridmerge.transforms import SimilarityTransform
    >>> d = np.zeros((60, 60)); d[[0, -1], :] = 1.0; d[:, [0, -1]] = 1.0
    >>> room = OccupancyGrid(d)              # a closed room, 60 x 60 cells
    >>> e = d.copy(); e[30, 10:50] = 1.0     # the same room with a wall across it
    >>> c = crossing(room, OccupancyGrid(e), SimilarityTransform())
    >>> c.walls, c.deep
    (512, 40)
    """
    if transform.scale < 1.0:
        a, b, transform = b, a, transform.inverse
    sub, warped = _overlap_box(a, b, transform)
    both = ~np.isnan(sub) & ~np.isnan(warped)
    with np.errstate(invalid="ignore"):
        ao, bo = (sub > OCCUPIED_THRESHOLD) & both, (warped > OCCUPIED_THRESHOLD) & both
        af, bf = sub < FREE_THRESHOLD, warped < FREE_THRESHOLD  # NaN (unknown) is not free
    walls = int(np.count_nonzero(ao) + np.count_nonzero(bo))
    if not walls:
        return Crossing(0, 0, math.nan)
    if max_walls is not None and walls >= max_walls:
        return Crossing(walls, None, math.nan)
    deep = int(np.count_nonzero(bo & (_free_depth(af) > depth)) + np.count_nonzero(ao & (_free_depth(bf) > depth)))
    return Crossing(walls, deep, deep / walls)


def _free_depth(free: np.ndarray) -> np.ndarray:
    """Each cell's distance (cells, Euclidean) to the nearest cell that is not free, 0 off
    ``free`` (``(h, w)`` bool); beyond the array's edge counts as not free."""
    padded = np.pad(free, 1).view(np.uint8)
    return cv2.distanceTransform(padded, cv2.DIST_L2, cv2.DIST_MASK_5)[1:-1, 1:-1]


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
    shared : float
        The larger of the two shares of known cells landing on the other map's known cells
        (about the share of the smaller map that overlaps the other).
    """

    wall_agreement: float
    overlap: float
    walls_compared: int
    consistency: float = 0.0
    shared: float = 0.0


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
        for g in (a, b):
            walls = g.occupied()
            known = g.known
            # One byte per cell: 1 known, 2 free; then one cell more, unknown and far from
            # any wall, that every point off the map looks up.
            # (Written in place into the arrays one cell longer: a copy of a 4000 x 4000
            # map's would cost 50 ms.)
            n = known.size
            code = np.empty(n + 1, np.uint8)
            cells = code[:n].reshape(g.shape)
            np.copyto(cells, known, casting="unsafe")
            cells[g.free()] |= 2
            code[n] = 0
            dist = np.empty(n + 1, np.float32)
            if walls.any():
                cv2.distanceTransform((~walls).astype(np.uint8), cv2.DIST_L2, 3, dst=dist[:n].reshape(g.shape))
            else:
                dist[:n] = np.inf
            dist[n] = np.inf
            self._maps.append((g.shape, code, dist, _columns(_strided_cells(walls, max_points)), _columns(_strided_cells(known, max_points))))

    @staticmethod
    def _cells(points: tuple[np.ndarray, np.ndarray], m: np.ndarray, shape) -> np.ndarray:
        """Flat indices of the cells the ``(x, y)`` columns ``points`` land on, moved by
        the ``(3, 3)`` matrix ``m``; ``h * w`` (the extra cell) off the map."""
        x, y = points
        h, w = shape
        px = x * m[0, 0]
        px += y * m[0, 1]
        px += m[0, 2]
        py = x * m[1, 0]
        py += y * m[1, 1]
        py += m[1, 2]
        xi = np.rint(px, out=px).astype(np.intp)
        yi = np.rint(py, out=py).astype(np.intp)
        # Negative indices wrap to huge unsigned ones: one comparison per axis.
        inside = (xi.view(np.uintp) < w) & (yi.view(np.uintp) < h)
        yi *= w
        yi += xi
        return np.where(inside, yi, h * w)

    @classmethod
    def _lookup(cls, points, m, shape, code: np.ndarray, dist: np.ndarray | None, tol: float):
        """``(on known, near a wall among those, on free away from walls)`` counts."""
        flat = cls._cells(points, m, shape)
        c = code.take(flat)
        on_known = (c & 1).view(bool)
        if dist is None:
            return int(np.count_nonzero(on_known)), 0, 0
        near = dist.take(flat) <= tol
        good = int(np.count_nonzero(on_known & near))
        conflict = int(np.count_nonzero((c >> 1).view(bool) & ~near))
        return int(np.count_nonzero(on_known)), good, conflict

    def __call__(self, transform: AffineTransform, *, tolerance: float | None = None) -> QuickScore:
        """The verdict on ``transform``, with walls coinciding within ``tolerance`` (a's
        cells; default: the scorer's)."""
        (sa, ca, da, wa, pa), (sb, cb, db, wb, pb) = self._maps
        tol = self.tolerance if tolerance is None else float(tolerance)
        t = transform.params
        inv = np.linalg.inv(t)
        scale = math.sqrt(abs(float(np.linalg.det(t[:2, :2])))) or 1.0
        n_ab, good_ab, bad_ab = self._lookup(wb, t, sa, ca, da, tol)
        n_ba, good_ba, bad_ba = self._lookup(wa, inv, sb, cb, db, tol / scale)
        shares = [g / n for g, n in ((good_ab, n_ab), (good_ba, n_ba)) if n > 0]
        wall = float(np.mean(shares)) if shares else 0.0
        cons = [g / (g + c) for g, c in ((good_ab, bad_ab), (good_ba, bad_ba)) if g + c > 0]
        consistency = float(np.mean(cons)) if cons else 0.0
        landed, _, _ = self._lookup(pb, t, sa, ca, None, 0.0)
        overlap = landed / len(pb[0]) if len(pb[0]) else 0.0
        landed_a, _, _ = self._lookup(pa, inv, sb, cb, None, 0.0)
        shared = max(overlap, landed_a / len(pa[0]) if len(pa[0]) else 0.0)
        return QuickScore(wall, overlap, n_ab + n_ba, consistency, shared)


def _columns(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The ``x`` and ``y`` columns of ``(K, 2)`` points, each contiguous."""
    return np.ascontiguousarray(points[:, 0]), np.ascontiguousarray(points[:, 1])


def _strided_cells(mask: np.ndarray, max_points: int) -> np.ndarray:
    """``(K, 2)`` float ``(x, y)`` of every ``step``-th True cell of ``mask`` in row-major
    order, ``step = max(1, count // max_points)`` (as ``np.nonzero(mask)[::step]``, in
    row blocks so that a huge mask needs no index array of its size)."""
    h, w = mask.shape
    count = int(np.count_nonzero(mask))
    step = max(1, count // max(1, int(max_points)))
    out = []
    seen = 0
    rows = max(1, (1 << 20) // max(1, w))
    flat = mask.reshape(-1) if mask.flags.c_contiguous else np.ascontiguousarray(mask).reshape(-1)
    for r0 in range(0, h, rows):
        idx = np.flatnonzero(flat[r0 * w : min(h, r0 + rows) * w])
        first = (-seen) % step  # the block's first index whose global rank is a multiple of step
        out.append(idx[first::step] + r0 * w)
        seen += len(idx)
    idx = np.concatenate(out) if out else np.zeros(0, np.int64)
    return np.stack([idx % w, idx // w], axis=1).astype(float)

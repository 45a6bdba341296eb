"""Sample maps that gridmerge generates itself.

Examples, tests and benchmarks run from a fresh clone without any data file: this module
draws procedural indoor floor plans (:func:`building`), simulates what robots with a
360-degree laser scanner map of them (:func:`explore`, :func:`random_viewpoints`,
:func:`trajectory`), and moves a map into another robot's frame (:func:`warp`). The pair
builders return two maps and the ground-truth transform between them:

* :func:`table1_pair` -- the paper's Table I experiment (a map and the same map rotated by
  30 degrees, shifted by (-86, -36) pixels and scaled by 0.95);
* :func:`robot_pair` -- two robots that explore overlapping parts of one building, the
  second one in its own rotated, shifted and scaled frame;
* :func:`negative_pair` -- maps of two different buildings (nothing to merge).

Every ground truth is a (3, 3) matrix that maps homogeneous pixels ``(x, y, 1)`` of map
``b`` to pixels of map ``a`` (OpenCV convention: ``x`` = column, ``y`` = row, integer values
at cell centres), so that ``b(p) == a(truth @ p)`` wherever both are known.

Everything is deterministic for a given seed; every random choice is drawn from a
``numpy.random.Generator`` (an ``int`` seed is turned into one with
``numpy.random.default_rng``).
"""

from __future__ import annotations

import math
from typing import Optional, Sequence, Union

import cv2
import numpy as np

from .fuse import reindexed
from .grid import DEFAULT_RESOLUTION, OCCUPIED_THRESHOLD, OccupancyGrid

__all__ = [
    "building",
    "explore",
    "random_viewpoints",
    "trajectory",
    "warp",
    "table1_pair",
    "robot_pair",
    "negative_pair",
    "TABLE1_THETA_DEG",
    "TABLE1_TRANSLATION",
    "TABLE1_SCALE",
    "TABLE1_B_SHAPE",
]

RngLike = Union[None, int, np.random.Generator, np.random.SeedSequence]

#: Rotation of the paper's Table I experiment, degrees.
TABLE1_THETA_DEG = 30.0
#: Translation ``(dx, dy)`` of the paper's Table I experiment, pixels.
TABLE1_TRANSLATION = (-86.0, -36.0)
#: Scale of the paper's Table I experiment.
TABLE1_SCALE = 0.95
#: ``(H, W)`` of map ``b`` in :func:`table1_pair` (for the default 480 x 640 building).
TABLE1_B_SHAPE = (280, 860)

# ------------------------------------------------------------------ floor plans
# Sizes in cells, tuned for 0.05 m cells (a 640 x 480 map is a 32 m x 24 m floor).
_MIN_ROOM = 56  # smallest room side between wall lines (2.8 m)
_MAX_ROOM = 190  # rooms with a longer side are usually split (9.5 m)
_OUTER_T = 4  # outer wall thickness
_DOOR_MIN, _DOOR_MAX = 14, 22  # door widths (0.7 m .. 1.1 m)
_DOOR_CLEAR = 14  # no furniture this close to a door, across the wall
_GAP = 10  # free-standing furniture keeps this distance to everything else
_MIN_SHAPE = 120


def _check_shape(shape: Sequence[int], minimum: int = 1) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in shape)
    except (TypeError, ValueError):
        raise ValueError(f"shape must be two integers (H, W), got {shape!r}") from None
    if h < minimum or w < minimum:
        raise ValueError(f"shape must be at least ({minimum}, {minimum}), got ({h}, {w})")
    return h, w


class _Leaf:
    """A room or corridor of the floor plan: wall lines ``x0 < x1``, ``y0 < y1``."""

    __slots__ = ("x0", "y0", "x1", "y1", "corridor")

    def __init__(self, x0: int, y0: int, x1: int, y1: int, corridor: bool) -> None:
        self.x0, self.y0, self.x1, self.y1, self.corridor = int(x0), int(y0), int(x1), int(y1), corridor

    @property
    def w(self) -> int:
        return self.x1 - self.x0

    @property
    def h(self) -> int:
        return self.y1 - self.y0


def building(
    seed: RngLike = 0,
    shape: Sequence[int] = (480, 640),
    *,
    resolution: float = DEFAULT_RESOLUTION,
) -> OccupancyGrid:
    """A procedural indoor floor plan, fully mapped.

    The floor is split recursively: first into corridors (a main corridor along the
    building and sometimes cross corridors), then into rooms of varied sizes. Interior
    walls are 2-3 cells thick, the outer wall 4; every room is reachable through doors
    (0.7-1.1 m wide), corridor junctions are open. Some corner rooms are left out (L- or
    U-shaped outlines), some outer corners are cut diagonally or rounded, and the rooms
    are furnished at random (cabinets along the walls, tables at any angle, round tables
    and pillars, irregular blobs, L-shaped desks, free-standing diagonal partitions and
    curved counters), so that SIFT finds many distinctive, non-repetitive keypoints.
    Free space is one connected region.

    Parameters
    ----------
    seed : int or numpy.random.Generator, optional
        Seed of the layout; the same seed gives the same map.
    shape : (int, int), optional
        ``(H, W)`` of the map in cells, at least 120 x 120. Room and wall sizes are in
        cells (tuned for 0.05 m cells), so a larger shape gives a larger building.
    resolution : float, optional
        Cell size stored in the map, metres per cell.

    Returns
    -------
    OccupancyGrid
        Free cells ``0.0``, walls and furniture ``1.0``, outside the building ``NaN``;
        origin ``(0, 0, 0)``.

    Examples
    --------
    >>> from gridmerge.samples import building
    >>> g = building(seed=3, shape=(200, 240))
    >>> g.shape
    (200, 240)
    >>> bool(g.free().any() and g.occupied().any() and not g.known.all())
    True
    """
    rng = np.random.default_rng(seed)
    H, W = _check_shape(shape, _MIN_SHAPE)

    # Bounding box of the building: wall lines X0 < X1, Y0 < Y1; a wall line at c is the
    # band of cells [c, c + thickness).
    mx = rng.integers(6, max(7, W // 24) + 1, size=2)
    my = rng.integers(6, max(7, H // 24) + 1, size=2)
    X0, X1 = int(mx[0]), int(W - mx[1] - _OUTER_T)
    Y0, Y1 = int(my[0]), int(H - my[1] - _OUTER_T)
    thick: dict[tuple[str, int], int] = {("x", X0): _OUTER_T, ("x", X1): _OUTER_T, ("y", Y0): _OUTER_T, ("y", Y1): _OUTER_T}

    def t(axis: str, c: int) -> int:
        key = (axis, int(c))
        if key not in thick:
            thick[key] = int(rng.integers(2, 4))
        return thick[key]

    leaves: list[_Leaf] = []

    def rooms(x0: int, y0: int, x1: int, y1: int) -> None:
        w, h = x1 - x0, y1 - y0
        can_x, can_y = w >= 2 * _MIN_ROOM, h >= 2 * _MIN_ROOM
        stop = 0.35 if max(w, h) <= _MAX_ROOM else 0.08 if max(w, h) <= 1.5 * _MAX_ROOM else 0.0
        if not (can_x or can_y) or rng.random() < stop:
            leaves.append(_Leaf(x0, y0, x1, y1, False))
            return
        if can_x and can_y:
            if w > 1.25 * h:
                axis = "x"
            elif h > 1.25 * w:
                axis = "y"
            else:
                axis = "x" if rng.random() < 0.5 else "y"
        else:
            axis = "x" if can_x else "y"
        if axis == "x":
            c = int(rng.integers(x0 + _MIN_ROOM, x1 - _MIN_ROOM + 1))
            t("x", c)
            rooms(x0, y0, c, y1)
            rooms(c, y0, x1, y1)
        else:
            c = int(rng.integers(y0 + _MIN_ROOM, y1 - _MIN_ROOM + 1))
            t("y", c)
            rooms(x0, y0, x1, c)
            rooms(x0, c, x1, y1)

    def corridors(x0: int, y0: int, x1: int, y1: int, depth: int) -> None:
        w, h = x1 - x0, y1 - y0
        # depth 0: a main corridor along the building; depth 1: cross corridors.
        along_x = (w >= h) if depth == 0 else (w < h)
        length, across = (w, h) if along_x else (h, w)
        cw = int(rng.integers(22, 35))
        p = 1.0 if depth == 0 else 0.55
        if depth <= 1 and length >= (200 if depth == 0 else 110) and across >= 2 * _MIN_ROOM + cw + 8 and rng.random() < p:
            lo = (y0 if along_x else x0) + _MIN_ROOM
            hi = (y1 if along_x else x1) - _MIN_ROOM - cw
            c = int(rng.integers(lo, hi + 1))
            axis = "y" if along_x else "x"
            t(axis, c)
            t(axis, c + cw)
            if along_x:
                leaves.append(_Leaf(x0, c, x1, c + cw, True))
                corridors(x0, y0, x1, c, depth + 1)
                corridors(x0, c + cw, x1, y1, depth + 1)
            else:
                leaves.append(_Leaf(c, y0, c + cw, y1, True))
                corridors(x0, y0, c, y1, depth + 1)
                corridors(c + cw, y0, x1, y1, depth + 1)
        else:
            rooms(x0, y0, x1, y1)

    corridors(X0, Y0, X1, Y1, 0)
    n = len(leaves)

    # Shared wall segments between leaves: (i, j, axis, line, s0, s1).
    edges = []
    for i in range(n):
        a = leaves[i]
        for j in range(i + 1, n):
            b = leaves[j]
            for axis, (a0, a1, b0, b1), (ao0, ao1, bo0, bo1) in (
                ("x", (a.x0, a.x1, b.x0, b.x1), (a.y0, a.y1, b.y0, b.y1)),
                ("y", (a.y0, a.y1, b.y0, b.y1), (a.x0, a.x1, b.x0, b.x1)),
            ):
                if a1 == b0 or b1 == a0:
                    line = a1 if a1 == b0 else a0
                    s0, s1 = max(ao0, bo0), min(ao1, bo1)
                    other = "y" if axis == "x" else "x"
                    lo, hi = s0 + t(other, s0), s1
                    if hi - lo >= _DOOR_MIN + 6:
                        edges.append((i, j, axis, line, lo, hi))

    def connected(keep: np.ndarray) -> bool:
        idx = np.flatnonzero(keep)
        if idx.size == 0:
            return False
        seen = {int(idx[0])}
        stack = [int(idx[0])]
        while stack:
            k = stack.pop()
            for i, j, *_ in edges:
                for u, v in ((i, j), (j, i)):
                    if u == k and keep[v] and v not in seen:
                        seen.add(v)
                        stack.append(v)
        return len(seen) == idx.size

    # Leave out some rooms on the outline (L- and U-shaped buildings).
    keep = np.ones(n, dtype=bool)
    box_area = float((X1 - X0) * (Y1 - Y0))
    removed = 0.0
    for _ in range(int(rng.integers(0, 3))):
        cands, weights = [], []
        for k, lf in enumerate(leaves):
            if not keep[k] or lf.corridor:
                continue
            sides = (lf.x0 == X0) + (lf.x1 == X1) + (lf.y0 == Y0) + (lf.y1 == Y1)
            if sides:
                cands.append(k)
                weights.append(3.0 if sides >= 2 else 1.0)
        if not cands:
            break
        w_arr = np.asarray(weights)
        k = int(cands[int(rng.choice(len(cands), p=w_arr / w_arr.sum()))])
        area = leaves[k].w * leaves[k].h
        trial = keep.copy()
        trial[k] = False
        if removed + area <= 0.22 * box_area and connected(trial):
            keep = trial
            removed += area

    region = np.zeros((H, W), dtype=bool)
    occ = np.zeros((H, W), dtype=np.uint8)
    for k, lf in enumerate(leaves):
        if not keep[k]:
            continue
        xe, ye = lf.x1 + t("x", lf.x1), lf.y1 + t("y", lf.y1)
        region[lf.y0 : ye, lf.x0 : xe] = True
        occ[lf.y0 : lf.y0 + t("y", lf.y0), lf.x0 : xe] = 1
        occ[lf.y1 : ye, lf.x0 : xe] = 1
        occ[lf.y0 : ye, lf.x0 : lf.x0 + t("x", lf.x0)] = 1
        occ[lf.y0 : ye, lf.x1 : xe] = 1

    # Doors: a random spanning tree of the rooms (corridors first), then extra doors.
    live = [e for e in edges if keep[e[0]] and keep[e[1]]]
    keys = np.array(
        [rng.random() - (0.6 if (leaves[e[0]].corridor or leaves[e[1]].corridor) else 0.0) for e in live]
    )
    parent = list(range(n))

    def find(u: int) -> int:
        while parent[u] != u:
            parent[u] = parent[parent[u]]
            u = parent[u]
        return u

    doors = []
    for e_idx in np.argsort(keys, kind="stable"):
        e = live[int(e_idx)]
        ri, rj = find(e[0]), find(e[1])
        corr = leaves[e[0]].corridor + leaves[e[1]].corridor
        if ri != rj:
            parent[ri] = rj
            doors.append(e)
        elif rng.random() < (1.0 if corr == 2 else 0.65 if corr == 1 else 0.15):
            doors.append(e)
    door_clear = np.zeros((H, W), dtype=bool)
    for i, j, axis, line, lo, hi in doors:
        tc = t(axis, line)
        if leaves[i].corridor and leaves[j].corridor:
            d0, d1 = lo, hi  # open corridor junction
        else:
            dw = int(min(rng.integers(_DOOR_MIN, _DOOR_MAX + 1), hi - lo - 6))
            d0 = int(rng.integers(lo + 3, hi - 3 - dw + 1))
            d1 = d0 + dw
        if axis == "x":
            occ[d0:d1, line : line + tc] = 0
            door_clear[max(d0 - 3, 0) : d1 + 3, max(line - _DOOR_CLEAR, 0) : line + tc + _DOOR_CLEAR] = True
        else:
            occ[line : line + tc, d0:d1] = 0
            door_clear[max(line - _DOOR_CLEAR, 0) : line + tc + _DOOR_CLEAR, max(d0 - 3, 0) : d1 + 3] = True

    # Cut or round some outer corners of the bounding box.
    yy, xx = np.mgrid[0:H, 0:W]
    for sx, sy in ((1, 1), (-1, 1), (1, -1), (-1, -1)):
        corner = None
        for k, lf in enumerate(leaves):
            if keep[k] and (lf.x0 == X0 if sx > 0 else lf.x1 == X1) and (lf.y0 == Y0 if sy > 0 else lf.y1 == Y1):
                corner = lf
        style = rng.choice(3, p=[0.4, 0.35, 0.25])
        if corner is None or style == 0:
            continue
        cx = X0 if sx > 0 else X1 + _OUTER_T
        cy = Y0 if sy > 0 else Y1 + _OUTER_T
        dx = (xx - cx) * sx
        dy = (yy - cy) * sy
        side = min(corner.w, corner.h)
        if style == 1:
            lx, ly = rng.uniform(0.25, 0.45, size=2) * side
            cut = (dx >= 0) & (dy >= 0) & (dx / lx + dy / ly < 1.0)
        else:
            r = rng.uniform(0.3, 0.45) * side
            cut = (dx >= 0) & (dy >= 0) & (dx < r) & (dy < r) & ((dx - r) ** 2 + (dy - r) ** 2 > r * r)
        region &= ~cut

    # Outer walls: every building cell within _OUTER_T cells of the outside.
    outside = (~region).astype(np.uint8)
    near_out = cv2.dilate(outside, np.ones((2 * _OUTER_T - 1, 2 * _OUTER_T - 1), np.uint8)) > 0
    occ[region & near_out] = 1
    occ[~region] = 0

    # Furniture.
    items = np.zeros((H, W), dtype=np.uint8)
    for k, lf in enumerate(leaves):
        if not keep[k]:
            continue
        ys = slice(lf.y0 + t("y", lf.y0), lf.y1)
        xs = slice(lf.x0 + t("x", lf.x0), lf.x1)
        _furnish(occ[ys, xs], items[ys, xs], region[ys, xs], door_clear[ys, xs], lf.corridor, rng)

    # Whatever free pocket the furniture cut off is filled (a robot would never see it).
    free = (region & (occ == 0)).astype(np.uint8)
    count, labels = cv2.connectedComponents(free, connectivity=4)
    if count > 2:
        sizes = np.bincount(labels.ravel(), minlength=count)
        sizes[0] = 0
        main = int(np.argmax(sizes))
        occ[(labels != main) & (free > 0)] = 1

    data = np.full((H, W), np.nan, dtype=np.float32)
    data[region] = occ[region].astype(np.float32)
    return OccupancyGrid(data, resolution=resolution, name=f"building(seed={seed})" if isinstance(seed, (int, np.integer)) else "building")


def _furnish(
    occ: np.ndarray,
    items: np.ndarray,
    region: np.ndarray,
    door_clear: np.ndarray,
    corridor: bool,
    rng: np.random.Generator,
) -> None:
    """Furnish one room or corridor (``occ``, ``items``... are views of its interior).

    Pieces of furniture are drawn at random and kept when they stay out of the doors'
    clearance, keep their distance (``_GAP`` cells for furniture that stands free, 4 for
    small things, none to the wall a cabinet stands against) and do not cut the room's
    free space in two.
    """
    h, w = occ.shape
    if h < 8 or w < 8:
        return
    forbidden = door_clear | ~region
    n_comp0 = cv2.connectedComponents((region & (occ == 0)).astype(np.uint8), connectivity=4)[0]
    if corridor:
        want = int(rng.integers(0, 2 + max(h, w) // 140))
        n_small = int(rng.integers(0, 2 + max(h, w) // 120))
        kinds = ["pillar", "round", "blob"]
        probs = [0.6, 0.25, 0.15]
    else:
        want = min(1 + int(rng.poisson(h * w / 3500.0)), 10)
        n_small = min(int(rng.poisson(h * w / 2500.0)), 10)
        kinds = ["cabinet", "table", "round", "blob", "desk", "partition", "arc"]
        probs = [0.26, 0.22, 0.12, 0.12, 0.1, 0.09, 0.09]
    for small in [False] * want + [True] * n_small:  # furniture first, then small things
        for _attempt in range(6):
            kind = "small" if small else kinds[int(rng.choice(len(kinds), p=probs))]
            item = _draw_item(kind, h, w, rng)
            if item is None:
                continue
            if _fits(item, kind, small, occ, items, region, forbidden, n_comp0):
                occ[item] = 1
                items[item] = 1
                break


def _draw_item(kind: str, h: int, w: int, rng: np.random.Generator) -> Optional[np.ndarray]:
    """A random piece of furniture of ``kind`` in an ``(h, w)`` room, as a bool mask."""
    item = np.zeros((h, w), dtype=np.uint8)
    if kind in ("cabinet", "pillar"):  # against a wall, axis-aligned
        side = int(rng.integers(4))
        along, perp = (w, h) if side < 2 else (h, w)
        if kind == "pillar":
            length = int(rng.integers(4, 8))
            depth = int(rng.integers(3, 6))
        else:
            length = int(rng.integers(12, max(13, int(0.6 * along))))
            depth = int(rng.integers(5, max(6, min(16, perp // 4))))
        if length >= along - 2 or depth >= perp // 3:
            return None
        s = int(rng.integers(0, along - length + 1))
        if side == 0:
            item[:depth, s : s + length] = 1
        elif side == 1:
            item[h - depth :, s : s + length] = 1
        elif side == 2:
            item[s : s + length, :depth] = 1
        else:
            item[s : s + length, w - depth :] = 1
        return item > 0
    cx, cy = rng.uniform(0, w), rng.uniform(0, h)
    if kind == "small":  # chairs, bins, plants
        a, b = rng.uniform(2.5, 6.0, size=2)
        if rng.random() < 0.4:
            cv2.ellipse(item, _pt((cx, cy)), (int(a * 8), int(b * 8)), rng.uniform(0, 180), 0, 360, 1, -1, cv2.LINE_8, 4)
        else:
            _fill(item, cv2.boxPoints(((cx, cy), (a, b), rng.uniform(0, 180))))
    elif kind in ("table", "desk"):
        a, b = rng.uniform(12, 36), rng.uniform(8, 20)
        ang = 0.0 if rng.random() < 0.4 else rng.uniform(0, 180)
        _fill(item, cv2.boxPoints(((cx, cy), (a, b), ang)))
        if kind == "desk":  # an L: a second arm from one end of the first
            rad = math.radians(ang)
            u = np.array([math.cos(rad), math.sin(rad)])
            v = np.array([-u[1], u[0]])
            end = np.array([cx, cy]) + u * (a / 2 - b / 4)
            arm = rng.uniform(14, 28)
            centre = end + v * (arm / 2) * (1 if rng.random() < 0.5 else -1)
            _fill(item, cv2.boxPoints(((float(centre[0]), float(centre[1])), (b / 2, arm), ang)))
    elif kind == "round":  # round tables, pillars
        r = rng.uniform(2.5, 9)
        cv2.circle(item, _pt((cx, cy)), int(round(r * 16)), 1, -1, cv2.LINE_8, 4)
    elif kind == "blob":  # irregular things: sofas, plants, machines
        m = int(rng.integers(5, 10))
        ang = np.sort(rng.uniform(0, 2 * np.pi, m))
        rad = rng.uniform(6, 15) * rng.uniform(0.45, 1.0, m)
        _fill(item, np.stack([cx + rad * np.cos(ang), cy + rad * np.sin(ang)], axis=1))
    elif kind == "partition":  # a free-standing wall at any angle
        ln = rng.uniform(25, 60)
        ang = rng.uniform(0, np.pi)
        p1 = (cx + ln * math.cos(ang), cy + ln * math.sin(ang))
        cv2.line(item, _pt((cx, cy)), _pt(p1), 1, int(rng.integers(2, 4)), cv2.LINE_8, 4)
    elif kind == "arc":  # a curved counter
        r1 = rng.uniform(12, 30)
        r2 = r1 * rng.uniform(0.6, 1.0)
        start = rng.uniform(0, 360)
        span = rng.uniform(60, 170)
        axes = (int(round(r1 * 16)), int(round(r2 * 16)))
        cv2.ellipse(item, _pt((cx, cy)), axes, rng.uniform(0, 360), start, start + span, 1, int(rng.integers(2, 4)), cv2.LINE_8, 4)
    else:  # pragma: no cover - internal
        raise AssertionError(kind)
    return item > 0


def _fits(
    item: np.ndarray,
    kind: str,
    small: bool,
    occ: np.ndarray,
    items: np.ndarray,
    region: np.ndarray,
    forbidden: np.ndarray,
    n_comp0: int,
) -> bool:
    if not item.any() or (item & forbidden).any():
        return False
    gap = 4 if small else _GAP
    if kind in ("cabinet", "pillar"):
        grown = cv2.dilate(item.astype(np.uint8), np.ones((2 * gap + 1, 2 * gap + 1), np.uint8)) > 0
        if (grown & (items > 0)).any():
            return False
    else:
        if item.sum() < (3 if small else 6):
            return False
        obstacle = ((occ > 0) | ~region).astype(np.uint8)
        padded = np.pad(1 - obstacle, 1, constant_values=0)
        dist = cv2.distanceTransform(padded, cv2.DIST_L2, 3)[1:-1, 1:-1]
        if dist[item].min() < gap:
            return False
    trial = (region & (occ == 0) & ~item).astype(np.uint8)
    return cv2.connectedComponents(trial, connectivity=4)[0] <= n_comp0


def _pt(p) -> tuple[int, int]:
    """A point in cv2's fixed-point format with shift=4."""
    return int(round(float(p[0]) * 16)), int(round(float(p[1]) * 16))


def _fill(img: np.ndarray, poly) -> None:
    pts = np.round(np.asarray(poly, dtype=np.float64) * 16).astype(np.int32).reshape(-1, 1, 2)
    cv2.fillPoly(img, [pts], 1, cv2.LINE_8, 4)


# ------------------------------------------------------------------- exploration
def explore(
    world: OccupancyGrid,
    viewpoints,
    *,
    max_range_px: float = 150,
    n_rays: int = 720,
    rng: RngLike = None,
    noise: float = 0.0,
    see_through: int = 0,
) -> OccupancyGrid:
    """What a robot with a 360-degree laser scanner maps from some viewpoints.

    From every viewpoint, rays are cast in all directions and traced exactly cell by cell
    (a 4-connected traversal, so a ray never slips diagonally between two wall cells).
    Cells a ray passes through are free; a ray stops at the first cell that is occupied in
    the world (``p > 0.65``), which is marked occupied, or at an unknown cell of the world
    or the map's edge, which stay unknown. Cells that no ray reaches within
    ``max_range_px`` stay unknown. With ``see_through > 0``, a ray crosses up to that
    many consecutive unknown cells of the world (they stay unknown) and goes on to what
    lies behind them.

    Parameters
    ----------
    world : OccupancyGrid
        The true map.
    viewpoints : (N, 2) array_like of float
        Scanner positions, pixels ``(x = column, y = row)``; they must lie on the map.
    max_range_px : float, optional
        Range of the scanner, in cells.
    n_rays : int, optional
        Rays per viewpoint. It is raised to ``ceil(1.2 * 2 * pi * max_range_px)`` when
        smaller, so that neighbouring rays are less than a cell apart at the maximum range
        and the observed free space has no holes.
    rng : int or numpy.random.Generator, optional
        Source of the noise (``None``: fresh entropy). Unused when ``noise == 0``.
    noise : float, optional
        In ``[0, 1]``: each wall cell that was hit is missed (left unknown) with
        probability ``noise``, and each observed free cell is turned into a spurious
        occupied cell with probability ``noise / 50``.

    Returns
    -------
    OccupancyGrid
        Free ``0.0``, occupied ``1.0``, unknown ``NaN``; the world's shape, resolution and
        origin.

    Examples
    --------
    >>> import numpy as np
    >>> from gridmerge.grid import OccupancyGrid
    >>> from gridmerge.samples import explore
    >>> world = np.zeros((21, 21)); world[:, 15] = 1.0  # a wall at column 15
    >>> seen = explore(OccupancyGrid(world), [[5, 10]], max_range_px=30)
    >>> float(seen.data[10, 14]), float(seen.data[10, 15]), bool(np.isnan(seen.data[10, 16]))
    (0.0, 1.0, True)
    """
    data = world.data
    H, W = world.shape
    vp = np.asarray(viewpoints, dtype=float)
    if vp.ndim == 1 and vp.size == 2:
        vp = vp.reshape(1, 2)
    if vp.ndim != 2 or vp.shape[1] != 2:
        raise ValueError(f"viewpoints must be an (N, 2) array of pixel positions, got shape {vp.shape}")
    if not np.isfinite(vp).all():
        raise ValueError("viewpoints must be finite")
    if len(vp) and ((vp[:, 0] < -0.5) | (vp[:, 0] >= W - 0.5) | (vp[:, 1] < -0.5) | (vp[:, 1] >= H - 0.5)).any():
        raise ValueError(f"viewpoints must lie on the {W} x {H} map")
    max_range = float(max_range_px)
    if not math.isfinite(max_range) or max_range <= 0:
        raise ValueError(f"max_range_px must be > 0, got {max_range_px!r}")
    noise = float(noise)
    if not 0.0 <= noise <= 1.0:
        raise ValueError(f"noise must be in [0, 1], got {noise!r}")
    see_through = int(see_through)
    if see_through < 0:
        raise ValueError(f"see_through must be >= 0, got {see_through}")
    n = max(int(n_rays), int(math.ceil(1.2 * 2.0 * math.pi * max_range)))

    with np.errstate(invalid="ignore"):
        occupied = (data > OCCUPIED_THRESHOLD).ravel()
    unknown = np.isnan(data).ravel()
    free = np.zeros(H * W, dtype=bool)
    hit = np.zeros(H * W, dtype=bool)

    if len(vp):
        ang = (np.arange(n) + 0.5) * (2.0 * math.pi / n)
        dx = np.tile(np.cos(ang), len(vp))
        dy = np.tile(np.sin(ang), len(vp))
        ox = np.repeat(vp[:, 0] + 0.5, n)  # cell (i, j) covers [j, j+1) x [i, i+1) here
        oy = np.repeat(vp[:, 1] + 0.5, n)
        cx = np.floor(ox).astype(np.int64)
        cy = np.floor(oy).astype(np.int64)
        gap = np.zeros(cx.size, dtype=np.int64)  # consecutive unknown cells crossed
        with np.errstate(divide="ignore", invalid="ignore"):
            sx = np.where(dx > 0, 1, -1)
            sy = np.where(dy > 0, 1, -1)
            tdx = np.where(dx != 0, 1.0 / np.abs(dx), np.inf)
            tdy = np.where(dy != 0, 1.0 / np.abs(dy), np.inf)
            tmx = np.where(dx > 0, (cx + 1 - ox) / dx, np.where(dx < 0, (cx - ox) / dx, np.inf))
            tmy = np.where(dy > 0, (cy + 1 - oy) / dy, np.where(dy < 0, (cy - oy) / dy, np.inf))
        while cx.size:
            inside = (cx >= 0) & (cx < W) & (cy >= 0) & (cy < H)
            idx = np.where(inside, cy * W + cx, 0)
            wall = inside & occupied[idx]
            hole = inside & unknown[idx]
            gap = np.where(hole, gap + 1, 0)
            hit[idx[wall]] = True
            go = inside & ~wall & (gap <= see_through)
            free[idx[go & ~hole]] = True
            step_x = tmx < tmy
            t_next = np.where(step_x, tmx, tmy)
            go &= t_next <= max_range
            if not go.all():
                cx, cy, sx, sy, tdx, tdy, tmx, tmy, step_x, gap = (
                    a[go] for a in (cx, cy, sx, sy, tdx, tdy, tmx, tmy, step_x, gap)
                )
            cx = cx + np.where(step_x, sx, 0)
            cy = cy + np.where(step_x, 0, sy)
            tmx = tmx + np.where(step_x, tdx, 0.0)
            tmy = tmy + np.where(step_x, 0.0, tdy)

    if noise > 0:
        gen = np.random.default_rng(rng)
        hit_idx = np.flatnonzero(hit)
        hit[hit_idx[gen.random(hit_idx.size) < noise]] = False
        free_idx = np.flatnonzero(free)
        spurious = free_idx[gen.random(free_idx.size) < noise / 50.0]
        free[spurious] = False
        hit[spurious] = True
    out = np.full(H * W, np.nan, dtype=np.float32)
    out[free] = 0.0
    out[hit] = 1.0
    return OccupancyGrid(out.reshape(H, W), resolution=world.resolution, origin=world.origin, name=None)


def _clear_free(world: OccupancyGrid, clearance: float) -> np.ndarray:
    """Free cells at least ``clearance`` cells away from every non-free cell."""
    free = world.free().astype(np.uint8)
    if clearance <= 0:
        return free > 0
    padded = np.pad(free, 1, constant_values=0)
    dist = cv2.distanceTransform(padded, cv2.DIST_L2, 5)[1:-1, 1:-1]
    return dist >= clearance


def random_viewpoints(
    world: OccupancyGrid,
    n: int,
    *,
    rng: RngLike,
    region: Optional[np.ndarray] = None,
    clearance: float = 4.0,
) -> np.ndarray:
    """Random scanner positions in the free space of a map.

    Parameters
    ----------
    world : OccupancyGrid
        The map.
    n : int
        Number of viewpoints (distinct cells while there are enough candidates).
    rng : int or numpy.random.Generator
        Source of the random choice.
    region : (H, W) array_like of bool, optional
        Only cells where ``region`` is true are candidates.
    clearance : float, optional
        Minimum distance, in cells, from any cell that is not free (a robot has a body).

    Returns
    -------
    (n, 2) float array
        Cell centres ``(x = column, y = row)``.

    Raises
    ------
    ValueError
        If no cell qualifies.

    Examples
    --------
    >>> import numpy as np
    >>> from gridmerge.grid import OccupancyGrid
    >>> from gridmerge.samples import random_viewpoints
    >>> world = OccupancyGrid(np.zeros((30, 40)))
    >>> random_viewpoints(world, 3, rng=0).shape
    (3, 2)
    """
    gen = np.random.default_rng(rng)
    n = int(n)
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    ok = _clear_free(world, clearance)
    if region is not None:
        reg = np.asarray(region, dtype=bool)
        if reg.shape != world.shape:
            raise ValueError(f"region must have the map's shape {world.shape}, got {reg.shape}")
        ok &= reg
    ys, xs = np.nonzero(ok)
    if n == 0:
        return np.zeros((0, 2))
    if xs.size == 0:
        raise ValueError("no free cell qualifies as a viewpoint (check region and clearance)")
    pick = gen.choice(xs.size, size=n, replace=n > xs.size)
    return np.stack([xs[pick], ys[pick]], axis=1).astype(float)


def trajectory(
    world: OccupancyGrid,
    length: int,
    *,
    rng: RngLike,
    start=None,
    step: float = 4.0,
    clearance: float = 4.0,
) -> np.ndarray:
    """A random walk through the free space of a map.

    The walker keeps a heading that drifts at random and turns away from obstacles; every
    segment between consecutive positions stays at least ``clearance`` cells from any
    cell that is not free.

    Parameters
    ----------
    world : OccupancyGrid
        The map.
    length : int
        Number of positions.
    rng : int or numpy.random.Generator
        Source of the random walk.
    start : (2,) array_like of float, optional
        First position ``(x, y)``, pixels; by default a random free cell.
    step : float, optional
        Distance between consecutive positions, cells.
    clearance : float, optional
        Minimum distance, in cells, from any cell that is not free.

    Returns
    -------
    (length, 2) float array
        Positions ``(x = column, y = row)``.

    Examples
    --------
    >>> import numpy as np
    >>> from gridmerge.grid import OccupancyGrid
    >>> from gridmerge.samples import trajectory
    >>> path = trajectory(OccupancyGrid(np.zeros((50, 50))), 20, rng=1)
    >>> path.shape, bool((np.hypot(*np.diff(path, axis=0).T) <= 4.0 + 1e-9).all())
    ((20, 2), True)
    """
    gen = np.random.default_rng(rng)
    length = int(length)
    if length <= 0:
        return np.zeros((0, 2))
    ok = _clear_free(world, clearance)
    H, W = world.shape
    if start is None:
        pos = random_viewpoints(world, 1, rng=gen, clearance=clearance)[0]
    else:
        pos = np.asarray(start, dtype=float).reshape(2)
    path = np.empty((length, 2))
    path[0] = pos
    heading = gen.uniform(0, 2 * np.pi)
    samples = np.linspace(0.0, 1.0, max(2, int(math.ceil(step * 2)) + 1))[1:]

    def free_segment(p: np.ndarray, q: np.ndarray) -> bool:
        pts = p + (q - p) * samples[:, None]
        c = np.rint(pts).astype(int)
        if (c[:, 0] < 0).any() or (c[:, 0] >= W).any() or (c[:, 1] < 0).any() or (c[:, 1] >= H).any():
            return False
        return bool(ok[c[:, 1], c[:, 0]].all())

    for k in range(1, length):
        heading += gen.normal(0.0, 0.25)
        moved = False
        for attempt in range(24):
            h = heading if attempt == 0 else heading + gen.normal(0.0, 0.4 + 0.15 * attempt)
            q = pos + step * np.array([math.cos(h), math.sin(h)])
            if free_segment(pos, q):
                pos, heading, moved = q, h, True
                break
        if not moved:
            heading += np.pi  # dead end: turn around, stay here for this step
        path[k] = pos
    return path


# ------------------------------------------------------------------------ warping
def warp(
    grid: OccupancyGrid,
    matrix,
    out_shape: Sequence[int],
    *,
    interpolation: str = "linear",
    resolution: Optional[float] = None,
    name: Optional[str] = None,
) -> OccupancyGrid:
    """The map another robot would have of ``grid``'s area, in its own pixel frame.

    ``out(p) = grid(matrix @ [p, 1])``: ``matrix`` maps output pixels to input pixels (as
    ``cv2.warpAffine`` with ``WARP_INVERSE_MAP``). Unknown cells are carried correctly: the
    known mask and the values (0 where unknown) are warped separately with a zero border;
    an output cell is known where the warped mask is at least 0.5, and its value is the
    warped value divided by the warped mask (so unknown neighbours do not dilute it).
    Quarter turns, mirrorings and whole-cell shifts copy the cells exactly
    (:func:`gridmerge.fuse.reindexed`).

    Parameters
    ----------
    grid : OccupancyGrid
        The map to warp.
    matrix : (2, 3) or (3, 3) array_like
        Affine transform from output pixels ``(x, y)`` to input pixels.
    out_shape : (int, int)
        ``(H, W)`` of the output.
    interpolation : {"linear", "nearest"}, optional
        Interpolation of the values and of the known mask.
    resolution : float, optional
        Cell size of the output (default: ``grid.resolution``).
    name : str, optional
        Name of the output.

    Returns
    -------
    OccupancyGrid
        With origin ``(0, 0, 0)``.

    Examples
    --------
    >>> import numpy as np
    >>> from gridmerge.grid import OccupancyGrid
    >>> from gridmerge.samples import warp
    >>> g = OccupancyGrid(np.array([[0.0, 1.0, np.nan]]))
    >>> warp(g, [[1, 0, 1], [0, 1, 0]], (1, 3)).data.tolist()  # out(x) = g(x + 1)
    [[1.0, nan, nan]]
    """
    M = np.asarray(matrix, dtype=float)
    if M.shape == (3, 3):
        if not np.allclose(M[2], [0.0, 0.0, 1.0]):
            raise ValueError("a (3, 3) matrix must be affine (last row 0, 0, 1)")
        M = M[:2]
    if M.shape != (2, 3) or not np.isfinite(M).all():
        raise ValueError(f"matrix must be a finite (2, 3) or (3, 3) affine matrix, got shape {M.shape}")
    H, W = _check_shape(out_shape, 1)
    flags = {"linear": cv2.INTER_LINEAR, "nearest": cv2.INTER_NEAREST}.get(interpolation)
    if flags is None:
        raise ValueError(f"interpolation must be 'linear' or 'nearest', got {interpolation!r}")
    res = grid.resolution if resolution is None else resolution
    moved = reindexed(grid.data, M, (H, W))
    if moved is not None:  # quarter turns, mirrorings, whole-cell shifts: cell for cell
        return OccupancyGrid(moved, resolution=res, origin=(0.0, 0.0, 0.0), name=name)
    known = grid.known.astype(np.float32)
    values = np.nan_to_num(grid.data, nan=0.0).astype(np.float32) * known
    kw = dict(flags=flags | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    wk = cv2.warpAffine(known, M, (W, H), **kw)
    wv = cv2.warpAffine(values, M, (W, H), **kw)
    out = np.full((H, W), np.nan, dtype=np.float32)
    ok = wk >= 0.5
    out[ok] = np.clip(wv[ok] / wk[ok], 0.0, 1.0)
    return OccupancyGrid(out, resolution=res, origin=(0.0, 0.0, 0.0), name=name)


# -------------------------------------------------------------------------- pairs
def _similarity(theta: float, scale: float, tx: float, ty: float) -> np.ndarray:
    c, s = scale * math.cos(theta), scale * math.sin(theta)
    return np.array([[c, -s, tx], [s, c, ty], [0.0, 0.0, 1.0]])


def table1_pair(seed: int = 0) -> tuple[OccupancyGrid, OccupancyGrid, np.ndarray]:
    """The paper's Table I experiment: a map and the same map in a rotated, scaled frame.

    Map ``a`` is ``building(seed)`` (480 x 640 cells). Map ``b`` is ``a`` seen through the
    similarity ``truth`` with rotation 30 degrees, translation ``(dx, dy) = (-86, -36)``
    pixels and scale 0.95, which maps ``b`` pixels to ``a`` pixels::

        truth = [[0.95 cos 30, -0.95 sin 30, -86],
                 [0.95 sin 30,  0.95 cos 30, -36],
                 [0,            0,             1]]

    ``b = warp(a, truth[:2], (280, 860))`` (bilinear). The rotation is about ``b``'s
    top-left corner, which lands outside ``a`` at ``(-86, -36)``, and ``b``'s y axis
    points down-left in ``a``, so a tall canvas would mostly show the outside of ``a``.
    The 280 x 860 canvas is the one that holds the largest part of ``a`` (about half of
    its known cells) while 70 % of ``b``'s cells still fall on ``a``'s canvas; half to
    two thirds of ``b``'s cells are known, depending on the building's outline. One ``b`` cell is 0.95 ``a`` cells, so ``b.resolution`` is
    ``0.95 * a.resolution``.

    Parameters
    ----------
    seed : int, optional
        Seed of the building.

    Returns
    -------
    a, b : OccupancyGrid
    truth : (3, 3) float array
        Maps homogeneous ``b`` pixels to ``a`` pixels.

    Examples
    --------
    >>> from gridmerge.samples import table1_pair
    >>> a, b, truth = table1_pair(0)
    >>> a.shape, b.shape, truth[:2, 2].tolist()
    ((480, 640), (280, 860), [-86.0, -36.0])
    """
    a = building(seed)
    theta = math.radians(TABLE1_THETA_DEG)
    truth = _similarity(theta, TABLE1_SCALE, *TABLE1_TRANSLATION)
    b = warp(a, truth[:2], TABLE1_B_SHAPE, resolution=a.resolution * TABLE1_SCALE, name=f"table1 b (seed={seed})")
    a = a.replace(name=f"table1 a (seed={seed})")
    return a, b, truth


def _crop_known(grid: OccupancyGrid, margins: np.ndarray) -> tuple[OccupancyGrid, int, int]:
    """Crop to the known cells plus ``margins`` (left, top, right, bottom), keeping the frame."""
    ys, xs = np.nonzero(grid.known)
    H, W = grid.shape
    c0 = max(int(xs.min()) - int(margins[0]), 0)
    r0 = max(int(ys.min()) - int(margins[1]), 0)
    c1 = min(int(xs.max()) + 1 + int(margins[2]), W)
    r1 = min(int(ys.max()) + 1 + int(margins[3]), H)
    # The crop's lower-left corner, in the grid's metric frame, is its new origin.
    corner = grid.pixel_to_metric([[c0 - 0.5, r1 - 0.5]])[0]
    origin = (float(corner[0]), float(corner[1]), grid.origin[2])
    return grid.replace(data=grid.data[r0:r1, c0:c1], origin=origin), c0, r0


def _robot_map(world: OccupancyGrid, region: np.ndarray, rng: np.random.Generator) -> OccupancyGrid:
    n_free = int((world.free() & region).sum())
    n = max(8, int(round(n_free / 2500.0)))
    vps = random_viewpoints(world, n, rng=rng, region=region, clearance=5.0)
    return explore(world, vps, rng=rng)


def _halves(world: OccupancyGrid, overlap: float) -> tuple[np.ndarray, np.ndarray]:
    """Two regions of the building along its longer side sharing ``overlap`` of it."""
    ys, xs = np.nonzero(world.known)
    H, W = world.shape
    if xs.max() - xs.min() >= ys.max() - ys.min():
        lo, hi, coord = xs.min(), xs.max(), np.broadcast_to(np.arange(W)[None, :], (H, W))
    else:
        lo, hi, coord = ys.min(), ys.max(), np.broadcast_to(np.arange(H)[:, None], (H, W))
    f = (1.0 + overlap) / 2.0
    return coord <= lo + f * (hi - lo), coord >= hi - f * (hi - lo)


def _make_pair(
    world_a: OccupancyGrid,
    world_b: OccupancyGrid,
    rng: np.random.Generator,
    overlap: float,
    rotation_deg: Optional[float],
    scale: Optional[float],
    names: tuple[str, str],
) -> tuple[OccupancyGrid, OccupancyGrid, np.ndarray]:
    region_a, _ = _halves(world_a, overlap)
    _, region_b = _halves(world_b, overlap)
    a_full = _robot_map(world_a, region_a, rng)
    b_full = _robot_map(world_b, region_b, rng)
    a, c0, r0 = _crop_known(a_full, rng.integers(5, 21, size=4))
    a = a.replace(name=names[0])

    theta = rng.uniform(-math.pi, math.pi) if rotation_deg is None else math.radians(float(rotation_deg))
    s = math.exp(rng.uniform(math.log(0.8), math.log(1.25))) if scale is None else float(scale)
    if not (math.isfinite(s) and s > 0):
        raise ValueError(f"scale must be > 0, got {scale!r}")
    A = _similarity(theta, s, 0.0, 0.0)[:2, :2]  # b pixels -> world pixels (linear part)
    ys, xs = np.nonzero(b_full.known)
    q = np.stack([xs, ys], axis=1).astype(float) @ np.linalg.inv(A).T
    qmin, qmax = q.min(axis=0), q.max(axis=0)
    m = rng.integers(5, 21, size=4).astype(float)  # margins left, top, right, bottom
    t = A @ (qmin - m[:2])
    out_shape = (int(math.ceil(qmax[1] - qmin[1] + m[1] + m[3])) + 1, int(math.ceil(qmax[0] - qmin[0] + m[0] + m[2])) + 1)
    b_to_world = np.vstack([np.hstack([A, t[:, None]]), [0.0, 0.0, 1.0]])
    b = warp(b_full, b_to_world[:2], out_shape, resolution=b_full.resolution * s, name=names[1])
    world_to_a = np.array([[1.0, 0.0, -c0], [0.0, 1.0, -r0], [0.0, 0.0, 1.0]])
    return a, b, world_to_a @ b_to_world


def robot_pair(
    seed: int = 0,
    *,
    overlap: float = 0.5,
    rotation_deg: Optional[float] = None,
    scale: Optional[float] = None,
    shape: Sequence[int] = (480, 640),
) -> tuple[OccupancyGrid, OccupancyGrid, np.ndarray]:
    """Maps of two robots that explored overlapping parts of one building.

    The building is ``building(seed, shape)``. Along its longer side it is cut into two
    regions that share a band of ``overlap`` times its length (``overlap = 0.5``: the
    first 75 % and the last 75 %). Each robot scans from random viewpoints in its region
    (about one per 2500 free cells, at least 8) with :func:`explore`; the scans reach
    beyond the region through doors and open space, so the maps share more than the band.
    Robot ``a`` maps in the building's frame; its map is cropped to its known cells plus
    5-20 cells of unknown margin, and ``a.origin`` is set so that ``a.pixel_to_metric``
    still gives the building's metric coordinates. Robot ``b``'s map is rotated, scaled
    and shifted into its own frame with :func:`warp` (bilinear) and cropped the same way;
    ``b.resolution`` is the building's times the scale, ``b.origin`` is ``(0, 0, 0)``.

    Parameters
    ----------
    seed : int, optional
        Seed of the building, the viewpoints and the transform.
    overlap : float, optional
        In ``[0, 1]``: the share of the building's length both robots' regions cover.
    rotation_deg : float, optional
        Rotation of ``b``'s frame, degrees (default: uniform in ``[-180, 180)``).
    scale : float, optional
        Scale of the transform (``b`` pixels to ``a`` pixels) (default: log-uniform in
        ``[0.8, 1.25]``).
    shape : (int, int), optional
        Shape of the building's map.

    Returns
    -------
    a, b : OccupancyGrid
    truth : (3, 3) float array
        Similarity that maps homogeneous ``b`` pixels to ``a`` pixels; its linear part is
        ``scale`` times a rotation by ``rotation_deg``.

    Examples
    --------
    >>> import numpy as np
    >>> from gridmerge.samples import robot_pair
    >>> a, b, truth = robot_pair(1, rotation_deg=90, scale=1.0, shape=(200, 260))
    >>> np.round(truth[:2, :2], 6).tolist()
    [[0.0, -1.0], [1.0, 0.0]]
    """
    overlap = float(overlap)
    if not 0.0 <= overlap <= 1.0:
        raise ValueError(f"overlap must be in [0, 1], got {overlap!r}")
    rng = np.random.default_rng([int(seed), 1])
    world = building(seed, shape)
    return _make_pair(world, world, rng, overlap, rotation_deg, scale, (f"robot a (seed={seed})", f"robot b (seed={seed})"))


def negative_pair(seed: int = 0, *, shape: Sequence[int] = (480, 640)) -> tuple[OccupancyGrid, OccupancyGrid]:
    """Maps of two different buildings: a pair that must not be merged.

    Map ``a`` is made as in :func:`robot_pair` from ``building(seed)``, map ``b`` from
    ``building(seed + 1)`` (random rotation and scale).

    Parameters
    ----------
    seed : int, optional
        Seed of the first building.
    shape : (int, int), optional
        Shape of the buildings' maps.

    Returns
    -------
    a, b : OccupancyGrid

    Examples
    --------
    >>> from gridmerge.samples import negative_pair
    >>> a, b = negative_pair(0, shape=(200, 260))
    >>> bool(a.known.any() and b.known.any())
    True
    """
    rng = np.random.default_rng([int(seed), 2])
    wa = building(seed, shape)
    wb = building(int(seed) + 1, shape)
    a, b, _ = _make_pair(wa, wb, rng, 0.5, None, None, (f"negative a (seed={seed})", f"negative b (seed={seed + 1})"))
    return a, b


#: The sample pairs :func:`write_sample` can write.
SAMPLE_KINDS = ("robots", "table1", "different", "fleet")

#: Robots of the ``"fleet"`` sample.
FLEET_ROBOTS = 8


def write_sample(folder, kind: str = "robots", seed: int = 0) -> dict:
    """Write a sample pair of maps as map_server files, for trying the command line.

    Writes ``a.yaml``/``a.pgm`` and ``b.yaml``/``b.pgm`` (and ``truth.json`` with the 3x3
    matrix mapping b's pixels to a's, except for ``"different"``) into ``folder``, which
    must exist. The ``"fleet"`` sample is eight robots' maps of one building
    (``robot1.yaml`` ... ``robot8.yaml``), a robot's map of another building
    (``stranger.yaml``), the same nine maps as ``nav_msgs/OccupancyGrid`` messages on
    topics ``/robot1/map`` ... ``/stranger/map`` of a ROS 1 bag (``fleet.bag``), and
    ``truth.json`` (each robot's pixels -> the building's pixels).

    Parameters
    ----------
    folder : str or path-like
    kind : {"robots", "table1", "different", "fleet"}
        Two robots exploring one building (:func:`robot_pair`), the paper's Table I
        experiment (:func:`table1_pair`), maps of two different buildings
        (:func:`negative_pair`), or a fleet (:func:`gridmerge.bench.fleet.simulate_fleet`).
    seed : int

    Returns
    -------
    dict
        The paths written, by role (``"a"``, ``"b"``, ``"truth"``; for a fleet the robots'
        names, ``"stranger"``, ``"bag"``, ``"truth"``).
    """
    import json
    from pathlib import Path

    from .io import atomic_write, save_map

    folder = Path(folder)
    if kind == "fleet":
        return _write_fleet(folder, seed)
    if kind == "robots":
        a, b, truth = robot_pair(seed)
    elif kind == "table1":
        a, b, truth = table1_pair(seed)
    elif kind == "different":
        (a, b), truth = negative_pair(seed), None
    else:
        raise ValueError(f"unknown sample kind {kind!r} (use one of {', '.join(SAMPLE_KINDS)})")
    out = {"a": save_map(a, folder / "a.yaml"), "b": save_map(b, folder / "b.yaml")}
    if truth is not None:
        out["truth"] = folder / "truth.json"
        atomic_write(out["truth"], (json.dumps({"b_to_a": np.asarray(truth).tolist()}) + "\n").encode())
    return out


def sample_outputs(kind: str) -> list:
    """File names :func:`write_sample` writes for ``kind`` (so callers can check them first)."""
    if kind == "fleet":
        names = [f"robot{k}" for k in range(1, FLEET_ROBOTS + 1)] + ["stranger"]
        return [f"{n}.{ext}" for n in names for ext in ("yaml", "pgm")] + ["fleet.bag", "truth.json"]
    return ["a.yaml", "a.pgm", "b.yaml", "b.pgm"] + ([] if kind == "different" else ["truth.json"])


def _write_fleet(folder, seed: int) -> dict:
    import json

    from .bench.fleet import simulate_fleet
    from .io import atomic_write, save_map
    from .io.bags import write_map_messages

    fleet = simulate_fleet(FLEET_ROBOTS, seed=seed)
    stranger = simulate_fleet(1, seed=seed + 5, shape=(500, 700)).maps[0].replace(name="stranger")
    out: dict = {}
    maps = list(fleet.maps) + [stranger]
    for m in maps:
        out[m.name] = save_map(m, folder / f"{m.name}.yaml")
    stamp = 1_700_000_000 * 10**9
    out["bag"] = write_map_messages(
        folder / "fleet.bag", [(f"/{m.name}/map", m, stamp + k) for k, m in enumerate(maps)], format="ros1", overwrite=True
    )
    out["truth"] = folder / "truth.json"
    truth = {m.name: np.asarray(t).tolist() for m, t in zip(fleet.maps, fleet.to_source)}
    atomic_write(out["truth"], (json.dumps({"to_building": truth}) + "\n").encode())
    return out

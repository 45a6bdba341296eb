"""Benchmark cases: pairs of maps with their ground truth (or none, for negatives).

Four data sets:

:func:`simulated`
    Two robots explore overlapping parts of a source map (a real map of the shared data,
    or a procedural building): each one only maps what its laser sees from random
    free-space viewpoints (ray casting, :func:`gridmerge.samples.explore`). Robot b maps
    in its own frame: any rotation, any shift, and another resolution (b's ``resolution``
    is the source's times the scale). The ground truth is exact. Cases come in tiers of
    difficulty (:data:`TIERS`), and a share of them are *negative* pairs, maps of two
    different places that a method must decline.
:func:`halmstad`
    The annotated real pairs of the Halmstad data set (``../shared/data/halmstad``),
    scored with the data set's own protocol (see :mod:`gridmerge.bench.metrics`).
:func:`halmstad_partial`
    Two robots that explored part of a building each, in two real maps of it (Halmstad
    sessions of one building, aligned by the annotations): small overlaps of maps that
    bend and differ, scored with the Halmstad protocol on the annotated points in the
    overlap, and negative pairs of two distant parts.
:func:`paper`
    The paper's Table I experiment (:func:`gridmerge.samples.table1_pair`), with the
    paper's own estimate in ``meta`` for the report.

Every data set is a :class:`Dataset`: a sized, re-iterable sequence whose cases are built
on demand (real maps are large; a run never holds more than one case), each from its own
seed, so that ``simulated(n=10, seed=s)`` is the first ten cases of ``simulated(n=60,
seed=s)`` and the same seed always gives the same cases.

Examples
--------
>>> from gridmerge.bench import datasets
>>> ds = datasets.paper()
>>> case = ds[0]
>>> case.id, case.positive, case.truth.shape
('paper/table1-seed0', True, (3, 3))
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Callable, Iterator, Optional, Sequence

import cv2
import numpy as np

from .. import samples
from ..errors import GridMergeError
from ..grid import OccupancyGrid
from ..io import load_map
from ..transforms import AffineTransform

__all__ = [
    "Case",
    "Dataset",
    "Tier",
    "TIERS",
    "SEE_THROUGH",
    "DATASETS",
    "SEEDED",
    "PAPER_TABLE1",
    "default_data_dir",
    "resolve_data_dir",
    "simulated",
    "halmstad",
    "halmstad_environments",
    "halmstad_partial",
    "PARTIAL_RADIUS",
    "PARTIAL_POINTS",
    "check_name",
    "paper",
    "load",
    "measure_overlap",
    "shared_walls",
    "unswapped",
    "robot_views_pair",
    "source_map",
    "source_names",
    "swapped",
]

#: Names of the data sets :func:`load` knows.
DATASETS = ("simulated", "halmstad", "halmstad-partial", "paper")

#: The data sets whose cases are drawn from a seed, ``n`` of them (the others are fixed
#: sets of pairs): a case id names another pair under another seed.
SEEDED = ("simulated", "halmstad-partial")

#: The paper's Table I: the true transform and the paper's estimate of it
#: (rotation degrees, translation x and y in pixels, scale).
PAPER_TABLE1 = {
    "truth": {"rotation_deg": 30.0, "x": -86.0, "y": -36.0, "scale": 0.95},
    "paper": {"rotation_deg": 29.91, "x": -85.79, "y": -36.11, "scale": 0.9503},
}

#: The Halmstad sensor maps :func:`simulated` draws from (a fixed list, so that a seed
#: gives the same cases whatever else the data folder holds; :func:`halmstad` reads every
#: environment there).
_HALMSTAD_ENVIRONMENTS = {"E5": 14, "HIH": 4}


# ------------------------------------------------------------------ data folder
def default_data_dir() -> Path:
    """``../shared/data`` next to the project root (``src/gridmerge/bench`` -> root)."""
    return Path(__file__).resolve().parents[3].parent / "shared" / "data"


def resolve_data_dir(data_dir=None) -> Optional[Path]:
    """The shared data folder to use, or ``None`` when there is none.

    An explicit ``data_dir`` must exist (:class:`GridMergeError` otherwise); without one,
    :func:`default_data_dir` is used when it exists.
    """
    if data_dir is not None:
        p = Path(data_dir)
        if not p.is_dir():
            raise GridMergeError(f"data folder not found: {p}")
        return p
    p = default_data_dir()
    return p if p.is_dir() else None


# ------------------------------------------------------------------------ cases
@dataclass
class Case:
    """One benchmark pair.

    Attributes
    ----------
    id : str
        Unique within a run, e.g. ``"simulated/0007"``.
    dataset : str
        ``"simulated"``, ``"halmstad"``, ``"halmstad-layout"`` or ``"paper"``.
    a, b : OccupancyGrid
        The reference map and the map to align onto it.
    truth : (3, 3) float array or None
        Maps b's pixels to a's pixels; ``None`` for negative pairs. For the Halmstad pairs
        it is the least-median fit to the annotated points (informative only: those pairs
        are scored on the points).
    positive : bool
        ``False``: the maps show different places and must not be merged.
    meta : dict
        JSON-ready description: ``tier``, ``overlap``, ``rotation_deg``, ``scale``,
        ``noise``, ``source`` ... (see the generators).
    """

    id: str
    dataset: str
    a: OccupancyGrid
    b: OccupancyGrid
    truth: Optional[np.ndarray]
    positive: bool
    meta: dict = field(default_factory=dict)

    @property
    def tier(self) -> str:
        return str(self.meta.get("tier", "all"))

    def describe(self) -> dict:
        """A JSON-ready summary (no cell data)."""
        return {
            "id": self.id,
            "dataset": self.dataset,
            "positive": bool(self.positive),
            "a_shape": list(self.a.shape),
            "b_shape": list(self.b.shape),
            "truth": None if self.truth is None else np.asarray(self.truth, dtype=float).tolist(),
            "meta": self.meta,
        }


@dataclass
class Dataset:
    """A sized, re-iterable sequence of :class:`Case`, each built on demand.

    Attributes
    ----------
    name : str
    size : int
    build : callable
        ``build(k) -> Case``; deterministic.
    notes : list of str
        What a reader of the results should know (e.g. that the shared data was absent).
    params : dict
        How the cases were built, beyond their number and seed (e.g. :func:`simulated`'s
        ``see_through``); recorded in a run's ``config.json``.
    """

    name: str
    size: int
    build: Callable[[int], Case]
    notes: list = field(default_factory=list)
    params: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return self.size

    def __getitem__(self, k: int) -> Case:
        if not -self.size <= k < self.size:
            raise IndexError(k)
        return self.build(k % self.size)

    def __iter__(self) -> Iterator[Case]:
        for k in range(self.size):
            yield self.build(k)


# ---------------------------------------------------------------------- tiers
@dataclass(frozen=True)
class Tier:
    """Difficulty of simulated cases.

    Attributes
    ----------
    name : str
    overlap : (float, float)
        Range of the overlap fraction aimed at (see :func:`measure_overlap`).
    scale : (float, float)
        Range of the scale (b's cell size over a's), drawn log-uniformly.
    noise : float
        Sensor noise of both robots: each wall hit is missed with this probability, and
        each free cell turned into a spurious hit with probability ``noise / 50``.
    """

    name: str
    overlap: tuple
    scale: tuple
    noise: float


#: The tiers of :func:`simulated`. Rotation is uniform over the whole circle in every tier.
TIERS = {
    "easy": Tier("easy", (0.5, 0.8), (0.8, 1.25), 0.0),
    "medium": Tier("medium", (0.35, 0.5), (2 / 3, 1.5), 0.05),
    "hard": Tier("hard", (0.2, 0.35), (0.5, 2.0), 0.12),
}

#: Scanner range, in source cells (7.5 m at 0.05 m/cell).
RANGE_PX = 150.0
#: Consecutive unknown cells of a source map a scanner ray crosses
#: (:func:`gridmerge.samples.explore`). The real maps used as sources leave a band of
#: one or two unknown cells between the floor and many walls: of the floor cells at the
#: edge of the known area, 45-55 % border unknown cells only in the Halmstad E5 maps
#: (35-45 % in HIH, 89 % in Willow Garage), and 63-85 % of those have a wall within 3
#: cells (HIH 88-92 %, Willow Garage 50 %). A scanner in the building sees those walls. (Until 2026-11-30 rays stopped at the first unknown cell
#: (``see_through=0``): from the same positions, robots saw about 60 % of the wall
#: cells they see now in a Halmstad source, a quarter in Willow Garage.)
SEE_THROUGH = 2
_CLEARANCE = 5.0
_MIN_GAP = 20  # negative pairs of one source: cells between the two robots' maps


# --------------------------------------------------------------- source maps
def source_names(data_dir=None) -> list:
    """Source maps of :func:`simulated` available with the shared data (``[]`` without)."""
    d = resolve_data_dir(data_dir)
    if d is None:
        return []
    names = []
    if (d / "ros_maps" / "willow-full-0.05.pgm").is_file():
        names.append("willow")
    for env, count in _HALMSTAD_ENVIRONMENTS.items():
        for k in range(1, count + 1):
            if (d / "halmstad" / env / f"{env}_{k:02d}.png").is_file():
                names.append(f"halmstad:{env}_{k:02d}")
    return names


#: Prefix of a source map given by its file (:func:`file_source`).
FILE_PREFIX = "file:"


def file_source(path) -> str:
    """The source name of a map file (``"file:"`` + its absolute path), for
    :func:`simulated`'s ``source_maps``, :func:`source_map` and the fleet benchmark.

    Raises
    ------
    GridMergeError
        The file does not exist.
    """
    p = Path(path).expanduser()
    if not p.is_file():
        raise GridMergeError(f"source map not found: {path}")
    return FILE_PREFIX + str(p.resolve())


def source_map(name: str, data_dir=None) -> OccupancyGrid:
    """A source map of :func:`simulated` by name.

    ``"willow"`` (the Willow Garage SLAM map), ``"halmstad:E5_03"`` (a Halmstad sensor
    map, cut to its known cells plus 8 cells), ``"building:SEED:HxW"`` (a procedural
    building, :func:`gridmerge.samples.building`), ``"file:PATH"`` (any map
    :func:`gridmerge.load_map` reads, cut to its known cells plus 8 cells; see
    :func:`file_source`).
    """
    d = resolve_data_dir(data_dir)
    return _source_map(name, None if d is None else str(d))


@lru_cache(maxsize=4)
def _source_map(name: str, data_dir: Optional[str]) -> OccupancyGrid:
    if name.startswith("building:"):
        _, seed, shape = name.split(":")
        h, w = (int(v) for v in shape.split("x"))
        return samples.building(int(seed), (h, w))
    if name.startswith(FILE_PREFIX):
        g = load_map(name[len(FILE_PREFIX):])
        if not g.known.any():
            raise GridMergeError(f"source map {name[len(FILE_PREFIX):]} has no known cells")
        return g.crop_known(8)[0]
    if data_dir is None:
        raise GridMergeError(f"source map {name!r} needs the shared data folder")
    d = Path(data_dir)
    if name == "willow":
        return load_map(d / "ros_maps" / "willow-full-0.05.pgm")
    if name.startswith("halmstad:"):
        stem = name.split(":", 1)[1]
        env = stem.split("_")[0]
        g = load_map(d / "halmstad" / env / f"{stem}.png")
        return g.crop_known(8)[0]
    raise GridMergeError(f"unknown source map {name!r}")


# ------------------------------------------------------------ geometry helpers
def measure_overlap(known_a: np.ndarray, known_b: np.ndarray) -> float:
    """Fraction of the smaller map's known cells that are known in both.

    Both masks are in one frame (the source map's, for :func:`simulated`).

    >>> import numpy as np
    >>> a = np.zeros((4, 4), bool); a[:, :2] = True
    >>> b = np.zeros((4, 4), bool); b[:, 1:] = True
    >>> measure_overlap(a, b)
    0.5
    """
    na, nb = int(known_a.sum()), int(known_b.sum())
    if min(na, nb) == 0:
        return 0.0
    return float((known_a & known_b).sum()) / min(na, nb)


def shared_walls(world_a: np.ndarray, world_b: np.ndarray) -> int:
    """Cells that two robots' maps of one world, in the world's frame, both hold as walls.

    The structure an alignment can rest on: the overlap of the known cells
    (:func:`measure_overlap`) counts open floor too, which fixes no pose. ``world_a``
    and ``world_b`` are occupancy arrays of the world's shape (occupied above 0.5,
    unknown NaN).

    >>> a = np.full((4, 4), np.nan); b = np.full((4, 4), np.nan)
    >>> a[0, :] = 1.0; b[0, 2:] = 1.0; b[1, :] = 0.0
    >>> shared_walls(a, b)
    2
    """
    with np.errstate(invalid="ignore"):
        return int(((world_a > 0.5) & (world_b > 0.5)).sum())


def _similarity(theta: float, scale: float, tx: float = 0.0, ty: float = 0.0) -> np.ndarray:
    c, s = scale * math.cos(theta), scale * math.sin(theta)
    return np.array([[c, -s, tx], [s, c, ty], [0.0, 0.0, 1.0]])


def _shift(x: float, y: float) -> np.ndarray:
    return np.array([[1.0, 0.0, x], [0.0, 1.0, y], [0.0, 0.0, 1.0]])


class _World:
    """A source map prepared for ray casting: where a robot can stand, what it sees."""

    def __init__(self, grid: OccupancyGrid, name: str, see_through: int = SEE_THROUGH):
        self.grid = grid
        self.name = name
        self.see_through = int(see_through)
        H, W = grid.shape
        free = grid.free().astype(np.uint8)
        dist = cv2.distanceTransform(np.pad(free, 1), cv2.DIST_L2, 5)[1:-1, 1:-1]
        clear = (dist >= _CLEARANCE).astype(np.uint8)
        count, labels, stats, _ = cv2.connectedComponentsWithStats(clear, connectivity=4)
        if count <= 1:
            raise GridMergeError(f"source map {name} has no free space for a robot")
        main = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        self.region = labels == main
        self.area = int(stats[main, cv2.CC_STAT_AREA])
        self._views: dict = {}

    def viewpoints(self, rng: np.random.Generator) -> np.ndarray:
        k = int(np.clip(round(self.area / 4000.0), 16, 100))
        return samples.random_viewpoints(self.grid, k, rng=rng, region=self.region, clearance=_CLEARANCE)

    def view(self, vp) -> tuple[np.ndarray, np.ndarray]:
        """Flat indices of the cells seen free and seen occupied from one viewpoint."""
        key = (float(vp[0]), float(vp[1]))
        if key not in self._views:
            H, W = self.grid.shape
            r = int(math.ceil(RANGE_PX)) + 2
            x, y = int(round(vp[0])), int(round(vp[1]))
            x0, x1 = max(0, x - r), min(W, x + r + 1)
            y0, y1 = max(0, y - r), min(H, y + r + 1)
            sub = OccupancyGrid(self.grid.data[y0:y1, x0:x1], resolution=self.grid.resolution)
            seen = samples.explore(sub, [[vp[0] - x0, vp[1] - y0]], max_range_px=RANGE_PX, see_through=self.see_through)
            yy, xx = np.nonzero(~np.isnan(seen.data))
            occ = seen.data[yy, xx] > 0.5
            flat = (yy + y0).astype(np.int64) * W + (xx + x0)
            self._views[key] = (flat[~occ], flat[occ])
        return self._views[key]

    def known(self, vps) -> np.ndarray:
        H, W = self.grid.shape
        m = np.zeros(H * W, dtype=bool)
        for vp in vps:
            f, o = self.view(vp)
            m[f] = True
            m[o] = True
        return m.reshape(H, W)

    def seen(self, vps, thick: int = 0) -> np.ndarray:
        """What a robot maps from ``vps``: free 0, occupied 1, unknown NaN (source frame).

        ``thick``: a wall keeps the source's wall cells up to that many cells behind the
        face the scanner hit (a real map's walls as thick as its sensor drew them); 0,
        the face only.
        """
        H, W = self.grid.shape
        out = np.full(H * W, np.nan, dtype=np.float32)
        for vp in vps:
            f, o = self.view(vp)
            out[f] = 0.0
            out[o] = 1.0
        out = out.reshape(H, W)
        if thick > 0:
            with np.errstate(invalid="ignore"):
                hit = (out > 0.5).astype(np.uint8)
                wall = self.grid.data > 0.5
            kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * thick + 1, 2 * thick + 1))
            out[(cv2.dilate(hit, kernel) > 0) & wall] = 1.0
        return out


def _add_noise(data: np.ndarray, noise: float, rng: np.random.Generator) -> np.ndarray:
    """Missed hits (wall cells left unknown) and spurious hits (free cells marked occupied)."""
    out = data.copy()
    if noise <= 0:
        return out
    with np.errstate(invalid="ignore"):
        hit = np.flatnonzero(out.ravel() > 0.5)
        free = np.flatnonzero(out.ravel() < 0.5)
    flat = out.reshape(-1)
    flat[hit[rng.random(hit.size) < noise]] = np.nan
    flat[free[rng.random(free.size) < noise / 50.0]] = 1.0
    return out


def _observed_in_frame(seen: np.ndarray, M: np.ndarray, shape: tuple, scale: float) -> np.ndarray:
    """What a robot observed (``seen``, the world's cells: free 0, occupied 1, unknown
    NaN), as its own map with cells ``scale`` times the world's, in its frame.

    ``M`` maps the robot's pixels to the world's. The robot ray-casts at the world's
    resolution, as robot a does, and its map keeps a wall where the centre of an
    observed wall cell is: a coarser cell is occupied when it holds one, a finer cell
    when its centre lies in one. A cell is free when its centre lies in an observed free
    cell (and it holds no wall), unknown otherwise. Robot b's walls are then where
    robot a's are, whatever the resolution: the true transform is the best fit of the
    two maps.

    (Until 2026-11-29, the robot ray-cast the world carried into its frame at its own
    resolution. A coarser robot's walls lay half a world cell nearer the scanner, later
    0.3-0.4 cells, and a perfect aligner was off by up to 0.6 % in scale, 1-6 px at b's
    corners.)
    """
    H, W = shape
    with np.errstate(invalid="ignore"):
        occ = (seen > 0.5).astype(np.uint8)
        free = (seen < 0.5).astype(np.uint8)
    kw = dict(flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    M2 = np.ascontiguousarray(M[:2])
    f_out = cv2.warpAffine(free, M2, (W, H), **kw) > 0
    if scale <= 1.0:
        o_out = cv2.warpAffine(occ, M2, (W, H), **kw) > 0
    else:
        ys, xs = np.nonzero(occ)
        p = np.stack([xs, ys], axis=1).astype(np.float64)
        Minv = np.linalg.inv(M)
        q = np.rint(p @ Minv[:2, :2].T + Minv[:2, 2]).astype(np.int64)
        ok = (q[:, 0] >= 0) & (q[:, 0] < W) & (q[:, 1] >= 0) & (q[:, 1] < H)
        o_out = np.zeros((H, W), dtype=bool)
        o_out[q[ok, 1], q[ok, 0]] = True
    data = np.full((H, W), np.nan, dtype=np.float32)
    data[f_out] = 0.0
    data[o_out] = 1.0
    return data


def _crop_box(known: np.ndarray, margins) -> tuple[int, int, int, int]:
    ys, xs = np.nonzero(known)
    H, W = known.shape
    x0 = max(int(xs.min()) - int(margins[0]), 0)
    y0 = max(int(ys.min()) - int(margins[1]), 0)
    x1 = min(int(xs.max()) + 1 + int(margins[2]), W)
    y1 = min(int(ys.max()) + 1 + int(margins[3]), H)
    return x0, y0, x1, y1


#: Wavelengths (source cells) of the smooth waves that bend a map (:func:`bent`).
BEND_WAVELENGTHS = (400.0, 900.0)


def bent(seen: np.ndarray, bend: float, rng: np.random.Generator) -> np.ndarray:
    """``seen`` (a robot's observations in the source's cells: free 0, occupied 1,
    unknown NaN) bent as a SLAM map bends against another session's: each cell shows
    what lies up to ``bend`` cells away, along a smooth displacement field (for each
    axis, three plane waves of random direction, phase and wavelength in
    :data:`BEND_WAVELENGTHS`, scaled so that the largest displacement is ``bend``;
    nearest cell). The map's shape and resolution do not change, so the rigid
    transform stays the truth, which the bent map no longer fits exactly: Halmstad's
    Tango maps, hand-matched, leave 5-15 px of residual on 1585 x 1585 cells.

    Examples
    --------
    >>> import numpy as np
    >>> seen = np.full((200, 300), np.nan, np.float32); seen[50:150, 50:250] = 0.0; seen[100, 50:250] = 1.0
    >>> b = bent(seen, 3.0, np.random.default_rng(0))
    >>> b.shape == seen.shape and bool(np.all(np.isnan(b[:40])))  # far from what was seen: unknown
    True
    >>> rows = np.nonzero(np.nanmax(np.nan_to_num(b, nan=0.0), axis=1) > 0.5)[0]
    >>> bool(rows.min() >= 97 and rows.max() <= 103)  # the wall moved by 3 cells at most
    True
    """
    h, w = seen.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    maps = []
    for base in (xx, yy):
        d = np.zeros((h, w), np.float32)
        for _ in range(3):
            lam = rng.uniform(*BEND_WAVELENGTHS)
            ang, ph = rng.uniform(0.0, 2.0 * math.pi, size=2)
            d += np.sin(2.0 * math.pi * (xx * math.cos(ang) + yy * math.sin(ang)) / lam + ph).astype(np.float32)
        top = float(np.abs(d).max())
        maps.append(base + d * np.float32(bend / top) if top > 0 else base)
    return cv2.remap(np.ascontiguousarray(seen, dtype=np.float32), maps[0], maps[1], cv2.INTER_NEAREST,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))


def _robot_in_frame(wb: _World, vps_b, rng: np.random.Generator, *, rotation_deg: float, scale: float, noise: float,
                    thick: int = 0, bend: float = 0.0):
    """The map a robot makes of ``wb`` from ``vps_b`` in its own frame: rotated by
    ``rotation_deg``, shifted, cells ``scale`` times the source's, cropped, with noise;
    ``bend`` > 0: bent first (:func:`bent`; its field drawn from a generator spawned from
    ``rng``, so that ``rng``'s own draws are those of the unbent map).

    Returns ``b, M, known_b_in_source``: ``M`` maps the map's pixels to the source's
    (the rigid part: the truth).
    """
    theta = math.radians(rotation_deg)
    A = _similarity(theta, scale)
    kb_src = wb.known(vps_b)
    ys, xs = np.nonzero(kb_src)
    Ainv = np.linalg.inv(A)
    q = np.stack([xs, ys, np.ones_like(xs)], axis=0).astype(float)
    p = (Ainv @ q)[:2]
    pad = 25.0
    pmin = p.min(axis=1) - pad
    M = A @ _shift(pmin[0], pmin[1])  # b canvas pixels -> source pixels
    shape = (int(math.ceil(p[1].max() - pmin[1] + pad)) + 1, int(math.ceil(p[0].max() - pmin[0] + pad)) + 1)
    seen = wb.seen(vps_b, thick)
    if bend > 0:
        seen = bent(seen, bend, np.random.default_rng(rng.bit_generator.seed_seq.spawn(1)[0]))
    b_full = _observed_in_frame(seen, M, shape, scale)
    kb = ~np.isnan(b_full)
    bx0, by0, bx1, by1 = _crop_box(kb, rng.integers(5, 21, size=4))
    b_clean = b_full[by0:by1, bx0:bx1]
    M = M @ _shift(bx0, by0)
    b_data = _add_noise(b_clean, noise, rng)
    b = OccupancyGrid(b_data, resolution=wb.grid.resolution * scale)
    # b's known cells seen from the source's cells (nearest b cell of each source cell).
    Hs, Ws = wb.grid.shape
    kb_in_src = cv2.warpAffine(
        (~np.isnan(b_clean)).astype(np.uint8),
        np.ascontiguousarray(np.linalg.inv(M)[:2]),
        (Ws, Hs),
        flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    ) > 0
    return b, M, kb_in_src


def _robot_maps(
    world: _World,
    vps_a,
    vps_b,
    rng: np.random.Generator,
    *,
    rotation_deg: float,
    scale: float,
    noise: float,
    world_b: Optional[_World] = None,
    thick: int = 0,
    bend: float = 0.0,
):
    """Maps of robot a (the source's frame, cropped) and robot b (its own frame).

    Robot b explores ``world_b`` (default: ``world``); ``thick``: as :meth:`_World.seen`;
    ``bend``: b's map bent by up to that many source cells (:func:`bent`). Returns ``a, b, b_to_source,
    offset_a, known_b_in_source`` where ``b_to_source`` maps b's pixels to the pixels of
    its source map and ``offset_a`` is a's crop offset in ``world``.
    """
    wb = world if world_b is None else world_b
    src = world.grid
    # Robot a: the source's frame, cut to what it knows plus 5-20 unknown cells.
    a_clean = world.seen(vps_a, thick)
    ka = ~np.isnan(a_clean)
    x0, y0, x1, y1 = _crop_box(ka, rng.integers(5, 21, size=4))
    a_data = _add_noise(a_clean[y0:y1, x0:x1], noise, rng)
    corner = src.pixel_to_metric([[x0 - 0.5, y1 - 0.5]])[0]
    a = OccupancyGrid(a_data, resolution=src.resolution, origin=(float(corner[0]), float(corner[1]), src.origin[2]))

    b, M, kb_in_src = _robot_in_frame(wb, vps_b, rng, rotation_deg=rotation_deg, scale=scale, noise=noise, thick=thick,
                                      bend=bend)
    return a, b, M, (x0, y0), ka, kb_in_src


def robot_views_pair(
    world: OccupancyGrid,
    views_a,
    views_b,
    *,
    rotation_deg: float,
    scale: float,
    noise: float = 0.0,
    rng=0,
    see_through: int = SEE_THROUGH,
) -> tuple[OccupancyGrid, OccupancyGrid, np.ndarray, dict]:
    """Maps of two robots scanning ``world`` from given viewpoints, with the exact truth.

    Robot a maps in ``world``'s frame (cut to its known cells plus 5-20 unknown cells);
    robot b in its own frame, rotated by ``rotation_deg``, with cells ``scale`` times the
    world's: it ray-casts at the world's resolution, as robot a does, and its map keeps a
    wall where an observed wall cell's centre is (:func:`_observed_in_frame`). Both scan
    360 degrees up to :data:`RANGE_PX` world cells (:func:`gridmerge.samples.explore`),
    seeing through up to ``see_through`` unknown cells of the world, then get ``noise``
    (missed and spurious hits).

    Parameters
    ----------
    world : OccupancyGrid
        The source map.
    views_a, views_b : (N, 2) array_like
        Viewpoints in ``world``'s pixels.
    rotation_deg, scale : float
    noise : float
    rng : int or numpy.random.Generator
    see_through : int, optional
        Unknown cells of the world a ray crosses (:data:`SEE_THROUGH`).

    Returns
    -------
    a, b : OccupancyGrid
    truth : (3, 3) float array
        b's pixels -> a's pixels.
    meta : dict
        ``overlap`` (:func:`measure_overlap` of the two robots' known cells before noise,
        in the world's frame, b's known cells taken at the nearest b cell of each world
        cell), ``shared_walls`` (:func:`shared_walls` of what the two robots saw, before
        noise, in the world's cells), ``a_offset`` (a's pixel ``(0, 0)`` is world pixel ``a_offset``),
        ``b_to_source`` (3x3), ``rotation_deg``, ``scale``, ``noise``.
    """
    gen = np.random.default_rng(rng)
    w = _World(world, "world", see_through)
    a, b, M, off, ka, kb = _robot_maps(w, views_a, views_b, gen, rotation_deg=rotation_deg, scale=scale, noise=noise)
    truth = _shift(-off[0], -off[1]) @ M
    meta = {
        "overlap": measure_overlap(ka, kb),
        "shared_walls": shared_walls(w.seen(views_a), w.seen(views_b)),
        "a_offset": [int(off[0]), int(off[1])],
        "b_to_source": M.tolist(),
        "rotation_deg": float(rotation_deg),
        "scale": float(scale),
        "noise": float(noise),
    }
    return a, b, truth, meta


# ------------------------------------------------------------------ simulated
def _split_views(world: _World, vps: np.ndarray, rng: np.random.Generator, target: float, bounds, *, negative: bool = False,
                 gap: int = _MIN_GAP):
    """Viewpoints of robots a and b: the pool ordered along a random direction, a takes
    the first ones, b the last ones, as many as brings the overlap nearest ``target``.

    Returns ``(vps_a, vps_b, overlap_estimate, direction_deg)`` of the best of a few
    random directions (the first whose overlap falls in ``bounds``), or ``None`` for a
    negative split that cannot keep the maps ``gap`` cells apart.
    """
    K = len(vps)
    m = max(3, K // 5)
    best = None
    kernel = np.ones((2 * gap + 1, 2 * gap + 1), np.uint8)
    for _attempt in range(4):
        phi = rng.uniform(0, 2 * math.pi)
        order = np.argsort(vps @ np.array([math.cos(phi), math.sin(phi)]), kind="stable")
        c = int(rng.integers(int(0.4 * K), int(0.6 * K) + 1))
        h_lo, h_hi = max(m - c, c - (K - m)), min(K - c, c)
        if h_lo > h_hi:
            continue

        def split(h):
            return vps[order[: c + h]], vps[order[c - h :]]

        if negative:
            def apart(h):
                va, vb = split(h)
                ka = cv2.dilate(world.known(va).astype(np.uint8), kernel) > 0
                return not (ka & world.known(vb)).any()

            if not apart(h_lo):
                continue
            lo, hi = h_lo, h_hi  # largest h whose maps stay apart
            while lo < hi:
                mid = (lo + hi + 1) // 2
                if apart(mid):
                    lo = mid
                else:
                    hi = mid - 1
            va, vb = split(lo)
            return va, vb, 0.0, math.degrees(phi)

        cache: dict = {}

        def ov(h):
            if h not in cache:
                va, vb = split(h)
                cache[h] = measure_overlap(world.known(va), world.known(vb))
            return cache[h]

        lo, hi = h_lo, h_hi  # overlap grows with h: bisect for the target
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if ov(mid) < target:
                lo = mid
            else:
                hi = mid
        h = min((lo, hi), key=lambda v: abs(ov(v) - target))
        o = ov(h)
        miss = max(bounds[0] - o, o - bounds[1], 0.0)
        if best is None or miss < best[0]:
            va, vb = split(h)
            best = (miss, va, vb, o, math.degrees(phi))
        if miss == 0.0:
            break
    if best is None:
        return None
    return best[1], best[2], best[3], best[4]


def _pick_source(rng: np.random.Generator, available: list, building_shapes, exclude: str = "") -> str:
    files = [s for s in available if s.startswith(FILE_PREFIX)]
    if files:  # maps given by the user: drawn evenly, nothing else
        others = [s for s in files if s != exclude] or files
        return others[int(rng.integers(len(others)))]
    kinds = [k for k in ("willow", "halmstad", "building") if any(s == k or s.startswith(k + ":") for s in available)]
    weights = {"willow": 0.3, "halmstad": 0.3, "building": 0.4}
    for _ in range(20):
        p = np.array([weights[k] for k in kinds])
        kind = kinds[int(rng.choice(len(kinds), p=p / p.sum()))]
        if kind == "building":
            shape = building_shapes[int(rng.integers(len(building_shapes)))]
            name = f"building:{int(rng.integers(1, 1 << 30))}:{int(shape[0])}x{int(shape[1])}"
        elif kind == "willow":
            name = "willow"
        else:
            hal = [s for s in available if s.startswith("halmstad:")]
            name = hal[int(rng.integers(len(hal)))]
        if name != exclude and not (exclude.startswith("halmstad:") and name.startswith("halmstad:") and name.split("_")[0] == exclude.split("_")[0]):
            return name
    return f"building:{int(rng.integers(1, 1 << 30))}:{int(building_shapes[0][0])}x{int(building_shapes[0][1])}"


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


@dataclass(frozen=True)
class _Plan:
    """Which cases of a seeded data set are negative pairs (a share ``negatives`` of
    them, evenly spread: with 0.2, every fifth) and which tier each positive takes
    (``tiers``, cycled over the positives)."""

    tiers: tuple
    negatives: float

    @classmethod
    def checked(cls, n, tiers: Sequence[str], negatives: float) -> tuple[int, "_Plan"]:
        """``(n, plan)``, the arguments checked (:class:`GridMergeError`)."""
        n = int(n)
        if n < 0:
            raise GridMergeError(f"n must be >= 0, got {n}")
        for t in tiers:
            if t not in TIERS:
                raise GridMergeError(f"unknown tier {t!r} (use {', '.join(TIERS)})")
        if not 0.0 <= negatives < 1.0:
            raise GridMergeError(f"negatives must be in [0, 1), got {negatives}")
        return n, cls(tuple(tiers), float(negatives))

    def negative(self, k: int) -> bool:
        return math.floor((k + 1) * self.negatives) > math.floor(k * self.negatives)

    def tier(self, k: int) -> Tier:
        """The tier of case ``k``, a positive."""
        j = k - sum(self.negative(i) for i in range(k))
        return TIERS[self.tiers[j % len(self.tiers)]]


def simulated(
    n: int = 60,
    seed: int = 0,
    *,
    data_dir=None,
    sources: Optional[Sequence[str]] = None,
    tiers: Sequence[str] = ("easy", "medium", "hard"),
    negatives: float = 0.2,
    building_shapes: Sequence[Sequence[int]] = ((560, 760), (720, 960)),
    see_through: int = SEE_THROUGH,
    source_maps: Optional[Sequence] = None,
    bend: float = 0.0,
) -> Dataset:
    """Simulated robot pairs with exact ground truth.

    Case ``k`` is built from its own generator (seed ``[seed, k]``). A share ``negatives``
    of the cases (evenly spread: with 0.2, every fifth) are negative pairs; the others
    cycle through ``tiers`` (:data:`TIERS`).

    A positive case: a source map is drawn (Willow Garage 30 %, a Halmstad sensor map
    30 %, a procedural building 40 %; only buildings without the shared data); a pool of
    scanner positions is drawn in its main free space (one per 4000 cells of it, 16 to
    100), ordered along a random direction; robot a takes the first ones, robot b the
    last ones, as many as brings the overlap of their known cells nearest a target drawn
    in the tier's range (a few directions are tried). Each robot ray-casts from its
    positions (:func:`robot_views_pair`); b's frame has a uniform random rotation and a
    log-uniform scale in the tier's range. The overlap actually obtained is measured and
    recorded in ``meta["overlap"]`` (it can fall a little outside the tier's range).

    A negative case is either two distant parts of one source (the two robots' known
    cells at least 20 cells apart, ``meta["negative_kind"] = "distant-parts"``) or parts
    of two different sources (``"different-places"``), b again rotated and scaled
    (medium tier's scale range and noise).

    Parameters
    ----------
    n : int
        Number of cases.
    seed : int
    data_dir : path, optional
        The shared data folder (default: :func:`default_data_dir` when it exists).
    sources : sequence of str, optional
        Kinds of source maps: ``"building"``, ``"willow"``, ``"halmstad"`` (default: all
        that are available).
    tiers : sequence of str
        Tiers of the positive cases, cycled.
    negatives : float
        Share of negative cases, in ``[0, 1)``.
    building_shapes : sequence of (int, int)
        Shapes of the procedural buildings.
    see_through : int
        Unknown cells of a source map a scanner ray crosses (:data:`SEE_THROUGH`; 0
        rebuilds the set as it was until 2026-11-30). Procedural buildings have no
        unknown cells: their cases are the same whatever the value.
    source_maps : sequence of path, optional
        Map files (anything :func:`gridmerge.load_map` reads: a map_server YAML, a PGM or
        PNG image) to simulate the robots in, instead of the shared data and the
        procedural buildings: each case draws one of them evenly (a negative pair of two
        different places, two of them; with a single map, every negative pair is two
        distant parts of it; a single map too small for them is refused at once).
        ``sources`` is then ignored. Their paths and the SHA-256 of their cells are
        recorded in ``params["source_maps"]``, so that a run names the maps it used.
    bend : float
        Robot b's map bent by up to this many source cells before it is turned and
        resampled (:func:`bent`), as real maps of two SLAM sessions bend against each
        other; 0 (the default) keeps the set as it was. The truth stays the rigid
        transform, which a bent map fits only within about ``bend`` cells (and b's far
        corners farther): read the corner errors with that in mind. Recorded in
        ``params["bend"]`` and each case's ``meta["bend"]`` when above 0.

    Returns
    -------
    Dataset
        Cases ``"simulated/0000"`` ...; ``meta``: ``tier`` (``"negative"`` for negatives),
        ``source`` (and ``source_b``), ``overlap``, ``overlap_target``, ``shared_walls``
        (positives: :func:`shared_walls` of what the two robots saw, before noise, in the
        source's cells), ``rotation_deg``, ``scale``, ``noise``, ``views`` (a, b),
        ``direction_deg``, ``a_offset``, ``b_to_source``, ``see_through``.
    """
    n, plan = _Plan.checked(n, tiers, negatives)
    see_through = int(see_through)
    if see_through < 0:
        raise GridMergeError(f"see_through must be >= 0, got {see_through}")
    bend = float(bend)
    if not (math.isfinite(bend) and bend >= 0.0):
        raise GridMergeError(f"bend must be a number of cells >= 0, got {bend}")
    params: dict = {"see_through": see_through}
    if bend > 0:
        params["bend"] = bend
    notes: list = []
    if source_maps is not None:
        available, digests = _check_source_maps(source_maps, see_through)
        params["source_maps"] = [{"path": s[len(FILE_PREFIX):], "cells_sha256": h} for s, h in zip(available, digests)]
        data_key = None
    else:
        d = resolve_data_dir(data_dir)
        shared = source_names(d) if d is not None else []
        wanted = set(sources) if sources is not None else {"building", "willow", "halmstad"}
        unknown = wanted - {"building", "willow", "halmstad"}
        if unknown:
            raise GridMergeError(f"unknown source kinds {sorted(unknown)} (use building, willow, halmstad)")
        available = [s for s in shared if s.split(":")[0] in wanted]
        if "building" in wanted:
            available.append("building")
        if d is None:
            notes.append(f"shared data not found at {default_data_dir()}: simulated cases use procedural buildings only")
            available = ["building"]
        elif not available:
            raise GridMergeError(f"no source maps of kinds {sorted(wanted)} in {d}")
        data_key = None if d is None else str(d)
    shapes = [tuple(int(v) for v in s) for s in building_shapes]

    def build(k: int) -> Case:
        rng = np.random.default_rng([int(seed), int(k), 7])
        if plan.negative(k):
            case = _negative_case(k, rng, available, data_key, shapes, see_through, bend)
        else:
            case = _positive_case(k, rng, plan.tier(k), available, data_key, shapes, see_through, bend)
        case.meta["see_through"] = see_through
        if bend > 0:
            case.meta["bend"] = bend
        return case

    if source_maps is not None and len(available) == 1:
        # One map: its negative pairs are two distant parts of it. A map too small for
        # them fails here, before a run starts, not in the middle of one.
        first = next((k for k in range(n) if plan.negative(k)), None)
        if first is not None:
            build(first)
    return Dataset("simulated", n, build, notes, params)


def _check_source_maps(paths, see_through: int) -> tuple[list, list]:
    """``(source names, cell digests)`` of the map files ``paths`` (duplicates dropped),
    each read once and found to hold free space where a robot fits; a bad one raises
    :class:`GridMergeError`."""
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    names = list(dict.fromkeys(file_source(p) for p in paths))
    if not names:
        raise GridMergeError("no source map given: give at least one map file")
    digests = []
    for name in names:
        grid = _source_map(name, None)
        _World(grid, name[len(FILE_PREFIX):], see_through)  # raises if no robot fits
        digests.append(_cells_digest(grid))
    return names, digests


def _cells_digest(grid: OccupancyGrid) -> str:
    """SHA-256 of a map's cells as simulated (shape, resolution and values), whatever its
    file format: two runs that name the same digest drew from the same map."""
    h = hashlib.sha256(f"{grid.shape[0]}x{grid.shape[1]}@{grid.resolution!r}:".encode())
    h.update(np.ascontiguousarray(grid.data, dtype=np.float32).tobytes())
    return h.hexdigest()


def _world(name: str, data_key: Optional[str], see_through: int) -> _World:
    return _world_cached(name, data_key, see_through)


@lru_cache(maxsize=2)
def _world_cached(name: str, data_key: Optional[str], see_through: int) -> _World:
    # Only the geometry is cached; the views cache grows with the viewpoints used.
    return _World(_source_map(name, data_key), name, see_through)


def _positive_case(k: int, rng, tier: Tier, available, data_key, shapes, see_through: int, bend: float = 0.0) -> Case:
    name = _pick_source(rng, available, shapes)
    world = _world(name, data_key, see_through)
    world._views.clear()
    vps = world.viewpoints(rng)
    target = float(rng.uniform(*tier.overlap))
    va, vb, _est, phi = _split_views(world, vps, rng, target, tier.overlap)
    rot = float(rng.uniform(-180.0, 180.0))
    scale = _log_uniform(rng, *tier.scale)
    a, b, M, off, ka, kb = _robot_maps(world, va, vb, rng, rotation_deg=rot, scale=scale, noise=tier.noise, bend=bend)
    walls = shared_walls(world.seen(va), world.seen(vb))  # the views are cached: no ray is cast again
    world._views.clear()
    truth = _shift(-off[0], -off[1]) @ M
    cid = f"simulated/{k:04d}"
    meta = {
        "tier": tier.name,
        "source": name,
        "overlap": round(measure_overlap(ka, kb), 6),
        "shared_walls": walls,
        "overlap_target": round(target, 6),
        "rotation_deg": rot,
        "scale": scale,
        "noise": tier.noise,
        "views": [len(va), len(vb)],
        "direction_deg": phi,
        "range_px": RANGE_PX,
        "a_offset": [int(off[0]), int(off[1])],
        "b_to_source": M.tolist(),
    }
    return Case(cid, "simulated", a.replace(name=f"{cid} a"), b.replace(name=f"{cid} b"), truth, True, meta)


def _negative_case(k: int, rng, available, data_key, shapes, see_through: int, bend: float = 0.0) -> Case:
    tier = TIERS["medium"]
    rot = float(rng.uniform(-180.0, 180.0))
    scale = _log_uniform(rng, *tier.scale)
    name = _pick_source(rng, available, shapes)
    world = _world(name, data_key, see_through)
    world._views.clear()
    vps = world.viewpoints(rng)
    kind = "distant-parts" if rng.random() < 0.5 else "different-places"
    alone = [s for s in available if s.startswith(FILE_PREFIX)] == [name]  # no other place to draw
    split = _split_views(world, vps, rng, 0.0, (0.0, 0.0), negative=True) if kind == "distant-parts" or alone else None
    if split is None and alone:
        raise GridMergeError(f"source map {name[len(FILE_PREFIX):]} is too small for a negative pair of two distant "
                             "parts; give two maps or more")
    meta: dict = {"tier": "negative", "source": name, "rotation_deg": rot, "scale": scale, "noise": tier.noise, "range_px": RANGE_PX}
    if split is not None:
        va, vb, _, phi = split
        a, b, M, off, ka, kb = _robot_maps(world, va, vb, rng, rotation_deg=rot, scale=scale, noise=tier.noise, bend=bend)
        meta.update(negative_kind="distant-parts", overlap=measure_overlap(ka, kb), views=[len(va), len(vb)], direction_deg=phi)
    else:
        # Two different places: a from this source, b from another one.
        other = _pick_source(rng, available, shapes, exclude=name)
        K = len(vps)
        order = np.argsort(vps @ rng.normal(size=2), kind="stable")
        va = vps[order[: max(3, int(rng.uniform(0.4, 0.7) * K))]]
        world_b = _world_cached_pair(other, data_key, see_through)
        world_b._views.clear()
        vps_b = world_b.viewpoints(rng)
        order_b = np.argsort(vps_b @ rng.normal(size=2), kind="stable")
        vb = vps_b[order_b[: max(3, int(rng.uniform(0.4, 0.7) * len(vps_b)))]]
        a, b, M, off, ka, kb = _robot_maps(world, va, vb, rng, rotation_deg=rot, scale=scale, noise=tier.noise, world_b=world_b,
                                           bend=bend)
        world_b._views.clear()
        meta.update(negative_kind="different-places", source_b=other, overlap=0.0, views=[len(va), len(vb)])
    world._views.clear()
    cid = f"simulated/{k:04d}"
    return Case(cid, "simulated", a.replace(name=f"{cid} a"), b.replace(name=f"{cid} b"), None, False, meta)


@lru_cache(maxsize=1)
def _world_cached_pair(name: str, data_key: Optional[str], see_through: int) -> _World:
    return _World(_source_map(name, data_key), name, see_through)


# ------------------------------------------------------------------- halmstad
def halmstad_environments(data_dir=None) -> list:
    """Names of the Halmstad environments in the shared data folder, sorted: every
    ``halmstad/ENV_pairs.json`` that has its maps' folder ``halmstad/ENV/`` (``[]``
    without the folder). Environments added to the folder in the same layout (another
    building of the Halmstad data set, or a set of annotated maps of one's own) are
    benchmarked with no change to the code."""
    d = resolve_data_dir(data_dir)
    if d is None or not (d / "halmstad").is_dir():
        return []
    root = d / "halmstad"
    names = (f.name[: -len("_pairs.json")] for f in root.glob("*_pairs.json"))
    return sorted(env for env in names if (root / env).is_dir())


def _annotated_pairs(root: Path, environments: Sequence[str], kinds: Sequence[str]) -> tuple[list, list]:
    """``([(environment, pair), ...], notes)``: the annotated pairs of ``kinds`` of each
    environment (``root/ENV_pairs.json``) in file order, those whose map files are all
    in ``root/ENV/``; ``notes`` name the maps missing.

    Raises
    ------
    GridMergeError
        An environment's annotations are missing.
    """
    entries = []
    missing: dict = {}
    for env in environments:
        f = root / f"{env}_pairs.json"
        if not f.is_file():
            raise GridMergeError(f"Halmstad annotations not found: {f}")
        for p in json.loads(f.read_text())["pairs"]:
            if p.get("kind", "sensor") not in kinds:
                continue
            absent = [m for m in (p["a"], p["b"]) if not (root / env / f"{m}.png").is_file()]
            if absent:
                missing.setdefault(env, set()).update(absent)
            else:
                entries.append((env, p))
    notes = [f"halmstad {env}: pairs with {', '.join(sorted(m))}.png left out (not in {root / env})" for env, m in missing.items()]
    return entries, notes


def _map_number(stem: str) -> int:
    """The number of a sensor map (``E5_07`` -> 7, ``F5_2`` -> 2)."""
    return int(stem.rsplit("_", 1)[1])


def _sensor_stems(root: Path, env: str) -> list:
    """The sensor maps of an environment (``ENV_<number>.png``), by number."""
    stems = [p.stem for p in (root / env).glob(f"{env}_[0-9]*.png") if p.stem.rsplit("_", 1)[1].isdigit()]
    return sorted(stems, key=_map_number)


def halmstad(
    data_dir=None,
    *,
    kinds: Sequence[str] = ("sensor", "layout", "cross"),
    environments: Optional[Sequence[str]] = None,
    limit: Optional[int] = None,
) -> Dataset:
    """The annotated real pairs of the Halmstad data set, and real negative pairs.

    Sensor pairs (two Tango maps) are data set ``"halmstad"``; layout pairs (a sensor map
    against the RGBA blueprint) ``"halmstad-layout"``, reported separately. Cross pairs
    (``"halmstad-cross"``) are negatives: every sensor map of one environment against
    every sensor map of another (E5, a university building, against HIH, an apartment,
    with the shared data as it is), for every two environments; the map of the first
    environment (by name) is map a when its number is odd, map b when it is even. Maps of
    two different buildings must not be merged; they are real maps, with the noise,
    bending and room shapes that the simulated negatives lack.

    Parameters
    ----------
    data_dir : path, optional
        The shared data folder (default: :func:`default_data_dir`).
    kinds : sequence of {"sensor", "layout", "cross"}
    environments : sequence of str, optional
        Environments to read (default: every one in the folder,
        :func:`halmstad_environments`; ``E5`` and ``HIH`` in the shared data).
    limit : int, optional
        At most this many pairs of each kind and environment (the first ones); at most
        this many cross pairs.

    Returns
    -------
    Dataset
        Cases ``"halmstad/E5_01-E5_02"`` ...; ``truth`` is the annotation's least-median
        fit (3x3); ``meta``: ``environment``, ``kind``, ``map_a``, ``map_b``,
        ``points_a``, ``points_b``, ``fit_median_residual_px`` and the protocol's
        ``threshold_px = max(20, 2 * fit_median_residual_px)``, ``protocol = "halmstad"``,
        ``resolutions_known`` (``False`` for layout pairs: the benchmark aligns them
        with ``max_scale_disagreement=None``). Cross cases ``"halmstad-cross/E5_01-HIH_01"``
        ...: ``truth`` ``None``, tier ``"negative"``, ``environment`` ``"E5+HIH"``.
        An annotated pair whose map file is missing is left out, and said so in the
        data set's ``notes``.

    Raises
    ------
    GridMergeError
        When the data folder, an asked environment's annotations, or every environment
        are missing.
    """
    d = resolve_data_dir(data_dir)
    if d is None:
        raise GridMergeError(f"the Halmstad data needs the shared data folder ({default_data_dir()} not found)")
    root = d / "halmstad"
    if environments is None:
        environments = halmstad_environments(d)
        if not environments:
            raise GridMergeError(f"no Halmstad annotations (ENV_pairs.json with a folder ENV/) in {root}")
    entries, notes = _annotated_pairs(root, environments, kinds)
    if limit is not None:  # the first ``limit`` of each environment and kind
        counts: dict = {}
        kept = []
        for env, p in entries:
            key = (env, p.get("kind", "sensor"))
            counts[key] = counts.get(key, 0) + 1
            if counts[key] <= limit:
                kept.append((env, p))
        entries = kept
    # Sensor pairs first, then layout pairs (keeps the file order within each).
    entries.sort(key=lambda e: 0 if e[1].get("kind", "sensor") == "sensor" else 1)
    if "cross" in kinds:
        envs = sorted(set(environments))
        stems = {env: _sensor_stems(root, env) for env in envs}
        cross = []
        for i, first in enumerate(envs):
            for other in envs[i + 1:]:
                for m in stems[first]:
                    for h in stems[other]:
                        pair = ((first, m), (other, h)) if _map_number(m) % 2 else ((other, h), (first, m))
                        cross.append(("cross", {"kind": "cross", "a": pair[0], "b": pair[1]}))
        entries += cross[:limit]
    root_s = str(root)

    def build(k: int) -> Case:
        env, p = entries[k]
        if env == "cross":
            (env_a, name_a), (env_b, name_b) = p["a"], p["b"]
            a = _halmstad_map(root_s, env_a, name_a)
            b = _halmstad_map(root_s, env_b, name_b)
            both = "+".join(sorted((env_a, env_b)))
            meta = {"tier": "negative", "environment": both, "kind": "cross", "map_a": name_a, "map_b": name_b,
                    "negative_kind": "different-buildings", "source": f"halmstad:{both}"}
            return Case(f"halmstad-cross/{name_a}-{name_b}", "halmstad-cross", a, b, None, False, meta)
        kind = p.get("kind", "sensor")
        a = _halmstad_map(root_s, env, p["a"])
        b = _halmstad_map(root_s, env, p["b"])
        fit = np.vstack([np.asarray(p["fit_b_to_a"], dtype=float), [0.0, 0.0, 1.0]])
        resid = float(p["fit_median_residual_px"])
        fit_rot = math.degrees(math.atan2(fit[1, 0], fit[0, 0]))
        meta = {
            "tier": kind,
            "environment": env,
            "kind": kind,
            "map_a": p["a"],
            "map_b": p["b"],
            "points_a": p["points_a"],
            "points_b": p["points_b"],
            "fit_median_residual_px": resid,
            "threshold_px": max(20.0, 2.0 * resid),
            "protocol": "halmstad",
            "rotation_deg": fit_rot,
            "scale": float(math.hypot(fit[0, 0], fit[1, 0])),
            "source": f"halmstad:{env}",
            # The Tango maps share one (unstated) pixel size; a blueprint's against them
            # is unknown, so layout pairs are aligned at any scale (CLI --any-scale).
            "resolutions_known": kind == "sensor",
        }
        dataset = "halmstad" if kind == "sensor" else "halmstad-layout"
        return Case(f"{dataset}/{p['a']}-{p['b']}", dataset, a, b, fit, True, meta)

    return Dataset("halmstad", len(entries), build, notes)


# ----------------------------------------------------------- halmstad-partial
#: Radius, in cells of the real map, of the part of the building a partial case's team
#: has explored (:func:`halmstad_partial`; drawn log-uniformly).
PARTIAL_RADIUS = (150.0, 450.0)
#: Annotated points a positive partial case's overlap holds at least: its score is their
#: median error, as the Halmstad protocol's.
PARTIAL_POINTS = 3
_PARTIAL_MARGIN = 10  # cells: a point this near both robots' known cells is in their overlap
_PARTIAL_SNAP = 15  # cells: how far one of b's viewpoints may move to stand in b's free space
_PARTIAL_GAP = 40  # negatives: cells between the two robots' maps (in a's map: the maps bend)
_PARTIAL_TRIES = 20  # draws of a pair before the next pair is tried
_PARTIAL_THICK = 3  # cells of a real wall kept behind the face a scanner hit (World.seen)
_PARTIAL_WALL = 4  # cells: a wall of a this near one of b's (carried by the fit) is shared


@lru_cache(maxsize=4)
def _session_world(data_key: str, env: str, stem: str, see_through: int) -> tuple[_World, np.ndarray]:
    """A Halmstad sensor map cut to its known cells plus 8, ready for ray casting, and the
    cut's offset ``(x, y)`` in the map's image (where its annotated points are)."""
    cut, offset = load_map(Path(data_key) / "halmstad" / env / f"{stem}.png").crop_known(8)
    return _World(cut, f"halmstad:{stem}", see_through), offset


def _warp_mask(mask: np.ndarray, M: np.ndarray, shape: tuple) -> np.ndarray:
    """``mask`` carried by ``M`` (its pixels -> the output's) onto an array of ``shape``,
    nearest cell."""
    return cv2.warpAffine(mask.astype(np.uint8), np.ascontiguousarray(M[:2]), (shape[1], shape[0]),
                          flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0) > 0


def _near(mask: np.ndarray, cells: int) -> np.ndarray:
    """Cells within ``cells`` (a square) of ``mask``."""
    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * cells + 1, 2 * cells + 1), np.uint8)) > 0


def _inside(mask: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Which of ``points`` ((N, 2), x = column, y = row) fall on a true cell of ``mask``."""
    q = np.rint(points).astype(np.int64)
    H, W = mask.shape
    ok = (q[:, 0] >= 0) & (q[:, 0] < W) & (q[:, 1] >= 0) & (q[:, 1] < H)
    out = np.zeros(len(q), dtype=bool)
    out[ok] = mask[q[ok, 1], q[ok, 0]]
    return out


def _snap(world: _World, points: np.ndarray) -> np.ndarray:
    """Each point moved to the nearest cell where a robot can stand in ``world`` (its
    ``region``) within :data:`_PARTIAL_SNAP` cells; points with none are dropped."""
    H, W = world.region.shape
    r = _PARTIAL_SNAP
    out = []
    for x, y in points:
        xi, yi = int(round(x)), int(round(y))
        x0, y0 = max(0, xi - r), max(0, yi - r)
        ys, xs = np.nonzero(world.region[y0 : min(H, yi + r + 1), x0 : min(W, xi + r + 1)])
        if len(xs):
            d = np.hypot(xs + x0 - x, ys + y0 - y)
            j = int(np.argmin(d))
            if d[j] <= r:
                out.append((float(xs[j] + x0), float(ys[j] + y0)))
    return np.array(out, dtype=float).reshape(-1, 2)


def halmstad_partial(
    n: int = 60,
    seed: int = 0,
    *,
    data_dir=None,
    environments: Optional[Sequence[str]] = None,
    tiers: Sequence[str] = ("easy", "medium", "hard"),
    negatives: float = 0.2,
    radius: Sequence[float] = PARTIAL_RADIUS,
    see_through: int = SEE_THROUGH,
) -> Dataset:
    """Two robots that explored part of one real building each, in two real maps of it.

    The simulated set's robots both scan one source map, so their maps agree wherever they
    overlap; the Halmstad pairs are whole buildings. A real team's maps may overlap little
    *and* differ: two sessions of a building bend against each other, furniture and doors
    move, and what one scanner saw as glass the other saw as a wall. This set has both.
    Case ``k`` (its own generator, seed ``[seed, k, 17]``) takes an annotated sensor pair
    of the Halmstad data (two Tango maps of one building, say E5_03 and E5_07; pairs in an
    order drawn from ``seed``, cycled) and:

    * draws scanner positions over the building in map a (as :func:`simulated` does), a
      centre among them and a radius (log-uniform in ``radius``, cells), and keeps the
      positions within it: the part of the building the team has explored so far;
    * splits them between the two robots along a random direction, aiming at an overlap
      in the tier's range (:data:`TIERS`; negatives: the two robots' maps
      :data:`_PARTIAL_GAP` cells apart in map a, two distant parts of the building);
    * robot a ray-casts **map a** from its positions; robot b ray-casts **map b** from
      its positions carried into map b by the pair's annotation fit (each moved to the
      nearest free cell of map b within 15 cells, or dropped), then gets a random rotation
      and a scale in the tier's range, as in :func:`simulated`. No noise is added: the
      real maps bring their own.

    Positive cases are scored by the Halmstad protocol on the annotated points that lie in
    the two robots' overlap (within 10 cells of cells both know, in both maps): a case is
    drawn again until at least :data:`PARTIAL_POINTS` do (after 20 draws, the next pair
    is taken). ``truth`` is the annotation fit carried into the two robots' frames
    (informative: the maps bend, so it is 5-15 px off in places, as for the Halmstad
    pairs).

    Parameters
    ----------
    n : int
    seed : int
    data_dir : path, optional
        The shared data folder (default: :func:`default_data_dir`).
    environments : sequence of str, optional
        Default: every one in the folder (:func:`halmstad_environments`).
    tiers : sequence of str
        Tiers of the positive cases, cycled (their overlap and scale ranges).
    negatives : float
        Share of negative cases, in ``[0, 1)``, spread as in :func:`simulated`.
    radius : (float, float)
        Range of the explored part's radius, cells of the real map.
    see_through : int
        Unknown cells of the real map a scanner ray crosses (:data:`SEE_THROUGH`).

    Returns
    -------
    Dataset
        Cases ``"halmstad-partial/0000"`` ...; ``meta``: ``tier``, ``environment``,
        ``map_a``, ``map_b``, ``source`` (``"halmstad:E5"``), ``overlap`` (of the robots'
        known cells, b's carried into map a by the fit), ``overlap_target``,
        ``shared_walls`` (a's wall cells within 4 cells of one of b's, so carried:
        the maps bend),
        ``rotation_deg`` and ``scale`` (of ``truth``), ``cell_scale`` (b's cells over
        a's), ``radius_px``, ``views``, ``points_a``, ``points_b`` (the points scored, in
        the two robots' pixels), ``fit_median_residual_px``, ``threshold_px``,
        ``protocol = "halmstad"``.

    Raises
    ------
    GridMergeError
        No shared data, no annotated sensor pair, bad parameters.
    """
    n, plan = _Plan.checked(n, tiers, negatives)
    lo, hi = (float(v) for v in radius)
    if not 0 < lo <= hi:
        raise GridMergeError(f"radius must be two lengths 0 < lo <= hi, got {tuple(radius)}")
    d = resolve_data_dir(data_dir)
    if d is None:
        raise GridMergeError(f"the Halmstad data needs the shared data folder ({default_data_dir()} not found)")
    root = d / "halmstad"
    if environments is None:
        environments = halmstad_environments(d)
    pairs, notes = _annotated_pairs(root, environments, ("sensor",))
    if not pairs:
        raise GridMergeError(f"no annotated sensor pair (ENV_pairs.json with its maps in ENV/) in {root}")
    order = np.random.default_rng([int(seed), 13]).permutation(len(pairs))
    data_key = str(d)

    def build(k: int) -> Case:
        rng = np.random.default_rng([int(seed), int(k), 17])
        negative = plan.negative(k)
        tier = TIERS["medium"] if negative else plan.tier(k)
        cid = f"halmstad-partial/{k:04d}"
        for step in range(len(pairs)):
            env, p = pairs[order[(k + step) % len(pairs)]]
            case = _partial_case(cid, env, p, rng, tier, negative, (lo, hi), data_key, int(see_through))
            if case is not None:
                return case
        raise GridMergeError(f"no pair of {root} gives case {cid} (too little free space in the maps?)")

    return Dataset("halmstad-partial", n, build, notes, {"see_through": int(see_through), "radius": [lo, hi]})


def _partial_case(cid, env, p, rng, tier: Tier, negative: bool, radius, data_key, see_through) -> Optional[Case]:
    wa, off_a = _session_world(data_key, env, p["a"], see_through)
    wb, off_b = _session_world(data_key, env, p["b"], see_through)
    fit = np.vstack([np.asarray(p["fit_b_to_a"], dtype=float), [0.0, 0.0, 1.0]])
    b_to_a = _shift(-off_a[0], -off_a[1]) @ fit @ _shift(off_b[0], off_b[1])  # world b -> world a pixels
    pa = np.asarray(p["points_a"], dtype=float) - off_a
    pb = np.asarray(p["points_b"], dtype=float) - off_b
    wa._views.clear()
    wb._views.clear()
    try:
        pool = wa.viewpoints(rng)
        for _ in range(_PARTIAL_TRIES):
            centre = pool[int(rng.integers(len(pool)))]
            r = _log_uniform(rng, *radius)
            dist = np.hypot(*(pool - centre).T)
            part = pool[dist <= r] if (dist <= r).sum() >= 6 else pool[np.argsort(dist, kind="stable")[:6]]
            target = 0.0 if negative else float(rng.uniform(*tier.overlap))
            split = _split_views(wa, part, rng, target, (0.0, 0.0) if negative else tier.overlap, negative=negative,
                                 gap=_PARTIAL_GAP)
            if split is None:
                continue
            va, vb_in_a, _, phi = split
            vb = _snap(wb, AffineTransform(b_to_a).inverse(vb_in_a))
            if len(vb) == 0:
                continue
            rot = float(rng.uniform(-180.0, 180.0))
            cell_scale = _log_uniform(rng, *tier.scale)
            a, b, M, off, ka, kb = _robot_maps(wa, va, vb, rng, rotation_deg=rot, scale=cell_scale, noise=0.0, world_b=wb,
                                               thick=_PARTIAL_THICK)
            kb_in_a = _warp_mask(kb, b_to_a, ka.shape)
            meta = {"tier": "negative" if negative else tier.name, "environment": env, "map_a": p["a"], "map_b": p["b"], "source": f"halmstad:{env}",
                    "cell_scale": cell_scale, "radius_px": r, "views": [len(va), len(vb)], "direction_deg": phi,
                    "a_offset": [int(off[0]), int(off[1])], "b_to_source": M.tolist()}
            if negative:
                if (_near(ka, _PARTIAL_GAP // 2) & kb_in_a).any():
                    continue  # the maps bend: b's part came near a's
                meta.update(negative_kind="distant-parts", overlap=0.0, rotation_deg=rot, scale=cell_scale)
                return Case(cid, "halmstad-partial", a.replace(name=f"{cid} a"), b.replace(name=f"{cid} b"), None, False, meta)
            both = _near(ka & kb_in_a, _PARTIAL_MARGIN)
            scored = _inside(both, pa) & _inside(_near(kb, _PARTIAL_MARGIN), pb)
            if scored.sum() < PARTIAL_POINTS:
                continue
            truth = _shift(-off[0], -off[1]) @ b_to_a @ M
            with np.errstate(invalid="ignore"):
                walls_a = wa.seen(va, _PARTIAL_THICK) > 0.5
                walls_b = _warp_mask(wb.seen(vb, _PARTIAL_THICK) > 0.5, b_to_a, ka.shape)
            resid = float(p["fit_median_residual_px"])
            meta.update(
                overlap=round(measure_overlap(ka, kb_in_a), 6),
                overlap_target=round(target, 6),
                shared_walls=int((walls_a & _near(walls_b, _PARTIAL_WALL)).sum()),
                rotation_deg=math.degrees(math.atan2(truth[1, 0], truth[0, 0])),
                scale=float(math.hypot(truth[0, 0], truth[1, 0])),
                points_a=(pa[scored] - off).tolist(),
                points_b=AffineTransform(M).inverse(pb[scored]).tolist(),
                fit_median_residual_px=resid,
                threshold_px=max(20.0, 2.0 * resid),
                protocol="halmstad",
            )
            return Case(cid, "halmstad-partial", a.replace(name=f"{cid} a"), b.replace(name=f"{cid} b"), truth, True, meta)
        return None
    finally:
        wa._views.clear()
        wb._views.clear()


def unswapped(name: str) -> str:
    """The data set whose cases a data set name's cases are, swapped or not.

    >>> unswapped("simulated-swapped"), unswapped("halmstad-cross")
    ('simulated', 'halmstad-cross')
    """
    return name[: -len(_SWAPPED)] if name.endswith(_SWAPPED) else name


def swapped(ds: Dataset) -> Dataset:
    """The cases of ``ds`` with their two maps swapped: b is the reference and a is
    aligned onto it (``truth`` inverted; annotated points, map names and the rotation and
    scale of the Halmstad pairs swapped alike). A method whose result depends on which
    map comes first scores differently here. Case ids ``"halmstad-swapped/E5_02-E5_01"``
    (data set name with ``-swapped``).

    Examples
    --------
    >>> from gridmerge.bench import datasets
    >>> case = datasets.swapped(datasets.paper())[0]
    >>> case.id, case.dataset
    ('paper-swapped/table1-seed0', 'paper-swapped')
    """

    def build(k: int) -> Case:
        c = ds[k]
        meta = dict(c.meta)
        for x, y in (("points_a", "points_b"), ("map_a", "map_b")):
            if x in meta or y in meta:
                meta[x], meta[y] = c.meta.get(y), c.meta.get(x)
        truth = None if c.truth is None else np.linalg.inv(np.asarray(c.truth, dtype=float))
        if truth is not None:
            if "rotation_deg" in meta:
                meta["rotation_deg"] = math.degrees(math.atan2(truth[1, 0], truth[0, 0]))
            if "scale" in meta:
                meta["scale"] = float(math.hypot(truth[0, 0], truth[1, 0]))
        meta["swapped"] = True
        name = f"{c.dataset}-swapped"
        if "map_a" in meta:
            rest = f"{meta['map_a']}-{meta['map_b']}"
        else:
            rest = c.id.split("/", 1)[1]
        return Case(f"{name}/{rest}", name, c.b, c.a, truth, c.positive, meta)

    return Dataset(f"{ds.name}-swapped", len(ds), build, list(ds.notes), dict(ds.params))


def _halmstad_map(root: str, env: str, stem: str) -> OccupancyGrid:
    if stem.endswith("layout"):
        return _halmstad_layout(root, env, stem)  # decoding the RGBA blueprint is slow: cached
    return load_map(Path(root) / env / f"{stem}.png")


@lru_cache(maxsize=2)
def _halmstad_layout(root: str, env: str, stem: str) -> OccupancyGrid:
    return load_map(Path(root) / env / f"{stem}.png")


# ---------------------------------------------------------------------- paper
def paper(seeds: Sequence[int] = (0,)) -> Dataset:
    """The paper's Table I experiment (:func:`gridmerge.samples.table1_pair`).

    One case per building seed; ``meta["table1"]`` holds :data:`PAPER_TABLE1` (the true
    transform and the paper's estimate) for the report.
    """
    seeds = [int(s) for s in seeds]

    def build(k: int) -> Case:
        s = seeds[k]
        a, b, truth = samples.table1_pair(s)
        meta = {
            "tier": "table1",
            "seed": s,
            "rotation_deg": samples.TABLE1_THETA_DEG,
            "scale": samples.TABLE1_SCALE,
            "translation": list(samples.TABLE1_TRANSLATION),
            "source": f"building:{s}:480x640",
            "table1": PAPER_TABLE1,
        }
        return Case(f"paper/table1-seed{s}", "paper", a, b, np.asarray(truth, dtype=float), True, meta)

    return Dataset("paper", len(seeds), build, [])


# ----------------------------------------------------------------------- load
def load(name: str, *, seed: int = 0, n: Optional[int] = None, quick: bool = False, data_dir=None,
         source_maps: Optional[Sequence] = None, bend: float = 0.0) -> Dataset:
    """A data set by name, with the benchmark's default sizes.

    ``simulated``: ``n`` cases (default 60; 6 with ``quick``); ``halmstad-partial``: ``n``
    cases (default 60; 3 with ``quick``; :func:`halmstad_partial`); ``halmstad``: every
    annotated pair and every cross-building negative (with ``quick``: the first 2 sensor
    pairs and the first layout pair of each environment, and one cross pair), or the first
    ``n`` of each kind and environment; ``halmstad:ENV`` or ``halmstad:ENV+ENV...``: the
    same with these environments only; ``paper``: seeds 0-4 (seed 0 with ``quick``);
    any of them followed by ``-swapped`` (``halmstad-swapped``): its cases with the two
    maps swapped (:func:`swapped`). ``source_maps`` (map files) are the simulated set's
    source maps instead of the shared data's (:func:`simulated`), and ``bend`` bends its
    robot b's maps (:func:`simulated`); the other sets ignore both.

    Raises
    ------
    GridMergeError
        Unknown name; ``halmstad`` or ``halmstad-partial`` without the shared data.
    """
    base, envs, swap = check_name(name)
    if swap:
        return swapped(load(unswapped(name), seed=seed, n=n, quick=quick, data_dir=data_dir, source_maps=source_maps, bend=bend))
    if base == "simulated":
        return simulated(n=(6 if quick else 60) if n is None else n, seed=seed, data_dir=data_dir, source_maps=source_maps,
                         bend=bend)
    if base == "halmstad-partial":
        return halmstad_partial(n=(3 if quick else 60) if n is None else n, seed=seed, data_dir=data_dir)
    if base == "halmstad":
        if quick:
            sensor = halmstad(data_dir, kinds=("sensor",), limit=2, environments=envs)
            layout = halmstad(data_dir, kinds=("layout",), limit=1, environments=envs)
            cross = halmstad(data_dir, kinds=("cross",), limit=1, environments=envs)
            return _concat("halmstad", [sensor, layout, cross])
        return halmstad(data_dir, limit=n, environments=envs)
    return paper((0,) if quick else tuple(range(5)))


_SWAPPED = "-swapped"


def check_name(name: str) -> tuple[str, Optional[list], bool]:
    """``(data set, environments, swapped)`` of a name :func:`load` knows: one of
    :data:`DATASETS`, ``halmstad:ENV[+ENV...]`` (environments, else ``None``), either
    followed by ``-swapped``.

    Raises
    ------
    GridMergeError
        Any other name.
    """
    swap = name.endswith(_SWAPPED)
    base = unswapped(name)
    envs = None
    if base.startswith("halmstad:"):
        envs = base.split(":", 1)[1].split("+")
        base = "halmstad" if all(envs) else base
    if base not in DATASETS:
        raise GridMergeError(f"unknown data set {name!r} (use {', '.join(DATASETS)} or halmstad:ENV, each with {_SWAPPED} or not)")
    return base, envs, swap


def _concat(name: str, parts: Sequence[Dataset]) -> Dataset:
    index = [(i, k) for i, p in enumerate(parts) for k in range(len(p))]

    def build(j: int) -> Case:
        i, k = index[j]
        return parts[i][k]

    return Dataset(name, len(index), build, [note for p in parts for note in p.notes])

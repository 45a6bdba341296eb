"""The occupancy grid type and the coordinate conventions of gridmerge.

Conventions
-----------
*Image pixels* are ``(x, y) = (column, row)`` with the origin at the **centre** of the
top-left cell of the image as stored in a file (row 0 is the top row). This is OpenCV's
convention, and the one of every 2x3 ``matrix`` that gridmerge returns.

*Metric frames* follow ROS: ``x, y`` in metres, yaw in radians. A map's ``origin`` is the
pose ``(x, y, yaw)`` of the lower-left **corner** of the lower-left cell, as in ROS
map_server and ``nav_msgs/OccupancyGrid``. The centre of the cell at pixel ``(x, y)`` of a
grid of height ``H`` therefore lies, in the map's own axes, at
``((x + 0.5) * resolution, (H - 0.5 - y) * resolution)``, which is then rotated by ``yaw``
and shifted by ``(origin_x, origin_y)``.

*Cell values* are the probability that the cell is occupied, in ``[0, 1]``; unknown cells
are ``NaN``. ROS's int8 values map as ``v -> v / 100`` and ``-1 -> NaN``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from .errors import MapFormatError

__all__ = [
    "OccupancyGrid",
    "DEFAULT_RESOLUTION",
    "OCCUPIED_THRESHOLD",
    "FREE_THRESHOLD",
]

#: Resolution (m/cell) given to maps whose file does not say (bare images, ``.npy``).
DEFAULT_RESOLUTION = 0.05
#: map_server's default ``occupied_thresh``: a cell is occupied above this probability.
OCCUPIED_THRESHOLD = 0.65
#: map_server's default ``free_thresh``: a cell is free below this probability.
FREE_THRESHOLD = 0.196


def _check_origin(origin: Sequence[float]) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in origin)
    except (TypeError, ValueError):
        raise MapFormatError(f"origin must be three numbers [x, y, yaw], got {origin!r}", field="origin") from None
    if len(values) != 3:
        raise MapFormatError(f"origin must be three numbers [x, y, yaw], got {len(values)}", field="origin")
    if not all(math.isfinite(v) for v in values):
        raise MapFormatError(f"origin must be finite, got {list(values)}", field="origin")
    return values  # type: ignore[return-value]


@dataclass(frozen=True, eq=False)
class OccupancyGrid:
    """A 2-D occupancy grid map with its metric frame.

    Parameters
    ----------
    data : (H, W) array_like
        Occupancy probability of each cell in ``[0, 1]``; ``NaN`` where unknown. Row 0 is
        the top row of the map's image (the cells farthest along the map's +y axis). The
        array is copied to ``float32`` and made read-only; the caller's array is never
        modified.
    resolution : float
        Cell size in metres per cell (> 0).
    origin : (3,) sequence of float
        ``(x, y, yaw)`` of the lower-left corner of the lower-left cell in the map frame,
        metres and radians, as in ROS.
    name : str, optional
        A label used in reports (usually the path the map was read from).

    Examples
    --------
    >>> import numpy as np
    >>> from gridmerge import OccupancyGrid
    >>> g = OccupancyGrid(np.array([[1.0, np.nan], [0.0, 0.0]]), resolution=0.1)
    >>> g.shape
    (2, 2)
    >>> g.to_ros().tolist()  # ROS order: bottom row first
    [0, 0, 100, -1]
    >>> g.pixel_to_metric([[0, 0]]).round(3).tolist()  # centre of the top-left cell
    [[0.05, 0.15]]
    """

    data: np.ndarray
    resolution: float = DEFAULT_RESOLUTION
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    name: str | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        arr = np.array(self.data, dtype=np.float32, copy=True)
        if arr.ndim != 2:
            raise MapFormatError(f"map data must be 2-D, got shape {arr.shape}", path=self.name, field="data")
        if arr.size == 0:
            raise MapFormatError("map is empty (0 cells)", path=self.name, field="data")
        finite = np.isfinite(arr)
        if np.isinf(arr).any():
            raise MapFormatError("map data contains infinite values", path=self.name, field="data")
        if finite.any():
            lo = float(np.nanmin(arr))
            hi = float(np.nanmax(arr))
            if lo < 0.0 or hi > 1.0:
                raise MapFormatError(
                    f"cell values must be probabilities in [0, 1] (NaN = unknown), got [{lo}, {hi}]",
                    path=self.name,
                    field="data",
                )
        arr.flags.writeable = False
        try:
            res = float(self.resolution)
        except (TypeError, ValueError):
            raise MapFormatError(f"resolution must be a number, got {self.resolution!r}", path=self.name, field="resolution") from None
        if not math.isfinite(res) or res <= 0:
            raise MapFormatError(f"resolution must be a finite number > 0, got {self.resolution!r}", path=self.name, field="resolution")
        try:
            origin = _check_origin(self.origin)
        except MapFormatError as exc:
            raise MapFormatError(str(exc).split(": ", 1)[-1], path=self.name, field="origin") from None
        object.__setattr__(self, "data", arr)
        object.__setattr__(self, "resolution", res)
        object.__setattr__(self, "origin", origin)

    # ------------------------------------------------------------------ basics
    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``: rows and columns."""
        return self.data.shape  # type: ignore[return-value]

    @property
    def height(self) -> int:
        return int(self.data.shape[0])

    @property
    def width(self) -> int:
        return int(self.data.shape[1])

    @property
    def known(self) -> np.ndarray:
        """(H, W) bool array: cells whose occupancy is known."""
        return ~np.isnan(self.data)

    def occupied(self, threshold: float = OCCUPIED_THRESHOLD) -> np.ndarray:
        """(H, W) bool array: cells with occupancy probability above ``threshold``."""
        with np.errstate(invalid="ignore"):
            return self.data > threshold

    def free(self, threshold: float = FREE_THRESHOLD) -> np.ndarray:
        """(H, W) bool array: cells with occupancy probability below ``threshold``."""
        with np.errstate(invalid="ignore"):
            return self.data < threshold

    def replace(self, **changes) -> "OccupancyGrid":
        """A copy with some fields changed (``data``, ``resolution``, ``origin``, ``name``)."""
        kwargs = dict(data=self.data, resolution=self.resolution, origin=self.origin, name=self.name)
        kwargs.update(changes)
        return OccupancyGrid(**kwargs)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, OccupancyGrid):
            return NotImplemented
        return (
            self.shape == other.shape
            and self.resolution == other.resolution
            and self.origin == other.origin
            and bool(np.array_equal(self.data, other.data, equal_nan=True))
        )

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        known = self.known
        n = known.size
        return (
            f"OccupancyGrid({self.height}x{self.width}, resolution={self.resolution:g}, "
            f"origin={tuple(round(v, 6) for v in self.origin)}, known={known.sum() / n:.0%}"
            + (f", name={self.name!r}" if self.name else "")
            + ")"
        )

    # -------------------------------------------------------------- ROS values
    @classmethod
    def from_ros(
        cls,
        values: Sequence[int] | np.ndarray,
        width: int,
        height: int,
        resolution: float,
        origin: Sequence[float] = (0.0, 0.0, 0.0),
        name: str | None = None,
    ) -> "OccupancyGrid":
        """Build a grid from ``nav_msgs/OccupancyGrid`` data.

        Parameters
        ----------
        values : (width * height,) int array
            Row-major cell values starting at the lower-left cell: ``-1`` unknown,
            ``0..100`` occupancy in percent.
        width, height : int
            ``info.width`` and ``info.height``.
        resolution : float
            ``info.resolution``.
        origin : (3,) sequence of float
            ``(x, y, yaw)`` of ``info.origin``.
        """
        dims = []
        for label, v in (("width", width), ("height", height)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or int(v) < 0:
                raise MapFormatError(f"must be a non-negative integer, got {v!r}", path=name, field=label)
            dims.append(int(v))
        w, h = dims
        vals = np.asarray(values)
        if vals.dtype.kind not in "iub":
            raise MapFormatError(f"cell values must be integers (int8), got {vals.dtype}", path=name, field="data")
        if vals.ndim != 1 or vals.size != w * h:
            raise MapFormatError(
                f"data has {vals.size} cells but width x height = {w} x {h} = {w * h}",
                path=name,
                field="data",
            )
        v = vals.astype(np.int64, copy=False).reshape(h, w)[::-1]
        prob = np.where((v >= 0) & (v <= 100), v.astype(np.float32) / 100.0, np.nan)
        return cls(prob, resolution=resolution, origin=tuple(origin), name=name)  # type: ignore[arg-type]

    def to_ros(self) -> np.ndarray:
        """``nav_msgs/OccupancyGrid`` data: ``(W * H,)`` int8, bottom row first, ``-1`` unknown."""
        pct = np.rint(np.nan_to_num(self.data, nan=0.0) * 100.0).astype(np.int8)
        pct[~self.known] = -1
        return np.ascontiguousarray(pct[::-1]).reshape(-1)

    # ------------------------------------------------------------ coordinates
    def pixel_to_metric_matrix(self) -> np.ndarray:
        """(3, 3) float array mapping homogeneous pixels ``(x, y, 1)`` to metres in the map frame."""
        r = self.resolution
        local = np.array([[r, 0.0, 0.5 * r], [0.0, -r, (self.height - 0.5) * r], [0.0, 0.0, 1.0]])
        ox, oy, yaw = self.origin
        c, s = math.cos(yaw), math.sin(yaw)
        pose = np.array([[c, -s, ox], [s, c, oy], [0.0, 0.0, 1.0]])
        return pose @ local

    def metric_to_pixel_matrix(self) -> np.ndarray:
        """(3, 3) float array, the inverse of :meth:`pixel_to_metric_matrix`."""
        return np.linalg.inv(self.pixel_to_metric_matrix())

    def pixel_to_metric(self, xy: np.ndarray | Sequence[Sequence[float]]) -> np.ndarray:
        """Map ``(N, 2)`` image pixels ``(x = column, y = row)`` to ``(N, 2)`` metres."""
        return _apply(self.pixel_to_metric_matrix(), xy)

    def metric_to_pixel(self, xy: np.ndarray | Sequence[Sequence[float]]) -> np.ndarray:
        """Map ``(N, 2)`` metres in the map frame to ``(N, 2)`` image pixels."""
        return _apply(self.metric_to_pixel_matrix(), xy)

    def known_bounds(self, margin: int = 0) -> tuple[int, int, int, int] | None:
        """``(x0, y0, x1, y1)``: the known cells' bounding box (end exclusive) grown by
        ``margin`` cells and clipped to the map; ``None`` when no cell is known."""
        known = self.known
        rows = np.flatnonzero(known.any(1))
        if len(rows) == 0:
            return None
        cols = np.flatnonzero(known.any(0))
        m = int(margin)
        return (
            max(0, int(cols[0]) - m),
            max(0, int(rows[0]) - m),
            min(self.width, int(cols[-1]) + 1 + m),
            min(self.height, int(rows[-1]) + 1 + m),
        )

    def crop_known(self, margin: int = 0) -> tuple["OccupancyGrid", np.ndarray]:
        """The map cut to :meth:`known_bounds`, and the cut's pixel offset ``(x, y)``.

        Pixel ``p`` of the cut is pixel ``p + offset`` of this map, and the cut's origin
        is set so that every cell keeps its metric coordinates. A map with nothing known,
        or nothing to cut, is returned as it is (offset 0).
        """
        box = self.known_bounds(margin)
        if box is None or box == (0, 0, self.width, self.height):
            return self, np.zeros(2)
        x0, y0, x1, y1 = box
        corner = self.pixel_to_metric([[x0 - 0.5, y1 - 0.5]])[0]  # new lower-left corner
        cut = self.replace(data=self.data[y0:y1, x0:x1], origin=(float(corner[0]), float(corner[1]), self.origin[2]))
        return cut, np.array([x0, y0], dtype=float)

    def corners(self) -> np.ndarray:
        """(4, 2) float array: pixel coordinates of the image's outer corners (cell edges)."""
        h, w = self.shape
        return np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])

    # --------------------------------------------------------------- display
    def render(self, unknown: int = 127) -> np.ndarray:
        """(H, W) uint8 image: free white (255), occupied black (0), unknown grey.

        Intermediate probabilities are shaded linearly, ``(1 - p) * 255``.
        """
        img = np.rint((1.0 - np.nan_to_num(self.data, nan=0.0)) * 255.0).astype(np.uint8)
        img[~self.known] = unknown
        return img


def _apply(matrix: np.ndarray, xy) -> np.ndarray:
    pts = np.asarray(xy, dtype=float).reshape(-1, 2)
    return pts @ matrix[:2, :2].T + matrix[:2, 2]

"""Reading maps from ROS bags and writing merged maps into new ones (no ROS installation).

Bags are read and written with the pure-Python `rosbags <https://gitlab.com/ternaris/rosbags>`_
library:

* ROS 1 bags: one ``.bag`` file (format 2.0, any compression rosbags reads).
* ROS 2 bags: a folder holding ``metadata.yaml`` and its storage files, with the
  ``sqlite3`` (``.db3``) or ``mcap`` (``.mcap``) storage plugin, compressed or not. A
  ``.db3`` or ``.mcap`` file inside such a folder stands for the folder; one without a
  ``metadata.yaml`` next to it is read on its own (rosbags reads bare storage files too).

Maps are ``nav_msgs/OccupancyGrid`` messages (``nav_msgs/msg/OccupancyGrid`` in the
names rosbags uses for both ROS generations).

Conventions
-----------
Metric frames follow ROS: ``x, y`` in metres, yaw in radians, and a map's ``origin`` is
the pose of the lower-left **corner** of its lower-left cell (``info.origin``). The
message's cells are row-major starting at that cell (bottom row first), ``-1`` unknown and
``0..100`` percent; :meth:`OccupancyGrid.from_ros <gridmerge.grid.OccupancyGrid.from_ros>`
turns them into gridmerge's image order (row 0 = top) and probabilities.

What survives a trip through a bag
----------------------------------
* Cell values are whole percentages (int8), as in every ROS map: a probability ``p``
  becomes ``rint(100 p)``.
* ``info.resolution`` is a 32-bit float. :func:`read_bag_maps` returns the *shortest
  decimal* that gives the stored float32 (a map published at 0.05 m/cell reads as
  ``0.05``, not ``0.0500000007``), so every resolution with at most about seven
  significant digits comes back exactly; others come back rounded to float32 precision.
* The origin's yaw is stored as the quaternion ``(0, 0, sin(yaw/2), cos(yaw/2))`` and read
  back in ``[-pi, pi]`` (a yaw outside comes back as the equivalent angle in it). Several
  floats can share one quaternion, so the reader picks the one with the shortest decimal
  form: a yaw written by hand or in a YAML comes back bit for bit from any bag. Bags
  written by gridmerge are exact for every yaw in ``[-pi, pi]`` (denormals aside): where needed, the
  quaternion is moved by an ulp or two (about 1e-16) so that it reads back exactly.

Examples
--------
>>> import tempfile, pathlib
>>> import numpy as np
>>> from gridmerge import OccupancyGrid
>>> tmp = tempfile.TemporaryDirectory()
>>> grid = OccupancyGrid(np.array([[1.0, np.nan], [0.0, 0.5]]), resolution=0.05,
...                      origin=(-1.0, 2.0, 0.5), name="merged")
>>> bag = write_bag(pathlib.Path(tmp.name) / "merged", grid,
...                 [BagTransform("robot1/map", x=1.0, y=0.0, yaw=0.0)], stamp_ns=10**18)
>>> is_bag(bag), sorted(p.name for p in bag.iterdir())
(True, ['merged.db3', 'metadata.yaml'])
>>> bag_topics(bag)
[('/map', 'nav_msgs/msg/OccupancyGrid', 1), ('/tf_static', 'tf2_msgs/msg/TFMessage', 1)]
>>> [back] = read_bag_maps(bag)
>>> back == grid, back.name, back.origin
(True, '/map', (-1.0, 2.0, 0.5))
>>> tmp.cleanup()
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import re
import shutil
import sqlite3
import stat
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable, Iterator, Optional, Sequence, Union

import numpy as np

from ..errors import GridMergeError, InputTooLargeError, MapFormatError, OutputError, _shorten
from ..grid import OccupancyGrid
from ..limits import DEFAULT_LIMITS, Limits
from .atomic import _fsync_folder, _sibling

if TYPE_CHECKING:  # pragma: no cover
    from rosbags.highlevel import AnyReader

__all__ = [
    "BagTransform",
    "is_bag",
    "bag_topics",
    "read_bag_maps",
    "write_bag",
    "write_map_messages",
    "child_frame_for",
    "OCCUPANCY_GRID",
    "TF_MESSAGE",
    "BAG_FORMATS",
    "BAG_STORAGES",
]

PathLike = Union[str, "os.PathLike[str]"]

#: The rosbags name of ``nav_msgs/OccupancyGrid`` (the same for ROS 1 and ROS 2 bags).
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
#: The rosbags name of ``tf2_msgs/TFMessage``.
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
#: Values of ``write_bag(format=...)``: a ROS 1 ``.bag`` file or a ROS 2 bag folder.
BAG_FORMATS = ("ros1", "ros2")
#: Values of ``write_bag(storage=...)`` (ROS 2 storage plugins).
BAG_STORAGES = ("sqlite3", "mcap")

#: ROS 2 bag metadata version written. rosbags 0.11 writes only versions 8 and 9; 8 keeps
#: the QoS profiles in the older string form that ROS 2 releases before Jazzy parse too.
ROS2_BAG_VERSION = 8

_GRID_TYPES = frozenset({OCCUPANCY_GRID, "nav_msgs/OccupancyGrid"})
#: A quaternion counts as a rotation about z when sqrt(x^2 + y^2) / |q| is at most this
#: (a tilt of about 2e-6 rad).
_PLANAR_TOLERANCE = 1e-6
#: Largest stamp written: ROS 2's ``builtin_interfaces/Time.sec`` is an int32.
_MAX_STAMP_NS = 2**31 * 10**9 - 1
_ROS1_BAG_MAGIC = b"#ROSBAG V2.0\n"
_MCAP_MAGIC = b"\x89MCAP0\r\n"
_SQLITE_MAGIC = b"SQLite format 3\x00"
_NAME_RE = re.compile(r"^[^\s\x00]+$")


# ----------------------------------------------------------------------------- rosbags
def _rosbags() -> Any:
    """Import rosbags lazily (it costs ~60 ms, and only bag users need it)."""
    try:
        import rosbags.highlevel  # noqa: F401
        import rosbags.rosbag1  # noqa: F401
        import rosbags.rosbag2  # noqa: F401
        import rosbags.typesys  # noqa: F401
    except ImportError as exc:  # pragma: no cover - rosbags is a dependency
        raise GridMergeError(f"reading and writing ROS bags needs the 'rosbags' package ({exc})") from None
    import rosbags

    return rosbags


@functools.lru_cache(maxsize=None)
def _typestore(ros1: bool) -> Any:
    """The typestore messages are written with: ROS 1 Noetic or ROS 2 Humble.

    Both define (or are given) ``nav_msgs/OccupancyGrid`` and ``tf2_msgs/TFMessage`` with the same
    layout as every other distribution of their ROS generation.
    """
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if TF_MESSAGE not in store.types:
        # rosbags' Noetic store has no tf2_msgs; this is its ROS 1 definition (md5
        # 94810edda583a504dfda3829e70d7eec, as rosbag records it).
        store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms\n", TF_MESSAGE))
    return store


# ----------------------------------------------------------------------------- frames
def child_frame_for(topic: str) -> str:
    """The TF frame name of a map published on ``topic``: the topic without leading ``/``.

    Parameters
    ----------
    topic : str
        A topic name such as ``"/robot1/map"``.

    Returns
    -------
    str
        ``topic`` without its leading slashes; ``"map"`` when nothing is left.

    Examples
    --------
    >>> child_frame_for("/robot1/map"), child_frame_for("map"), child_frame_for("/")
    ('robot1/map', 'map', 'map')
    >>> child_frame_for("/robot1/map_merge")
    'robot1/map_merge'
    """
    frame = str(topic).lstrip("/")
    return frame or "map"


def _check_frame(value: object, what: str) -> str:
    if not isinstance(value, str) or not _NAME_RE.match(value):
        raise ValueError(f"{what} must be a non-empty string without spaces, got {value!r}")
    if value.startswith("/"):
        raise ValueError(
            f"{what} must not start with '/' (tf2 rejects such frames), got {value!r}; "
            f"child_frame_for() turns a topic into a frame name"
        )
    return value


def _check_topic_name(value: object, what: str = "topic") -> str:
    if not isinstance(value, str) or not _NAME_RE.match(value):
        raise ValueError(f"{what} must be a non-empty string without spaces, got {value!r}")
    return value if value.startswith("/") else "/" + value


@dataclass(frozen=True)
class BagTransform:
    """The pose of a child frame in the parent frame, written as one TF entry.

    A point ``p_child`` of the child frame is ``p_parent = R(yaw) p_child + (x, y)`` in
    the parent frame (ROS convention: x, y in metres, yaw in radians, counter-clockwise).
    :func:`write_bag` writes it as a ``geometry_msgs/TransformStamped`` with
    ``header.frame_id`` = the parent frame, ``child_frame_id`` = ``child_frame``,
    translation ``(x, y, 0)`` and rotation ``(0, 0, sin(yaw/2), cos(yaw/2))``.

    Parameters
    ----------
    child_frame : str
        TF name of the child frame (no leading ``/``; see :func:`child_frame_for`).
    x, y : float
        Position of the child frame's origin in the parent frame, metres.
    yaw : float
        Rotation of the child frame in the parent frame, radians.

    Examples
    --------
    >>> t = BagTransform("robot2/map", x=2.0, y=1.0, yaw=1.5707963267948966)
    >>> t.apply([[1.0, 0.0]]).round(12).tolist()  # a point of robot2/map in the parent frame
    [[2.0, 2.0]]
    >>> BagTransform.from_matrix("robot2/map", t.matrix()) == t
    True
    """

    child_frame: str
    x: float
    y: float
    yaw: float

    def __post_init__(self) -> None:
        _check_frame(self.child_frame, "child_frame")
        for name in ("x", "y", "yaw"):
            value = getattr(self, name)
            if isinstance(value, bool):
                raise ValueError(f"{name} must be a number, got {value!r}")
            try:
                number = float(value)
            except (TypeError, ValueError):
                raise ValueError(f"{name} must be a number, got {value!r}") from None
            if not math.isfinite(number):
                raise ValueError(f"{name} must be finite, got {value!r}")
            object.__setattr__(self, name, number)

    @classmethod
    def from_matrix(cls, child_frame: str, matrix: Any, *, max_scale_error: float = 0.01) -> "BagTransform":
        """The transform of a rigid ``(2, 3)`` or ``(3, 3)`` matrix (or an object with ``params``).

        The matrix maps child-frame metres to parent-frame metres (as the metric
        transforms of :func:`gridmerge.transforms.pixel_to_metric` do). TF cannot hold a
        scale, so a matrix whose scale differs from 1 by more than ``max_scale_error``,
        or that mirrors, is refused (``ValueError``); a smaller scale error is dropped.
        """
        m = np.asarray(getattr(matrix, "params", matrix), dtype=float)
        if m.shape not in ((2, 3), (3, 3)) or not np.isfinite(m).all():
            raise ValueError(f"matrix must be a finite (2, 3) or (3, 3) array, got shape {m.shape}")
        det = float(np.linalg.det(m[:2, :2]))
        scale = math.sqrt(abs(det))
        if det <= 0 or abs(scale - 1.0) > max_scale_error:
            raise ValueError(
                f"matrix is not a rigid transform (scale {scale:.6g}{', mirrored' if det < 0 else ''}); "
                f"TF can only hold a rotation and a translation"
            )
        return cls(child_frame, float(m[0, 2]), float(m[1, 2]), math.atan2(m[1, 0], m[0, 0]))

    def matrix(self) -> np.ndarray:
        """``(3, 3)`` float array mapping homogeneous child-frame points to the parent frame."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, -s, self.x], [s, c, self.y], [0.0, 0.0, 1.0]])

    def apply(self, xy: Any) -> np.ndarray:
        """Map ``(N, 2)`` child-frame points (metres) to the parent frame."""
        m = self.matrix()
        return np.asarray(xy, dtype=float).reshape(-1, 2) @ m[:2, :2].T + m[:2, 2]

    def quaternion(self) -> tuple[float, float, float, float]:
        """``(x, y, z, w)`` of the rotation, as written to the bag."""
        return _yaw_to_quaternion(self.yaw)


def _yaw_to_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """``(0, 0, sin(yaw/2), cos(yaw/2))``, nudged by an ulp or two where that is needed
    for :func:`_quaternion_to_yaw` to give back exactly ``yaw`` (for ``|yaw| <= pi``)."""
    z, w = math.sin(yaw / 2.0), math.cos(yaw / 2.0)
    if abs(yaw) > math.pi or _quaternion_to_yaw(0.0, 0.0, z, w) == yaw:
        return (0.0, 0.0, z, w)
    for zz, ww in _nudged(z, w):
        if _quaternion_to_yaw(0.0, 0.0, zz, ww) == yaw:
            return (0.0, 0.0, zz, ww)
    return (0.0, 0.0, z, w)  # pragma: no cover - not seen in millions of random yaws


def _nudged(z: float, w: float, steps: int = 3) -> Iterator[tuple[float, float]]:
    """``(z, w)`` moved by up to ``steps`` ulps each, the smallest moves first."""

    def moved(v: float, k: int) -> float:
        for _ in range(abs(k)):
            v = math.nextafter(v, math.inf if k > 0 else -math.inf)
        return v

    moves = sorted(
        ((i, j) for i in range(-steps, steps + 1) for j in range(-steps, steps + 1) if (i, j) != (0, 0)),
        key=lambda m: (abs(m[0]) + abs(m[1]), m),
    )
    for i, j in moves:
        yield moved(z, i), moved(w, j)


def _quaternion_to_yaw(x: float, y: float, z: float, w: float) -> Optional[float]:
    """The yaw of a rotation about z, in ``[-pi, pi]``; ``None`` if it is not one.

    An all-zero quaternion (what default-constructed ROS 1 C++ messages hold) counts as
    the identity. For a quaternion ``(0, 0, z, w)`` as :func:`_yaw_to_quaternion` writes
    it, the yaw is chosen among the floats next to ``2 atan2(z, w)`` whose
    ``(sin(yaw/2), cos(yaw/2))`` is exactly ``(z, w)``: the one with the shortest decimal
    form (then the nearest). Several floats can share one quaternion; this picks the one
    a person or a YAML file wrote, so such yaws round-trip bit for bit.
    """
    q = [float(v) for v in (x, y, z, w)]
    if not all(math.isfinite(v) for v in q):
        return None
    norm = math.sqrt(sum(v * v for v in q))
    if norm == 0.0:
        return 0.0
    if math.hypot(q[0], q[1]) > _PLANAR_TOLERANCE * norm:
        return None
    if q[3] < 0.0:  # q and -q are the same rotation; pick the one with w >= 0
        q = [-v for v in q]
    yaw = 2.0 * math.atan2(q[2], q[3])  # in [-pi, pi] as w >= 0
    if q[0] != 0.0 or q[1] != 0.0:
        return yaw
    candidates = [yaw]
    up = down = yaw
    for _ in range(4):
        up, down = math.nextafter(up, math.inf), math.nextafter(down, -math.inf)
        candidates += [up, down]
    exact = [c for c in candidates if abs(c) <= math.pi and (math.sin(c / 2.0), math.cos(c / 2.0)) == (q[2], q[3])]
    if not exact:
        return yaw
    return min(exact, key=lambda c: (len(repr(c)), abs(c - yaw)))


def _resolution_from_float32(value: float) -> float:
    """The shortest decimal that rounds to the float32 ``value`` (0.05, not 0.0500000007)."""
    f32 = np.float32(value)
    return float(str(f32)) if np.isfinite(f32) else float(value)


# ----------------------------------------------------------------------------- finding bags
def is_bag(path: PathLike) -> bool:
    """Whether ``path`` names a ROS bag (decided from the name, not the content).

    True for a path ending in ``.bag`` (ROS 1), ``.db3`` or ``.mcap`` (ROS 2 storage
    files; they need not exist), a folder holding a ``metadata.yaml`` (a ROS 2 bag), and
    the ``metadata.yaml`` of such a folder. The suffixes are compared case-sensitively,
    as rosbags does. :func:`read_bag_maps` says what is wrong with a path that is named
    like a bag but is none.

    Examples
    --------
    >>> is_bag("run.bag"), is_bag("run_0.mcap"), is_bag("run_0.db3"), is_bag("map.yaml")
    (True, True, True, False)
    """
    try:
        p = Path(path)
    except TypeError:
        return False
    if p.suffix in (".bag", ".db3", ".mcap"):
        return True
    try:
        if p.is_dir():
            return (p / "metadata.yaml").is_file()
        return p.name == "metadata.yaml" and p.is_file() and _looks_like_bag_metadata(p)
    except OSError:
        return False


def _looks_like_bag_metadata(path: Path) -> bool:
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError:
        return False
    return b"rosbag2_bagfile_information" in head


def _resolve_one(path: PathLike) -> tuple[Path, bool]:
    """``(path given to rosbags, is ROS 1)`` for one bag path; MapFormatError if none."""
    p = Path(path)
    if not os.path.lexists(p):
        raise MapFormatError("no such file or folder", path=p)
    if p.is_dir():
        if not (p / "metadata.yaml").is_file():
            raise MapFormatError(
                "not a ROS bag: a folder without metadata.yaml (a ROS 2 bag folder has one)", path=p
            )
        if p.suffix == ".bag":
            raise MapFormatError(
                "a ROS 2 bag folder whose name ends in .bag cannot be read (rosbags takes it for a ROS 1 "
                "bag); rename the folder",
                path=p,
            )
        return p, False
    if p.name == "metadata.yaml" and _looks_like_bag_metadata(p):
        return p.parent, False
    if p.suffix == ".bag":
        _check_magic(p, _ROS1_BAG_MAGIC, "a ROS 1 bag (format 2.0)")
        return p, True
    if p.suffix in (".db3", ".mcap"):
        if (p.parent / "metadata.yaml").is_file():
            return p.parent, False
        if p.suffix == ".mcap":
            _check_magic(p, _MCAP_MAGIC, "an MCAP file")
        else:
            _check_magic(p, _SQLITE_MAGIC, "an SQLite database")
        return p, False
    raise MapFormatError(
        "not a ROS bag: expected a ROS 1 .bag file, a ROS 2 bag folder (with metadata.yaml), "
        "or a ROS 2 .db3/.mcap file",
        path=p,
    )


def _check_magic(path: Path, magic: bytes, what: str) -> None:
    """MapFormatError unless the file starts with ``magic`` (clearer than rosbags' errors)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(len(magic))
    except IsADirectoryError:
        raise MapFormatError(f"is a folder, not {what}", path=path) from None
    except OSError as exc:
        raise MapFormatError(f"cannot read: {exc.strerror or exc}", path=path) from None
    if head != magic:
        found = "the file is empty" if not head else f"it starts with {head[:16]!r}"
        if magic == _ROS1_BAG_MAGIC and head.startswith(b"#ROSBAG V"):
            found = f"it is a {head.decode('ascii', 'replace').strip()[1:]} bag; rosbags reads format 2.0 only"
        raise MapFormatError(f"not {what} ({found})", path=path)


def _resolve(path: Union[PathLike, Sequence[PathLike]]) -> tuple[list[Path], str]:
    """The bags to open and the label that names them in messages."""
    if isinstance(path, (list, tuple)):
        if not path:
            raise GridMergeError("no bag given")
        resolved = [_resolve_one(p) for p in path]
        kinds = {ros1 for _, ros1 in resolved}
        if len(kinds) > 1:
            raise MapFormatError(
                "cannot read ROS 1 and ROS 2 bags together", path=", ".join(str(p) for p in path)
            )
        paths = [p for p, _ in resolved]
        if len({os.path.abspath(p) for p in paths}) != len(paths):
            raise MapFormatError("the same bag is given twice", path=", ".join(str(p) for p in path))
        return paths, ", ".join(str(p) for p in path)
    p, _ = _resolve_one(path)
    return [p], str(path)


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return _shorten(text, 300)


@contextlib.contextmanager
def _reading(label: str) -> Iterator[None]:
    """Turn whatever rosbags raises on bad input into a one-line MapFormatError."""
    try:
        yield
    except GridMergeError:
        raise
    except MemoryError:
        raise
    except FileNotFoundError as exc:
        raise MapFormatError(f"cannot read bag: a file is missing ({_one_line(exc)})", path=label) from None
    except PermissionError as exc:
        raise MapFormatError(f"cannot read bag: permission denied ({_one_line(exc)})", path=label) from None
    except Exception as exc:  # noqa: BLE001 - a corrupt bag makes rosbags raise anything
        from rosbags.highlevel.anyreader import AnyReaderError

        kind = "not a readable ROS bag" if isinstance(exc, AnyReaderError) else "corrupt or unreadable bag"
        raise MapFormatError(f"{kind}: {_one_line(exc)}", path=label) from exc


@contextlib.contextmanager
def _open_bag(paths: list[Path], label: str) -> Iterator["AnyReader"]:
    _rosbags()
    from rosbags.highlevel import AnyReader

    with _reading(label):
        # The default typestore is only used by ROS 2 bags that embed no message
        # definitions (recorded before Iron); ROS 1 bags always embed them.
        with AnyReader(paths, default_typestore=_typestore(False)) as reader:
            yield reader


def _msgtypes(info: Any) -> list[str]:
    """The message types of a topic (several in ROS 1 bags with mixed connections)."""
    return sorted({c.msgtype for c in info.connections}) or ([info.msgtype] if info.msgtype else [])


def bag_topics(path: Union[PathLike, Sequence[PathLike]]) -> list[tuple[str, str, int]]:
    """The topics of a bag: ``(topic, message type, message count)``, sorted.

    Message types use rosbags' names (``nav_msgs/msg/OccupancyGrid`` for ROS 1 bags
    too). A topic recorded with several types (possible in ROS 1) has one entry per type.

    Parameters
    ----------
    path : str or path-like, or a list of them
        A bag as :func:`read_bag_maps` takes it.

    Raises
    ------
    MapFormatError
        ``path`` is not a readable bag.
    """
    paths, label = _resolve(path)
    counts: dict[tuple[str, str], int] = {}
    with _open_bag(paths, label) as reader:
        for topic, info in reader.topics.items():
            for conn in info.connections:
                key = (topic, conn.msgtype)
                counts[key] = counts.get(key, 0) + max(0, int(conn.msgcount))
    return [(topic, msgtype, n) for (topic, msgtype), n in sorted(counts.items())]


# ----------------------------------------------------------------------------- reading
def _grid_connections(info: Any) -> list[Any]:
    return [c for c in info.connections if c.msgtype in _GRID_TYPES]


def _describe_topics(names: Iterable[str], limit: int = 12) -> str:
    names = list(names)
    text = ", ".join(names[:limit])
    return text + (f", ... ({len(names) - limit} more)" if len(names) > limit else "")


def _select_topics(topics: dict[str, Any], wanted: Optional[list[str]], label: str) -> list[str]:
    grid_topics = sorted(t for t, info in topics.items() if _grid_connections(info))
    if wanted is None:
        if not grid_topics:
            others = [f"{t} ({' | '.join(_msgtypes(info)) or '?'})" for t, info in sorted(topics.items())]
            raise MapFormatError(
                "no nav_msgs/OccupancyGrid topic in the bag"
                + (f" (its topics: {_describe_topics(others, 8)})" if others else " (it has no topics)"),
                path=label,
            )
        return grid_topics
    chosen = []
    for name in wanted:
        topic = name
        if topic not in topics and not topic.startswith("/") and "/" + topic in topics:
            topic = "/" + topic
        if topic not in topics:
            have = f"its OccupancyGrid topics: {_describe_topics(grid_topics)}" if grid_topics else (
                "it has no OccupancyGrid topic"
            )
            raise MapFormatError(f"topic not found in the bag ({have})", path=label, field=name)
        if not _grid_connections(topics[topic]):
            types = ", ".join(_msgtypes(topics[topic])) or "unknown"
            raise MapFormatError(f"topic has type {types}, not {OCCUPANCY_GRID}", path=label, field=topic)
        chosen.append(topic)
    return chosen


def _check_wanted(topics: Union[None, str, Iterable[str]]) -> Optional[list[str]]:
    if topics is None:
        return None
    names = [topics] if isinstance(topics, str) else list(topics)
    if not names:
        raise GridMergeError("no topic given (pass topics=None to read every OccupancyGrid topic)")
    seen: set[str] = set()
    for name in names:
        if not isinstance(name, str) or not _NAME_RE.match(name):
            raise GridMergeError(f"a topic must be a non-empty string without spaces, got {name!r}")
        key = name if name.startswith("/") else "/" + name
        if key in seen:
            raise GridMergeError(f"topic {name!r} is given twice")
        seen.add(key)
    return names


def _field(msg: Any, dotted: str) -> Any:
    value = msg
    for part in dotted.split("."):
        value = getattr(value, part)
    return value


def _decode_grid(msg: Any, topic: str, label: str, max_pixels: int) -> OccupancyGrid:
    """The grid of a deserialised ``nav_msgs/OccupancyGrid`` message."""

    def fail(message: str, cls: type = MapFormatError, **extra: Any) -> GridMergeError:
        return cls(message, path=label, field=topic, **extra)

    try:
        width = int(_field(msg, "info.width"))
        height = int(_field(msg, "info.height"))
        resolution = float(_field(msg, "info.resolution"))
        pos = _field(msg, "info.origin.position")
        ori = _field(msg, "info.origin.orientation")
        px, py = float(pos.x), float(pos.y)
        q = (float(ori.x), float(ori.y), float(ori.z), float(ori.w))
        data = msg.data
    except (AttributeError, TypeError, ValueError) as exc:
        raise fail(f"message does not have the fields of {OCCUPANCY_GRID} ({_one_line(exc)})") from None
    cells = width * height
    if cells > max_pixels:
        # Checked before any cell is converted: rosbags hands ``data`` over as a view of
        # the raw message, so nothing proportional to the map has been allocated yet.
        raise fail(
            f"map is {width} x {height} = {cells} cells, more than max_pixels = {max_pixels}",
            InputTooLargeError,
            limit="max_pixels",
        )
    try:
        n = len(data)
    except TypeError:
        raise fail("message data is not a sequence") from None
    if n != cells:
        raise fail(f"data has {n} cells but info.width x info.height = {width} x {height} = {cells}")
    if cells == 0:
        raise fail(f"map is empty (info.width x info.height = {width} x {height})")
    if not (math.isfinite(resolution) and resolution > 0):
        raise fail(f"info.resolution must be a finite number > 0, got {resolution!r}")
    if not (math.isfinite(px) and math.isfinite(py)):
        raise fail(f"info.origin.position must be finite, got ({px!r}, {py!r})")
    yaw = _quaternion_to_yaw(*q)
    if yaw is None:
        raise fail(
            f"info.origin.orientation (x, y, z, w) = {tuple(round(v, 9) for v in q)} is not a rotation "
            f"about z (the map is tilted: roll/pitch are not zero) or is not finite"
        )
    values = np.asarray(data)
    if values.dtype.kind not in "iu":
        values = np.asarray(values, dtype=np.int64)
    try:
        return OccupancyGrid.from_ros(
            values, width, height, _resolution_from_float32(resolution), origin=(px, py, yaw), name=topic
        )
    except MapFormatError as exc:  # already checked above; kept as a safety net
        raise MapFormatError(str(exc), path=label) from None


def read_bag_maps(
    path: Union[PathLike, Sequence[PathLike]],
    topics: Union[None, str, Iterable[str]] = None,
    *,
    max_pixels: Optional[int] = None,
    limits: Optional[Limits] = None,
) -> list[OccupancyGrid]:
    """Read the last ``nav_msgs/OccupancyGrid`` message of topics of a ROS 1 or ROS 2 bag.

    The bag is only read (ROS 2 sqlite3 databases are opened read-only and immutable):
    its bytes and modification time are left as they were.

    Parameters
    ----------
    path : str or path-like, or a list of them
        A ROS 1 ``.bag`` file; a ROS 2 bag folder (holding ``metadata.yaml``), its
        ``metadata.yaml``, or one of its ``.db3``/``.mcap`` files (which stands for the
        folder); or a bare ``.db3``/``.mcap`` file without ``metadata.yaml``. A list reads
        several bags of the same ROS generation as one (e.g. a split ROS 1 recording).
    topics : str or iterable of str, optional
        The topics to read, in the order wanted. A name without its leading ``/`` also
        matches the topic with it. Default: every topic of type OccupancyGrid, sorted by
        name (topics of other types are ignored).
    max_pixels : int, optional
        Refuse maps with more cells (``info.width * info.height``); overrides
        ``limits.max_pixels``. Checked before any cell is converted.
    limits : gridmerge.limits.Limits, optional
        Default :data:`gridmerge.limits.DEFAULT_LIMITS`.

    Returns
    -------
    list of OccupancyGrid
        One per topic: the topic's last message (latest bag time stamp; SLAM nodes
        republish a growing map, so the last one is the most complete). ``name`` is the
        topic; ``resolution`` and ``origin`` are ``info.resolution`` and ``info.origin``
        (yaw from its quaternion); see the module documentation for what is exact.

    Raises
    ------
    MapFormatError
        One line naming the bag and the topic: the path is not a bag or is unreadable or
        corrupt; a named topic does not exist (the message lists the OccupancyGrid topics
        there are) or has another type; a topic has no message; the bag has no
        OccupancyGrid topic at all; a message is malformed (data length is not width x
        height, the origin is tilted or not finite, the resolution is not > 0).
        :class:`~gridmerge.errors.InputTooLargeError` (a ``MapFormatError``) when a map
        has more than ``max_pixels`` cells.
    GridMergeError
        ``topics`` is empty or names a topic twice.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> import numpy as np
    >>> from gridmerge import OccupancyGrid
    >>> tmp = tempfile.TemporaryDirectory()
    >>> maps = [("/robot2/map", OccupancyGrid(np.zeros((2, 3)), resolution=0.1), 1),
    ...         ("/robot1/map", OccupancyGrid(np.ones((4, 4)), resolution=0.05), 2)]
    >>> bag = write_map_messages(pathlib.Path(tmp.name) / "robots.bag", maps, format="ros1")
    >>> [(g.name, g.shape) for g in read_bag_maps(bag)]
    [('/robot1/map', (4, 4)), ('/robot2/map', (2, 3))]
    >>> read_bag_maps(bag, ["/robot3/map"])  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    gridmerge.errors.MapFormatError: .../robots.bag: /robot3/map: topic not found in the bag (its OccupancyGrid topics: /robot1/map, /robot2/map)
    >>> tmp.cleanup()
    """
    lim = limits or DEFAULT_LIMITS
    if max_pixels is not None:
        lim = lim.replace(max_pixels=max_pixels)
    wanted = _check_wanted(topics)
    paths, label = _resolve(path)
    with _open_bag(paths, label) as reader:  # turns rosbags' errors into MapFormatError
        infos = reader.topics
        chosen = _select_topics(infos, wanted, label)
        for topic in chosen:
            if all(int(c.msgcount) == 0 for c in _grid_connections(infos[topic])):
                raise MapFormatError("topic has no messages", path=label, field=topic)
        connections = [c for topic in chosen for c in _grid_connections(infos[topic])]
        last: dict[str, tuple[Any, bytes]] = {}
        # Messages come in time order: keep the raw bytes of the latest of each topic
        # only, and deserialise nothing else.
        for conn, _stamp, raw in reader.messages(connections=connections):
            last[conn.topic] = (conn, raw)
        grids = []
        for topic in chosen:
            if topic not in last:
                raise MapFormatError("topic has no messages", path=label, field=topic)
            conn, raw = last.pop(topic)
            msg = reader.deserialize(raw, conn.msgtype)
            grids.append(_decode_grid(msg, topic, label, lim.max_pixels))
            del raw, msg
    return grids


# ----------------------------------------------------------------------------- writing
def _check_stamp(stamp_ns: Optional[int]) -> int:
    if stamp_ns is None:
        return time.time_ns()
    if isinstance(stamp_ns, bool) or not isinstance(stamp_ns, (int, np.integer)):
        raise ValueError(f"stamp_ns must be an integer number of nanoseconds, got {stamp_ns!r}")
    value = int(stamp_ns)
    if not 0 <= value <= _MAX_STAMP_NS:
        raise ValueError(f"stamp_ns must be in [0, {_MAX_STAMP_NS}] (int32 seconds), got {value}")
    return value


def _time(types: dict, stamp_ns: int) -> Any:
    sec, nsec = divmod(stamp_ns, 10**9)
    return types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)


def _header(types: dict, ros1: bool, stamp_ns: int, frame_id: str) -> Any:
    kwargs = {"seq": 0} if ros1 else {}
    return types["std_msgs/msg/Header"](stamp=_time(types, stamp_ns), frame_id=frame_id, **kwargs)


def _grid_message(types: dict, ros1: bool, grid: OccupancyGrid, frame_id: str, stamp_ns: int) -> Any:
    ox, oy, yaw = grid.origin
    qx, qy, qz, qw = _yaw_to_quaternion(yaw)
    info = types["nav_msgs/msg/MapMetaData"](
        map_load_time=_time(types, stamp_ns),
        resolution=float(np.float32(grid.resolution)),
        width=grid.width,
        height=grid.height,
        origin=types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](x=float(ox), y=float(oy), z=0.0),
            orientation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        ),
    )
    return types[OCCUPANCY_GRID](header=_header(types, ros1, stamp_ns, frame_id), info=info, data=grid.to_ros())


def _tf_message(types: dict, ros1: bool, transforms: Sequence[BagTransform], frame_id: str, stamp_ns: int) -> Any:
    entries = []
    for t in transforms:
        qx, qy, qz, qw = t.quaternion()
        entries.append(
            types["geometry_msgs/msg/TransformStamped"](
                header=_header(types, ros1, stamp_ns, frame_id),
                child_frame_id=t.child_frame,
                transform=types["geometry_msgs/msg/Transform"](
                    translation=types["geometry_msgs/msg/Vector3"](x=t.x, y=t.y, z=0.0),
                    rotation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
                ),
            )
        )
    return types[TF_MESSAGE](transforms=entries)


class _Sink:
    """The writer of one bag, hiding the differences between ROS 1 and ROS 2."""

    def __init__(self, writer: Any, ros1: bool):
        self.writer = writer
        self.ros1 = ros1
        self.typestore = _typestore(ros1)
        self.types = self.typestore.types
        self.connections: dict[tuple[str, str], Any] = {}

    def write(self, topic: str, msgtype: str, stamp_ns: int, message: Any) -> None:
        """Write ``message`` on ``topic`` (latched / transient-local, as maps and static TF are)."""
        conn = self.connections.get((topic, msgtype))
        if conn is None:
            if self.ros1:
                conn = self.writer.add_connection(
                    topic, msgtype, typestore=self.typestore, callerid="/gridmerge", latching=1
                )
            else:
                conn = self.writer.add_connection(
                    topic, msgtype, typestore=self.typestore, offered_qos_profiles=[_latched_qos()]
                )
            self.connections[(topic, msgtype)] = conn
        if self.ros1:
            raw = self.typestore.serialize_ros1(message, msgtype)
        else:
            raw = self.typestore.serialize_cdr(message, msgtype)
        self.writer.write(conn, stamp_ns, raw)


def _latched_qos() -> Any:
    """QoS of map_server's ``/map`` and of ``/tf_static``: reliable, transient local, depth 1."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    infinite = QosTime(2147483647, 4294967295)
    return Qos(
        history=QosHistory.KEEP_LAST,
        depth=1,
        reliability=QosReliability.RELIABLE,
        durability=QosDurability.TRANSIENT_LOCAL,
        deadline=infinite,
        lifespan=infinite,
        liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=infinite,
        avoid_ros_namespace_conventions=False,
    )


def _check_output(target: Path, ros1: bool, overwrite: bool) -> None:
    folder = target.parent
    if not folder.is_dir():
        raise OutputError(f"output folder does not exist: {folder}")
    if not os.path.lexists(target):
        return
    if not overwrite:
        raise OutputError(f"{target} exists already (pass overwrite=True to replace it)")
    if ros1:
        if target.is_dir():
            raise OutputError(f"{target} is a folder; a ROS 1 bag is a file, refusing to replace it")
        return
    if not target.is_dir() or target.is_symlink():
        raise OutputError(f"{target} exists and is not a folder; a ROS 2 bag is a folder, refusing to replace it")
    try:
        empty = not any(target.iterdir())
    except OSError as exc:
        raise OutputError(f"cannot read {target}: {exc.strerror or exc}") from None
    if not empty and not (target / "metadata.yaml").is_file():
        raise OutputError(f"{target} is a folder but not a ROS 2 bag (no metadata.yaml); refusing to replace it")


def _make_staging(target: Path) -> Path:
    """A new hidden folder next to ``target`` to build the bag in."""
    while True:
        staging = _sibling(target, "tmp")
        try:
            staging.mkdir()
            return staging
        except FileExistsError:
            continue
        except OSError as exc:
            raise OutputError(f"cannot create a folder in {target.parent}: {exc.strerror or exc}") from None


def _fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_tree(path: Path) -> None:
    if path.is_dir():
        for child in path.iterdir():
            if child.is_file():
                _fsync_file(child)
        _fsync_folder(path)
    else:
        _fsync_file(path)


def _publish(built: Path, target: Path, ros1: bool, overwrite: bool, staging: Path) -> None:
    """Move the complete bag ``built`` to ``target``; the old target stays until then."""
    if not overwrite or not os.path.lexists(target):
        if ros1:
            try:
                os.link(built, target)  # fails if target exists: no race with another writer
                os.unlink(built)
                return
            except FileExistsError:
                raise OutputError(f"{target} exists already (pass overwrite=True to replace it)") from None
            except OSError:
                pass  # no hard links here: check, then rename
        if os.path.lexists(target):
            raise OutputError(f"{target} exists already (pass overwrite=True to replace it)")
        os.rename(built, target)
        return
    if ros1:
        with contextlib.suppress(OSError):
            os.chmod(built, stat.S_IMODE(os.stat(target).st_mode))
        os.replace(built, target)
        return
    # A folder cannot be replaced in one step: move the old bag aside, move the new one
    # in, then delete the old one (and put it back if the second step fails).
    backup = staging / ".previous"
    os.rename(target, backup)
    try:
        os.rename(built, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.rename(backup, target)
        raise


def _write_bag(
    path: PathLike,
    fmt: str,
    storage: str,
    overwrite: bool,
    fill: Callable[[_Sink], None],
) -> Path:
    """Build a bag in a hidden staging folder next to ``path``, then move it into place."""
    if fmt not in BAG_FORMATS:
        raise ValueError(f"format must be one of {BAG_FORMATS}, got {fmt!r}")
    if storage not in BAG_STORAGES:
        raise ValueError(f"storage must be one of {BAG_STORAGES}, got {storage!r}")
    ros1 = fmt == "ros1"
    target = Path(path)
    if not target.name or target.name in (".", ".."):
        raise OutputError(f"not a bag path: {str(path)!r}")
    _check_output(target, ros1, overwrite)
    _rosbags()
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag1 import WriterError as WriterError1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.rosbag2 import WriterError as WriterError2

    staging = _make_staging(target)
    try:
        # The bag is built under the target's own name, so that a ROS 2 bag's storage file
        # is called NAME.db3 / NAME.mcap as metadata.yaml says.
        built = staging / target.name
        try:
            if ros1:
                writer = Writer1(built)
            else:
                plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
                writer = Writer2(built, version=ROS2_BAG_VERSION, storage_plugin=plugin)
            with writer:
                fill(_Sink(writer, ros1))
            _fsync_tree(built)
            _publish(built, target, ros1, overwrite, staging)
        except (WriterError1, WriterError2, sqlite3.Error) as exc:
            raise OutputError(f"cannot write {target}: {_one_line(exc)}") from exc
        except OutputError:
            raise
        except OSError as exc:
            raise OutputError(f"cannot write {target}: {exc.strerror or exc}") from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    _fsync_folder(target.parent)
    return target


def write_map_messages(
    path: PathLike,
    messages: Iterable[tuple[str, OccupancyGrid, int]],
    *,
    format: str = "ros2",
    storage: str = "sqlite3",
    frame_id: str = "map",
    overwrite: bool = False,
) -> Path:
    """Write maps as ``nav_msgs/OccupancyGrid`` messages into a new bag.

    Handy to hand several robots' maps to ROS tools, or to build test data. The output is
    atomic like :func:`write_bag`'s.

    Parameters
    ----------
    path : str or path-like
        The bag to create (see :func:`write_bag`).
    messages : iterable of (topic, OccupancyGrid, stamp_ns)
        Written in this order; a topic may get several messages. ``stamp_ns`` is the
        bag time and the header stamp, in nanoseconds since the epoch.
    format, storage, frame_id, overwrite
        As for :func:`write_bag`; ``frame_id`` is the ``header.frame_id`` of every map.

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    frame = _check_frame(frame_id, "frame_id")
    items = []
    for item in messages:
        try:
            topic, grid, stamp = item
        except (TypeError, ValueError):
            raise ValueError(f"each message must be (topic, OccupancyGrid, stamp_ns), got {item!r}") from None
        if not isinstance(grid, OccupancyGrid):
            raise TypeError(f"expected an OccupancyGrid, got {type(grid).__name__}")
        items.append((_check_topic_name(topic), grid, _check_stamp(stamp)))

    def fill(sink: _Sink) -> None:
        for topic, grid, stamp in items:
            sink.write(topic, OCCUPANCY_GRID, stamp, _grid_message(sink.types, sink.ros1, grid, frame, stamp))

    return _write_bag(path, format, storage, overwrite, fill)


def write_bag(
    path: PathLike,
    grid: OccupancyGrid,
    transforms: Iterable[BagTransform] = (),
    *,
    format: str = "ros2",
    storage: str = "sqlite3",
    map_topic: str = "/map",
    frame_id: str = "map",
    stamp_ns: Optional[int] = None,
    overwrite: bool = False,
) -> Path:
    """Write a (merged) map and the transforms of its input maps into a new bag.

    The bag holds one ``nav_msgs/OccupancyGrid`` message on ``map_topic`` whose
    ``header.frame_id`` is ``frame_id``, ``info.map_load_time`` and header stamp are
    ``stamp_ns``, and ``info`` has the grid's resolution (as float32) and origin (the
    pose of the lower-left cell corner, yaw as a quaternion about z). If ``transforms``
    is not empty, it also holds one ``tf2_msgs/TFMessage`` on ``/tf_static`` with one
    ``geometry_msgs/TransformStamped`` per transform: ``header.frame_id`` = ``frame_id``
    (the parent), ``child_frame_id`` = the transform's ``child_frame``, and the pose of
    the child frame in ``frame_id`` (see :class:`BagTransform`). Both topics are marked
    latched (ROS 1) / reliable + transient local (ROS 2), as map_server and static TF
    publish them, so that ``rosbag play`` / ``ros2 bag play`` hand them to late
    subscribers.

    The output is atomic: the bag is built in a hidden folder next to ``path``
    (``.NAME.tmp-PID-N``), flushed to disk and moved into place only when complete; on any
    failure nothing is left behind and an existing ``path`` is untouched.

    Parameters
    ----------
    path : str or path-like
        ``format="ros1"``: the ``.bag`` file to create. ``format="ros2"``: the bag folder
        to create (it will hold ``NAME.db3`` or ``NAME.mcap`` and ``metadata.yaml``).
        Its folder must exist.
    grid : OccupancyGrid
        The map. Cells are written as whole percentages (``rint(100 p)``, -1 unknown).
    transforms : iterable of BagTransform, optional
        Poses of other frames (e.g. each robot's map frame) in ``frame_id``.
    format : {"ros2", "ros1"}
    storage : {"sqlite3", "mcap"}
        ROS 2 storage plugin (ignored for ROS 1). ROS 2 bags are written with metadata
        version 8 (readable by ROS 2 Jazzy and later; see the module notes).
    map_topic : str
        Topic of the map; a leading ``/`` is added if missing.
    frame_id : str
        TF frame of the map and parent frame of the transforms (no leading ``/``).
    stamp_ns : int, optional
        Time stamp in nanoseconds since the epoch (default: now).
    overwrite : bool
        Replace an existing bag at ``path`` (only a file for ROS 1; only a ROS 2 bag
        folder, or an empty folder, for ROS 2). The old bag stays until the new one is
        complete. Default: an existing ``path`` is an error.

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    OutputError
        ``path`` exists (and ``overwrite`` is false, or it is not something a bag may
        replace), its folder does not exist, or the bag cannot be written.
    ValueError
        An invalid ``format``, ``storage``, topic, frame name or ``stamp_ns``; a child
        frame given twice or equal to ``frame_id``.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> import numpy as np
    >>> from gridmerge import OccupancyGrid
    >>> tmp = tempfile.TemporaryDirectory()
    >>> grid = OccupancyGrid(np.zeros((3, 4)), resolution=0.1)
    >>> out = write_bag(pathlib.Path(tmp.name) / "merged.bag", grid, format="ros1",
    ...                 transforms=[BagTransform(child_frame_for("/robot1/map"), 0.0, 0.0, 0.0)])
    >>> out.name, bag_topics(out)[1]
    ('merged.bag', ('/tf_static', 'tf2_msgs/msg/TFMessage', 1))
    >>> write_bag(out, grid, format="ros1")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    gridmerge.errors.OutputError: .../merged.bag exists already (pass overwrite=True to replace it)
    >>> tmp.cleanup()
    """
    if not isinstance(grid, OccupancyGrid):
        raise TypeError(f"grid must be an OccupancyGrid, got {type(grid).__name__}")
    if not (np.isfinite(np.float32(grid.resolution)) and np.float32(grid.resolution) > 0):
        raise ValueError(f"resolution {grid.resolution!r} does not fit a float32 (nav_msgs/MapMetaData)")
    topic = _check_topic_name(map_topic, "map_topic")
    frame = _check_frame(frame_id, "frame_id")
    stamp = _check_stamp(stamp_ns)
    tfs = []
    for t in transforms:
        if not isinstance(t, BagTransform):
            try:
                t = BagTransform(*t)
            except TypeError:
                raise TypeError(f"transforms must be BagTransform objects, got {t!r}") from None
        tfs.append(t)
    children = [t.child_frame for t in tfs]
    for child in children:
        if child == frame:
            raise ValueError(f"child frame {child!r} is the parent frame_id; give the maps other frame names")
        if children.count(child) > 1:
            raise ValueError(f"child frame {child!r} is given twice")

    def fill(sink: _Sink) -> None:
        sink.write(topic, OCCUPANCY_GRID, stamp, _grid_message(sink.types, sink.ros1, grid, frame, stamp))
        if tfs:
            sink.write("/tf_static", TF_MESSAGE, stamp, _tf_message(sink.types, sink.ros1, tfs, frame, stamp))

    return _write_bag(path, format, storage, overwrite, fill)

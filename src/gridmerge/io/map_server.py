"""Loading and saving maps in the format of ROS map_server.

A ROS map is a YAML file naming an image and giving its metric frame::

    image: map.pgm            # relative to the YAML's folder, or absolute
    resolution: 0.05          # metres per cell
    origin: [-10.0, -5.0, 0.0]  # x, y, yaw of the lower-left corner of the image
    negate: 0
    occupied_thresh: 0.65
    free_thresh: 0.196
    mode: trinary             # optional: trinary (default), scale or raw

How pixels become occupancy (ROS 1 map_server, ``image_loader.cpp``)
--------------------------------------------------------------------
:func:`pixels_to_ros` reproduces ``map_server::loadMapFromFile`` of ROS 1 (noetic), which
reads the image with SDL_image, exactly (same double arithmetic, same truncations):

1. ``color_avg`` is the mean of the pixel's channels. The alpha channel, if the image
   has one, is **included in the mean in trinary mode** ("to preserve existing
   behavior") and excluded in scale and raw modes. SDL_image turns grey + alpha into
   RGBA, so a grey + alpha pixel averages to ``(3 * grey + alpha) / 4`` in trinary mode.
2. If ``negate``: ``color_avg = 255 - color_avg``.
3. ``raw`` mode: the cell value is ``(unsigned char) color_avg`` (truncated) stored in
   the ``int8`` map data, so 0..100 are occupancy percentages, 255 becomes -1 (unknown),
   101..127 stay as out-of-range positive values and 128..254 wrap to negative values;
   gridmerge treats everything outside 0..100 as unknown.
4. Otherwise ``occ = (255 - color_avg) / 255``; ``occ > occupied_thresh`` gives 100,
   else ``occ < free_thresh`` gives 0, else in trinary mode -1 (unknown). In scale mode
   the cell is unknown when ``alpha < 1``, i.e. fully transparent (``alpha == 0``), and
   otherwise ``(unsigned char)(1 + 98 * (occ - free_thresh) / (occupied_thresh -
   free_thresh))``, a value in 1..99. ROS 1 takes "alpha" to be the **last byte of the
   pixel**: for an RGB image without alpha that is the blue channel, so in scale mode an
   intermediate pixel whose blue value is 0 is unknown. This quirk is reproduced.

The ROS values ``v`` become probabilities ``v / 100`` (``NaN`` for unknown) through
:meth:`OccupancyGrid.from_ros`; the grid's row 0 is the image's top row.

Where ROS 2 (nav2_map_server, ``map_io.cpp``, GraphicsMagick) differs
---------------------------------------------------------------------
* scale mode: the value is ``rint(100 * ratio)`` (0..100) instead of
  ``trunc(1 + 98 * ratio)`` (1..99), and a pixel is unknown as soon as it is not fully
  opaque (``alpha != 255``) instead of fully transparent; an RGB image has no alpha
  there (no blue-channel quirk).
* raw mode: the value is ``round(255 * shade)`` of the **un-negated** shade (``negate``
  is ignored), and every value outside 0..100 becomes -1.
* ``occupied_thresh``, ``free_thresh``, ``origin`` and ``negate`` are required by both
  ROS 1 and ROS 2 map_server; gridmerge gives them map_server's usual defaults (0.65,
  0.196, ``[0, 0, 0]``, 0) when missing.
* Reading pixels (a ROS 1 quirk, not reproduced): SDL_image hands palette PNGs to
  map_server as palette *indices*, and ignores a ``tRNS`` transparency chunk of grey or
  RGB PNGs; gridmerge, like ROS 2, uses the palette's colours and OpenCV's alpha.
* nav2's map_saver writes ``free_thresh: 0.25`` and classifies cells with the
  thresholds it was given; ROS 1's map_saver writes ``free_thresh: 0.196`` and
  classifies ``0 <= v <= 25`` as free, ``v >= 65`` as occupied (see :func:`save_map` for
  gridmerge's rule).

Other map files
---------------
Bare images (``.pgm``, ``.png``, ...) are read as map_server would read them with the
default thresholds, trinary mode and ``negate: 0``. ``.npy`` files hold a 2-D array in
image order (row 0 = top): integers are ROS percentages (outside 0..100 = unknown),
floats are probabilities in [0, 1] (``NaN`` = unknown).
"""

from __future__ import annotations

import io
import math
import os
import reprlib
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence, Union

import numpy as np
import yaml

from ..errors import InputTooLargeError, MapFormatError
from ..grid import DEFAULT_RESOLUTION, FREE_THRESHOLD, OCCUPIED_THRESHOLD, OccupancyGrid
from ..limits import DEFAULT_LIMITS, Limits
from .atomic import atomic_files, atomic_write
from .images import _read_at_most, encode_pgm, encode_png, open_input, read_image

__all__ = [
    "load_map",
    "save_map",
    "pixels_to_ros",
    "grid_to_pixels",
    "MAP_MODES",
    "SAVE_MODES",
    "IMAGE_SUFFIXES",
    "YAML_SUFFIXES",
    "yaml_image_path",
]

PathLike = Union[str, "os.PathLike[str]"]

#: The ``mode`` values of a map_server YAML.
MAP_MODES = ("trinary", "scale", "raw")
#: The modes :func:`save_map` writes.
SAVE_MODES = ("trinary", "raw")
#: Extensions of map_server YAML files.
YAML_SUFFIXES = (".yaml", ".yml")
#: Extensions read as bare map images (compared case-insensitively).
IMAGE_SUFFIXES = frozenset(
    {".pgm", ".ppm", ".pnm", ".pbm", ".png", ".bmp", ".jpg", ".jpeg", ".tif", ".tiff", ".webp"}
)

#: Pixel values map_saver writes in trinary mode.
FREE_PIXEL, OCCUPIED_PIXEL, UNKNOWN_PIXEL = 254, 0, 205

#: Cells of the pixel-conversion blocks (bounds the temporaries of colour images).
_BLOCK_PIXELS = 1 << 20


# --------------------------------------------------------------------------- pixels
def pixels_to_ros(
    img: np.ndarray,
    *,
    mode: str = "trinary",
    negate: bool = False,
    occupied_thresh: float = OCCUPIED_THRESHOLD,
    free_thresh: float = FREE_THRESHOLD,
) -> np.ndarray:
    """Convert image pixels to ROS occupancy values exactly as ROS 1 map_server does.

    See the module documentation for the rules and for where ROS 2 differs.

    Parameters
    ----------
    img : (H, W), (H, W, 2), (H, W, 3) or (H, W, 4) uint8 array
        Grey, grey + alpha, BGR or BGRA (as returned by :func:`~gridmerge.io.read_image`).
    mode : {"trinary", "scale", "raw"}
    negate : bool
        Swap black and white before anything else.
    occupied_thresh, free_thresh : float
        The YAML's thresholds (``occ`` is compared with ``>`` and ``<``).

    Returns
    -------
    (H, W) int8 array
        ROS values in **image order** (row 0 = top): 0..100, or -1 (and in raw mode
        possibly other values outside 0..100) for unknown.

    Examples
    --------
    >>> import numpy as np
    >>> pixels_to_ros(np.array([[254, 0, 205, 100]], dtype=np.uint8)).tolist()
    [[0, 100, -1, -1]]
    >>> pixels_to_ros(np.array([[0, 100, 255]], dtype=np.uint8), mode="raw").tolist()
    [[0, 100, -1]]
    >>> pixels_to_ros(np.array([[150]], dtype=np.uint8), mode="scale").tolist()
    [[47]]
    """
    if mode not in MAP_MODES:
        raise ValueError(f"mode must be one of {MAP_MODES}, got {mode!r}")
    arr = np.asarray(img)
    if arr.dtype != np.uint8:
        raise ValueError(f"image must be uint8, got {arr.dtype}")
    if arr.ndim == 2:
        # Grey: apply the rule to the 256 possible values once, then look them up.
        levels = np.arange(256, dtype=np.uint8).reshape(256, 1, 1)
        return _pixels_to_ros(levels, mode, negate, occupied_thresh, free_thresh)[:, 0][arr]
    if arr.ndim != 3 or arr.shape[2] not in (1, 2, 3, 4):
        raise ValueError(f"image must be (H, W) or (H, W, C) with C in 1..4, got shape {arr.shape}")
    out = np.empty(arr.shape[:2], dtype=np.int8)
    # Row blocks of about _BLOCK_PIXELS cells: the float temporaries stay small.
    rows = max(1, _BLOCK_PIXELS // max(1, arr.shape[1]))
    for top in range(0, arr.shape[0], rows):
        block = arr[top : top + rows]
        if block.shape[2] == 2:  # grey + alpha: SDL_image hands it over as RGBA
            block = block[:, :, [0, 0, 0, 1]]
        out[top : top + rows] = _pixels_to_ros(block, mode, negate, occupied_thresh, free_thresh)
    return out


def _pixels_to_ros(arr: np.ndarray, mode: str, negate: bool, occupied_thresh: float, free_thresh: float) -> np.ndarray:
    """:func:`pixels_to_ros` of an (H, W, C) uint8 array, C in (1, 3, 4)."""
    n_channels = arr.shape[2]
    has_alpha = n_channels == 4
    avg_channels = n_channels if (mode == "trinary" or not has_alpha) else n_channels - 1
    color_avg = arr[:, :, :avg_channels].sum(axis=2, dtype=np.int64) / float(avg_channels)
    if negate:
        color_avg = 255 - color_avg
    if mode == "raw":
        return np.trunc(color_avg).astype(np.uint8).view(np.int8)

    occ = (255 - color_avg) / 255.0
    if n_channels == 1:
        transparent = np.zeros(occ.shape, dtype=bool)
    else:
        # ROS 1 reads "alpha" from the pixel's last byte in SDL's RGB(A) order: alpha for
        # RGBA, blue for RGB, which is channel 0 of OpenCV's BGR.
        transparent = arr[:, :, 3 if has_alpha else 0] < 1
    unknown = np.ones(occ.shape, dtype=bool) if mode == "trinary" else transparent
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ratio = (occ - free_thresh) / (occupied_thresh - free_thresh)
        scaled = np.trunc(1 + 98 * ratio)
    # Only cells with free_thresh <= occ <= occupied_thresh use it (1..99); clip the rest.
    scaled = np.clip(np.nan_to_num(scaled, nan=-1.0), -1, 100).astype(np.int8)
    return np.select(
        [occ > occupied_thresh, occ < free_thresh, unknown],
        [np.int8(100), np.int8(0), np.int8(-1)],
        default=scaled,
    ).astype(np.int8)


def grid_to_pixels(grid: OccupancyGrid, mode: str = "trinary") -> np.ndarray:
    """The grey image :func:`save_map` writes for ``grid``.

    Cells are first rounded to ROS percentages ``v`` as :meth:`OccupancyGrid.to_ros`
    does (``v = rint(100 p)``).

    * ``"trinary"``: like map_saver, 254 for free, 0 for occupied, 205 for unknown. A cell
      is free when ``v / 100 < free_thresh`` (0.196, so ``v <= 19``) and occupied when
      ``v / 100 > occupied_thresh`` (0.65, so ``v >= 66``): the classification
      map_server applies to a probability with the thresholds written in the YAML.
      Reading the file back gives 0, 1 or ``NaN`` for exactly these cells, so a trinary
      map round-trips unchanged.
    * ``"raw"``: the pixel is ``v`` (0..100) and 255 for unknown; map_server's raw mode
      reads every value back unchanged.

    Parameters
    ----------
    grid : OccupancyGrid
    mode : {"trinary", "raw"}

    Returns
    -------
    (H, W) uint8 array, row 0 = top.

    Examples
    --------
    >>> import numpy as np
    >>> from gridmerge import OccupancyGrid
    >>> g = OccupancyGrid(np.array([[0.0, 0.19, 0.2, 0.65, 0.66, 1.0, np.nan]]))
    >>> grid_to_pixels(g).tolist()
    [[254, 254, 205, 205, 0, 0, 205]]
    >>> grid_to_pixels(g, "raw").tolist()
    [[0, 19, 20, 65, 66, 100, 255]]
    """
    if mode not in SAVE_MODES:
        raise ValueError(f"mode must be one of {SAVE_MODES}, got {mode!r}")
    # int8 percentages (-1 unknown) seen as uint8: 0..100 stay, -1 becomes 255
    percent = np.ascontiguousarray(grid.to_ros().reshape(grid.height, grid.width)[::-1]).view(np.uint8)
    if mode == "raw":
        return percent
    levels = np.arange(256)
    prob = levels / 100.0
    lut = np.full(256, UNKNOWN_PIXEL, dtype=np.uint8)
    lut[(levels <= 100) & (prob < FREE_THRESHOLD)] = FREE_PIXEL
    lut[(levels <= 100) & (prob > OCCUPIED_THRESHOLD)] = OCCUPIED_PIXEL
    return lut[percent]


def _grid_from_ros(values: np.ndarray, resolution, origin, name: str) -> OccupancyGrid:
    """A grid from (H, W) ROS values in image order."""
    height, width = values.shape
    return OccupancyGrid.from_ros(values[::-1].reshape(-1), width, height, resolution, origin, name=name)


# ----------------------------------------------------------------------------- YAML
_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxlist, _REPR.maxtuple, _REPR.maxdict, _REPR.maxset = 2, 4, 4, 3, 3
_REPR.maxstring, _REPR.maxlong, _REPR.maxother = 40, 40, 40


def _show(value: Any) -> str:
    """A short, one-line ``repr`` of a YAML value, in bounded time (YAML aliases can make
    a small file hold a structure whose full ``repr`` has billions of characters)."""
    try:
        text = _REPR.repr(value)
    except Exception:  # noqa: BLE001 - a value that cannot even be shown
        text = f"<{type(value).__name__}>"
    text = " ".join(text.split())
    return text if len(text) <= 60 else text[:57] + "..."


#: Flow collections (``[...]``, ``{...}``) nested deeper than this are refused before
#: parsing. A map YAML nests none; PyYAML's pure-Python parser takes seconds to reach
#: Python's recursion limit on a few kilobytes of brackets.
_MAX_FLOW_DEPTH = 64


def _flow_depth(raw: bytes) -> int:
    """The deepest nesting of ``[``/``{`` in ``raw``, quotes not excepted (an upper bound
    on the YAML's flow nesting where brackets are balanced)."""
    b = np.frombuffer(raw, np.uint8)
    if b.size == 0:
        return 0
    step = np.isin(b, (ord("["), ord("{"))).astype(np.int32) - np.isin(b, (ord("]"), ord("}"))).astype(np.int32)
    return int(np.cumsum(step).max())


def _read_yaml(path: Path, max_bytes: int) -> Any:
    with open_input(path, "a map YAML file") as fh:
        raw = _read_at_most(fh, max_bytes + 1)
    if len(raw) > max_bytes:
        raise InputTooLargeError(
            f"too large for a map YAML file: more than the limit of {max_bytes} bytes (max_yaml_bytes)",
            path=path,
            limit="max_yaml_bytes",
        )
    try:
        if b"\x00" in raw:
            raise UnicodeDecodeError("utf-8", raw, 0, 1, "NUL byte")
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise MapFormatError("not a YAML text file (binary data)", path=path) from None
    if _flow_depth(raw) > _MAX_FLOW_DEPTH:
        raise MapFormatError("invalid YAML: nested too deeply", path=path)
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        problem = getattr(exc, "problem", None) or "syntax error"
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        message = f"invalid YAML: {problem}{where}".replace("\n", " ")
        raise MapFormatError(message, path=path) from None
    except RecursionError:
        raise MapFormatError("invalid YAML: nested too deeply", path=path) from None
    except (ValueError, OverflowError, TypeError) as exc:  # e.g. an integer of 5000 digits
        reason = (str(exc).splitlines() or [type(exc).__name__])[0].split(": ")[0][:100]
        raise MapFormatError(f"invalid YAML: {reason}", path=path) from None


def _as_float(value: Any, key: str, path: Path) -> float:
    try:
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise ValueError
        number = float(value)
    except (ValueError, OverflowError):
        raise MapFormatError(f"must be a number, got {_show(value)}", path=path, field=key) from None
    if not math.isfinite(number):
        raise MapFormatError(f"must be a finite number, got {_show(value)}", path=path, field=key)
    return number


def _number(doc: Mapping, key: str, path: Path, default: Optional[float] = None) -> float:
    """``doc[key]`` as a finite float; ``default`` if missing or null (required if no default)."""
    if doc.get(key) is None:
        if default is None:
            raise MapFormatError("missing (required key)", path=path, field=key)
        return default
    return _as_float(doc[key], key, path)


def _parse_map_yaml(path: Path, max_yaml_bytes: int = DEFAULT_LIMITS.max_yaml_bytes) -> dict:
    """Validated map_server parameters of a YAML file."""
    doc = _read_yaml(path, max_yaml_bytes)
    if not isinstance(doc, dict):
        kind = "is empty" if doc is None else f"holds a {type(doc).__name__}"
        raise MapFormatError(
            f"missing: the file {kind}, not a mapping of map_server keys (image, resolution, origin, ...)",
            path=path,
            field="image",
        )

    image = doc.get("image")
    if image is None:
        raise MapFormatError("missing (required key)", path=path, field="image")
    if not isinstance(image, str) or not image.strip():
        raise MapFormatError(f"must be a non-empty file name, got {_show(image)}", path=path, field="image")
    image_path = Path(image)
    if not image_path.is_absolute():
        image_path = path.parent / image_path

    resolution = _number(doc, "resolution", path)
    if resolution <= 0:
        raise MapFormatError(f"must be > 0, got {_show(doc['resolution'])}", path=path, field="resolution")

    origin: Sequence[float] = (0.0, 0.0, 0.0)
    if doc.get("origin") is not None:
        raw_origin = doc["origin"]
        try:
            if not isinstance(raw_origin, (list, tuple)) or len(raw_origin) != 3:
                raise ValueError
            origin = tuple(_as_float(v, "origin", path) for v in raw_origin)
        except ValueError:  # MapFormatError is a ValueError too
            raise MapFormatError(
                f"must be three finite numbers [x, y, yaw], got {_show(raw_origin)}", path=path, field="origin"
            ) from None

    negate = doc.get("negate", 0)
    if negate is None:
        negate = 0
    if not isinstance(negate, int) or negate not in (0, 1):  # bool is an int
        raise MapFormatError(f"must be 0 or 1, got {_show(negate)}", path=path, field="negate")

    thresholds = {}
    for key, default in (("occupied_thresh", OCCUPIED_THRESHOLD), ("free_thresh", FREE_THRESHOLD)):
        value = _number(doc, key, path, default)
        if not 0.0 <= value <= 1.0:
            raise MapFormatError(f"must be in [0, 1], got {_show(doc[key])}", path=path, field=key)
        thresholds[key] = value
    if thresholds["free_thresh"] >= thresholds["occupied_thresh"]:
        raise MapFormatError(
            f"must be smaller than occupied_thresh ({thresholds['occupied_thresh']:g}), "
            f"got {thresholds['free_thresh']:g}",
            path=path,
            field="free_thresh",
        )

    mode = doc.get("mode")
    if mode is None:
        mode = "trinary"
    if mode not in MAP_MODES:
        raise MapFormatError(f"must be one of {', '.join(MAP_MODES)}, got {_show(mode)}", path=path, field="mode")

    return dict(
        image=image_path,
        resolution=resolution,
        origin=origin,
        negate=bool(negate),
        mode=mode,
        **thresholds,
    )


def _yaml_float(value: float) -> str:
    """The shortest text that YAML 1.1 (PyYAML) and yaml-cpp read back as this float."""
    text = repr(float(value))
    if "e" in text and "." not in text:  # '1e-05' is a string to PyYAML; '1.0e-05' is a float
        mantissa, exponent = text.split("e")
        text = f"{mantissa}.0e{exponent}"
    return text


def _map_yaml(image_name: str, grid: OccupancyGrid, mode: str) -> str:
    image_line = yaml.safe_dump({"image": image_name}, allow_unicode=True, width=1 << 16).strip()
    origin = ", ".join(_yaml_float(v) for v in grid.origin)
    return (
        f"{image_line}\n"
        f"resolution: {_yaml_float(grid.resolution)}\n"
        f"origin: [{origin}]\n"
        f"negate: 0\n"
        f"occupied_thresh: {_yaml_float(OCCUPIED_THRESHOLD)}\n"
        f"free_thresh: {_yaml_float(FREE_THRESHOLD)}\n"
        f"mode: {mode}\n"
    )


# ------------------------------------------------------------------------- loaders
def _load_yaml_map(path: Path, resolution, origin, limits: Limits) -> OccupancyGrid:
    params = _parse_map_yaml(path, limits.max_yaml_bytes)
    try:
        img = read_image(params["image"], max_pixels=limits.max_pixels)
    except InputTooLargeError as exc:
        raise InputTooLargeError(str(exc), path=path, field="image", limit=exc.limit) from None
    except MapFormatError as exc:
        raise MapFormatError(str(exc), path=path, field="image") from None
    values = pixels_to_ros(
        img,
        mode=params["mode"],
        negate=params["negate"],
        occupied_thresh=params["occupied_thresh"],
        free_thresh=params["free_thresh"],
    )
    return _grid_from_ros(
        values,
        params["resolution"] if resolution is None else resolution,
        params["origin"] if origin is None else origin,
        str(path),
    )


def _load_image_map(path: Path, resolution, origin, max_pixels: int) -> OccupancyGrid:
    values = pixels_to_ros(read_image(path, max_pixels=max_pixels))
    return _grid_from_ros(values, resolution, origin, str(path))


def _npy_header(fh) -> tuple[tuple, np.dtype]:
    """Shape and dtype from a .npy header (format versions 1 and 2)."""
    version = np.lib.format.read_magic(fh)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
    elif version == (2, 0):
        shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
    else:
        raise ValueError(f"unsupported .npy format version {version[0]}.{version[1]}")
    return shape, dtype


def _load_npy(path: Path, resolution, origin, max_pixels: int) -> OccupancyGrid:
    with open_input(path, "a .npy file") as fh:
        try:
            shape, dtype = _npy_header(fh)
            if dtype.hasobject or dtype.kind not in "iuf" or dtype.itemsize > 8:
                raise MapFormatError(
                    f"unsupported dtype {_show(dtype.str)}: use integers (ROS percentages) or floats (probabilities)",
                    path=path,
                    field="data",
                )
            cells = math.prod(shape)
            if cells > max_pixels:
                raise InputTooLargeError(
                    f"array of shape {_show(shape)} has {cells} cells, more than the limit of {max_pixels} (max_pixels)",
                    path=path,
                    limit="max_pixels",
                )
            available = os.fstat(fh.fileno()).st_size - fh.tell()
            if cells >= 0 and available < cells * dtype.itemsize:
                raise MapFormatError(
                    f"truncated: {available} of {cells * dtype.itemsize} bytes of array data", path=path, field="data"
                )
            fh.seek(0)
            arr = np.load(fh, allow_pickle=False)
        except (MapFormatError, MemoryError):
            raise
        except Exception as exc:  # noqa: BLE001 - numpy's header parser raises many kinds (tokenize errors too)
            reason = (str(exc).splitlines() or [type(exc).__name__])[0][:100] or type(exc).__name__
            raise MapFormatError(f"not a valid .npy file: {reason}", path=path) from None
    if not isinstance(arr, np.ndarray) or arr.ndim != 2:
        raise MapFormatError(f"must hold a 2-D array, got shape {np.shape(arr)}", path=path, field="data")
    if arr.shape[0] * arr.shape[1] > max_pixels:
        raise InputTooLargeError(
            f"array has {arr.size} cells, more than the limit of {max_pixels} (max_pixels)", path=path, limit="max_pixels"
        )
    if arr.dtype.kind in "iu":  # ROS percentages
        values = np.where((arr >= 0) & (arr <= 100), arr, -1).astype(np.int8)
        return _grid_from_ros(values, resolution, origin, str(path))
    if arr.dtype.kind == "f":  # probabilities, NaN unknown
        return OccupancyGrid(arr, resolution=resolution, origin=origin, name=str(path))
    raise MapFormatError(
        f"unsupported dtype {arr.dtype}: use integers (ROS percentages) or floats (probabilities)",
        path=path,
        field="data",
    )


def load_map(
    path: PathLike,
    *,
    resolution: Optional[float] = None,
    origin: Optional[Sequence[float]] = None,
    max_pixels: Optional[int] = None,
    limits: Optional[Limits] = None,
) -> OccupancyGrid:
    """Load an occupancy grid from a map_server YAML, a bare image or a ``.npy`` file.

    Parameters
    ----------
    path : str or path-like
        ``.yaml``/``.yml``: a ROS map_server map (the image is converted exactly as ROS 1
        map_server converts it, see the module documentation). ``.pgm``, ``.png`` and the
        other :data:`IMAGE_SUFFIXES`: an image read with map_server's defaults
        (trinary, ``negate: 0``, thresholds 0.65 and 0.196). ``.npy``: a 2-D array in
        image order, integers = ROS percentages (outside 0..100 unknown), floats =
        probabilities (``NaN`` unknown).
    resolution : float, optional
        Metres per cell. For images and ``.npy`` files it defaults to
        :data:`gridmerge.grid.DEFAULT_RESOLUTION`; for a YAML, if given, it overrides
        the file's value.
    origin : (3,) sequence of float, optional
        ``(x, y, yaw)`` of the lower-left corner. Defaults to ``(0, 0, 0)`` for images
        and ``.npy`` files; for a YAML, if given, it overrides the file's value.
    max_pixels : int, optional
        Refuse images or arrays with more cells than this (checked from the file's header
        before decoding). Overrides ``limits.max_pixels``.
    limits : gridmerge.limits.Limits, optional
        ``max_pixels`` and ``max_yaml_bytes`` (default
        :data:`gridmerge.limits.DEFAULT_LIMITS`).

    Returns
    -------
    OccupancyGrid
        With ``name`` set to ``str(path)``.

    Raises
    ------
    MapFormatError
        The file is missing, unreadable or malformed, a YAML key is missing or invalid,
        the image is missing or not an image, or the extension is unknown. The message
        is one line naming the file (the YAML for problems with its image) and the
        field. :class:`~gridmerge.errors.InputTooLargeError` (a ``MapFormatError``)
        when a limit is exceeded.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> tmp = tempfile.TemporaryDirectory()
    >>> folder = pathlib.Path(tmp.name)
    >>> _ = (folder / "m.pgm").write_bytes(b"P5\\n3 1\\n255\\n\\xfe\\x00\\xcd")
    >>> _ = (folder / "m.yaml").write_text("image: m.pgm\\nresolution: 0.1\\norigin: [1, 2, 0]\\n")
    >>> grid = load_map(folder / "m.yaml")
    >>> grid.data.tolist(), grid.resolution, grid.origin
    ([[0.0, 1.0, nan]], 0.1, (1.0, 2.0, 0.0))
    >>> tmp.cleanup()
    """
    lim = limits or DEFAULT_LIMITS
    if max_pixels is not None:
        lim = lim.replace(max_pixels=max_pixels)
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix in YAML_SUFFIXES:
        return _load_yaml_map(p, resolution, origin, lim)
    res = DEFAULT_RESOLUTION if resolution is None else resolution
    org = (0.0, 0.0, 0.0) if origin is None else origin
    if suffix == ".npy":
        return _load_npy(p, res, org, lim.max_pixels)
    if suffix in IMAGE_SUFFIXES:
        return _load_image_map(p, res, org, lim.max_pixels)
    raise MapFormatError(
        f"unknown map file extension {suffix or '(none)'!r}: expected .yaml, .yml, .npy or an image "
        f"({', '.join(sorted(IMAGE_SUFFIXES))})",
        path=p,
    )


def yaml_image_path(path: PathLike, *, max_yaml_bytes: int = DEFAULT_LIMITS.max_yaml_bytes) -> Optional[Path]:
    """The image a map_server YAML names, or ``None`` (best effort, never raises).

    Used to keep outputs from overwriting the images of inputs; :func:`load_map` reports
    what is wrong with a YAML that gives ``None``.
    """
    try:
        p = Path(path)
        if p.suffix.lower() not in YAML_SUFFIXES:
            return None
        image = _read_yaml(p, max_yaml_bytes).get("image")
        if not isinstance(image, str) or not image.strip():
            return None
        img = Path(image)
        return img if img.is_absolute() else p.parent / img
    except Exception:  # noqa: BLE001 - best effort by design
        return None


# -------------------------------------------------------------------------- saving
def save_map(
    grid: OccupancyGrid,
    path: PathLike,
    *,
    mode: str = "trinary",
    image_format: Optional[str] = None,
) -> Path:
    """Save a grid as a map_server map (YAML + image) or as a ``.npy`` array.

    Parameters
    ----------
    grid : OccupancyGrid
    path : str or path-like
        * ``STEM.yaml`` or ``STEM.yml``: writes the YAML there and the image as
          ``STEM.pgm`` (or ``STEM.png``) in the same folder.
        * ``STEM.pgm`` or ``STEM.png``: writes the image there and the YAML as
          ``STEM.yaml`` in the same folder.
        * ``STEM.npy``: writes the probabilities as a float32 array (``NaN`` unknown,
          row 0 = top); ``mode`` and ``image_format`` do not apply.
    mode : {"trinary", "raw"}
        How cells become pixels, see :func:`grid_to_pixels`. ``"trinary"`` writes
        map_saver's 254/0/205 (lossy: only free, occupied and unknown survive);
        ``"raw"`` writes percentages 0..100 and 255 for unknown, which round-trip
        exactly. The YAML says ``mode: trinary`` or ``mode: raw`` accordingly.
    image_format : {"pgm", "png"}, optional
        Image format for a ``.yaml``/``.yml`` path (default ``"pgm"``). For an image
        path the extension decides; a conflicting ``image_format`` is an error.

    Returns
    -------
    pathlib.Path
        The YAML file written (the ``.npy`` file for a ``.npy`` path).

    Raises
    ------
    MapFormatError
        Unsupported extension, ``mode`` or ``image_format``.
    OutputError
        The folder does not exist or a file cannot be written. Nothing is written then:
        the YAML and the image replace their targets together, or not at all.

    Notes
    -----
    The YAML has map_saver's keys in map_saver's order, ``negate: 0``,
    ``occupied_thresh: 0.65``, ``free_thresh: 0.196``, plus ``mode``. Numbers are
    written with full precision, so resolution and origin round-trip exactly.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> import numpy as np
    >>> from gridmerge import OccupancyGrid
    >>> tmp = tempfile.TemporaryDirectory()
    >>> grid = OccupancyGrid(np.array([[0.0, 1.0, np.nan]]), resolution=0.05, origin=(-1.5, 2.0, 0.0))
    >>> yaml_path = save_map(grid, pathlib.Path(tmp.name) / "map.yaml")
    >>> print(yaml_path.read_text(), end="")
    image: map.pgm
    resolution: 0.05
    origin: [-1.5, 2.0, 0.0]
    negate: 0
    occupied_thresh: 0.65
    free_thresh: 0.196
    mode: trinary
    >>> load_map(yaml_path) == grid
    True
    >>> tmp.cleanup()
    """
    if not isinstance(grid, OccupancyGrid):
        raise TypeError(f"grid must be an OccupancyGrid, got {type(grid).__name__}")
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".npy":
        buffer = io.BytesIO()
        np.save(buffer, grid.data, allow_pickle=False)
        return atomic_write(p, buffer.getvalue())
    if mode not in SAVE_MODES:
        raise MapFormatError(f"must be one of {', '.join(SAVE_MODES)}, got {_show(mode)}", field="mode")
    if image_format is not None and str(image_format).lower() not in ("pgm", "png"):
        raise MapFormatError(f"must be 'pgm' or 'png', got {_show(image_format)}", field="image_format")
    if suffix in YAML_SUFFIXES:
        fmt = (image_format or "pgm").lower()
        yaml_path, image_path = p, p.with_suffix("." + fmt)
    elif suffix in (".pgm", ".png"):
        fmt = suffix[1:]
        if image_format is not None and image_format.lower() != fmt:
            raise MapFormatError(
                f"image_format {image_format!r} conflicts with the file extension {p.suffix!r}", path=p
            )
        yaml_path, image_path = p.with_suffix(".yaml"), p
    else:
        raise MapFormatError(
            f"cannot save a map to {'extension ' + repr(p.suffix) if suffix else 'a path without extension'}: "
            "use .yaml, .yml, .pgm, .png or .npy",
            path=p,
        )
    pixels = grid_to_pixels(grid, mode)
    image_bytes = encode_pgm(pixels) if fmt == "pgm" else encode_png(pixels)
    yaml_bytes = _map_yaml(image_path.name, grid, mode).encode("utf-8")
    with atomic_files() as out:
        out.write(image_path, image_bytes)
        out.write(yaml_path, yaml_bytes)
    return yaml_path

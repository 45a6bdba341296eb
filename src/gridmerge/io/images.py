"""Reading and writing 8-bit images.

Netpbm grey and colour maps (``P2``, ``P3``, ``P5``, ``P6``) are decoded here rather than
by OpenCV, because ROS map_server reads them with SDL_image, which scales samples of a
file whose ``maxval`` is below 255 up to 0..255 (``v * 255 // maxval``); OpenCV does that
for the ASCII variants only. Every other format is decoded by
``cv2.imdecode(..., cv2.IMREAD_UNCHANGED)``.

Before anything is decoded, the width and height that a PNM header or a PNG ``IHDR``
chunk claims are checked against ``max_pixels``, so that a tiny file announcing a huge
image is refused without allocating it.
"""

from __future__ import annotations

import contextlib
import os
import re
import struct
import zlib
from pathlib import Path
from typing import BinaryIO, Iterator, NamedTuple, Optional, Union

import cv2
import numpy as np

from ..errors import MapFormatError

__all__ = ["MAX_PIXELS", "read_image", "image_size", "encode_pgm", "encode_png"]

#: Default limit on ``width * height`` of an image read by :func:`read_image`.
MAX_PIXELS = 100_000_000

PathLike = Union[str, "os.PathLike[str]"]

_HEAD_BYTES = 64 * 1024
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_WHITESPACE = b" \t\n\r\v\f"
_COMMENT = re.compile(rb"#[^\r\n]*")


class _PnmHeader(NamedTuple):
    magic: bytes  # b"P1" .. b"P6"
    width: int
    height: int
    maxval: int  # 1 for bitmaps
    offset: int  # where the raster starts


class _Incomplete(Exception):
    """The header continues past the bytes read so far."""


def _parse_pnm_header(buf: bytes) -> Optional[_PnmHeader]:
    """The header of a Netpbm file ``P1``..``P6``; ``None`` if ``buf`` is not one.

    Raises ``_Incomplete`` when ``buf`` ends inside the header and ``ValueError`` (with a
    message for the user) when the header is malformed.
    """
    if len(buf) < 2 or buf[0:1] != b"P" or buf[1:2] not in (b"1", b"2", b"3", b"4", b"5", b"6"):
        return None
    magic = bytes(buf[:2])
    n_fields = 2 if magic in (b"P1", b"P4") else 3
    fields: list[int] = []
    pos = 2
    while len(fields) < n_fields:
        # whitespace and comments between fields
        while pos < len(buf) and (buf[pos] in _WHITESPACE or buf[pos] == ord("#")):
            if buf[pos] == ord("#"):
                while pos < len(buf) and buf[pos] not in b"\r\n":
                    pos += 1
            else:
                pos += 1
        start = pos
        while pos < len(buf) and 48 <= buf[pos] <= 57:  # digits
            pos += 1
        if pos == len(buf):
            raise _Incomplete
        last = len(fields) == n_fields - 1
        allowed = _WHITESPACE if last else _WHITESPACE + b"#"
        if pos == start or buf[pos] not in allowed or pos - start > 12:
            name = ("width", "height", "maxval")[len(fields)]
            raise ValueError(f"invalid {magic.decode()} header: bad {name} field")
        fields.append(int(buf[start:pos]))
    width, height = fields[0], fields[1]
    maxval = fields[2] if n_fields == 3 else 1
    if width <= 0 or height <= 0:
        raise ValueError(f"invalid {magic.decode()} header: size {width} x {height}")
    if not 0 < maxval < 65536:
        raise ValueError(f"invalid {magic.decode()} header: maxval {maxval} not in 1..65535")
    # A binary raster starts after exactly one whitespace character.
    offset = pos + 1 if magic in (b"P4", b"P5", b"P6") else pos
    return _PnmHeader(magic, width, height, maxval, offset)


def _png_size(buf: bytes) -> Optional[tuple[int, int]]:
    if buf[:8] == _PNG_SIGNATURE and buf[12:16] == b"IHDR" and len(buf) >= 24:
        width, height = struct.unpack(">II", buf[16:24])
        return width, height
    return None


def _png_problem(data: bytes) -> Optional[str]:
    """Why a PNG file is damaged (missing bytes, bad chunk checksum), or ``None``.

    Checked before decoding because libpng reports such errors on stderr.
    """
    view = memoryview(data)
    pos = len(_PNG_SIGNATURE)
    while pos + 12 <= len(data):
        (length,) = struct.unpack(">I", view[pos : pos + 4])
        end = pos + 12 + length
        if end > len(data):
            break
        chunk_type = bytes(view[pos + 4 : pos + 8])
        (crc,) = struct.unpack(">I", view[end - 4 : end])
        if zlib.crc32(view[pos + 4 : end - 4]) != crc:
            return f"corrupt PNG: bad checksum of chunk {chunk_type.decode('latin-1')!r}"
        if chunk_type == b"IEND":
            return None
        pos = end
    return "truncated PNG (no IEND chunk)"


def image_size(head: bytes) -> Optional[tuple[int, int]]:
    """``(width, height)`` claimed by the header of a PNM or PNG file, without decoding.

    Parameters
    ----------
    head : bytes
        The first bytes of the file (a few hundred are usually enough).

    Returns
    -------
    (int, int) or None
        ``None`` for other formats, or when ``head`` is too short to tell.

    Examples
    --------
    >>> image_size(b"P5\\n# a comment\\n200000 100\\n255\\n")
    (200000, 100)
    >>> image_size(b"GIF89a") is None
    True
    """
    try:
        header = _parse_pnm_header(head)
    except (_Incomplete, ValueError):
        return None
    if header is not None:
        return header.width, header.height
    return _png_size(head)


def _check_pixels(path: Path, width: int, height: int, max_pixels: int) -> None:
    if width * height > max_pixels:
        raise MapFormatError(
            f"image is {width} x {height} = {width * height} pixels, more than the limit of {max_pixels}",
            path=path,
        )


@contextlib.contextmanager
def open_input(path: Path, kind: str) -> Iterator[BinaryIO]:
    """Open an input file in binary mode; OS errors become one-line :class:`MapFormatError`.

    ``kind`` names what the file should be, for the message about a directory
    (e.g. ``"an image file"``).
    """
    if path.is_dir():
        raise MapFormatError(f"is a directory, not {kind}", path=path)
    try:
        fh = open(path, "rb")
    except FileNotFoundError:
        raise MapFormatError("no such file", path=path) from None
    except OSError as exc:
        raise MapFormatError(f"cannot read the file: {exc.strerror or exc}", path=path) from None
    with fh:
        try:
            yield fh
        except OSError as exc:
            raise MapFormatError(f"cannot read the file: {exc.strerror or exc}", path=path) from None


def _read_bytes(path: Path, max_pixels: int) -> tuple[bytes, Optional[_PnmHeader]]:
    """The content of the file, refused early if its header claims too many pixels."""
    with open_input(path, "an image file") as fh:
        data = fh.read(_HEAD_BYTES)
        header: Optional[_PnmHeader] = None
        try:
            header = _parse_pnm_header(data)
        except _Incomplete:
            data += fh.read()
            try:
                header = _parse_pnm_header(data)
            except _Incomplete:
                raise MapFormatError("truncated image header", path=path) from None
        except ValueError as exc:
            raise MapFormatError(str(exc), path=path) from None
        size = (header.width, header.height) if header is not None else _png_size(data)
        if size is not None:
            _check_pixels(path, size[0], size[1], max_pixels)
        data += fh.read()
    if not data:
        raise MapFormatError("the file is empty", path=path)
    return data, header


def _to_uint8(samples: np.ndarray, maxval: int) -> np.ndarray:
    """Scale samples in ``0..maxval`` to ``0..255`` like SDL_image: ``v * 255 // maxval``."""
    if maxval == 255:
        return samples.astype(np.uint8)
    return (samples.astype(np.int64) * 255 // maxval).astype(np.uint8)


def _decode_pnm(path: Path, data: bytes, header: _PnmHeader) -> np.ndarray:
    """Decode a ``P2``/``P3``/``P5``/``P6`` raster; colour comes back in BGR order like OpenCV."""
    channels = 3 if header.magic in (b"P3", b"P6") else 1
    count = header.width * header.height * channels
    kind = header.magic.decode()
    if header.magic in (b"P5", b"P6"):
        dtype = np.dtype(np.uint8) if header.maxval < 256 else np.dtype(">u2")
        raster = data[header.offset : header.offset + count * dtype.itemsize]
        if len(raster) < count * dtype.itemsize:
            raise MapFormatError(
                f"truncated {kind} image: {len(raster)} of {count * dtype.itemsize} bytes of pixel data",
                path=path,
            )
        samples = np.frombuffer(raster, dtype=dtype)
    else:
        tokens = _COMMENT.sub(b" ", data[header.offset :]).split(None, count)[:count]
        if len(tokens) < count:
            raise MapFormatError(f"truncated {kind} image: {len(tokens)} of {count} samples", path=path)
        if not all(t.isdigit() and len(t) <= 6 for t in tokens):
            raise MapFormatError(f"invalid {kind} image: a sample is not a number in 0..65535", path=path)
        samples = np.array(tokens).astype(np.int64)
    if int(samples.max()) > header.maxval:
        raise MapFormatError(f"invalid {kind} image: a sample exceeds maxval {header.maxval}", path=path)
    img = _to_uint8(samples, header.maxval).reshape(header.height, header.width, channels)
    return img[:, :, 0] if channels == 1 else np.ascontiguousarray(img[:, :, ::-1])


@contextlib.contextmanager
def _quiet_opencv() -> Iterator[None]:
    """Keep OpenCV from logging decoder warnings to stderr (we raise errors instead)."""
    log = getattr(getattr(cv2, "utils", None), "logging", None)
    if log is None:  # pragma: no cover - very old OpenCV
        yield
        return
    previous = log.getLogLevel()
    log.setLogLevel(log.LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        log.setLogLevel(previous)


def _decode_opencv(path: Path, data: bytes) -> np.ndarray:
    if data.startswith(_PNG_SIGNATURE):
        problem = _png_problem(data)
        if problem is not None:
            raise MapFormatError(problem, path=path)
    with _quiet_opencv():
        try:
            img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        except cv2.error:
            img = None
    if img is None:
        raise MapFormatError("not a readable image (unknown format, corrupt or truncated data)", path=path)
    if img.dtype == np.uint16:
        # Keep the high byte, as libpng's png_set_strip_16 (used by SDL_image) does.
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise MapFormatError(f"unsupported image sample type {img.dtype} (8- or 16-bit images only)", path=path)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    return img


def read_image(path: PathLike, *, max_pixels: int = MAX_PIXELS) -> np.ndarray:
    """Read an 8-bit image file (grey, grey + alpha, colour or colour + alpha).

    Parameters
    ----------
    path : str or path-like
        A PGM/PPM (``P2``, ``P3``, ``P5``, ``P6``), PNG or any other format OpenCV reads.
    max_pixels : int, optional
        Refuse images with more than this many pixels. For PNM and PNG files the size is
        taken from the header, before anything is decoded.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` uint8 for grey images, ``(H, W, 3)`` uint8 in **BGR** order for
        colour, ``(H, W, 4)`` uint8 in **BGRA** order for images with alpha (a grey +
        alpha PNG comes back as BGRA with ``B = G = R``). Row 0 is the top row. Samples
        of a PNM file with ``maxval != 255`` are scaled to 0..255 as ``v * 255 //
        maxval`` (SDL_image's rule, which ROS map_server uses); 16-bit samples of other
        formats keep their high byte (libpng's ``png_set_strip_16``).

    Raises
    ------
    MapFormatError
        The file is missing, a directory, unreadable, empty, not an image, truncated,
        malformed, or larger than ``max_pixels``. The message names the file.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> tmp = tempfile.TemporaryDirectory()
    >>> f = pathlib.Path(tmp.name) / "tiny.pgm"
    >>> _ = f.write_bytes(b"P2\\n3 1\\n100\\n0 50 100\\n")
    >>> read_image(f).tolist()  # maxval 100 scaled to 0..255
    [[0, 127, 255]]
    >>> tmp.cleanup()
    """
    p = Path(path)
    data, header = _read_bytes(p, max_pixels)
    if header is not None and header.magic in (b"P2", b"P3", b"P5", b"P6"):
        return _decode_pnm(p, data, header)
    img = _decode_opencv(p, data)
    _check_pixels(p, img.shape[1], img.shape[0], max_pixels)
    return img


def _check_image(img: np.ndarray, channels: tuple[int, ...]) -> np.ndarray:
    arr = np.asarray(img)
    if arr.dtype != np.uint8:
        raise ValueError(f"image must be uint8, got {arr.dtype}")
    n = 1 if arr.ndim == 2 else (arr.shape[2] if arr.ndim == 3 else 0)
    if n not in channels:
        raise ValueError(f"image must be (H, W) or (H, W, C) with C in {channels[1:]}, got shape {arr.shape}")
    if arr.size == 0:
        raise ValueError(f"image is empty, shape {arr.shape}")
    return arr


def encode_pgm(img: np.ndarray) -> bytes:
    """Encode a grey image as a binary PGM (``P5``, maxval 255).

    Parameters
    ----------
    img : (H, W) uint8 array
        Row 0 is the top row.

    Returns
    -------
    bytes
        The file content: header ``P5\\n<W> <H>\\n255\\n`` followed by the pixels.

    Examples
    --------
    >>> import numpy as np
    >>> encode_pgm(np.array([[0, 254, 205]], dtype=np.uint8))
    b'P5\\n3 1\\n255\\n\\x00\\xfe\\xcd'
    """
    arr = _check_image(img, (1,))
    height, width = arr.shape
    return b"P5\n%d %d\n255\n" % (width, height) + np.ascontiguousarray(arr).tobytes()


def encode_png(img: np.ndarray) -> bytes:
    """Encode an image as PNG.

    Parameters
    ----------
    img : (H, W), (H, W, 3) or (H, W, 4) uint8 array
        Grey, BGR or BGRA (OpenCV's channel order, as returned by :func:`read_image`).

    Returns
    -------
    bytes
        The file content.

    Examples
    --------
    >>> import numpy as np
    >>> encode_png(np.zeros((2, 3), dtype=np.uint8))[:8]
    b'\\x89PNG\\r\\n\\x1a\\n'
    """
    arr = _check_image(img, (1, 3, 4))
    ok, buf = cv2.imencode(".png", arr)
    if not ok:  # pragma: no cover - OpenCV accepts every array _check_image lets through
        raise ValueError("OpenCV could not encode the image as PNG")
    return buf.tobytes()

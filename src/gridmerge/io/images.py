"""Reading and writing 8-bit images.

Netpbm grey and colour maps (``P2``, ``P3``, ``P5``, ``P6``) are decoded here rather than
by OpenCV, because ROS map_server reads them with SDL_image, which scales samples of a
file whose ``maxval`` is below 255 up to 0..255 (``v * 255 // maxval``); OpenCV does that
for the ASCII variants only. Every other format is decoded by
``cv2.imdecode(..., cv2.IMREAD_UNCHANGED)``.

Before anything is decoded, the width and height that the file's header claims (PNM,
PNG ``IHDR``, BMP, JPEG ``SOF``, TIFF, WebP) are checked against ``max_pixels``, so that a
tiny file announcing a huge image (a decompression bomb) is refused without allocating
it. Files in other formats are refused, since their size cannot be checked before
OpenCV allocates the image; so are files that are not regular files (FIFOs, devices) and
files larger than any image of ``max_pixels`` pixels can be.
"""

from __future__ import annotations

import contextlib
import os
import re
import stat
import struct
import zlib
from pathlib import Path
from typing import BinaryIO, Iterator, NamedTuple, Optional, Union

import cv2
import numpy as np

from ..errors import InputTooLargeError, MapFormatError
from ..limits import DEFAULT_LIMITS

__all__ = ["MAX_PIXELS", "read_image", "image_size", "encode_pgm", "encode_png", "max_file_bytes"]

#: Default limit on ``width * height`` of an image read by :func:`read_image`
#: (:data:`gridmerge.limits.DEFAULT_LIMITS`).
MAX_PIXELS = DEFAULT_LIMITS.max_pixels

#: The formats whose size is checked before decoding, hence the only ones read.
IMAGE_FORMATS = "PGM/PPM/PBM, PNG, BMP, JPEG, TIFF or WebP"

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


def _bmp_size(buf: bytes) -> Optional[tuple[int, int]]:
    if buf[:2] != b"BM" or len(buf) < 26:
        return None
    (header_size,) = struct.unpack("<I", buf[14:18])
    if header_size == 12:  # BITMAPCOREHEADER
        return struct.unpack("<HH", buf[18:22])
    width, height = struct.unpack("<ii", buf[18:26])
    return abs(width), abs(height)


# JPEG start-of-frame markers (baseline, progressive, lossless, arithmetic...).
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def _jpeg_size(buf: bytes) -> Optional[tuple[int, int]]:
    if buf[:2] != b"\xff\xd8":
        return None
    pos = 2
    while pos + 4 <= len(buf):
        if buf[pos] != 0xFF:
            return None
        marker = buf[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # markers without a length
            pos += 2
            continue
        (length,) = struct.unpack(">H", buf[pos + 2 : pos + 4])
        if marker in _JPEG_SOF:
            if pos + 9 > len(buf):
                return None
            height, width = struct.unpack(">HH", buf[pos + 5 : pos + 9])
            return width, height
        if marker in (0xDA, 0xD9) or length < 2:  # scan data or end before any frame
            return None
        pos += 2 + length
    return None


def _webp_size(buf: bytes) -> Optional[tuple[int, int]]:
    if buf[:4] != b"RIFF" or buf[8:12] != b"WEBP" or len(buf) < 30:
        return None
    kind = buf[12:16]
    if kind == b"VP8 " and buf[23:26] == b"\x9d\x01\x2a":
        width, height = struct.unpack("<HH", buf[26:30])
        return width & 0x3FFF, height & 0x3FFF
    if kind == b"VP8L" and buf[20] == 0x2F:
        (bits,) = struct.unpack("<I", buf[21:25])
        return (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
    if kind == b"VP8X":
        width = int.from_bytes(buf[24:27], "little") + 1
        height = int.from_bytes(buf[27:30], "little") + 1
        return width, height
    return None


def _tiff_size(buf: bytes) -> Optional[tuple[int, int]]:
    """Size of the first image of a (classic, not Big-) TIFF file."""
    if buf[:4] == b"II*\x00":
        order = "<"
    elif buf[:4] == b"MM\x00*":
        order = ">"
    else:
        return None
    if len(buf) < 8:
        return None
    (ifd,) = struct.unpack(order + "I", buf[4:8])
    if ifd + 2 > len(buf):
        return None
    (count,) = struct.unpack(order + "H", buf[ifd : ifd + 2])
    found: dict[int, int] = {}
    for k in range(count):
        entry = ifd + 2 + 12 * k
        if entry + 12 > len(buf):
            return None
        tag, kind, n = struct.unpack(order + "HHI", buf[entry : entry + 8])
        if tag in (256, 257) and n == 1 and kind in (3, 4):
            fmt = order + ("H" if kind == 3 else "I")
            (found[tag],) = struct.unpack_from(fmt, buf, entry + 8)
    if 256 in found and 257 in found:
        return found[256], found[257]
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
    """``(width, height)`` claimed by the header of an image file, without decoding.

    Parameters
    ----------
    head : bytes
        The first bytes of the file (a few hundred are usually enough; a JPEG's size may
        follow its metadata, a TIFF's may be anywhere in the file).

    Returns
    -------
    (int, int) or None
        ``None`` for formats other than PNM (``P1``..``P6``), PNG, BMP, JPEG, TIFF and
        WebP, or when ``head`` is too short to tell.

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
    for size in (_png_size, _bmp_size, _jpeg_size, _webp_size, _tiff_size):
        found = size(head)
        if found is not None:
            return found
    return None


def max_file_bytes(max_pixels: int) -> int:
    """The largest image file read for a limit of ``max_pixels`` pixels.

    No supported format needs more than 32 bytes per pixel (an ASCII colour PNM with
    16-bit samples needs 18); larger files are refused before they are read.
    """
    return 32 * int(max_pixels) + (1 << 20)


def _check_pixels(path: Path, width: int, height: int, max_pixels: int) -> None:
    if width * height > max_pixels:
        raise InputTooLargeError(
            f"image is {width} x {height} = {width * height} pixels, more than the limit of {max_pixels} (max_pixels)",
            path=path,
            limit="max_pixels",
        )


@contextlib.contextmanager
def open_input(path: Path, kind: str) -> Iterator[BinaryIO]:
    """Open an input file in binary mode; OS errors become one-line :class:`MapFormatError`.

    ``kind`` names what the file should be, for the message about a directory
    (e.g. ``"an image file"``).
    """
    try:
        # Opened without blocking (a FIFO would wait for a writer), then checked to be a
        # regular file: devices and FIFOs never end.
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0))
    except FileNotFoundError:
        raise MapFormatError("no such file", path=path) from None
    except IsADirectoryError:
        raise MapFormatError(f"is a directory, not {kind}", path=path) from None
    except OSError as exc:
        if os.path.isdir(path):  # Windows refuses to open folders with "permission denied"
            raise MapFormatError(f"is a directory, not {kind}", path=path) from None
        raise MapFormatError(f"cannot read the file: {exc.strerror or exc}", path=path) from None
    except ValueError:  # a NUL byte or a lone surrogate in the name
        raise MapFormatError("invalid file name", path=_printable(path)) from None
    fh = None
    try:
        mode = os.fstat(fd).st_mode
        if stat.S_ISDIR(mode):
            raise MapFormatError(f"is a directory, not {kind}", path=path)
        if not stat.S_ISREG(mode):
            raise MapFormatError(f"is not a regular file (a device, FIFO or socket), not {kind}", path=path)
        if getattr(os, "O_NONBLOCK", 0):
            os.set_blocking(fd, True)
        fh = os.fdopen(fd, "rb")
    except BaseException:
        # A Ctrl-C can land after os.fdopen made its file object and before ``fh`` holds
        # it: the discarded object has then closed the descriptor already, and closing it
        # again turned the interrupt into "Bad file descriptor".
        if fh is None:
            with contextlib.suppress(OSError):
                os.close(fd)
        raise
    with fh:
        try:
            yield fh
        except OSError as exc:
            raise MapFormatError(f"cannot read the file: {exc.strerror or exc}", path=path) from None


def _printable(path) -> str:
    """``path`` as text that can be printed (NUL bytes and surrogates escaped)."""
    text = os.fspath(path)
    if isinstance(text, bytes):
        text = text.decode("utf-8", "backslashreplace")
    return text.encode("utf-8", "backslashreplace").decode("utf-8").replace("\x00", "\\x00")


def _read_at_most(fh: BinaryIO, limit: int, first: bytes = b"") -> bytes:
    """``first`` and the rest of the file, but no more than ``limit`` bytes in all (read in
    chunks: a single ``read(limit)`` would allocate ``limit`` bytes up front)."""
    chunks = [first]
    total = len(first)
    while total < limit:
        chunk = fh.read(min(1 << 24, limit - total))
        if not chunk:
            break
        chunks.append(chunk)
        total += len(chunk)
    return b"".join(chunks)


# Signatures of the formats image_size() knows (PNM is recognised by its header parser).
_SIGNATURES = (_PNG_SIGNATURE, b"BM", b"\xff\xd8", b"II*\x00", b"MM\x00*")


def _known_format(head: bytes) -> bool:
    return head.startswith(_SIGNATURES) or (head[:4] == b"RIFF" and head[8:12] == b"WEBP")


def _read_bytes(path: Path, max_pixels: int) -> tuple[bytes, Optional[_PnmHeader]]:
    """The content of the file, refused early if its header claims too many pixels."""
    unknown = f"not a readable image: unknown format or unreadable header (expected {IMAGE_FORMATS})"
    limit = max_file_bytes(max_pixels)
    with open_input(path, "an image file") as fh:
        size_on_disk = os.fstat(fh.fileno()).st_size
        if size_on_disk > limit:
            raise InputTooLargeError(
                f"file of {size_on_disk} bytes is larger than any image of at most {max_pixels} pixels (max_pixels)",
                path=path,
                limit="max_pixels",
            )
        data = fh.read(_HEAD_BYTES)
        if not data:
            raise MapFormatError("the file is empty", path=path)
        header: Optional[_PnmHeader] = None
        try:
            header = _parse_pnm_header(data)
        except _Incomplete:
            data = _read_at_most(fh, limit + 1, data)
            try:
                header = _parse_pnm_header(data)
            except _Incomplete:
                raise MapFormatError("truncated image header", path=path) from None
            except ValueError as exc:
                raise MapFormatError(str(exc), path=path) from None
        except ValueError as exc:
            raise MapFormatError(str(exc), path=path) from None
        if header is None and not _known_format(data):
            raise MapFormatError(unknown, path=path)  # refused without reading the rest
        size = (header.width, header.height) if header is not None else image_size(data)
        if size is not None:
            _check_pixels(path, size[0], size[1], max_pixels)
        data = _read_at_most(fh, limit + 1, data)
    if len(data) > limit:  # grew while being read
        raise InputTooLargeError(
            f"file is larger than any image of at most {max_pixels} pixels (max_pixels)", path=path, limit="max_pixels"
        )
    if header is None:
        # JPEG and TIFF may give their size after the first bytes: checked on the whole file.
        size = image_size(data)
        if size is None or size[0] <= 0 or size[1] <= 0:
            raise MapFormatError(unknown, path=path)
        _check_pixels(path, size[0], size[1], max_pixels)
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

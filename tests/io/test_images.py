import os
import struct
import time
import tracemalloc
import zlib

import cv2
import numpy as np
import pytest

from gridmerge.errors import MapFormatError
from gridmerge.io import MAX_PIXELS, encode_pgm, encode_png, image_size, read_image


def png_bytes(arr, color_type, bit_depth=8, palette=None):
    """A minimal PNG writer (so that every colour type can be produced)."""
    arr = np.asarray(arr)
    height, width = arr.shape[:2]
    sample = ">u2" if bit_depth == 16 else "u1"
    raw = b"".join(b"\x00" + arr[y].astype(sample).tobytes() for y in range(height))

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    out = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, bit_depth, color_type, 0, 0, 0))
    if palette is not None:
        out += chunk(b"PLTE", bytes(np.asarray(palette, np.uint8).ravel()))
    return out + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")


def write(path, data):
    path.write_bytes(data)
    return path


def assert_error_names(excinfo, path):
    message = str(excinfo.value)
    assert message.startswith(str(path) + ": ")
    assert "\n" not in message
    assert excinfo.value.path == str(path)


# ------------------------------------------------------------------------ PNM
def test_p5_grey(tmp_path):
    f = write(tmp_path / "a.pgm", b"P5\n3 2\n255\n" + bytes([0, 1, 2, 253, 254, 255]))
    img = read_image(f)
    assert img.dtype == np.uint8
    assert img.tolist() == [[0, 1, 2], [253, 254, 255]]


def test_p5_header_with_comments_and_odd_whitespace(tmp_path):
    f = write(tmp_path / "a.pgm", b"P5 # comment\n#another\n 2\t# w\n1\r\n255\n" + bytes([7, 9]))
    assert read_image(f).tolist() == [[7, 9]]


def test_p2_ascii_with_comments(tmp_path):
    f = write(tmp_path / "a.pgm", b"P2\n# made by hand\n3 2\n255\n0 10 20\n# mid comment\n30 40 255\n")
    assert read_image(f).tolist() == [[0, 10, 20], [30, 40, 255]]


@pytest.mark.parametrize("ascii_", [False, True])
def test_maxval_below_255_is_scaled_like_sdl_image(tmp_path, ascii_):
    samples = [0, 1, 50, 99, 100]
    if ascii_:
        data = b"P2\n5 1\n100\n" + " ".join(map(str, samples)).encode() + b"\n"
    else:
        data = b"P5\n5 1\n100\n" + bytes(samples)
    img = read_image(write(tmp_path / "a.pgm", data))
    assert img.tolist() == [[v * 255 // 100 for v in samples]]  # [0, 2, 127, 252, 255]
    assert img.tolist() == [[0, 2, 127, 252, 255]]


def test_16_bit_pgm_is_scaled_to_8_bits(tmp_path):
    samples = np.array([0, 1, 500, 999, 1000], dtype=">u2")
    img = read_image(write(tmp_path / "a.pgm", b"P5\n5 1\n1000\n" + samples.tobytes()))
    assert img.dtype == np.uint8
    assert img.tolist() == [[0, 0, 127, 254, 255]]
    img2 = read_image(write(tmp_path / "b.pgm", b"P2\n2 1\n65535\n65535 32768\n"))
    assert img2.tolist() == [[255, 127]]


def test_p6_colour_comes_back_in_bgr_order(tmp_path):
    f = write(tmp_path / "a.ppm", b"P6\n2 1\n255\n" + bytes([10, 20, 30, 40, 50, 60]))
    img = read_image(f)
    assert img.shape == (1, 2, 3)
    assert img.tolist() == [[[30, 20, 10], [60, 50, 40]]]


def test_p3_ascii_colour(tmp_path):
    f = write(tmp_path / "a.ppm", b"P3\n1 1\n255\n1 2 3\n")
    assert read_image(f).tolist() == [[[3, 2, 1]]]


def test_pbm_goes_through_opencv(tmp_path):
    f = write(tmp_path / "a.pbm", b"P1\n3 1\n0 1 0\n")
    img = read_image(f)
    assert img.shape == (1, 3)
    assert img[0, 1] < img[0, 0]  # 1 = black in PBM


# ------------------------------------------------------------------------ PNG
def test_png_grey(tmp_path):
    arr = np.array([[0, 127, 255]], np.uint8)
    assert read_image(write(tmp_path / "g.png", png_bytes(arr, 0))).tolist() == arr.tolist()


def test_png_grey_alpha_becomes_bgra(tmp_path):
    ga = np.array([[[100, 0], [200, 255]]], np.uint8)
    img = read_image(write(tmp_path / "ga.png", png_bytes(ga, 4)))
    assert img.shape == (1, 2, 4)
    assert img.tolist() == [[[100, 100, 100, 0], [200, 200, 200, 255]]]


def test_png_rgb_and_rgba_in_bgr_order(tmp_path):
    rgb = np.array([[[10, 20, 30]]], np.uint8)
    assert read_image(write(tmp_path / "c.png", png_bytes(rgb, 2))).tolist() == [[[30, 20, 10]]]
    rgba = np.array([[[10, 20, 30, 40]]], np.uint8)
    assert read_image(write(tmp_path / "d.png", png_bytes(rgba, 6))).tolist() == [[[30, 20, 10, 40]]]


def test_png_16_bit_keeps_high_byte(tmp_path):
    arr = np.array([[0, 255, 256, 0x8080, 0xFF00, 0xFFFF]], np.uint16)
    img = read_image(write(tmp_path / "g16.png", png_bytes(arr, 0, bit_depth=16)))
    assert img.dtype == np.uint8
    assert img.tolist() == [[0, 0, 1, 0x80, 0xFF, 0xFF]]


def test_palette_png_is_expanded_to_colours(tmp_path):
    palette = [[0, 0, 0], [255, 255, 255], [205, 205, 205]]
    img = read_image(write(tmp_path / "p.png", png_bytes(np.array([[2, 1, 0]], np.uint8), 3, palette=palette)))
    assert img.shape == (1, 3, 3)
    assert img[..., 0].tolist() == [[205, 255, 0]]


def test_other_formats_are_decoded_by_opencv(tmp_path):
    arr = np.array([[0, 128], [255, 7]], np.uint8)
    ok, buf = cv2.imencode(".bmp", arr)
    assert ok
    img = read_image(write(tmp_path / "a.bmp", buf.tobytes()))
    assert img.ndim in (2, 3)
    grey = img if img.ndim == 2 else img[..., 0]
    assert grey.tolist() == arr.tolist()


# --------------------------------------------------------------------- errors
def test_missing_file(tmp_path):
    with pytest.raises(MapFormatError, match="no such file") as excinfo:
        read_image(tmp_path / "missing.pgm")
    assert_error_names(excinfo, tmp_path / "missing.pgm")


def test_directory(tmp_path):
    (tmp_path / "d.png").mkdir()
    with pytest.raises(MapFormatError, match="directory") as excinfo:
        read_image(tmp_path / "d.png")
    assert_error_names(excinfo, tmp_path / "d.png")


def test_empty_file(tmp_path):
    f = write(tmp_path / "e.png", b"")
    with pytest.raises(MapFormatError, match="empty") as excinfo:
        read_image(f)
    assert_error_names(excinfo, f)


@pytest.mark.parametrize(
    "name, data, match",
    [
        ("garbage.png", b"this is not an image at all", "not a readable image"),
        ("trunc.pgm", b"P5\n3 2\n255\n" + bytes([1, 2, 3, 4]), "truncated"),
        ("trunc_header.pgm", b"P5\n3 2\n", "truncated"),
        ("trunc_ascii.pgm", b"P2\n3 2\n255\n1 2 3 4\n", "truncated"),
        ("bad_header.pgm", b"P5\nabc 2\n255\n" + bytes(6), "header"),
        ("zero_size.pgm", b"P5\n0 2\n255\n", "header"),
        ("bad_maxval.pgm", b"P5\n1 1\n70000\n\x00\x00", "maxval"),
        ("over_maxval.pgm", b"P2\n2 1\n100\n5 101\n", "exceeds maxval"),
        ("bad_sample.pgm", b"P2\n2 1\n255\n5 x\n", "not a number"),
        ("negative.pgm", b"P2\n2 1\n255\n5 -1\n", "not a number"),
    ],
)
def test_malformed_files(tmp_path, name, data, match):
    f = write(tmp_path / name, data)
    with pytest.raises(MapFormatError, match=match) as excinfo:
        read_image(f)
    assert_error_names(excinfo, f)


def test_truncated_and_corrupt_png_are_refused_silently(tmp_path, capfd):
    good = png_bytes(np.arange(100, dtype=np.uint8).reshape(10, 10), 0)
    truncated = write(tmp_path / "t.png", good[: len(good) - 20])
    corrupt = bytearray(good)
    corrupt[45] ^= 0xFF  # inside IDAT
    corrupt_file = write(tmp_path / "c.png", bytes(corrupt))
    with pytest.raises(MapFormatError, match="truncated") as excinfo:
        read_image(truncated)
    assert_error_names(excinfo, truncated)
    with pytest.raises(MapFormatError, match="corrupt") as excinfo:
        read_image(corrupt_file)
    assert_error_names(excinfo, corrupt_file)
    with pytest.raises(MapFormatError):
        read_image(write(tmp_path / "g.png", b"\x89PNG but not really"))
    captured = capfd.readouterr()
    assert captured.out == "" and captured.err == ""


# ----------------------------------------------------------------- size limit
def test_huge_pgm_header_is_refused_before_decoding(tmp_path):
    f = write(tmp_path / "huge.pgm", b"P5\n200000 200000\n255\n" + bytes(16))
    tracemalloc.start()
    start = time.perf_counter()
    try:
        with pytest.raises(MapFormatError, match="200000 x 200000") as excinfo:
            read_image(f)
        elapsed = time.perf_counter() - start
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert elapsed < 1.0
    assert peak < 10_000_000  # nowhere near the 40 GB the header claims
    assert str(MAX_PIXELS) in str(excinfo.value)
    assert_error_names(excinfo, f)


def test_huge_png_header_is_refused_before_decoding(tmp_path):
    data = png_bytes(np.zeros((1, 1), np.uint8), 0)
    data = data[:16] + struct.pack(">II", 300000, 300000) + data[24:]  # lie in IHDR
    f = write(tmp_path / "huge.png", data)
    start = time.perf_counter()
    with pytest.raises(MapFormatError, match="300000 x 300000"):
        read_image(f)
    assert time.perf_counter() - start < 1.0


def test_max_pixels_is_settable(tmp_path):
    f = write(tmp_path / "a.pgm", b"P5\n10 10\n255\n" + bytes(100))
    assert read_image(f, max_pixels=100).shape == (10, 10)
    with pytest.raises(MapFormatError, match="limit of 99"):
        read_image(f, max_pixels=99)
    ok, buf = cv2.imencode(".bmp", np.zeros((10, 10), np.uint8))
    bmp = write(tmp_path / "a.bmp", buf.tobytes())
    with pytest.raises(MapFormatError, match="limit of 99"):  # checked after decoding
        read_image(bmp, max_pixels=99)


def test_image_size():
    assert image_size(b"P5\n# c\n640 480\n255\n") == (640, 480)
    assert image_size(b"P1\n3 2\n") == (3, 2)
    assert image_size(png_bytes(np.zeros((7, 5), np.uint8), 0)) == (5, 7)
    assert image_size(b"P5\n640") is None  # incomplete
    assert image_size(b"BM....") is None


# ------------------------------------------------------------------- encoding
def test_encode_pgm_bytes_and_round_trip(tmp_path):
    img = np.array([[0, 254], [205, 255], [1, 2]], np.uint8)
    data = encode_pgm(img)
    assert data == b"P5\n2 3\n255\n" + bytes([0, 254, 205, 255, 1, 2])
    assert read_image(write(tmp_path / "a.pgm", data)).tolist() == img.tolist()
    # non-contiguous input
    assert encode_pgm(img[::-1]) == b"P5\n2 3\n255\n" + bytes([1, 2, 205, 255, 0, 254])


@pytest.mark.parametrize("shape", [(3, 4), (3, 4, 3), (3, 4, 4)])
def test_encode_png_round_trip(tmp_path, shape):
    img = (np.arange(np.prod(shape)) * 7 % 256).astype(np.uint8).reshape(shape)
    out = read_image(write(tmp_path / "a.png", encode_png(img)))
    assert out.tolist() == img.tolist()


@pytest.mark.parametrize(
    "bad",
    [np.zeros((2, 2), np.uint16), np.zeros((2, 2, 3), np.uint8), np.zeros((0, 3), np.uint8), np.zeros(4, np.uint8)],
)
def test_encode_pgm_refuses_bad_arrays(bad):
    with pytest.raises(ValueError):
        encode_pgm(bad)


def test_encode_png_refuses_bad_arrays():
    with pytest.raises(ValueError):
        encode_png(np.zeros((2, 2, 2), np.uint8))
    with pytest.raises(ValueError):
        encode_png(np.zeros((2, 2), np.float32))


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0, reason="needs a non-root POSIX user")
def test_unreadable_file(tmp_path):
    f = write(tmp_path / "secret.pgm", b"P5\n1 1\n255\n\x00")
    os.chmod(f, 0)
    try:
        with pytest.raises(MapFormatError, match="cannot read") as excinfo:
            read_image(f)
    finally:
        os.chmod(f, 0o644)
    assert_error_names(excinfo, f)


def test_an_interrupt_while_opening_stays_an_interrupt(tmp_path, monkeypatch):
    """Ctrl-C right after os.fdopen made its file object (which, discarded, closes the
    descriptor): the KeyboardInterrupt comes out, not "Bad file descriptor"."""
    from gridmerge.io import images

    path = tmp_path / "m.pgm"
    path.write_bytes(encode_pgm(np.zeros((4, 5), np.uint8)))
    real = os.fdopen

    def interrupted(fd, *args, **kwargs):
        real(fd, *args, **kwargs).close()  # made, then lost to the interrupt
        raise KeyboardInterrupt

    monkeypatch.setattr(images.os, "fdopen", interrupted)
    with pytest.raises(KeyboardInterrupt):
        read_image(path)

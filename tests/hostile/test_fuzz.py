"""Fuzzing: random bytes and random YAML documents fed to ``load_map`` and to the CLI.

``load_map`` may return a grid or raise :class:`MapFormatError` (one line naming the
file), nothing else; the command line may exit 0, 1 or 2, never with a traceback and never
with an "unexpected" error.
"""

from __future__ import annotations

import math
import os
import shutil
import struct
import tempfile
import zlib
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gridmerge import GridMergeError, MapFormatError, OccupancyGrid, load_map


def examples(n: int):
    """``n`` examples, times GRIDMERGE_HYPOTHESIS_SCALE (e.g. 20 to search harder locally)."""
    return settings(max_examples=max(1, int(n * float(os.environ.get("GRIDMERGE_HYPOTHESIS_SCALE", "1")))))


MAP_KEYS = ["image", "resolution", "origin", "negate", "occupied_thresh", "free_thresh", "mode"]

scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(),
    st.builds(lambda d, sign: sign * 10**d + 7, st.integers(15, 6000), st.sampled_from([1, -1])),  # too big to print, some
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, 1, -1, 0.05, 0.0, -0.0, 1e-300, 1e300, 0.65, 0.196, 0.5, 1.0]),
    st.text(max_size=20),
    st.sampled_from(["trinary", "scale", "raw", "a.pgm", "missing.pgm", "", ".", "/", "a.pgm\x00", "../a.pgm", "~"]),
)
values = st.recursive(
    scalars,
    lambda children: st.one_of(st.lists(children, max_size=4), st.dictionaries(st.text(max_size=8), children, max_size=4)),
    max_leaves=12,
)


@st.composite
def map_documents(draw):
    """A YAML mapping close to a map_server map: its keys, some valid values, some not."""
    doc = {}
    for key in MAP_KEYS:
        choice = draw(st.integers(0, 3))
        if choice == 0:
            continue  # missing
        if choice == 1:  # plausible
            doc[key] = {
                "image": draw(st.sampled_from(["a.pgm", "a.png", "missing.pgm", "b.bin", "a.yaml"])),
                "resolution": draw(st.one_of(st.floats(-1, 1), st.just(math.nan))),
                "origin": draw(st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=2, max_size=4)),
                "negate": draw(st.sampled_from([0, 1, 2, True, -1])),
                "occupied_thresh": draw(st.floats(-0.5, 1.5)),
                "free_thresh": draw(st.floats(-0.5, 1.5)),
                "mode": draw(st.sampled_from(["trinary", "scale", "raw", "Trinary", "rgb"])),
            }[key]
        else:
            doc[key] = draw(values)
    doc.update(draw(st.dictionaries(st.text(max_size=6), values, max_size=2)))
    return doc


documents = st.one_of(map_documents(), values)


def _yaml_text(doc) -> str:
    try:
        return yaml.safe_dump(doc, allow_unicode=True)
    except (ValueError, yaml.YAMLError):  # e.g. an integer Python refuses to print
        return "image: a.pgm\nresolution: " + "9" * 5000 + "\n"


def _fixture_files(folder: Path) -> None:
    """The files a fuzzed YAML may name."""
    (folder / "a.pgm").write_bytes(b"P5\n4 3\n255\n" + bytes([0, 254, 205, 100] * 3))
    import cv2

    ok, buf = cv2.imencode(".png", np.array([[0, 254], [205, 100]], np.uint8))
    (folder / "a.png").write_bytes(buf.tobytes())
    (folder / "b.bin").write_bytes(bytes(range(256)))


def _check_load(path: Path) -> None:
    try:
        grid = load_map(path)
    except MapFormatError as exc:
        message = str(exc)
        assert "\n" not in message and message.startswith(exc.path or "")
        assert exc.path is not None and Path(exc.path).name == path.name, message
        return
    assert isinstance(grid, OccupancyGrid)


# ------------------------------------------------------------------ load_map
@examples(200)
@given(documents)
def test_random_yaml_documents(doc):
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        _fixture_files(folder)
        path = folder / "map.yaml"
        path.write_text(_yaml_text(doc), encoding="utf-8", errors="surrogatepass")
        _check_load(path)


@examples(150)
@given(st.text(alphabet=st.sampled_from(list("image:resolution origin[]{},&*!|>-?'\"#\n\t 0123456789.e+naf%@`")), max_size=200))
def test_random_yaml_text(text):
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        _fixture_files(folder)
        path = folder / "map.yaml"
        path.write_text(text)
        _check_load(path)


def _png_prefix(rest: bytes) -> bytes:
    ihdr = b"IHDR" + struct.pack(">IIBBBBB", 16, 16, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + ihdr + struct.pack(">I", zlib.crc32(ihdr)) + rest


PREFIXES = {
    "none": lambda rest: rest,
    "pgm": lambda rest: b"P5\n16 16\n255\n" + rest,
    "ascii-pgm": lambda rest: b"P2\n4 4\n15\n" + rest,
    "png": _png_prefix,
    "bmp": lambda rest: b"BM" + rest,
    "jpeg": lambda rest: b"\xff\xd8\xff" + rest,
    "tiff": lambda rest: b"II*\x00" + rest,
    "webp": lambda rest: b"RIFF\x00\x00\x00\x00WEBPVP8 " + rest,
    "npy": lambda rest: b"\x93NUMPY\x01\x00" + rest,
}


@examples(300)
@given(st.sampled_from(sorted(PREFIXES)), st.binary(max_size=600), st.sampled_from([".pgm", ".png", ".bmp", ".jpg", ".tif", ".webp", ".npy", ".yaml"]))
def test_random_bytes(prefix, rest, suffix):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"map{suffix}"
        path.write_bytes(PREFIXES[prefix](rest))
        _check_load(path)


@examples(60)
@given(st.binary(min_size=1, max_size=64), st.integers(0, 2000))
def test_damaged_real_files(noise, position):
    """A valid map's files with some bytes overwritten."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        from gridmerge import save_map, samples

        grid = samples.building(0, (120, 160))
        for name in ("m.yaml", "n.npy"):
            path = save_map(grid, folder / name, image_format="png" if name == "m.yaml" else None)
            target = folder / "m.png" if name == "m.yaml" else path
            data = bytearray(target.read_bytes())
            pos = position % len(data)
            data[pos : pos + len(noise)] = noise
            target.write_bytes(bytes(data))
            _check_load(path)


# ------------------------------------------------------------------- the CLI
@pytest.fixture(scope="module")
def cli_folder(tmp_path_factory, pair_folder):
    folder = tmp_path_factory.mktemp("cli-fuzz")
    for name in ("a.yaml", "a.pgm"):
        shutil.copy2(pair_folder / name, folder / name)
    _fixture_files(folder)
    (folder / "a.pgm").write_bytes((pair_folder / "a.pgm").read_bytes())
    return folder


@settings(parent=examples(15), suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(
    st.one_of(
        documents.map(lambda d: ("yaml", _yaml_text(d).encode("utf-8", "surrogatepass"))),
        st.tuples(st.sampled_from(sorted(PREFIXES)), st.binary(max_size=300)).map(lambda t: ("pgm", PREFIXES[t[0]](t[1]))),
    )
)
def test_cli_on_random_inputs(cli_folder, h, case):
    suffix, data = case
    bad = cli_folder / f"bad.{suffix}"
    bad.write_bytes(data)
    proc = h.run_cli("align", "a.yaml", bad.name, cwd=cli_folder)
    assert proc.returncode in (0, 1, 2), h.describe(proc)
    assert "Traceback" not in proc.stderr, h.describe(proc)
    if proc.returncode == 2:
        h.assert_one_line_error(proc, 2)
    else:
        assert proc.stderr == "", h.describe(proc)

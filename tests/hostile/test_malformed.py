"""Malformed metadata and damaged files, through the real command line.

Every case runs ``python -m gridmerge align a.yaml BAD`` in its own folder and must end
with exit 2 and a single ``gridmerge: error:`` line on stderr that names the file at fault
and the field (the YAML key) where there is one, with no traceback; the folder must be
left exactly as it was. The runs are declared once and run two at a time.
"""

from __future__ import annotations

import math
import os
import shutil
import struct
import time
import zlib
from pathlib import Path

import numpy as np
import pytest

from gridmerge import MapFormatError, OccupancyGrid, load_map

GOOD = "image: a.pgm\nresolution: 0.05\n"


def _png(width: int, height: int, raw: bytes = b"", color_type: int = 0) -> bytes:
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, color_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")


def _text(name, text):
    return lambda folder: (folder / name).write_text(text)


def _bytes(name, data):
    return lambda folder: (folder / name).write_bytes(data)


def _truncated_pgm(folder: Path):
    data = (folder / "a.pgm").read_bytes()
    (folder / "t.pgm").write_bytes(data[: len(data) // 2])
    (folder / "tpgm.yaml").write_text("image: t.pgm\nresolution: 0.05\n")


def _truncated_png(folder: Path):
    raw = b"".join(b"\x00" + bytes(range(40)) for _ in range(30))
    data = _png(40, 30, raw)
    (folder / "t.png").write_bytes(data[: len(data) - 30])
    (folder / "tpng.yaml").write_text("image: t.png\nresolution: 0.05\n")


# (id, setup(folder), the bad file given to `align a.yaml FILE`, pieces of the error line)
CASES = [
    ("resolution-zero", _text("r0.yaml", GOOD.replace("0.05", "0")), "r0.yaml", ["resolution"]),
    ("resolution-negative", _text("rn.yaml", GOOD.replace("0.05", "-0.05")), "rn.yaml", ["resolution"]),
    ("resolution-nan", _text("rnan.yaml", GOOD.replace("0.05", ".nan")), "rnan.yaml", ["resolution"]),
    ("origin-nan", _text("onan.yaml", GOOD + "origin: [0.0, .nan, 0.0]\n"), "onan.yaml", ["origin"]),
    ("origin-inf", _text("oinf.yaml", GOOD + "origin: [.inf, 0.0, 0.0]\n"), "oinf.yaml", ["origin"]),
    ("origin-short", _text("o2.yaml", GOOD + "origin: [0.0, 0.0]\n"), "o2.yaml", ["origin"]),
    ("origin-long", _text("o4.yaml", GOOD + "origin: [0, 0, 0, 0]\n"), "o4.yaml", ["origin"]),
    ("occupied-above-1", _text("occ.yaml", GOOD + "occupied_thresh: 1.5\n"), "occ.yaml", ["occupied_thresh"]),
    ("free-below-0", _text("free.yaml", GOOD + "free_thresh: -0.1\n"), "free.yaml", ["free_thresh"]),
    ("free-above-occupied", _text("fo.yaml", GOOD + "occupied_thresh: 0.5\nfree_thresh: 0.6\n"), "fo.yaml", ["free_thresh"]),
    ("free-equals-occupied", _text("fe.yaml", GOOD + "occupied_thresh: 0.5\nfree_thresh: 0.5\n"), "fe.yaml", ["free_thresh"]),
    ("unknown-mode", _text("mode.yaml", GOOD + "mode: greyscale\n"), "mode.yaml", ["mode", "greyscale"]),
    ("yaml-list", _text("list.yaml", "- image\n- a.pgm\n"), "list.yaml", ["image", "list"]),
    ("yaml-string", _text("str.yaml", "just a string\n"), "str.yaml", ["image", "str"]),
    ("yaml-no-map-keys", _text("keys.yaml", "name: office\nfloors: 3\n"), "keys.yaml", ["image", "missing"]),
    ("truncated-pgm-via-yaml", _truncated_pgm, "tpgm.yaml", ["tpgm.yaml", "image", "t.pgm", "truncated"]),
    ("truncated-png-via-yaml", _truncated_png, "tpng.yaml", ["tpng.yaml", "image", "t.png", "truncated"]),
    ("truncated-pgm", _truncated_pgm, "t.pgm", ["truncated"]),
    ("truncated-png", _truncated_png, "t.png", ["truncated"]),
    ("binary-yaml", _bytes("bin.yaml", bytes(range(256)) * 8), "bin.yaml", ["not a YAML text file"]),
    # Limits (issue item 1): refused before anything is allocated.
    ("huge-pgm-header", _bytes("huge.pgm", b"P5\n200000 200000\n255\n" + bytes(64)), "huge.pgm", ["200000 x 200000", "--max-pixels"]),
    ("png-bomb", _bytes("bomb.png", _png(100000, 100000, bytes(1000))), "bomb.png", ["100000 x 100000", "--max-pixels"]),
    ("png-bomb-via-yaml", lambda f: (_bytes("bomb.png", _png(100000, 100000, bytes(1000)))(f), _text("bomb.yaml", "image: bomb.png\nresolution: 0.05\n")(f)), "bomb.yaml", ["image", "bomb.png", "--max-pixels"]),
    ("yaml-too-large", _text("big.yaml", GOOD + "# " + "x" * 100_000 + "\n"), "big.yaml", ["--max-yaml-bytes"]),
]


@pytest.fixture(scope="module")
def results(tmp_path_factory, pair_folder, h):
    """Every case's folder, snapshot before the run, and completed process."""
    base = tmp_path_factory.mktemp("malformed")
    jobs, folders = [], {}
    for key, setup, bad, _ in CASES:
        folder = base / key
        folder.mkdir()
        for name in ("a.yaml", "a.pgm"):
            shutil.copy2(pair_folder / name, folder / name)
        setup(folder)
        folders[key] = (folder, h.snapshot(folder))
        jobs.append((["align", "a.yaml", bad], folder))
    procs = h.run_many(jobs)
    return {key: (*folders[key], proc) for (key, *_), proc in zip(CASES, procs)}


@pytest.mark.parametrize("key, bad, pieces", [(c[0], c[2], c[3]) for c in CASES], ids=[c[0] for c in CASES])
def test_cli_refuses_with_one_line_naming_file_and_field(key, bad, pieces, results, h):
    folder, before, proc = results[key]
    h.assert_one_line_error(proc, 2, bad, *pieces)
    assert h.snapshot(folder) == before  # nothing written, nothing changed


def test_limit_options_raise_the_bound(tmp_path, pair_folder, h):
    """A genuinely large image that is small on disk (a mild decompression bomb) loads
    when within the limit, and is refused, before decoding, by a lower --max-pixels."""
    for name in ("a.yaml", "a.pgm"):
        shutil.copy2(pair_folder / name, tmp_path / name)
    # 1500 x 1500 free cells: 2.25 M pixels decoded, a few kB on disk.
    (tmp_path / "large.png").write_bytes(_png(1500, 1500, (b"\x00" + b"\xfe" * 1500) * 1500))
    assert (tmp_path / "large.png").stat().st_size < 20_000
    low, default = h.run_many(
        [(["align", "a.yaml", "large.png", "--max-pixels", "2e6"], tmp_path), (["align", "a.yaml", "large.png", "--json"], tmp_path)]
    )
    h.assert_one_line_error(low, 2, "large.png", "1500 x 1500", "limit of 2000000", "--max-pixels")
    assert default.returncode == 1, h.describe(default)  # loaded; nothing to align with
    assert "Traceback" not in default.stderr


# ------------------------------------------------------------- library level
@pytest.mark.parametrize(
    "text, field",
    [
        # YAML aliases: a 1 kB file whose value is a structure of 9**9 leaves. Showing it in
        # the message must not expand it.
        (
            "".join(f"{x}: &{x} [{', '.join([('*' + p) if p else 'z'] * 9)}]\n" for x, p in zip("abcdefghi", ["", *"abcdefgh"]))
            + "image: a.pgm\nresolution: *i\n",
            "resolution",
        ),
        ("image: a.pgm\nresolution: " + "[" * 3000 + "]" * 3000 + "\n", None),  # deeper than Python's recursion
        ("image: a.pgm\nresolution: 1" + "0" * 5000 + "\n", None),  # an integer Python refuses to convert
        ('image: "a\\0b.pgm"\nresolution: 0.05\n', "image"),  # NUL byte in the image name
        ('image: "\\ud800.pgm"\nresolution: 0.05\n', "image"),  # lone surrogate
        ("image: " + "x" * 5000 + ".pgm\nresolution: 0.05\n", "image"),  # name too long for the OS
        ("image: .\nresolution: 0.05\n", "image"),  # a directory
        ("image: a.pgm\nresolution: 0.05\norigin: {x: 1}\n", "origin"),
        ("image: a.pgm\nresolution: !!binary aGVsbG8=\n", "resolution"),
        ("image: a.pgm\nresolution: 2001-12-14\n", "resolution"),
        ("image: a.pgm\nresolution: 0.05\nnegate: .nan\n", "negate"),
        ("image: a.pgm\nresolution: 0.05\noccupied_thresh: .nan\n", "occupied_thresh"),
        ("image: a.pgm\nresolution: 0.05\nmode: [trinary]\n", "mode"),
    ],
    ids=["alias-bomb", "deep-nesting", "huge-integer", "nul-in-name", "surrogate-in-name", "long-name", "image-is-folder",
         "origin-mapping", "binary-value", "date-value", "negate-nan", "threshold-nan", "mode-list"],
)
def test_hostile_yaml_values(tmp_path, pair_folder, text, field):
    shutil.copy2(pair_folder / "a.pgm", tmp_path / "a.pgm")
    path = tmp_path / "bad.yaml"
    path.write_text(text, errors="surrogatepass")
    start = time.perf_counter()
    with pytest.raises(MapFormatError) as excinfo:
        load_map(path)
    assert time.perf_counter() - start < 5.0
    message = str(excinfo.value)
    assert "\n" not in message and len(message) < 500
    assert message.startswith(str(path) + ": ")
    if field is not None:
        assert excinfo.value.field == field and f": {field}: " in message


def test_deep_nesting_is_refused_before_parsing_and_shallow_nesting_is_read(tmp_path, pair_folder):
    """Brackets nested deeper than any map YAML needs are refused unparsed (PyYAML took 3 s
    on a slow machine to hit the recursion limit on 6 kB of them); a few levels are parsed
    and judged as usual, and brackets in a quoted name do not count against a real map."""
    shutil.copy2(pair_folder / "a.pgm", tmp_path / "a.pgm")
    deep = tmp_path / "deep.yaml"
    deep.write_text("image: a.pgm\nresolution: " + "[" * 65 + "]" * 65 + "\n")
    with pytest.raises(MapFormatError, match="nested too deeply"):
        load_map(deep)
    shallow = tmp_path / "shallow.yaml"
    shallow.write_text("image: a.pgm\nresolution: " + "[" * 10 + "0.05" + "]" * 10 + "\n")
    with pytest.raises(MapFormatError) as excinfo:
        load_map(shallow)
    assert excinfo.value.field == "resolution" and "nested" not in str(excinfo.value)
    shutil.copy2(pair_folder / "a.pgm", tmp_path / "[[a]].pgm")
    named = tmp_path / "named.yaml"
    named.write_text('image: "[[a]].pgm"\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\n')
    assert load_map(named).resolution == 0.05


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_fifo_and_device_inputs_do_not_hang(tmp_path):
    os.mkfifo(tmp_path / "fifo.pgm")
    (tmp_path / "fifo.yaml").write_text("image: fifo.pgm\nresolution: 0.05\n")
    os.mkfifo(tmp_path / "fifo2.yaml")
    targets = [tmp_path / "fifo.pgm", tmp_path / "fifo.yaml", tmp_path / "fifo2.yaml"]
    if os.path.exists("/dev/zero"):
        os.symlink("/dev/zero", tmp_path / "zero.pgm")
        targets.append(tmp_path / "zero.pgm")
    for path in targets:
        start = time.perf_counter()
        with pytest.raises(MapFormatError, match="regular file"):
            load_map(path)
        assert time.perf_counter() - start < 2.0


def test_npy_hostile_headers_are_refused_before_loading(tmp_path):
    def npy(name, header: dict, payload: bytes = b""):
        text = repr(header).encode("latin1")
        text += b" " * (-(len(text) + 11) % 64) + b"\n"
        (tmp_path / name).write_bytes(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text + payload)
        return tmp_path / name

    cases = [
        (npy("huge.npy", {"descr": "<f4", "fortran_order": False, "shape": (100000, 100000)}), "limit"),
        (npy("void.npy", {"descr": "|V100000000", "fortran_order": False, "shape": (10, 10)}), "dtype"),
        (npy("short.npy", {"descr": "<f8", "fortran_order": False, "shape": (1000, 1000)}, bytes(80)), "truncated"),
        (npy("obj.npy", {"descr": "|O", "fortran_order": False, "shape": (2, 2)}), "dtype"),
        (npy("cplx.npy", {"descr": "<c16", "fortran_order": False, "shape": (2, 2)}, bytes(64)), "dtype"),
    ]
    for path, match in cases:
        start = time.perf_counter()
        with pytest.raises(MapFormatError, match=match) as excinfo:
            load_map(path)
        assert time.perf_counter() - start < 1.0
        assert str(path) in str(excinfo.value)


# ------------------------------------------------------------ from_ros messages
@pytest.mark.parametrize("n, width, height", [(5, 2, 3), (7, 2, 3), (6, 3, 3), (0, 4, 4), (12, 0, 4)])
def test_from_ros_length_must_match_width_times_height(n, width, height):
    with pytest.raises(MapFormatError) as excinfo:
        OccupancyGrid.from_ros(np.zeros(n, np.int8), width, height, 0.05, name="robot1/map")
    message = str(excinfo.value)
    assert message.startswith("robot1/map: data: ") and "\n" not in message
    assert excinfo.value.field == "data"


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(resolution=0.0), "resolution"),
        (dict(resolution=math.nan), "resolution"),
        (dict(resolution=-1.0), "resolution"),
        (dict(origin=(0.0, math.inf, 0.0)), "origin"),
        (dict(origin=(0.0, 0.0)), "origin"),
    ],
)
def test_from_ros_bad_info_names_the_field(kwargs, field):
    args = dict(values=np.zeros(6, np.int8), width=2, height=3, resolution=0.05, name="robot1/map")
    args.update(kwargs)
    with pytest.raises(MapFormatError) as excinfo:
        OccupancyGrid.from_ros(**args)
    assert excinfo.value.field == field
    assert str(excinfo.value).startswith(f"robot1/map: {field}: ")


@pytest.mark.parametrize(
    "values, width, height",
    [(np.zeros(6, np.int8), -2, -3), (np.zeros(6, np.int8), 2, 3.5), (np.full(6, 65536 + 50), 2, 3), (np.array(["a"] * 6), 2, 3)],
    ids=["negative-size", "fractional-size", "wrapping-values", "text-values"],
)
def test_from_ros_bad_sizes_and_values(values, width, height):
    try:
        grid = OccupancyGrid.from_ros(values, width, height, 0.05, name="m")
    except MapFormatError:
        return
    # Accepted: then it must at least not invent known cells from out-of-range values.
    assert np.isnan(grid.data).all()

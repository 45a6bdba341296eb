import errno
import math
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

import gridmerge.io.atomic as atomic_module
from gridmerge.errors import MapFormatError, OutputError
from gridmerge.grid import DEFAULT_RESOLUTION, OccupancyGrid
from gridmerge.io import grid_to_pixels, load_map, pixels_to_ros, read_image, save_map

NAN = float("nan")


# ------------------------------------------------------------------- helpers
def write_pgm(path, img):
    img = np.asarray(img, dtype=np.uint8)
    path.write_bytes(b"P5\n%d %d\n255\n" % (img.shape[1], img.shape[0]) + img.tobytes())
    return path


def write_png(path, img):
    ok, buf = cv2.imencode(".png", np.asarray(img, dtype=np.uint8))
    assert ok
    path.write_bytes(buf.tobytes())
    return path


def write_map(folder, img, name="map", **keys):
    """Write NAME.pgm (grey) or NAME.png (colour) and NAME.yaml with the given keys."""
    img = np.asarray(img, dtype=np.uint8)
    if img.ndim == 2:
        image = write_pgm(folder / f"{name}.pgm", img)
    else:
        image = write_png(folder / f"{name}.png", img)
    doc = {"image": image.name, "resolution": 0.05, **keys}
    path = folder / f"{name}.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def ros_reference(img, occ_th=0.65, free_th=0.196, negate=False):
    """map_server's trinary rule for grey pixels, written out independently."""
    out = []
    for row in np.asarray(img, dtype=int).tolist():
        cells = []
        for p in row:
            avg = 255 - p if negate else p
            occ = (255 - avg) / 255.0
            cells.append(1.0 if occ > occ_th else 0.0 if occ < free_th else NAN)
        out.append(cells)
    return np.array(out, dtype=np.float32)


def scale_reference(p, occ_th=0.65, free_th=0.196):
    occ = (255 - p) / 255.0
    if occ > occ_th:
        return 100
    if occ < free_th:
        return 0
    return int(1 + 98 * ((occ - free_th) / (occ_th - free_th)))


def assert_same(data, expected):
    np.testing.assert_array_equal(np.asarray(data), np.asarray(expected, dtype=np.float32))


def assert_map_error(excinfo, path, field=None):
    err = excinfo.value
    message = str(err)
    assert "\n" not in message
    assert str(path) in message
    assert err.path == str(path)
    if field is not None:
        assert err.field == field
        assert f": {field}: " in message


# ------------------------------------------------------------- trinary (default)
def test_default_thresholds_trinary(tmp_path):
    # 206 -> occ 0.192 (free), 205 -> 0.19608 (unknown), 90 -> 0.647 (unknown), 89 -> 0.65098 (occupied)
    img = np.array([[254, 0, 205, 255], [206, 204, 90, 89]], np.uint8)
    grid = load_map(write_map(tmp_path, img))
    assert grid.shape == (2, 4)
    assert_same(grid.data, [[0, 1, NAN, 0], [0, NAN, NAN, 1]])
    assert_same(grid.data, ros_reference(img))
    assert grid.name == str(tmp_path / "map.yaml")
    assert grid.resolution == 0.05
    assert grid.origin == (0.0, 0.0, 0.0)


def test_rows_are_not_flipped(tmp_path):
    img = np.array([[0, 0], [254, 254], [205, 205]], np.uint8)  # top row occupied
    grid = load_map(write_map(tmp_path, img))
    assert_same(grid.data, [[1, 1], [0, 0], [NAN, NAN]])
    # in ROS order the top image row comes last
    assert grid.to_ros().tolist() == [-1, -1, 0, 0, 100, 100]


def test_custom_grey_levels_and_thresholds(tmp_path):
    # unknown = 230 (occ 0.098), occupied = 64 (occ 0.749), free = 255 (occ 0)
    img = np.array([[230, 64, 255], [255, 230, 64]], np.uint8)
    expected = [[NAN, 1, 0], [0, NAN, 1]]
    path = write_map(tmp_path, img, occupied_thresh=0.7, free_thresh=0.05)
    assert_same(load_map(path).data, expected)
    assert_same(load_map(path).data, ros_reference(img, 0.7, 0.05))
    # with map_server's default thresholds 230 would be free
    assert_same(load_map(write_map(tmp_path, img, name="default")).data, [[0, 1, 0], [0, 0, 1]])


@pytest.mark.parametrize("negate", [1, True])
def test_negate(tmp_path, negate):
    img = np.array([[230, 64, 255], [255, 230, 64]], np.uint8)
    path = write_map(tmp_path, 255 - img, occupied_thresh=0.7, free_thresh=0.05, negate=negate)
    assert_same(load_map(path).data, [[NAN, 1, 0], [0, NAN, 1]])
    assert_same(load_map(path).data, ros_reference(255 - img, 0.7, 0.05, negate=True))


def test_negate_zero_and_false_are_plain(tmp_path):
    img = np.array([[0, 254]], np.uint8)
    for value in (0, False):
        assert_same(load_map(write_map(tmp_path, img, negate=value)).data, [[1, 0]])


def test_trinary_rgba_averages_alpha_like_ros1(tmp_path):
    # BGRA; ROS 1 averages alpha with the colour channels in trinary mode
    img = np.array([[[254, 254, 254, 255], [254, 254, 254, 0], [0, 0, 0, 255], [0, 0, 0, 0]]], np.uint8)
    grid = load_map(write_map(tmp_path, img))
    # (3*254 + 0)/4 = 190.5 -> occ 0.253 unknown; (0+0+0+255)/4 = 63.75 -> occ 0.75 occupied
    assert_same(grid.data, [[0, NAN, 1, 1]])


def test_trinary_rgb_averages_channels(tmp_path):
    img = np.array([[[250, 250, 250], [0, 0, 255], [100, 0, 0]]], np.uint8)  # BGR
    # avg 250 -> free; avg 85 -> occ 0.667 occupied; avg 33.3 -> occupied
    assert_same(load_map(write_map(tmp_path, img)).data, [[0, 1, 1]])


def test_grey_alpha_array_is_treated_as_rgba():
    ga = np.array([[[254, 0], [254, 255]]], np.uint8)
    rgba = np.array([[[254, 254, 254, 0], [254, 254, 254, 255]]], np.uint8)
    for mode in ("trinary", "scale", "raw"):
        assert pixels_to_ros(ga, mode=mode).tolist() == pixels_to_ros(rgba, mode=mode).tolist()


# ---------------------------------------------------------------------- scale
def test_scale_mode_grey(tmp_path):
    pixels = [0, 89, 90, 120, 150, 180, 204, 205, 206, 255]
    img = np.array([pixels], np.uint8)
    values = [scale_reference(p) for p in pixels]
    assert values[4] == 47  # 150: occ 0.4118, ratio 0.4752, 1 + 98 * ratio = 47.57
    assert values[:2] == [100, 100] and values[-2:] == [0, 0]
    assert min(values[2:8]) >= 1 and max(values[2:8]) <= 99
    grid = load_map(write_map(tmp_path, img, mode="scale"))
    assert_same(grid.data, [[v / 100 for v in values]])
    assert pixels_to_ros(img, mode="scale").tolist() == [values]


def test_scale_mode_custom_thresholds():
    img = np.array([[30, 128, 200, 230]], np.uint8)
    got = pixels_to_ros(img, mode="scale", occupied_thresh=0.9, free_thresh=0.05)
    assert got.tolist() == [[scale_reference(p, 0.9, 0.05) for p in (30, 128, 200, 230)]]


def test_scale_mode_rgba_alpha(tmp_path):
    img = np.array(
        [
            [
                [100, 150, 200, 255],  # opaque, colour average 150 -> 47 (alpha not averaged)
                [100, 150, 200, 128],  # half transparent: ROS 1 still scales (alpha < 1 only)
                [100, 150, 200, 0],  # fully transparent -> unknown
                [255, 255, 255, 0],  # transparent but white -> free (thresholds come first)
                [0, 0, 0, 0],  # transparent but black -> occupied
            ]
        ],
        np.uint8,
    )
    grid = load_map(write_map(tmp_path, img, mode="scale"))
    assert_same(grid.data, [[0.47, 0.47, NAN, 0, 1]])


def test_scale_mode_rgb_blue_zero_quirk():
    # ROS 1 reads "alpha" from the last byte of an RGB pixel, i.e. blue.
    img = np.array([[[0, 200, 250], [1, 200, 249]]], np.uint8)  # BGR, both average 150
    assert pixels_to_ros(img, mode="scale").tolist() == [[-1, 47]]


def test_scale_mode_with_negate(tmp_path):
    img = np.array([[105, 255, 0]], np.uint8)  # negated: 150, 0, 255
    grid = load_map(write_map(tmp_path, img, mode="scale", negate=1))
    assert_same(grid.data, [[0.47, 1, 0]])


# ------------------------------------------------------------------------ raw
def test_raw_mode(tmp_path):
    img = np.array([[0, 1, 50, 99, 100, 101, 127, 128, 200, 254, 255]], np.uint8)
    grid = load_map(write_map(tmp_path, img, mode="raw"))
    assert_same(grid.data, [[0, 0.01, 0.5, 0.99, 1, NAN, NAN, NAN, NAN, NAN, NAN]])
    assert pixels_to_ros(img, mode="raw").tolist() == [[0, 1, 50, 99, 100, 101, 127, -128, -56, -2, -1]]


def test_raw_mode_negate_and_colour_truncation(tmp_path):
    assert_same(load_map(write_map(tmp_path, np.array([[255, 155, 0]], np.uint8), mode="raw", negate=1)).data,
                [[0, 1, NAN]])
    # BGR average (10 + 11 + 11) / 3 = 10.67 is truncated to 10
    img = np.array([[[10, 11, 11], [0, 0, 255]]], np.uint8)
    assert pixels_to_ros(img, mode="raw").tolist() == [[10, 85]]
    # alpha is not averaged in raw mode
    rgba = np.array([[[40, 40, 40, 0]]], np.uint8)
    assert pixels_to_ros(rgba, mode="raw").tolist() == [[40]]


# ----------------------------------------------------------- metric frame
def test_origin_and_resolution_honoured(tmp_path):
    path = write_map(tmp_path, np.full((3, 4), 254, np.uint8), resolution=0.025, origin=[1.5, -2.25, 0.3])
    grid = load_map(path)
    assert grid.resolution == 0.025
    assert grid.origin == (1.5, -2.25, 0.3)
    # centre of the bottom-left cell
    x, y = grid.pixel_to_metric([[0, 2]])[0]
    c, s = math.cos(0.3), math.sin(0.3)
    assert x == pytest.approx(1.5 + 0.0125 * c - 0.0125 * s)
    assert y == pytest.approx(-2.25 + 0.0125 * s + 0.0125 * c)


def test_kwargs_override_yaml_frame(tmp_path):
    path = write_map(tmp_path, np.full((2, 2), 254, np.uint8), resolution=0.1, origin=[1, 2, 0])
    grid = load_map(path, resolution=0.2, origin=(3, 4, 0.5))
    assert grid.resolution == 0.2 and grid.origin == (3.0, 4.0, 0.5)


def test_origin_defaults_and_integer_values(tmp_path):
    img = np.full((2, 2), 254, np.uint8)
    write_pgm(tmp_path / "m.pgm", img)
    (tmp_path / "m.yaml").write_text("image: m.pgm\nresolution: 1\n")
    grid = load_map(tmp_path / "m.yaml")
    assert grid.resolution == 1.0 and grid.origin == (0.0, 0.0, 0.0)


def test_image_path_relative_to_yaml_folder_or_absolute(tmp_path, monkeypatch):
    (tmp_path / "maps" / "img").mkdir(parents=True)
    write_pgm(tmp_path / "maps" / "img" / "a.pgm", [[0, 254]])
    yaml_path = tmp_path / "maps" / "a.yaml"
    yaml_path.write_text("image: img/a.pgm\nresolution: 0.05\n")
    monkeypatch.chdir(tmp_path)  # relative to the YAML, not to the working folder
    assert_same(load_map(Path("maps") / "a.yaml").data, [[1, 0]])
    other = tmp_path / "elsewhere.yaml"
    other.write_text(yaml.safe_dump({"image": str(tmp_path / "maps" / "img" / "a.pgm"), "resolution": 0.05}))
    assert_same(load_map(other).data, [[1, 0]])


def test_yml_suffix_and_upper_case(tmp_path):
    write_pgm(tmp_path / "a.pgm", [[0]])
    (tmp_path / "a.YML").write_text("image: a.pgm\nresolution: 0.05\n")
    assert_same(load_map(tmp_path / "a.YML").data, [[1]])


# ----------------------------------------------------------------- bare images
def test_bare_pgm_and_png_with_resolution_kwarg(tmp_path):
    img = np.array([[0, 254, 205], [255, 127, 64]], np.uint8)
    expected = ros_reference(img)
    for path in (write_pgm(tmp_path / "a.pgm", img), write_png(tmp_path / "a.png", img)):
        grid = load_map(path, resolution=0.1, origin=(1, 2, 0))
        assert_same(grid.data, expected)
        assert grid.resolution == 0.1 and grid.origin == (1.0, 2.0, 0.0)
        assert grid.name == str(path)
        default = load_map(path)
        assert default.resolution == DEFAULT_RESOLUTION and default.origin == (0.0, 0.0, 0.0)


def test_bare_image_round_trip_through_save(tmp_path):
    img = np.array([[0, 254, 205], [254, 205, 0]], np.uint8)
    grid = load_map(write_pgm(tmp_path / "in.pgm", img), resolution=0.1)
    yaml_path = save_map(grid, tmp_path / "out.png")
    assert yaml_path == tmp_path / "out.yaml"
    assert read_image(tmp_path / "out.png").tolist() == img.tolist()
    assert load_map(yaml_path) == grid
    assert load_map(tmp_path / "out.png", resolution=0.1) == grid


# ------------------------------------------------------------------------ npy
def test_npy_float_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    data = rng.random((5, 7)).astype(np.float32)
    data[rng.random((5, 7)) < 0.3] = np.nan
    grid = OccupancyGrid(data, resolution=0.2, origin=(1, 2, 3))
    path = save_map(grid, tmp_path / "g.npy")
    assert path == tmp_path / "g.npy"
    saved = np.load(path)
    assert saved.dtype == np.float32
    np.testing.assert_array_equal(saved, data)
    loaded = load_map(path, resolution=0.2, origin=(1, 2, 3))
    assert loaded == grid
    assert load_map(path).resolution == DEFAULT_RESOLUTION


@pytest.mark.parametrize("dtype", [np.int8, np.int16, np.int64, np.uint8])
def test_npy_integer_percentages(tmp_path, dtype):
    values = np.array([[0, 50, 100], [-1, 101, 7]]) if np.dtype(dtype).kind == "i" else np.array([[0, 50, 100], [255, 101, 7]])
    np.save(tmp_path / "p.npy", values.astype(dtype))
    assert_same(load_map(tmp_path / "p.npy").data, [[0, 0.5, 1], [NAN, NAN, 0.07]])


def test_npy_huge_integers_are_unknown(tmp_path):
    np.save(tmp_path / "p.npy", np.array([[65536, 65, -65536]], np.int64))
    assert_same(load_map(tmp_path / "p.npy").data, [[NAN, 0.65, NAN]])


def test_npy_float64_is_accepted(tmp_path):
    np.save(tmp_path / "p.npy", np.array([[0.25, np.nan]]))
    assert_same(load_map(tmp_path / "p.npy").data, [[0.25, NAN]])


@pytest.mark.parametrize(
    "name, array, match",
    [
        ("three_d.npy", np.zeros((2, 2, 2), np.float32), "2-D"),
        ("one_d.npy", np.zeros(4, np.float32), "2-D"),
        ("bool.npy", np.zeros((2, 2), bool), "dtype"),
        ("text.npy", np.array([["a", "b"]]), "dtype"),
        ("range.npy", np.array([[0.5, 1.5]], np.float32), r"\[0, 1\]"),
        ("inf.npy", np.array([[0.5, np.inf]], np.float32), "infinite"),
        ("empty.npy", np.zeros((0, 3), np.float32), "empty"),
    ],
)
def test_npy_malformed(tmp_path, name, array, match):
    np.save(tmp_path / name, array)
    with pytest.raises(MapFormatError, match=match) as excinfo:
        load_map(tmp_path / name)
    assert_map_error(excinfo, tmp_path / name)


def test_npy_pickled_garbage_and_missing(tmp_path):
    np.save(tmp_path / "obj.npy", np.array([[{"a": 1}]], dtype=object), allow_pickle=True)
    (tmp_path / "garbage.npy").write_bytes(b"definitely not numpy")
    (tmp_path / "zero.npy").write_bytes(b"")
    np.savez(tmp_path / "archive.npz", a=np.zeros((2, 2)))
    (tmp_path / "archive.npz").rename(tmp_path / "archive.npy")
    for name in ("obj.npy", "garbage.npy", "zero.npy", "archive.npy", "missing.npy"):
        with pytest.raises(MapFormatError) as excinfo:
            load_map(tmp_path / name)
        assert_map_error(excinfo, tmp_path / name)


def test_npy_max_pixels_checked_from_header(tmp_path):
    np.save(tmp_path / "p.npy", np.zeros((10, 10), np.float32))
    assert load_map(tmp_path / "p.npy", max_pixels=100).shape == (10, 10)
    with pytest.raises(MapFormatError, match="limit of 99"):
        load_map(tmp_path / "p.npy", max_pixels=99)


# ----------------------------------------------------------------- round trips
def test_trinary_yaml_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(7)
    img = rng.choice(np.array([254, 0, 205], np.uint8), size=(20, 30))
    src = write_map(tmp_path, img, resolution=0.05, origin=[-12.345678901, 3.25, 0.1])
    grid = load_map(src)
    out = save_map(grid, tmp_path / "copy.yaml")
    assert out == tmp_path / "copy.yaml"
    again = load_map(out)
    assert again == grid
    assert again.origin == (-12.345678901, 3.25, 0.1)
    # the PGM written is byte-for-byte map_saver's 254/0/205 image of the input
    assert (tmp_path / "copy.pgm").read_bytes() == b"P5\n30 20\n255\n" + img.tobytes()


def test_raw_round_trip_of_all_percentages(tmp_path):
    rng = np.random.default_rng(3)
    values = rng.integers(-1, 101, size=(40, 50))
    values.ravel()[:102] = np.arange(-1, 101)  # every value at least once
    grid = OccupancyGrid.from_ros(values.ravel(), 50, 40, resolution=0.1, origin=(1e-05, -2.5, 3.0))
    path = save_map(grid, tmp_path / "raw.yaml", mode="raw")
    doc = yaml.safe_load(path.read_text())
    assert doc["mode"] == "raw"
    loaded = load_map(path)
    assert loaded == grid
    assert loaded.origin == (1e-05, -2.5, 3.0)
    assert (loaded.to_ros() == values.ravel()).all()


def test_raw_round_trip_through_png(tmp_path):
    grid = OccupancyGrid(np.array([[0.0, 0.37, np.nan], [1.0, 0.5, 0.01]]), resolution=0.05)
    path = save_map(grid, tmp_path / "m.yaml", mode="raw", image_format="png")
    assert (tmp_path / "m.png").exists() and not (tmp_path / "m.pgm").exists()
    assert yaml.safe_load(path.read_text())["image"] == "m.png"
    assert load_map(path) == grid


def test_intermediate_probabilities_in_trinary_mode(tmp_path):
    data = np.array([[0.0, 0.19, 0.195, 0.2, 0.5, 0.65, 0.654, 0.66, 1.0, np.nan]], np.float32)
    grid = OccupancyGrid(data)
    pixels = grid_to_pixels(grid)
    assert pixels.tolist() == [[254, 254, 205, 205, 205, 205, 205, 0, 0, 205]]
    loaded = load_map(save_map(grid, tmp_path / "m.yaml"))
    assert_same(loaded.data, [[0, 0, NAN, NAN, NAN, NAN, NAN, 1, 1, NAN]])
    # the result is what map_server's thresholds say about the rounded percentages
    percent = np.rint(np.nan_to_num(data) * 100)
    expected = np.where(percent / 100 > 0.65, 1.0, np.where(percent / 100 < 0.196, 0.0, np.nan))
    expected[np.isnan(data)] = np.nan
    assert_same(loaded.data, expected)


# ---------------------------------------------------------------------- saving
def test_saved_pgm_bytes_and_yaml(tmp_path):
    grid = OccupancyGrid(np.array([[0.0, 1.0, np.nan], [0.19, 0.2, 0.66]]), resolution=0.05, origin=(-1.5, 2.0, 0.25))
    yaml_path = save_map(grid, tmp_path / "map.yaml")
    assert yaml_path == tmp_path / "map.yaml"
    assert (tmp_path / "map.pgm").read_bytes() == b"P5\n3 2\n255\n" + bytes([254, 0, 205, 254, 205, 0])
    assert yaml_path.read_text() == (
        "image: map.pgm\n"
        "resolution: 0.05\n"
        "origin: [-1.5, 2.0, 0.25]\n"
        "negate: 0\n"
        "occupied_thresh: 0.65\n"
        "free_thresh: 0.196\n"
        "mode: trinary\n"
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.pgm", "map.yaml"]


def test_save_via_image_path(tmp_path):
    grid = OccupancyGrid(np.array([[0.0, 1.0]]))
    assert save_map(grid, tmp_path / "m.pgm") == tmp_path / "m.yaml"
    assert yaml.safe_load((tmp_path / "m.yaml").read_text())["image"] == "m.pgm"
    assert load_map(tmp_path / "m.yaml") == grid


def test_save_odd_file_names(tmp_path):
    grid = OccupancyGrid(np.array([[0.0, 1.0]]))
    for stem in ("true", "1.5", "a: b", "#x", "naïve map"):
        path = save_map(grid, tmp_path / f"{stem}.yaml")
        assert yaml.safe_load(path.read_text(encoding="utf-8"))["image"] == f"{stem}.pgm"
        assert load_map(path) == grid


def test_save_full_precision_floats(tmp_path):
    for res, origin in [(1e-05, (1e20, -1e-7, 3.141592653589793)), (0.1 + 0.2, (-0.0, 5e-324, 1e16))]:
        grid = OccupancyGrid(np.array([[0.0]]), resolution=res, origin=origin)
        loaded = load_map(save_map(grid, tmp_path / "f.yaml"))
        assert loaded.resolution == res and loaded.origin == tuple(float(v) for v in origin)
        doc = yaml.safe_load((tmp_path / "f.yaml").read_text())
        assert all(isinstance(v, float) for v in [doc["resolution"], *doc["origin"]])


@pytest.mark.parametrize(
    "name, kwargs, match",
    [
        ("map.txt", {}, "extension"),
        ("map", {}, "extension"),
        ("map.yaml", {"mode": "scale"}, "mode"),
        ("map.yaml", {"image_format": "jpg"}, "image_format"),
        ("map.png", {"image_format": "pgm"}, "conflicts"),
    ],
)
def test_save_refuses_bad_requests(tmp_path, name, kwargs, match):
    grid = OccupancyGrid(np.array([[0.0]]))
    with pytest.raises(MapFormatError, match=match):
        save_map(grid, tmp_path / name, **kwargs)
    assert list(tmp_path.iterdir()) == []


def test_save_needs_a_grid(tmp_path):
    with pytest.raises(TypeError):
        save_map(np.zeros((2, 2)), tmp_path / "m.yaml")


def test_save_into_missing_folder(tmp_path):
    grid = OccupancyGrid(np.array([[0.0]]))
    with pytest.raises(OutputError) as excinfo:
        save_map(grid, tmp_path / "missing" / "m.yaml")
    assert str(tmp_path / "missing") in str(excinfo.value)
    assert list(tmp_path.iterdir()) == []


def test_save_failing_midway_keeps_previous_map(tmp_path, monkeypatch):
    old = OccupancyGrid(np.array([[0.0, 1.0]]), resolution=0.5)
    save_map(old, tmp_path / "m.yaml")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    real_replace = os.replace
    calls = []

    def flaky_replace(src, dst):
        calls.append(dst)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_replace(src, dst)

    monkeypatch.setattr(atomic_module.os, "replace", flaky_replace)
    with pytest.raises(OutputError, match="No space left"):
        save_map(OccupancyGrid(np.array([[np.nan, np.nan]]), resolution=0.1), tmp_path / "m.yaml")
    monkeypatch.undo()
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    assert load_map(tmp_path / "m.yaml") == old


def test_load_and_save_do_not_modify_inputs(tmp_path):
    img = np.array([[0, 254, 205]], np.uint8)
    src = write_map(tmp_path, img, origin=[1, 2, 0])
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    grid = load_map(src)
    data_before = grid.data.copy()
    (tmp_path / "out").mkdir()
    save_map(grid, tmp_path / "out" / "copy.yaml", mode="raw")
    np.testing.assert_array_equal(grid.data, data_before)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == before


# --------------------------------------------------------------- malformed YAML
GOOD = "image: map.pgm\nresolution: 0.05\n"


@pytest.mark.parametrize(
    "text, field",
    [
        ("- image\n- map.pgm\n", None),
        ("", None),
        ("just a string\n", None),
        ("resolution: 0.05\n", "image"),
        ("image: ''\nresolution: 0.05\n", "image"),
        ("image: 5\nresolution: 0.05\n", "image"),
        ("image: map.pgm\n", "resolution"),
        (GOOD.replace("0.05", "0"), "resolution"),
        (GOOD.replace("0.05", "-0.05"), "resolution"),
        (GOOD.replace("0.05", ".nan"), "resolution"),
        (GOOD.replace("0.05", ".inf"), "resolution"),
        (GOOD.replace("0.05", "fast"), "resolution"),
        (GOOD.replace("0.05", "true"), "resolution"),
        (GOOD.replace("0.05", "[0.05]"), "resolution"),
        (GOOD + "origin: [0, 0]\n", "origin"),
        (GOOD + "origin: [0, 0, 0, 0]\n", "origin"),
        (GOOD + "origin: [0, .nan, 0]\n", "origin"),
        (GOOD + "origin: [0, x, 0]\n", "origin"),
        (GOOD + "origin: [0, ~, 0]\n", "origin"),
        (GOOD + "origin: 0\n", "origin"),
        (GOOD + "occupied_thresh: 1.5\n", "occupied_thresh"),
        (GOOD + "occupied_thresh: high\n", "occupied_thresh"),
        (GOOD + "free_thresh: -0.1\n", "free_thresh"),
        (GOOD + "free_thresh: 0.7\n", "free_thresh"),
        (GOOD + "free_thresh: 0.65\n", "free_thresh"),
        (GOOD + "occupied_thresh: 0.1\n", "free_thresh"),
        (GOOD + "mode: greyscale\n", "mode"),
        (GOOD + "mode: 3\n", "mode"),
        (GOOD + "mode: Trinary\n", "mode"),
        (GOOD + "negate: 2\n", "negate"),
        (GOOD + "negate: 0.5\n", "negate"),
        (GOOD + "negate: maybe\n", "negate"),
        ("image: missing.pgm\nresolution: 0.05\n", "image"),
        ("image: broken.pgm\nresolution: 0.05\n", "image"),
        ("image: [unclosed\nresolution: 0.05\n", None),
        ("image: map.pgm\n  resolution: 0.05\n bad: indentation\n", None),
        ("a: 1\n---\nb: 2\n", None),
    ],
)
def test_malformed_yaml(tmp_path, text, field):
    write_pgm(tmp_path / "map.pgm", [[0, 254]])
    (tmp_path / "broken.pgm").write_bytes(b"P5\n4 4\n255\n\x00")
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(MapFormatError) as excinfo:
        load_map(path)
    assert_map_error(excinfo, path, field)


def test_missing_image_message_names_both_files(tmp_path):
    path = tmp_path / "m.yaml"
    path.write_text("image: nothere.pgm\nresolution: 0.05\n")
    with pytest.raises(MapFormatError) as excinfo:
        load_map(path)
    message = str(excinfo.value)
    assert message.startswith(f"{path}: image: ")
    assert str(tmp_path / "nothere.pgm") in message
    assert "no such file" in message


def test_binary_file_named_yaml(tmp_path):
    path = tmp_path / "image.yaml"
    write_png(path, np.zeros((4, 4), np.uint8))
    with pytest.raises(MapFormatError, match="not a YAML text file") as excinfo:
        load_map(path)
    assert_map_error(excinfo, path)
    latin = tmp_path / "latin.yaml"
    latin.write_bytes("image: caf\u00e9.pgm\n".encode("latin-1"))
    with pytest.raises(MapFormatError):
        load_map(latin)


def test_yaml_syntax_error_is_one_line_with_position(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text("image: map.pgm\nresolution: [0.05\n")
    with pytest.raises(MapFormatError, match=r"invalid YAML: .* line \d+, column \d+") as excinfo:
        load_map(path)
    assert_map_error(excinfo, path)


def test_missing_yaml_and_directory(tmp_path):
    with pytest.raises(MapFormatError, match="no such file") as excinfo:
        load_map(tmp_path / "none.yaml")
    assert_map_error(excinfo, tmp_path / "none.yaml")
    (tmp_path / "dir.yaml").mkdir()
    with pytest.raises(MapFormatError, match="directory") as excinfo:
        load_map(tmp_path / "dir.yaml")
    assert_map_error(excinfo, tmp_path / "dir.yaml")


@pytest.mark.parametrize("name", ["map.txt", "map", "map.json", "map.pgm.bak"])
def test_unknown_extension(tmp_path, name):
    (tmp_path / name).write_bytes(b"P5\n1 1\n255\n\x00")
    with pytest.raises(MapFormatError, match="extension") as excinfo:
        load_map(tmp_path / name)
    assert_map_error(excinfo, tmp_path / name)


def test_invalid_resolution_kwarg(tmp_path):
    write_pgm(tmp_path / "a.pgm", [[0]])
    with pytest.raises(MapFormatError) as excinfo:
        load_map(tmp_path / "a.pgm", resolution=-1)
    assert_map_error(excinfo, tmp_path / "a.pgm", "resolution")


def test_huge_image_behind_yaml_is_refused(tmp_path):
    (tmp_path / "huge.pgm").write_bytes(b"P5\n200000 200000\n255\n\x00")
    (tmp_path / "huge.yaml").write_text("image: huge.pgm\nresolution: 0.05\n")
    with pytest.raises(MapFormatError, match="limit") as excinfo:
        load_map(tmp_path / "huge.yaml")
    assert_map_error(excinfo, tmp_path / "huge.yaml", "image")
    write_pgm(tmp_path / "small.pgm", np.zeros((10, 10)))
    with pytest.raises(MapFormatError, match="limit of 99"):
        load_map(tmp_path / "small.pgm", max_pixels=99)


def test_pixels_to_ros_argument_checks():
    with pytest.raises(ValueError):
        pixels_to_ros(np.zeros((2, 2), np.uint8), mode="other")
    with pytest.raises(ValueError):
        pixels_to_ros(np.zeros((2, 2), np.float32))
    with pytest.raises(ValueError):
        pixels_to_ros(np.zeros((2, 2, 5), np.uint8))
    with pytest.raises(ValueError):
        grid_to_pixels(OccupancyGrid(np.zeros((1, 1))), mode="scale")


# ------------------------------------------------------------- shared real data
@pytest.mark.shared
def test_lse_arena(shared_data):
    path = shared_data / "ros_maps" / "lse_arena.yaml"
    img = read_image(path.with_suffix(".pgm"))
    grid = load_map(path)
    assert grid.shape == img.shape == (60, 80)
    assert grid.resolution == 0.05 and grid.origin == (0.0, 0.0, 0.0)
    assert_same(grid.data, ros_reference(img))
    assert int((grid.data == 1).sum()) == int((img == 0).sum()) == 345
    assert grid.known.all()


@pytest.mark.shared
def test_willow_garage_map_and_round_trip(shared_data, tmp_path):
    path = shared_data / "ros_maps" / "willow-full-0.05.yaml"
    img = read_image(shared_data / "ros_maps" / "willow-full-0.05.pgm")
    grid = load_map(path)
    assert grid.shape == (945, 1165)
    assert grid.resolution == 0.05
    assert_same(grid.data, ros_reference(img))
    copy = save_map(grid, tmp_path / "willow.yaml")
    assert load_map(copy) == grid
    raw = save_map(grid, tmp_path / "willow_raw.yaml", mode="raw")
    assert load_map(raw) == grid


@pytest.mark.shared
def test_halmstad_png(shared_data):
    path = shared_data / "halmstad" / "HIH" / "HIH_01.png"
    img = read_image(path)
    assert img.dtype == np.uint8 and img.ndim == 2
    assert set(np.unique(img).tolist()) <= {0, 127, 255}
    grid = load_map(path, resolution=0.1)
    assert grid.resolution == 0.1
    np.testing.assert_array_equal(grid.data == 1, img == 0)
    np.testing.assert_array_equal(grid.data == 0, img == 255)
    np.testing.assert_array_equal(np.isnan(grid.data), img == 127)


@pytest.mark.parametrize("mode", ["trinary", "scale", "raw"])
@pytest.mark.parametrize("negate", [False, True])
def test_every_grey_level_against_reference(mode, negate):
    levels = np.arange(256, dtype=np.uint8).reshape(16, 16)
    got = pixels_to_ros(levels, mode=mode, negate=negate)
    # the (H, W, 1) path computes pixel by pixel, the (H, W) path through a lookup table
    assert got.tolist() == pixels_to_ros(levels[:, :, None], mode=mode, negate=negate).tolist()
    for p, value in zip(levels.ravel().tolist(), got.ravel().tolist()):
        avg = 255 - p if negate else p
        if mode == "raw":
            assert value == (avg if avg < 128 else avg - 256)
        elif mode == "scale":
            assert value == scale_reference(avg)
        else:
            occ = (255 - avg) / 255.0
            assert value == (100 if occ > 0.65 else 0 if occ < 0.196 else -1)

"""ROS bags: reading nav_msgs/OccupancyGrid maps and writing merged maps with TF.

The input bags of these tests are built with rosbags' own writers (ROS 1, ROS 2 sqlite3,
ROS 2 mcap), independently of :func:`gridmerge.io.bags.write_bag`, from simulated robot
maps and, when ``../shared/data`` exists, a real ROS map.
"""

from __future__ import annotations

import errno
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

import gridmerge.io.bags as bags_module
from gridmerge import GridMergeError, MapFormatError, OccupancyGrid, load_map
from gridmerge.errors import InputTooLargeError, OutputError
from gridmerge.io import BagTransform, bag_topics, is_bag, read_bag_maps, write_bag
from gridmerge.io.bags import child_frame_for, write_map_messages
from gridmerge.samples import robot_pair

GRID = "nav_msgs/msg/OccupancyGrid"
FORMATS = [("ros1", "sqlite3"), ("ros2", "sqlite3"), ("ros2", "mcap")]
FORMAT_IDS = ["ros1", "ros2-sqlite3", "ros2-mcap"]
T0 = 1_700_000_000 * 10**9


# ------------------------------------------------------------------------- helpers
def typestore(ros1: bool):
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    return store


def bag_path(folder: Path, fmt: str, name: str = "input") -> Path:
    return folder / (f"{name}.bag" if fmt == "ros1" else name)


def grid_message(
    types,
    ros1: bool,
    *,
    width: int,
    height: int,
    data,
    resolution: float = 0.05,
    position=(0.0, 0.0),
    orientation=(0.0, 0.0, 0.0, 1.0),
    frame_id: str = "map",
    stamp_ns: int = T0,
):
    """A nav_msgs/OccupancyGrid message with any field values (also inconsistent ones)."""
    sec, nsec = divmod(stamp_ns, 10**9)
    time = types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
    header = types["std_msgs/msg/Header"](stamp=time, frame_id=frame_id, **({"seq": 0} if ros1 else {}))
    qx, qy, qz, qw = orientation
    info = types["nav_msgs/msg/MapMetaData"](
        map_load_time=time,
        resolution=resolution,
        width=width,
        height=height,
        origin=types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](x=position[0], y=position[1], z=0.0),
            orientation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        ),
    )
    return types[GRID](header=header, info=info, data=np.asarray(data, dtype=np.int8))


def message_of(grid: OccupancyGrid):
    """A builder of the message that ROS would publish for ``grid``."""
    x, y, yaw = grid.origin

    def build(types, ros1, stamp_ns):
        return grid_message(
            types,
            ros1,
            width=grid.width,
            height=grid.height,
            data=grid.to_ros(),
            resolution=grid.resolution,
            position=(x, y),
            orientation=(0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)),
            stamp_ns=stamp_ns,
        )

    return build


def string_message(text: str):
    def build(types, ros1, stamp_ns):
        return types["std_msgs/msg/String"](data=text)

    return build


def make_bag(path: Path, fmt: str, storage: str, messages, *, empty_topics=(), version: int = 9) -> Path:
    """Write a bag with rosbags' writers.

    ``messages``: ``(topic, msgtype, stamp_ns, build)`` with ``build(types, ros1, stamp_ns)``
    returning the message; ``empty_topics``: ``(topic, msgtype)`` connections without
    messages.
    """
    ros1 = fmt == "ros1"
    store = typestore(ros1)
    if ros1:
        writer = Writer1(path)
    else:
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=version, storage_plugin=plugin)
    conns = {}
    with writer:
        for topic, msgtype in empty_topics:
            conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
        for topic, msgtype, stamp, build in messages:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
            msg = build(store.types, ros1, stamp)
            raw = store.serialize_ros1(msg, msgtype) if ros1 else store.serialize_cdr(msg, msgtype)
            writer.write(conns[topic], stamp, raw)
    return path


def quantized(grid: OccupancyGrid) -> OccupancyGrid:
    """``grid`` with its cells rounded to whole percentages, as a ROS message holds them."""
    return OccupancyGrid.from_ros(grid.to_ros(), grid.width, grid.height, grid.resolution, grid.origin, grid.name)


def snapshot(path: Path) -> dict:
    """Bytes and modification time of every file of a bag (file or folder)."""
    files = sorted(path.rglob("*")) if path.is_dir() else [path]
    return {str(f): (f.read_bytes(), f.stat().st_mtime_ns) for f in files if f.is_file()}


def yaw_of(q) -> float:
    return 2 * math.atan2(q.z, q.w)


def check_one_line(exc: BaseException, *parts: str) -> str:
    text = str(exc)
    assert "\n" not in text and text.strip() == text
    for part in parts:
        assert part in text, (part, text)
    return text


@pytest.fixture(scope="module")
def robots():
    """Two simulated robot maps, quantized to percent, with non-trivial origins."""
    a, b, _ = robot_pair(seed=0)
    a = quantized(a.replace(origin=(0.7, -3.25, 0.8)))
    b = quantized(b.replace(resolution=round(b.resolution, 6), origin=(-12.5, 4.0, -2.5)))
    return a, b


@pytest.fixture(params=FORMATS, ids=FORMAT_IDS)
def fmt(request):
    return request.param


# ------------------------------------------------------------------ round trips
def test_round_trip_rosbags_bag(tmp_path, fmt, robots):
    kind, storage = fmt
    a, b = robots
    path = make_bag(
        bag_path(tmp_path, kind),
        kind,
        storage,
        [("/robot1/map", GRID, T0, message_of(a)), ("/robot2/map", GRID, T0 + 1, message_of(b))],
    )
    got = read_bag_maps(path)
    assert [g.name for g in got] == ["/robot1/map", "/robot2/map"]
    for back, grid in zip(got, (a, b)):
        assert back == grid  # values (NaN = unknown), shape, resolution, origin incl. yaw
        assert back.resolution == grid.resolution and back.origin == grid.origin


def test_round_trip_write_bag(tmp_path, fmt, robots):
    kind, storage = fmt
    a, b = robots
    for grid in (a, b):
        out = write_bag(bag_path(tmp_path, kind, grid.name.split()[1]), grid, format=kind, storage=storage)
        [back] = read_bag_maps(out)
        assert back == grid and back.name == "/map"


@pytest.mark.shared
def test_round_trip_real_map(tmp_path, fmt, shared_data):
    kind, storage = fmt
    grid = load_map(shared_data / "ros_maps" / "willow-full.yaml")  # 584 x 526 at 0.1 m
    grid = grid.replace(origin=(-3.5, 7.25, math.pi))
    out = write_bag(bag_path(tmp_path, kind), grid, format=kind, storage=storage, map_topic="/willow/map")
    [back] = read_bag_maps(out)
    assert back == grid and back.name == "/willow/map"
    # and from a bag written with rosbags directly
    path = make_bag(bag_path(tmp_path, kind, "direct"), kind, storage, [("/map", GRID, T0, message_of(grid))])
    assert read_bag_maps(path)[0] == grid


def test_unrounded_resolution_comes_back_at_float32_precision(tmp_path, robots):
    a, _ = robots
    res = 0.05259027897550328  # robot b's resolution in the simulator: no short decimal
    out = write_bag(tmp_path / "out", a.replace(resolution=res))
    [back] = read_bag_maps(out)
    assert back.resolution == pytest.approx(res, rel=1e-7)
    assert np.float32(back.resolution) == np.float32(res)


SPECIAL_YAWS = [0.0, -0.0, 1e-12, 0.1, 1.0, math.pi / 2, -math.pi / 2, math.pi / 4, math.pi, -math.pi, 3.0, -3.1]


@pytest.mark.parametrize("yaw", SPECIAL_YAWS)
def test_yaw_round_trips_exactly(yaw):
    assert bags_module._quaternion_to_yaw(*bags_module._yaw_to_quaternion(yaw)) == yaw


def test_random_yaws_round_trip_exactly():
    rng = np.random.default_rng(0)
    for yaw in rng.uniform(-math.pi, math.pi, 5000):
        q = bags_module._yaw_to_quaternion(float(yaw))
        assert bags_module._quaternion_to_yaw(*q) == yaw
        assert q[:2] == (0.0, 0.0)
        assert abs(q[2] - math.sin(yaw / 2)) <= 1e-15 and abs(q[3] - math.cos(yaw / 2)) <= 1e-15


def test_short_yaws_of_other_writers_come_back_exactly():
    """Quaternions computed as plain (sin(yaw/2), cos(yaw/2)), as map_server does."""
    rng = np.random.default_rng(1)
    for yaw in rng.uniform(-math.pi, math.pi, 2000):
        short = float(f"{yaw:.{rng.integers(1, 16)}g}")
        assert bags_module._quaternion_to_yaw(0.0, 0.0, math.sin(short / 2), math.cos(short / 2)) == short


def test_yaw_outside_pi_comes_back_equivalent():
    for yaw in (4.0, -4.0, 7.0):
        back = bags_module._quaternion_to_yaw(*bags_module._yaw_to_quaternion(yaw))
        assert -math.pi <= back <= math.pi
        assert math.isclose(math.remainder(back - yaw, 2 * math.pi), 0.0, abs_tol=1e-12)


# ------------------------------------------------------------------ selection
def two_maps(a: OccupancyGrid, b: OccupancyGrid, stamps=(T0, T0 + 1)):
    return [("/map", GRID, stamps[0], message_of(a)), ("/map", GRID, stamps[1], message_of(b))]


def test_last_message_per_topic_wins(tmp_path, fmt, robots):
    kind, storage = fmt
    a, b = robots
    path = make_bag(bag_path(tmp_path, kind), kind, storage, two_maps(a, b))
    [back] = read_bag_maps(path)
    assert back == b


def test_last_means_latest_time_stamp(tmp_path, fmt, robots):
    kind, storage = fmt
    a, b = robots
    # b is written first but stamped later
    path = make_bag(bag_path(tmp_path, kind), kind, storage, two_maps(b, a, stamps=(T0 + 5, T0)))
    [back] = read_bag_maps(path)
    assert back == b


def test_topics_filter_and_order(tmp_path, fmt, robots):
    kind, storage = fmt
    a, b = robots
    path = make_bag(
        bag_path(tmp_path, kind),
        kind,
        storage,
        [
            ("/robot2/map", GRID, T0, message_of(b)),
            ("/chatter", "std_msgs/msg/String", T0 + 1, string_message("hello")),
            ("/robot1/map", GRID, T0 + 2, message_of(a)),
            ("/robot3/map", GRID, T0 + 3, message_of(a.replace(resolution=0.1))),
        ],
    )
    assert [g.name for g in read_bag_maps(path)] == ["/robot1/map", "/robot2/map", "/robot3/map"]
    got = read_bag_maps(path, ["/robot2/map", "/robot1/map"])
    assert [g.name for g in got] == ["/robot2/map", "/robot1/map"]
    assert got[0] == b and got[1] == a
    # a single name, and a name without its leading slash
    [only] = read_bag_maps(path, "robot3/map")
    assert only.name == "/robot3/map" and only.resolution == 0.1


def test_default_ignores_other_topics(tmp_path, fmt, robots):
    kind, storage = fmt
    a, _ = robots
    path = make_bag(
        bag_path(tmp_path, kind),
        kind,
        storage,
        [
            ("/chatter", "std_msgs/msg/String", T0, string_message("x")),
            ("/map", GRID, T0 + 1, message_of(a)),
            ("/zzz", "std_msgs/msg/String", T0 + 2, string_message("y")),
        ],
    )
    assert [g.name for g in read_bag_maps(path)] == ["/map"]
    assert bag_topics(path) == [
        ("/chatter", "std_msgs/msg/String", 1),
        ("/map", GRID, 1),
        ("/zzz", "std_msgs/msg/String", 1),
    ]


def test_several_ros1_bags_read_as_one(tmp_path, robots):
    a, b = robots
    first = make_bag(tmp_path / "run_0.bag", "ros1", "", [("/map", GRID, T0, message_of(a))])
    second = make_bag(tmp_path / "run_1.bag", "ros1", "", [("/map", GRID, T0 + 10, message_of(b))])
    assert read_bag_maps([second, first])[0] == b
    ros2 = write_bag(tmp_path / "ros2", a)
    with pytest.raises(MapFormatError) as info:
        read_bag_maps([first, ros2])
    check_one_line(info.value, "ROS 1 and ROS 2")


# ------------------------------------------------------------------ paths
def test_is_bag(tmp_path):
    folder = tmp_path / "bag2"
    folder.mkdir()
    assert not is_bag(folder)
    (folder / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    assert is_bag(folder) and is_bag(folder / "metadata.yaml")
    assert is_bag(tmp_path / "x.bag") and is_bag(tmp_path / "x.db3") and is_bag(tmp_path / "x.mcap")
    assert not is_bag(tmp_path / "map.yaml") and not is_bag(tmp_path / "map.pgm") and not is_bag(tmp_path)
    (tmp_path / "metadata.yaml").write_text("image: map.pgm\n")  # a map_server YAML so named
    assert not is_bag(tmp_path / "metadata.yaml")


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_storage_file_stands_for_its_folder_or_alone(tmp_path, robots, storage):
    a, b = robots
    folder = make_bag(tmp_path / "rec", "ros2", storage, two_maps(a, b))
    [file] = [p for p in folder.iterdir() if p.suffix in (".db3", ".mcap")]
    assert is_bag(file)
    assert read_bag_maps(file)[0] == b
    assert read_bag_maps(folder / "metadata.yaml")[0] == b
    bare = tmp_path / f"bare{file.suffix}"  # no metadata.yaml next to it: read on its own
    shutil.copy(file, bare)
    assert read_bag_maps(bare)[0] == b
    assert bag_topics(bare) == [("/map", GRID, 2)]


def test_reading_leaves_the_bag_untouched(tmp_path, fmt, robots):
    kind, storage = fmt
    a, b = robots
    path = make_bag(bag_path(tmp_path, kind), kind, storage, two_maps(a, b))
    before = snapshot(path)
    listing = sorted(os.listdir(tmp_path))
    read_bag_maps(path)
    bag_topics(path)
    with pytest.raises(MapFormatError):
        read_bag_maps(path, ["/nope"])
    assert snapshot(path) == before
    assert sorted(os.listdir(tmp_path)) == listing


# ------------------------------------------------------------------ errors
@pytest.fixture
def small():
    return quantized(OccupancyGrid(np.array([[0.0, 1.0, np.nan], [0.5, 0.0, 1.0]]), resolution=0.05))


def test_error_named_topic_absent(tmp_path, fmt, small):
    kind, storage = fmt
    path = make_bag(
        bag_path(tmp_path, kind),
        kind,
        storage,
        [("/robot1/map", GRID, T0, message_of(small)), ("/robot2/map", GRID, T0, message_of(small))],
    )
    with pytest.raises(MapFormatError) as info:
        read_bag_maps(path, ["/robot1/map", "/robot9/map"])
    check_one_line(info.value, path.name, "/robot9/map", "not found", "/robot1/map, /robot2/map")


def test_error_topic_of_other_type(tmp_path, fmt, small):
    kind, storage = fmt
    path = make_bag(
        bag_path(tmp_path, kind),
        kind,
        storage,
        [("/map", GRID, T0, message_of(small)), ("/chatter", "std_msgs/msg/String", T0, string_message("x"))],
    )
    with pytest.raises(MapFormatError) as info:
        read_bag_maps(path, ["/chatter"])
    check_one_line(info.value, path.name, "/chatter", "std_msgs/msg/String", "not nav_msgs/msg/OccupancyGrid")


def test_error_topic_without_messages(tmp_path, fmt, small):
    kind, storage = fmt
    path = make_bag(
        bag_path(tmp_path, kind),
        kind,
        storage,
        [("/robot1/map", GRID, T0, message_of(small))],
        empty_topics=[("/robot2/map", GRID)],
    )
    with pytest.raises(MapFormatError) as info:
        read_bag_maps(path)
    check_one_line(info.value, path.name, "/robot2/map", "no messages")
    assert read_bag_maps(path, ["/robot1/map"])[0] == small


def test_error_no_occupancy_grid_topic(tmp_path, fmt):
    kind, storage = fmt
    path = make_bag(bag_path(tmp_path, kind), kind, storage, [("/chatter", "std_msgs/msg/String", T0, string_message("x"))])
    with pytest.raises(MapFormatError) as info:
        read_bag_maps(path)
    check_one_line(info.value, path.name, "no nav_msgs/OccupancyGrid topic", "/chatter (std_msgs/msg/String)")


def test_error_too_large(tmp_path, fmt, robots):
    kind, storage = fmt
    a, _ = robots
    path = make_bag(bag_path(tmp_path, kind), kind, storage, [("/map", GRID, T0, message_of(a))])
    with pytest.raises(InputTooLargeError) as info:
        read_bag_maps(path, max_pixels=a.width * a.height - 1)
    assert info.value.limit == "max_pixels"
    check_one_line(info.value, path.name, "/map", f"{a.width} x {a.height}", "max_pixels")
    assert read_bag_maps(path, max_pixels=a.width * a.height)[0] == a


def test_size_is_checked_before_the_data(tmp_path, fmt, monkeypatch):
    kind, storage = fmt

    def huge(types, ros1, stamp_ns):  # claims 10^10 cells, holds 4
        return grid_message(types, ros1, width=100_000, height=100_000, data=[0, 0, 0, 0], stamp_ns=stamp_ns)

    path = make_bag(bag_path(tmp_path, kind), kind, storage, [("/map", GRID, T0, huge)])
    monkeypatch.setattr(OccupancyGrid, "from_ros", classmethod(lambda *a, **k: pytest.fail("data decoded")))
    with pytest.raises(InputTooLargeError) as info:
        read_bag_maps(path)
    check_one_line(info.value, "100000 x 100000 = 10000000000 cells", "/map")


@pytest.mark.parametrize(
    "fields, expected",
    [
        (dict(width=3, height=2, data=[0] * 5), "data has 5 cells but info.width x info.height = 3 x 2 = 6"),
        (dict(width=0, height=0, data=[]), "empty"),
        (dict(width=1, height=1, data=[0], resolution=0.0), "info.resolution"),
        (dict(width=1, height=1, data=[0], resolution=float("nan")), "info.resolution"),
        (dict(width=1, height=1, data=[0], position=(float("inf"), 0.0)), "info.origin.position"),
        (dict(width=1, height=1, data=[0], orientation=(0.0, 0.3, 0.0, 0.95)), "roll/pitch"),
        (dict(width=1, height=1, data=[0], orientation=(0.1, 0.0, 0.2, 0.97)), "roll/pitch"),
        (dict(width=1, height=1, data=[0], orientation=(0.0, 0.0, float("nan"), 1.0)), "not finite"),
    ],
    ids=["length", "empty", "res0", "resnan", "posinf", "pitch", "roll", "nanq"],
)
def test_error_malformed_message(tmp_path, fields, expected):
    for kind, storage in FORMATS[:2]:
        path = make_bag(
            bag_path(tmp_path, kind, f"bad-{kind}"),
            kind,
            storage,
            [("/robot1/map", GRID, T0, lambda types, ros1, stamp: grid_message(types, ros1, stamp_ns=stamp, **fields))],
        )
        with pytest.raises(MapFormatError) as info:
            read_bag_maps(path)
        check_one_line(info.value, path.name, "/robot1/map", expected)


def test_zero_and_unnormalised_quaternions(tmp_path):
    def msg(orientation):
        return lambda types, ros1, stamp: grid_message(
            types, ros1, width=2, height=1, data=[0, 100], orientation=orientation, stamp_ns=stamp
        )

    path = make_bag(
        tmp_path / "q.bag",
        "ros1",
        "",
        [
            ("/zero", GRID, T0, msg((0.0, 0.0, 0.0, 0.0))),  # default-constructed in ROS 1 C++
            ("/scaled", GRID, T0, msg((0.0, 0.0, 2 * math.sin(0.3), 2 * math.cos(0.3)))),
            ("/negated", GRID, T0, msg((0.0, 0.0, -math.sin(0.3), -math.cos(0.3)))),
        ],
    )
    negated, scaled, zero = read_bag_maps(path)
    assert zero.origin == (0.0, 0.0, 0.0)
    assert scaled.origin[2] == pytest.approx(0.6, abs=1e-12)
    assert negated.origin[2] == pytest.approx(0.6, abs=1e-12)


NOT_BAGS = {
    "missing.bag": None,
    "text.txt": b"hello",
    "garbage.bag": b"#ROSBAG V2.0\n" + bytes(range(256)) * 4,
    "empty.bag": b"",
    "garbage.mcap": b"\x89MCAP0\r\n" + b"\x00" * 100,
    "garbage.db3": b"SQLite format 3\x00" + b"\x01" * 200,
    "folder": "dir",
    "bagdir": "badmeta",
}


@pytest.mark.parametrize("name", sorted(NOT_BAGS))
def test_error_not_a_bag(tmp_path, name):
    path = tmp_path / name
    content = NOT_BAGS[name]
    if content == "dir":
        path.mkdir()
    elif content == "badmeta":
        path.mkdir()
        (path / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n")
    elif content is not None:
        path.write_bytes(content)
    for call in (read_bag_maps, bag_topics):
        with pytest.raises(MapFormatError) as info:
            call(path)
        check_one_line(info.value, name)


def test_error_truncated_bags(tmp_path, fmt, robots):
    kind, storage = fmt
    a, b = robots
    path = make_bag(bag_path(tmp_path, kind), kind, storage, two_maps(a, b))
    file = path if kind == "ros1" else next(p for p in path.iterdir() if p.suffix in (".db3", ".mcap"))
    data = file.read_bytes()
    for cut in (len(data) // 2, len(data) - 10, 20):
        file.write_bytes(data[:cut])
        with pytest.raises(MapFormatError) as info:
            read_bag_maps(path)
        check_one_line(info.value, path.name)


def test_corrupt_bags_never_give_a_traceback(tmp_path, fmt, small):
    """Bytes flipped all over a small bag: a result or a MapFormatError, nothing else."""
    kind, storage = fmt
    path = make_bag(bag_path(tmp_path, kind), kind, storage, [("/map", GRID, T0, message_of(small))])
    file = path if kind == "ros1" else next(p for p in path.iterdir() if p.suffix in (".db3", ".mcap"))
    data = bytearray(file.read_bytes())
    rng = np.random.default_rng(1)
    outcomes = set()
    for offset in np.linspace(0, len(data) - 1, 30).astype(int):
        bad = bytearray(data)
        bad[offset] ^= int(rng.integers(1, 256))
        file.write_bytes(bytes(bad))
        try:
            read_bag_maps(path)
            outcomes.add("ok")
        except MapFormatError as exc:
            check_one_line(exc)
            outcomes.add("error")
    assert "error" in outcomes


def test_error_bad_topics_argument(tmp_path, small):
    path = write_bag(tmp_path / "b", small)
    with pytest.raises(GridMergeError, match="no topic given"):
        read_bag_maps(path, [])
    with pytest.raises(GridMergeError, match="given twice"):
        read_bag_maps(path, ["/map", "map"])


# ------------------------------------------------------------------ writing
def read_all(path: Path):
    """``{topic: [(connection, stamp, message)]}`` of a bag, via rosbags."""
    out: dict = {}
    with AnyReader([path]) as reader:
        for conn, stamp, raw in reader.messages():
            out.setdefault(conn.topic, []).append((conn, stamp, reader.deserialize(raw, conn.msgtype)))
    return out


def test_write_bag_map_and_tf(tmp_path, fmt, robots):
    kind, storage = fmt
    a, _ = robots
    transforms = [
        BagTransform(child_frame_for("/robot1/map"), 0.0, 0.0, 0.0),
        BagTransform(child_frame_for("/robot2/map"), x=12.5, y=-3.0, yaw=2.75),
    ]
    stamp = T0 + 123_456_789
    out = write_bag(
        bag_path(tmp_path, kind, "merged"),
        a,
        transforms,
        format=kind,
        storage=storage,
        map_topic="/map_merged",
        frame_id="world",
        stamp_ns=stamp,
    )
    assert out == bag_path(tmp_path, kind, "merged")
    assert bag_topics(out) == [("/map_merged", GRID, 1), ("/tf_static", "tf2_msgs/msg/TFMessage", 1)]
    if kind == "ros2":
        suffix = ".mcap" if storage == "mcap" else ".db3"
        assert sorted(p.name for p in out.iterdir()) == sorted(["metadata.yaml", f"merged{suffix}"])
    content = read_all(out)
    [(conn, t, msg)] = content["/map_merged"]
    assert t == stamp
    assert msg.header.frame_id == "world"
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == divmod(stamp, 10**9)
    assert (msg.info.map_load_time.sec, msg.info.map_load_time.nanosec) == divmod(stamp, 10**9)
    assert (msg.info.width, msg.info.height) == (a.width, a.height)
    assert np.array_equal(msg.data, a.to_ros())
    [(tf_conn, t, tf)] = content["/tf_static"]
    assert t == stamp
    assert [e.header.frame_id for e in tf.transforms] == ["world", "world"]
    assert [e.child_frame_id for e in tf.transforms] == ["robot1/map", "robot2/map"]
    for entry, want in zip(tf.transforms, transforms):
        tr, q = entry.transform.translation, entry.transform.rotation
        assert (tr.x, tr.y, tr.z) == (want.x, want.y, 0.0)
        assert (q.x, q.y) == (0.0, 0.0)
        assert math.isclose(q.x**2 + q.y**2 + q.z**2 + q.w**2, 1.0, rel_tol=1e-12)
        assert yaw_of(q) == pytest.approx(want.yaw, abs=1e-12)
        assert (entry.header.stamp.sec, entry.header.stamp.nanosec) == divmod(stamp, 10**9)
    # latched (ROS 1) / transient local (ROS 2), as map_server and static TF publish
    for c in (conn, tf_conn):
        if kind == "ros1":
            assert c.ext.latching == 1
        else:
            assert [q.durability.name for q in c.ext.offered_qos_profiles] == ["TRANSIENT_LOCAL"]


def test_write_bag_without_transforms(tmp_path, small):
    out = write_bag(tmp_path / "m", small, stamp_ns=5)
    assert bag_topics(out) == [("/map", GRID, 1)]


def test_write_map_messages(tmp_path, fmt, robots):
    kind, storage = fmt
    a, b = robots
    out = write_map_messages(
        bag_path(tmp_path, kind),
        [("/robot1/map", a, T0), ("robot2/map", b, T0), ("/robot1/map", b, T0 + 1)],
        format=kind,
        storage=storage,
    )
    assert bag_topics(out) == [("/robot1/map", GRID, 2), ("/robot2/map", GRID, 1)]
    assert read_bag_maps(out) == [b, b]


def test_bag_transform():
    t = BagTransform("robot2/map", 1.0, 2.0, math.pi / 2)
    assert np.allclose(t.apply([[1.0, 0.0], [0.0, 0.0]]), [[1.0, 3.0], [1.0, 2.0]])
    m = t.matrix()
    assert np.allclose(m[:2, :2] @ [1.0, 0.0] + m[:2, 2], [1.0, 3.0])
    assert BagTransform.from_matrix("robot2/map", m) == t
    assert BagTransform.from_matrix("robot2/map", m[:2]) == t
    scaled = m.copy()
    scaled[:2, :2] *= 1.1
    with pytest.raises(ValueError, match="not a rigid"):
        BagTransform.from_matrix("r", scaled)
    with pytest.raises(ValueError, match="mirrored"):
        BagTransform.from_matrix("r", np.diag([1.0, -1.0, 1.0]))
    for bad in (dict(child_frame=""), dict(child_frame="/robot"), dict(child_frame="a b"), dict(x=float("nan")), dict(yaw="x")):
        kwargs = dict(child_frame="r", x=0.0, y=0.0, yaw=0.0) | bad
        with pytest.raises(ValueError):
            BagTransform(**kwargs)


def test_child_frame_for():
    assert child_frame_for("/robot1/map") == "robot1/map"
    assert child_frame_for("map") == "map"
    assert child_frame_for("/robot1/map_merge") == "robot1/map_merge"
    assert child_frame_for("") == "map" and child_frame_for("/") == "map"


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(format="ros3"),
        dict(storage="leveldb"),
        dict(frame_id="/map"),
        dict(frame_id=""),
        dict(map_topic="a b"),
        dict(stamp_ns=-1),
        dict(stamp_ns=2**63),
        dict(stamp_ns=1.5),
        dict(transforms=[BagTransform("map", 0, 0, 0)]),
        dict(transforms=[BagTransform("r", 0, 0, 0), BagTransform("r", 1, 0, 0)]),
    ],
)
def test_write_bag_refuses_bad_arguments(tmp_path, small, kwargs):
    with pytest.raises(ValueError):
        write_bag(tmp_path / "out", small, **kwargs)
    assert os.listdir(tmp_path) == []


# ------------------------------------------------------------------ atomicity
def test_existing_output_is_refused(tmp_path, fmt, small):
    kind, storage = fmt
    out = write_bag(bag_path(tmp_path, kind), small, format=kind, storage=storage, stamp_ns=1)
    before = snapshot(out)
    with pytest.raises(OutputError) as info:
        write_bag(out, small.replace(resolution=0.2), format=kind, storage=storage)
    check_one_line(info.value, "exists already", "overwrite=True")
    assert snapshot(out) == before
    assert sorted(os.listdir(tmp_path)) == [out.name]


def test_overwrite_replaces_a_bag(tmp_path, fmt, small):
    kind, storage = fmt
    out = write_bag(bag_path(tmp_path, kind), small, format=kind, storage=storage)
    new = small.replace(resolution=0.2)
    write_bag(out, new, format=kind, storage=storage, overwrite=True)
    assert read_bag_maps(out) == [new]
    assert sorted(os.listdir(tmp_path)) == [out.name]


def test_overwrite_refuses_what_is_not_a_bag(tmp_path, small):
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "cat.jpg").write_bytes(b"meow")
    with pytest.raises(OutputError, match="not a ROS 2 bag"):
        write_bag(folder, small, overwrite=True)
    with pytest.raises(OutputError, match="is a folder"):
        write_bag(folder, small, format="ros1", overwrite=True)
    (tmp_path / "file").write_bytes(b"x")
    with pytest.raises(OutputError, match="not a folder"):
        write_bag(tmp_path / "file", small, overwrite=True)
    assert (folder / "cat.jpg").read_bytes() == b"meow" and (tmp_path / "file").read_bytes() == b"x"
    empty = tmp_path / "empty"
    empty.mkdir()
    write_bag(empty, small, overwrite=True)  # an empty folder may become the bag
    assert read_bag_maps(empty) == [small]
    assert sorted(os.listdir(tmp_path)) == ["empty", "file", "photos"]


def test_missing_output_folder(tmp_path, small):
    with pytest.raises(OutputError, match="does not exist"):
        write_bag(tmp_path / "nope" / "out", small)


@pytest.mark.parametrize("overwrite", [False, True], ids=["new", "overwrite"])
def test_failure_mid_write_leaves_nothing(tmp_path, fmt, small, monkeypatch, overwrite):
    kind, storage = fmt
    out = bag_path(tmp_path, kind)
    before = {}
    if overwrite:
        write_bag(out, small, format=kind, storage=storage)
        before = snapshot(out)
    store = bags_module._typestore(kind == "ros1")
    name = "serialize_ros1" if kind == "ros1" else "serialize_cdr"
    original = getattr(store, name)
    calls = []

    def failing(message, typename, *args, **kwargs):
        calls.append(typename)
        if len(calls) == 2:  # the map is in the bag, the TF message fails
            raise RuntimeError("serializer exploded")
        return original(message, typename, *args, **kwargs)

    monkeypatch.setattr(store, name, failing)
    with pytest.raises(RuntimeError, match="exploded"):
        write_bag(out, small, [BagTransform("robot1/map", 0, 0, 0)], format=kind, storage=storage, overwrite=overwrite)
    assert calls == [GRID, "tf2_msgs/msg/TFMessage"]
    assert sorted(os.listdir(tmp_path)) == ([out.name] if overwrite else [])
    if overwrite:
        assert snapshot(out) == before


def test_disk_full_is_an_output_error(tmp_path, fmt, small, monkeypatch):
    kind, storage = fmt
    import rosbags.rosbag1
    import rosbags.rosbag2

    writer = rosbags.rosbag1.Writer if kind == "ros1" else rosbags.rosbag2.Writer

    def full(self, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(writer, "write", full)
    with pytest.raises(OutputError) as info:
        write_bag(bag_path(tmp_path, kind), small, format=kind, storage=storage)
    check_one_line(info.value, "No space left on device")
    assert os.listdir(tmp_path) == []


def test_failed_publish_keeps_the_old_bag(tmp_path, small, monkeypatch):
    out = write_bag(tmp_path / "bag", small)
    before = snapshot(out)
    real_rename = os.rename

    def rename(src, dst):
        if Path(dst) == out and Path(src).name != ".previous":  # moving the new bag in fails
            raise OSError(errno.EIO, "I/O error")
        return real_rename(src, dst)

    monkeypatch.setattr(os, "rename", rename)
    with pytest.raises(OutputError, match="I/O error"):
        write_bag(out, small.replace(resolution=0.3), overwrite=True)
    assert snapshot(out) == before
    assert sorted(os.listdir(tmp_path)) == ["bag"]

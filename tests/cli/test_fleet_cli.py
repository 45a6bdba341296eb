"""``gridmerge merge`` with many maps: files and ROS bags in, map + bag out, executors.

Run in process (``gridmerge.cli.main.main``) to keep the fleet merges few and fast; the
subprocess behaviour of the program is covered by ``test_cli.py``.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from gridmerge import load_map
from gridmerge.cli.main import main
from gridmerge.io.bags import read_bag_maps, write_map_messages
from gridmerge.samples import write_sample

ROBOTS = [f"robot{k}" for k in range(1, 9)]
#: Three robots of the sample fleet whose maps all overlap one another.
TRIO = ["robot1", "robot6", "robot8"]

# The fleets merged once per module: its tests run in one worker (pytest-xdist, --dist loadgroup).
pytestmark = pytest.mark.xdist_group("fleet-cli")


@pytest.fixture(scope="module")
def fleet_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fleet")
    write_sample(folder, "fleet", 0)
    return folder


def _files(folder: Path) -> dict:
    return {p.name: p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _run(capsys, *args, cwd=None):
    import os

    old = os.getcwd()
    if cwd is not None:
        os.chdir(cwd)
    try:
        code = main([str(a) for a in args])
    finally:
        os.chdir(old)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def bag_merge(fleet_dir, tmp_path_factory):
    """Three robots and the stranger chosen from the sample bag by topic, merged once: JSON,
    merged map, ROS 2 out-bag, picture (on two worker processes, which give the same merge
    as one: test_workers_give_the_same_merge). The eight robots' merge is the library's
    (tests/test_fleet.py); a bag's topics all merge by default in
    test_files_ros1_and_ros2_bags_give_the_same_merge."""
    import contextlib
    import io

    out = tmp_path_factory.mktemp("bagmerge")
    args = ["merge", str(fleet_dir / "fleet.bag"), "-o", str(out / "merged.yaml"), "--json",
            "--out-bag", str(out / "merged_bag"), "--plot", str(out / "fleet.png"), "--workers", "2"]
    for name in TRIO + ["stranger"]:
        args += ["--topic", f"/{name}/map"]
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(args)
    return code, json.loads(buf.getvalue()), out


def test_topics_from_a_bag_place_the_robots_and_leave_the_stranger_out(bag_merge):
    code, d, out = bag_merge
    assert code == 0 and d["success"]
    assert d["unplaced"] == ["/stranger/map"]
    placed = [e["name"] for e in d["maps"] if e["placed"]]
    assert placed == [f"/{n}/map" for n in TRIO]
    assert d["out_bag"] == str(out / "merged_bag") and d["output"] == str(out / "merged.yaml")
    assert (out / "fleet.png").read_bytes().startswith(b"\x89PNG")


def test_the_same_fleet_from_a_ros2_bag_gives_the_same_maps(fleet_dir, tmp_path):
    # A merge is a function of the maps (their names aside), and the CLI merges from ROS 2
    # bags as from ROS 1 bags (test_files_ros1_and_ros2_bags_give_the_same_merge): the
    # fleet through a ROS 2 bag is the same maps, cell for cell, so the same merge.
    maps = read_bag_maps(fleet_dir / "fleet.bag")
    write_map_messages(tmp_path / "fleet_ros2", [(m.name, m, 10**18 + k) for k, m in enumerate(maps)], storage="mcap")
    again = read_bag_maps(tmp_path / "fleet_ros2")
    assert [m.name for m in again] == [m.name for m in maps] == [f"/{n}/map" for n in ROBOTS] + ["/stranger/map"]
    for m, n in zip(maps, again):
        assert n == m and n.data.dtype == m.data.dtype
        assert n.origin == m.origin and n.resolution == m.resolution


def test_out_bag_holds_the_merged_map(bag_merge):
    _, _, out = bag_merge
    merged = load_map(out / "merged.yaml")  # trinary: grey cells between the thresholds
    (m,) = read_bag_maps(out / "merged_bag")
    assert m.name == "/map" and m.shape == merged.shape
    assert m.resolution == pytest.approx(merged.resolution, rel=1e-6)
    np.testing.assert_allclose(m.origin, merged.origin, atol=1e-4)
    assert (m.known | ~merged.known).all()
    both = merged.known
    np.testing.assert_array_equal(m.occupied()[both], merged.occupied()[both])


def test_fleet_json_names_maps_by_topic(fleet_dir, bag_merge):
    # The three-robot subset plus the stranger, from the bag, by --topic.
    _, d, _ = bag_merge
    names = [e["name"] for e in d["maps"]]
    assert names == [f"/{n}/map" for n in TRIO + ["stranger"]]
    assert d["unplaced"] == ["/stranger/map"] and d["reference"] == "/robot1/map"
    truth = json.loads((fleet_dir / "truth.json").read_text())["to_building"]
    ref = load_map(fleet_dir / "robot1.yaml")
    for e, name in zip(d["maps"][:3], TRIO):
        assert e["placed"] and len(e["matrix"]) == 2 and len(e["matrix"][0]) == 3
        assert set(e["metric"]) == {"x", "y", "yaw", "scale"} and 0.5 <= e["confidence"] <= 1
        # The metric pose against the truth (robot frames have origin 0, yaw 0).
        rel = np.linalg.inv(np.array(truth["robot1"])) @ np.array(truth[name])
        mine = load_map(fleet_dir / f"{name}.yaml")
        want = ref.pixel_to_metric_matrix() @ rel @ mine.metric_to_pixel_matrix()
        assert e["metric"]["x"] == pytest.approx(want[0, 2], abs=0.1)
        assert e["metric"]["y"] == pytest.approx(want[1, 2], abs=0.1)
        assert math.cos(e["metric"]["yaw"] - math.atan2(want[1, 0], want[0, 0])) > math.cos(0.01)
    assert not d["maps"][3]["placed"]


def test_files_ros1_and_ros2_bags_give_the_same_merge(fleet_dir, capsys, tmp_path):
    maps = [load_map(fleet_dir / f"{n}.yaml") for n in TRIO]
    msgs = [(f"/{n}/map", m, 10**18 + k) for k, (n, m) in enumerate(zip(TRIO, maps))]
    write_map_messages(tmp_path / "trio.bag", msgs, format="ros1")
    write_map_messages(tmp_path / "trio_sqlite", msgs, format="ros2", storage="sqlite3")
    write_map_messages(tmp_path / "trio_mcap", msgs, format="ros2", storage="mcap")
    outputs = []
    for k, inputs in enumerate([[fleet_dir / f"{n}.yaml" for n in TRIO], [tmp_path / "trio.bag"],
                                [tmp_path / "trio_sqlite"], [tmp_path / "trio_mcap"]]):
        code, out, err = _run(capsys, "merge", *inputs, "-o", tmp_path / f"m{k}.yaml")
        assert code == 0, err
        assert "merged 3 of 3 maps" in out
        outputs.append((tmp_path / f"m{k}.pgm").read_bytes())
    assert all(o == outputs[0] for o in outputs[1:])


def test_several_bags_each_give_their_topics(fleet_dir, capsys, tmp_path):
    maps = {n: load_map(fleet_dir / f"{n}.yaml") for n in TRIO}
    write_map_messages(tmp_path / "one.bag", [("/robot1/map", maps["robot1"], 1)], format="ros1")
    write_map_messages(tmp_path / "two", [("/robot6/map", maps["robot6"], 1), ("/robot8/map", maps["robot8"], 2)])
    code, out, err = _run(capsys, "merge", tmp_path / "one.bag", tmp_path / "two", "-o", tmp_path / "m.yaml",
                          "--topic", "/robot1/map", "--topic", "robot8/map", "--json")
    assert code == 0, err
    assert [e["name"] for e in json.loads(out)["maps"]] == ["/robot1/map", "/robot8/map"]


def test_out_bag_carries_each_robot_transform_as_tf(fleet_dir, capsys, tmp_path):
    from rosbags.highlevel import AnyReader

    inputs = [fleet_dir / f"{n}.yaml" for n in TRIO]
    code, out, err = _run(capsys, "merge", *inputs, "-o", tmp_path / "m.yaml", "--out-bag", tmp_path / "out.bag", "--json")
    assert code == 0, err
    d = json.loads(out)
    with AnyReader([tmp_path / "out.bag"]) as reader:
        conns = [c for c in reader.connections if c.topic == "/tf_static"]
        (_, _, raw), = list(reader.messages(connections=conns))
        msg = reader.deserialize(raw, conns[0].msgtype)
    tfs = {t.child_frame_id: t for t in msg.transforms}
    assert set(tfs) == {"robot1/map", "robot2/map", "robot3/map"}  # files: robotK by position
    for k, e in enumerate(d["maps"]):
        t = tfs[f"robot{k + 1}/map"]
        assert t.header.frame_id == "map"
        assert t.transform.translation.x == pytest.approx(e["metric"]["x"], abs=1e-6)
        assert t.transform.translation.y == pytest.approx(e["metric"]["y"], abs=1e-6)
        q = t.transform.rotation
        assert math.atan2(2 * q.w * q.z, 1 - 2 * q.z * q.z) == pytest.approx(e["metric"]["yaw"], abs=1e-6)


def test_workers_give_the_same_merge(fleet_dir, capsys, tmp_path):
    inputs = [fleet_dir / f"{n}.yaml" for n in TRIO]
    code1, _, err1 = _run(capsys, "merge", *inputs, "-o", tmp_path / "serial.yaml")
    code2, _, err2 = _run(capsys, "merge", *inputs, "-o", tmp_path / "pool.yaml", "--workers", "2")
    assert code1 == code2 == 0, (err1, err2)
    assert (tmp_path / "serial.pgm").read_bytes() == (tmp_path / "pool.pgm").read_bytes()


def test_reference_and_resolution(fleet_dir, capsys, tmp_path):
    inputs = [fleet_dir / f"{n}.yaml" for n in TRIO]
    code, out, err = _run(capsys, "merge", *inputs, "-o", tmp_path / "m.yaml", "--reference", inputs[1],
                          "--resolution", "0.1", "--json")
    assert code == 0, err
    d = json.loads(out)
    assert d["reference"] == str(inputs[1]) and d["merged"]["resolution"] == pytest.approx(0.1)
    assert d["maps"][1]["metric"]["x"] == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize(
    "extra, piece",
    [
        (["--topic", "/robot1/map"], "no input is a bag"),
        (["--reference", "nowhere.yaml"], "--reference"),
        (["--resolution", "0"], "--resolution"),
        (["--scheduler", "tcp://127.0.0.1:9"], "Dask scheduler"),
        (["--workers", "0"], "workers"),
    ],
)
def test_bad_fleet_options_are_one_line_errors(fleet_dir, capsys, tmp_path, extra, piece):
    before = _files(fleet_dir)
    inputs = [fleet_dir / f"{n}.yaml" for n in TRIO[:2]]
    code, out, err = _run(capsys, "merge", *inputs, "-o", tmp_path / "m.yaml", *extra)
    assert code == 2 and piece in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "m.yaml").exists() and _files(fleet_dir) == before


def test_unknown_topic_in_a_bag(fleet_dir, capsys, tmp_path):
    code, out, err = _run(capsys, "merge", fleet_dir / "fleet.bag", "-o", tmp_path / "m.yaml", "--topic", "/robot9/map")
    assert code == 2 and "/robot9/map" in err and "/robot1/map" in err


def test_nothing_to_merge_writes_nothing(fleet_dir, capsys, tmp_path):
    inputs = [fleet_dir / "robot1.yaml", fleet_dir / "stranger.yaml"]
    code, out, err = _run(capsys, "merge", *inputs, "-o", tmp_path / "m.yaml", "--out-bag", tmp_path / "b.bag")
    assert code == 1 and "not merged" in out
    assert list(tmp_path.iterdir()) == []


def test_a_corrupt_bag_is_one_line_and_nothing_is_written(fleet_dir, capsys, tmp_path):
    bad = tmp_path / "broken.bag"
    bad.write_bytes((fleet_dir / "fleet.bag").read_bytes()[:5000])  # truncated recording
    code, out, err = _run(capsys, "merge", bad, fleet_dir / "robot1.yaml", "-o", tmp_path / "m.yaml")
    assert code == 2 and "broken.bag" in err and len(err.strip().splitlines()) == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.bag"]


def test_bags_and_map_files_mix(fleet_dir, capsys, tmp_path):
    robot1 = load_map(fleet_dir / "robot1.yaml")
    write_map_messages(tmp_path / "one.bag", [("/robot6/map", load_map(fleet_dir / "robot6.yaml"), 1)], format="ros1")
    code, out, err = _run(capsys, "merge", fleet_dir / "robot1.yaml", tmp_path / "one.bag", "-o", tmp_path / "m.yaml", "--json")
    assert code == 0, err
    d = json.loads(out)
    assert [e["name"] for e in d["maps"]] == [str(fleet_dir / "robot1.yaml"), "/robot6/map"]
    assert all(e["placed"] for e in d["maps"]) and d["merged"]["resolution"] == pytest.approx(robot1.resolution)

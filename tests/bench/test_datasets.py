"""Benchmark cases: determinism, recorded overlap, exact truth, tiers, real data."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from gridmerge import OccupancyGrid
from gridmerge.bench import datasets
from gridmerge.bench.metrics import halmstad_point_error, judge
from gridmerge.errors import GridMergeError

SMALL = dict(sources=("building",), building_shapes=((360, 480),))


def _same(c1, c2) -> bool:
    return (
        c1.id == c2.id
        and c1.a == c2.a
        and c1.b == c2.b
        and c1.positive == c2.positive
        and (c1.truth is None and c2.truth is None or np.array_equal(c1.truth, c2.truth))
        and c1.meta == c2.meta
    )


@pytest.fixture(scope="module")
def small_set():
    """Four small simulated cases: easy, negative, medium, negative."""
    ds = datasets.simulated(n=4, seed=1, negatives=0.5, **SMALL)
    return ds, list(ds)


def test_simulated_is_deterministic_per_seed(small_set):
    ds, cases = small_set
    again = list(datasets.simulated(n=4, seed=1, negatives=0.5, **SMALL))
    assert all(_same(c1, c2) for c1, c2 in zip(cases, again))
    # A case does not depend on how many cases are asked for, nor on the order of building.
    assert _same(datasets.simulated(n=1, seed=1, negatives=0.5, **SMALL)[0], cases[0])
    assert _same(ds[2], cases[2])
    other = datasets.simulated(n=1, seed=2, negatives=0.5, **SMALL)[0]
    assert not _same(other, cases[0])


def test_simulated_case_fields(small_set):
    _, cases = small_set
    assert [c.id for c in cases] == [f"simulated/{k:04d}" for k in range(4)]
    assert [c.positive for c in cases] == [True, False, True, False]
    assert [c.tier for c in cases] == ["easy", "negative", "medium", "negative"]
    for c in cases:
        assert c.dataset == "simulated"
        m = c.meta
        assert m["source"].startswith("building:")
        assert -180 <= m["rotation_deg"] < 180
        assert c.b.resolution == pytest.approx(c.a.resolution * m["scale"])
        if c.positive:
            tier = datasets.TIERS[m["tier"]]
            assert tier.scale[0] <= m["scale"] <= tier.scale[1]
            assert m["noise"] == tier.noise
            assert 0.0 < m["overlap"] <= 1.0
            # The truth is a similarity with the recorded rotation and scale.
            t = c.truth
            assert t.shape == (3, 3)
            assert math.hypot(t[0, 0], t[1, 0]) == pytest.approx(m["scale"])
            rot = math.degrees(math.atan2(t[1, 0], t[0, 0]))
            assert (rot - m["rotation_deg"] + 180) % 360 - 180 == pytest.approx(0, abs=1e-9)
        else:
            assert c.truth is None
            assert m["overlap"] == 0.0
            assert m["negative_kind"] in ("distant-parts", "different-places")
        d = c.describe()
        assert d["a_shape"] == list(c.a.shape) and d["meta"] is m


def test_simulated_truth_maps_b_onto_the_source(small_set):
    """b's known cells, carried by the truth into a (and a into the source), land on
    source cells of the same kind."""
    _, cases = small_set
    for c in [c for c in cases if c.positive]:
        src = datasets.source_map(c.meta["source"])
        ox, oy = c.meta["a_offset"]
        a_to_src = np.array([[1.0, 0, ox], [0, 1.0, oy], [0, 0, 1.0]])
        np.testing.assert_allclose(a_to_src @ c.truth, np.array(c.meta["b_to_source"]), atol=1e-9)
        ys, xs = np.nonzero(c.b.known)
        q = a_to_src @ c.truth @ np.stack([xs, ys, np.ones_like(xs)]).astype(float)
        sx, sy = np.rint(q[:2]).astype(int)
        H, W = src.shape
        inside = (sx >= 0) & (sx < W) & (sy >= 0) & (sy < H)
        assert inside.mean() > 0.99
        b_occ = c.b.data[ys, xs][inside] > 0.5
        near_wall = cv2.dilate(src.occupied().astype(np.uint8), np.ones((5, 5), np.uint8))[sy[inside], sx[inside]] > 0
        src_free = src.free()[sy[inside], sx[inside]]
        agree = np.where(b_occ, near_wall, src_free)
        assert agree.mean() > 0.9, c.id
        # Robot a maps in the source's frame.
        ka = c.a.known
        a_vals = c.a.data[ka]
        ya, xa = np.nonzero(ka)
        src_vals = src.data[ya + oy, xa + ox]
        assert ((a_vals > 0.5) == (src_vals > 0.5)).mean() > 0.95


def _lens(r: float, d: float) -> float:
    return 2 * r * r * math.acos(d / (2 * r)) - d / 2 * math.sqrt(4 * r * r - d * d)


def test_recorded_overlap_matches_the_geometry():
    """Two scanners in an empty hall each see a disc; the overlap is the lens over a disc."""
    world = np.zeros((400, 500), np.float32)
    world[:4, :] = world[-4:, :] = 1.0
    world[:, :4] = world[:, -4:] = 1.0
    grid = OccupancyGrid(world)
    r = datasets.RANGE_PX
    for d, rot, scale in ((100.0, 37.0, 1.3), (200.0, -120.0, 0.7), (0.0, 10.0, 1.0)):
        va = [[250 - d / 2, 200.0]]
        vb = [[250 + d / 2, 200.0]]
        a, b, truth, meta = datasets.robot_views_pair(grid, va, vb, rotation_deg=rot, scale=scale, rng=0)
        expect = _lens(r, d) / (math.pi * r * r)
        # The discs are clipped by the hall's walls only above and below (r = 150 < 200 - 4).
        assert meta["overlap"] == pytest.approx(expect, abs=0.03), (d, meta["overlap"], expect)
        assert b.resolution == pytest.approx(a.resolution * scale)
        # b's scanner position, carried by the truth, is where it was in the world.
        ox, oy = meta["a_offset"]
        seen = np.argwhere(b.known)
        centre_b = seen.mean(axis=0)[::-1]
        centre_a = (truth @ np.r_[centre_b, 1.0])[:2] + [ox, oy]
        assert np.hypot(*(centre_a - vb[0])) < 3.0


def test_shared_walls_are_the_walls_both_robots_saw():
    """Two scanners in a corridor 250 cells wide see its two walls where their discs
    reach them; the walls they share are the stretches both discs cover, none when the
    scanners are too far apart. The overlap of their known cells counts the floor too."""
    world = np.zeros((250, 700), np.float32)
    world[:4, :] = world[-4:, :] = 1.0
    world[:, :4] = world[:, -4:] = 1.0
    grid = OccupancyGrid(world)
    r = datasets.RANGE_PX
    reach = math.sqrt(r * r - (125 - 4) ** 2)  # half the stretch of each wall one disc reaches
    for d in (0.0, 100.0, 250.0):
        va, vb = [[350 - d / 2, 125.0]], [[350 + d / 2, 125.0]]
        _, _, _, meta = datasets.robot_views_pair(grid, va, vb, rotation_deg=20.0, scale=1.2, rng=0)
        expect = 2 * max(0.0, 2 * reach - d)  # the inner face of both walls, one cell deep
        assert meta["shared_walls"] == pytest.approx(expect, rel=0.1, abs=4), (d, meta["shared_walls"], expect)
        assert meta["overlap"] > 0.05  # the discs overlap even when no wall is shared
    assert datasets.shared_walls(np.full((3, 3), np.nan), np.ones((3, 3))) == 0


def test_simulated_positives_record_their_shared_walls(small_set):
    _, cases = small_set
    for c in cases:
        if not c.positive:
            assert "shared_walls" not in c.meta
            continue
        n = c.meta["shared_walls"]
        assert isinstance(n, int) and 0 < n
        # At most the walls robot a saw (its map before noise is the source's cells).
        assert n <= int((c.a.data > 0.5).sum()) * 1.2 + 10


@pytest.mark.parametrize("scale", [0.7, 1.0, 1.45, 1.9])
def test_walls_are_where_robot_a_sees_them_at_any_resolution(scale):
    """The truth is the best fit: b's walls, carried into a's frame, lie where a's are,
    at any resolution of b."""
    world = np.zeros((200, 240), np.float32)
    world[:3, :] = world[-3:, :] = 1.0
    world[:, :3] = world[:, -3:] = 1.0
    grid = OccupancyGrid(world)
    a, b, truth, meta = datasets.robot_views_pair(grid, [[120.0, 100.0]], [[120.0, 100.0]], rotation_deg=33.0, scale=scale, rng=0)
    ox, oy = meta["a_offset"]
    ya, xa = np.nonzero(a.data > 0.5)
    pa = np.stack([xa + ox, ya + oy], axis=1).astype(float)
    yb, xb = np.nonzero(b.data > 0.5)
    pb = (np.stack([xb, yb, np.ones_like(xb)], axis=1) @ truth.T)[:, :2] + [ox, oy]

    def depth(p):
        # Distance from the room's inside into the nearest wall, for points of the
        # straight parts of the walls (corners left out).
        d = np.stack([p[:, 0], 239 - p[:, 0], p[:, 1], 199 - p[:, 1]], axis=1)
        near = np.sort(d, axis=1)
        straight = near[:, 1] > 20
        return near[straight, 0]

    da, db = depth(pa), depth(pb)
    assert len(da) > 200 and len(db) > 100
    assert da.mean() == pytest.approx(2.0)  # a sees the inner wall cells, centres 2 cells deep
    # Robot b ray-casts at the world's resolution too, and keeps the observed walls'
    # centres: its walls lie where a's do (ray casting in b's own, coarser cells put them
    # 0.3-0.4 world cells nearer the scanner; the rule before that a whole cell).
    assert db.mean() == pytest.approx(da.mean(), abs=0.05), (da.mean(), db.mean())


def test_measure_overlap():
    a = np.zeros((10, 10), bool)
    b = np.zeros((10, 10), bool)
    assert datasets.measure_overlap(a, b) == 0.0
    a[:, :6] = True
    b[:, 4:] = True
    assert datasets.measure_overlap(a, b) == pytest.approx(20 / 60)
    b[:] = False
    b[0, 0] = True
    assert datasets.measure_overlap(a, b) == 1.0


def test_simulated_arguments_are_checked():
    with pytest.raises(GridMergeError):
        datasets.simulated(n=-1)
    with pytest.raises(GridMergeError):
        datasets.simulated(n=1, tiers=("impossible",))
    with pytest.raises(GridMergeError):
        datasets.simulated(n=1, sources=("moon",))
    with pytest.raises(GridMergeError):
        datasets.simulated(n=1, data_dir="/nonexistent/folder")


def test_without_shared_data_only_buildings(monkeypatch, tmp_path):
    monkeypatch.setattr(datasets, "default_data_dir", lambda: tmp_path / "absent")
    ds = datasets.simulated(n=3, seed=0)
    assert len(ds) == 3
    assert any("procedural buildings only" in note for note in ds.notes)
    with pytest.raises(GridMergeError, match="shared data"):
        datasets.halmstad()


def test_paper_case():
    ds = datasets.paper()
    assert len(ds) == 1
    c = ds[0]
    assert c.id == "paper/table1-seed0" and c.dataset == "paper" and c.positive
    assert c.truth[:2, 2].tolist() == [-86.0, -36.0]
    assert c.meta["table1"]["paper"] == {"rotation_deg": 29.91, "x": -85.79, "y": -36.11, "scale": 0.9503}
    assert len(datasets.load("paper")) == 5 and len(datasets.load("paper", quick=True)) == 1
    assert len(datasets.load("simulated", quick=True)) == 6
    with pytest.raises(GridMergeError):
        datasets.load("nope")


def test_default_data_dir_is_next_to_the_project():
    from pathlib import Path

    root = Path(datasets.__file__).resolve().parents[3]
    assert (root / "pyproject.toml").is_file()
    assert datasets.default_data_dir() == root.parent / "shared" / "data"


# -------------------------------------------------- a Halmstad-like folder
def _write_halmstad(root, maps: dict, pairs: dict) -> None:
    """A folder laid out as the shared data's ``halmstad/``: ``maps`` {environment: map
    names}, ``pairs`` {environment: [(a, b, kind)]}; tiny gray PNG maps."""
    import json

    rng = np.random.default_rng(0)
    for env, names in maps.items():
        (root / env).mkdir(parents=True)
        for name in names:
            img = np.full((30, 40), 127, np.uint8)
            img[5:25, 5:35] = 255
            img[5, 5:35] = 0
            img[rng.integers(6, 24), 5:35] = 0
            cv2.imwrite(str(root / env / f"{name}.png"), img)
    for env, plist in pairs.items():
        doc = {"pairs": [
            {"a": a, "b": b, "kind": kind, "points_a": [[1.0, 2.0], [3.0, 4.0]], "points_b": [[1.0, 2.0], [3.0, 4.0]],
             "fit_b_to_a": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], "fit_median_residual_px": 3.0}
            for a, b, kind in plist
        ]}
        (root / f"{env}_pairs.json").write_text(json.dumps(doc))


def test_halmstad_reads_every_environment_of_the_folder(tmp_path):
    """Another building dropped into the folder in the same layout is benchmarked: its
    pairs, and its maps against every other building's as negatives."""
    root = tmp_path / "halmstad"
    maps = {"AB1": ["AB1_01", "AB1_02", "AB1_03"], "F5": ["F5_1", "F5_2", "F5_10"], "HOME": ["HOME_01", "HOME_02"]}
    pairs = {
        "AB1": [("AB1_01", "AB1_02", "sensor"), ("AB1_01", "AB1_layout", "layout"), ("AB1_02", "AB1_03", "sensor")],
        "F5": [("F5_2", "F5_10", "sensor"), ("F5_1", "F5_10", "sensor")],
        "HOME": [("HOME_01", "HOME_02", "sensor")],
    }
    _write_halmstad(root, maps, pairs)
    (root / "NOMAPS_pairs.json").write_text('{"pairs": []}')  # annotations without a maps' folder
    assert datasets.halmstad_environments(tmp_path) == ["AB1", "F5", "HOME"]

    ds = datasets.halmstad(tmp_path)
    ids = [ds[k].id for k in range(len(ds))]
    sensor = [i for i in ids if i.startswith("halmstad/")]
    cross = [i for i in ids if i.startswith("halmstad-cross/")]
    assert sensor == ["halmstad/AB1_01-AB1_02", "halmstad/AB1_02-AB1_03", "halmstad/F5_2-F5_10", "halmstad/F5_1-F5_10",
                      "halmstad/HOME_01-HOME_02"]
    assert ids[: len(sensor)] == sensor  # sensor pairs first
    # The layout pair's blueprint is not in the folder: left out, and said so.
    assert not any(i.startswith("halmstad-layout/") for i in ids)
    assert any("AB1_layout.png" in note for note in ds.notes)
    # Every map of each building against every map of each other one, once; the first
    # building's (by name) map is map a when its number is odd.
    assert len(cross) == 3 * 3 + 3 * 2 + 3 * 2
    assert cross[:6] == ["halmstad-cross/AB1_01-F5_1", "halmstad-cross/AB1_01-F5_2", "halmstad-cross/AB1_01-F5_10",
                         "halmstad-cross/F5_1-AB1_02", "halmstad-cross/F5_2-AB1_02", "halmstad-cross/F5_10-AB1_02"]
    assert "halmstad-cross/F5_1-HOME_01" in cross and "halmstad-cross/HOME_02-F5_10" in cross  # F5's 10 is even
    c = ds[ids.index("halmstad-cross/F5_2-AB1_02")]
    assert not c.positive and c.truth is None and c.meta["environment"] == "AB1+F5" and c.meta["map_b"] == "AB1_02"
    assert c.meta["source"] == "halmstad:AB1+F5" and c.a.shape == (30, 40)
    f5 = ds[ids.index("halmstad/F5_2-F5_10")]
    assert f5.positive and f5.meta["environment"] == "F5" and f5.meta["threshold_px"] == 20.0

    # Chosen environments only; the first n of each kind and environment.
    two = datasets.halmstad(tmp_path, environments=("HOME", "F5"), kinds=("sensor", "cross"), limit=1)
    assert [two[k].id for k in range(len(two))] == ["halmstad/HOME_01-HOME_02", "halmstad/F5_2-F5_10", "halmstad-cross/F5_1-HOME_01"]
    with pytest.raises(GridMergeError, match="KPT4A_pairs.json"):
        datasets.halmstad(tmp_path, environments=("KPT4A",))
    empty = tmp_path / "empty"
    (empty / "halmstad").mkdir(parents=True)
    assert datasets.halmstad_environments(empty) == []
    with pytest.raises(GridMergeError, match="no Halmstad annotations"):
        datasets.halmstad(empty)


def test_halmstad_results_by_environment(tmp_path):
    """With more than one building, each building's pairs are summed up on their own."""
    from gridmerge.bench.metrics import evaluate, summarize
    from gridmerge.bench.report import results_markdown
    from gridmerge.bench.runner import BenchRun

    root = tmp_path / "halmstad"
    _write_halmstad(root, {"E9": ["E9_01", "E9_02"], "H2": ["H2_01", "H2_02"]},
                    {"E9": [("E9_01", "E9_02", "sensor")], "H2": [("H2_01", "H2_02", "sensor")]})
    ds = datasets.halmstad(tmp_path, kinds=("sensor",))
    from gridmerge.align import AlignResult
    from gridmerge.transforms import SimilarityTransform

    def result(success):
        t = SimilarityTransform(np.eye(3))
        return AlignResult(success=success, transform=t if success else None, candidate=t, metric_transform=None, confidence=0.9,
                           acceptance_index=0.9, inliers=10, matches=20, keypoints=(5, 5), method="m", message="", elapsed_s=0.1)

    recs = [evaluate(ds[0], result(True)), evaluate(ds[1], result(False))]
    rows = summarize(recs)
    by_env = {r["tier"]: r for r in rows if r.get("by") == "environment"}
    assert set(by_env) == {"E9", "H2"}
    assert by_env["E9"]["success"] == 1 and by_env["H2"]["declined"] == 1
    assert [r for r in rows if r["tier"] == "all"][0]["success_rate"] == 0.5
    # One environment: no breakdown.
    assert not [r for r in summarize(recs[:1]) if r.get("by")]
    run = BenchRun(None, {"seed": 0, "methods": ["m"], "datasets": []}, [r.to_dict() for r in recs], {"rows": rows})
    md = results_markdown(run)
    assert "## halmstad by environment" in md and "| E9 | `m` |" in md


# ------------------------------------------------------------- shared data
@pytest.mark.shared
def test_halmstad_pairs(shared_data):
    ds = datasets.halmstad(shared_data)
    assert len(ds) == 115 + 56  # E5: 91 sensor + 14 layout; HIH: 6 + 4; 14 x 4 cross pairs
    first = ds[0]
    assert first.dataset == "halmstad" and first.id == "halmstad/E5_01-E5_02"
    m = first.meta
    assert m["protocol"] == "halmstad" and m["kind"] == "sensor"
    assert m["threshold_px"] == max(20.0, 2 * m["fit_median_residual_px"])
    assert first.a.shape == (1585, 1585) and first.truth.shape == (3, 3)
    # The annotation's own fit passes the protocol.
    assert halmstad_point_error(first.truth, m["points_a"], m["points_b"]) == pytest.approx(m["fit_median_residual_px"], abs=0.05)
    assert judge(first.truth, first.truth, first.b.shape, positive=True, protocol=m)["success"]
    last = ds[114]
    assert last.dataset == "halmstad-layout" and last.meta["kind"] == "layout"
    # A blueprint's pixel size against the Tango maps' is not known; theirs is one.
    assert not last.meta["resolutions_known"] and first.meta["resolutions_known"]
    quick = datasets.load("halmstad", quick=True, data_dir=shared_data)
    assert [c.dataset for c in quick] == ["halmstad"] * 4 + ["halmstad-layout"] * 2 + ["halmstad-cross"]


@pytest.mark.shared
def test_halmstad_cross_building_pairs_are_negatives(shared_data):
    """Every E5 sensor map against every HIH one, once: real maps of two buildings."""
    ds = datasets.halmstad(shared_data, kinds=("cross",))
    assert len(ds) == 14 * 4
    pairs, sides = set(), set()
    for k in range(len(ds)):  # one case at a time: 112 maps of 1585 x 1585 cells in all
        c = ds[k]
        assert c.dataset == "halmstad-cross" and not c.positive and c.truth is None and c.meta["tier"] == "negative"
        envs = {c.meta["map_a"].split("_")[0], c.meta["map_b"].split("_")[0]}
        assert envs == {"E5", "HIH"}
        assert c.a.known.any() and c.b.known.any()
        pairs.add(frozenset((c.meta["map_a"], c.meta["map_b"])))
        sides.add(c.meta["map_a"][:2])
    assert len(pairs) == 56
    # Either building's maps on either side.
    assert sides == {"E5", "HI"}
    # Only with both buildings.
    assert len(datasets.halmstad(shared_data, kinds=("cross",), environments=("E5",))) == 0


@pytest.mark.shared
def test_simulated_from_real_maps(shared_data):
    names = datasets.source_names(shared_data)
    assert "willow" in names and "halmstad:E5_01" in names and "halmstad:HIH_04" in names
    ds = datasets.simulated(n=1, seed=0, data_dir=shared_data, sources=("willow",))
    c = ds[0]
    assert c.meta["source"] == "willow" and c.positive and not ds.notes


def test_procedural_cases_are_the_same_whatever_the_see_through():
    # A procedural building has no unknown cells: rays never cross any.
    default = datasets.simulated(n=2, seed=1, **SMALL)
    stopped = datasets.simulated(n=2, seed=1, see_through=0, **SMALL)
    for c0, c2 in zip(stopped, default):
        assert c0.a == c2.a and c0.b == c2.b and np.array_equal(c0.truth, c2.truth)
        assert c0.meta["see_through"] == 0 and c2.meta["see_through"] == datasets.SEE_THROUGH
    with pytest.raises(GridMergeError):
        datasets.simulated(n=1, see_through=-1)


def test_robots_see_the_walls_behind_a_real_maps_unknown_band(shared_data):
    # Halmstad E5_02 leaves a band of unknown cells between the floor and many of its
    # walls; scanners that stop at the band see far fewer of the walls that are there.
    # (20 scanner positions: 2042 wall cells seen when stopping, 3309 seeing through.)
    from gridmerge.samples import random_viewpoints

    world = datasets.source_map("halmstad:E5_02", shared_data)
    vps = random_viewpoints(world, 20, rng=0, clearance=5)
    kw = dict(rotation_deg=0.0, scale=1.0, rng=0)
    _, _, _, stopped = datasets.robot_views_pair(world, vps, vps, see_through=0, **kw)
    a, _, _, seen = datasets.robot_views_pair(world, vps, vps, **kw)
    assert seen["shared_walls"] > 1.4 * stopped["shared_walls"]
    # Every wall a robot maps is a wall of the building.
    x0, y0 = seen["a_offset"]
    ys, xs = np.nonzero(a.data > 0.5)
    assert (world.data[ys + y0, xs + x0] > 0.65).all()


def test_swapped_cases_align_a_onto_b(tmp_path):
    """``NAME-swapped``: the same pairs, b as the reference; the truth inverted and the
    annotated points swapped, so that the protocol judges the swapped truth right."""
    root = tmp_path / "halmstad"
    _write_halmstad(root, {"E9": ["E9_01", "E9_02"], "H2": ["H2_01"]}, {"E9": [("E9_01", "E9_02", "sensor")], "H2": []})
    # A fit that is not its own inverse, and points that agree with it.
    import json

    doc = json.loads((root / "E9_pairs.json").read_text())
    fit = np.array([[math.cos(0.3), -math.sin(0.3), 5.0], [math.sin(0.3), math.cos(0.3), -2.0], [0, 0, 1.0]])
    pts_b = np.array([[3.0, 4.0], [20.0, 6.0], [10.0, 25.0]])
    doc["pairs"][0].update(fit_b_to_a=fit[:2].tolist(), points_b=pts_b.tolist(),
                           points_a=(pts_b @ fit[:2, :2].T + fit[:2, 2]).tolist())
    (root / "E9_pairs.json").write_text(json.dumps(doc))
    plain = datasets.load("halmstad", data_dir=tmp_path)
    swap = datasets.load("halmstad-swapped", data_dir=tmp_path)
    assert len(swap) == len(plain) == 1 + 2  # one sensor pair, 2 x 1 cross pairs
    c, s = plain[0], swap[0]
    assert s.id == "halmstad-swapped/E9_02-E9_01" and s.dataset == "halmstad-swapped"
    assert s.a == c.b and s.b == c.a and np.allclose(s.truth @ c.truth, np.eye(3))
    assert s.meta["points_a"] == c.meta["points_b"] and s.meta["map_b"] == "E9_01" and s.meta["swapped"]
    assert s.meta["rotation_deg"] == pytest.approx(-math.degrees(0.3))
    assert judge(s.truth, s.truth, s.b.shape, positive=True, protocol=s.meta)["success"]
    assert halmstad_point_error(s.truth, s.meta["points_a"], s.meta["points_b"]) == pytest.approx(0.0, abs=1e-9)
    cross = [swap[k] for k in range(1, 3)]
    assert all(x.dataset == "halmstad-cross-swapped" and not x.positive and x.truth is None for x in cross)
    assert datasets.load("paper-swapped")[0].id == "paper-swapped/table1-seed0"
    with pytest.raises(GridMergeError):
        datasets.load("nothing-swapped")


# ------------------------------------------------------------ user's source maps
@pytest.fixture(scope="module")
def map_files(tmp_path_factory):
    """Two procedural buildings saved as map_server maps (YAML + PGM) and as a PNG."""
    from gridmerge import save_map
    from gridmerge import samples

    folder = tmp_path_factory.mktemp("source_maps")
    one = save_map(samples.building(11, (360, 480)), folder / "one.yaml")
    two = folder / "two.png"
    cv2.imwrite(str(two), samples.building(12, (380, 460)).render(unknown=205))
    return one, two


def test_simulated_in_the_users_maps(map_files):
    """Every case is drawn from the maps given (nothing else), positives of one map,
    negatives of two different places from both; the run names the maps and digests."""
    one, two = map_files
    ds = datasets.simulated(n=10, seed=2, negatives=0.4, source_maps=[one, str(two), one])
    names = {"file:" + str(one.resolve()), "file:" + str(two.resolve())}
    cases = list(ds)
    assert {c.meta["source"] for c in cases} == names
    assert [m["path"] for m in ds.params["source_maps"]] == [str(one.resolve()), str(two.resolve())]  # duplicates dropped
    digests = [m["cells_sha256"] for m in ds.params["source_maps"]]
    assert len(set(digests)) == 2 and all(len(d) == 64 for d in digests)
    negatives = [c for c in cases if not c.positive]
    assert len(negatives) == 4
    for c in negatives:
        if c.meta["negative_kind"] == "different-places":
            assert c.meta["source_b"] != c.meta["source"] and c.meta["source_b"] in names
    for c in cases:
        if c.positive:
            assert c.truth is not None and c.meta["shared_walls"] > 0
    # The same seed gives the same cases; the source maps are read as source_map reads them.
    again = list(datasets.simulated(n=10, seed=2, negatives=0.4, source_maps=[one, two]))
    assert all(_same(c1, c2) for c1, c2 in zip(cases, again))
    from gridmerge import load_map

    assert datasets.source_map("file:" + str(one.resolve())) == load_map(one).crop_known(8)[0]


def test_one_source_map_gives_negatives_of_distant_parts(tmp_path):
    from gridmerge import save_map
    from gridmerge import samples

    one = save_map(samples.building(13, (560, 760)), tmp_path / "large.yaml")
    cases = list(datasets.simulated(n=6, seed=5, negatives=0.5, source_maps=[one]))
    kinds = {c.meta["negative_kind"] for c in cases if not c.positive}
    assert kinds == {"distant-parts"}
    assert all(c.meta["overlap"] == 0.0 for c in cases if not c.positive)


def test_bad_source_maps_are_one_line_errors(map_files, tmp_path):
    with pytest.raises(GridMergeError, match="source map not found: .*nope.yaml"):
        datasets.simulated(n=2, source_maps=[tmp_path / "nope.yaml"])
    with pytest.raises(GridMergeError, match="no source map given"):
        datasets.simulated(n=2, source_maps=[])
    walls = tmp_path / "walls.png"
    cv2.imwrite(str(walls), np.zeros((50, 60), np.uint8))  # all occupied: nowhere to stand
    with pytest.raises(GridMergeError, match="no free space for a robot"):
        datasets.simulated(n=2, source_maps=[walls])
    unknown = tmp_path / "unknown.png"
    cv2.imwrite(str(unknown), np.full((50, 60), 205, np.uint8))
    with pytest.raises(GridMergeError, match="no known cells"):
        datasets.simulated(n=2, source_maps=[unknown])
    tiny = tmp_path / "tiny.png"
    img = np.zeros((60, 60), np.uint8)
    img[5:55, 5:55] = 254
    cv2.imwrite(str(tiny), img)  # one room: no two parts of it are apart
    with pytest.raises(GridMergeError, match="too small for a negative pair"):
        datasets.simulated(n=2, negatives=0.5, source_maps=[tiny])
    assert len(datasets.simulated(n=2, negatives=0.0, source_maps=[tiny])) == 2  # positives only: fine


# --------------------------------------------------------------- halmstad-partial
_SESSION_TURN = np.array([[math.cos(0.35), -math.sin(0.35), 180.0], [math.sin(0.35), math.cos(0.35), -60.0], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def two_sessions(tmp_path_factory):
    """A data folder with one building mapped twice: ``SYN_02`` is ``SYN_01`` turned by
    20 degrees and shifted (``_SESSION_TURN``: SYN_01's pixels -> SYN_02's), annotated
    by 30 points spread over it and the exact fit."""
    import json

    from gridmerge import samples

    root = tmp_path_factory.mktemp("sessions")
    (root / "halmstad" / "SYN").mkdir(parents=True)
    first = samples.building(5, (520, 700)).render()
    second = cv2.warpAffine(first, _SESSION_TURN[:2], (820, 720), flags=cv2.INTER_NEAREST, borderValue=127)
    cv2.imwrite(str(root / "halmstad" / "SYN" / "SYN_01.png"), first)
    cv2.imwrite(str(root / "halmstad" / "SYN" / "SYN_02.png"), second)
    rng = np.random.default_rng(4)
    pa = np.column_stack([rng.uniform(20, 680, 30), rng.uniform(20, 500, 30)])
    pb = pa @ _SESSION_TURN[:2, :2].T + _SESSION_TURN[:2, 2]
    doc = {"pairs": [{"a": "SYN_01", "b": "SYN_02", "kind": "sensor", "points_a": pa.tolist(), "points_b": pb.tolist(),
                      "fit_b_to_a": np.linalg.inv(_SESSION_TURN)[:2].tolist(), "fit_median_residual_px": 0.5}]}
    (root / "halmstad" / "SYN_pairs.json").write_text(json.dumps(doc))
    return root


def test_partial_cases_carry_the_sessions_fit_into_the_robots_frames(two_sessions):
    """Each robot maps its own session of the building; the truth is the annotation fit
    carried into the two robots' frames: it lays b's walls on a's and b's scored points
    on a's, and a case is the same whatever else is asked."""
    from gridmerge.transforms import AffineTransform
    from gridmerge.verify import verify

    ds = datasets.halmstad_partial(n=5, seed=2, data_dir=two_sessions, negatives=0.4)
    cases = list(ds)
    assert [c.positive for c in cases] == [True, True, False, True, False]
    assert [c.tier for c in cases] == ["easy", "medium", "negative", "hard", "negative"]
    again = datasets.halmstad_partial(n=3, seed=2, data_dir=two_sessions, negatives=0.4)
    assert all(_same(c, d) for c, d in zip(cases, again))
    assert not _same(cases[0], datasets.halmstad_partial(n=1, seed=3, data_dir=two_sessions)[0])
    for c in cases:
        assert c.id.startswith("halmstad-partial/") and c.dataset == "halmstad-partial"
        assert (c.meta["map_a"], c.meta["map_b"], c.meta["environment"], c.meta["source"]) == ("SYN_01", "SYN_02", "SYN", "halmstad:SYN")
        assert c.a.known.sum() > 2000 and c.b.known.sum() > 2000
    for c in (c for c in cases if c.positive):
        m = c.meta
        assert m["protocol"] == "halmstad" and m["threshold_px"] == 20.0
        assert len(m["points_a"]) == len(m["points_b"]) >= datasets.PARTIAL_POINTS
        assert halmstad_point_error(c.truth, m["points_a"], m["points_b"]) < 1.0
        pa = np.asarray(m["points_a"])
        assert (pa >= -10).all() and (pa[:, 0] < c.a.shape[1] + 10).all() and (pa[:, 1] < c.a.shape[0] + 10).all()
        assert verify(c.a, c.b, AffineTransform(c.truth)).wall_agreement > 0.8
        assert m["scale"] == pytest.approx(m["cell_scale"], rel=1e-9)  # the sessions share a cell size
        assert 0.0 < m["overlap"] <= 1.0 and m["shared_walls"] > 0
        assert judge(c.truth, c.truth, c.b.shape, positive=True, protocol=m)["success"]
        assert not judge(np.eye(3), c.truth, c.b.shape, positive=True, protocol=m)["success"]
    for c in (c for c in cases if not c.positive):
        assert c.truth is None and c.meta["overlap"] == 0.0 and c.meta["negative_kind"] == "distant-parts"


def test_partial_set_by_name_and_its_errors(two_sessions, tmp_path):
    assert len(datasets.load("halmstad-partial", quick=True, data_dir=two_sessions)) == 3
    assert len(datasets.load("halmstad-partial", n=7, data_dir=two_sessions)) == 7
    swapped = datasets.load("halmstad-partial-swapped", n=1, data_dir=two_sessions)[0]
    assert swapped.id == "halmstad-partial-swapped/SYN_02-SYN_01"
    with pytest.raises(GridMergeError, match="radius"):
        datasets.halmstad_partial(data_dir=two_sessions, radius=(300, 100))
    with pytest.raises(GridMergeError, match="no annotated sensor pair"):
        datasets.halmstad_partial(data_dir=tmp_path)
    with pytest.raises(GridMergeError, match="data folder not found"):
        datasets.halmstad_partial(data_dir=tmp_path / "nowhere")


def test_partial_robots_keep_the_real_walls_thickness(shared_data):
    """A robot's map of a real building keeps the walls as thick as its session drew them
    (up to 3 cells behind the face its scanner hit), not only the face."""
    ds = datasets.halmstad_partial(n=1, seed=0, data_dir=shared_data)
    c = ds[0]
    world, offset = datasets._session_world(str(shared_data), c.meta["environment"], c.meta["map_a"], datasets.SEE_THROUGH)
    assert offset.shape == (2,)
    views = world.viewpoints(np.random.default_rng(0))[:5]
    face, thick = world.seen(views), world.seen(views, 3)
    with np.errstate(invalid="ignore"):
        assert (thick > 0.5).sum() > 1.5 * (face > 0.5).sum()
        assert ((face > 0.5) <= (thick > 0.5)).all()  # the face is kept
        assert ((thick > 0.5) <= ((face > 0.5) | (world.grid.data > 0.5))).all()  # only the session's own walls added
    assert np.array_equal(np.isnan(face) & ~(thick > 0.5), np.isnan(thick))  # no free cell added


def test_a_bent_robot_map_moves_its_walls_by_at_most_the_bend():
    """``bend``: robot b's map is bent (its walls moved by up to ``bend`` source cells, by
    a smooth field) before it is turned and resampled; a's map, the case's other draws
    and the recorded bend are as asked, and the rigid truth still carries b's walls
    within ``bend`` cells (plus a cell of resampling) of the source's walls, but no
    longer all within one cell."""
    plain = datasets.simulated(n=1, seed=1, **SMALL)[0]
    case = datasets.simulated(n=1, seed=1, bend=4.0, **SMALL)[0]
    assert case.a == plain.a and case.b != plain.b
    assert case.meta["bend"] == 4.0 and "bend" not in plain.meta
    assert case.meta["rotation_deg"] == plain.meta["rotation_deg"] and case.meta["scale"] == plain.meta["scale"]
    src = datasets.source_map(case.meta["source"])
    dist = cv2.distanceTransform((~src.occupied()).astype(np.uint8), cv2.DIST_L2, 5)

    def wall_distances(c):
        ys, xs = np.nonzero(c.b.occupied())
        q = np.array(c.meta["b_to_source"]) @ np.stack([xs, ys, np.ones_like(xs)]).astype(float)
        sx, sy = np.rint(q[:2]).astype(int)
        return dist[sy, sx]

    d_plain, d_bent = wall_distances(plain), wall_distances(case)
    assert np.quantile(d_plain, 0.95) <= 1.5
    assert np.quantile(d_bent, 0.95) <= 4.0 + 1.5 and np.quantile(d_bent, 0.95) > 1.5


def test_bend_is_checked_and_recorded_by_the_run(tmp_path):
    with pytest.raises(GridMergeError, match="bend"):
        datasets.simulated(n=1, bend=-1.0)
    from gridmerge.bench import runner

    run = runner.run(["hybrid"], datasets="simulated", n=1, seed=1, out_dir=tmp_path / "run", plots=False, memory=False,
                     bend=2.0)
    assert run.config["datasets"][0]["params"]["bend"] == 2.0
    again = runner.rebuild_case(tmp_path / "run", "simulated/0000")
    assert again.meta["bend"] == 2.0
    with pytest.raises(GridMergeError, match="simulated data set only"):
        runner.run(["hybrid"], datasets="paper", quick=True, out_dir=tmp_path / "paper", plots=False, memory=False, bend=2.0)

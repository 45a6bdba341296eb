"""Tests of gridmerge.samples: procedural buildings, simulated scans, warps and pairs."""

from __future__ import annotations

import math
import time

import cv2
import numpy as np
import pytest

from gridmerge.grid import OccupancyGrid
from gridmerge.samples import (
    TABLE1_B_SHAPE,
    building,
    explore,
    negative_pair,
    random_viewpoints,
    robot_pair,
    table1_pair,
    trajectory,
    warp,
)

SMALL = (240, 320)


@pytest.fixture(scope="module")
def world() -> OccupancyGrid:
    return building(0)


@pytest.fixture(scope="module")
def pair0():
    return robot_pair(0)


def _apply(matrix: np.ndarray, xy: np.ndarray) -> np.ndarray:
    m = np.asarray(matrix, dtype=float)
    return xy @ m[:2, :2].T + m[:2, 2]


def _cells(mask: np.ndarray) -> np.ndarray:
    ys, xs = np.nonzero(mask)
    return np.stack([xs, ys], axis=1).astype(float)


def _open_world(h: int, w: int) -> np.ndarray:
    return np.zeros((h, w), dtype=np.float32)


# ------------------------------------------------------------------------- building
def test_building_is_deterministic_per_seed():
    a1, a2, b = building(3, SMALL), building(3, SMALL), building(4, SMALL)
    assert a1 == a2
    assert not np.array_equal(a1.data, b.data, equal_nan=True)
    assert building(0) == building(0)


def test_building_contents(world):
    g = world
    assert g.shape == (480, 640)
    assert g.resolution == 0.05 and g.origin == (0.0, 0.0, 0.0)
    vals = np.unique(g.data[g.known])
    assert set(vals.tolist()) == {0.0, 1.0}
    free, occ, unknown = g.free().mean(), g.occupied().mean(), 1.0 - g.known.mean()
    assert 0.55 < free < 0.9
    assert 0.05 < occ < 0.25
    assert 0.02 < unknown < 0.4
    # Free space is one connected region, enclosed by walls: no free cell touches unknown.
    count = cv2.connectedComponents(g.free().astype(np.uint8), connectivity=4)[0]
    assert count == 2
    near_unknown = cv2.dilate((~g.known).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    assert not (near_unknown & g.free()).any()
    # The map's border is outside the building.
    assert not g.known[0].any() and not g.known[-1].any()
    assert not g.known[:, 0].any() and not g.known[:, -1].any()


def test_building_has_many_distinctive_keypoints(world):
    sift = cv2.SIFT_create()
    kp, desc = sift.detectAndCompute(world.render(), None)
    assert len(kp) >= 300
    # Non-repetitive: many descriptors pass Lowe's ratio test against all the others of
    # the same image (a repetitive map has few such keypoints).
    desc = desc.astype(np.float64)
    sq = (desc**2).sum(axis=1)
    d = np.sqrt(np.maximum(sq[:, None] + sq[None, :] - 2.0 * desc @ desc.T, 0.0))
    np.fill_diagonal(d, np.inf)
    d.sort(axis=1)
    distinct = (d[:, 0] / d[:, 1]) < 0.8
    assert distinct.sum() >= 80


def test_building_other_shapes_and_errors():
    g = building(5, (150, 400), resolution=0.1)
    assert g.shape == (150, 400) and g.resolution == 0.1
    assert g.free().any() and g.occupied().any()
    with pytest.raises(ValueError):
        building(0, (50, 50))
    with pytest.raises(ValueError):
        building(0, (100,))


# -------------------------------------------------------------------------- explore
def test_explore_closed_room_stays_unknown():
    w = _open_world(100, 100)
    w[40:60, 40:60] = 1.0
    w[42:58, 42:58] = 0.0  # a closed room, walls 2 cells thick
    seen = explore(OccupancyGrid(w), [[10.0, 10.0]], max_range_px=150)
    assert np.isnan(seen.data[42:58, 42:58]).all()
    # The faces of the room that the scanner sees are occupied, not the far ones.
    assert (seen.data[40, 42:58] == 1.0).all() and (seen.data[42:58, 40] == 1.0).all()
    assert np.isnan(seen.data[59, 42:58]).all()
    # Free space is exactly what is free in the world and seen.
    assert seen.free().sum() > 0.6 * (100 * 100 - 20 * 20)
    assert not (seen.free() & (w > 0.65)).any()


def test_explore_cells_behind_a_wall_are_not_free():
    w = _open_world(101, 201)
    w[30:71, 100:103] = 1.0  # a wall, 3 cells thick
    seen = explore(OccupancyGrid(w), [[50.0, 50.0]], max_range_px=140)
    assert (seen.data[30:71, 100] == 1.0).all()  # near face hit
    assert np.isnan(seen.data[30:71, 101:103]).all()  # inside the wall: never seen
    # The shadow: cells straight behind the wall are unknown.
    assert np.isnan(seen.data[40:61, 103:180]).all()
    # Around the wall, in line of sight, free.
    assert (seen.data[50, 0:100] == 0.0).all()
    assert seen.data[5, 150] == 0.0 and seen.data[95, 150] == 0.0


def test_explore_has_no_holes_in_open_space():
    R = 150
    n = 2 * R + 41
    seen = explore(OccupancyGrid(_open_world(n, n)), [[n // 2, n // 2 + 0.3]], max_range_px=R)
    yy, xx = np.mgrid[0:n, 0:n]
    dist = np.hypot(xx - n // 2, yy - (n // 2 + 0.3))
    assert (seen.data[dist <= R - 1] == 0.0).all()
    assert np.isnan(seen.data[dist > R + 1.5]).all()


def test_explore_unknown_world_cells_stop_rays():
    w = _open_world(60, 60)
    w[:, 40] = np.nan
    seen = explore(OccupancyGrid(w), [[20.0, 30.0]], max_range_px=100)
    assert np.isnan(seen.data[:, 40:]).all()
    assert (seen.data[30, :40] == 0.0).all()


def test_explore_sees_a_wall_behind_a_thin_band_of_unknown():
    # A real map used as the world often leaves a cell or two unknown between the floor
    # and a wall; with see_through the scanner sees the wall behind (the band stays
    # unknown), and a wider band still stops the rays.
    w = _open_world(60, 80)
    w[:, 50] = np.nan  # a one-cell band before the wall at column 51
    w[:, 51] = 1.0
    w[:, 11:14] = np.nan  # a three-cell band before the wall at column 10
    w[:, 10] = 1.0
    vp = [[30.0, 30.0]]
    stopped = explore(OccupancyGrid(w), vp, max_range_px=100)
    seen = explore(OccupancyGrid(w), vp, max_range_px=100, see_through=2)
    assert np.isnan(stopped.data[20:41, 51]).all()
    assert (seen.data[20:41, 51] == 1.0).all()
    assert np.isnan(seen.data[:, 50]).all()  # the band itself is never known
    assert np.isnan(seen.data[:, :14]).all()  # three cells: not crossed
    assert (seen.data[30, 14:50] == 0.0).all() and (stopped.data[30, 14:50] == 0.0).all()
    # Beyond the seen wall, nothing.
    assert np.isnan(seen.data[:, 52:]).all()
    with pytest.raises(ValueError):
        explore(OccupancyGrid(w), vp, see_through=-1)


def test_explore_sees_through_small_unknown_holes_in_the_floor():
    w = _open_world(60, 80)
    w[28:33, 40:42] = np.nan  # a hole of 2 cells across, in the open
    vp = [[20.0, 30.0]]
    stopped = explore(OccupancyGrid(w), vp, max_range_px=100)
    seen = explore(OccupancyGrid(w), vp, max_range_px=100, see_through=2)
    assert np.isnan(stopped.data[30, 42:70]).all()  # its shadow
    assert (seen.data[30, 42:70] == 0.0).all()
    assert np.isnan(seen.data[28:33, 40:42]).all()


def test_explore_building_is_consistent_and_fast(world):
    vps = random_viewpoints(world, 20, rng=1)
    explore(world, vps[:2])  # warm-up
    t0 = time.perf_counter()
    seen = explore(world, vps)
    elapsed = time.perf_counter() - t0
    assert elapsed < 1.0
    assert seen.shape == world.shape and seen.resolution == world.resolution and seen.origin == world.origin
    assert not (seen.free() & ~world.free()).any()
    assert not (seen.occupied() & ~world.occupied()).any()
    assert seen.occupied().sum() > 1000 and seen.free().sum() > 0.2 * world.free().sum()
    # Every hit wall cell is next to a cell seen free.
    near_free = cv2.dilate(seen.free().astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    assert (near_free[seen.occupied()]).all()
    # Every viewpoint's own cell is seen free.
    c = np.rint(vps).astype(int)
    assert (seen.data[c[:, 1], c[:, 0]] == 0.0).all()


def test_explore_noise(world):
    vps = random_viewpoints(world, 10, rng=2)
    clean = explore(world, vps)
    noisy1 = explore(world, vps, noise=0.3, rng=5)
    noisy2 = explore(world, vps, noise=0.3, rng=5)
    assert noisy1 == noisy2
    assert explore(world, vps, rng=7) == clean  # no noise: rng unused
    hits_clean, hits_noisy = clean.occupied(), noisy1.occupied()
    kept = (hits_noisy & hits_clean).sum() / hits_clean.sum()
    assert 0.6 < kept < 0.8  # about 30 % of the hits are missed
    spurious = hits_noisy & ~hits_clean
    assert spurious.any() and clean.free()[spurious].all()
    assert spurious.sum() < 0.02 * clean.free().sum()


def test_explore_rejects_bad_input(world):
    with pytest.raises(ValueError):
        explore(world, [[-5.0, 10.0]])
    with pytest.raises(ValueError):
        explore(world, [[1.0, 2.0, 3.0]])
    with pytest.raises(ValueError):
        explore(world, [[10.0, 10.0]], noise=2.0)


# ------------------------------------------------------------ viewpoints, trajectory
def test_random_viewpoints(world):
    vps = random_viewpoints(world, 50, rng=3)
    assert vps.shape == (50, 2)
    assert np.array_equal(vps, random_viewpoints(world, 50, rng=3))
    assert not np.array_equal(vps, random_viewpoints(world, 50, rng=4))
    c = vps.astype(int)
    assert np.array_equal(c, vps)  # cell centres
    assert world.free()[c[:, 1], c[:, 0]].all()
    # Clearance: no obstacle within 4 cells.
    oy, ox = np.nonzero(~world.free())
    for x, y in c[:10]:
        assert np.hypot(ox - x, oy - y).min() >= 4.0
    region = np.zeros(world.shape, dtype=bool)
    region[:, :200] = True
    vr = random_viewpoints(world, 30, rng=3, region=region)
    assert (vr[:, 0] < 200).all()
    with pytest.raises(ValueError):
        random_viewpoints(world, 3, rng=0, region=np.zeros(world.shape, dtype=bool))


def test_trajectory_stays_in_free_space(world):
    path = trajectory(world, 300, rng=4)
    assert path.shape == (300, 2)
    assert np.array_equal(path, trajectory(world, 300, rng=4))
    steps = np.hypot(*np.diff(path, axis=0).T)
    assert (steps <= 4.0 + 1e-9).all() and (steps > 0).mean() > 0.8
    c = np.rint(path).astype(int)
    assert world.free()[c[:, 1], c[:, 0]].all()
    assert np.ptp(path, axis=0).max() > 40  # it actually goes somewhere
    start = path[0]
    assert np.array_equal(trajectory(world, 5, rng=1, start=start)[0], start)


# ---------------------------------------------------------------------------- warp
def test_warp_identity_is_the_same_map(world):
    for interp in ("linear", "nearest"):
        out = warp(world, np.eye(3), world.shape, interpolation=interp)
        assert np.array_equal(out.data, world.data, equal_nan=True)
        assert out.resolution == world.resolution and out.origin == (0.0, 0.0, 0.0)


def test_warp_integer_shift_moves_cells_exactly():
    rng = np.random.default_rng(0)
    data = rng.random((40, 50)).astype(np.float32)
    data[rng.random((40, 50)) < 0.2] = np.nan
    g = OccupancyGrid(data)
    dx, dy = 7, -3
    for interp in ("linear", "nearest"):
        out = warp(g, [[1, 0, dx], [0, 1, dy]], (40, 50), interpolation=interp)  # out(p) = g(p + d)
        assert np.array_equal(out.data[3:, : 50 - dx], data[: 40 - 3, dx:], equal_nan=True)
        assert np.isnan(out.data[:3]).all() and np.isnan(out.data[:, 50 - dx :]).all()


def test_warp_rotation_by_90_degrees_is_exact():
    rng = np.random.default_rng(1)
    data = rng.random((20, 30)).astype(np.float32)
    data[rng.random((20, 30)) < 0.3] = np.nan
    # out(x, y) = g(y, 19 - x): g turned by 90 degrees, shape (30, 20).
    out = warp(OccupancyGrid(data), [[0, 1, 0], [-1, 0, 19]], (30, 20))
    assert np.array_equal(out.data, data.T[:, ::-1], equal_nan=True)


def test_warp_does_not_dilute_known_values_with_unknown():
    data = np.full((30, 30), np.nan, dtype=np.float32)
    data[10:20, 10:20] = 1.0
    out = warp(OccupancyGrid(data), [[1, 0, 0.37], [0, 1, -0.21]], (30, 30))
    assert np.allclose(out.data[out.known], 1.0)
    assert 80 <= out.known.sum() <= 121


def test_warp_options_and_errors(world):
    out = warp(world, [[2, 0, 0], [0, 2, 0]], (240, 320), resolution=0.1, name="half")
    assert out.resolution == 0.1 and out.name == "half" and out.shape == (240, 320)
    with pytest.raises(ValueError):
        warp(world, np.eye(3), world.shape, interpolation="cubic")
    with pytest.raises(ValueError):
        warp(world, np.ones((2, 2)), world.shape)
    with pytest.raises(ValueError):
        warp(world, [[1, 0, 0], [0, 1, 0], [1, 0, 1]], world.shape)


# -------------------------------------------------------------------------- table 1
def test_table1_pair():
    a, b, truth = table1_pair(0)
    assert a == building(0)
    assert b.shape == TABLE1_B_SHAPE
    t = math.radians(30.0)
    expected = np.array([[0.95 * math.cos(t), -0.95 * math.sin(t), -86.0], [0.95 * math.sin(t), 0.95 * math.cos(t), -36.0], [0, 0, 1]])
    assert np.allclose(truth, expected, atol=1e-12)
    assert b.resolution == pytest.approx(0.95 * a.resolution)
    # At least 70 % of b's canvas maps onto a's canvas.
    H, W = b.shape
    q = _apply(truth, _cells(np.ones((H, W), dtype=bool)))
    on_a = (q[:, 0] >= -0.5) & (q[:, 0] < a.width - 0.5) & (q[:, 1] >= -0.5) & (q[:, 1] < a.height - 0.5)
    assert on_a.mean() >= 0.7
    assert b.known.sum() > 0.4 * a.known.sum()
    # b's values agree with a's at the mapped positions, away from walls.
    kernel = np.ones((5, 5), np.uint8)
    clear_free = cv2.erode(b.free().astype(np.uint8), kernel) > 0
    clear_occ = b.occupied(0.99)
    for mask, lo, hi in ((clear_free, 0.0, 0.0), (clear_occ, 1.0, 1.0)):
        p = _cells(mask)
        c = np.rint(_apply(truth, p)).astype(int)
        v = a.data[c[:, 1], c[:, 0]]
        assert p.shape[0] > 1000 or mask is clear_occ
        assert ((v >= lo) & (v <= hi)).mean() > 0.99


# ----------------------------------------------------------------------- robot pair
def _world_offset(a: OccupancyGrid, world: OccupancyGrid) -> np.ndarray:
    return world.metric_to_pixel(a.pixel_to_metric([[0.0, 0.0]]))[0]


def _margins(g: OccupancyGrid) -> tuple[int, int, int, int]:
    ys, xs = np.nonzero(g.known)
    return int(xs.min()), int(ys.min()), g.width - 1 - int(xs.max()), g.height - 1 - int(ys.max())


def test_robot_pair_truth_maps_b_onto_a(pair0):
    a, b, truth = pair0
    world = building(0)
    off = _world_offset(a, world)
    assert np.allclose(off, np.rint(off), atol=1e-6)
    ox, oy = np.rint(off).astype(int)
    # a is a crop of the robot's scan of the building, in the building's frame.
    crop = world.data[oy : oy + a.height, ox : ox + a.width]
    assert (crop[a.free()] == 0.0).all() and (crop[a.occupied()] == 1.0).all()
    # truth is a similarity with a scale in [0.8, 1.25].
    lin = truth[:2, :2]
    s = math.hypot(lin[0, 0], lin[1, 0])
    assert 0.8 <= s <= 1.25
    assert np.allclose(lin.T @ lin, s * s * np.eye(2), atol=1e-9)
    assert np.allclose(truth[2], [0, 0, 1])
    assert b.resolution == pytest.approx(world.resolution * s)
    # b's free cells land on free space of the building (free or unknown in a) ...
    world_from_b = np.array([[1, 0, ox], [0, 1, oy], [0, 0, 1]]) @ truth
    clear_free = cv2.erode(b.free().astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    c = np.rint(_apply(world_from_b, _cells(clear_free))).astype(int)
    assert (world.data[c[:, 1], c[:, 0]] == 0.0).mean() > 0.99
    c_a = np.rint(_apply(truth, _cells(clear_free))).astype(int)
    inside = (c_a[:, 0] >= 0) & (c_a[:, 0] < a.width) & (c_a[:, 1] >= 0) & (c_a[:, 1] < a.height)
    va = a.data[c_a[inside, 1], c_a[inside, 0]]
    assert ((va == 0.0) | np.isnan(va)).mean() > 0.99
    assert (va == 0.0).sum() > 0.2 * clear_free.sum()  # the maps do overlap
    # ... and its walls on walls of the building, within one cell.
    walls = cv2.dilate(world.occupied().astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    c = np.rint(_apply(world_from_b, _cells(b.occupied()))).astype(int)
    assert walls[c[:, 1], c[:, 0]].mean() > 0.97


def test_robot_pair_margins_and_parameters():
    a, b, truth = robot_pair(2, rotation_deg=-120.0, scale=1.2, shape=SMALL)
    for g in (a, b):
        assert all(0 <= m <= 21 for m in _margins(g))
    assert np.degrees(math.atan2(truth[1, 0], truth[0, 0])) == pytest.approx(-120.0)
    assert math.hypot(truth[0, 0], truth[1, 0]) == pytest.approx(1.2)
    assert b.origin == (0.0, 0.0, 0.0)


def test_robot_pair_is_deterministic_and_overlap_matters():
    p1 = robot_pair(3, shape=SMALL)
    p2 = robot_pair(3, shape=SMALL)
    assert p1[0] == p2[0] and p1[1] == p2[1] and np.array_equal(p1[2], p2[2])
    p3 = robot_pair(4, shape=SMALL)
    assert not np.array_equal(p1[2], p3[2])
    with pytest.raises(ValueError):
        robot_pair(0, overlap=1.5, shape=SMALL)


def test_robot_pair_overlap_controls_shared_area():
    def shared(overlap: float) -> float:
        a, b, truth = robot_pair(5, overlap=overlap, rotation_deg=0.0, scale=1.0, shape=SMALL)
        c = np.rint(_apply(truth, _cells(b.free()))).astype(int)
        ok = (c[:, 0] >= 0) & (c[:, 0] < a.width) & (c[:, 1] >= 0) & (c[:, 1] < a.height)
        return float((a.free()[c[ok, 1], c[ok, 0]]).sum() / b.free().sum())

    assert shared(0.1) < shared(0.9)


def test_negative_pair():
    a, b = negative_pair(0, shape=SMALL)
    a2, b2 = negative_pair(0, shape=SMALL)
    assert a == a2 and b == b2
    assert a.known.mean() > 0.3 and b.known.mean() > 0.3
    # a comes from building 0 and b from building 1.
    w0 = building(0, SMALL)
    ox, oy = np.rint(_world_offset(a, w0)).astype(int)
    crop = w0.data[oy : oy + a.height, ox : ox + a.width]
    assert (crop[a.free()] == 0.0).all()

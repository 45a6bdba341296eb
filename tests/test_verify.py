import numpy as np

from gridmerge import OccupancyGrid
from gridmerge.verify import despeckle


def test_despeckle_makes_isolated_hits_unknown_only():
    d = np.zeros((7, 7))
    d[1, 1] = 1.0  # isolated hit
    d[4, 2:6] = 1.0  # a wall
    d[6, 0] = d[5, 1] = 1.0  # two hits touching diagonally: a wall, however short
    d[0, 6] = np.nan
    d[2, 6] = 0.3  # a graded value, kept
    g = OccupancyGrid(d)
    out = despeckle(g)
    assert np.isnan(out.data[1, 1])
    np.testing.assert_array_equal(out.data[4], g.data[4])
    unchanged = np.ones(d.shape, bool)
    unchanged[1, 1] = False
    np.testing.assert_array_equal(out.data[unchanged], g.data[unchanged])
    assert np.isnan(out.data[0, 6]) and g.data[1, 1] == 1.0  # input untouched
    clean = OccupancyGrid(np.zeros((3, 3)))
    assert despeckle(clean) is clean


import math

import cv2
import pytest

from gridmerge import samples
from gridmerge.fuse import warp_values
from gridmerge.grid import OCCUPIED_THRESHOLD
from gridmerge.transforms import SimilarityTransform
from gridmerge.verify import WallScorer, _strided_cells, acceptance_index, verify


def _verify_whole_frame(a, b, transform, tolerance):
    """verify() as first written: b warped into the whole of a's frame."""
    warped = warp_values(b.data, transform.params, a.shape, interpolation="nearest")
    both = a.known & ~np.isnan(warped)
    pa, pb = np.where(both, a.data, np.nan), np.where(both, warped, np.nan)
    index, agr, dis = acceptance_index(pa, pb)
    with np.errstate(invalid="ignore"):
        wa, wb = pa > OCCUPIED_THRESHOLD, pb > OCCUPIED_THRESHOLD

    def near(m):
        return cv2.distanceTransform((~m).astype(np.uint8), cv2.DIST_L2, 3) <= tolerance

    shares = []
    if wa.any() and wb.any():
        shares = [np.count_nonzero(wa & near(wb)) / np.count_nonzero(wa), np.count_nonzero(wb & near(wa)) / np.count_nonzero(wb)]
    elif wa.any() or wb.any():
        shares = [0.0]
    counts = (int(np.count_nonzero(wa)), int(np.count_nonzero(wb)))
    return index, agr, dis, float(np.mean(shares)) if shares else math.nan, int(np.count_nonzero(both)), counts


@pytest.mark.parametrize("seed", range(4))
def test_verify_on_the_footprint_equals_the_whole_frame(seed):
    a, b, truth = samples.robot_pair(seed % 2)
    rng = np.random.default_rng(seed)
    t = SimilarityTransform(truth)
    if seed >= 2:  # a wrong pose, partly outside a
        t = SimilarityTransform(rotation=t.rotation + rng.normal(0, 0.5), scale=t.scale, translation=t.translation + rng.normal(0, 150, 2))
    v = verify(a, b, t, tolerance=3.0)
    index, agr, dis, wall, overlap, walls = _verify_whole_frame(a, b, t, 3.0)
    assert (v.agreement, v.disagreement, v.overlap_cells, (v.walls_a, v.walls_b)) == (agr, dis, overlap, walls)
    assert v.wall_agreement == pytest.approx(wall, nan_ok=True) and v.acceptance_index == pytest.approx(index, nan_ok=True)


def test_verify_without_any_overlap():
    d = np.zeros((30, 30))
    d[10, :] = 1.0
    g = OccupancyGrid(d)
    v = verify(g, g, SimilarityTransform(translation=(500, 0)))
    assert v.overlap_cells == 0 and math.isnan(v.acceptance_index) and math.isnan(v.wall_agreement)
    assert v.walls_a == v.walls_b == 0


def test_verify_counts_each_maps_walls_in_the_overlap():
    """A wall of 10 cells, the other map's wall of 20 cells, both inside the overlap;
    walls outside the other map's known cells are not counted."""
    a = np.zeros((40, 40))
    a[10, 5:15] = 1.0  # 10 wall cells
    a[:, 30:] = np.nan
    b = np.zeros((40, 40))
    b[20, 5:25] = 1.0  # 20 wall cells
    b[30, 32:38] = 1.0  # outside a's known cells
    v = verify(OccupancyGrid(a), OccupancyGrid(b), SimilarityTransform())
    assert (v.walls_a, v.walls_b) == (10, 20) and v.wall_agreement == 0.0
    assert (v.matched_a, v.matched_b) == (0, 0)


def test_verify_counts_each_maps_matched_walls():
    """The wall agreement is the mean of the two maps' matched shares, and the counts
    say which map's walls went unmatched."""
    a = np.zeros((40, 40))
    a[10, 5:15] = 1.0  # 10 wall cells, all on b's wall
    a[30, 5:35] = 1.0  # 30 more, across b's free space
    b = np.zeros((40, 40))
    b[11, 5:15] = 1.0  # 10 wall cells, a cell from a's
    v = verify(OccupancyGrid(a), OccupancyGrid(b), SimilarityTransform(), tolerance=2.0)
    assert (v.walls_a, v.matched_a, v.walls_b, v.matched_b) == (40, 10, 10, 10)
    assert v.wall_agreement == pytest.approx((10 / 40 + 10 / 10) / 2)


def test_strided_cells_are_numpys_nonzero_with_a_stride():
    rng = np.random.default_rng(0)
    for shape, p, k in [((300, 200), 0.3, 1000), ((50, 7000), 0.01, 77), ((3, 3), 0.5, 10), ((40, 40), 0.0, 5)]:
        mask = rng.random(shape) < p
        ys, xs = np.nonzero(mask)
        step = max(1, len(xs) // k)
        expect = np.stack([xs[::step], ys[::step]], 1).astype(float)
        np.testing.assert_array_equal(_strided_cells(mask, k), expect.reshape(-1, 2))


def test_wall_scorer_agrees_with_itself_and_tells_wrong_poses():
    a, b, truth = samples.robot_pair(0)
    s = WallScorer(a, b, tolerance=3.0)
    right = s(SimilarityTransform(truth))
    wrong = s(SimilarityTransform(truth) @ SimilarityTransform(translation=(40, 25)))
    assert right.wall_agreement > 0.8 and right.overlap > 0.2 and right.walls_compared > 100
    assert wrong.wall_agreement < right.wall_agreement - 0.3
    same = WallScorer(a, a, tolerance=3.0)(SimilarityTransform())
    assert same.wall_agreement == 1.0 and same.consistency == 1.0 and same.overlap == 1.0


def _scorer_reference(a, b, t, tol):
    """WallScorer's verdict computed plainly: every sampled point moved by a matrix
    product, rounded, kept when it lands inside the other map."""
    def lookup(points, m, g, dist, tol):
        p = np.rint(points @ m[:2, :2].T + m[:2, 2]).astype(int)
        h, w = g.shape
        inside = (p[:, 0] >= 0) & (p[:, 0] < w) & (p[:, 1] >= 0) & (p[:, 1] < h)
        x, y = p[inside, 0], p[inside, 1]
        known, free = g.known[y, x], g.free()[y, x]
        if dist is None:
            return int(known.sum()), 0, 0
        near = dist[y, x] <= np.float32(tol)
        return int(known.sum()), int((known & near).sum()), int((free & ~near).sum())

    def dist(g):
        return cv2.distanceTransform((~g.occupied()).astype(np.uint8), cv2.DIST_L2, 3)

    wa, wb = _strided_cells(a.occupied(), 20000), _strided_cells(b.occupied(), 20000)
    ka, kb = _strided_cells(a.known, 20000), _strided_cells(b.known, 20000)
    inv = np.linalg.inv(t.params)
    scale = np.sqrt(abs(np.linalg.det(t.params[:2, :2])))
    n1, g1, c1 = lookup(wb, t.params, a, dist(a), tol)
    n2, g2, c2 = lookup(wa, inv, b, dist(b), tol / scale)
    landed_b = lookup(kb, t.params, a, None, 0)[0] / len(kb)
    landed_a = lookup(ka, inv, b, None, 0)[0] / len(ka)
    shares = [g / n for g, n in ((g1, n1), (g2, n2)) if n]
    wall = float(np.mean(shares)) if shares else 0.0
    return wall, landed_b, n1 + n2, max(landed_b, landed_a)


def test_wall_scorer_counts_as_a_plain_lookup_also_off_the_maps():
    # Poses that move points off both maps on every side (negative coordinates included):
    # points off a map count as on no known cell, exactly as a plain bounds check.
    a, b, truth = samples.robot_pair(0)
    rng = np.random.default_rng(3)
    # b known to its very edges (free, walls every few cells), so that a point one cell
    # beyond them would count.
    d = np.where(rng.random((120, 90)) < 0.15, 1.0, 0.0)
    b = OccupancyGrid(d)
    s = WallScorer(a, b, tolerance=2.0)
    poses = [SimilarityTransform(truth)] + [
        SimilarityTransform(rotation=rng.uniform(-np.pi, np.pi), scale=rng.uniform(0.6, 1.6), translation=rng.uniform(-300, 500, 2))
        for _ in range(40)
    ]
    for t in poses:
        q = s(t)
        wall, overlap, compared, shared = _scorer_reference(a, b, t, 2.0)
        assert (q.wall_agreement, q.overlap, q.walls_compared, q.shared) == pytest.approx((wall, overlap, compared, shared), abs=1e-12)
    assert any(s(t).walls_compared == 0 for t in poses) and any(0 < s(t).overlap < 1 for t in poses)


def test_wall_scorer_judges_at_another_tolerance_on_request():
    # 6 px off, few walls are within the scorer's 2 px of each other, most within 10 px;
    # the scorer's own tolerance is unchanged by the request.
    a, b, truth = samples.robot_pair(0)
    s = WallScorer(a, b, tolerance=2.0)
    off = SimilarityTransform(translation=(6, 0)) @ SimilarityTransform(truth)
    strict, loose, again = s(off), s(off, tolerance=10.0), s(off)
    assert loose.wall_agreement > strict.wall_agreement + 0.3
    assert again == strict and s.tolerance == 2.0


def test_despeckle_keeps_a_valid_read_only_grid():
    d = np.zeros((9, 9), np.float32)
    d[4, 4] = 1.0
    out = despeckle(OccupancyGrid(d))
    assert np.isnan(out.data[4, 4]) and not out.data.flags.writeable
    unknown = np.zeros((9, 9))
    unknown[4, 4] = np.nan
    assert out.resolution == 0.05 and out == OccupancyGrid(unknown)


def test_near_is_the_distance_transforms_own_threshold():
    """``_near`` dilates small tolerances by the offsets the distance transform puts
    within them; it must mark exactly the cells the transform does, whatever the mask,
    its edges and the tolerance (including ties such as 0.955 and 1.3693, its weights)."""
    from gridmerge.verify import _DILATE_MAX, _near

    rng = np.random.default_rng(3)
    tolerances = [-1.0, 0.0, 0.5, 0.955, 1.0, 1.3693, 2.0, 2.865, 2.9, 3.0, 3.3, 5.0, _DILATE_MAX, 9.5, float("nan")]
    for k in range(600):
        h, w = (int(v) for v in rng.integers(1, 50, 2))
        mask = rng.random((h, w)) < [0.002, 0.02, 0.1, 0.6][k % 4]
        tol = tolerances[k % len(tolerances)] if k < 450 else float(rng.uniform(0.0, 10.0))
        dist = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 3)
        expected = dist <= tol if mask.any() else np.zeros_like(mask)
        got = _near(mask, tol)
        assert got.dtype == bool and got.shape == mask.shape
        np.testing.assert_array_equal(got, expected, err_msg=f"{h}x{w}, tolerance {tol}")
    # A strided view is read as the cells it shows.
    big = rng.random((40, 60)) < 0.05
    np.testing.assert_array_equal(_near(big[::2, 1::3], 3.0), _near(np.ascontiguousarray(big[::2, 1::3]), 3.0))


from gridmerge.verify import slide  # noqa: E402


def _band_with_wall(angle_deg: float = 0.0) -> OccupancyGrid:
    """Free space around one straight wall through its middle, unknown elsewhere."""
    d = np.full((120, 120), np.nan)
    yy, xx = np.mgrid[0:120, 0:120]
    u = np.array([math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))])
    along = (xx - 60) * u[0] + (yy - 60) * u[1]
    across = -(xx - 60) * u[1] + (yy - 60) * u[0]
    band = (np.abs(along) < 45) & (np.abs(across) < 20)
    d[band] = 0.0
    d[band & (np.abs(across) < 0.6)] = 1.0
    return OccupancyGrid(d)


@pytest.mark.parametrize("angle", [0.0, 30.0, 90.0])
def test_slide_along_one_wall_keeps_its_agreement(angle):
    """b on a by one straight wall: the maps do not say where along it b lies."""
    g = _band_with_wall(angle)
    s = slide(g, g, SimilarityTransform(), tolerance=2.0, fraction=0.15)
    u = np.array([math.cos(math.radians(angle)), math.sin(math.radians(angle))])
    assert abs(float(np.dot(s.direction, u))) > 0.98  # slid along the wall
    assert s.kept > 0.9
    assert s.distance == pytest.approx(0.15 * math.sqrt(verify(g, g, SimilarityTransform()).overlap_cells))


def test_slide_in_a_closed_room_loses_its_walls():
    d = np.full((90, 90), np.nan)
    d[15:75, 15:75] = 0.0
    d[15:75, [15, 74]] = 1.0
    d[[15, 74], 15:75] = 1.0
    g = OccupancyGrid(d)
    s = slide(g, g, SimilarityTransform(), tolerance=2.0, fraction=0.15)
    assert s.kept < 0.7  # half the walls cross the room's free space either way


def test_slide_without_agreeing_walls_is_none():
    a = np.zeros((40, 40))
    a[10, 5:35] = 1.0
    b = np.zeros((40, 40))
    b[30, 5:35] = 1.0
    assert slide(OccupancyGrid(a), OccupancyGrid(b), SimilarityTransform(), tolerance=2.0) is None
    empty = OccupancyGrid(np.zeros((40, 40)))
    assert slide(empty, empty, SimilarityTransform()) is None


from gridmerge.verify import crossing  # noqa: E402


def _room(size: int = 80, across=None) -> np.ndarray:
    """A closed room of free cells, walls round it; ``across``: a row with a wall from
    column 20 to 60 (cells)."""
    d = np.zeros((size, size))
    d[[0, -1], :] = 1.0
    d[:, [0, -1]] = 1.0
    if across is not None:
        d[across, 20:60] = 1.0
    return d


def test_crossing_counts_walls_deep_in_the_other_maps_open_space():
    plain, crossed = OccupancyGrid(_room()), OccupancyGrid(_room(across=40))
    c = crossing(plain, crossed, SimilarityTransform())
    assert c.deep == 40 and c.walls == 2 * 316 + 40
    assert c.share == pytest.approx(40 / c.walls)
    # Either way round: a's wall across b's room counts alike.
    assert crossing(crossed, plain, SimilarityTransform()) == c


def test_crossing_ignores_walls_beside_the_other_maps_walls_or_unknown():
    # A wall 3 cells inside the room (a bent map, a thick wall) is not deep.
    beside = _room()
    beside[3, 10:70] = 1.0
    assert crossing(OccupancyGrid(_room()), OccupancyGrid(beside), SimilarityTransform()).deep == 0
    # Nor is one next to what the other map does not know: it may not have seen there.
    unseen = _room()
    unseen[30:50, 30:50] = np.nan
    c = crossing(OccupancyGrid(unseen), OccupancyGrid(_room(across=52)), SimilarityTransform())
    # Row 52 passes 3 cells below the unknown square (columns 30-49): of columns 20-59,
    # only 20-25 and 54-59 lie more than 5 cells from it.
    assert c.deep == 12
    assert crossing(OccupancyGrid(_room()), OccupancyGrid(_room(across=52)), SimilarityTransform()).deep == 40


def test_crossing_is_counted_in_the_finer_maps_cells():
    fine = OccupancyGrid(_room(across=40))
    coarse = OccupancyGrid(cv2.resize(_room(), (40, 40), interpolation=cv2.INTER_NEAREST))
    two = SimilarityTransform(scale=2.0, translation=(0.5, 0.5))  # coarse pixels -> fine pixels
    c = crossing(fine, coarse, two)
    assert c == crossing(coarse, fine, two.inverse)
    assert c.deep == 40  # the fine map's wall across, in its own cells


def test_crossing_beyond_max_walls_is_not_searched():
    c = crossing(OccupancyGrid(_room()), OccupancyGrid(_room(across=40)), SimilarityTransform(), max_walls=600)
    assert (c.walls, c.deep) == (672, None) and math.isnan(c.share)
    assert crossing(OccupancyGrid(_room()), OccupancyGrid(_room(across=40)), SimilarityTransform(), max_walls=673).deep == 40


def test_crossing_without_walls_has_no_share():
    empty = OccupancyGrid(np.zeros((30, 30)))
    c = crossing(empty, empty, SimilarityTransform())
    assert (c.walls, c.deep) == (0, 0) and math.isnan(c.share)

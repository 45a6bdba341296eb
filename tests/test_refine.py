"""Coarse-to-fine refinement against the maps (gridmerge.refine)."""

import math

import cv2

import numpy as np
import pytest

from gridmerge import OccupancyGrid, samples
from gridmerge import refine as refine_mod
from gridmerge.refine import WallICP, chamfer_polish, wall_search, _a_field, _corner_shift, _blurred_free, _facing, _plane_step, _same_face, _b_points, _block_fields, _planes, _smoothed, _whole, prepare_fields, refine_direct
from gridmerge.transforms import SimilarityTransform, corner_error


@pytest.fixture(scope="module")
def robots():
    a, b, truth = samples.robot_pair(0)
    return a, b, SimilarityTransform(truth)


def _perturbed(truth: SimilarityTransform, seed: int) -> SimilarityTransform:
    # 2-5 px off at b's corners: what the candidates of align typically are.
    rng = np.random.default_rng(seed)
    sign = rng.choice([-1.0, 1.0], 4)
    return SimilarityTransform(
        rotation=truth.rotation + sign[0] * 0.003,
        scale=truth.scale * (1 + sign[1] * 0.002),
        translation=truth.translation + sign[2:] * 2.0,
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_coarse_to_fine_reaches_sub_pixel_accuracy(robots, seed):
    a, b, truth = robots
    start = _perturbed(truth, seed)
    assert corner_error(start, truth, b.shape) > 2.0
    refined, report = refine_direct(a, b, start, cache={})
    assert report.accepted and report.points > 1000
    assert corner_error(refined, truth, b.shape) < 0.5
    assert isinstance(refined, SimilarityTransform)


def test_large_maps_refine_coarse_to_fine_as_precisely(robots, monkeypatch):
    # Maps above LARGE_CELLS run the smoothest levels at half resolution and judge b's
    # cells block by block from a shared pool at full resolution; force that path on the
    # small pair and check that nothing is lost.
    a, b, truth = robots
    start = _perturbed(truth, 5)
    whole, _ = refine_direct(a, b, start, cache={})
    monkeypatch.setattr(refine_mod, "LARGE_CELLS", 0)
    cache: dict = {}
    coarse, report = refine_direct(a, b, start, cache=cache)
    assert report.accepted
    assert corner_error(coarse, truth, b.shape) < 0.5
    assert corner_error(coarse, whole, b.shape) < 0.3
    assert any(k[0] == "a" and k[2] == 2 for k in cache if isinstance(k, tuple) and len(k) == 3)
    # A second candidate reuses the cells judged for the first.
    pool = next(v for k, v in cache.items() if k[0] == "b pool")
    judged = len(pool["chunks"])
    again, _ = refine_direct(a, b, _perturbed(truth, 6), cache=cache)
    assert len(pool["chunks"]) <= judged + 1
    assert corner_error(again, truth, b.shape) < 0.5


def test_prepared_fields_are_those_refinement_uses(robots):
    a, b, truth = robots
    start = _perturbed(truth, 2)
    cache = prepare_fields(a, b, {}, scale=truth.scale)
    keys = set(cache)
    prepared, _ = refine_direct(a, b, start, cache=cache)
    assert set(cache) == keys  # nothing left to compute
    fresh, _ = refine_direct(a, b, start, cache={})
    np.testing.assert_array_equal(prepared.params, fresh.params)


def test_a_refinement_does_not_depend_on_what_was_refined_before(robots, monkeypatch):
    # b has more cells near structure than max_points at every level (55 526 at the
    # coarsest): the subset is evenly spread, not drawn, so a candidate refined after
    # another (sharing the cache) is refined exactly as alone.
    a, b, truth = robots
    start = _perturbed(truth, 3)
    alone, _ = refine_direct(a, b, start)
    cache: dict = {}
    refine_direct(a, b, _perturbed(truth, 9), cache=cache)
    shared, _ = refine_direct(a, b, start, cache=cache)
    np.testing.assert_array_equal(alone.params, shared.params)
    assert corner_error(alone, truth, b.shape) < 0.5
    # The same on the large maps' path, whose pool of judged blocks grows with the
    # candidates: the blocks are judged in one fixed order.
    monkeypatch.setattr(refine_mod, "LARGE_CELLS", 0)
    big_alone, _ = refine_direct(a, b, start, cache={})
    cache = {}
    refine_direct(a, b, _perturbed(truth, 9), cache=cache)
    refine_direct(a, b, _perturbed(truth, 4), cache=cache)
    big_shared, _ = refine_direct(a, b, start, cache=cache)
    np.testing.assert_array_equal(big_alone.params, big_shared.params)


def test_fewer_cells_spread_evenly_still_refine_precisely(robots):
    a, b, truth = robots
    few, report = refine_direct(a, b, _perturbed(truth, 0), max_points=3000, cache={})
    assert report.accepted and report.points == 3000
    assert corner_error(few, truth, b.shape) < 0.5


def test_the_subsets_are_spread_over_the_whole_range():
    pick = refine_mod._evenly(10, 4)
    np.testing.assert_array_equal(pick, [0, 2, 5, 7])
    assert np.array_equal(refine_mod._evenly(7, 7), np.arange(7))
    order = refine_mod._spread_order(1000)
    np.testing.assert_array_equal(np.sort(order), np.arange(1000))
    # Every prefix reaches across the range: its largest gap is a few times the even one.
    for k in (10, 50, 200):
        gaps = np.diff(np.sort(np.concatenate([[-1], order[:k], [1000]])))
        assert gaps.max() <= 3 * 1000 / k


def test_every_level_at_full_resolution_still_works(robots):
    a, b, truth = robots
    refined, report = refine_direct(a, b, _perturbed(truth, 1), factors=(1, 1, 1))
    assert report.accepted and corner_error(refined, truth, b.shape) < 0.5
    with pytest.raises(ValueError):
        refine_direct(a, b, truth, sigmas=(3.0, 1.0), factors=(2,))


def test_refinement_never_moves_farther_than_max_shift(robots):
    a, b, truth = robots
    far = SimilarityTransform(rotation=truth.rotation + 0.05, scale=truth.scale, translation=truth.translation + 15)
    out, report = refine_direct(a, b, far, max_shift=3.0)
    assert (out is far) == (not report.accepted)
    assert corner_error(out, far, b.shape) <= 3.0 + 1e-9


def test_a_candidate_of_the_coarse_correlation_converges(robots):
    """About 15 px off at b's corners, as the wall correlation's candidates can be (its
    cells are several pixels wide), within a wide ``max_shift``."""
    a, b, truth = robots
    start = SimilarityTransform(rotation=truth.rotation - 0.015, scale=truth.scale, translation=truth.translation + [-15.0, 6.0])
    assert 10.0 < corner_error(start, truth, b.shape) < 25.0
    refined, report = refine_direct(a, b, start, max_shift=30.0)
    assert report.accepted
    assert corner_error(refined, truth, b.shape) < 0.5
    # ... and not within the default reach.
    kept, report = refine_direct(a, b, start)
    assert not report.accepted and kept is start


def test_steps_stay_within_max_shift_on_noisy_maps():
    """On noisy maps far from the truth no step runs away (undamped steps went thousands
    of pixels off), and a refinement held back by ``max_shift`` keeps the start."""
    from gridmerge.bench import datasets

    ds = datasets.simulated(n=3, seed=3, sources=("building",), building_shapes=((360, 480),), tiers=("hard",))
    rng = np.random.default_rng(1)
    for c in ds:
        if c.truth is None:
            continue
        truth = SimilarityTransform(np.asarray(c.truth))
        for _ in range(4):
            turn, r, direction = rng.uniform(-0.01, 0.01), rng.uniform(6.0, 12.0), rng.uniform(0, 2 * math.pi)
            start = SimilarityTransform(rotation=truth.rotation + turn, scale=truth.scale, translation=truth.translation + r * np.array([math.cos(direction), math.sin(direction)]))
            out, report = refine_direct(c.a, c.b, start, max_shift=30.0)
            assert report.shift_px <= 30.0 + 1e-6
            assert (out is start) == (not report.accepted)


def test_a_refinement_held_back_by_max_shift_is_refused(robots):
    """Stopping at the edge of ``max_shift`` would return a pose that is neither the
    start nor where the cells lead: the start is kept."""
    a, b, truth = robots
    start = SimilarityTransform(rotation=truth.rotation, scale=truth.scale, translation=truth.translation + [4.0, -3.0])
    out, report = refine_direct(a, b, start, max_shift=2.0)
    assert not report.accepted and out is start
    out, report = refine_direct(a, b, start, max_shift=12.0)
    assert report.accepted and corner_error(out, truth, b.shape) < 0.5


def _heterogeneous_pair(scale: float, noise: float = 0.0):
    """Robot maps of one building from the benchmark's simulator (exact truth): b's cells
    ``scale`` times a's, with ``noise`` (spurious and missed hits)."""
    from gridmerge.bench import datasets

    world = samples.building(5, (360, 480))
    rng = np.random.default_rng(0)
    free = np.argwhere(world.free())
    views = free[rng.choice(len(free), 6)][:, ::-1].astype(float)
    a, b, truth, _ = datasets.robot_views_pair(world, views[:4], views[2:], rotation_deg=30.0, scale=scale, noise=noise, rng=1)
    return a, b, SimilarityTransform(truth)


@pytest.mark.parametrize("scale", [0.5, 0.55])
def test_a_map_twice_as_fine_is_refined(scale):
    """b's cells half a's: at a's coarse smoothing, b's thin walls blur over many of b's
    cells and change by less than 0.01 per cell; that level once found no structure and
    ended the whole refinement."""
    a, b, truth = _heterogeneous_pair(scale, noise=0.12)
    start = SimilarityTransform(rotation=truth.rotation + 0.01, scale=truth.scale, translation=truth.translation + [3.0, -2.0])
    assert corner_error(start, truth, b.shape) > 3.0
    refined, report = refine_direct(a, b, start)
    assert report.accepted and report.iterations > 0
    assert corner_error(refined, truth, b.shape) < 1.5


def test_the_finer_map_is_the_field_the_other_is_fitted_to():
    """The coarse map's field steps at the front of its wall cells, half a coarse cell
    ahead of where they are: the fine map's cells fitted to it shrink or grow the pose's
    scale. With the coarse map (b, cells twice a's) as the field, a start 11 px off and
    the truth itself both end 1.7 % off in scale, 5 px at b's corners; with
    ``reference="finer"`` the last level fits b's cells to a's field instead."""
    a, b, truth = _heterogeneous_pair(2.0)
    inv = truth.inverse  # a's pixels -> b's: b, the coarse map, is the field
    rough = SimilarityTransform(rotation=inv.rotation + 0.01, scale=inv.scale * 1.004, translation=inv.translation + [4.0, -3.0])
    assert corner_error(rough.inverse, truth, b.shape) > 10.0
    for start in (inv, rough):
        coarse, report = refine_direct(b, a, start)
        assert report.accepted and abs(coarse.inverse.scale / truth.scale - 1) > 0.01
        assert corner_error(coarse.inverse, truth, b.shape) > 3.0
        finer, report = refine_direct(b, a, start, reference="finer")
        assert report.accepted and report.shift_px == pytest.approx(_corner_shift(start.params, finer.params, a.shape))
        assert abs(finer.inverse.scale / truth.scale - 1) < 0.006
        assert corner_error(finer.inverse, truth, b.shape) < 1.5
    # Fields prepared ahead for the finer reference are the ones it uses.
    cache = prepare_fields(b, a, {}, scale=1 / truth.scale, reference="finer")
    cached, _ = refine_direct(b, a, rough, reference="finer", cache=cache)
    np.testing.assert_array_equal(cached.params, finer.params)
    # a the finer map already: the usual refinement.
    direct, _ = refine_direct(a, b, truth)
    same, _ = refine_direct(a, b, truth, reference="finer")
    np.testing.assert_array_equal(same.params, direct.params)
    with pytest.raises(ValueError, match="reference"):
        refine_direct(a, b, truth, reference="b")


def test_block_fields_equal_the_dense_fields():
    rng = np.random.default_rng(0)
    d = rng.random((120, 140)).astype(np.float32)
    d[rng.random(d.shape) < 0.3] = np.nan
    d[40:44, :] = 1.0
    grid = OccupancyGrid(d)
    for sigma in (1.0, 1.7):
        k, v = _planes(grid, _whole(grid), 1)
        f, gx, gy, sk = _smoothed(k, v, sigma)
        for c in (1, 2, 3):
            bx = rng.integers(0, 140 // c, 400)
            by = rng.integers(0, 120 // c, 400)
            x, y, F, GX, GY, SK, KN = _block_fields(grid.data, bx, by, c, sigma)
            assert len(x) > 100
            np.testing.assert_allclose(F, f[y, x], atol=1e-5)
            np.testing.assert_allclose(GX, gx[y, x], atol=1e-5)
            np.testing.assert_allclose(GY, gy[y, x], atol=1e-5)
            np.testing.assert_allclose(SK, sk[y, x], atol=1e-5)
            assert (KN == ~np.isnan(grid.data[y, x])).all()


@pytest.mark.parametrize("sigma", [0.8, 1.0, 3.0])
def test_structure_cells_are_those_of_the_written_rule(robots, sigma):
    # b's cells near structure: well inside its known cells (smoothed known mask > 0.9),
    # known themselves, with a field changing by 0.01 per cell (or per smoothing width),
    # row by row as numpy lists them.
    _, b, _ = robots
    k, v = _planes(b, _whole(b), 1)
    f, gx, gy, sk = _smoothed(k, v, sigma)
    change = np.hypot(gx, gy) * max(1.0, sigma)
    rule = (sk > 0.9) & (change > 0.01) & (k > 0.5)
    x, y, values = _b_points(b, _whole(b), 1, sigma)
    found = np.zeros_like(rule)
    found[y, x] = True
    assert rule.sum() > 1000
    # The same cells (but for any whose change is within float rounding of 0.01) ...
    assert not ((found != rule) & (np.abs(change - 0.01) > 1e-6)).any()
    # ... each once, row by row, with its field value.
    assert (np.diff(y.astype(np.int64) * b.width + x) > 0).all()
    np.testing.assert_array_equal(values, f[y, x].astype(np.float64))


def test_half_resolution_fields_sample_the_full_resolution_ones():
    # Reduced cell (x, y) is cell (2x, 2y); the prefilter and the smaller blur together
    # smooth as much as the full-resolution blur.
    a, _, _ = samples.robot_pair(1)
    # (Field, x and y gradients and smoothed known mask, interleaved: channels last.)
    full = np.moveaxis(_a_field(a, _whole(a), 1, 3.0), -1, 0)
    half = np.moveaxis(_a_field(a, _whole(a), 2, 3.0), -1, 0)
    h, w = half[0].shape
    assert (h, w) == ((a.height + 1) // 2, (a.width + 1) // 2)
    inside = full[3][::2, ::2] > 0.99  # well inside the known area
    for f, g, per_cell in zip(full[:3], half[:3], (1.0, 2.0, 2.0)):  # gradients per reduced cell
        diff = np.abs(f[::2, ::2] - g / per_cell)[inside]
        assert np.percentile(diff, 99) < 0.03 * max(1e-6, np.abs(f).max())


def test_huge_maps_keep_the_initial_estimate():
    a = OccupancyGrid(np.zeros((2, 40000), np.float32))
    t = SimilarityTransform(rotation=0.1)
    out, report = refine_direct(a, a, t)
    assert out is t and not report.accepted and math.isnan(report.rms_after)


def test_scale_prior_helps_only_where_the_cells_agree(robots):
    # robot_pair's b has the building's resolution times the scale: the resolution ratio
    # is the true scale. A prior at the truth refines as precisely as the cells alone; a
    # prior 1 % off would cost fit, so the refinement is refused and the candidate kept.
    a, b, truth = robots
    start = _perturbed(truth, 0)
    free, _ = refine_direct(a, b, start, cache={})
    right, report = refine_direct(a, b, start, cache={}, scale_prior=(truth.scale, 4.0))
    assert report.accepted and corner_error(right, truth, b.shape) < 0.5
    assert abs(right.scale / truth.scale - 1) <= abs(free.scale / truth.scale - 1) + 1e-4
    wrong, report = refine_direct(a, b, start, cache={}, scale_prior=(truth.scale * 1.01, 4.0))
    assert not report.accepted and report.rms_after > report.rms_before
    np.testing.assert_array_equal(wrong.params, start.params)


# --- WallICP: the walls' own last step ------------------------------------------------


def test_wall_icp_brings_a_pose_a_few_pixels_off_onto_the_walls(robots):
    a, b, truth = robots
    icp = WallICP(a, b)
    for seed in range(3):
        rng = np.random.default_rng(seed)
        start = SimilarityTransform(rotation=truth.rotation + rng.choice([-1, 1]) * 0.003, scale=truth.scale,
                                    translation=truth.translation + rng.choice([-1, 1], 2) * 2.0)
        assert corner_error(start, truth, b.shape) > 2.0
        polished = icp.polish(start)
        assert isinstance(polished, SimilarityTransform)
        assert corner_error(polished, truth, b.shape) < 0.5
        assert math.isclose(polished.scale, start.scale)  # the scale is kept by default


def test_swapped_wall_icp_is_the_icp_with_b_as_reference(robots):
    a, b, truth = robots
    icp = WallICP(a, b)
    start = (SimilarityTransform(translation=(2.0, -2.0)) @ SimilarityTransform(truth.params)).inverse  # a -> b
    swapped = icp.swapped()
    assert np.array_equal(swapped.polish(start).params, WallICP(b, a).polish(start).params)
    assert corner_error(swapped.polish(start).inverse, truth, b.shape) < 0.5
    assert icp._maps[0][0] is swapped._maps[1][0]  # the tables are shared, not made again


def test_wall_icp_can_fit_the_scale_too(robots):
    a, b, truth = robots
    start = SimilarityTransform(rotation=truth.rotation, scale=truth.scale * 1.01, translation=truth.translation + [1.5, -1.0])
    icp = WallICP(a, b)
    assert corner_error(icp.polish(start, keep_scale=False), truth, b.shape) < 0.5
    assert corner_error(icp.polish(start), truth, b.shape) > 1.0  # held at the wrong scale


def test_wall_icp_reaches_the_walls_where_the_smoothed_cells_do_not(shared_data):
    """Simulated pair 2 of seed 1 (hard tier: b at 0.7 of a's cell size, 12 % spurious
    and missed hits, 25 % overlap): from the wall correlation's candidate, the
    smoothed-occupancy refinement stops 3 px from the truth, where the thin walls agree
    on a fifth of the overlap; ICP on the walls goes the rest of the way."""
    import importlib

    from gridmerge.bench import datasets
    from gridmerge.correlate import correlation_hypotheses, rotation_candidates
    from gridmerge.verify import verify

    A = importlib.import_module("gridmerge.align")
    # Pair 2 of seed 1 as built until 2026-11-30 (rays stopped at the source's unknown cells).
    c = datasets.simulated(n=60, seed=1, data_dir=shared_data, see_through=0)[2]
    a, oa, b, ob = A.working_maps(c.a, c.b)
    truth = A.full_to_crop(SimilarityTransform(np.asarray(c.truth)), oa, ob)
    hyps = correlation_hypotheses(a, b, scales=[b.resolution / a.resolution], rotations=rotation_candidates(a, b), fine_deg=(-2.0, -1.0, 0.0, 1.0, 2.0))
    start = next(h.transform for h in hyps if corner_error(h.transform, truth, b.shape) < 15.0)
    refined, report = refine_direct(a, b, start, max_shift=30.0, scale_prior=(b.resolution / a.resolution, 1.0))
    polished = WallICP(a, b).polish(refined)
    assert corner_error(refined, truth, b.shape) > 2.0
    assert corner_error(polished, truth, b.shape) < 1.5
    assert verify(a, b, polished).wall_agreement > 0.5 > 0.3 > verify(a, b, refined).wall_agreement


def _rooms(shape, boxes, partitions=()):
    """A map (NaN unknown): each ``(x0, y0, x1, y1)`` box free inside with walls on its
    border; each partition ``(x, y0, y1)`` a wall one cell thick down column ``x``."""
    d = np.full(shape, np.nan)
    for x0, y0, x1, y1 in boxes:
        d[y0 : y1 + 1, x0 : x1 + 1] = 1.0
    for x0, y0, x1, y1 in boxes:
        d[y0 + 1 : y1, x0 + 1 : x1] = 0.0
    for x, y0, y1 in partitions:
        d[y0 : y1 + 1, x] = 1.0
    return OccupancyGrid(d)


def test_a_wall_cell_faces_the_free_side_it_was_seen_from():
    g = _rooms((120, 160), [(10, 20, 140, 100)], partitions=[(80, 40, 80)])
    cells = np.array([[10, 50], [140, 50], [60, 20], [60, 100], [80, 60], [30, 60]])
    n = _facing(_blurred_free(g), cells)
    # Outer walls face into the room; the partition, free on both sides, faces nowhere;
    # so does a free cell in the open.
    np.testing.assert_array_equal(n, [[1, 0], [-1, 0], [0, 1], [0, -1], [0, 0], [0, 0]])
    assert _same_face(n[:2], n[1::-1]).tolist() == [False, False]
    assert _same_face(n[[0, 4]], n[[0, 0]]).tolist() == [True, True]  # nowhere agrees with any


@pytest.mark.parametrize("dx", [-2.5, -1.5, 1.5])
def test_facing_pairs_do_not_take_the_next_rooms_wall_for_this_one(dx):
    """a: two rooms with a partition three cells thick (faces at x = 60 and 63); b: the
    right room alone, seen from inside. Started a couple of pixels off, point-to-point
    ICP pairs b's partition face with the nearer face of a's partition, the left room's,
    and stops between; pairs that face the same way put b's on its own."""
    a = _rooms((120, 160), [(10, 20, 60, 100), (63, 20, 140, 100)])
    b = _rooms((120, 160), [(63, 20, 140, 100)])
    start = SimilarityTransform(translation=(dx, 1.0))
    truth = np.eye(3)
    assert corner_error(WallICP(a, b).polish(start), truth, b.shape) < 0.05
    assert corner_error(WallICP(a, b, facing=False).polish(start), truth, b.shape) > 0.5


def test_facing_wall_icp_lands_on_the_same_pose_from_any_side(robots):
    """Point-to-plane pairs slide along the walls: from starts 2-4 px off in different
    directions, the same pose within a hundredth of a pixel, and closer to the truth than
    point-to-point pairs get."""
    a, b, truth = robots
    icp, plain = WallICP(a, b), WallICP(a, b, facing=False)
    ends = []
    for off in [(3.0, 0.0), (0.0, -3.0), (-2.0, 2.5), (2.5, 2.5)]:
        start = SimilarityTransform(translation=off) @ truth
        ends.append(icp.polish(start))
        assert corner_error(ends[-1], truth, b.shape) < 0.1 < corner_error(plain.polish(start), truth, b.shape)
    assert max(corner_error(e, ends[0].params, b.shape) for e in ends) < 0.01


def _square_pairs(n_side=20):
    """Cells on the four sides of a 40 x 40 square and their outward normals."""
    t = np.linspace(0.0, 40.0, n_side)
    z, f = np.zeros_like(t), np.full_like(t, 40.0)
    pts = np.vstack([np.c_[t, z], np.c_[t, f], np.c_[z, t], np.c_[f, t]])
    nrm = np.vstack([np.tile([0.0, -1.0], (n_side, 1)), np.tile([0.0, 1.0], (n_side, 1)),
                     np.tile([-1.0, 0.0], (n_side, 1)), np.tile([1.0, 0.0], (n_side, 1))])
    return pts, nrm


def test_a_plane_step_recovers_a_small_motion_of_a_square():
    pts, nrm = _square_pairs()
    motion = SimilarityTransform(rotation=0.01, translation=(1.5, -0.8))
    dst = motion(pts)
    step = _plane_step(np.eye(3), pts, dst, nrm)
    assert np.abs(step - motion.params).max() < 5e-3  # one linearised step
    step = _plane_step(step, pts, dst, nrm)
    assert np.abs(step - motion.params).max() < 1e-5
    # Pairs facing nowhere count both axes: the same motion, point to point.
    step = _plane_step(np.eye(3), pts, dst, np.zeros_like(nrm))
    assert np.abs(_plane_step(step, pts, dst, np.zeros_like(nrm)) - motion.params).max() < 1e-5
    # The scale too, when it is free.
    grown = SimilarityTransform(scale=1.01, translation=(0.5, 0.5))
    free = _plane_step(_plane_step(np.eye(3), pts, grown(pts), nrm, keep_scale=False), pts, grown(pts), nrm, keep_scale=False)
    assert np.abs(free - grown.params).max() < 1e-4


def test_a_plane_step_holds_the_motion_along_a_wall_weakly():
    # One straight wall: across it the pairs fix the motion; along it only their small
    # weight along the wall does, which alone there still recovers it.
    t = np.linspace(0.0, 40.0, 30)
    pts = np.c_[np.zeros_like(t), t]
    nrm = np.tile([1.0, 0.0], (len(t), 1))
    step = _plane_step(np.eye(3), pts, pts + [1.0, 2.0], nrm)
    np.testing.assert_allclose(step[:2, 2], [1.0, 2.0], atol=1e-9)
    # Pairs all at one spot determine no rotation: refused.
    spot = np.tile([[5.0, 5.0]], (30, 1))
    assert _plane_step(np.eye(3), spot, spot + [1.0, 0.0], np.tile([[1.0, 0.0]], (30, 1))) is None


def test_wall_icp_without_walls_returns_the_pose_itself(robots):
    a, _, truth = robots
    empty = OccupancyGrid(np.zeros((50, 60)))
    assert WallICP(a, empty).polish(truth) is truth
    assert WallICP(empty, a).polish(truth) is truth


@pytest.mark.parametrize("rows", [7, 40, None])
def test_nearest_wall_table_in_blocks_finds_the_nearest_wall(rows):
    from gridmerge.refine import _NO_WALL, _nearest_walls

    rng = np.random.default_rng(3)
    walls = rng.random((90, 70)) < 0.01
    walls[40, 10:60] = True
    table = _nearest_walls(walls, 6, rows=rows)
    wy, wx = np.nonzero(walls)
    for y in range(walls.shape[0]):
        for x in range(walls.shape[1]):
            exact = np.hypot(wx - x, wy - y).min()
            dx, dy = (int(v) for v in table[y, x])
            if dx == _NO_WALL:
                assert exact > 6 - 0.5
            else:
                assert walls[y + dy, x + dx]
                assert math.hypot(dx, dy) <= exact + 0.5  # the transform's metric is near Euclidean


def test_chamfer_norms_are_opencvs_distances():
    """The nearest-wall table keeps offsets, not distances: the pairing radius is compared
    with the distance OpenCV's transform gives for that offset, as before the table."""
    import cv2

    from gridmerge.refine import WALL_ICP_REACH, _chamfer_norms

    n = WALL_ICP_REACH
    img = np.ones((2 * n + 1, 2 * n + 1), np.uint8)
    img[n, n] = 0
    d = cv2.distanceTransform(img, cv2.DIST_L2, 5)
    ys, xs = np.mgrid[-n : n + 1, -n : n + 1]
    assert np.allclose(_chamfer_norms()[np.abs(ys), np.abs(xs)], d, atol=1e-3)


# --- wall_search: starts for ICP beyond its reach --------------------------------------


@pytest.mark.parametrize("off", [(12.0, -9.0, 0.02), (15.0, 0.0, 0.0), (0.0, 0.0, 0.03)])
def test_wall_search_finds_the_walls_beyond_icps_reach(robots, off):
    # 15-28 px (up to 1.7 degrees) off at b's corners: ICP alone stays 7-13 px off; the
    # search's best start, polished, lands on the truth; the same starts every time.
    a, b, truth = robots
    dx, dy, turn = off
    start = SimilarityTransform(rotation=truth.rotation + turn, scale=truth.scale, translation=truth.translation + [dx, dy])
    icp = WallICP(a, b)
    assert corner_error(icp.polish(start), truth, b.shape) > 5.0
    starts = wall_search(a, b, start)
    assert 1 <= len(starts) <= 6
    assert all(math.isclose(s.scale, start.scale) for s in starts)  # the scale is kept
    assert corner_error(icp.polish(starts[0]), truth, b.shape) < 0.5
    again = wall_search(a, b, start)
    assert all(np.array_equal(s.params, t.params) for s, t in zip(starts, again))


def test_wall_search_at_another_scale_finds_a_pose_off_in_scale(robots):
    a, b, truth = robots
    start = SimilarityTransform(rotation=truth.rotation, scale=truth.scale * 1.02, translation=truth.translation + [4.0, -3.0])
    icp = WallICP(a, b)
    kept = wall_search(a, b, start)
    assert all(math.isclose(s.scale, start.scale) for s in kept)
    assert min(corner_error(icp.polish(s), truth, b.shape) for s in kept) > 2.0  # held at the wrong scale
    both = wall_search(a, b, start, scales=(1.0, 1 / 1.02))
    assert any(math.isclose(s.scale, truth.scale) for s in both)
    assert min(corner_error(icp.polish(s), truth, b.shape) for s in both) < 0.5


def test_wall_search_without_walls_or_overlap_has_no_start(robots):
    a, b, truth = robots
    empty = OccupancyGrid(np.where(b.occupied(), 0.0, b.data))
    assert wall_search(a, empty, truth) == []
    away = SimilarityTransform(translation=(5000.0, 5000.0)) @ truth  # b lands off a
    assert wall_search(a, b, away) == []


def test_a_thinned_wall_icp_shares_the_tables_and_uses_fewer_cells(robots):
    a, b, truth = robots
    icp = WallICP(a, b)
    thin = icp.thinned(300)
    assert len(icp._maps[0][1]) > 300 and len(thin._maps[0][1]) == 300 and len(thin._maps[1][1]) == 300
    assert thin._maps[0][0] is icp._maps[0][0] and thin._maps[1][0] is icp._maps[1][0]
    assert np.array_equal(thin._maps[0][3], icp._maps[0][3][refine_mod._evenly(len(icp._maps[0][1]), 300)])
    assert icp.thinned(10**6) is icp  # nothing to thin
    start = SimilarityTransform(rotation=truth.rotation + 0.003, scale=truth.scale, translation=truth.translation + [2.0, -2.0])
    assert corner_error(thin.polish(start), truth, b.shape) < 1.0


@pytest.mark.parametrize("off", [(1.5, -1.0, 0.0), (0.0, 0.0, 0.004), (-2.0, 1.5, -0.003)])
def test_chamfer_polish_puts_a_pose_a_few_pixels_off_onto_the_walls(robots, off):
    # 1-4 px off at b's corners: on the truth to a fraction of a cell, at the start's scale.
    a, b, truth = robots
    dx, dy, turn = off
    start = SimilarityTransform(rotation=truth.rotation + turn, scale=truth.scale, translation=truth.translation + [dx, dy])
    assert corner_error(start, truth, b.shape) > 1.0
    polished = chamfer_polish(a, b, start)
    assert corner_error(polished, truth, b.shape) < 0.3
    assert polished.scale == pytest.approx(start.scale, rel=1e-12)
    assert corner_error(chamfer_polish(a, b, truth), truth, b.shape) < 0.3  # the truth stays


def test_chamfer_polish_lowers_the_walls_distances(robots):
    # The cost it descends: b's wall cells' distance to a's nearest wall falls.
    a, b, truth = robots
    start = SimilarityTransform(rotation=truth.rotation + 0.003, scale=truth.scale, translation=truth.translation + [1.0, 2.0])
    field = cv2.distanceTransform((~a.occupied()).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    cells = refine_mod._strided_cells(b.occupied(), 10**6)

    def mean_distance(t):
        q = np.rint(cells @ t.params[:2, :2].T + t.params[:2, 2]).astype(int)
        inside = (q[:, 0] >= 0) & (q[:, 0] < a.width) & (q[:, 1] >= 0) & (q[:, 1] < a.height)
        q = q[inside]
        on = a.known[q[:, 1], q[:, 0]]
        return float(np.minimum(field[q[on, 1], q[on, 0]], 3.0).mean())

    assert mean_distance(chamfer_polish(a, b, start)) < mean_distance(start) - 0.3


def test_chamfer_polish_without_walls_or_overlap_keeps_the_pose(robots):
    a, b, truth = robots
    empty = OccupancyGrid(np.where(b.occupied(), 0.0, b.data))
    assert chamfer_polish(a, empty, truth) is truth
    away = SimilarityTransform(translation=(5000.0, 5000.0)) @ truth  # b lands off a
    assert chamfer_polish(a, b, away) is away


def test_the_wall_field_on_a_box_is_the_whole_maps_distance_inside_its_margin(robots):
    a, _, _ = robots
    walls = a.occupied()
    whole = cv2.distanceTransform((~walls).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    points = np.array([[40.0, 50.0], [120.5, 90.25]])
    field, gx, gy, corner = refine_mod._wall_field(walls, points, margin=11.0)
    assert corner.tolist() == [29.0, 39.0]
    assert field.shape == gx.shape == gy.shape == (103 - 39, 133 - 29)  # ceil(max) + margin + 1
    # Within the margin's reach of the points, the box's distances are the whole map's
    # (where the nearest wall lies within the margin).
    sub = whole[39:39 + field.shape[0], 29:29 + field.shape[1]]
    near = sub <= 5.0
    inner = np.zeros_like(near)
    inner[6:-6, 6:-6] = True
    assert np.allclose(field[near & inner], sub[near & inner], atol=1e-4)
    assert refine_mod._wall_field(np.zeros_like(walls), points, margin=11.0) is None


def test_bilinear_sampling_is_exact_on_a_plane_and_flags_the_outside():
    y, x = np.mgrid[0:20, 0:30].astype(float)
    plane = 2.0 * x - 3.0 * y + 1.0
    pts = np.array([[3.25, 4.5], [28.9, 18.1], [0.0, 0.0], [29.5, 3.0], [-0.5, 2.0]])
    got = refine_mod._bilinear(plane, pts, outside=-7.0)
    assert np.allclose(got[:3], 2.0 * pts[:3, 0] - 3.0 * pts[:3, 1] + 1.0)
    assert got[3] == -7.0 and got[4] == -7.0
    assert refine_mod._bilinear(plane, np.zeros((0, 2)), outside=1.0).shape == (0,)

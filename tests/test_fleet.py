"""Fleets: many maps, one frame; growing maps merged incrementally; mixed resolutions."""

import importlib
import math

import numpy as np
import pytest

import gridmerge
from gridmerge import Merger
from gridmerge.bench.fleet import Fleet, earlier_version, placement_errors, simulate_fleet
from gridmerge.errors import GridMergeError


# The fleets merged once per module: its tests run in one worker (pytest-xdist, --dist loadgroup).
pytestmark = pytest.mark.xdist_group("fleet")


@pytest.fixture(scope="module")
def fleet():
    return simulate_fleet(8, seed=0)


@pytest.fixture(scope="module")
def stranger():
    # A robot of another building.
    return simulate_fleet(1, seed=5, shape=(500, 700)).maps[0].replace(name="stranger")


@pytest.fixture(scope="module")
def fleet_merge(fleet, stranger):
    return gridmerge.merge(fleet.maps + [stranger])


def test_eight_robots_are_placed_within_2px_and_a_stranger_is_unplaced(fleet, fleet_merge):
    m = fleet_merge
    assert m.success, m.message
    assert m.unplaced == ["stranger"] and m.transforms[8] is None
    errors = placement_errors(fleet, m.transforms[:8])
    assert all(e is not None and e <= 2.0 for e in errors), errors
    assert "merged 8 of 9 maps" in m.message and "stranger" in m.message


def test_fleet_merge_keeps_the_reference_frame_and_reports_each_map(fleet, fleet_merge):
    m = fleet_merge
    ref = fleet.maps[0]
    # The reference's cells keep their metric coordinates in the merged map.
    pts = np.array([[0.0, 0.0], [ref.width - 1.0, ref.height - 1.0], [10.0, 20.0]])
    np.testing.assert_allclose(m.grid.metric_to_pixel(ref.pixel_to_metric(pts)), m.transforms[0](pts), atol=1e-6)
    d = m.to_dict()
    assert d["unplaced"] == ["stranger"] and d["reference"] == "robot1"
    entries = {e["name"]: e for e in d["maps"]}
    assert set(entries) == {f"robot{k}" for k in range(1, 9)} | {"stranger"}
    assert not entries["stranger"]["placed"] and "matrix" not in entries["stranger"]
    for k in range(8):
        e = entries[f"robot{k + 1}"]
        assert e["placed"] and np.array(e["matrix"]).shape == (2, 3)
        assert set(e["metric"]) == {"x", "y", "yaw", "scale"} and abs(e["metric"]["scale"] - 1) < 0.02
        assert 0.5 <= e["confidence"] <= 1.0
    # The metric pose of each robot's frame agrees with the truth (robot frames: origin 0).
    for k in range(1, 8):
        truth_px = fleet.relative(0, k)
        mine = fleet.maps[k]
        truth_metric = ref.pixel_to_metric_matrix() @ truth_px @ mine.metric_to_pixel_matrix()
        got = d["maps"][k]["metric"]
        assert got["x"] == pytest.approx(truth_metric[0, 2], abs=0.15)
        assert got["y"] == pytest.approx(truth_metric[1, 2], abs=0.15)
        dyaw = (got["yaw"] - math.atan2(truth_metric[1, 0], truth_metric[0, 0]) + math.pi) % (2 * math.pi) - math.pi
        assert abs(dyaw) < 0.01
    # The graph has loops, and its edges agree.
    assert m.graph.loops > 0 and max(m.graph.residuals.values()) < 5.0


def test_the_stranger_was_tried_and_declined(fleet_merge):
    tried = [p for p in fleet_merge.pairs if 8 in (p.i, p.j)]
    assert tried and not any(p.success for p in tried)


def test_reference_by_name_changes_the_frame(fleet):
    maps = [fleet.maps[k] for k in (0, 5, 7)]  # three robots that all overlap
    m = gridmerge.merge(maps, reference="robot6")
    assert m.success and m.reference == 1 and m.unplaced == []
    np.testing.assert_allclose(m.grid.origin[2], maps[1].origin[2])
    with pytest.raises(GridMergeError, match="reference"):
        gridmerge.merge(maps, reference="robot9")


def test_merger_update_reuses_unchanged_work(fleet):
    # Four robots whose maps all overlap (robot3's map grows): the mechanics of the
    # eight-robot fleet at a seventh of its search.
    team = Fleet(maps=[fleet.maps[k] for k in (0, 2, 5, 7)], to_source=[fleet.to_source[k] for k in (0, 2, 5, 7)],
                 source=fleet.source)
    earlier = earlier_version(team.maps[1], keep=0.6, direction_deg=30)
    assert earlier.shape != team.maps[1].shape  # grown maps move their origin
    merger = Merger()
    for k, g in enumerate(team.maps):
        merger.update(earlier if k == 1 else g)
    first = merger.merge()
    assert first.success and first.unplaced == []
    assert first.stats.features_computed == 4 and first.stats.pairs_searched == 6
    # Robot 3's map grew: only its features are recomputed; its pairs are re-verified,
    # nothing is searched again.
    merger.update(team.maps[1])
    second = merger.merge()
    assert second.success and second.unplaced == []
    s = second.stats
    assert s.features_computed == 1 and s.pairs_searched == 0 and s.pairs_reused == 3 and s.pairs_reverified == 3
    assert s.align_s < 0.25 * first.stats.align_s
    errors = placement_errors(team, second.transforms)
    assert max(errors) <= 2.0, errors
    assert {p.how for p in second.pairs if 1 in (p.i, p.j)} <= {"reverify", "predict"}
    # Nothing changed: nothing is computed.
    third = merger.merge()
    assert third.stats.features_computed == 0 and third.stats.pairs_reused == 6 and third.stats.align_s == 0.0
    for s_, t in zip(second.transforms, third.transforms):
        np.testing.assert_allclose(s_.params, t.params)


def test_merger_searches_a_new_map_and_forgets_a_removed_one(fleet):
    merger = Merger()
    for k in (0, 5, 7):
        merger.update(fleet.maps[k])
    assert merger.merge().success
    merger.update(fleet.maps[6])
    r = merger.merge()
    assert r.success and r.unplaced == []
    assert r.stats.pairs_searched == 3 and r.stats.pairs_reused == 3 and r.stats.features_computed == 1
    merger.remove("robot6")
    assert merger.names == ["robot1", "robot8", "robot7"]
    r = merger.merge()
    assert r.stats.pairs_searched == 0 and len(r.pairs) == 3
    with pytest.raises(GridMergeError):
        merger.remove("robot6")


def test_merger_refuses_what_is_not_a_map():
    with pytest.raises(GridMergeError):
        Merger().update(np.zeros((3, 3)))
    with pytest.raises(GridMergeError, match="at least two"):
        Merger().merge()
    with pytest.raises(GridMergeError):
        Merger(pairs="some")
    with pytest.raises(GridMergeError):
        Merger(resolution=0.0)


@pytest.fixture(scope="module")
def mixed():
    # 0.02, 0.05 and 0.1 m/cell robots in a 0.05 m/cell building.
    return simulate_fleet(3, seed=0, scales=(0.4, 1.0, 2.0), shape=(500, 700))


def test_maps_of_different_resolutions_merge_at_the_finest(mixed):
    res = [m.resolution for m in mixed.maps]
    assert res == pytest.approx([0.02, 0.05, 0.1])
    m = gridmerge.merge(mixed.maps)
    assert m.success and m.unplaced == [] and m.warnings == []
    assert m.grid.resolution == pytest.approx(0.02)
    for k, e in enumerate(placement_errors(mixed, m.transforms)):
        # In cells of the coarser of the reference and map k.
        assert e * 0.02 / max(0.02, res[k]) <= 2.0, (k, e)
    for k in range(3):
        assert abs(m.metric(k)["scale"] - 1.0) < 0.02  # the scale found agrees with the resolutions


def test_merged_resolution_can_be_chosen(mixed):
    m = gridmerge.merge(mixed.maps[1:], resolution=0.1)
    assert m.success and m.grid.resolution == pytest.approx(0.1)
    ref = mixed.maps[1]
    # The merged map keeps the reference's metric frame at the new resolution.
    pts = np.array([[5.0, 7.0], [100.0, 50.0]])
    np.testing.assert_allclose(m.grid.metric_to_pixel(ref.pixel_to_metric(pts)), m.transforms[0](pts), atol=1e-6)


def test_a_scale_that_contradicts_the_resolutions_is_flagged(mixed):
    # Robot 2 claims 0.02 m/cell but its cells are 0.05 m: the alignment's scale (2.5)
    # and the resolutions (1) disagree.
    # By default the alignment itself declines such a pair (AlignOptions.max_scale_disagreement).
    liar = mixed.maps[1].replace(resolution=0.02)
    maps = [mixed.maps[0], liar]
    declined = gridmerge.merge(maps)
    assert not declined.success and declined.unplaced == [liar.name]
    assert "resolutions" in declined.alignments[1].message and "--any-scale" in declined.alignments[1].message
    # For maps whose resolutions are unknown, any scale is aligned, and the merge's own
    # check warns, rejects or keeps quiet.
    warned = gridmerge.merge(maps, max_scale_disagreement=None)
    assert warned.success and len(warned.warnings) == 1 and "resolutions" in warned.warnings[0]
    rejected = gridmerge.merge(maps, scale_check="reject", max_scale_disagreement=None)
    assert not rejected.success and rejected.unplaced == [liar.name]
    assert gridmerge.merge(maps, scale_check="off", max_scale_disagreement=None).warnings == []


def test_reverify_refines_a_nearby_pose_and_declines_a_wrong_one(fleet):
    from gridmerge.merge import reverify
    from gridmerge.transforms import AffineTransform, SimilarityTransform, corner_error

    a, b = fleet.maps[0], fleet.maps[5]  # robots 1 and 6 overlap
    truth = fleet.relative(0, 5)
    near = SimilarityTransform(translation=(2.5, -2.0)) @ AffineTransform(truth)
    r = reverify(a, b, near, runner_up_ratio=0.5)
    assert r.success and r.details["reverified"]
    assert corner_error(r.transform, truth, b.shape) < 1.0 < corner_error(near, truth, b.shape)
    far = SimilarityTransform(translation=(60.0, 0.0)) @ AffineTransform(truth)
    wrong = reverify(a, b, far, runner_up_ratio=0.5)
    assert not wrong.success and wrong.transform is None and "declined" in wrong.message


def test_the_same_maps_under_other_names_merge_identically(fleet):
    maps = [fleet.maps[k] for k in (0, 5, 7, 6)]
    first = gridmerge.merge(maps, rng=4)
    renamed = gridmerge.merge([m.replace(name=f"/robot{k}/map") for k, m in enumerate(maps)], rng=4)
    assert first.success and renamed.success
    for s, t in zip(first.transforms, renamed.transforms):
        np.testing.assert_array_equal(s.params, t.params)
    np.testing.assert_array_equal(np.nan_to_num(first.grid.data, nan=-1), np.nan_to_num(renamed.grid.data, nan=-1))


def test_a_pair_whose_predicted_pose_fails_is_searched(fleet, monkeypatch):
    """With many maps only likely partners are searched first; the others that the
    placement says overlap are verified at the predicted pose. When that pose does not
    hold (on real maps, which bend, the graph's pose can be 20 px off), the pair has
    never been searched: it is searched then, not given up."""
    import dataclasses
    import importlib

    from gridmerge.transforms import corner_error

    merge_module = importlib.import_module("gridmerge.merge")  # the module, not the function
    real_reverify, real_align = merge_module.reverify, merge_module.align
    declined, searched = [], []

    def reverify(a, b, t, **kw):
        r = real_reverify(a, b, t, **kw)
        declined.append((a.name, b.name))
        return dataclasses.replace(r, success=False, transform=None, confidence=0.0, message="declined: the predicted pose does not hold")

    def align(a, b, **kw):
        searched.append((a.name, b.name))
        return real_align(a, b, **kw)

    monkeypatch.setattr(merge_module, "ALL_PAIRS_UP_TO", 2)
    monkeypatch.setattr(merge_module, "PARTNERS_PER_MAP", 1)
    monkeypatch.setattr(merge_module, "reverify", reverify)
    monkeypatch.setattr(merge_module, "align", align)
    maps = [fleet.maps[k] for k in (0, 5, 7, 6, 1)]
    m = gridmerge.merge(maps)
    assert m.success and m.placed == list(range(5)), m.message
    assert declined, "no pair was verified at a predicted pose"
    # Every pair verified at a predicted pose has been searched too (before, or after
    # its predicted pose failed), each once.
    assert set(declined) <= set(searched) and len(set(searched)) == len(searched) == m.stats.pairs_searched
    assert {p.how for p in m.pairs if (maps[p.i].name, maps[p.j].name) in declined} == {"search"} | (
        {"predict"} if any(not p.success for p in m.pairs if p.how == "predict") else set())
    for k, t in zip((0, 5, 7, 6, 1), m.transforms):
        relative = np.linalg.inv(m.transforms[0].params) @ t.params  # robot k -> robot 1
        assert corner_error(relative, fleet.relative(0, k), fleet.maps[k].shape) <= 2.0


@pytest.mark.shared
def test_reverify_lets_the_keypoint_matches_confirm_a_pose_of_maps_that_bend(shared_data):
    """E5_08 and E5_12 bend against each other: at the pose align found, their walls agree
    on 38 %, so the walls alone decline it when it is re-verified (a map grew, or the
    pose was predicted); with the maps' keypoints, the matches confirm it as align did,
    and a pose 60 px away is still declined."""
    from gridmerge.align import default_extractor
    from gridmerge.merge import reverify
    from gridmerge.transforms import SimilarityTransform

    e5 = shared_data / "halmstad" / "E5"
    a, b = gridmerge.load_map(e5 / "E5_08.png"), gridmerge.load_map(e5 / "E5_12.png")
    ext = default_extractor()
    features = (ext(a), ext(b))
    found = gridmerge.align(a, b, rng=0, features=features)
    assert found.success and "confirmed_by" in found.details
    walls_only = reverify(a, b, found.transform, runner_up_ratio=0.0)
    assert not walls_only.success
    r = reverify(a, b, found.transform, runner_up_ratio=0.0, features=features)
    assert r.success and r.details["reverified"] and "confirmed_by" in r.details
    assert "confirmed by the keypoint matches" in r.message
    capped = reverify(a, b, found.transform, runner_up_ratio=0.0, features=features, max_confidence=0.3)
    assert not capped.success  # as reliable as the chain that predicted it, no more
    far = reverify(a, b, SimilarityTransform(translation=(60.0, 0.0)) @ found.transform, runner_up_ratio=0.0, features=features)
    assert not far.success


def test_bridges_are_the_edges_on_no_loop():
    from gridmerge.graph import bridges

    assert bridges([(0, 1), (1, 2), (0, 2), (2, 3)]) == [(2, 3)]  # a triangle and a tail
    assert bridges([(0, 1), (1, 2)]) == [(0, 1), (1, 2)]
    assert bridges([]) == []
    assert bridges([(0, 1), (0, 1), (1, 2)]) == [(1, 2)]  # two alignments of one pair form a loop
    assert bridges([(0, 1), (2, 3), (3, 4), (4, 2)]) == [(0, 1)]  # two components


def _bridges_by_removal(edges):
    """The definition: an edge whose removal disconnects its two ends."""
    out = []
    for k, (i, j) in enumerate(edges):
        adj: dict = {}
        for m, (u, v) in enumerate(edges):
            if m != k:
                adj.setdefault(u, []).append(v)
                adj.setdefault(v, []).append(u)
        seen, stack = {i}, [i]
        while stack:
            for v in adj.get(stack.pop(), []):
                if v not in seen:
                    seen.add(v)
                    stack.append(v)
        if j not in seen:
            out.append((i, j))
    return out


def test_bridges_agree_with_their_definition_on_random_graphs():
    from gridmerge.graph import bridges

    rng = np.random.default_rng(0)
    for _ in range(200):
        n = int(rng.integers(2, 12))
        pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
        keep = rng.random(len(pairs)) < rng.uniform(0.1, 0.5)
        edges = [p for p, k in zip(pairs, keep) if k]
        assert bridges(edges) == _bridges_by_removal(edges)
    # A long chain: no recursion limit.
    chain = [(k, k + 1) for k in range(5000)]
    assert bridges(chain) == chain


def _fake_pairs(monkeypatch, aligned):
    """Three small maps and a fake pairwise search: ``aligned(pair, both_sides)`` says
    which pairs align (at confidence 0.6), also when a known pose is re-verified;
    returns the maps and the calls made ``(pair, both_sides)``, or ``(pair, "reverify")``."""
    from gridmerge import AlignResult, OccupancyGrid
    from gridmerge.transforms import SimilarityTransform

    rng = np.random.default_rng(0)
    maps = []
    for k in range(3):
        data = np.zeros((40, 50), np.float32)
        data[rng.integers(0, 40, 30), rng.integers(0, 50, 30)] = 1.0
        maps.append(OccupancyGrid(data, name=f"m{k}"))
    calls = []

    def fake(job):
        i, j = int(job.a.name[1:]), int(job.b.name[1:])  # by name: a map may be updated
        both = job.options.one_sided_confidence is not None
        calls.append(((i, j), "reverify" if job.prior is not None else both))
        ok = aligned((i, j), both)
        t = SimilarityTransform(translation=(3.0, 1.0))
        details = {"reverified": True} if job.prior is not None else {"other_side": {}} if both else {}
        return AlignResult(success=ok, transform=t if ok else None, candidate=t, metric_transform=None, confidence=0.6,
                           acceptance_index=0.9, inliers=10, matches=20, keypoints=(5, 5), method="hybrid",
                           message="" if ok else "declined: found from a's side only", elapsed_s=0.0, details=details)

    monkeypatch.setattr(importlib.import_module("gridmerge.merge"), "_run_pair", fake)
    return maps, calls


def test_a_fleet_searches_from_both_sides_only_what_no_loop_checks(monkeypatch):
    """Three maps in a chain (0-1, 1-2; 0-2 declined): pairs are first searched from one
    side, then the alignments on no loop below ``one_sided_confidence`` again from both
    sides; one found from one side only is declined there, and its map left unplaced."""
    maps, calls = _fake_pairs(monkeypatch, lambda pair, both: pair == (0, 1) or (pair == (1, 2) and not both))
    r = gridmerge.merge(maps)
    first = [c for c in calls if c[1] is not True]  # one side, or re-verified at the predicted pose
    again = [c for c in calls if c[1] is True]
    assert sorted(set(p for p, _ in first)) == [(0, 1), (0, 2), (1, 2)]  # (0, 2) also at its predicted pose
    assert sorted(p for p, _ in again) == [(0, 1), (1, 2)]  # both bridges, both at 0.6
    assert r.transforms[1] is not None and r.transforms[2] is None
    # Two maps: align's own rule, from both sides at once.
    calls.clear()
    gridmerge.merge(maps[:2])
    assert calls == [((0, 1), True)]


def test_a_merger_left_with_two_maps_checks_their_pair_from_both_sides(monkeypatch):
    """Three maps whose pairs all align (a loop checks each): searched from one side only.
    With one map removed, the remaining pair lies on no loop: searched from both sides."""
    maps, calls = _fake_pairs(monkeypatch, lambda pair, both: True)
    merger = Merger()
    for m in maps:
        merger.update(m, m.name)
    assert all(t is not None for t in merger.merge().transforms)
    assert calls and not any(both for _, both in calls)
    calls.clear()
    merger.remove("m2")
    assert merger.merge().success
    assert calls == [((0, 1), True)]


def _grown(m):
    """A newer version of map ``m``: one more cell seen."""
    data = m.data.copy()
    data[0, 0] = 1.0 - data[0, 0]
    return m.replace(data=data)


def test_a_merger_checks_a_re_verified_alignment_that_became_a_bridge(monkeypatch):
    """Three maps whose pairs all align (a loop checks each), searched from one side.
    Two maps grow and 0-2 no longer aligns: 0-1 and 1-2, re-verified at their known
    poses, are bridges now, never searched from both sides: they are searched so, and
    1-2, found from one side only, is declined. A re-verified pose that was searched
    from both sides keeps that, and is not searched again."""
    state = {"broken": False}
    maps, calls = _fake_pairs(monkeypatch, lambda pair, both: not (state["broken"] and (pair == (0, 2) or (pair == (1, 2) and both))))
    merger = Merger()
    for m in maps:
        merger.update(m, m.name)
    assert all(t is not None for t in merger.merge().transforms)
    calls.clear()
    state["broken"] = True
    merger.update(_grown(maps[0]), "m0")
    merger.update(_grown(maps[2]), "m2")
    r = merger.merge()
    assert sorted(set(p for p, how in calls if how == "reverify")) == [(0, 1), (0, 2), (1, 2)]  # (0, 2) also as predicted
    assert sorted(p for p, how in calls if how is True) == [(0, 1), (1, 2)]
    assert r.transforms[1] is not None and r.transforms[2] is None
    # 0-1 grows again: re-verified, and not searched from both sides a second time.
    calls.clear()
    merger.update(_grown(maps[1]), "m1")
    merger.merge()
    assert ((0, 1), "reverify") in calls and ((0, 1), True) not in calls

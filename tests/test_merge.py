import importlib
import math

import numpy as np
import pytest

import gridmerge
from gridmerge import OccupancyGrid, merge, samples
from gridmerge.merge import canvas_for
from gridmerge.transforms import SimilarityTransform


@pytest.fixture(scope="module")
def pair():
    a, b, truth = samples.robot_pair(0)
    # Give a a real ROS origin with yaw, so that frame handling is exercised.
    a = a.replace(origin=(3.0, -2.0, 0.3))
    return a, b, truth


@pytest.fixture(scope="module")
def merged(pair):
    a, b, _ = pair
    return merge([a, b])


def test_merge_places_b_and_keeps_a_in_its_metric_frame(pair, merged):
    a, b, _ = pair
    m = merged
    assert m.success and m.unplaced == [] and m.grid.resolution == a.resolution
    g = m.grid
    # Every known cell of a sits at the same metric coordinates in the merged map.
    ys, xs = np.nonzero(a.known)
    pick = np.linspace(0, len(xs) - 1, 200).astype(int)
    pa = np.stack([xs[pick], ys[pick]], 1).astype(float)
    pm = g.metric_to_pixel(a.pixel_to_metric(pa))
    np.testing.assert_allclose(pm, np.rint(pm), atol=1e-6)  # lands on cell centres
    np.testing.assert_allclose(m.transforms[0](pa), pm, atol=1e-6)
    assert g.origin[2] == pytest.approx(0.3)


def test_merged_cells_follow_eq_9(pair, merged):
    a, b, _ = pair
    g, t = merged.grid, merged.transforms
    ys, xs = np.nonzero(a.known)
    cells = np.rint(t[0](np.stack([xs, ys], 1))).astype(int)
    vals = g.data[cells[:, 1], cells[:, 0]]
    # Where a knows a cell, the merged map knows it; where b does not, it is a's value.
    assert not np.isnan(vals).any()
    warped_b = gridmerge.fuse.warp_values(b.data, t[1].params, g.shape)
    only_a = np.isnan(warped_b[cells[:, 1], cells[:, 0]])
    np.testing.assert_allclose(vals[only_a], a.data[ys, xs][only_a], atol=1e-6)
    both = ~only_a
    np.testing.assert_allclose(vals[both], (a.data[ys, xs][both] + warped_b[cells[:, 1], cells[:, 0]][both]) / 2, atol=1e-5)


def test_merged_map_holds_both_maps(pair, merged):
    a, b, _ = pair
    g = merged.grid
    assert np.count_nonzero(g.known) > max(np.count_nonzero(a.known), np.count_nonzero(b.known) * 0.8)
    assert merged.transforms[1] is not None


@pytest.mark.parametrize("fusion", ["average", "logodds", "max"])
def test_fusion_rules(pair, fusion):
    a, b, _ = pair
    m = merge([a, b], fusion=fusion)
    assert m.success and m.fusion == fusion
    assert np.isnan(m.grid.data).any() and (~np.isnan(m.grid.data)).any()


def test_unplaced_maps_are_reported_and_the_rest_merged(pair):
    a, b, _ = pair
    other, _ = samples.negative_pair(5)
    other = other.replace(name="elsewhere")
    m = merge([a, b, other])
    assert m.success and m.unplaced == ["elsewhere"] and m.transforms[2] is None
    d = m.to_dict()
    assert d["unplaced"] == ["elsewhere"] and [e["placed"] for e in d["maps"]] == [True, True, False]


def test_a_map_of_walls_everywhere_is_named_and_the_rest_merged(pair):
    """A map read with its free and occupied values swapped is declined by every pair
    at once: reported unplaced with a warning naming it; as the reference, the message
    says the others align and which to choose instead of "no two maps"."""
    a, b, _ = pair
    swapped = a.replace(data=np.where(a.known, 1.0 - a.data, np.nan), name="swapped")
    m = merge([a, swapped, b])
    assert m.success and m.unplaced == ["swapped"]
    assert [w for w in m.warnings if "walls everywhere" in w] == [m.warnings[-1]]
    assert m.warnings[-1].startswith("swapped is walls everywhere") and "negate" in m.warnings[-1]
    m = merge([swapped, a, b])
    assert not m.success and m.grid is None
    assert m.message.startswith("the reference swapped could not be aligned with any other map")
    assert m.message.endswith(f"{a.name}, {b.name} align with each other: make one of them the reference"), m.message
    assert "no two maps" not in m.message


def test_a_merge_resting_on_few_walls_warns_and_names_the_maps(pair, merged):
    # The pair's one alignment rests on many walls: no warning. Asked to warn below more
    # walls than its overlap holds, the same merge names the two maps in a warning.
    a, b, _ = pair
    assert merged.success and not [w for w in merged.warnings if "few walls" in w]
    m = merge([a, b], options=gridmerge.AlignOptions(few_walls=10**9))
    assert m.success and m.transforms[1] is not None
    np.testing.assert_allclose(m.transforms[1].params, merged.transforms[1].params)
    (note,) = [w for w in m.warnings if "few walls" in w]
    assert note.startswith(f"{a.name} - {b.name}: the pose rests on few walls")


def test_no_merge_when_nothing_aligns():
    a, b = samples.negative_pair(1)
    m = merge([a, b])
    assert not m.success and m.grid is None and "no two maps" in m.message


def test_merge_needs_two_maps_and_known_rules(pair):
    a, _, _ = pair
    with pytest.raises(gridmerge.GridMergeError):
        merge([a])
    with pytest.raises(gridmerge.GridMergeError):
        merge([a, a], fusion="median")


def test_canvas_covers_every_map():
    (h, w), (left, top, bottom) = canvas_for([(10, 10)], [SimilarityTransform(translation=(-5.0, 12.0))], (20, 20))
    assert (left, top, bottom) == (5, 0, 2) and (h, w) == (22, 25)
    (h, w), off = canvas_for([(10, 10)], [SimilarityTransform(rotation=math.pi, translation=(9, 9))], (20, 20))
    assert (h, w) == (20, 20) and off == (0, 0, 0)


def test_absurd_canvas_is_declined_not_allocated(pair, monkeypatch):
    a, b, _ = pair
    mm = importlib.import_module("gridmerge.merge")  # the module, not the function

    real_align = mm.align

    def far_away(*args, **kwargs):
        r = real_align(*args, **kwargs)
        r.transform = SimilarityTransform(translation=(1e7, 1e7))
        return r

    monkeypatch.setattr(mm, "align", far_away)
    m = mm.merge([a, b])
    assert not m.success and "limit" in m.message


def test_three_maps_or_more_get_their_blurred_keypoints_once_ahead(pair, monkeypatch):
    # The hybrid's second look asks for each map's blurred keypoints in most pairs of a
    # fleet: merge finds them once per map with the features (Method.prepare); a pair of
    # maps finds them only if its search asks.
    merge_module = importlib.import_module("gridmerge.merge")
    a, b, _ = pair
    other, _ = samples.negative_pair(5)
    jobs = []
    run = merge_module._run_features

    def recording(job):
        features = run(job)
        jobs.append((job.ahead, features))
        return features

    monkeypatch.setattr(merge_module, "_run_features", recording)
    merge([a, b])
    assert [ahead for ahead, _ in jobs] == [False, False] and all(f.blurred is None for _, f in jobs)
    jobs.clear()
    m = merge([a, b, other])
    assert m.success and [ahead for ahead, _ in jobs] == [True, True, True]
    assert all(f.blurred is not None and len(f.blurred) > 0 for _, f in jobs)
    # Methods that prepare nothing get their keypoints alone.
    job = merge_module._FeatureJob(a, "sift", gridmerge.AlignOptions(), None, True)
    assert run(job).blurred is None


def test_a_fleet_searches_again_with_coarser_keypoints_only_the_pairs_of_maps_left_out(pair, monkeypatch):
    # A fleet's many pairs that do not overlap are not searched twice: its first searches
    # do without the coarser look (AlignOptions.coarse_look), and only the declined pairs of
    # a map the placement leaves out get it, from their first search's result.
    align_module = importlib.import_module("gridmerge.align")
    merge_module = importlib.import_module("gridmerge.merge")
    a, b, _ = pair
    _, other = samples.negative_pair(0)  # another building, 0.3 M pixels of keypoint image
    looked = []
    real = align_module._coarse_look

    def spy(first, *args):
        looked.append(first)
        return real(first, *args)

    monkeypatch.setattr(merge_module, "_coarse_look", spy)
    m = merge([a, b, other])
    assert m.success and len(m.unplaced) == 1
    searched = {(p.i, p.j): p.result for p in m.pairs}
    assert searched[(0, 1)].success and "coarse_look" not in searched[(0, 1)].details
    assert len(looked) == 2 and all(not r.success for r in looked)
    for k in ((0, 2), (1, 2)):
        r = searched[k]
        assert not r.success and r.details["coarse_look"]["pixels"] == 200_000
    # Off: nothing searched again.
    looked.clear()
    off = merge([a, b, other], options=gridmerge.AlignOptions(coarse_look=0))
    assert not looked and all("coarse_look" not in p.result.details for p in off.pairs)

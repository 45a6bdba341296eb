import numpy as np
import pytest

from gridmerge import samples
from gridmerge.align import full_to_crop, working_maps
from gridmerge.correlate import correlation_hypotheses, match_rotation
from gridmerge.transforms import SimilarityTransform, corner_error


def _cropped(seed, overlap):
    a, b, truth = samples.robot_pair(seed, overlap=overlap)
    ca, oa, cb, ob = working_maps(a, b)
    return ca, cb, SimilarityTransform(full_to_crop(SimilarityTransform(truth), oa, ob).params)


@pytest.mark.parametrize("seed", [7, 8])
def test_wall_led_weights_find_a_small_overlap_first(seed):
    # Robots whose regions share a tenth of the building: shared free space, weighed
    # as much as the signed product of the first form did, pulls the best peak to poses
    # sharing more explored area; the default weights let the walls lead.
    a, b, truth = _cropped(seed, 0.1)
    scale = [b.resolution / a.resolution]
    led = correlation_hypotheses(a, b, scales=scale)
    seeking = correlation_hypotheses(a, b, scales=scale, free_agreement=0.0625)
    assert corner_error(led[0].transform, truth, b.shape) < 10
    assert corner_error(seeking[0].transform, truth, b.shape) > 10


def test_signed_product_shortcut_matches_the_general_form():
    # free_agreement == free_weight ** 2 takes one product of signed images; a hair away
    # the general two-product form runs: both must rank the same poses.
    a, b, _ = _cropped(0, 0.5)
    scale = [b.resolution / a.resolution]
    short = correlation_hypotheses(a, b, scales=scale, free_agreement=0.0625)
    general = correlation_hypotheses(a, b, scales=scale, free_agreement=0.0625 * (1 + 1e-6))
    assert len(short) == len(general) > 0
    for s, g in zip(short, general):
        np.testing.assert_allclose(s.transform.params, g.transform.params, atol=1e-6)
        assert s.score == pytest.approx(g.score, rel=1e-4)


def test_each_scale_keeps_its_own_hypotheses():
    a, b, _ = _cropped(0, 0.5)
    hyps = correlation_hypotheses(a, b, scales=[1.0, 0.5], max_hypotheses=5)
    assert [h.scale for h in hyps] == [1.0] * 5 + [0.5] * 5
    for part in (hyps[:5], hyps[5:]):
        assert [h.score for h in part] == sorted((h.score for h in part), reverse=True)


def test_the_rotation_right_matches_agree_on_is_voted_among_many_wrong_ones():
    rng = np.random.default_rng(3)
    wrong = rng.uniform(0.0, 360.0, 300)
    right = rng.normal(127.0, 0.7, 25)
    angles = np.concatenate([wrong, right])
    sizes = np.concatenate([rng.uniform(0.3, 3.0, 300), rng.normal(1.5, 0.02, 25)])
    voted = match_rotation(angles, sizes, 1.5)
    assert abs(voted - 127.0) <= 3.0
    # A match turned by half a turn votes for the same rotation modulo 180 degrees.
    flipped = match_rotation(np.concatenate([wrong, right + 180.0]), sizes, 1.5)
    assert flipped == voted
    # Matches of another size ratio do not vote; too few votes give no rotation.
    assert match_rotation(right[:10], np.full(10, 1.5), 1.5) is None
    assert match_rotation(right, np.full(25, 1.5), 0.5) is None


def test_a_cache_keeps_each_rotations_peaks_and_changes_nothing(monkeypatch):
    """With a cache, a later call on the same maps computes only the rotations it has
    not seen; its hypotheses are those of a call without one (copies: callers may tell
    hypotheses apart by identity)."""
    import gridmerge.correlate as correlate

    a, b, _ = samples.robot_pair(0)
    ca, _, cb, _ = working_maps(a, b)
    calls = []
    peaks = correlate._peaks
    monkeypatch.setattr(correlate, "_peaks", lambda *args, **kw: calls.append(1) or peaks(*args, **kw))

    def same(x, y):
        return len(x) == len(y) and all(
            np.array_equal(h.transform.params, k.transform.params) and (h.score, h.rotation_deg, h.scale) == (k.score, k.rotation_deg, k.scale)
            for h, k in zip(x, y))

    cache: dict = {}
    kw = dict(scales=(1.0,), fine_deg=(-1.0, 0.0, 1.0), peaks=6, max_hypotheses=50)
    first = correlation_hypotheses(ca, cb, rotations=[0.0, 90.0], cache=cache, **kw)
    assert len(calls) == 2 * 2 * 3  # two rotations, both half turns, three offsets
    calls.clear()
    more = correlation_hypotheses(ca, cb, rotations=[0.0, 90.0, 33.5], cache=cache, **kw)
    assert len(calls) == 2 * 3  # the new rotation only
    calls.clear()
    assert same(first, correlation_hypotheses(ca, cb, rotations=[0.0, 90.0], **kw))
    assert same(more, correlation_hypotheses(ca, cb, rotations=[0.0, 90.0, 33.5], **kw))
    assert len(calls) == 2 * 2 * 3 + 2 * 3 * 3
    again = correlation_hypotheses(ca, cb, rotations=[0.0, 90.0], cache=cache, **kw)
    assert same(first, again) and not {id(h) for h in first} & {id(h) for h in again}

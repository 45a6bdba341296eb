import numpy as np
import pytest

from gridmerge import samples
from gridmerge.align import full_to_crop, working_maps
from gridmerge.correlate import correlation_hypotheses
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

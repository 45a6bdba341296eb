import math

import numpy as np
import pytest

from gridmerge.estimate import paper_consensus, ransac, similarity_hypotheses
from gridmerge.transforms import AffineTransform, ScaledRotationTransform, SimilarityTransform, corner_error


def _data(seed, n=120, outliers=0.5, noise=0.3):
    rng = np.random.default_rng(seed)
    truth = SimilarityTransform(rotation=math.radians(30), scale=0.95, translation=(-86, -36))
    src = rng.uniform(0, 600, (n, 2))
    dst = truth(src) + rng.normal(0, noise, (n, 2))
    bad = rng.random(n) < outliers
    dst[bad] = rng.uniform(-200, 600, (bad.sum(), 2))
    return truth, src, dst, ~bad


@pytest.mark.parametrize("seed", range(3))
def test_ransac_finds_the_inliers_among_half_outliers(seed):
    truth, src, dst, good = _data(seed)
    model, inl = ransac((src, dst), SimilarityTransform, 2, 2.0, rng=seed)
    assert isinstance(model, SimilarityTransform)
    assert corner_error(model, truth, (600, 600)) < 0.5
    assert (inl == good).mean() > 0.97


def test_ransac_is_reproducible_for_a_seed():
    _, src, dst, _ = _data(7, outliers=0.7)
    m1, i1 = ransac((src, dst), SimilarityTransform, 2, 2.0, rng=11)
    m2, i2 = ransac((src, dst), SimilarityTransform, 2, 2.0, rng=11)
    assert m1 == m2 and (i1 == i2).all()


def test_ransac_with_too_few_points_returns_none():
    model, inl = ransac((np.zeros((1, 2)), np.zeros((1, 2))), SimilarityTransform, 2, 1.0, rng=0)
    assert model is None and inl.tolist() == [False]


def test_ransac_respects_model_validity():
    _, src, dst, _ = _data(1)
    model, _ = ransac((src, dst), SimilarityTransform, 2, 2.0, rng=0, is_model_valid=lambda m: m.scale > 5)
    assert model is None or model.scale > 5


def test_ransac_works_for_other_models():
    rng = np.random.default_rng(0)
    truth = AffineTransform([[1.1, 0.2, 5], [-0.1, 0.9, 3]])
    src = rng.uniform(0, 300, (60, 2))
    dst = truth(src)
    dst[:20] += rng.uniform(50, 100, (20, 2))
    model, inl = ransac((src, dst), AffineTransform, 3, 1.0, rng=0)
    np.testing.assert_allclose(model.params, truth.params, atol=1e-6)
    assert inl.sum() == 40


def test_paper_consensus_recovers_the_five_parameters():
    rng = np.random.default_rng(2)
    truth = ScaledRotationTransform.from_parameters(-86, -36, math.radians(30), 0.95, 0.95)
    src = rng.uniform(0, 500, (80, 2))
    dst = truth(src) + rng.normal(0, 0.2, src.shape)
    dst[:30] = rng.uniform(0, 500, (30, 2))  # wrong matches
    model, report = paper_consensus(src, dst, rng=0)
    dx, dy, th, sx, sy = model.parameters
    assert abs(math.degrees(th) - 30) < 0.1
    assert abs(dx + 86) < 0.5 and abs(dy + 36) < 0.5
    assert abs(sx - 0.95) < 2e-3 and abs(sy - 0.95) < 2e-3
    assert report.cluster_size >= 10 and report.samples > report.cluster_size


def test_paper_consensus_sees_anisotropic_scale():
    rng = np.random.default_rng(5)
    truth = ScaledRotationTransform.from_parameters(12, -7, 0.4, 0.8, 1.2)
    src = rng.uniform(0, 400, (40, 2))
    model, _ = paper_consensus(src, truth(src), rng=0)
    np.testing.assert_allclose(model.parameters, truth.parameters, atol=1e-6)


def test_paper_consensus_needs_three_points():
    model, report = paper_consensus(np.zeros((2, 2)), np.zeros((2, 2)), rng=0)
    assert model is None and report.samples == 0


def test_keypoint_hypotheses_from_single_matches():
    truth, src, dst, good = _data(4, n=200, outliers=0.8, noise=0.3)
    rng = np.random.default_rng(4)
    # Orientation and scale of each match: right (with a few degrees of noise) for the
    # inliers, random for the outliers.
    angle = np.where(good, truth.rotation + rng.normal(0, math.radians(3), 200), rng.uniform(-math.pi, math.pi, 200))
    scale = np.where(good, 0.95 * np.exp(rng.normal(0, 0.05, 200)), np.exp(rng.uniform(-1, 1, 200)))
    hyps = similarity_hypotheses(src, dst, angle, scale, threshold=2.0)
    best = hyps[0]
    assert corner_error(best.transform, truth, (600, 600)) < 0.5
    assert best.support >= 0.9 * good.sum()
    assert all(h.support <= best.support for h in hyps)
    # Hypotheses are distinct transforms.
    for h in hyps[1:]:
        assert corner_error(h.transform, best.transform, (600, 600)) > 1.0


def test_proposal_scores_count_as_the_plain_formula():
    from gridmerge.estimate import _proposal_scores

    rng = np.random.default_rng(3)
    n = 700
    src = rng.uniform(0, 800, (n, 2))
    truth = SimilarityTransform(rotation=0.4, scale=1.1, translation=(20, -30))
    dst = truth(src) + rng.normal(0, 1.5, (n, 2))
    dst[::3] = rng.uniform(0, 800, (len(dst[::3]), 2))
    angle = 0.4 + rng.normal(0, 0.03, n)
    scale = 1.1 * np.exp(rng.normal(0, 0.02, n))
    cand = np.arange(0, n, 2)
    cos, sin = np.cos(angle[cand]) * scale[cand], np.sin(angle[cand]) * scale[cand]
    tx = dst[cand, 0] - (cos * src[cand, 0] - sin * src[cand, 1])
    ty = dst[cand, 1] - (sin * src[cand, 0] + cos * src[cand, 1])
    growth = 0.06 * scale[cand]
    px = cos[:, None] * src[None, :, 0] - sin[:, None] * src[None, :, 1] + tx[:, None]
    py = sin[:, None] * src[None, :, 0] + cos[:, None] * src[None, :, 1] + ty[:, None]
    err = np.hypot(px - dst[None, :, 0], py - dst[None, :, 1])
    dist = np.hypot(src[None, :, 0] - src[cand, None, 0], src[None, :, 1] - src[cand, None, 1])
    expect = (err < 3.0 + growth[:, None] * dist).sum(1)
    for block in (1, 7, 32, 1000):
        got = _proposal_scores(src, dst, cand, cos, sin, tx, ty, growth, 3.0, block)
        np.testing.assert_array_equal(got, expect)


def _scene(seed, n_b=500, size=1000.0):
    rng = np.random.default_rng(seed)
    xy_b = rng.uniform(0, size, (n_b, 2))
    t = SimilarityTransform(rotation=0.4, scale=1.1, translation=(60.0, -25.0))
    return rng, xy_b, t, t(xy_b) + rng.normal(0, 1.0, (n_b, 2))


def _random_pairs(rng, n_a, n_b, k):
    """Each of a's keypoints matched to ``k`` of b's at random (uninformative descriptors)."""
    return np.array([(i, j) for i in range(n_a) for j in rng.choice(n_b, k, replace=False)])


@pytest.mark.parametrize("seed", range(5))
def test_match_evidence_of_random_matches_stays_at_chance_level(seed):
    from gridmerge.estimate import match_evidence

    rng, xy_b, t, xy_a = _scene(seed)
    e = match_evidence(xy_a, xy_b, _random_pairs(rng, len(xy_a), len(xy_b), 3), t)
    # About what chance gives: a few agreeing keypoints, insignificant.
    assert e.expected > 1.0
    assert e.significance < 3.0


def test_match_evidence_grows_with_the_right_matches_and_ignores_other_poses():
    from gridmerge.estimate import match_evidence

    rng, xy_b, t, xy_a = _scene(7)
    pairs = _random_pairs(rng, len(xy_a), len(xy_b), 3)
    pairs[: 3 * 12 : 3, 1] = np.arange(12)  # 12 of a's keypoints keep their true match
    e = match_evidence(xy_a, xy_b, pairs, t)
    assert e.consistent >= 12 and e.significance > 6
    # Another pose (shifted by 100 px) finds only chance agreement among the same matches.
    other = SimilarityTransform(translation=(100.0, 0.0)) @ t
    assert match_evidence(xy_a, xy_b, pairs, other).significance < 3.0


def test_match_evidence_counts_a_cluster_of_keypoints_once():
    """SIFT puts one keypoint per orientation on a corner, and a repeated object gives a
    tight group of matches: agreeing keypoints within one cell of ``separation`` count once."""
    from gridmerge.estimate import match_evidence

    rng, xy_b, t, xy_a = _scene(3)
    base = _random_pairs(rng, len(xy_a), len(xy_b), 3)
    alone = match_evidence(xy_a, xy_b, np.vstack([base, [[0, 0]]]), t)  # a's first keypoint matched right
    # 9 more keypoints of a on that one, each matched right.
    crowded = np.vstack([xy_a, np.repeat(xy_a[:1], 9, axis=0)])
    extra = np.stack([np.arange(len(xy_a), len(xy_a) + 9), np.zeros(9, int)], axis=1)
    one = match_evidence(crowded, xy_b, np.vstack([base, [[0, 0]], extra]), t)
    assert one.consistent == alone.consistent
    assert one.significance < 3.0


def test_match_evidence_without_matches_is_none():
    from gridmerge.estimate import match_evidence

    e = match_evidence(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2), int), SimilarityTransform())
    assert (e.consistent, e.expected, e.significance) == (0, 0.0, 0.0)


@pytest.mark.parametrize("k, lam", [(0, 2.0), (1, 2.3), (3, 2.3), (12, 2.3), (4, 0.5), (30, 12.0)])
def test_poisson_significance_is_the_upper_tail(k, lam):
    from gridmerge.estimate import _poisson_significance

    tail = 1.0 - sum(math.exp(-lam) * lam**j / math.factorial(j) for j in range(k))
    assert _poisson_significance(k, lam) == pytest.approx(-math.log10(tail), rel=1e-6, abs=1e-9)


def test_neighbour_counts_are_those_of_all_pairs():
    from gridmerge.estimate import _neighbour_counts

    rng = np.random.default_rng(1)
    points, queries = rng.uniform(-50, 300, (3000, 2)), rng.uniform(-80, 330, (500, 2))
    brute = (np.hypot(*(points[None] - queries[:, None]).transpose(2, 0, 1)) <= 8.0).sum(axis=1)
    assert np.array_equal(_neighbour_counts(points, queries, 8.0), brute)


def test_match_evidence_with_orientations_counts_only_matches_that_turn_with_the_pose():
    """With the keypoints' orientations and sizes, a match agrees only when they differ
    by the pose's rotation and scale: true matches gain significance (chance must now
    also get the orientation right), and matches in the right place whose keypoints do
    not turn with the pose do not count."""
    from gridmerge.estimate import match_evidence

    rng, xy_b, t, xy_a = _scene(11)
    n = len(xy_b)
    angle_b = rng.uniform(0, 360, n)
    size_b = rng.uniform(2, 20, n)
    turn = math.degrees(0.4)  # _scene's rotation; its scale is 1.1
    angle_a = (angle_b + turn + rng.normal(0, 3, n)) % 360.0
    size_a = size_b * 1.1
    oriented = {"angles": (angle_a, angle_b), "sizes": (size_a, size_b)}
    pairs = _random_pairs(rng, n, n, 3)
    pairs[: 3 * 8 : 3, 1] = np.arange(8)  # 8 true matches among random ones
    plain = match_evidence(xy_a, xy_b, pairs, t)
    turned = match_evidence(xy_a, xy_b, pairs, t, **oriented)
    assert turned.consistent >= 8 and turned.significance > plain.significance + 3
    # Random matches that never pick a keypoint's true counterpart (one that does agrees
    # in orientation as in position: that is a true match, not chance).
    others = np.array([(i, j) for i in range(n) for j in rng.choice(np.delete(np.arange(n), i), 3, replace=False)])
    assert match_evidence(xy_a, xy_b, others, t, **oriented).significance < 3.0
    # The same places, but b's keypoints turned the other way: nothing agrees.
    wrong = {"angles": ((angle_b - turn) % 360.0, angle_b), "sizes": (size_a, size_b)}
    assert match_evidence(xy_a, xy_b, pairs, t, **wrong).consistent <= 1

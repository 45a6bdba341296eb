"""The baseline methods: m-explore's ``"orb"`` and Carpin's ``"hough"``."""

import json
import math

import cv2
import numpy as np
import pytest

import gridmerge
from gridmerge import OccupancyGrid, align, samples
from gridmerge.align import METHODS
from gridmerge.baselines import (
    HOUGH_MIN_ACCEPTANCE,
    MEXPLORE_CONFIDENCE_THRESHOLD,
    RosGridRenderer,
    best_of_2_nearest,
    hough_spectrum,
    mexplore_confidence,
    mexplore_extractor,
)
from gridmerge.features import Features
from gridmerge.transforms import SimilarityTransform, corner_error


@pytest.fixture(scope="module")
def table1():
    return samples.table1_pair(0)


@pytest.fixture(scope="module")
def robots_37():
    return samples.robot_pair(0, scale=1.0, rotation_deg=37)


@pytest.fixture(scope="module")
def different():
    return samples.negative_pair(0)


def test_registered_as_self_judging_methods():
    assert {"orb", "hough"} <= set(METHODS)
    assert METHODS["orb"].verified is False and METHODS["hough"].verified is False
    assert METHODS["orb"].extractor is not None and METHODS["hough"].extractor is None


# ------------------------------------------------------------------------ orb


def test_ros_renderer_is_the_int8_data_as_bytes():
    g = OccupancyGrid(np.array([[0.0, 1.0], [0.5, np.nan]]))
    img, mask = RosGridRenderer()(g)
    assert img.dtype == np.uint8 and mask is None
    assert img.tolist() == [[0, 100], [50, 255]]


def test_orb_features_are_those_of_the_ros_image(robots_37):
    # m-explore runs cv::ORB::create() on the message's bytes: bottom row first.
    a, _, _ = robots_37
    f = mexplore_extractor()(a)
    ros = a.to_ros().view(np.uint8).reshape(a.shape)
    kps, desc = cv2.ORB_create().detectAndCompute(ros, None)
    xy = np.array([k.pt for k in kps])
    xy[:, 1] = a.height - 1 - xy[:, 1]
    d = np.hypot(*(f.xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
    assert len(f) == len(kps) == 500 and f.binary
    assert (d.min(axis=1) < 1e-3).all()
    same = (f.descriptors == desc[d.argmin(axis=1)]).all(axis=1)
    assert same.mean() > 0.98  # the rest differ by float rounding of the flipped keypoints


def test_best_of_2_nearest_ratio_test_both_ways():
    rng = np.random.default_rng(0)
    d = rng.integers(0, 256, (20, 32), dtype=np.uint8)
    pairs = best_of_2_nearest(d, d[::-1].copy())
    assert sorted(map(tuple, pairs.tolist())) == [(i, 19 - i) for i in range(20)]
    # Two identical candidates: the ratio test rejects both directions.
    assert len(best_of_2_nearest(d[:1].repeat(2, 0), d[:1].repeat(2, 0))) == 0
    assert len(best_of_2_nearest(d[:1], d)) == 0  # no second neighbour, no match


def _constructed(n_inliers: int, n_outliers: int):
    """Two fully known maps and hand-made features: b's inlier keypoints moved by a known similarity."""
    rng = np.random.default_rng(1)
    truth = SimilarityTransform(rotation=math.radians(20), translation=(30.0, -10.0))
    n = n_inliers + n_outliers
    xb = rng.uniform(20, 180, (n, 2))
    xa = truth(xb)
    xa[n_inliers:] += rng.uniform(40, 80, (n_outliers, 2)) * rng.choice([-1, 1], (n_outliers, 2))
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)

    def feats(xy):
        return Features(xy, np.full(len(xy), 31.0), np.zeros(len(xy)), np.ones(len(xy)), desc.copy(), binary=True)

    grid = OccupancyGrid(np.zeros((200, 200)))
    return grid, feats(xa), feats(xb), truth


@pytest.mark.parametrize("n_inliers, n_outliers", [(20, 10), (10, 30)])
def test_orb_confidence_is_m_explores(n_inliers, n_outliers):
    grid, fa, fb, truth = _constructed(n_inliers, n_outliers)
    r = align(grid, grid, method="orb", features=(fa, fb))
    matches = n_inliers + n_outliers
    expected = n_inliers / (8 + 0.3 * matches)
    assert r.matches == matches and r.inliers == n_inliers
    assert r.confidence == pytest.approx(expected) == pytest.approx(mexplore_confidence(n_inliers, matches))
    assert r.details["mexplore_confidence"] == pytest.approx(expected)
    assert r.success == (expected >= MEXPLORE_CONFIDENCE_THRESHOLD)
    assert corner_error(r.candidate, truth, grid.shape) < 0.01
    if not r.success:
        assert r.transform is None and "confidence" in r.message


def test_orb_needs_six_matches():
    grid, fa, fb, _ = _constructed(5, 0)
    r = align(grid, grid, method="orb", features=(fa, fb))
    assert not r.success and r.candidate is None and r.matches == 5
    assert r.details["mexplore_confidence"] == 0.0


def test_orb_recovers_table1(table1):
    a, b, truth = table1
    r = align(a, b, method="orb")
    assert r.success and r.method == "orb"
    assert isinstance(r.transform, SimilarityTransform)
    assert corner_error(r.transform, truth, b.shape) < 3.0
    assert r.confidence >= MEXPLORE_CONFIDENCE_THRESHOLD
    assert r.confidence == pytest.approx(mexplore_confidence(r.inliers, r.matches))


def test_orb_declines_robot_pair_by_its_own_threshold(robots_37):
    # What m-explore really does here: the right transform, but fewer inliers than its
    # default estimation_confidence = 1.0 asks for.
    a, b, truth = robots_37
    r = align(a, b, method="orb")
    assert not r.success and r.transform is None
    assert 0 < r.confidence < MEXPLORE_CONFIDENCE_THRESHOLD
    assert f"{r.confidence:.2f}" in r.message
    assert corner_error(r.candidate, truth, b.shape) < 5.0


# ---------------------------------------------------------------------- hough


def test_hough_spectrum_turns_with_the_map():
    rng = np.random.default_rng(2)
    walls = np.concatenate([np.stack([np.arange(200.0), np.full(200, 40.0)], 1), np.stack([np.full(120, 10.0), np.arange(120.0)], 1), rng.uniform(0, 200, (30, 2))])
    th, hs = hough_spectrum(walls, theta_step_deg=1.0)
    turned = SimilarityTransform(rotation=math.radians(30))(walls)
    _, hs30 = hough_spectrum(turned, theta_step_deg=1.0)
    assert len(th) == 180 and hs.max() == 1.0
    assert np.corrcoef(np.roll(hs, 30), hs30)[0, 1] > 0.9


def test_hough_recovers_rotation_and_translation(robots_37):
    a, b, truth = robots_37
    r = align(a, b, method="hough")
    assert r.success and r.method == "hough"
    assert type(r.transform) is SimilarityTransform and r.transform.scale == pytest.approx(1.0, abs=1e-12)
    assert r.rotation_deg == pytest.approx(37.0, abs=0.5)
    assert corner_error(r.transform, truth, b.shape) < 3.0
    assert r.confidence == pytest.approx(r.details["acceptance_index"]) and r.confidence >= HOUGH_MIN_ACCEPTANCE
    # The index it decided by is Birk & Carpin's, as gridmerge's verification computes it.
    assert r.acceptance_index == pytest.approx(r.confidence, abs=1e-4)


def test_hough_does_not_handle_scale(table1):
    a, b, truth = table1  # scale 0.95
    r = align(a, b, method="hough")
    assert not r.success and r.candidate.scale == pytest.approx(1.0)
    assert r.confidence < HOUGH_MIN_ACCEPTANCE and "acceptance index" in r.message


# -------------------------------------------------------------- both methods


@pytest.mark.parametrize("method", ["orb", "hough"])
def test_declines_different_buildings(method, different):
    a, b = different
    r = align(a, b, method=method)
    assert not r.success and r.transform is None and r.message.startswith("declined")


@pytest.mark.parametrize("method", ["orb", "hough"])
@pytest.mark.parametrize("blank", ["unknown", "free"])
def test_declines_blank_maps(method, blank, robots_37):
    a, _, _ = robots_37
    empty = OccupancyGrid(np.full((120, 160), np.nan if blank == "unknown" else 0.0))
    for x, y in ((empty, a), (a, empty), (empty, empty)):
        r = align(x, y, method=method)
        assert not r.success and r.transform is None and r.message


def test_hough_hypotheses_sharing_no_cell_have_no_index(monkeypatch, robots_37):
    # Birk & Carpin's index is undefined where the maps share no known cell: such a
    # hypothesis is not ranked, and its index in the details is None (JSON null), not NaN.
    import gridmerge.baselines as baselines

    monkeypatch.setattr(baselines, "acceptance_index", lambda p, q: (math.nan, 0, 0))
    a, b, _ = robots_37
    r = align(a, b, method="hough")
    assert not r.success and r.message.startswith("declined: no hypothesis shares")
    hyps = r.details["hypotheses"]
    assert hyps and all(h["acceptance_index"] is None for h in hyps)
    json.dumps(r.details, allow_nan=False, default=float)


@pytest.mark.parametrize("method", ["orb", "hough"])
def test_deterministic(method, robots_37):
    a, b, _ = robots_37
    r1, r2 = align(a, b, method=method, rng=3), align(a, b, method=method, rng=3)
    assert np.array_equal(r1.candidate.matrix, r2.candidate.matrix)
    assert r1.confidence == r2.confidence and r1.success == r2.success
    json.dumps(r1.to_dict())  # details are JSON-ready


def test_inputs_untouched(robots_37):
    a, b, _ = robots_37
    before = a.data.copy(), b.data.copy()
    for method in ("orb", "hough"):
        align(a, b, method=method)
    assert np.array_equal(a.data, before[0], equal_nan=True) and np.array_equal(b.data, before[1], equal_nan=True)


def test_command_line_method(tmp_path, capsys):
    from gridmerge.cli.main import main

    samples.write_sample(tmp_path, "table1")
    code = main(["align", str(tmp_path / "a.yaml"), str(tmp_path / "b.yaml"), "--method", "orb", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0 and out["success"] and out["method"] == "orb"
    assert gridmerge.align  # the package import registered the methods

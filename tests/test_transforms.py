import math

import numpy as np
import pytest

from gridmerge import OccupancyGrid
from gridmerge.transforms import (
    AffineTransform,
    FailedEstimation,
    ScaledRotationTransform,
    SimilarityTransform,
    corner_error,
    metric_to_pixel,
    pixel_to_metric,
)

RNG = np.random.default_rng(3)
SRC = RNG.uniform(-200, 400, (30, 2))


@pytest.mark.parametrize(
    "truth",
    [
        SimilarityTransform(rotation=math.radians(30), scale=0.95, translation=(-86, -36)),
        ScaledRotationTransform(rotation=-1.2, scale=(0.9, 1.3), translation=(4, 7)),
        AffineTransform([[1.1, 0.2, 3], [-0.1, 0.8, -4]]),
    ],
)
def test_from_estimate_recovers_exact_transforms(truth):
    est = type(truth).from_estimate(SRC, truth(SRC))
    assert est
    np.testing.assert_allclose(est.params, truth.params, atol=1e-8)
    np.testing.assert_allclose(est.residuals(SRC, truth(SRC)), 0, atol=1e-6)


def test_least_squares_with_noise_beats_the_noise():
    truth = SimilarityTransform(rotation=0.4, scale=1.5, translation=(10, -3))
    dst = truth(SRC) + RNG.normal(0, 0.5, SRC.shape)
    est = SimilarityTransform.from_estimate(SRC, dst)
    assert corner_error(est, truth, (600, 600)) < 1.0


def test_paper_five_parameters_from_three_points():
    truth = ScaledRotationTransform.from_parameters(-86, -36, math.radians(30), 0.95, 0.95)
    est = ScaledRotationTransform.from_estimate(SRC[:3], truth(SRC[:3]))
    np.testing.assert_allclose(est.parameters, [-86, -36, math.radians(30), 0.95, 0.95], atol=1e-9)


@pytest.mark.parametrize("cls", [AffineTransform, SimilarityTransform, ScaledRotationTransform])
def test_failures_are_falsy_with_a_reason(cls):
    line = np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]])
    same = np.zeros((3, 2))
    for src in (line, same) if cls is not SimilarityTransform else (same,):
        r = cls.from_estimate(src, src + 1)
        assert isinstance(r, FailedEstimation) and not r and r.message
    assert not cls.from_estimate(SRC[:1], SRC[:1])
    bad = SRC[:5].copy()
    bad[0, 0] = np.nan
    assert not cls.from_estimate(bad, SRC[:5])


def test_similarity_refuses_shear_and_reflection():
    with pytest.raises(ValueError):
        SimilarityTransform([[1, 0.2, 0], [0, 1, 0]])
    with pytest.raises(ValueError):
        SimilarityTransform([[1, 0, 0], [0, -1, 0]])


def test_inverse_and_composition():
    t = SimilarityTransform(rotation=0.7, scale=2.0, translation=(5, 6))
    u = SimilarityTransform(rotation=-0.2, scale=0.5, translation=(-1, 3))
    np.testing.assert_allclose(t.inverse(t(SRC)), SRC, atol=1e-9)
    np.testing.assert_allclose((t @ u)(SRC), t(u(SRC)), atol=1e-9)
    assert isinstance(t.inverse, SimilarityTransform)
    assert math.isclose(t.inverse.scale, 0.5)


def test_properties():
    t = ScaledRotationTransform(rotation=0.3, scale=(2.0, 3.0), translation=(1, 2))
    assert math.isclose(t.rotation, 0.3)
    assert np.allclose(t.scale_xy, (2.0, 3.0))
    assert math.isclose(t.scale, math.sqrt(6.0))
    assert t.translation.tolist() == [1, 2]
    d = t.to_dict()
    assert d["kind"] == "ScaledRotationTransform" and math.isclose(d["rotation_deg"], math.degrees(0.3))
    assert AffineTransform.from_dict(d) == t


def test_pixel_metric_round_trip_and_meaning():
    # Map b is map a shifted: b's pixel (x, y) is a's pixel (x + 10, y + 4), same resolution.
    a = OccupancyGrid(np.zeros((50, 60)), resolution=0.1, origin=(1.0, 2.0, 0.0))
    b = OccupancyGrid(np.zeros((30, 20)), resolution=0.1, origin=(0.0, 0.0, 0.0))
    pix = SimilarityTransform(translation=(10, 4))
    metric = pixel_to_metric(pix, b, a)
    assert isinstance(metric, SimilarityTransform)
    # A cell centre seen in both maps has the same metric coordinates after the transform.
    p_b = np.array([[3.0, 7.0]])
    np.testing.assert_allclose(metric(b.pixel_to_metric(p_b)), a.pixel_to_metric(pix(p_b)))
    assert math.isclose(metric.scale, 1.0) and abs(metric.rotation) < 1e-12
    back = metric_to_pixel(metric, b, a)
    np.testing.assert_allclose(back.params, pix.params, atol=1e-9)


def test_metric_rotation_sign_follows_ros():
    # Rotating b's image by +90 deg in pixel terms (x right, y down) is a -90 deg yaw in
    # ROS terms (x right, y up).
    a = OccupancyGrid(np.zeros((10, 10)), resolution=1.0)
    b = OccupancyGrid(np.zeros((10, 10)), resolution=1.0)
    pix = SimilarityTransform(rotation=math.pi / 2, translation=(9, 0))
    metric = pixel_to_metric(pix, b, a)
    assert math.isclose(metric.rotation, -math.pi / 2)


def test_metric_scale_accounts_for_resolutions():
    # b at 0.1 m/cell, a at 0.05 m/cell: one b cell spans two a cells, and the metric
    # frames agree (scale 1) when the pixel scale is 2.
    a = OccupancyGrid(np.zeros((100, 100)), resolution=0.05)
    b = OccupancyGrid(np.zeros((50, 50)), resolution=0.1)
    metric = pixel_to_metric(SimilarityTransform(scale=2.0, translation=(0.5, 0.5)), b, a)
    assert math.isclose(metric.scale, 1.0)
    np.testing.assert_allclose(metric.translation, [0, 0], atol=1e-12)

"""Properties that hold for every input: transforms, frames, file round trips, fusion."""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from gridmerge import OccupancyGrid, load_map, save_map
from gridmerge.fuse import FUSION_RULES, fuse_values, warp_values
from gridmerge.transforms import AffineTransform, ScaledRotationTransform, SimilarityTransform, metric_to_pixel, pixel_to_metric

def examples(n: int):
    """``n`` examples, times GRIDMERGE_HYPOTHESIS_SCALE (e.g. 20 to search harder locally)."""
    return settings(max_examples=max(1, int(n * float(os.environ.get("GRIDMERGE_HYPOTHESIS_SCALE", "1")))))


angles = st.floats(-math.pi, math.pi)
scales = st.floats(0.05, 20.0)
offsets = st.floats(-1e4, 1e4)
resolutions = st.floats(1e-3, 10.0)
shapes = st.tuples(st.integers(1, 40), st.integers(1, 40))


@st.composite
def similarities(draw):
    return SimilarityTransform(rotation=draw(angles), scale=draw(scales), translation=(draw(offsets), draw(offsets)))


@st.composite
def affines(draw):
    """Well-conditioned affine transforms (singular values within 1:100)."""
    m = draw(hnp.arrays(np.float64, (2, 2), elements=st.floats(-5, 5)))
    s = np.linalg.svd(m, compute_uv=False)
    assume(s[-1] > 0.05 and s[0] / s[-1] < 100)
    t = [draw(offsets), draw(offsets)]
    return AffineTransform(np.array([[m[0, 0], m[0, 1], t[0]], [m[1, 0], m[1, 1], t[1]], [0, 0, 1.0]]))


@st.composite
def five_parameter(draw):
    return ScaledRotationTransform.from_parameters(draw(offsets), draw(offsets), draw(angles), draw(scales), draw(scales))


@st.composite
def grids(draw, shape=shapes):
    h, w = draw(shape)
    return OccupancyGrid(np.zeros((h, w)), resolution=draw(resolutions), origin=(draw(offsets), draw(offsets), draw(angles)))


def _close(m1: np.ndarray, m2: np.ndarray, scale: float = 1.0) -> bool:
    return bool(np.allclose(m1, m2, rtol=1e-9, atol=1e-9 * max(1.0, scale)))


# ---------------------------------------------------------------- transforms
@examples(150)
@given(st.one_of(similarities(), affines(), five_parameter()))
def test_transform_composed_with_its_inverse_is_identity(t):
    size = float(np.abs(t.params).max())
    assert _close((t @ t.inverse).params, np.eye(3), size)
    assert _close((t.inverse @ t).params, np.eye(3), size)
    assert _close(t.inverse.inverse.params, t.params, size)


@examples(100)
@given(similarities(), similarities(), hnp.arrays(np.float64, (5, 2), elements=st.floats(-1e3, 1e3)))
def test_composition_applies_right_to_left(s, t, pts):
    expected = s(t(pts))
    assert np.allclose((s @ t)(pts), expected, rtol=1e-9, atol=1e-6 * max(1.0, float(np.abs(expected).max())))
    assert isinstance(s @ t, SimilarityTransform)


# ------------------------------------------------------------ pixel <-> metric
@examples(150)
@given(grids(), hnp.arrays(np.float64, (6, 2), elements=st.floats(-100, 100)))
def test_grid_pixel_metric_round_trip(grid, px):
    back = grid.metric_to_pixel(grid.pixel_to_metric(px))
    assert np.allclose(back, px, rtol=0, atol=1e-6)


@examples(100)
@given(grids())
def test_lower_left_cell_centre_is_half_a_cell_from_the_origin(grid):
    ox, oy, yaw = grid.origin
    r = grid.resolution
    expected = np.array([ox, oy]) + r / 2 * np.array([math.cos(yaw) - math.sin(yaw), math.sin(yaw) + math.cos(yaw)])
    assert np.allclose(grid.pixel_to_metric([[0, grid.height - 1]])[0], expected, rtol=1e-9, atol=1e-7)


@examples(100)
@given(grids(), grids(), similarities())
def test_transform_pixel_metric_round_trip(src, dst, t):
    m = pixel_to_metric(t, src, dst)
    back = metric_to_pixel(m, src, dst)
    size = float(np.abs(t.params).max())
    assert np.allclose(back.params, t.params, rtol=1e-6, atol=1e-6 * max(1.0, size))
    assert isinstance(m, SimilarityTransform)
    # Moving a point in pixels then to metres equals moving it in metres.
    p = np.array([[0.0, 0.0], [src.width - 1.0, src.height - 1.0]])
    lhs = dst.pixel_to_metric(t(p))
    rhs = m(src.pixel_to_metric(p))
    assert np.allclose(lhs, rhs, rtol=1e-6, atol=1e-6 * max(1.0, float(np.abs(lhs).max())))


@examples(50)
@given(grids())
def test_identity_between_a_map_and_itself(grid):
    m = pixel_to_metric(SimilarityTransform(), grid, grid)
    assert np.allclose(m.params, np.eye(3), atol=1e-6)


# ------------------------------------------------------------------ file I/O
names = st.text(alphabet=st.sampled_from(list("abcXYZ019 _-.:#'\"é地")), min_size=1, max_size=12).filter(
    lambda s: s.strip(" .") == s and s not in (".", "..")
)


@st.composite
def trinary_grids(draw):
    h, w = draw(shapes)
    data = draw(hnp.arrays(np.float32, (h, w), elements=st.sampled_from([0.0, 1.0, math.nan])))
    return OccupancyGrid(data, resolution=draw(resolutions), origin=(draw(offsets), draw(offsets), draw(angles)))


@st.composite
def percent_grids(draw):
    h, w = draw(shapes)
    values = draw(hnp.arrays(np.int16, h * w, elements=st.integers(-1, 100)))
    return OccupancyGrid.from_ros(values, w, h, draw(resolutions), (draw(offsets), draw(offsets), draw(angles)))


@examples(60)
@given(trinary_grids(), names, st.sampled_from(["pgm", "png"]))
def test_trinary_save_load_round_trip(grid, name, fmt):
    with tempfile.TemporaryDirectory() as tmp:
        path = save_map(grid, Path(tmp) / f"{name}.yaml", image_format=fmt)
        loaded = load_map(path)
    assert loaded == grid  # data, resolution and origin exactly


@examples(60)
@given(percent_grids(), st.sampled_from(["pgm", "png"]))
def test_raw_save_load_round_trip(grid, fmt):
    with tempfile.TemporaryDirectory() as tmp:
        path = save_map(grid, Path(tmp) / "m.yaml", mode="raw", image_format=fmt)
        loaded = load_map(path)
    assert loaded == grid


@examples(60)
@given(
    st.tuples(st.integers(1, 30), st.integers(1, 30)).flatmap(
        lambda s: hnp.arrays(np.float32, s, elements=st.one_of(st.floats(0, 1, width=32), st.just(math.nan)))
    ),
    resolutions,
)
def test_npy_save_load_round_trip(data, resolution):
    grid = OccupancyGrid(data, resolution=resolution)
    with tempfile.TemporaryDirectory() as tmp:
        path = save_map(grid, Path(tmp) / "m.npy")
        loaded = load_map(path, resolution=resolution)
    assert loaded == grid


# -------------------------------------------------------------------- fusion
probabilities = st.one_of(st.floats(0, 1, width=32), st.just(math.nan))


def layers(n):
    return st.tuples(st.integers(1, 8), st.integers(1, 8)).flatmap(
        lambda s: st.lists(hnp.arrays(np.float32, s, elements=probabilities), min_size=n, max_size=n)
    )


@examples(100)
@given(layers(2), st.sampled_from(FUSION_RULES))
def test_fusion_of_two_layers_is_commutative(pair, rule):
    a, b = pair
    np.testing.assert_array_equal(fuse_values([a, b], rule), fuse_values([b, a], rule))


@examples(100)
@given(st.integers(2, 4).flatmap(layers), st.sampled_from(FUSION_RULES), st.randoms(use_true_random=False))
def test_fusion_is_symmetric_in_its_layers(stack, rule, rnd):
    shuffled = list(stack)
    rnd.shuffle(shuffled)
    np.testing.assert_allclose(fuse_values(stack, rule), fuse_values(shuffled, rule), rtol=1e-5, atol=1e-6)


@examples(100)
@given(st.integers(1, 4).flatmap(layers), st.sampled_from(FUSION_RULES))
def test_fusion_never_invents_or_loses_knowledge(stack, rule):
    out = fuse_values(stack, rule)
    known = np.stack([~np.isnan(l) for l in stack])
    np.testing.assert_array_equal(~np.isnan(out), known.any(0))  # unknown stays unknown, known stays known
    finite = out[~np.isnan(out)]
    assert ((finite >= 0) & (finite <= 1)).all()
    # A cell known by one layer only keeps that layer's value exactly.
    single = known.sum(0) == 1
    only = np.where(known, np.stack(stack), 0).sum(0)
    np.testing.assert_array_equal(out[single], only[single])


@examples(60)
@given(layers(1), st.sampled_from(["average", "max"]))
def test_fusing_a_layer_with_itself_changes_nothing(stack, rule):
    (a,) = stack
    np.testing.assert_array_equal(fuse_values([a, a], rule), fuse_values([a], rule))


@examples(60)
@given(layers(1), st.sampled_from(["linear", "nearest"]))
def test_identity_warp_keeps_every_cell(stack, interpolation):
    (a,) = stack
    out = warp_values(a, np.eye(3), a.shape, interpolation=interpolation)
    np.testing.assert_array_equal(np.isnan(out), np.isnan(a))
    np.testing.assert_allclose(out[~np.isnan(a)], a[~np.isnan(a)], atol=1e-6)

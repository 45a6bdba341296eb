import math

import numpy as np
import pytest

from gridmerge.fuse import fuse_values, warp_values

N = np.nan
A = np.array([[0.0, 1.0, 0.2, N, 0.9, N]], dtype=np.float32)
B = np.array([[1.0, 1.0, N, 0.3, 0.8, N]], dtype=np.float32)


def test_average_is_eq_9_cell_by_cell():
    out = fuse_values([A, B], "average")
    np.testing.assert_allclose(out[0, :5], [0.5, 1.0, 0.2, 0.3, 0.85], rtol=1e-6)
    assert math.isnan(out[0, 5])


def test_max_rule():
    out = fuse_values([A, B], "max")
    np.testing.assert_allclose(out[0, :5], [1.0, 1.0, 0.2, 0.3, 0.9], rtol=1e-6)
    assert math.isnan(out[0, 5])


def test_logodds_rule():
    out = fuse_values([A, B], "logodds")
    # 0.9 and 0.8: odds 9 and 4 multiply to 36.
    assert math.isclose(out[0, 4], 36 / 37, rel_tol=1e-5)
    # Certain evidence on both sides cancels.
    assert math.isclose(out[0, 0], 0.5, rel_tol=1e-5)
    assert out[0, 1] > 0.999
    # Cells known to one map keep that map's value.
    np.testing.assert_allclose(out[0, 2:4], [0.2, 0.3], rtol=1e-6)
    assert math.isnan(out[0, 5])


@pytest.mark.parametrize("rule", ["average", "logodds", "max"])
def test_rules_are_symmetric_and_keep_unknown(rule):
    np.testing.assert_array_equal(fuse_values([A, B], rule), fuse_values([B, A], rule))
    out = fuse_values([A, B], rule)
    assert np.isnan(out).tolist() == (np.isnan(A) & np.isnan(B)).tolist()


def test_unknown_rule_is_an_error():
    with pytest.raises(ValueError):
        fuse_values([A], "median")


def test_warp_identity_and_integer_shift():
    rng = np.random.default_rng(0)
    data = rng.random((20, 30)).astype(np.float32)
    data[rng.random((20, 30)) < 0.3] = np.nan
    same = warp_values(data, np.eye(3), data.shape)
    np.testing.assert_array_equal(same, data)
    shifted = warp_values(data, [[1, 0, 5], [0, 1, 2]], (22, 35), interpolation="nearest")
    np.testing.assert_array_equal(shifted[2:, 5:], data)
    assert np.isnan(shifted[:2]).all() and np.isnan(shifted[:, :5]).all()


def test_warp_never_spreads_unknown_into_known_values():
    data = np.array([[0.0, 0.0, N, N]] * 4, dtype=np.float32)
    half = warp_values(data, [[1, 0, 0.5], [0, 1, 0]], (4, 4))
    known = ~np.isnan(half)
    # Every known value stays a true mix of known cells (0 here), never pulled by NaN.
    assert (half[known] == 0).all()
    assert known[:, 0].all() and not known[:, 3].any()


@pytest.mark.parametrize("rule", ["average", "logodds", "max"])
def test_layers_are_consumed_one_at_a_time_and_left_alone(rule):
    rng = np.random.default_rng(0)
    layers = []
    for _ in range(4):
        v = rng.random((30, 40)).astype(np.float32)
        v[rng.random(v.shape) < 0.4] = np.nan
        layers.append(v)
    copies = [v.copy() for v in layers]
    # A generator (merge warps each map only when it is asked for the next layer).
    out = fuse_values((v for v in layers), rule)
    np.testing.assert_array_equal(out, fuse_values(list(layers), rule))
    for v, c in zip(layers, copies):
        np.testing.assert_array_equal(v, c)  # inputs are not modified
    known = ~np.isnan(np.stack(layers))
    assert np.array_equal(np.isnan(out), ~known.any(0))
    if rule == "average":
        some = known.any(0)
        expected = np.nansum(np.stack(layers), 0)[some] / known.sum(0)[some]
        np.testing.assert_allclose(out[some], expected, rtol=1e-6)


def test_layers_of_different_shapes_are_refused():
    with pytest.raises(ValueError, match="different shapes"):
        fuse_values([A, np.zeros((2, 2), np.float32)])
    with pytest.raises(ValueError, match="nothing to fuse"):
        fuse_values(iter([]))


def test_quarter_turns_mirrorings_and_shifts_copy_cells_exactly():
    """Transforms that move the cell grid onto itself are carried cell for cell, with
    either interpolation, whatever OpenCV's warps do with round-off (5.1's bilinear
    weights are not exactly 0 and 1 at whole cells)."""
    from gridmerge.fuse import reindexed

    rng = np.random.default_rng(0)
    turns = [np.array(m, float) for m in ([[1, 0], [0, 1]], [[-1, 0], [0, 1]], [[1, 0], [0, -1]], [[-1, 0], [0, -1]],
                                          [[0, 1], [1, 0]], [[0, -1], [1, 0]], [[0, 1], [-1, 0]], [[0, -1], [-1, 0]])]
    for k in range(400):
        h, w = (int(v) for v in rng.integers(1, 12, 2))
        oh, ow = (int(v) for v in rng.integers(1, 12, 2))
        data = rng.random((h, w)).astype(np.float32)
        data[rng.random((h, w)) < 0.2] = np.nan
        a, t = turns[k % 8], rng.integers(-13, 13, 2).astype(float)
        inverse = np.hstack([a, t[:, None]])  # output pixels -> data's pixels
        expected = np.full((oh, ow), np.nan, np.float32)
        for y in range(oh):
            for x in range(ow):
                xi, yi = (a @ [x, y] + t).astype(int)
                if 0 <= xi < w and 0 <= yi < h:
                    expected[y, x] = data[yi, xi]
        np.testing.assert_array_equal(reindexed(data, inverse, (oh, ow)), expected)
        forward = np.vstack([np.hstack([a.T, (-a.T @ t)[:, None]]), [0, 0, 1]])  # data's pixels -> output
        for interpolation in ("linear", "nearest"):
            np.testing.assert_array_equal(warp_values(data, forward, (oh, ow), interpolation=interpolation), expected)
    # Anything else is interpolated as before.
    assert reindexed(np.zeros((3, 3)), [[1, 0, 0.5], [0, 1, 0]], (3, 3)) is None
    assert reindexed(np.zeros((3, 3)), [[2, 0, 0], [0, 1, 0]], (3, 3)) is None
    assert reindexed(np.zeros((3, 3)), [[1, 1, 0], [0, 1, 0]], (3, 3)) is None

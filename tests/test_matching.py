import numpy as np
import pytest

from gridmerge.matching import knn, match_mnn, match_nn, match_smnn, match_snn

RNG = np.random.default_rng(0)
D1 = RNG.random((300, 128), dtype=np.float32)
PERM = RNG.permutation(300)
D2 = D1[PERM] + RNG.normal(0, 0.01, (300, 128)).astype(np.float32)


@pytest.mark.parametrize("method", ["flann", "brute"])
def test_nearest_neighbours_find_the_permutation(method):
    _, idxs = match_nn(D1, D2, method=method)
    inv = np.argsort(PERM)
    assert (idxs[:, 1] == inv[idxs[:, 0]]).mean() > 0.99


def test_ratio_test_drops_ambiguous_matches():
    d2 = np.vstack([D2, D2[:10] + 1e-4])  # ten descriptors now have a twin
    _, idxs = match_snn(D1, d2, ratio=0.8, method="brute")
    inv = np.argsort(PERM)
    twins = set(PERM[:10].tolist())
    assert not twins & set(idxs[:, 0].tolist())
    assert len(idxs) >= 285


def test_mutual_check():
    d2 = D2[:50]
    _, nn = match_nn(D1, d2, method="brute")
    _, mnn = match_mnn(D1, d2, method="brute")
    assert len(nn) == 300 and len(mnn) == 50
    _, smnn = match_smnn(D1, d2, method="brute")
    assert len(smnn) <= len(mnn)


def test_knn_shapes_and_empty_inputs():
    d, i = knn(D1[:5], D2, 3, method="brute")
    assert d.shape == i.shape == (5, 3)
    assert (np.diff(d, axis=1) >= 0).all()
    d, i = knn(D1[:5], D2[:0], 2)
    assert np.isinf(d).all() and (i == -1).all()
    dists, idxs = match_snn(D1[:0], D2)
    assert idxs.shape == (0, 2)


def _direct(d1, d2, k):
    """The k nearest by float64 distances of every pair, ties to the lower index."""
    dist = np.sqrt(((d1[:, None, :].astype(np.float64) - d2[None].astype(np.float64)) ** 2).sum(axis=2))
    order = np.argsort(dist, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(dist, order, axis=1), order


def test_exhaustive_search_is_exact_on_integer_descriptors_and_breaks_ties_by_index(monkeypatch):
    import gridmerge.matching as matching

    rng = np.random.default_rng(3)
    # SIFT-like: integer-valued floats up to 255, where float32 distances are exact.
    d1 = np.round(255 * rng.random((120, 128)) ** 3).astype(np.float32)
    d2 = np.round(255 * rng.random((90, 128)) ** 3).astype(np.float32)
    d2[40] = d2[7]  # a twin: equally near to every descriptor
    d1[3] = d2[7]
    monkeypatch.setattr(matching, "_BLOCK_PAIRS", 1000)  # several blocks of rows
    dist, idx = knn(d1, d2, 3, method="brute")
    want_d, want_i = _direct(d1, d2, 3)
    np.testing.assert_array_equal(idx, want_i)
    np.testing.assert_array_equal(dist, want_d)  # not approximately: exactly
    assert idx[3, 0] == 7 and idx[3, 1] == 40 and dist[3, 0] == dist[3, 1] == 0.0
    # The twins make the nearest ambiguous: the ratio test drops row 3.
    _, pairs = match_snn(d1, d2, ratio=0.8, method="brute")
    assert 3 not in pairs[:, 0]
    # Descriptors that are not integers: compared in float64.
    f1, f2 = d1 / 7.3, d2 / 7.3
    dist, idx = knn(f1, f2, 2, method="brute")
    want_d, want_i = _direct(f1, f2, 2)
    np.testing.assert_array_equal(idx[:, 0], want_i[:, 0])
    np.testing.assert_allclose(dist, want_d, rtol=1e-9)



def test_exhaustive_search_with_one_blas_thread_finds_the_same(monkeypatch):
    # threads=1: the matrix product runs on one BLAS thread (a helper thread of align
    # keeps the other core busy); the neighbours do not change.
    import gridmerge.matching as matching
    from threadpoolctl import threadpool_info

    rng = np.random.default_rng(5)
    d1 = np.round(255 * rng.random((200, 128)) ** 3).astype(np.float32)
    d2 = np.round(255 * rng.random((150, 128)) ** 3).astype(np.float32)
    seen = []
    exhaustive = matching._exhaustive

    def spy(*args):
        seen.append({i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"})
        return exhaustive(*args)

    monkeypatch.setattr(matching, "_exhaustive", spy)
    free = knn(d1, d2, 4, method="brute")
    one = knn(d1, d2, 4, method="brute", threads=1)
    np.testing.assert_array_equal(one[1], free[1])
    np.testing.assert_array_equal(one[0], free[0])
    assert seen[1] <= {1}  # empty when numpy's BLAS is not one threadpoolctl knows
    assert seen[0] == {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}  # restored

def test_flann_is_approximate_where_the_exhaustive_search_is_exact():
    rng = np.random.default_rng(4)
    d1 = np.round(255 * rng.random((400, 128)) ** 4).astype(np.float32)
    d2 = np.round(255 * rng.random((300, 128)) ** 4).astype(np.float32)
    (bd, bi), (fd, fi) = knn(d1, d2, 2, method="brute"), knn(d1, d2, 2, method="flann")
    assert not np.array_equal(bi, fi)
    # FLANN never finds a nearer neighbour than the exhaustive search.
    assert (fd[:, 0] >= bd[:, 0] - 1e-3).all()
    want_d, want_i = _direct(d1, d2, 2)
    np.testing.assert_array_equal(bi, want_i)
    np.testing.assert_array_equal(bd, want_d)


def test_binary_descriptors_use_hamming():
    b1 = RNG.integers(0, 256, (40, 32), dtype=np.uint8)
    b2 = b1[::-1].copy()
    d, idxs = match_nn(b1, b2)
    assert (idxs[:, 1] == 39 - idxs[:, 0]).all() and (d == 0).all()


def test_mismatched_sizes_and_methods_are_errors():
    with pytest.raises(ValueError):
        knn(D1, D2[:, :64])
    with pytest.raises(ValueError):
        knn(D1, D2, method="nope")


def test_features_render_only_the_known_box():
    from gridmerge import OccupancyGrid
    from gridmerge.features import FeatureExtractor, GreyRenderer, _grey

    rng = np.random.default_rng(0)
    d = np.full((300, 400), np.nan)
    d[50:250, 60:330] = (rng.random((200, 270)) < 0.1).astype(float)
    d[100:104, 60:300] = 1.0
    d[70, 70] = 0.37
    grid = OccupancyGrid(d)
    np.testing.assert_array_equal(_grey(grid.data, 127), grid.render())
    fast = FeatureExtractor()(grid)
    slow = FeatureExtractor(renderer=_FullGrey())(grid)  # renders the whole map, then cuts
    np.testing.assert_array_equal(fast.xy, slow.xy)
    np.testing.assert_array_equal(fast.descriptors, slow.descriptors)


class _FullGrey:
    def __call__(self, grid):
        return grid.render(), None


class _Separate:
    """SIFT without its one-pass detect_and_compute: detect, then compute."""

    binary = False

    def __init__(self):
        from gridmerge.features import SIFT

        self._sift = SIFT()

    def detect(self, image, mask=None):
        return self._sift.detect(image, mask)

    def compute(self, image, keypoints):
        return self._sift.compute(image, keypoints)


@pytest.mark.parametrize("cap", [0, 40])
def test_one_pass_sift_finds_what_detect_then_compute_finds(cap):
    from gridmerge import samples
    from gridmerge.features import SIFT, FeatureExtractor

    a, _, _ = samples.robot_pair(0)
    one = FeatureExtractor(SIFT(), max_keypoints=cap)(a)
    two = FeatureExtractor(_Separate(), max_keypoints=cap)(a)
    assert len(one) > (cap or 100) - 1 and one.capped == two.capped == bool(cap)
    np.testing.assert_array_equal(one.xy, two.xy)
    np.testing.assert_array_equal(one.descriptors, two.descriptors)
    np.testing.assert_array_equal(one.angle, two.angle)

import numpy as np

from gridmerge import OccupancyGrid
from gridmerge.verify import despeckle


def test_despeckle_frees_isolated_hits_only():
    d = np.zeros((7, 7))
    d[1, 1] = 1.0  # isolated hit
    d[4, 2:6] = 1.0  # a wall
    d[0, 6] = np.nan
    g = OccupancyGrid(d)
    out = despeckle(g)
    assert out.data[1, 1] == 0.0
    np.testing.assert_array_equal(out.data[4], g.data[4])
    assert np.isnan(out.data[0, 6]) and g.data[1, 1] == 1.0  # input untouched
    clean = OccupancyGrid(np.zeros((3, 3)))
    assert despeckle(clean) is clean

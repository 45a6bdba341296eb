import math

import numpy as np
import pytest

from gridmerge import MapFormatError, OccupancyGrid


def test_data_is_copied_read_only_and_input_untouched():
    src = np.array([[0.0, 1.0], [np.nan, 0.5]])
    before = src.copy()
    g = OccupancyGrid(src)
    assert g.data.dtype == np.float32
    assert not g.data.flags.writeable
    src[0, 0] = 0.7
    assert g.data[0, 0] == 0.0
    np.testing.assert_array_equal(before[1:], src[1:])


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(data=np.zeros((0, 3))), "data"),
        (dict(data=np.zeros(5)), "data"),
        (dict(data=np.full((2, 2), 2.0)), "data"),
        (dict(data=np.full((2, 2), np.inf)), "data"),
        (dict(data=np.zeros((2, 2)), resolution=0), "resolution"),
        (dict(data=np.zeros((2, 2)), resolution=-1), "resolution"),
        (dict(data=np.zeros((2, 2)), resolution=float("nan")), "resolution"),
        (dict(data=np.zeros((2, 2)), origin=(0, 0)), "origin"),
        (dict(data=np.zeros((2, 2)), origin=(0, float("inf"), 0)), "origin"),
    ],
)
def test_invalid_grids_are_refused_naming_the_field(kwargs, field):
    with pytest.raises(MapFormatError) as e:
        OccupancyGrid(**kwargs)
    assert e.value.field == field


def test_ros_round_trip_and_row_order():
    g = OccupancyGrid(np.array([[1.0, np.nan, 0.3], [0.0, 0.0, 0.5]]), resolution=0.1, origin=(1, 2, 0.5))
    ros = g.to_ros()
    assert ros.dtype == np.int8
    assert ros.tolist() == [0, 0, 50, 100, -1, 30]  # bottom row first
    back = OccupancyGrid.from_ros(ros, 3, 2, 0.1, (1, 2, 0.5))
    assert back == g


def test_from_ros_refuses_wrong_length():
    with pytest.raises(MapFormatError, match="width x height"):
        OccupancyGrid.from_ros([0, 0, 0], 2, 2, 0.05)


def test_pixel_metric_frame_follows_ros():
    # 4 rows x 3 columns at 0.5 m, origin at (10, 20) with no yaw.
    g = OccupancyGrid(np.zeros((4, 3)), resolution=0.5, origin=(10.0, 20.0, 0.0))
    # Centre of the lower-left cell (x = 0, y = H - 1) is half a cell from the origin.
    np.testing.assert_allclose(g.pixel_to_metric([[0, 3]]), [[10.25, 20.25]])
    # The top-left cell is H - 1 cells higher.
    np.testing.assert_allclose(g.pixel_to_metric([[0, 0]]), [[10.25, 21.75]])
    xy = np.array([[0.3, 2.7], [2.0, 0.0]])
    np.testing.assert_allclose(g.metric_to_pixel(g.pixel_to_metric(xy)), xy)


def test_origin_yaw_rotates_about_the_origin():
    g = OccupancyGrid(np.zeros((2, 2)), resolution=1.0, origin=(5.0, 0.0, math.pi / 2))
    # Lower-left cell centre is (0.5, 0.5) in the map's axes; yaw 90 deg turns it to (-0.5, 0.5).
    np.testing.assert_allclose(g.pixel_to_metric([[0, 1]]), [[4.5, 0.5]], atol=1e-12)


def test_render_levels():
    g = OccupancyGrid(np.array([[0.0, 1.0, np.nan]]))
    assert g.render().tolist() == [[255, 0, 127]]
    assert g.known.tolist() == [[True, True, False]]
    assert g.occupied().tolist() == [[False, True, False]]
    assert g.free().tolist() == [[True, False, False]]


def test_crop_known_keeps_metric_coordinates():
    d = np.full((10, 12), np.nan)
    d[3:6, 4:9] = 0.0
    g = OccupancyGrid(d, resolution=0.5, origin=(1.0, -2.0, 0.4))
    assert g.known_bounds() == (4, 3, 9, 6)
    assert g.known_bounds(2) == (2, 1, 11, 8)
    cut, off = g.crop_known(1)
    assert cut.shape == (5, 7) and off.tolist() == [3, 2]
    p = np.array([[0.0, 0.0], [6.0, 4.0]])
    np.testing.assert_allclose(cut.pixel_to_metric(p), g.pixel_to_metric(p + off))
    empty = OccupancyGrid(np.full((3, 3), np.nan))
    assert empty.known_bounds() is None and empty.crop_known()[0] is empty

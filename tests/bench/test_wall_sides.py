"""``benchmarks/wall_sides.py``: walls two maps saw from opposite sides."""

from __future__ import annotations

import numpy as np
import pytest

from gridmerge import OccupancyGrid


@pytest.fixture(scope="module")
def sides(benchmark_script):
    return benchmark_script("wall_sides")


def _room(free_rows: slice, wall_row: int, shape=(60, 80)) -> OccupancyGrid:
    """Free cells in ``free_rows`` (columns 10-69), a wall line on ``wall_row``, unknown elsewhere."""
    data = np.full(shape, np.nan)
    data[free_rows, 10:70] = 0.0
    data[wall_row, 10:70] = 1.0
    return OccupancyGrid(data)


def test_gaps_measure_the_cells_between_free_regions(sides):
    free = np.zeros((5, 12), bool)
    free[:, :3] = True
    free[:, 7:] = True
    g = sides.gaps(free)
    assert g[2, 3] == 4 and g[2, 6] == 4  # 4 cells between the two free regions along the row
    one_sided = np.zeros((5, 12), bool)
    one_sided[:, :3] = True
    assert np.isinf(sides.gaps(one_sided)[2, 5])


def test_faces_laid_on_each_other_are_contacts_and_the_truth_keeps_them_apart(sides):
    # a: free above its wall (row 30); b: free below its wall (row 30 of b). A thick wall:
    # at the truth b lies 8 rows lower (its face 8 cells below a's).
    a = _room(slice(5, 30), 30)
    b = _room(slice(31, 55), 30)
    on_top = np.eye(3)
    matched, contact, normals = sides.contacts(a, b, on_top)
    assert matched.sum() == 60 and contact.sum() == 60
    assert np.allclose(normals.mean(axis=0), [0.0, -1.0], atol=0.05)  # a's free space lies above (-y)

    class Case:
        truth = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 8.0], [0.0, 0.0, 1.0]])

    Case.a, Case.b = a, b
    rec = {"estimate": {"matrix": on_top[:2].tolist()}}
    line = sides.measure(rec, Case(), tolerance=2, thin=4)
    assert line["contacts"] == 60 and line["share"] == 1.0
    assert line["shift_px"] == pytest.approx(8.0)

    # Walls seen from the same side (both maps free above) are matched, never contacts.
    same_side = _room(slice(5, 30), 30)
    matched, contact, _ = sides.contacts(a, same_side, on_top)
    assert matched.sum() == 60 and contact.sum() == 0

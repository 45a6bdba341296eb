"""Pictures of an alignment: the two maps drawn on each other at its pose."""

from dataclasses import replace

import cv2
import numpy as np
import pytest

from gridmerge import align, samples
from gridmerge.errors import GridMergeError
from gridmerge.plot import OVERLAY_COLOURS, alignment_overlay, plot_alignment
from gridmerge.transforms import SimilarityTransform

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _count(img: np.ndarray, colour: str) -> int:
    return int((img == np.array(OVERLAY_COLOURS[colour], np.uint8)).all(axis=2).sum())


@pytest.fixture(scope="module")
def pair():
    a, b, truth = samples.robot_pair(0)
    return a, b, SimilarityTransform(truth)


def test_the_overlay_shows_agreeing_walls_at_the_truth_and_few_at_a_wrong_pose(pair):
    a, b, truth = pair
    right, _ = alignment_overlay(a, b, truth)
    off, _ = alignment_overlay(a, b, SimilarityTransform(translation=(25, -15)) @ truth)
    assert right.dtype == np.uint8 and right.shape[2] == 3
    # At the truth most walls in the overlap lie on the other map's: black; 25 px off
    # they are red and blue, and fewer agree by chance (the rooms repeat).
    assert _count(right, "wall_both") > 2000
    assert _count(off, "wall_both") < _count(right, "wall_both") / 2
    assert _count(off, "wall_a") + _count(off, "wall_b") > _count(right, "wall_a") + _count(right, "wall_b")
    # The overlap (both maps' free cells) and each map's own free cells are there.
    for colour in ("free_both", "free_a", "free_b"):
        assert _count(right, colour) > 1000


def test_the_overlay_is_cut_to_the_known_cells_and_located_in_a(pair):
    a, b, truth = pair
    img, (x0, y0) = alignment_overlay(a, b, truth, margin=5)
    box = a.known_bounds()
    # a's known cells start 5 cells inside the picture's edge (b's reach farther: the
    # picture starts at or before a's box, never after).
    assert x0 <= box[0] - 5 and y0 <= box[1] - 5
    assert img.shape[0] >= box[3] - box[1] and img.shape[1] >= box[2] - box[0]
    # Nothing but unknown along the edges (the margin).
    edge = np.concatenate([img[0], img[-1], img[:, 0], img[:, -1]])
    assert (edge == np.array(OVERLAY_COLOURS["unknown"], np.uint8)).all()


def test_a_large_overlay_is_shrunk_with_its_walls_kept(pair):
    a, b, truth = pair
    full, _ = alignment_overlay(a, b, truth)
    small, _ = alignment_overlay(a, b, truth, max_side=200)
    assert max(small.shape[:2]) <= 200 and max(full.shape[:2]) > 200
    # A block holding a wall cell shows it: the thin walls survive the shrinking.
    assert _count(small, "wall_both") > 200


def test_the_overlay_refuses_a_transform_that_is_not_a_matrix(pair):
    a, b, _ = pair
    with pytest.raises(GridMergeError, match="2x3 or 3x3"):
        alignment_overlay(a, b, np.eye(2))
    with pytest.raises(GridMergeError, match="finite"):
        alignment_overlay(a, b, np.full((2, 3), np.nan))


def test_pictures_of_a_merge_a_decline_and_no_pose_are_pngs(pair):
    a, b, _ = pair
    r = align(a, b, rng=0)
    assert r.success
    na, nb = samples.negative_pair(0)
    declined = align(na, nb, rng=0)
    assert not declined.success and declined.candidate is not None
    nothing = replace(declined, candidate=None)
    for x, y, result in ((a, b, r), (na, nb, declined), (na, nb, nothing)):
        png = plot_alignment(x, y, result)
        assert png.startswith(PNG_SIGNATURE)
        img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        assert img is not None and min(img.shape[:2]) > 300

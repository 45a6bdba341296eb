"""The map graph: spanning tree, joint least squares over loops, dropping contradicted edges."""

import math

import numpy as np
import pytest

from gridmerge.graph import Edge, edge_residuals, optimize_poses, solve, spanning_tree
from gridmerge.transforms import SimilarityTransform, corner_error

SHAPE = (200, 300)


def _truth(n, seed=0):
    """Random poses: map k's pixels -> map 0's pixels (map 0 the identity)."""
    rng = np.random.default_rng(seed)
    poses = [SimilarityTransform()]
    for _ in range(n - 1):
        poses.append(SimilarityTransform(rotation=rng.uniform(-math.pi, math.pi), scale=rng.uniform(0.6, 1.6),
                                         translation=rng.uniform(-300, 300, 2)))
    return poses


def _edge(poses, i, j, conf=1.0, noise=None):
    t = poses[i].inverse @ poses[j]
    if noise is not None:
        t = SimilarityTransform(translation=noise) @ t
    return Edge(i, j, t, conf)


def test_spanning_tree_keeps_the_most_confident_chain():
    poses = _truth(4)
    edges = [_edge(poses, 0, 1, 0.9), _edge(poses, 1, 2, 0.9), _edge(poses, 0, 2, 0.5), _edge(poses, 2, 3, 0.7)]
    tree, parents, order = spanning_tree(5, edges, reference=0)
    assert {(e.i, e.j) for e in tree} == {(0, 1), (1, 2), (2, 3)}
    assert parents == [None, 0, 1, 2, None] and order == [0, 1, 2, 3]


def test_chained_tree_is_exact_and_unconnected_maps_stay_unplaced():
    poses = _truth(4, seed=1)
    edges = [_edge(poses, 0, 1), _edge(poses, 2, 1), _edge(poses, 3, 2)]
    got, report = solve(5, edges, reference=0, shapes=[SHAPE] * 5)
    assert report.loops == 0 and got[4] is None and report.placed == [0, 1, 2, 3]
    for k in range(4):
        assert corner_error(got[k], poses[k], SHAPE) < 1e-6


def test_another_reference_gives_that_map_the_identity():
    poses = _truth(3, seed=2)
    edges = [_edge(poses, 0, 1), _edge(poses, 1, 2)]
    got, _ = solve(3, edges, reference=2, shapes=[SHAPE] * 3)
    assert np.allclose(got[2].params, np.eye(3))
    expected = poses[2].inverse @ poses[0]
    assert corner_error(got[0], expected, SHAPE) < 1e-6


def test_joint_least_squares_spreads_loop_error_and_beats_the_worst_chain():
    poses = _truth(4, seed=3)
    rng = np.random.default_rng(0)
    pairs = [(0, 1), (1, 2), (2, 3), (3, 0), (0, 2), (1, 3)]
    edges = [_edge(poses, i, j, noise=rng.normal(0, 1.0, 2)) for i, j in pairs]
    tree_only, _ = solve(4, edges, reference=0, shapes=[SHAPE] * 4, joint=False)
    joint, report = solve(4, edges, reference=0, shapes=[SHAPE] * 4)
    assert report.loops == 3 and report.dropped == []
    err_tree = max(corner_error(tree_only[k], poses[k], SHAPE) for k in range(1, 4))
    err_joint = max(corner_error(joint[k], poses[k], SHAPE) for k in range(1, 4))
    assert err_joint < err_tree
    assert err_joint < 3.0


def test_consistent_loops_are_solved_exactly():
    poses = _truth(5, seed=4)
    edges = [_edge(poses, i, j) for i in range(5) for j in range(i + 1, 5)]
    got = optimize_poses(5, edges, placed=range(5), reference=0, shapes=[SHAPE] * 5)
    for k in range(5):
        assert corner_error(got[k], poses[k], SHAPE) < 1e-6
    assert max(edge_residuals(edges, got, [SHAPE] * 5).values()) < 1e-6


def test_an_edge_the_loops_contradict_is_dropped():
    poses = _truth(4, seed=5)
    good = [_edge(poses, 0, 1, 0.8), _edge(poses, 1, 2, 0.8), _edge(poses, 2, 3, 0.8), _edge(poses, 0, 3, 0.8)]
    # A confident but wrong alignment (a repeated corridor 60 px away).
    wrong = _edge(poses, 0, 2, 0.95, noise=(60.0, 0.0))
    got, report = solve(4, good + [wrong], reference=0, shapes=[SHAPE] * 4, loop_tolerance=10.0)
    assert [(e.i, e.j) for e in report.dropped] == [(0, 2)]
    for k in range(4):
        assert corner_error(got[k], poses[k], SHAPE) < 1e-6


def test_robust_weights_stop_one_slightly_wrong_edge_pulling_every_map():
    n = 8
    poses = _truth(n, seed=6)
    edges = [_edge(poses, i, j) for i in range(n) for j in range(i + 1, n) if (i, j) != (0, 3)]
    # Within the loop tolerance, so not dropped, but 6 px off.
    edges.append(_edge(poses, 0, 3, 1.0, noise=(6.0, 0.0)))
    plain = optimize_poses(n, edges, placed=range(n), reference=0, shapes=[SHAPE] * n, robust=None)
    robust = optimize_poses(n, edges, placed=range(n), reference=0, shapes=[SHAPE] * n)
    err_plain = max(corner_error(plain[k], poses[k], SHAPE) for k in range(1, n))
    err_robust = max(corner_error(robust[k], poses[k], SHAPE) for k in range(1, n))
    assert err_plain > 1.0 and err_robust < 0.3 * err_plain


def test_robust_scale_follows_maps_that_all_bend_a_little():
    # Every alignment a few pixels off (real maps bend): the robust solution stays the
    # plain least-squares compromise instead of trusting a few edges.
    n = 6
    poses = _truth(n, seed=7)
    rng = np.random.default_rng(1)
    edges = [_edge(poses, i, j, noise=rng.normal(0, 4.0, 2)) for i in range(n) for j in range(i + 1, n)]
    plain = optimize_poses(n, edges, placed=range(n), reference=0, shapes=[SHAPE] * n, robust=None)
    robust = optimize_poses(n, edges, placed=range(n), reference=0, shapes=[SHAPE] * n)
    gap = max(corner_error(robust[k], plain[k], SHAPE) for k in range(1, n))
    err = max(corner_error(plain[k], poses[k], SHAPE) for k in range(1, n))
    assert gap < 0.5 * err

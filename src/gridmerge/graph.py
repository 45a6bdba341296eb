"""The map graph of a fleet: pairwise alignments as edges, one global frame from them.

Nodes are maps (by index); an :class:`Edge` ``(i, j)`` carries the transform of map
``j``'s image pixels (x = column, y = row) into map ``i``'s and a confidence. From the
confident edges:

1. :func:`spanning_tree` keeps, for every map reachable from the reference, the most
   reliable chain of alignments to it (a maximum-confidence spanning tree grown from the
   reference, Prim's algorithm);
2. :func:`optimize_poses` refines every map's transform into the reference's pixels
   jointly, by weighted least squares over all edges (the tree's and the loops'), so
   that loops agree; with no loop the tree's chained transforms are exact and kept;
3. :func:`solve` repeats 2 without the edges that the others contradict (a loop whose
   alignments disagree by more than ``loop_tolerance`` pixels loses its least
   consistent edge), and says which edges it dropped.

Poses are similarity transforms ``[[a, -b, tx], [b, a, ty]]`` (rotation, uniform scale,
translation), linear in ``(a, b, tx, ty)``: the least-squares problem is linear and is
solved exactly, with no iteration and no starting point.

Examples
--------
>>> import numpy as np
>>> from gridmerge.graph import Edge, solve
>>> from gridmerge.transforms import SimilarityTransform
>>> t01 = SimilarityTransform(translation=(10, 0))        # map 1 -> map 0
>>> t12 = SimilarityTransform(translation=(0, 5))         # map 2 -> map 1
>>> t02 = SimilarityTransform(translation=(10, 5))        # map 2 -> map 0 (agrees)
>>> edges = [Edge(0, 1, t01, 0.9), Edge(1, 2, t12, 0.8), Edge(0, 2, t02, 0.7)]
>>> poses, report = solve(3, edges, reference=0)
>>> np.round(poses[2].translation, 6).tolist(), report.dropped
([10.0, 5.0], [])
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from .transforms import AffineTransform, SimilarityTransform

__all__ = ["Edge", "GraphReport", "spanning_tree", "bridges", "optimize_poses", "edge_residuals", "solve"]


@dataclass(frozen=True)
class Edge:
    """One confident pairwise alignment.

    Attributes
    ----------
    i, j : int
        Map indices; ``transform`` maps ``j``'s image pixels to ``i``'s.
    transform : AffineTransform
    confidence : float
        In (0, 1]; the weight of the edge in the tree and in the least squares.
    points : (K, 2) float array, optional
        Points of map ``j`` (its pixels) where the two maps overlap, at which the
        joint least squares compares poses; default: ``j``'s image corners and centre.
    """

    i: int
    j: int
    transform: AffineTransform
    confidence: float
    points: np.ndarray | None = field(default=None, repr=False, compare=False)

    def other(self, k: int) -> int:
        return self.j if k == self.i else self.i


@dataclass
class GraphReport:
    """What :func:`solve` did.

    Attributes
    ----------
    tree : list of Edge
        The spanning tree's edges (each placed map's chain to the reference).
    parents : list of (int or None)
        For each map, its parent in the tree (``None`` for the reference and unplaced maps).
    placed : list of int
        Maps in the reference's component (the reference included), in placement order.
    dropped : list of Edge
        Edges removed because the rest of the graph contradicted them.
    residuals : dict of (int, int) -> float
        Each kept edge's RMS disagreement with the final poses, in pixels of map ``i``.
    loops : int
        Independent loops among the kept edges (edges beyond the tree).
    """

    tree: list[Edge]
    parents: list[int | None]
    placed: list[int]
    dropped: list[Edge] = field(default_factory=list)
    residuals: dict = field(default_factory=dict)
    loops: int = 0


def _default_points(shape: tuple[int, int] | None) -> np.ndarray:
    if shape is None:
        return np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 100.0], [0.0, 100.0], [50.0, 50.0]])
    h, w = shape
    return np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5], [(w - 1) / 2, (h - 1) / 2]])


def spanning_tree(n: int, edges: Sequence[Edge], reference: int = 0) -> tuple[list[Edge], list[int | None], list[int]]:
    """Maximum-confidence spanning tree of the reference's component (Prim).

    Returns
    -------
    tree : list of Edge
    parents : list of (int or None)
        ``parents[k]``: the map ``k`` is chained to (``None`` for the reference and for
        maps outside its component).
    order : list of int
        The reference, then the maps in the order they joined the tree.
    """
    adj: list[list[Edge]] = [[] for _ in range(n)]
    for e in edges:
        adj[e.i].append(e)
        adj[e.j].append(e)
    parents: list[int | None] = [None] * n
    seen = [False] * n
    seen[reference] = True
    order = [reference]
    tree: list[Edge] = []
    heap: list = []
    counter = 0
    for e in adj[reference]:
        heapq.heappush(heap, (-e.confidence, counter, reference, e))
        counter += 1
    while heap:
        _, _, src, e = heapq.heappop(heap)
        k = e.other(src)
        if seen[k]:
            continue
        seen[k] = True
        parents[k] = src
        order.append(k)
        tree.append(e)
        for f in adj[k]:
            if not seen[f.other(k)]:
                heapq.heappush(heap, (-f.confidence, counter, k, f))
                counter += 1
    return tree, parents, order


def bridges(edges: Sequence[tuple[int, int]]) -> list[tuple[int, int]]:
    """The edges ``(i, j)`` of an undirected graph that lie on no cycle: removing one
    disconnects its two maps, so no loop checks its alignment. In the order given; an
    edge given twice lies on a cycle (the two copies).

    One depth-first search (Tarjan's bridge finding): an edge to a child is a bridge when
    nothing below the child reaches back above it. Linear in the edges.

    Examples
    --------
    >>> bridges([(0, 1), (1, 2), (0, 2), (2, 3)])  # a triangle and a tail
    [(2, 3)]
    """
    adj: dict[int, list[tuple[int, int]]] = {}  # vertex -> [(neighbour, edge index)]
    for k, (i, j) in enumerate(edges):
        adj.setdefault(i, []).append((j, k))
        adj.setdefault(j, []).append((i, k))
    order: dict[int, int] = {}  # discovery index
    low: dict[int, int] = {}  # lowest discovery index reached from the subtree
    found: set[int] = set()
    for root in adj:
        if root in order:
            continue
        order[root] = low[root] = len(order)
        # Iterative, for fleets of any size: (vertex, edge it was entered by, next neighbour).
        stack = [(root, -1, 0)]
        while stack:
            v, via, k = stack[-1]
            if k < len(adj[v]):
                stack[-1] = (v, via, k + 1)
                w, e = adj[v][k]
                if e == via:
                    continue
                if w in order:
                    low[v] = min(low[v], order[w])
                else:
                    order[w] = low[w] = len(order)
                    stack.append((w, e, 0))
                continue
            stack.pop()
            if stack:
                parent = stack[-1][0]
                low[parent] = min(low[parent], low[v])
                if low[v] > order[parent]:
                    found.add(via)
    return [e for k, e in enumerate(edges) if k in found]


def _chain(n: int, tree: Sequence[Edge], parents: Sequence[int | None], order: Sequence[int], reference: int) -> list[AffineTransform | None]:
    """Each placed map's pixels -> the reference's pixels, by chaining the tree's edges."""
    by_child = {}
    for e in tree:
        child = e.j if parents[e.j] == e.i else e.i
        by_child[child] = e
    poses: list[AffineTransform | None] = [None] * n
    poses[reference] = SimilarityTransform()
    for k in order[1:]:
        e = by_child[k]
        p = parents[k]
        step = e.transform if e.j == k else e.transform.inverse
        poses[k] = poses[p] @ step  # type: ignore[operator]
    return poses


def _rows(points: np.ndarray) -> np.ndarray:
    """For points (K, 2): the (2K, 4) matrix mapping (a, b, tx, ty) to the similarity's images."""
    x, y = points[:, 0], points[:, 1]
    one, zero = np.ones_like(x), np.zeros_like(x)
    rx = np.stack([x, -y, one, zero], axis=1)
    ry = np.stack([y, x, zero, one], axis=1)
    return np.stack([rx, ry], axis=1).reshape(-1, 4)


def optimize_poses(
    n: int,
    edges: Sequence[Edge],
    placed: Sequence[int],
    reference: int = 0,
    shapes: Sequence[tuple[int, int] | None] | None = None,
    *,
    robust: float | None = 1.5,
    iterations: int = 10,
) -> list[AffineTransform | None]:
    """Similarity poses (each map's pixels -> the reference's) that best agree with all edges.

    Minimises ``sum_e w_e sum_p |T_i(E(p)) - T_j(p)|^2`` over the edges' points ``p``
    (in map ``j``'s pixels), with ``T_reference`` the identity and
    ``w_e = confidence``: linear least squares; maps outside ``placed`` stay ``None``.

    With ``robust`` (pixels), the weights are re-estimated ``iterations`` times as
    ``confidence / (1 + (r_e / c)^2)`` from each edge's RMS disagreement ``r_e`` (Cauchy's
    loss), with the scale ``c = max(robust, 3.5 x the median r_e)`` of the plain solution:
    one alignment that is off (a small overlap leaves a slightly wrong rotation looking
    right) then stops pulling every map towards it and shows its disagreement in full,
    while maps that all bend a little against each other (real maps do; their median
    disagreement is several pixels) keep their plain least-squares compromise.
    """
    weights = [max(e.confidence, 1e-6) for e in edges]
    poses = _solve_linear(n, edges, placed, reference, shapes, weights)
    if robust is None or robust <= 0:
        return poses
    first = edge_residuals(edges, poses, shapes)
    scale = max(float(robust), 3.5 * float(np.median(list(first.values())))) if first else float(robust)
    for _ in range(iterations):
        res = edge_residuals(edges, poses, shapes)
        new = [max(e.confidence, 1e-6) / (1.0 + (res.get((e.i, e.j), 0.0) / scale) ** 2) for e in edges]
        if np.allclose(new, weights, rtol=1e-3, atol=1e-9):
            break
        weights = new
        poses = _solve_linear(n, edges, placed, reference, shapes, weights)
    return poses


def _solve_linear(n, edges, placed, reference, shapes, weights) -> list[AffineTransform | None]:
    index = {k: c for c, k in enumerate(k for k in placed if k != reference)}
    m = len(index)
    poses: list[AffineTransform | None] = [None] * n
    poses[reference] = SimilarityTransform()
    if m == 0:
        return poses
    blocks_a, blocks_b = [], []
    for e, weight in zip(edges, weights):
        if e.i not in index and e.i != reference or e.j not in index and e.j != reference:
            continue
        pts = e.points if e.points is not None else _default_points(None if shapes is None else shapes[e.j])
        q = e.transform(pts)  # in i's pixels
        w = math.sqrt(weight)
        row = np.zeros((2 * len(pts), 4 * m))
        rhs = np.zeros(2 * len(pts))
        # T_i(q) - T_j(p) = 0, the reference's pose (the identity) moved to the right.
        if e.i == reference:
            rhs -= q.reshape(-1)
        else:
            c = index[e.i]
            row[:, 4 * c : 4 * c + 4] += _rows(q)
        if e.j == reference:
            rhs += pts.reshape(-1)
        else:
            c = index[e.j]
            row[:, 4 * c : 4 * c + 4] -= _rows(pts)
        blocks_a.append(w * row)
        blocks_b.append(w * rhs)
    A = np.concatenate(blocks_a)
    rhs_all = np.concatenate(blocks_b)
    # Condition the columns: translations are hundreds of pixels, a and b about 1.
    norm = np.linalg.norm(A, axis=0)
    norm[norm == 0] = 1.0
    sol, *_ = np.linalg.lstsq(A / norm, rhs_all, rcond=None)
    sol = sol / norm
    for k, c in index.items():
        a, b, tx, ty = sol[4 * c : 4 * c + 4]
        poses[k] = SimilarityTransform(np.array([[a, -b, tx], [b, a, ty], [0.0, 0.0, 1.0]]))
    return poses


def edge_residuals(edges: Sequence[Edge], poses: Sequence[AffineTransform | None], shapes=None) -> dict:
    """Each edge's RMS disagreement with the poses, in pixels of map ``i``.

    For points ``p`` of map ``j``: ``E(p)`` against ``T_i^-1(T_j(p))``.
    """
    out = {}
    for e in edges:
        ti, tj = poses[e.i], poses[e.j]
        if ti is None or tj is None:
            continue
        pts = e.points if e.points is not None else _default_points(None if shapes is None else shapes[e.j])
        d = e.transform(pts) - ti.inverse(tj(pts))
        out[(e.i, e.j)] = float(np.sqrt(np.mean(np.sum(d * d, axis=1))))
    return out


def solve(
    n: int,
    edges: Sequence[Edge],
    reference: int = 0,
    *,
    shapes: Sequence[tuple[int, int] | None] | None = None,
    loop_tolerance: float = 20.0,
    joint: bool = True,
) -> tuple[list[AffineTransform | None], GraphReport]:
    """Every map's transform into the reference's pixels, from the pairwise edges.

    Parameters
    ----------
    n : int
        Number of maps.
    edges : sequence of Edge
        The confident pairwise alignments.
    reference : int
        The map whose pixels are the global frame.
    shapes : sequence of (H, W), optional
        The maps' shapes (default points of edges without their own).
    loop_tolerance : float
        An edge that disagrees with the jointly optimised poses by more than this (RMS,
        in pixels of its map ``i``) is dropped, the worst first, and the poses solved
        again. Real maps bend: a few pixels of disagreement are normal.
    joint : bool
        ``False``: keep the tree's chained transforms (no least squares).

    Returns
    -------
    poses : list of (AffineTransform or None)
        Map ``k``'s pixels -> the reference's pixels; ``None`` for maps not connected to
        the reference.
    report : GraphReport
    """
    kept = list(edges)
    dropped: list[Edge] = []
    while True:
        tree, parents, order = spanning_tree(n, kept, reference)
        placed_set = set(order)
        inside = [e for e in kept if e.i in placed_set and e.j in placed_set]
        loops = len(inside) - len(tree)
        if loops == 0 or not joint:
            poses = _chain(n, tree, parents, order, reference)
        else:
            poses = optimize_poses(n, inside, order, reference, shapes)
        res = edge_residuals(inside, poses, shapes)
        if loops == 0:
            break
        worst = max(inside, key=lambda e: (res[(e.i, e.j)], -e.confidence))
        if res[(worst.i, worst.j)] <= loop_tolerance:
            break
        kept.remove(worst)
        dropped.append(worst)
    report = GraphReport(tree=tree, parents=parents, placed=list(order), dropped=dropped, residuals=res, loops=max(0, loops))
    return poses, report

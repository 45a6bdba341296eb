"""Merging maps into one: align the pairs, place every map in one frame, fuse the cells.

Two or more maps (a fleet) are merged in four steps:

1. features of every map, once (:mod:`gridmerge.features`);
2. pairwise alignments (:func:`gridmerge.align`) of all pairs, or of the likeliest
   pairs when there are many maps (``pairs="auto"``); the confident ones are the edges
   of a graph whose nodes are the maps;
3. the global frame (:mod:`gridmerge.graph`): the most reliable spanning tree anchored
   at the reference map, then a joint least-squares refinement over all edges so that
   loops agree (an edge the others contradict is dropped); maps connected to no other
   map are *unplaced* and left out;
4. every placed map warped onto one canvas, at the finest resolution among them (or the
   one asked for), and fused cell by cell (:mod:`gridmerge.fuse`).

:func:`merge` does it once; :class:`Merger` keeps the work of earlier merges (features
of maps that did not change, pairwise transforms that are only re-verified and refined
locally when a map grows) for maps that keep growing. Pairwise alignments run on any
:class:`gridmerge.parallel.Executor` (serial, a process pool, a Dask cluster) with the
same results: each pair has its own seed.

Examples
--------
>>> import gridmerge
>>> from gridmerge import samples
>>> a, b, truth = samples.table1_pair()
>>> m = gridmerge.merge([a, b])
>>> m.success, m.unplaced, m.grid.resolution == min(a.resolution, b.resolution)
(True, [], True)
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np

from .align import (
    METHODS,
    _WALLS_EVERYWHERE_CAUSES,
    AlignOptions,
    AlignResult,
    _coarse_look,
    _confirmed_by,
    _confirmed_note,
    _decline_reason,
    _full_wall,
    _matched_alone,
    _scale_disagreement,
    _structural_confidence,
    few_walls_warning,
    align,
    crop_to_full,
    scale_prior,
    full_to_crop,
    working_maps,
)
from .errors import GridMergeError
from .features import Features
from .fuse import FUSION_RULES, fuse_values, warp_values
from .graph import Edge, GraphReport, bridges, solve
from .grid import OccupancyGrid
from .limits import DEFAULT_LIMITS, Limits, extractor_for
from .matching import match_snn
from .parallel import Executor, SerialExecutor
from .refine import refine_direct
from .transforms import AffineTransform, SimilarityTransform, pixel_to_metric
from .verify import verify

__all__ = [
    "MergeResult",
    "PairResult",
    "MergeStats",
    "Merger",
    "merge",
    "reverify",
    "canvas_for",
    "canvas_problem",
    "fuse_on_canvas",
    "PAIR_STRATEGIES",
    "SCALE_CHECKS",
    "MAX_CANVAS_FACTOR",
    "MAX_CANVAS_CELLS",
]

#: A merged canvas may hold at most this many times the cells of all inputs together
#: (:data:`gridmerge.limits.DEFAULT_LIMITS`).
MAX_CANVAS_FACTOR = DEFAULT_LIMITS.max_canvas_factor
#: ... and never more than this many cells (fusing two maps takes about 40 bytes per cell).
MAX_CANVAS_CELLS = DEFAULT_LIMITS.max_canvas_cells
#: Which pairs are aligned: every pair, or (``"auto"``) every pair up to
#: :data:`ALL_PAIRS_UP_TO` maps and the likeliest pairs beyond.
PAIR_STRATEGIES = ("auto", "all")
#: All pairs are aligned for up to this many maps with ``pairs="auto"``.
ALL_PAIRS_UP_TO = 8
#: With more maps: each map's this many likeliest partners (by descriptor matches).
PARTNERS_PER_MAP = 3
#: What to do when a pair's scale disagrees with the maps' resolutions.
SCALE_CHECKS = ("warn", "reject", "off")
#: ... by more than this factor (10 %).
SCALE_TOLERANCE = 0.10

Progress = Callable[[str, int, int], None]


# --------------------------------------------------------------------- results
@dataclass
class PairResult:
    """One pairwise alignment tried while merging: map ``j`` aligned onto map ``i``.

    Attributes
    ----------
    i, j : int
        Indices of the maps (in :attr:`MergeResult.names`).
    result : AlignResult
        ``result.transform`` maps ``j``'s image pixels to ``i``'s.
    how : {"search", "reverify", "reuse", "predict"}
        A full search; a known transform re-verified and refined locally after a map
        changed; reused as it was (neither map changed); or a transform predicted by
        the other maps' placement, verified.
    used : bool
        Whether the alignment is an edge of the map graph (confident, finite, not
        contradicted by the other edges, scale not rejected).
    note : str
        Why a confident alignment was not used, or a warning about it.
    """

    i: int
    j: int
    result: AlignResult
    how: str = "search"
    used: bool = False
    note: str = ""

    @property
    def success(self) -> bool:
        return bool(self.result.success)

    @property
    def confidence(self) -> float:
        return float(self.result.confidence)


@dataclass
class MergeStats:
    """Work done by one merge (what :class:`Merger` saved by reusing earlier work)."""

    features_computed: int = 0
    pairs_searched: int = 0
    pairs_reverified: int = 0
    pairs_reused: int = 0
    pairs_predicted: int = 0
    align_s: float = 0.0
    fuse_s: float = 0.0

    def to_dict(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


@dataclass
class MergeResult:
    """The outcome of :func:`merge` (or :meth:`Merger.merge`).

    Attributes
    ----------
    success : bool
        ``True`` when at least two maps were placed and fused.
    grid : OccupancyGrid or None
        The merged map. Its metric frame is the reference map's: every point of the
        reference keeps its coordinates (x, y in metres, ROS convention). Its resolution
        is the finest of the placed maps unless another was asked for.
    names : list of str
        The input maps' names (paths, bag topics, or ``map0``, ``map1``, ...).
    transforms : list of (AffineTransform or None)
        For each input map, its image pixels -> the merged map's image pixels; ``None``
        for maps that could not be placed.
    alignments : list of (AlignResult or None)
        For each placed map, the alignment that chained it to the map graph's tree
        (``None`` for the reference); for an unplaced map, its most confident attempt.
    parents : list of (int or None)
        For each placed map, the map it is chained to in the tree.
    confidences : list of (float or None)
        For each placed map, the weakest confidence along its chain to the reference
        (1 for the reference); ``None`` when unplaced.
    unplaced : list of str
        Names of the maps that overlap no placed map confidently.
    pairs : list of PairResult
        Every pairwise alignment tried.
    warnings : list of str
        Things a user should know (scales that disagree with resolutions, dropped edges).
    reference : int
    message : str
    fusion : str
    elapsed_s : float
    stats : MergeStats
    """

    success: bool
    grid: OccupancyGrid | None
    names: list[str]
    transforms: list[AffineTransform | None]
    alignments: list[AlignResult | None]
    parents: list[int | None]
    unplaced: list[str]
    message: str
    fusion: str = "average"
    elapsed_s: float = 0.0
    inputs: list[OccupancyGrid] = field(default_factory=list, repr=False)
    confidences: list[float | None] = field(default_factory=list)
    pairs: list[PairResult] = field(default_factory=list, repr=False)
    warnings: list[str] = field(default_factory=list)
    reference: int = 0
    stats: MergeStats = field(default_factory=MergeStats, repr=False)
    graph: GraphReport | None = field(default=None, repr=False)

    def __bool__(self) -> bool:
        return self.success

    @property
    def placed(self) -> list[int]:
        """Indices of the placed maps."""
        return [k for k, t in enumerate(self.transforms) if t is not None]

    def metric(self, k: int) -> dict | None:
        """Map ``k``'s frame in the merged map's: ``{"x", "y", "yaw", "scale"}`` (metres,
        radians; scale 1 when both agree on the size of the world), or ``None``."""
        t = self.transforms[k] if k < len(self.transforms) else None
        if t is None or self.grid is None or not self.inputs:
            return None
        m = pixel_to_metric(t, self.inputs[k], self.grid)
        x, y = m.translation
        return {"x": float(x), "y": float(y), "yaw": float(m.rotation), "scale": float(m.scale)}

    def to_dict(self) -> dict:
        """A JSON-ready summary (the CLI's ``--json`` output)."""
        maps = []
        for k, name in enumerate(self.names):
            t = self.transforms[k]
            al = self.alignments[k] if k < len(self.alignments) else None
            entry: dict = {"name": name, "placed": t is not None, "reference": k == self.reference, "parent": self.parents[k]}
            if t is not None:
                entry["matrix"] = t.matrix.tolist()
                entry["rotation_deg"] = math.degrees(t.rotation)
                entry["scale"] = t.scale
                entry["metric"] = self.metric(k)
                conf = self.confidences[k] if k < len(self.confidences) else None
                entry["confidence"] = float(conf) if conf is not None else (1.0 if al is None else float(al.confidence))
            if al is not None:
                entry["alignment"] = al.to_dict()
            maps.append(entry)
        out: dict = {
            "success": bool(self.success),
            "message": self.message,
            "fusion": self.fusion,
            "elapsed_s": float(self.elapsed_s),
            "reference": self.names[self.reference] if self.names else None,
            "maps": maps,
            "unplaced": list(self.unplaced),
            "pairs": [
                {
                    "a": self.names[p.i],
                    "b": self.names[p.j],
                    "success": p.success,
                    "used": p.used,
                    "how": p.how,
                    "confidence": p.confidence if math.isfinite(p.confidence) else None,
                    "message": p.result.message,
                    "note": p.note,
                }
                for p in self.pairs
            ],
            "warnings": list(self.warnings),
            "stats": self.stats.to_dict(),
        }
        if self.grid is not None:
            out["merged"] = {
                "width": self.grid.width,
                "height": self.grid.height,
                "resolution": self.grid.resolution,
                "origin": list(self.grid.origin),
            }
        return out

    def to_json(self, **kwargs) -> str:
        return json.dumps(self.to_dict(), **kwargs)
def canvas_for(shapes: Sequence[tuple[int, int]], transforms: Sequence[AffineTransform], reference_shape: tuple[int, int]):
    """Size of the canvas holding every map, and the pixel offset of the reference.

    Parameters
    ----------
    shapes : sequence of (H, W)
        Each placed map's shape.
    transforms : sequence of AffineTransform
        Each map's pixels -> the reference's pixels.
    reference_shape : (H, W)

    Returns
    -------
    (height, width), (left, top, bottom)
        Canvas shape; columns added left of the reference, rows added above and below it.
    """
    h, w = reference_shape
    xs, ys = [-0.5, w - 0.5], [-0.5, h - 0.5]
    for (hh, ww), t in zip(shapes, transforms):
        c = t(np.array([[-0.5, -0.5], [ww - 0.5, -0.5], [ww - 0.5, hh - 0.5], [-0.5, hh - 0.5]]))
        xs.extend(c[:, 0])
        ys.extend(c[:, 1])
    eps = 1e-6
    left = max(0, math.ceil(-0.5 - min(xs) - eps))
    right = max(0, math.ceil(max(xs) - (w - 0.5) - eps))
    top = max(0, math.ceil(-0.5 - min(ys) - eps))
    bottom = max(0, math.ceil(max(ys) - (h - 0.5) - eps))
    return (h + top + bottom, w + left + right), (left, top, bottom)


def fuse_on_canvas(
    maps: Sequence[OccupancyGrid],
    transforms: Sequence[AffineTransform],
    *,
    fusion: str = "average",
    interpolation: str = "linear",
) -> tuple[np.ndarray, SimilarityTransform]:
    """Maps placed in one pixel frame, fused on the smallest canvas that holds them all.

    Parameters
    ----------
    maps : sequence of OccupancyGrid
    transforms : sequence of AffineTransform
        Each map's pixels -> the common frame's pixels.
    fusion, interpolation : str
        As :func:`gridmerge.fuse.fuse_values` and :func:`gridmerge.fuse.warp_values`.

    Returns
    -------
    fused : (H, W) float array
        The canvas (``NaN`` unknown).
    to_canvas : SimilarityTransform
        The common frame's pixels -> the canvas's (a shift, :func:`canvas_for` with a
        1 x 1 reference); map ``k`` lies on the canvas by ``to_canvas @ transforms[k]``.

    Notes
    -----
    The maps are warped one at a time (the canvas may be large and the fleet long);
    check the canvas first with :func:`canvas_problem`.
    """
    (ch, cw), (left, top, _) = canvas_for([m.shape for m in maps], transforms, (1, 1))
    to_canvas = SimilarityTransform(translation=(left, top))
    layers = (warp_values(m.data, (to_canvas @ t).params, (ch, cw), interpolation=interpolation) for m, t in zip(maps, transforms))
    return fuse_values(layers, fusion), to_canvas


def canvas_problem(
    shapes: Sequence[tuple[int, int]],
    transforms: Sequence[AffineTransform],
    reference_shape: tuple[int, int],
    *,
    input_cells: int,
    max_canvas_cells: int,
    max_canvas_factor: float,
) -> str:
    """Why the canvas of these placed maps must not be allocated, or ``""``.

    Decided from the transforms alone, before anything is allocated: every transform
    must be finite and invertible, and the canvas may hold at most
    ``min(max_canvas_cells, max_canvas_factor * input_cells)`` cells.
    """
    for t in transforms:
        m = np.asarray(t.params, dtype=float)
        if not np.isfinite(m).all():
            return "declined: a map's transform is not finite"
        # A map shrunk to (almost) nothing: the warp cannot invert its transform.
        if not abs(float(np.linalg.det(m[:2, :2]))) > 1e-12:
            return "declined: a map's transform is degenerate (scale of almost 0)"
    (ch, cw), _ = canvas_for(shapes, transforms, reference_shape)
    limit = min(int(max_canvas_cells), math.floor(max_canvas_factor * input_cells))
    if ch * cw > limit:
        which = "max_canvas_cells" if limit == int(max_canvas_cells) else "max_canvas_factor"
        return f"declined: the merged map would have {ch} x {cw} cells, more than the limit of {limit} ({which})"
    return ""




# ------------------------------------------------------------------ the jobs
@dataclass(frozen=True)
class _FeatureJob:
    grid: OccupancyGrid
    method: str
    options: AlignOptions
    limits: Limits | None
    ahead: bool = False  # and what the method prepares (Method.prepare)


def _run_features(job: _FeatureJob) -> Features | None:
    spec = METHODS[job.method]
    if job.limits is not None:
        ext = extractor_for(job.method, job.limits.replace(max_keypoints=job.options.max_keypoints), job.options)
    else:
        ext = spec.extractor(job.options) if spec.extractor is not None else None
    f = ext(job.grid) if ext is not None else None
    if f is not None and job.ahead and spec.prepare is not None:
        f = spec.prepare(job.grid, f, job.options)
    return f


@dataclass(frozen=True)
class _Prior:
    """A pose of a pair known without a search, to be re-verified (:func:`reverify`).

    ``transform``: b's pixels -> a's; ``runner_up_ratio`` and ``confidence``: the
    ambiguity and confidence it carries; ``predicted``: it comes from the other maps'
    placement (a failure is then final), not from this pair's own earlier alignment
    (a failure then calls for a new search).
    """

    transform: AffineTransform
    runner_up_ratio: float = 1.0
    confidence: float = 1.0
    predicted: bool = False


@dataclass(frozen=True)
class _PairState:
    """What :class:`Merger` remembers of a pair: its alignment, and the versions and
    grids of the two maps it was made with (``result.transform``: grid_j's pixels ->
    grid_i's)."""

    version_i: int
    version_j: int
    grid_i: OccupancyGrid
    grid_j: OccupancyGrid
    result: AlignResult


def _carry(old: OccupancyGrid, new: OccupancyGrid) -> np.ndarray:
    """(3, 3) float array: a newer version's pixels -> the older version's pixels of one
    map, through their shared metric frame (a growing map's origin moves, its frame not)."""
    return old.metric_to_pixel_matrix() @ new.pixel_to_metric_matrix()


@dataclass(frozen=True)
class _PairJob:
    a: OccupancyGrid
    b: OccupancyGrid
    method: str
    options: AlignOptions
    seed: int
    features: tuple
    prior: _Prior | None = None
    first: AlignResult | None = None  # a declined search, to search again with coarser keypoints


def _run_pair(job: _PairJob) -> AlignResult:
    if job.first is not None:
        fa, fb = job.features
        # Timed from the first search's start, as align times its own second search.
        t0 = time.perf_counter() - job.first.elapsed_s
        return _coarse_look(job.first, job.a, job.b, fa, fb, job.method, job.options, job.seed, t0)
    p = job.prior
    if p is not None:
        return reverify(job.a, job.b, p.transform, method=job.method, options=job.options,
                        runner_up_ratio=p.runner_up_ratio, max_confidence=p.confidence, features=job.features)
    return align(job.a, job.b, method=job.method, options=job.options, rng=job.seed, features=job.features)


def _finite_result(r: AlignResult) -> AlignResult:
    """``r``, declined when its transform could not be composed or inverted."""
    if r.success:
        m = np.asarray(r.transform.params, dtype=float)  # type: ignore[union-attr]
        # Never composed or warped (see canvas_problem for the other bounds).
        if not np.isfinite(m).all():
            return replace(r, success=False, transform=None, message="declined: the transform is not finite")
        if not abs(float(np.linalg.det(m[:2, :2]))) > 1e-12:
            return replace(r, success=False, transform=None, message="declined: the transform is degenerate (scale of almost 0)")
    return r


def reverify(
    a: OccupancyGrid,
    b: OccupancyGrid,
    prior: AffineTransform,
    *,
    method: str = "hybrid",
    options: AlignOptions | None = None,
    runner_up_ratio: float = 1.0,
    max_confidence: float = 1.0,
    max_shift: float = 12.0,
    features: tuple[Features | None, Features | None] | None = None,
) -> AlignResult:
    """Check a known transform of ``b`` onto ``a`` against the maps, refining it locally.

    The cheap path of :class:`Merger`: when a map grew, the transform found before (or
    one predicted from the other maps' placement) is refined against the cells of both
    maps (:func:`gridmerge.refine.refine_direct`) and verified as :func:`align` verifies
    (acceptance index, wall agreement), instead of searched again.

    Parameters
    ----------
    a, b : OccupancyGrid
    prior : AffineTransform
        b's image pixels -> a's image pixels, within a few pixels of the truth.
    runner_up_ratio : float
        The ambiguity of the pose when it was found by a search (``details
        ["runner_up_ratio"]`` of its :class:`AlignResult`); 0 when the pose is known
        without ambiguity (predicted through other confident alignments).
    max_confidence : float
        The result's confidence is at most this (a predicted pose is as reliable as the
        chain that predicted it).
    max_shift : float
        Refinement moving b's corners farther than this (pixels) is refused.
    features : (Features or None, Features or None), optional
        The maps' keypoints (as :func:`align` takes them). When the walls alone would
        decline the pose (maps that bend), the keypoint matches may still confirm it, as
        in :func:`align`, up to ``max_confidence``; the pose's ambiguity was settled
        where it came from, so no rival is weighed.

    Returns
    -------
    AlignResult
        ``details["reverified"]`` is ``True``; declined when the maps no longer agree.
    """
    opts = options or AlignOptions()
    t0 = time.perf_counter()
    ca, oa, cb, ob = working_maps(a, b)
    t = full_to_crop(prior, oa, ob)
    if not isinstance(t, SimilarityTransform):
        t = SimilarityTransform.from_estimate(cb.corners(), t(cb.corners())) or SimilarityTransform(t.params)
    shift = 0.0
    if opts.refine:
        refined, report = refine_direct(ca, cb, t, max_shift=max_shift, scale_prior=scale_prior(ca, cb, t, opts), reference="finer")
        if report.accepted:
            t, shift = refined, float(report.shift_px)
    v = verify(ca, cb, t, tolerance=opts.wall_tolerance)
    scale_off = _scale_disagreement(t, ca, cb)
    conf = min(float(max_confidence), _structural_confidence(_full_wall(v), runner_up_ratio))
    message = _decline_reason(0, v, conf, opts, need_inliers=False, scale_off=scale_off)
    full = crop_to_full(t, oa, ob)
    details = {"reverified": True, "runner_up_ratio": float(runner_up_ratio), "refine_shift_px": round(shift, 3)}
    if message and features is not None and METHODS[method].verified:
        matched = _matched_alone(features[0], features[1], full, opts)
        evidence, own = matched if matched is not None else (None, 0.0)
        capped = min(float(max_confidence), own)
        if evidence is not None and capped > conf:
            details["keypoint_evidence"] = {**evidence.to_dict(), "confidence": round(own, 4)}
            if not _decline_reason(0, v, capped, opts, need_inliers=False, scale_off=scale_off, matched=True):
                conf, message = capped, ""
                details["confirmed_by"] = _confirmed_by(evidence)
    ok = not message
    return AlignResult(
        success=ok,
        transform=full if ok else None,
        candidate=full,
        metric_transform=pixel_to_metric(full, b, a),
        confidence=conf,
        acceptance_index=v.acceptance_index,
        inliers=0,
        matches=0,
        keypoints=(0, 0),
        method=method,
        message=message or f"re-verified, confidence {conf:.2f}" + _confirmed_note(details),
        elapsed_s=time.perf_counter() - t0,
        verification=v,
        details=details,
    )


def _pair_seed(base: int, digest_a: bytes, digest_b: bytes) -> int:
    """A seed of its own for each pair of maps, from the maps' contents (:func:`_digest`):
    the same maps get the same seed whatever their names (file paths or bag topics) and
    whatever order the pairs run in."""
    h = hashlib.blake2b((base % 2**64).to_bytes(8, "little") + digest_a + digest_b, digest_size=8).digest()
    return int.from_bytes(h, "little") >> 1


def _digest(grid: OccupancyGrid) -> bytes:
    h = hashlib.blake2b(digest_size=16)
    h.update(np.ascontiguousarray(grid.data).view(np.uint8))
    h.update(repr((grid.shape, float(grid.resolution), tuple(float(v) for v in grid.origin))).encode())
    return h.digest()


def _overlap_points(a: OccupancyGrid, b: OccupancyGrid, t: AffineTransform, samples: int = 6000) -> np.ndarray | None:
    """Points of b (its pixels) spanning the cells b and a both know when b is moved by
    ``t``: the overlap's centroid and its extreme points in 8 directions (``None`` when
    the maps share fewer than 10 sampled cells). The joint least squares compares poses
    there, so that an alignment constrains the rotation only as far as its overlap reaches.
    """
    ys, xs = np.nonzero(b.known)
    if len(xs) == 0:
        return None
    step = max(1, len(xs) // samples)
    pb = np.stack([xs[::step], ys[::step]], 1).astype(float)
    q = np.rint(t(pb)).astype(np.int64)
    h, w = a.shape
    inside = (q[:, 0] >= 0) & (q[:, 1] >= 0) & (q[:, 0] < w) & (q[:, 1] < h)
    on = np.zeros(len(pb), bool)
    on[inside] = a.known[q[inside, 1], q[inside, 0]]
    pb = pb[on]
    if len(pb) < 10:
        return None
    centre = pb.mean(0)
    angles = np.arange(8) * (np.pi / 4)
    dirs = np.stack([np.cos(angles), np.sin(angles)], 1)
    extremes = pb[np.argmax((pb - centre) @ dirs.T, axis=0)]
    return np.vstack([centre[None], extremes])


def _box_points(a: OccupancyGrid, b: OccupancyGrid, t: AffineTransform) -> np.ndarray | None:
    """Points of b (its pixels) spanning where b, moved by ``t``, overlaps a: the corners
    and centre of b's known box clipped to a's known box; ``None`` if they miss."""
    ba, bb = a.known_bounds(), b.known_bounds()
    if ba is None or bb is None:
        return None
    x0, y0, x1, y1 = ba
    corners_a = np.array([[x0 - 0.5, y0 - 0.5], [x1 - 0.5, y0 - 0.5], [x1 - 0.5, y1 - 0.5], [x0 - 0.5, y1 - 0.5]])
    ca = t.inverse(corners_a)
    lo = np.maximum(ca.min(0), [bb[0] - 0.5, bb[1] - 0.5])
    hi = np.minimum(ca.max(0), [bb[2] - 0.5, bb[3] - 0.5])
    if not (hi > lo).all():
        return None
    return np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]], [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2]])


def _predicted_overlap(a: OccupancyGrid, b: OccupancyGrid, t: AffineTransform, step: int = 4) -> int:
    """Cells (of a) known in both maps when b is moved by ``t``, counted on a coarse grid."""
    if _box_points(a, b, t) is None:  # the known boxes miss each other
        return 0
    ka = a.known[:: step, :: step]
    ys, xs = np.nonzero(ka)
    q = t.inverse(np.stack([xs * step, ys * step], 1).astype(float))
    u, v = np.rint(q[:, 0]).astype(int), np.rint(q[:, 1]).astype(int)
    inside = (u >= 0) & (v >= 0) & (u < b.width) & (v < b.height)
    hit = np.zeros(len(u), bool)
    hit[inside] = b.known[v[inside], u[inside]]
    return int(hit.sum()) * step * step


def _pair_scores(feats: Sequence[Features | None], matcher: str, keep: int = 600) -> np.ndarray:
    """How likely each pair of maps overlaps: ratio-test matches between their strongest
    descriptors, over the smaller count. Symmetric (N, N); 0 on the diagonal."""
    n = len(feats)
    out = np.zeros((n, n))
    top = []
    for f in feats:
        if f is None or len(f) == 0:
            top.append(None)
            continue
        idx = np.argsort(-f.response, kind="stable")[:keep]
        top.append(f.descriptors[idx])
    for i in range(n):
        for j in range(i + 1, n):
            if top[i] is None or top[j] is None:
                continue
            _, pairs = match_snn(top[i], top[j], method=matcher)
            out[i, j] = out[j, i] = len(pairs) / max(1, min(len(top[i]), len(top[j])))
    return out


# ------------------------------------------------------------------- merging
class Merger:
    """Merges a fleet's maps, again and again as they grow, reusing earlier work.

    Feed it maps (:meth:`update`), as a ROS node would receive them, and call
    :meth:`merge` whenever a merged map is wanted. Between merges it keeps:

    * the features of every map that did not change;
    * every pairwise alignment: pairs of unchanged maps are reused as they were; when a
      map changed, its known transforms are re-verified and refined locally
      (:func:`reverify`), through the maps' metric frames, so growing maps whose origin
      moves are handled; pairs that failed before and are now predicted to overlap by
      the other maps' placement are verified at the predicted pose;
    * only new maps, maps placed nowhere, and pairs whose known transform no longer
      holds pay the full search.

    With three maps or more, pairs are searched from one side
    (``AlignOptions.one_sided_confidence=None``): the loops of the map graph check the
    alignments that lie on them. After the placement, the alignments on no loop (the
    graph's bridges) below ``one_sided_confidence`` are searched again from both sides,
    as :func:`gridmerge.align` does for a single pair, and declined when only one side
    finds them. That holds for an alignment re-verified after a map grew, unless its
    pose was searched from both sides before.

    Parameters
    ----------
    method : str
        Alignment method (:func:`gridmerge.align`).
    fusion : {"average", "logodds", "max"}
    reference : str or int, optional
        Name (or insertion index) of the map whose metric frame is the merged map's;
        default the first map given.
    resolution : float, optional
        Resolution (m/cell) of the merged map; default the finest of the placed maps.
    pairs : {"auto", "all"}
        Which pairs are searched: all, or (``"auto"``) all up to 8 maps and beyond that
        each map's 3 likeliest partners (descriptor matches), more for maps left
        unplaced, and every pair the placement predicts to overlap (verified cheaply at
        the predicted pose; searched when that pose does not hold and the pair never was:
        real maps bend, and a pose chained through the graph can be 20 px off).
    executor : gridmerge.parallel.Executor, optional
        Where the features and pairwise alignments run (default serial).
    scale_check : {"warn", "reject", "off"}
        A pair whose scale disagrees with the maps' resolutions by more than 10 %
        (``metric scale`` not 1) is reported in ``warnings`` (``"warn"``) or not used
        (``"reject"``, for maps whose resolutions are right, as ROS maps' are). Beyond
        ``AlignOptions.max_scale_disagreement`` (15 %) the alignment itself declines
        the pair; with ``max_scale_disagreement=None`` (maps whose resolutions are
        unknown; CLI ``--any-scale``) every scale reaches this check.
    joint : bool
        Refine all transforms jointly over the loops of the map graph.
    loop_tolerance : float
        Pixels (RMS) by which an edge may disagree with the joint solution before it is
        dropped (:func:`gridmerge.graph.solve`).
    rng : int or numpy.random.Generator
        Base seed; each pair gets its own seed from it and the two maps' contents.
    progress : callable, optional
        ``progress(stage, done, total)``, stage ``"features"`` or ``"pairs"``.
    options, limits, interpolation, max_canvas_factor, max_canvas_cells, **overrides
        As for :func:`merge`.

    Examples
    --------
    >>> from gridmerge import Merger, samples
    >>> a, b, truth = samples.robot_pair(seed=0)
    >>> merger = Merger()
    >>> merger.update(a, "robot1"), merger.update(b, "robot2")
    ('robot1', 'robot2')
    >>> first = merger.merge()
    >>> first.success, first.stats.pairs_searched
    (True, 1)
    >>> again = merger.merge()                    # nothing changed: nothing searched
    >>> again.stats.pairs_searched, again.stats.pairs_reused
    (0, 1)
    """

    def __init__(
        self,
        *,
        method: str = "hybrid",
        fusion: str = "average",
        reference: str | int | None = None,
        resolution: float | None = None,
        pairs: str = "auto",
        executor: Executor | None = None,
        scale_check: str = "warn",
        joint: bool = True,
        loop_tolerance: float = 20.0,
        options: AlignOptions | None = None,
        rng=0,
        interpolation: str = "linear",
        max_canvas_factor: float | None = None,
        max_canvas_cells: int | None = None,
        limits: Limits | None = None,
        progress: Progress | None = None,
        **overrides,
    ):
        if method not in METHODS:
            raise GridMergeError(f"unknown alignment method {method!r} (use one of {', '.join(METHODS)})")
        if fusion not in FUSION_RULES:
            raise GridMergeError(f"unknown fusion rule {fusion!r} (use one of {', '.join(FUSION_RULES)})")
        if pairs not in PAIR_STRATEGIES:
            raise GridMergeError(f"unknown pair strategy {pairs!r} (use one of {', '.join(PAIR_STRATEGIES)})")
        if scale_check not in SCALE_CHECKS:
            raise GridMergeError(f"unknown scale check {scale_check!r} (use one of {', '.join(SCALE_CHECKS)})")
        if resolution is not None and not (math.isfinite(resolution) and resolution > 0):
            raise GridMergeError(f"the merged map's resolution must be a number > 0, got {resolution!r}")
        self.method, self.fusion, self.pairs, self.scale_check = method, fusion, pairs, scale_check
        self.reference, self.resolution = reference, resolution
        self.joint, self.loop_tolerance, self.interpolation = bool(joint), float(loop_tolerance), interpolation
        self.executor = executor or SerialExecutor()
        self.progress = progress
        self.limits = (limits or DEFAULT_LIMITS).replace(max_canvas_factor=max_canvas_factor, max_canvas_cells=max_canvas_cells)
        self._feature_limits = limits
        if limits is not None and "max_keypoints" not in overrides:
            overrides["max_keypoints"] = limits.max_keypoints
        self.options = replace(options or AlignOptions(), **overrides)
        gen = rng if isinstance(rng, np.random.Generator) else None
        self._seed = int(gen.integers(2**62)) if gen is not None else int(rng)
        self._maps: dict[str, OccupancyGrid] = {}
        self._digests: dict[str, bytes] = {}
        self._versions: dict[str, int] = {}
        self._features: dict[str, tuple[int, Features | None]] = {}
        self._pairs: dict[tuple[str, str], _PairState] = {}
        # name -> (grid, 3x3 pose: its pixels -> the merged map's metric frame) of the last merge.
        self._poses: dict[str, tuple[OccupancyGrid, np.ndarray]] = {}
        self._pose_conf: dict[str, float] = {}

    # ------------------------------------------------------------- the maps
    @property
    def names(self) -> list[str]:
        """The maps' names, in the order they were first given."""
        return list(self._maps)

    def __len__(self) -> int:
        return len(self._maps)

    def update(self, grid: OccupancyGrid, name: str | None = None) -> str:
        """Add a map, or replace the map of that name with its newer version.

        Returns the name (``grid.name``, else ``mapK``). A map whose cells, resolution
        and origin did not change keeps all its earlier work.
        """
        if not isinstance(grid, OccupancyGrid):
            raise GridMergeError(f"expected an OccupancyGrid, got {type(grid).__name__}")
        key = name or grid.name or f"map{len(self._maps)}"
        digest = _digest(grid)
        if self._digests.get(key) != digest:
            self._versions[key] = self._versions.get(key, -1) + 1
            self._digests[key] = digest
        self._maps[key] = grid
        return key

    def remove(self, name: str) -> None:
        """Forget a map and every alignment it took part in."""
        if name not in self._maps:
            raise GridMergeError(f"no map named {name!r}")
        for d in (self._maps, self._digests, self._versions, self._features, self._poses, self._pose_conf):
            d.pop(name, None)
        self._pairs = {k: v for k, v in self._pairs.items() if name not in k}

    # ------------------------------------------------------------ internals
    def _reference_index(self, names: list[str]) -> int:
        ref = self.reference
        if ref is None:
            return 0
        if isinstance(ref, (int, np.integer)) and not isinstance(ref, bool):
            if not 0 <= int(ref) < len(names):
                raise GridMergeError(f"reference {ref} is not the index of a map (0..{len(names) - 1})")
            return int(ref)
        if ref not in names:
            raise GridMergeError(f"reference {ref!r} is not one of the maps ({', '.join(names)})")
        return names.index(ref)

    def _report(self, stage: str, done: int, total: int) -> None:
        if self.progress is not None:
            self.progress(stage, done, total)

    def _run(self, stage: str, fn, jobs: list) -> list:
        """Run jobs on the executor, in chunks so that progress is reported."""
        out: list = []
        total = len(jobs)
        self._report(stage, 0, total)
        chunk = max(1, int(getattr(self.executor, "workers", 1))) * (4 if self.progress is not None else max(1, total))
        for s in range(0, total, chunk):
            out.extend(self.executor.map(fn, jobs[s : s + chunk]))
            self._report(stage, len(out), total)
        return out

    def _feats(self, names: list[str], stats: MergeStats) -> list[Features | None]:
        todo = [n for n in names if self._features.get(n, (-1, None))[0] != self._versions[n]]
        # Three maps or more: most pairs are not settled by their keypoints, and what the
        # method prepares per map (the hybrid's blurred keypoints) is found once, here.
        ahead = len(self._maps) >= 3
        jobs = [_FeatureJob(self._maps[n], self.method, self.options, self._feature_limits, ahead) for n in todo]
        for n, f in zip(todo, self._run("features", _run_features, jobs)):
            self._features[n] = (self._versions[n], f)
        stats.features_computed += len(todo)
        return [self._features[n][1] for n in names]

    def _prior(self, key: tuple[str, str]) -> _Prior | None:
        """The cached transform of a pair, carried into the maps' current pixel frames."""
        entry = self._pairs.get(key)
        if entry is None or not entry.result.success:
            return None
        r = entry.result
        ni, nj = key
        m = np.linalg.solve(_carry(entry.grid_i, self._maps[ni]), r.transform.params @ _carry(entry.grid_j, self._maps[nj]))
        ratio = float(r.details.get("runner_up_ratio", 1.0)) if r.details else 1.0
        return _Prior(type(r.transform)(m), ratio, float(r.confidence))

    def _placed_guess(self, ni: str, nj: str) -> _Prior | None:
        """The transform of ``nj`` onto ``ni`` that the last merge's placement implies
        (carried into the maps' current pixel frames), or ``None``."""
        if ni not in self._poses or nj not in self._poses:
            return None
        (gi, pi), (gj, pj) = self._poses[ni], self._poses[nj]
        mi = pi @ _carry(gi, self._maps[ni])
        mj = pj @ _carry(gj, self._maps[nj])
        t = AffineTransform(np.linalg.solve(mi, mj))
        return _Prior(t, 0.0, min(self._pose_conf.get(ni, 0.0), self._pose_conf.get(nj, 0.0)), predicted=True)

    def _job(self, i, j, names, feats, prior: _Prior | None = None, *, both_sides: bool = False,
             first: AlignResult | None = None) -> _PairJob:
        """A pair's job. In a fleet of three maps or more a pair is searched from one side
        (``one_sided_confidence=None``): the map graph's loops check its alignments, and
        the alignments no loop checks are searched from both sides afterwards
        (:meth:`_check_bridges`); ``both_sides`` asks for that second search. Nor is a
        declined pair searched again with coarser keypoints (``coarse_look``) then: only
        the pairs of maps the placement leaves out are (``first``, their declined
        search; :meth:`_look_coarser`)."""
        options = self.options
        if len(self._maps) >= 3:
            if not both_sides and options.one_sided_confidence is not None:
                options = replace(options, one_sided_confidence=None)
            if first is None and options.coarse_look:
                options = replace(options, coarse_look=0)
        return _PairJob(self._maps[names[i]], self._maps[names[j]], self.method, options,
                        _pair_seed(self._seed, self._digests[names[i]], self._digests[names[j]]), (feats[i], feats[j]), prior, first)

    def _store(self, names, i, j, r: AlignResult, how: str) -> PairResult:
        r = _finite_result(r)
        ni, nj = names[i], names[j]
        self._pairs[(ni, nj)] = _PairState(self._versions[ni], self._versions[nj], self._maps[ni], self._maps[nj], r)
        return PairResult(i, j, r, how)

    # ---------------------------------------------------------------- merge
    def merge(self) -> MergeResult:
        """Align what needs aligning, place the maps, fuse them; see the class docs."""
        t0 = time.perf_counter()
        names = self.names
        n = len(names)
        if n < 2:
            raise GridMergeError(f"merging needs at least two maps, got {n}")
        reference = self._reference_index(names)
        maps = [self._maps[k] for k in names]
        stats = MergeStats()
        feats = self._feats(names, stats)
        verified = METHODS[self.method].verified
        results: dict[tuple[int, int], PairResult] = {}

        # 1. Pairs known from earlier merges: reuse, or re-verify what changed.
        search: list[tuple[int, int]] = []
        recheck: list[tuple[int, int, tuple]] = []
        for i in range(n):
            for j in range(i + 1, n):
                entry = self._pairs.get((names[i], names[j]))
                if entry is None:
                    continue
                r = entry.result
                if (entry.version_i, entry.version_j) == (self._versions[names[i]], self._versions[names[j]]):
                    results[(i, j)] = PairResult(i, j, r, "reuse")
                    stats.pairs_reused += 1
                elif r.success and verified and (prior := self._prior((names[i], names[j]))) is not None:
                    recheck.append((i, j, prior))
                elif verified and (guess := self._placed_guess(names[i], names[j])) is not None:
                    # Failed before, but both maps were placed: their poses say where to look.
                    if _predicted_overlap(maps[i], maps[j], guess.transform) >= 4 * self.options.min_overlap_cells:
                        recheck.append((i, j, guess))
                    else:
                        kept = replace(r, details={**r.details, "predicted": True})
                        results[(i, j)] = self._store(names, i, j, kept, "predict")
                else:
                    search.append((i, j))
        if recheck:
            jobs = [self._job(i, j, names, feats, prior) for i, j, prior in recheck]
            t1 = time.perf_counter()
            for (i, j, prior), r in zip(recheck, self._run("pairs", _run_pair, jobs)):
                if r.success:
                    before = self._pairs[(names[i], names[j])].result.details
                    if not prior.predicted and "other_side" in before:  # its pose was searched from both sides
                        r.details["other_side"] = before["other_side"]
                    results[(i, j)] = self._store(names, i, j, r, "reverify")
                elif prior.predicted:  # a predicted pose that does not hold: not searched again
                    r.details["predicted"] = True
                    results[(i, j)] = self._store(names, i, j, r, "predict")
                else:
                    search.append((i, j))  # the known transform no longer holds
            stats.align_s += time.perf_counter() - t1
            stats.pairs_reverified += len(recheck)

        # 2. New pairs: all of them, or the likeliest when there are many maps.
        new = [(i, j) for i in range(n) for j in range(i + 1, n) if (i, j) not in results and (i, j) not in search
               and (names[i], names[j]) not in self._pairs]
        scores = None
        if self.pairs == "all" or n <= ALL_PAIRS_UP_TO or all(f is None for f in feats):
            search += new
        else:
            scores = _pair_scores(feats, self.options.matcher)
            chosen = set()
            for k in range(n):
                order = [int(x) for x in np.argsort(-scores[k], kind="stable") if x != k]
                for x in order[:PARTNERS_PER_MAP]:
                    chosen.add((min(k, x), max(k, x)))
            search += [p for p in new if p in chosen]
        self._search(names, feats, sorted(set(search)), results, stats)

        # 3. Place, then look for the pairs the placement says overlap.
        poses, report, warnings = self._solve(maps, names, results, reference)
        if verified:
            if scores is not None:
                # Maps left out: try their next likeliest partners.
                unplaced = [k for k in range(n) if poses[k] is None]
                extra = set()
                for k in unplaced:
                    order = [int(x) for x in np.argsort(-scores[k], kind="stable") if x != k]
                    for x in order[: 3 * PARTNERS_PER_MAP]:
                        p = (min(k, x), max(k, x))
                        if p not in results:
                            extra.add(p)
                if extra:
                    self._search(names, feats, sorted(extra), results, stats)
                    poses, report, warnings = self._solve(maps, names, results, reference)
            if self._look_coarser(names, feats, results, poses, stats):
                poses, report, warnings = self._solve(maps, names, results, reference)
            predicted = []
            for i in range(n):
                for j in range(i + 1, n):
                    if poses[i] is None or poses[j] is None:
                        continue
                    known = results.get((i, j))
                    if known is not None and (known.success or known.result.details.get("predicted")):
                        continue
                    t = poses[i].inverse @ poses[j]
                    if _predicted_overlap(maps[i], maps[j], t) < max(4 * self.options.min_overlap_cells, 1):
                        continue
                    conf = min(_chain_confidence(report, i), _chain_confidence(report, j))
                    predicted.append((i, j, _Prior(t, 0.0, conf, predicted=True)))
            if predicted:
                jobs = [self._job(i, j, names, feats, prior) for i, j, prior in predicted]
                t1 = time.perf_counter()
                unsearched = []  # the predicted pose does not hold, and the pair was never searched
                for (i, j, _), r in zip(predicted, self._run("pairs", _run_pair, jobs)):
                    if not r.success and (i, j) not in results:
                        unsearched.append((i, j))
                        continue
                    r.details["predicted"] = True
                    results[(i, j)] = self._store(names, i, j, r, "predict")
                stats.align_s += time.perf_counter() - t1
                stats.pairs_predicted += len(predicted)
                self._search(names, feats, unsearched, results, stats)
                poses, report, warnings = self._solve(maps, names, results, reference)

        checked: set = set()
        while verified and self._check_bridges(names, feats, results, stats, checked):
            # Declining a bridge cannot make another alignment a bridge, but the graph
            # solved again may use other alignments: check until nothing changes (each
            # pair at most once).
            poses, report, warnings = self._solve(maps, names, results, reference)

        result = self._fuse(maps, names, results, poses, report, warnings, reference, stats)
        result.elapsed_s = time.perf_counter() - t0
        if result.success and result.grid is not None:
            to_metric = result.grid.pixel_to_metric_matrix()
            self._poses = {names[k]: (maps[k], to_metric @ result.transforms[k].params) for k in result.placed}  # type: ignore[union-attr]
            self._pose_conf = {names[k]: float(result.confidences[k]) for k in result.placed}  # type: ignore[arg-type]
        return result

    def _check_bridges(self, names, feats, results, stats, checked: set) -> bool:
        """Search again, from both maps' sides, the used alignments that no loop of the map
        graph checks (its bridges) and that are below ``one_sided_confidence``, unless
        they were (a pair of two maps is searched from both sides at once; a Merger that
        had three maps and has two left may hold one-sided alignments; an alignment
        re-verified after a map grew keeps its search's ``other_side``): a pose found from
        one side only is declined there, as :func:`align` declines it for a single pair.
        Poses predicted through the other maps lie on a loop. ``checked``: the pairs
        searched so in this merge (updated). Returns whether any alignment changed."""
        tau = self.options.one_sided_confidence
        if tau is None:
            return False
        used = [(i, j) for (i, j), p in results.items() if p.used]
        todo = [(i, j) for i, j in bridges(used) if results[(i, j)].confidence < tau and (i, j) not in checked
                and not {"other_side", "predicted"} & set(results[(i, j)].result.details)]
        if not todo:
            return False
        checked.update(todo)
        before = {k: results[k].result for k in todo}
        self._search(names, feats, todo, results, stats, both_sides=True)
        changed = False
        for k in todo:
            r, old = results[k].result, before[k]
            same = r.success == old.success and (r.transform is None or np.array_equal(r.transform.params, old.transform.params))
            changed = changed or not same
        return changed

    def _look_coarser(self, names, feats, results, poses, stats) -> bool:
        """Search again, with keypoints detected on fewer pixels (``coarse_look``), the
        declined pairs of the maps the placement left out, as :func:`align` does for a
        single pair (a fleet's first searches do not, to spare the many pairs that do not
        overlap). Returns whether any pair was merged so."""
        if len(names) < 3 or not self.options.coarse_look or not METHODS[self.method].coarse_look:
            return False
        out = {k for k in range(len(names)) if poses[k] is None}
        todo = sorted((i, j) for (i, j), p in results.items() if (i in out or j in out) and not p.result.success
                      and not {"predicted", "coarse_look"} & set(p.result.details))
        if not todo:
            return False
        jobs = [self._job(i, j, names, feats, first=results[(i, j)].result) for i, j in todo]
        t1 = time.perf_counter()
        merged = False
        for (i, j), r in zip(todo, self._run("pairs", _run_pair, jobs)):
            results[(i, j)] = self._store(names, i, j, r, "search")
            merged = merged or r.success
            stats.pairs_searched += "coarse_look" in r.details  # not when nothing would change
        stats.align_s += time.perf_counter() - t1
        return merged

    def _search(self, names, feats, pairs, results, stats, *, both_sides: bool = False) -> None:
        if not pairs:
            return
        jobs = [self._job(i, j, names, feats, both_sides=both_sides) for i, j in pairs]
        t1 = time.perf_counter()
        for (i, j), r in zip(pairs, self._run("pairs", _run_pair, jobs)):
            results[(i, j)] = self._store(names, i, j, r, "search")
        stats.align_s += time.perf_counter() - t1
        stats.pairs_searched += len(pairs)

    def _solve(self, maps, names, results, reference):
        warnings: list[str] = []
        edges = []
        for (i, j), p in sorted(results.items()):
            p.used, p.note = False, ""
            r = p.result
            if not r.success:
                continue
            if self.scale_check != "off" and _scale_disagreement(r.transform, maps[i], maps[j]) > SCALE_TOLERANCE:
                p.note = (
                    f"scale {r.transform.scale:.3f} between {names[i]} and {names[j]} disagrees with their resolutions "
                    f"({maps[i].resolution:g} and {maps[j].resolution:g} m/cell say {maps[j].resolution / maps[i].resolution:.3f})"
                )
                if self.scale_check == "reject":
                    p.note += "; not used"
                    warnings.append(p.note)
                    continue
                warnings.append(p.note)
            pts = _overlap_points(maps[i], maps[j], r.transform)
            edges.append(Edge(i, j, r.transform, max(float(r.confidence), 1e-3), pts))
        poses, report = solve(len(maps), edges, reference, shapes=[m.shape for m in maps],
                              loop_tolerance=self.loop_tolerance, joint=self.joint)
        dropped = {(e.i, e.j) for e in report.dropped}
        for e in edges:
            p = results[(e.i, e.j)]
            if (e.i, e.j) in dropped:
                p.note = (p.note + "; " if p.note else "") + (
                    f"dropped: disagrees with the other alignments by {_worst_residual(report, e):.1f} px")
                warnings.append(f"{names[e.i]} - {names[e.j]}: {p.note}")
            else:
                p.used = True
        if METHODS[self.method].verified:
            # An alignment no loop checks that rests on few walls: the user should look.
            for i, j in bridges([(i, j) for (i, j), p in results.items() if p.used]):
                note = few_walls_warning(results[(i, j)].result.verification, self.options)
                if note:
                    warnings.append(f"{names[i]} - {names[j]}: {note}")
        return poses, report, warnings

    def _target_resolution(self, maps, placed) -> float:
        return float(self.resolution) if self.resolution is not None else min(maps[k].resolution for k in placed)

    def _fuse(self, maps, names, results, poses, report, warnings, reference, stats) -> MergeResult:
        n = len(maps)
        pairs = [results[k] for k in sorted(results)]
        placed = [k for k in range(n) if poses[k] is not None]
        unplaced = [names[k] for k in range(n) if poses[k] is None]
        alignments: list[AlignResult | None] = [None] * n
        by_edge = {(e.i, e.j): e for e in report.tree}
        for (i, j), e in by_edge.items():
            child = j if report.parents[j] == i else i
            alignments[child] = results[(i, j)].result
        for k in range(n):
            if poses[k] is None:
                tried = [p.result for p in pairs if k in (p.i, p.j)]
                alignments[k] = max(tried, key=lambda r: r.confidence, default=None)
        confidences = [(_chain_confidence(report, k) if poses[k] is not None else None) for k in range(n)]
        warnings = warnings + _walls_everywhere_warnings(names, pairs)
        base = dict(names=names, alignments=alignments, parents=list(report.parents), unplaced=unplaced, fusion=self.fusion,
                    inputs=maps, confidences=confidences, pairs=pairs, warnings=warnings, reference=reference, stats=stats, graph=report)
        if len(placed) < 2:
            others = [p.result for p in pairs if reference in (p.i, p.j)] or [p.result for p in pairs]
            best = max(others, key=lambda r: r.confidence, default=None)
            reason = best.message if best is not None else "no alignment"
            aligned = sorted({x for p in pairs if p.result.success and reference not in (p.i, p.j) for x in (p.i, p.j)})
            if aligned:
                # Others align with each other: only the reference is alone.
                message = (f"the reference {names[reference]} could not be aligned with any other map ({reason}); "
                           f"{', '.join(names[k] for k in aligned)} align with each other: make one of them the reference")
                return MergeResult(False, None, transforms=[None] * n, message=message, **base)
            return MergeResult(False, None, transforms=[None] * n, message=f"no two maps could be aligned ({reason})", **base)
        t1 = time.perf_counter()
        ref = maps[reference]
        res = self._target_resolution(maps, placed)
        f = ref.resolution / res
        # The reference's pixels -> pixels of the target resolution (cell edges kept).
        to_target = AffineTransform(np.array([[f, 0.0, (f - 1) / 2], [0.0, f, (f - 1) / 2], [0.0, 0.0, 1.0]]))
        shapes = [maps[k].shape for k in placed]
        placed_t = [to_target @ poses[k] for k in placed]  # type: ignore[operator]
        input_cells = sum(m.data.size for m in maps)
        problem = canvas_problem(shapes, placed_t, (1, 1), input_cells=int(input_cells * max(1.0, f * f)),
                                 max_canvas_cells=self.limits.max_canvas_cells, max_canvas_factor=self.limits.max_canvas_factor)
        if problem:
            return MergeResult(False, None, transforms=[None] * n, message=problem, **base)
        fused, shift = fuse_on_canvas([maps[k] for k in placed], placed_t, fusion=self.fusion, interpolation=self.interpolation)
        ch = fused.shape[0]
        transforms: list[AffineTransform | None] = [None] * n
        for k, t in zip(placed, placed_t):
            transforms[k] = shift @ t
        # The canvas's lower-left corner, in the reference's metric frame.
        back = (shift @ to_target).inverse
        corner = ref.pixel_to_metric(back(np.array([[-0.5, ch - 0.5]])))[0]
        grid = OccupancyGrid(fused, resolution=res, origin=(float(corner[0]), float(corner[1]), ref.origin[2]), name="merged")
        stats.fuse_s = time.perf_counter() - t1
        msg = f"merged {len(placed)} of {n} maps" + (f"; unplaced: {', '.join(unplaced)}" if unplaced else "")
        return MergeResult(True, grid, transforms=transforms, message=msg, **base)


def _walls_everywhere_warnings(names: list[str], pairs) -> list[str]:
    """A warning for each map that every alignment tried with it declined as walls
    everywhere (:func:`gridmerge.align.align`: noise, or values read wrongly)."""
    out = []
    for k, name in enumerate(names):
        flagged = []
        for p in pairs:
            if k not in (p.i, p.j):
                continue
            w = p.result.details.get("walls_everywhere")
            flagged.append(w["share"] if w and w["map"] == ("a" if p.i == k else "b") else None)
        if flagged and all(f is not None for f in flagged):
            out.append(f"{name} is walls everywhere ({max(flagged):.0%} of its known cells lie near an occupied one), "
                       f"so it was not aligned: {_WALLS_EVERYWHERE_CAUSES}")
    return out


def _chain_confidence(report: GraphReport, k: int) -> float:
    """The weakest confidence on map ``k``'s chain to the reference (1 for the reference)."""
    conf = 1.0
    by_pair = {(e.i, e.j): e for e in report.tree}
    seen = set()
    while report.parents[k] is not None and k not in seen:
        seen.add(k)
        p = report.parents[k]
        e = by_pair.get((p, k)) or by_pair.get((k, p))
        if e is None:
            break
        conf = min(conf, e.confidence)
        k = p
    return conf


def _worst_residual(report: GraphReport, e: Edge) -> float:
    return float(report.residuals.get((e.i, e.j), float("nan")))


def merge(
    maps: Sequence[OccupancyGrid],
    *,
    method: str = "hybrid",
    fusion: str = "average",
    reference: int | str = 0,
    resolution: float | None = None,
    pairs: str = "auto",
    executor: Executor | None = None,
    scale_check: str = "warn",
    joint: bool = True,
    loop_tolerance: float = 20.0,
    options: AlignOptions | None = None,
    rng=0,
    interpolation: str = "linear",
    max_canvas_factor: float | None = None,
    max_canvas_cells: int | None = None,
    limits: Limits | None = None,
    progress: Progress | None = None,
    names: Sequence[str] | None = None,
    **overrides,
) -> MergeResult:
    """Merge two or more maps into the metric frame of ``maps[reference]``.

    The pairs of maps are aligned (:func:`gridmerge.align`), the confident alignments
    placed in one frame by the map graph (:mod:`gridmerge.graph`: most reliable spanning
    tree from the reference, joint least squares over the loops), and the placed maps
    fused onto one canvas. Maps that overlap no placed map are reported in
    ``unplaced``; the merge of the others still succeeds.

    Parameters
    ----------
    maps : sequence of OccupancyGrid
        At least two maps.
    method : str
        Alignment method (see :func:`gridmerge.align`).
    fusion : {"average", "logodds", "max"}
        Cell fusion rule (:mod:`gridmerge.fuse`); ``"average"`` is the paper's eq. (9).
    reference : int or str
        Index (or name) of the map whose metric frame the merged map keeps.
    resolution : float, optional
        The merged map's resolution (m/cell); default the finest of the placed maps.
    pairs : {"auto", "all"}
        Which pairs are searched (see :class:`Merger`).
    executor : gridmerge.parallel.Executor, optional
        Runs features and pairwise alignments (serial by default; a process pool or a
        Dask cluster give the same results).
    scale_check : {"warn", "reject", "off"}
        Pairs whose scale disagrees with the maps' resolutions (see :class:`Merger`).
    joint : bool
        Refine all transforms jointly when the map graph has loops.
    loop_tolerance : float
        Pixels by which an alignment may disagree with the others before it is dropped.
    options : AlignOptions, optional
        Alignment settings; keyword ``overrides`` change single fields.
    rng : int or numpy.random.Generator
        Seed of every random choice.
    interpolation : {"linear", "nearest"}
        Resampling of the warped maps.
    max_canvas_factor, max_canvas_cells : float, int, optional
        The merge is declined when the merged canvas would hold more than
        ``max_canvas_cells`` cells or more than ``max_canvas_factor`` times the cells of
        all inputs together (defaults from ``limits``). Nothing is allocated then.
    limits : gridmerge.limits.Limits, optional
        Default :data:`gridmerge.limits.DEFAULT_LIMITS`. When given, its
        ``max_keypoints`` and ``max_feature_pixels`` also cap the features of every map
        (``options.max_keypoints`` is replaced, unless given as a keyword override).
    progress : callable, optional
        ``progress(stage, done, total)``.
    names : sequence of str, optional
        The maps' names (default each map's ``name``, else ``map0``, ``map1``, ...);
        must be unique.

    Returns
    -------
    MergeResult
    """
    maps = list(maps)
    if len(maps) < 2:
        raise GridMergeError(f"merging needs at least two maps, got {len(maps)}")
    labels = list(names) if names is not None else [m.name or f"map{k}" for k, m in enumerate(maps)]
    if len(labels) != len(maps):
        raise GridMergeError(f"{len(labels)} names for {len(maps)} maps")
    if len(set(labels)) != len(labels):
        # Two inputs of one name (e.g. the same file twice): tell them apart by position.
        labels = [f"{name}#{k}" if labels.count(name) > 1 else name for k, name in enumerate(labels)]
    if isinstance(reference, (int, np.integer)) and not isinstance(reference, bool) and not 0 <= int(reference) < len(maps):
        raise GridMergeError(f"reference {reference} is not the index of a map (0..{len(maps) - 1})")
    merger = Merger(method=method, fusion=fusion, reference=reference, resolution=resolution, pairs=pairs,
                    executor=executor, scale_check=scale_check, joint=joint, loop_tolerance=loop_tolerance,
                    options=options, rng=rng, interpolation=interpolation, max_canvas_factor=max_canvas_factor,
                    max_canvas_cells=max_canvas_cells, limits=limits, progress=progress, **overrides)
    for m, label in zip(maps, labels):
        merger.update(m, label)
    result = merger.merge()
    if names is None:
        result.names = [m.name or f"map{k}" for k, m in enumerate(maps)]
        result.unplaced = [result.names[labels.index(u)] for u in result.unplaced]
    return result

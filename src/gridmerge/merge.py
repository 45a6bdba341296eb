"""Merging maps into one: place each map in the reference's frame, then fuse the cells.

Examples
--------
>>> import gridmerge
>>> from gridmerge import samples
>>> a, b, truth = samples.table1_pair()
>>> m = gridmerge.merge([a, b])
>>> m.success, m.grid.resolution == a.resolution, m.unplaced
(True, True, [])
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from .align import METHODS, AlignOptions, AlignResult, align
from .errors import GridMergeError
from .fuse import FUSION_RULES, fuse_values, warp_values
from .grid import OccupancyGrid
from .limits import DEFAULT_LIMITS, Limits, extractor_for
from .transforms import AffineTransform, SimilarityTransform, pixel_to_metric

__all__ = ["MergeResult", "merge", "canvas_for", "canvas_problem", "MAX_CANVAS_FACTOR", "MAX_CANVAS_CELLS"]

#: A merged canvas may hold at most this many times the cells of all inputs together
#: (:data:`gridmerge.limits.DEFAULT_LIMITS`).
MAX_CANVAS_FACTOR = DEFAULT_LIMITS.max_canvas_factor
#: ... and never more than this many cells (fusing two maps takes about 40 bytes per cell).
MAX_CANVAS_CELLS = DEFAULT_LIMITS.max_canvas_cells


@dataclass
class MergeResult:
    """The outcome of :func:`merge`.

    Attributes
    ----------
    success : bool
        ``True`` when at least two maps were placed and fused.
    grid : OccupancyGrid or None
        The merged map, at the reference map's resolution, with a ROS origin such that
        every point of the reference map's metric frame keeps its coordinates.
    names : list of str
        The input maps' names (their paths when loaded from files).
    transforms : list of (AffineTransform or None)
        For each input map, its image pixels -> the merged map's image pixels; ``None``
        for maps that could not be placed.
    alignments : list of (AlignResult or None)
        For each input map, the alignment that placed it (``None`` for the reference).
    parents : list of (int or None)
        For each placed map, the map it was aligned against.
    unplaced : list of str
        Names of the maps that overlap no placed map confidently.
    message : str
    fusion : str
    elapsed_s : float
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

    def __bool__(self) -> bool:
        return self.success

    def to_dict(self) -> dict:
        """A JSON-ready summary (the CLI's ``--json`` output)."""
        maps = []
        for k, name in enumerate(self.names):
            t = self.transforms[k]
            al = self.alignments[k]
            entry: dict = {"name": name, "placed": t is not None, "parent": self.parents[k]}
            if t is not None:
                entry["matrix"] = t.matrix.tolist()
                entry["rotation_deg"] = math.degrees(t.rotation)
                entry["scale"] = t.scale
                if self.grid is not None and self.inputs:
                    m = pixel_to_metric(t, self.inputs[k], self.grid)
                    x, y = m.translation
                    entry["metric"] = {"x": float(x), "y": float(y), "yaw": float(m.rotation), "scale": float(m.scale)}
                entry["confidence"] = 1.0 if al is None else float(al.confidence)
            if al is not None:
                entry["alignment"] = al.to_dict()
            maps.append(entry)
        out: dict = {
            "success": bool(self.success),
            "message": self.message,
            "fusion": self.fusion,
            "elapsed_s": float(self.elapsed_s),
            "maps": maps,
            "unplaced": list(self.unplaced),
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


def merge(
    maps: Sequence[OccupancyGrid],
    *,
    method: str = "hybrid",
    fusion: str = "average",
    reference: int = 0,
    options: AlignOptions | None = None,
    rng=0,
    interpolation: str = "linear",
    max_canvas_factor: float | None = None,
    max_canvas_cells: int | None = None,
    limits: Limits | None = None,
    **overrides,
) -> MergeResult:
    """Merge two or more maps into the frame of ``maps[reference]``.

    Each map is aligned (:func:`gridmerge.align`) against the maps already placed, the
    reference first; maps that align with none are reported in ``unplaced``. The placed
    maps are warped onto a canvas that holds them all and fused cell by cell.

    Parameters
    ----------
    maps : sequence of OccupancyGrid
        At least two maps.
    method : str
        Alignment method (see :func:`gridmerge.align`).
    fusion : {"average", "logodds", "max"}
        Cell fusion rule (:mod:`gridmerge.fuse`); ``"average"`` is the paper's eq. (9).
    reference : int
        Index of the map whose frame and resolution the merged map keeps.
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

    Returns
    -------
    MergeResult
    """
    t0 = time.perf_counter()
    maps = list(maps)
    if len(maps) < 2:
        raise GridMergeError(f"merging needs at least two maps, got {len(maps)}")
    if fusion not in FUSION_RULES:
        raise GridMergeError(f"unknown fusion rule {fusion!r} (use one of {', '.join(FUSION_RULES)})")
    if not 0 <= reference < len(maps):
        raise GridMergeError(f"reference {reference} is not the index of a map (0..{len(maps) - 1})")
    lim = (limits or DEFAULT_LIMITS).replace(max_canvas_factor=max_canvas_factor, max_canvas_cells=max_canvas_cells)
    if limits is not None and "max_keypoints" not in overrides:
        overrides["max_keypoints"] = limits.max_keypoints
    opts = replace(options or AlignOptions(), **overrides)
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    names = [m.name or f"map{k}" for k, m in enumerate(maps)]
    if method not in METHODS:
        raise GridMergeError(f"unknown alignment method {method!r} (use one of {', '.join(METHODS)})")
    spec = METHODS[method]
    if limits is not None:
        extractor = extractor_for(method, lim.replace(max_keypoints=opts.max_keypoints), opts)
    else:
        extractor = spec.extractor(opts) if spec.extractor is not None else None
    feats = [extractor(m) if extractor is not None else None for m in maps]

    n = len(maps)
    to_ref: list[AffineTransform | None] = [None] * n
    to_ref[reference] = SimilarityTransform()
    alignments: list[AlignResult | None] = [None] * n
    parents: list[int | None] = [None] * n
    tried: set[tuple[int, int]] = set()
    progress = True
    while progress:
        progress = False
        for k in range(n):
            if to_ref[k] is not None:
                continue
            for j in range(n):
                if to_ref[j] is None or (j, k) in tried:
                    continue
                tried.add((j, k))
                r = align(maps[j], maps[k], method=method, options=opts, rng=gen, features=(feats[j], feats[k]), extractor=extractor)
                if r.success and not np.isfinite(r.transform.params).all():  # type: ignore[union-attr]
                    # Never composed or warped (see canvas_problem for the other bounds).
                    r = replace(r, success=False, transform=None, message="declined: the transform is not finite")
                if alignments[k] is None or r.confidence > alignments[k].confidence:
                    alignments[k] = r
                if r.success:
                    to_ref[k] = to_ref[j] @ r.transform  # type: ignore[operator]
                    parents[k] = j
                    alignments[k] = r
                    progress = True
                    break

    placed = [k for k in range(n) if to_ref[k] is not None]
    unplaced = [names[k] for k in range(n) if to_ref[k] is None]
    base = dict(names=names, alignments=alignments, parents=parents, unplaced=unplaced, fusion=fusion, inputs=maps)
    if len(placed) < 2:
        why = alignments[next(k for k in range(n) if k != reference)]
        reason = why.message if why is not None else "no alignment"
        return MergeResult(False, None, transforms=[None] * n, message=f"no two maps could be aligned ({reason})", elapsed_s=time.perf_counter() - t0, **base)

    ref = maps[reference]
    shapes, placed_transforms = [maps[k].shape for k in placed], [to_ref[k] for k in placed]
    problem = canvas_problem(
        shapes,
        placed_transforms,  # type: ignore[arg-type]
        ref.shape,
        input_cells=sum(m.data.size for m in maps),
        max_canvas_cells=lim.max_canvas_cells,
        max_canvas_factor=lim.max_canvas_factor,
    )
    if problem:
        return MergeResult(False, None, transforms=[None] * n, message=problem, elapsed_s=time.perf_counter() - t0, **base)
    (ch, cw), (left, top, bottom) = canvas_for(shapes, placed_transforms, ref.shape)  # type: ignore[arg-type]
    shift = SimilarityTransform(translation=(left, top))
    transforms: list[AffineTransform | None] = [None if t is None else shift @ t for t in to_ref]
    layers = [warp_values(maps[k].data, transforms[k].params, (ch, cw), interpolation=interpolation) for k in placed]  # type: ignore[union-attr]
    fused = fuse_values(layers, fusion)
    ox, oy, yaw = ref.origin
    res = ref.resolution
    dx, dy = -left * res, -bottom * res
    c, s = math.cos(yaw), math.sin(yaw)
    origin = (ox + c * dx - s * dy, oy + s * dx + c * dy, yaw)
    grid = OccupancyGrid(fused, resolution=res, origin=origin, name="merged")
    msg = f"merged {len(placed)} of {n} maps" + (f"; unplaced: {', '.join(unplaced)}" if unplaced else "")
    return MergeResult(True, grid, transforms=transforms, message=msg, elapsed_s=time.perf_counter() - t0, **base)

"""Pictures of an alignment and a merge (needs the ``plot`` extra: matplotlib).

:func:`plot_merge` draws the paper's Fig. 3 (matched keypoints between the two maps) above
its Fig. 2 (the merged map) and returns the PNG bytes; :func:`plot_alignment` draws the
two maps on each other at an alignment's pose, the walls that agree marked
(:func:`alignment_overlay`, which needs only numpy and OpenCV); :func:`plot_fleet` many
maps and where each went; :func:`save_plot` writes the bytes atomically.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from .align import AlignResult
from .errors import GridMergeError
from .grid import OccupancyGrid

__all__ = ["require_matplotlib", "plot_merge", "plot_alignment", "alignment_overlay", "plot_fleet", "save_plot"]


def require_matplotlib():
    """Import matplotlib with a headless backend, or raise a one-line GridMergeError."""
    try:
        import matplotlib

        matplotlib.use("Agg", force=True)
        import matplotlib.pyplot as plt  # noqa: F401
    except ImportError:
        raise GridMergeError("pictures need matplotlib: pip install 'gridmerge[plot]'") from None
    return plt


def _crop(grid: OccupancyGrid, margin: int = 20):
    """The rendered grid cut to its known cells (plus a margin), and the cut's (x, y) offset."""
    cut, offset = grid.crop_known(margin)
    return cut.render(), offset


def _side_by_side(a: np.ndarray, b: np.ndarray, gap: int = 10):
    h = max(a.shape[0], b.shape[0])
    canvas = np.full((h, a.shape[1] + gap + b.shape[1]), 255, dtype=np.uint8)
    canvas[: a.shape[0], : a.shape[1]] = a
    canvas[: b.shape[0], a.shape[1] + gap :] = b
    return canvas, a.shape[1] + gap


def plot_merge(
    a: OccupancyGrid,
    b: OccupancyGrid,
    alignment: AlignResult,
    merged: OccupancyGrid | None = None,
    *,
    max_lines: int = 150,
    dpi: int = 110,
) -> bytes:
    """PNG bytes: matches between ``a`` and ``b`` (top) and the merged map (bottom).

    Parameters
    ----------
    a, b : OccupancyGrid
    alignment : AlignResult
        Its inlier correspondences are drawn as lines (at most ``max_lines``).
    merged : OccupancyGrid, optional
        Drawn below when given.
    """
    plt = require_matplotlib()
    rows = 2 if merged is not None else 1
    fig, axes = plt.subplots(rows, 1, figsize=(10, 5.5 * rows), squeeze=False)
    img_a, off_a = _crop(a)
    img_b, off_b = _crop(b)
    img, off = _side_by_side(img_a, img_b)
    ax = axes[0, 0]
    ax.imshow(img, cmap="gray", vmin=0, vmax=255, interpolation="nearest")
    pts = alignment.inlier_xy
    if len(pts) > max_lines:
        pts = pts[np.linspace(0, len(pts) - 1, max_lines).astype(int)]
    pts = pts - np.stack([off_b, off_a])  # into the cropped panels' pixels
    for (xb, yb), (xa, ya) in pts:
        ax.plot([xa, xb + off], [ya, yb], "-", color="tab:red", lw=0.6, alpha=0.7)
    if len(pts):
        ax.plot(pts[:, 1, 0], pts[:, 1, 1], ".", color="tab:blue", ms=3)
        ax.plot(pts[:, 0, 0] + off, pts[:, 0, 1], ".", color="tab:blue", ms=3)
    state = "aligned" if alignment.success else "declined"
    ax.set_title(
        f"{Path(a.name or 'map a').name}  |  {Path(b.name or 'map b').name}: {alignment.inliers} inlier matches, {state}, "
        f"confidence {alignment.confidence:.2f}",
        fontsize=9,
    )
    ax.set_axis_off()
    if merged is not None:
        ax = axes[1, 0]
        ax.imshow(_crop(merged)[0], cmap="gray", vmin=0, vmax=255, interpolation="nearest")
        t = alignment.transform
        sub = ""
        if t is not None:
            sub = f": rotation {np.degrees(t.rotation):.2f} deg, scale {t.scale:.4f}, translation ({t.translation[0]:.1f}, {t.translation[1]:.1f}) px"
        ax.set_title("merged map" + sub, fontsize=9)
        ax.set_axis_off()
    return _png(plt, fig, dpi)


#: Colours (RGB, 0-255) of :func:`alignment_overlay`.
OVERLAY_COLOURS = {
    "unknown": (150, 150, 150),
    "free_a": (236, 236, 236),    # only a knows the cell is free
    "free_b": (214, 232, 214),    # only b (moved) knows it is free
    "free_both": (255, 255, 255),  # the overlap's free cells
    "wall_a": (200, 30, 30),      # a's walls with no wall of b near
    "wall_b": (30, 80, 210),      # b's walls with no wall of a near
    "wall_both": (0, 0, 0),       # walls of either map within the tolerance of the other's
}


#: :func:`alignment_overlay` with ``line=None``: pictures up to this many cells on a side
#: draw one-cell walls; larger ones a cell of wall per this many cells of side.
_SHOWN_SIDE = 900
_CELLS_PER_LINE = 600


def alignment_overlay(a: OccupancyGrid, b: OccupancyGrid, transform, *, tolerance: float = 3.0, margin: int = 10,
                      max_side: int = 2000, line: int | None = 1) -> tuple[np.ndarray, tuple[int, int]]:
    """The two maps drawn on each other at ``transform``: what a pose rests on.

    ``b`` is moved by ``transform`` (b's pixels -> a's, an :class:`~gridmerge.transforms.AffineTransform`
    or ``(2, 3)``/``(3, 3)`` array) onto a canvas in a's pixels that holds both maps'
    known cells (plus ``margin``). Free cells are light (white where both maps know
    them: the overlap), walls red (a) and blue (b), and black where a wall of either map
    lies within ``tolerance`` cells (a's) of a wall of the other *in the overlap*: the
    walls that agree. A pose on a few black cells is a weak claim whatever its
    confidence. The maps are drawn as given (isolated hits included), so the black cells
    are close to, not exactly, what the alignment counted
    (:attr:`~gridmerge.align.AlignResult.verification`). A canvas longer than
    ``max_side`` on a side is shrunk by a whole factor, a wall anywhere in a block
    kept; ``line`` > 1 draws every wall cell that many cells wide (after shrinking),
    for pictures shown smaller than their cells; ``None`` chooses it for a picture
    shown at about 800 pixels: one cell up to 900 on a side, else a cell per 600
    (rounded up), so that one-cell walls do not vanish.

    Returns
    -------
    image : (H, W, 3) uint8 array
        The picture, RGB (:data:`OVERLAY_COLOURS`).
    offset : (int, int)
        a's pixel ``(x, y)`` of the picture's top-left cell, before any shrinking.

    Examples
    --------
    >>> from gridmerge import samples
    >>> a, b, truth = samples.robot_pair(0)
    >>> img, offset = alignment_overlay(a, b, truth)
    >>> img.ndim, img.dtype.name
    (3, 'uint8')
    >>> black = (img == 0).all(axis=2).sum()
    >>> bool(black > 100)  # at the truth many walls agree
    True
    """
    import cv2

    m = np.asarray(getattr(transform, "params", transform), dtype=float)
    m = m[:2] if m.shape == (3, 3) else m
    if m.shape != (2, 3) or not np.isfinite(m).all():
        raise GridMergeError(f"a transform must be a finite 2x3 or 3x3 matrix, got shape {m.shape}")
    bb = b.known_bounds()
    bx0, by0, bx1, by1 = (0, 0, b.width, b.height) if bb is None else bb
    corners = np.array([[bx0, by0], [bx1, by0], [bx0, by1], [bx1, by1]], float) @ m[:, :2].T + m[:, 2]
    ab = a.known_bounds()
    x0, y0, x1, y1 = (0, 0, a.width, a.height) if ab is None else ab
    x0 = int(np.floor(min(x0, corners[:, 0].min()))) - margin
    y0 = int(np.floor(min(y0, corners[:, 1].min()))) - margin
    x1 = int(np.ceil(max(x1, corners[:, 0].max()))) + margin
    y1 = int(np.ceil(max(y1, corners[:, 1].max()))) + margin
    w, h = x1 - x0, y1 - y0
    shift = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0]])

    def drawn(grid: OccupancyGrid, mat: np.ndarray):
        # known, occupied and free masks of grid moved by mat onto the canvas (nearest cells).
        masks = (grid.known, grid.occupied(), grid.free())
        return [cv2.warpAffine(x.astype(np.uint8), mat, (w, h), flags=cv2.INTER_NEAREST, borderValue=0) > 0 for x in masks]

    to_canvas_b = np.vstack([shift, [0, 0, 1]]) @ np.vstack([m, [0, 0, 1]])
    ka, oa, fa = drawn(a, shift)
    kb, ob, fb = drawn(b, to_canvas_b[:2])
    rows, cols = np.flatnonzero((ka | kb).any(axis=1)), np.flatnonzero((ka | kb).any(axis=0))
    if len(rows):  # cut to the known cells of either map (b's box, turned, holds much unknown)
        r0, r1 = max(0, rows[0] - margin), min(h, rows[-1] + 1 + margin)
        c0, c1 = max(0, cols[0] - margin), min(w, cols[-1] + 1 + margin)
        ka, oa, fa, kb, ob, fb = (x[r0:r1, c0:c1] for x in (ka, oa, fa, kb, ob, fb))
        x0, y0, h, w = x0 + int(c0), y0 + int(r0), int(r1 - r0), int(c1 - c0)
    both = ka & kb
    near_a = cv2.distanceTransform((~oa).astype(np.uint8), cv2.DIST_L2, 3) <= tolerance if oa.any() else np.zeros_like(oa)
    near_b = cv2.distanceTransform((~ob).astype(np.uint8), cv2.DIST_L2, 3) <= tolerance if ob.any() else np.zeros_like(ob)
    agree_a, agree_b = oa & near_b & both, ob & near_a & both
    layers = [("free_a", fa), ("free_b", fb), ("free_both", fa & fb), ("wall_a", oa), ("wall_b", ob),
              ("wall_both", agree_a | agree_b)]
    factor = max(1, int(np.ceil(max(w, h) / max(1, int(max_side)))))
    if factor > 1:
        hh, ww = -(-h // factor), -(-w // factor)

        def pooled(mask):  # a block is set when any of its cells is
            padded = np.zeros((hh * factor, ww * factor), bool)
            padded[:h, :w] = mask
            return padded.reshape(hh, factor, ww, factor).any(axis=(1, 3))

        layers = [(name, pooled(mask)) for name, mask in layers]
        h, w = hh, ww
    if line is None:
        side = max(h, w)
        line = 1 if side <= _SHOWN_SIDE else int(np.ceil(side / _CELLS_PER_LINE))
    if int(line) > 1:
        kernel = np.ones((int(line), int(line)), np.uint8)
        layers = [(name, cv2.dilate(mask.astype(np.uint8), kernel) > 0 if name.startswith("wall") else mask)
                  for name, mask in layers]
    img = np.empty((h, w, 3), np.uint8)
    img[:] = OVERLAY_COLOURS["unknown"]
    for name, mask in layers:
        img[mask] = OVERLAY_COLOURS[name]
    return img, (x0, y0)


def plot_alignment(a: OccupancyGrid, b: OccupancyGrid, alignment: AlignResult, *, tolerance: float = 3.0,
                   dpi: int = 110) -> bytes:
    """PNG bytes: the two maps drawn on each other at the alignment's pose
    (:func:`alignment_overlay`), titled with the decision, its confidence and how many
    walls agree; for a declined alignment, its best candidate pose (when it had one),
    marked as declined with the reason. Without any pose, the two maps side by side.

    Parameters
    ----------
    a, b : OccupancyGrid
        The maps as aligned (``b`` onto ``a``).
    alignment : AlignResult
    tolerance : float
        Cells (a's) within which walls count as agreeing in the picture.
    """
    plt = require_matplotlib()
    names = f"{Path(a.name or 'map a').name} + {Path(b.name or 'map b').name}"
    pose = alignment.transform if alignment.success else alignment.candidate
    fig, ax = plt.subplots(1, 1, figsize=(10, 8))
    if pose is None:
        img, _ = _side_by_side(_crop(a)[0], _crop(b)[0])
        ax.imshow(img, cmap="gray", vmin=0, vmax=255, interpolation="nearest")
        ax.set_title(f"{names}: not aligned (no pose)\n{alignment.message}", fontsize=9, wrap=True)
    else:
        img, _ = alignment_overlay(a, b, pose, tolerance=tolerance, line=None)  # shown at about 800 pixels
        ax.imshow(img, interpolation="nearest")
        v = alignment.verification
        counts = "" if v is None else v.wall_counts(("a", "b"))
        walls = f"; walls agree on {v.wall_agreement:.0%} of the overlap ({counts})" if counts else ""
        if alignment.success:
            head = f"{names}: aligned, confidence {alignment.confidence:.2f}{walls}"
            sub = "red: a's walls, blue: b's, black: walls that agree in the overlap (white)"
        else:
            head = f"{names}: DECLINED; its best candidate pose drawn{walls}"
            sub = alignment.message
        ax.set_title(f"{head}\n{sub}", fontsize=9, wrap=True)
    ax.set_axis_off()
    return _png(plt, fig, dpi)


def plot_fleet(result, *, dpi: int = 110, max_thumbnails: int = 16) -> bytes:
    """PNG bytes: every input map in its own frame (left) and the merged map (right) with
    the outline of each placed map's known area in its colour.

    Parameters
    ----------
    result : gridmerge.MergeResult
        A merge of any number of maps (its ``inputs`` and ``transforms`` are drawn).
    """
    import cv2

    plt = require_matplotlib()
    maps = list(result.inputs)
    n = min(len(maps), max_thumbnails)
    cols = 2 if n > 1 else 1
    rows = int(np.ceil(n / cols))
    fig = plt.figure(figsize=(15, max(5.0, 2.4 * rows)))
    grid_spec = fig.add_gridspec(rows, cols + 3)
    colours = plt.get_cmap("tab10" if n <= 10 else "tab20")
    for k in range(n):
        ax = fig.add_subplot(grid_spec[k // cols, k % cols])
        ax.imshow(_crop(maps[k], 5)[0], cmap="gray", vmin=0, vmax=255, interpolation="nearest")
        placed = result.transforms[k] is not None
        ax.set_title(f"{Path(result.names[k]).name}" + ("" if placed else " (unplaced)"), fontsize=8,
                     color=colours(k % colours.N) if placed else "black")
        ax.set_axis_off()
    ax = fig.add_subplot(grid_spec[:, cols:])
    if result.grid is not None:
        merged = result.grid
        cut, (ox, oy) = _crop(merged, 10)
        ax.imshow(cut, cmap="gray", vmin=0, vmax=255, interpolation="nearest")
        for k, t in enumerate(result.transforms):
            if t is None or k >= len(maps):
                continue
            known = maps[k].known.astype(np.uint8)
            warped = cv2.warpAffine(known, np.ascontiguousarray(t.matrix), (merged.width, merged.height), flags=cv2.INTER_NEAREST)
            warped = cv2.morphologyEx(warped, cv2.MORPH_CLOSE, np.ones((9, 9), np.uint8))
            contours, _ = cv2.findContours(warped, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
            for c in contours:
                if len(c) < 3:
                    continue
                c = c[:, 0, :].astype(float)
                c = np.vstack([c, c[:1]])
                ax.plot(c[:, 0] - ox, c[:, 1] - oy, "-", color=colours(k % colours.N), lw=1.2)
        ax.set_title(f"merged map: {result.message}", fontsize=9)
    else:
        ax.text(0.5, 0.5, f"not merged: {result.message}", ha="center", va="center", wrap=True)
    ax.set_axis_off()
    return _png(plt, fig, dpi)


def _png(plt, fig, dpi: int) -> bytes:
    """The figure as PNG bytes; the figure is closed."""
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    return buf.getvalue()


def save_plot(png: bytes, path) -> Path:
    """Write PNG bytes atomically."""
    from .io.atomic import atomic_write

    p = Path(path)
    atomic_write(p, png)
    return p

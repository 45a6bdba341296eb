"""Pictures of an alignment and a merge (needs the ``plot`` extra: matplotlib).

:func:`plot_merge` draws the paper's Fig. 3 (matched keypoints between the two maps) above
its Fig. 2 (the merged map) and returns the PNG bytes; :func:`save_plot` writes them
atomically.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from .align import AlignResult
from .errors import GridMergeError
from .grid import OccupancyGrid

__all__ = ["require_matplotlib", "plot_merge", "plot_fleet", "save_plot"]


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

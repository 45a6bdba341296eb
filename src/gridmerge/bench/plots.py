"""Pictures of a benchmark run (matplotlib, Agg backend; PNG bytes)."""

from __future__ import annotations

import io
from typing import Sequence

import numpy as np

from .datasets import unswapped

__all__ = ["PLOTS", "make_plots"]

#: File names of the plots, and what they show.
PLOTS = {
    "success_vs_overlap.png": "success rate vs overlap (simulated positive pairs)",
    "success_vs_shared_walls.png": "success rate vs the wall cells both robots saw (simulated positive pairs)",
    "success_vs_rotation.png": "success rate vs rotation (simulated positive pairs)",
    "success_vs_scale.png": "success rate vs scale (simulated positive pairs)",
    "corner_error_cdf.png": "CDF of the corner error (simulated and paper positive pairs; declined = never)",
    "time_vs_size.png": "wall time of align vs cells of both maps (every case)",
}


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    _plt().close(fig)
    return buf.getvalue()


def _plain_log_ticks(axis) -> None:
    """Label a log axis at 1, 2 and 5 of each decade in plain numbers ("0.2", "5"),
    unlabelled minor ticks: matplotlib's default labels every minor tick of a short
    axis in powers of ten, and they overlap."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:g}"))
    axis.set_minor_formatter(NullFormatter())


def _binned(plt, records, methods, key, edges, xlabel, title, transform=None, log=False):
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    edges = np.asarray(edges, dtype=float)
    centres = np.sqrt(edges[:-1] * edges[1:]) if log else (edges[:-1] + edges[1:]) / 2
    for m in methods:
        sel = [r for r in records if r["method"] == m and r.get(key) is not None]
        x = np.array([r[key] if transform is None else transform(r[key]) for r in sel], dtype=float)
        ok = np.array([r["success"] for r in sel], dtype=bool)
        rates, xs = [], []
        for i in range(len(edges) - 1):
            inb = (x >= edges[i]) & ((x < edges[i + 1]) | ((i == len(edges) - 2) & (x <= edges[i + 1])))
            if inb.any():
                rates.append(ok[inb].mean())
                xs.append(centres[i])
        if xs:
            ax.plot(xs, rates, "o-", label=f"{m} ({len(sel)} pairs)")
    if log:
        ax.set_xscale("log")
        ax.set_xticks(edges)
        ax.set_xticklabels([f"{e:g}" for e in edges])
        ax.minorticks_off()
    ax.set_ylim(-0.03, 1.03)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("success rate")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    fig.tight_layout()
    return _png(fig)


def make_plots(records: Sequence[dict], methods: Sequence[str]) -> dict:
    """PNG bytes of every plot of :data:`PLOTS`, by file name."""
    plt = _plt()
    sim = [r for r in records if unswapped(r["dataset"]) == "simulated" and r["positive"]]
    out = {}
    out["success_vs_overlap.png"] = _binned(
        plt, sim, methods, "overlap", [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 1.0], "overlap fraction", "Success vs overlap"
    )
    out["success_vs_shared_walls.png"] = _binned(
        plt, sim, methods, "shared_walls", [1, 50, 200, 1000, 10000], "wall cells both robots saw (source cells)",
        "Success vs shared walls", transform=lambda n: min(max(n, 1), 10000), log=True
    )
    out["success_vs_rotation.png"] = _binned(
        plt, sim, methods, "rotation_deg", [0, 30, 60, 90, 120, 150, 180], "|rotation| (deg)", "Success vs rotation", transform=abs
    )
    out["success_vs_scale.png"] = _binned(
        plt, sim, methods, "scale", [0.5, 0.63, 0.8, 1.0, 1.25, 1.6, 2.0], "scale (b's cell / a's cell)", "Success vs scale", log=True
    )

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    pos = [r for r in records if r["positive"] and unswapped(r["dataset"]) in ("simulated", "paper")]
    for m in methods:
        sel = [r for r in pos if r["method"] == m]
        if not sel:
            continue
        e = np.sort([r["corner_error_px"] for r in sel if r["corner_error_px"] is not None])
        e = np.maximum(e, 1e-3)
        y = np.arange(1, len(e) + 1) / len(sel)
        ax.step(np.r_[1e-3, e], np.r_[0.0, y], where="post", label=f"{m} ({len(sel)} pairs)")
    for v, lab in ((2.0, "precise"), (10.0, "success")):
        ax.axvline(v, color="grey", ls="--", lw=0.8)
        ax.text(v, 1.0, f" {lab}", fontsize=7, va="top", color="grey")
    ax.set_xscale("log")
    ax.set_xlim(1e-2, 1e4)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("corner error (px of a)")
    ax.set_ylabel("fraction of positive pairs")
    ax.set_title("CDF of the corner error (declined pairs never reach it)", fontsize=10)
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    out["corner_error_cdf.png"] = _png(fig)

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for m in methods:
        sel = [r for r in records if r["method"] == m and r["cells"] > 0]
        if sel:
            ax.scatter([r["cells"] / 1e6 for r in sel], [max(r["wall_s"], 1e-4) for r in sel], s=10, alpha=0.6, label=m)
    ax.set_xscale("log")
    ax.set_yscale("log")
    _plain_log_ticks(ax.xaxis)
    _plain_log_ticks(ax.yaxis)
    ax.set_xlabel("cells of both maps (millions)")
    ax.set_ylabel("wall time of align (s)")
    ax.set_title("Time vs map size", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    fig.tight_layout()
    out["time_vs_size.png"] = _png(fig)
    return out

"""Small overlaps of real maps: windows cut from the Halmstad sensor pairs, aligned from scratch.

The benchmark's Halmstad pairs are whole buildings (8 700 overlap wall cells and more at
the poses taken); its simulated pairs overlap little but are cut from one source map, so
they agree wherever they overlap. A real team's maps may overlap little *and* differ
(bending, furniture, doors). This script measures that case, outside the benchmark:

* the reference is the pose a benchmark run took for each Halmstad sensor pair it merged
  right (``cases.jsonl`` of the run folder, method ``hybrid``; the top-level run in
  ``docs/results`` by default): within the annotation protocol of those pairs;
* for each pair, ``--per-pair`` windows of each ``--size``: a square of map a centred on
  a random cell that both maps know at that pose, and the same place in map b shifted by
  0.3 of the window's size in a random direction (so that the windows overlap partly);
* each pair of windows is aligned with ``gridmerge.align(..., rng=0)`` and the other
  options given (``--no-crossing``: ``max_crossing=None``); a merge is *right* when b's
  window corners are within ``--right-px`` (50, 2.5 m at 0.05 m/cell) of where the
  reference puts them, *wrong* otherwise. Bending between real maps leaves the
  reference 5-15 px off locally, hence the wide line.

It writes one JSON line per window (``--out``) and prints a summary. The forty-fourth
session's numbers (docs/benchmarks.md, "What was tried") came from

    python benchmarks/halmstad_windows.py --size 240 320 --no-crossing --out windows.jsonl

(about 15 minutes on two cores). Windows cut square are not robot maps: several lie
inside E5's open hall, with a few walls and clutter.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from gridmerge import OccupancyGrid, align
from gridmerge.bench import runner
from gridmerge.transforms import AffineTransform, SimilarityTransform, corner_error
from gridmerge.verify import crossing, despeckle

_SHIFT = 0.3


def windows(a: OccupancyGrid, b: OccupancyGrid, pose: np.ndarray, size: int, count: int, rng: np.random.Generator):
    """Yield ``(a_window, b_window, truth)``: ``count`` pairs of windows of ``a`` and ``b``
    (``pose``: (3, 3) b pixels -> a pixels), ``truth`` the pose between the windows."""
    inverse = np.linalg.inv(pose)
    known = np.argwhere(~np.isnan(a.data))
    scale = AffineTransform(pose).scale
    for _ in range(count):
        for _ in range(50):  # a cell of a that b knows too, at the pose
            y, x = known[rng.integers(len(known))]
            p = inverse @ [x, y, 1.0]
            if 0 <= p[0] < b.shape[1] and 0 <= p[1] < b.shape[0] and not np.isnan(b.data[int(p[1]), int(p[0])]):
                break
        y0, x0 = max(0, y - size // 2), max(0, x - size // 2)
        wa = OccupancyGrid(a.data[y0 : y0 + size, x0 : x0 + size].copy())
        d = rng.normal(size=2)
        d = _SHIFT * size * d / np.linalg.norm(d)
        c = inverse @ [x + d[0], y + d[1], 1.0]
        sb = int(size / scale)
        by0, bx0 = int(max(0, c[1] - sb // 2)), int(max(0, c[0] - sb // 2))
        wb = OccupancyGrid(b.data[by0 : by0 + sb, bx0 : bx0 + sb].copy())
        yield wa, wb, SimilarityTransform(translation=(-x0, -y0)).params @ pose @ SimilarityTransform(translation=(bx0, by0)).params


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", default=str(Path(__file__).resolve().parents[1] / "docs" / "results"),
                        help="benchmark run folder whose right Halmstad poses are the reference")
    parser.add_argument("--size", type=int, nargs="+", default=[240], help="window sizes, cells of map a")
    parser.add_argument("--per-pair", type=int, default=3)
    parser.add_argument("--right-px", type=float, default=50.0)
    parser.add_argument("--no-crossing", action="store_true", help="align with max_crossing=None")
    parser.add_argument("--limit", type=int, default=None, help="the first N pairs only (a quick look)")
    parser.add_argument("--out", default="windows.jsonl")
    args = parser.parse_args(argv)
    rows = [json.loads(line) for line in open(Path(args.run) / "cases.jsonl")]
    pairs = [r for r in rows if r["method"] == "hybrid" and r["case_id"].startswith("halmstad/") and r["success"]]
    pairs = pairs[: args.limit]
    options = {"max_crossing": None} if args.no_crossing else {}
    done = []
    with open(args.out, "w") as out:
        for size in args.size:
            for i, r in enumerate(pairs):
                case = runner.rebuild_case(args.run, r["case_id"])
                pose = np.vstack([np.asarray(r["estimate"]["matrix"], dtype=float), [0.0, 0.0, 1.0]])
                for k, (wa, wb, truth) in enumerate(windows(case.a, case.b, pose, size, args.per_pair,
                                                            np.random.default_rng(i))):
                    res = align(wa, wb, rng=0, **options)
                    rec = {"case": r["case_id"], "size": size, "window": k, "success": res.success,
                           "confidence": res.confidence, "message": res.message}
                    if res.success:
                        c = crossing(despeckle(wa), despeckle(wb), res.transform)
                        rec.update(error_px=corner_error(res.transform, truth, wb.shape),
                                   crossing={"walls": c.walls, "deep": c.deep}, details=res.details)
                    out.write(json.dumps(rec, default=str) + "\n")
                    out.flush()
                    done.append(rec)
                print(f"{size}: {i + 1}/{len(pairs)} pairs", file=sys.stderr, end="\r")
    merged = [r for r in done if r["success"]]
    wrong = [r for r in merged if r["error_px"] >= args.right_px]
    print(f"\n{len(done)} windows, {len(merged)} merged, {len(merged) - len(wrong)} right, {len(wrong)} wrong "
          f"({len(wrong) / max(1, len(merged)):.0%} of the merges; {sum(r['confidence'] >= 0.999 for r in wrong)} "
          f"of them at confidence 1.0)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""How well the two maps of each case agree at the truth, and what a method made of them.

A benchmark run reports success, declined and wrong; it does not say how many of its
cases could have been merged at all. Real maps of one building, made in two sessions,
may barely agree where they overlap (bending, furniture, doors, glass): at the truth
their walls can coincide on a small share of the overlap, and no method that reads the
maps can place them there with confidence. This script measures that ceiling, outside
the benchmark:

* for every positive case of the run folders given (``cases.jsonl``, method
  ``--method``, ``hybrid`` by default), the case is built again
  (:func:`gridmerge.bench.runner.rebuild_case`: the maps the run aligned);
* its ``truth`` (for ``halmstad`` and ``halmstad-partial``, the annotation fit: 5-15 px
  off in places, the maps bend) is polished by ICP on the walls
  (:class:`gridmerge.refine.WallICP`); the polished pose is kept when it is still right
  by the case's own measure: within the protocol's line on the annotated points
  (``points_a``, ``points_b``, ``threshold_px`` of the case), or, without points, b's
  corners within ``--reach`` px (default 10, the success line) of the truth;
* the walls' agreement at that pose (:func:`gridmerge.verify.verify`, tolerance 2 cells,
  as the decision uses) and the wall cells of either map in the overlap are recorded
  with the run's outcome for the case.

It prints the outcomes by the walls' agreement at the truth (Markdown) and writes one
JSON line per case (``--out``). The forty-ninth session's table (docs/benchmarks.md,
"Small overlaps of real maps") came from

    python benchmarks/truth_agreement.py docs/results/partial/seed{0..11} --out truth.jsonl

(about 45 minutes on two cores for the 576 positive cases of seeds 0-11).

``--despeckled`` measures on the maps with their isolated hits made unknown
(:func:`gridmerge.verify.despeckle`), as the default method's judge sees them: on noisy
simulated maps (spurious hits in the open floor) that is what its decision's floors
apply to. ``--outcomes declined,wrong`` measures only the cases a run did not merge
right. The fifty-sixth session's ceiling of the simulated set (docs/benchmarks.md,
"What was tried") came from

    python benchmarks/truth_agreement.py docs/results/s55/sim_s5{1..9} docs/results/s55/sim_s6{0,1} \
        docs/results/s56/sim_s6{2..9} docs/results/s56/sim_s70 --despeckled --outcomes declined,wrong
"""

from __future__ import annotations

import argparse
import json
import math
import sys

import numpy as np

from gridmerge.bench import runner
from gridmerge.bench.metrics import halmstad_point_error
from gridmerge.refine import WallICP
from gridmerge.transforms import SimilarityTransform, corner_error
from gridmerge.verify import despeckle, verify

#: Edges of the agreement bins of the printed table.
BINS = (0.0, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 1.01)


def outcome(record: dict) -> str:
    """``"right"``, ``"wrong"`` or ``"declined"`` of a positive case's record."""
    if record.get("success"):
        return "right"
    return "wrong" if record.get("aligned") else "declined"


def at_truth(case, reach: float, despeckled: bool = False) -> dict:
    """The walls' agreement of ``case``'s maps at its truth, polished by ICP on the walls
    when the polished pose is still right by the case's measure (the annotated points
    within the protocol's line, or b's corners within ``reach`` px of the truth)."""
    a, b = (despeckle(case.a), despeckle(case.b)) if despeckled else (case.a, case.b)
    truth = SimilarityTransform(np.asarray(case.truth, dtype=float))
    polished = WallICP(a, b).polish(truth)
    meta = case.meta
    if meta.get("points_a") and meta.get("threshold_px") is not None:
        error = halmstad_point_error(polished, np.asarray(meta["points_a"]), np.asarray(meta["points_b"]))
        kept = bool(math.isfinite(error) and error <= float(meta["threshold_px"]))
    else:
        error = corner_error(polished, truth, case.b.shape)
        kept = bool(error <= reach)
    v = verify(a, b, polished if kept else truth)
    return {
        "wall_agreement": None if not math.isfinite(v.wall_agreement) else round(float(v.wall_agreement), 4),
        "walls_a": v.walls_a,
        "walls_b": v.walls_b,
        "polished_error_px": round(float(error), 2),
        "polished": kept,
    }


def rows(runs, method: str, reach: float, despeckled: bool = False, outcomes=None):
    """Yield one dict per positive case of ``runs`` (result folders) whose outcome is
    one of ``outcomes`` (all when ``None``)."""
    for run in runs:
        bench = runner.BenchRun.load(run)  # read once: rebuild_case takes it as it is
        for r in bench.records:
            if r.get("method") != method or not r.get("positive"):
                continue
            if outcomes is not None and outcome(r) not in outcomes:
                continue
            case = runner.rebuild_case(bench, r["case_id"])
            yield {
                "run": str(run),
                "case_id": r["case_id"],
                "tier": r.get("tier"),
                "outcome": outcome(r),
                "candidate_success": r.get("candidate_success"),
                "confidence": r.get("confidence"),
                **at_truth(case, reach, despeckled),
            }


def _table_row(label: str, cases: list) -> str:
    """One Markdown row of :func:`table`: ``cases`` counted by outcome."""
    n = {k: sum(f["outcome"] == k for f in cases) for k in ("right", "wrong", "declined")}
    cand = sum(f["outcome"] == "declined" and bool(f["candidate_success"]) for f in cases)
    return f"| {label} | {len(cases)} | {n['right']} | {n['wrong']} | {n['declined']} | {cand} |"


def table(found: list) -> str:
    """Markdown: outcomes by the walls' agreement at the truth."""
    lines = [
        "| walls agree at the truth | cases | right | wrong | declined | of them, best candidate right |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        s = [f for f in found if f["wall_agreement"] is not None and lo <= f["wall_agreement"] < hi]
        if s:
            lines.append(_table_row(f"{lo:.0%}-{min(hi, 1.0):.0%}", s))
    none = [f for f in found if f["wall_agreement"] is None]
    if none:
        lines.append(_table_row("no wall in the overlap", none))
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", nargs="+", help="benchmark results folders")
    p.add_argument("--method", default="hybrid")
    p.add_argument("--reach", type=float, default=10.0, help="px the ICP polish of the truth may move b's corners (cases without annotated points)")
    p.add_argument("--out", help="JSON lines, one per positive case")
    p.add_argument("--despeckled", action="store_true",
                   help="measure on the maps with isolated hits made unknown, as the default method's judge sees them")
    p.add_argument("--outcomes", help="only the cases of these outcomes (comma-separated: right, wrong, declined)")
    args = p.parse_args(argv)
    found = []
    out = open(args.out, "w") if args.out else None
    try:
        outcomes = None if not args.outcomes else set(args.outcomes.split(","))
        for row in rows(args.runs, args.method, args.reach, args.despeckled, outcomes):
            found.append(row)
            if out is not None:
                out.write(json.dumps(row) + "\n")
                out.flush()
            print(f"\r{len(found)} cases", end="", file=sys.stderr, flush=True)
    finally:
        if out is not None:
            out.close()
    print(file=sys.stderr)
    print(table(found))
    return 0


if __name__ == "__main__":
    sys.exit(main())

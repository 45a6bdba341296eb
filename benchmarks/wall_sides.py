"""Where two maps meet only at walls seen from opposite sides, and what that costs.

Two robots in neighbouring rooms each map the face of the wall between them that their
laser hits. The two faces are one wall's thickness apart (one or two cells of a thin
partition, ten of a thick wall), but each map holds one line of occupied cells with free
space on its own side only, and an alignment that lays walls on walls (the wall
agreement, ICP on the walls) lays the two faces on each other: b is placed too close to
a, off by the wall's thickness along the wall's normal, and nothing in the two maps tells
how thick the wall was. This script measures how often the poses of a run rest on such
contacts, and how far the faces lie apart at the truth, outside the benchmark:

* for every aligned case of the run folders given (``cases.jsonl``, method ``--method``,
  ``hybrid`` by default) whose overlap holds fewer than ``--max-walls`` wall cells of
  one map (default 150: the poses resting on a few walls), the case is built again
  (:func:`gridmerge.bench.runner.rebuild_case`) and its maps despeckled
  (:func:`gridmerge.verify.despeckle`, as the default method's judge sees them);
* at the run's pose, a's wall cells within ``--tolerance`` cells (default 2) of b's
  walls, inside b's known cells, are *matched*; a matched cell is a *contact* when the
  two maps' free space together closes around it within ``--thin`` cells (default 4)
  along a row or a column while neither map's free space alone does: a's free space on
  one side, b's on the other;
* for a case with a truth, ``shift_px`` is how far the truth moves b's part at the
  contacts' centre along their mean normal, away from a's free space (the faces'
  distance at the truth, plus any error of the pose there).

It prints the outcomes by contact share (Markdown) and each case with a contact share of
at least 0.3, and writes one JSON line per case (``--out``). The fifty-eighth session's
numbers (docs/benchmarks.md) came from the latest run of every simulated, HM3D, bent and
``halmstad-partial`` seed and Halmstad (``docs/results/s54``-``s57``), about 4 minutes
on two cores for 480 cases, e.g.

    python benchmarks/wall_sides.py docs/results/s57/sim_s7{3,5,9} docs/results/s57/beyond_sim_s80
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys

import cv2
import numpy as np

from gridmerge.bench import runner
from gridmerge.errors import GridMergeError
from gridmerge.transforms import corner_error
from gridmerge.verify import despeckle

#: Edges of the contact-share bins of the printed table.
BINS = (0.0, 0.1, 0.3, 0.5, 1.01)


def gaps(free: np.ndarray) -> np.ndarray:
    """For every cell, the number of cells between the nearest free cells before and after
    it along its row or its column, whichever is fewer (``inf`` where a side has none).

    ``free``: (H, W) bool array. A wall line between two free regions gets its thickness;
    a wall with free space on one side only gets ``inf`` (or the width of the room behind)."""
    return np.minimum(_gaps_along_rows(free), _gaps_along_rows(free.T).T)


def _gaps_along_rows(free: np.ndarray) -> np.ndarray:
    w = free.shape[1]
    cols = np.arange(w)[None, :]
    before = np.maximum.accumulate(np.where(free, cols, -1), axis=1)
    after = np.minimum.accumulate(np.where(free, cols, w)[:, ::-1], axis=1)[:, ::-1]
    g = (after - before - 1).astype(float)
    g[(before < 0) | (after >= w)] = np.inf
    return g


def contacts(a, b, pose: np.ndarray, *, tolerance: int = 2, thin: int = 4):
    """The matched wall cells of ``a`` at ``pose`` (b pixels -> a pixels, (3, 3) float
    array) and those of them that are contacts: ``(matched, contact, normals)``, two (H, W)
    bool arrays of a's shape and the (N, 2) unit normals (x, y) of a's free space at the N
    contact cells (pointing into a's free space)."""
    h, w = a.shape
    m = np.asarray(pose, float)[:2]

    def warped(mask):
        return cv2.warpAffine(mask.astype(np.uint8), m, (w, h), flags=cv2.INTER_NEAREST) > 0

    free_b, walls_b, known_b = warped(b.free()), warped(b.occupied()), warped(b.known)
    free_a, walls_a = a.free(), a.occupied()
    near_b = cv2.dilate(walls_b.astype(np.uint8), np.ones((2 * tolerance + 1,) * 2, np.uint8)) > 0
    matched = walls_a & near_b & known_b
    contact = matched & (gaps(free_a | free_b) <= thin) & (gaps(free_a) > thin) & (gaps(free_b) > thin)
    smooth = cv2.GaussianBlur(free_a.astype(np.float32), (0, 0), 2.0)
    gx, gy = cv2.Sobel(smooth, cv2.CV_32F, 1, 0), cv2.Sobel(smooth, cv2.CV_32F, 0, 1)
    ys, xs = np.nonzero(contact)
    n = np.stack([gx[ys, xs], gy[ys, xs]], axis=1).astype(float)
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
    return matched, contact, n


def measure(record: dict, case, *, tolerance: int, thin: int) -> dict:
    """One case's line: contact share, normals' coherence, the truth's shift at the contacts."""
    a, b = despeckle(case.a), despeckle(case.b)
    pose = _pose(record)
    matched, contact, normals = contacts(a, b, pose, tolerance=tolerance, thin=thin)
    n_matched, n_contact = int(matched.sum()), int(contact.sum())
    line = {"matched": n_matched, "contacts": n_contact, "share": n_contact / n_matched if n_matched else None,
            "coherence": None, "shift_px": None}
    if n_contact:
        mean = normals.mean(axis=0)
        line["coherence"] = float(np.linalg.norm(mean))
        truth = getattr(case, "truth", None)
        if truth is not None and line["coherence"] > 0.5:
            ys, xs = np.nonzero(contact)
            centre = np.array([xs.mean(), ys.mean(), 1.0])
            moved = np.asarray(truth, float) @ np.linalg.solve(pose, centre) - centre
            line["shift_px"] = float(-moved[:2] @ mean / line["coherence"])
    return line


def _pose(record: dict) -> np.ndarray:
    """The record's estimate, b pixels -> a pixels: a (3, 3) float array."""
    return np.vstack([np.asarray(record["estimate"]["matrix"], float), [0.0, 0.0, 1.0]])


def _outcome(rec: dict) -> str:
    if rec.get("success"):
        return "right"
    if rec.get("false_merge"):
        return "false"
    return "wrong" if rec.get("wrong") else "other"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", help="benchmark results folders")
    p.add_argument("--method", default="hybrid")
    p.add_argument("--max-walls", type=int, default=150, help="only poses with fewer wall cells of one map in the overlap")
    p.add_argument("--tolerance", type=int, default=2, help="cells between walls that match")
    p.add_argument("--thin", type=int, default=4, help="most cells between the two maps' free space at a contact")
    p.add_argument("--out", help="JSON lines, one per case")
    args = p.parse_args(argv)
    try:
        benches = [(folder, runner.BenchRun.load(folder)) for folder in args.runs]
    except GridMergeError as e:
        print(f"wall_sides: error: {e}", file=sys.stderr)
        return 2
    with contextlib.ExitStack() as stack:
        out = stack.enter_context(open(args.out, "w")) if args.out else None
        lines = []
        for folder, bench in benches:
            for rec in bench.records:
                if rec.get("method") != args.method or not rec.get("aligned"):
                    continue
                v = rec.get("verification") or {}
                if min(v.get("walls_a") or 0, v.get("walls_b") or 0) >= args.max_walls:
                    continue
                case = runner.rebuild_case(bench, rec["case_id"])
                line = dict(run=folder, case=rec["case_id"], outcome=_outcome(rec), error_px=rec.get("corner_error_px"),
                            wall_agreement=v.get("wall_agreement"), walls=[v.get("walls_a"), v.get("walls_b")],
                            **measure(rec, case, tolerance=args.tolerance, thin=args.thin))
                if line["error_px"] is None and getattr(case, "truth", None) is not None:
                    line["error_px"] = float(corner_error(_pose(rec), case.truth, case.b.shape))
                lines.append(line)
                if out:
                    out.write(json.dumps(line) + "\n")
                    out.flush()
    outcomes = ("right", "wrong", "false", "other")
    print("| contact share | " + " | ".join(outcomes) + " |")
    print("|---|" + "---|" * len(outcomes))
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        row = [sum(1 for x in lines if x["outcome"] == o and lo <= (x["share"] or 0.0) < hi) for o in outcomes]
        print(f"| {lo:.1f}-{min(hi, 1.0):.1f} | " + " | ".join(map(str, row)) + " |")
    print()
    for x in lines:
        if (x["share"] or 0.0) >= 0.3:
            err = "-" if x["error_px"] is None else f"{x['error_px']:.1f}"
            shift = "-" if x["shift_px"] is None else f"{x['shift_px']:.1f}"
            print(f"{x['run']} {x['case']}: {x['outcome']}, error {err} px, contacts {x['contacts']} of "
                  f"{x['matched']} ({x['share']:.2f}), faces apart at the truth {shift} px")
    return 0


if __name__ == "__main__":
    sys.exit(main())

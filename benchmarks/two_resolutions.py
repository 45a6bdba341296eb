"""Every alignment method on a real pair of maps of two resolutions.

Willow Garage mapped at 0.05 and at 0.1 m per cell (``../shared/data/ros_maps``,
ros-planning's navigation tutorials), each order. The pair has no annotated truth: each
method's pose is compared with :func:`gridmerge.bench.metrics.ecc_reference` (the affine
pose ECC fits to every cell's grey value), started from the default method's pose.
Prints a Markdown table (docs/benchmarks.md, twenty-seventh session)::

    python benchmarks/two_resolutions.py [--data DIR]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import gridmerge
from gridmerge.bench.datasets import resolve_data_dir
from gridmerge.bench.metrics import ecc_reference
from gridmerge.transforms import corner_error

METHODS = ("hybrid", "sift", "ransac", "paper", "orb", "hough")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", help="the shared data folder (default: ../shared/data next to the project)")
    args = parser.parse_args(argv)
    try:
        root = resolve_data_dir(args.data)
    except gridmerge.GridMergeError as exc:
        print(f"two_resolutions: {exc}", file=sys.stderr)
        return 2
    maps = None if root is None else Path(root) / "ros_maps"
    if maps is None or not (maps / "willow-full.yaml").is_file():
        print("two_resolutions: the Willow Garage maps (shared data, ros_maps/) were not found", file=sys.stderr)
        return 2
    fine = gridmerge.load_map(maps / "willow-full-0.05.yaml")
    coarse = gridmerge.load_map(maps / "willow-full.yaml")
    rows = {m: [] for m in METHODS}
    for a, b in ((fine, coarse), (coarse, fine)):
        results = {m: gridmerge.align(a, b, method=m) for m in METHODS}
        reference = ecc_reference(a, b, results["hybrid"].transform)
        ratio = math.hypot(*reference[:2, 0]) * a.resolution / b.resolution
        print(f"a at {a.resolution} m: the reference's scale is the resolutions' ratio x {ratio:.5f}", file=sys.stderr)
        for m, r in results.items():
            if r.transform is None:
                rows[m].append(("declined", ""))
                continue
            err = corner_error(r.transform, reference, b.shape)
            rows[m].append((f"{err:.2f} px", f"{r.metric_transform.scale:.5f}"))
    print("| method | fine first | coarse first | metric scale (fine first) | metric scale (coarse first) |")
    print("| --- | --- | --- | --- | --- |")
    for m, ((e1, s1), (e2, s2)) in rows.items():
        print(f"| `{m}` | {e1} | {e2} | {s1} | {s2} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

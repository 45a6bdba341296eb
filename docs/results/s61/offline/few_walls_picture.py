"""docs/images/few_walls.png: two poses resting on about a hundred overlap wall cells,
drawn with gridmerge.plot.alignment_overlay at the poses the sixtieth session's code took
(stored in the runs' cases.jsonl): a false merge (simulated seed 104, negative pair 14)
and a right one (seed 84, pair 58).

    python docs/results/s61/offline/few_walls_picture.py RUN104 RUN84 OUT.png
"""
import json
import sys

import numpy as np

from gridmerge.bench import runner
from gridmerge.plot import alignment_overlay, require_matplotlib


def stored(run, cid):
    bench = runner.BenchRun.load(run)
    case = runner.rebuild_case(bench, cid)
    rec = next(c for c in (json.loads(line) for line in open(f"{run}/cases.jsonl")) if c["case_id"] == cid and c["method"] == "hybrid")
    return case, rec


plt = require_matplotlib()
fig, axes = plt.subplots(1, 2, figsize=(13, 6.5))
for ax, (run, cid, what) in zip(axes, ((sys.argv[1], "simulated/0014", "two places (a negative pair), merged by the 60th session's code"),
                                       (sys.argv[2], "simulated/0058", "a right pose on as few walls"))):
    case, rec = stored(run, cid)
    img, _ = alignment_overlay(case.a, case.b, np.asarray(rec["estimate"]["matrix"]), line=3)
    v = rec["verification"]
    ax.imshow(img, interpolation="nearest")
    ax.set_title(f"{cid}: {what}\nwalls agree on {v['wall_agreement']:.0%} of {v['walls_a']} + {v['walls_b']} overlap wall cells, "
                 f"confidence {rec['confidence']:.2f}", fontsize=9)
    ax.set_axis_off()
fig.tight_layout()
fig.savefig(sys.argv[3], dpi=90)

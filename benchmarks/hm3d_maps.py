"""Floor plans of real homes, for the simulated benchmark in maps nobody tuned on.

The ir-sim package (MIT; https://pypi.org/project/ir-sim/) ships nine binary maps made
from scenes of the Habitat-Matterport 3D data set (HM3D: scans of real homes): the
navigable area of each scene, drawn as a plot whose obstacles are hatched. This script
turns them into ROS map_server maps (trinary PGM + YAML): the rooms free, every obstacle
solid (a simulated scanner sees its outline), a band of unknown around. They are not
shipped with gridmerge (HM3D has its own terms of use); fetch the wheel and convert:

    python -m pip download ir-sim==2.12.0 --no-deps -d /tmp/irsim
    python benchmarks/hm3d_maps.py /tmp/irsim/ir_sim-2.12.0-py3-none-any.whl hm3d-maps
    gridmerge bench --dataset simulated --source-map hm3d-maps/hm3d_1.yaml ... --source-map hm3d-maps/hm3d_9.yaml

The plots' pixels have no stated size; each map is given 0.05 m per cell, as the shared
data's maps. The simulated robots' range and the cases are in cells, so the choice
changes no case.
"""

from __future__ import annotations

import re
import sys
import zipfile
from pathlib import Path

import cv2
import numpy as np

#: Hatch stripes between an obstacle's lines are at most this wide (half-width, pixels,
#: by the distance transform): 11.2 in all nine plots; rooms are wider.
STRIPE_HALF_WIDTH = 12.0
UNKNOWN_BAND = 10


def plot_to_map(image: np.ndarray) -> np.ndarray:
    """A grey plot (H, W) uint8 -> map_server PGM values: 254 free, 0 occupied, 205 unknown."""
    dark = image < 128
    ys, xs = np.nonzero(dark)
    dark = dark[ys.min() : ys.max() + 1, xs.min() : xs.max() + 1]  # the plot's frame
    white = (~dark).astype(np.uint8)
    count, labels = cv2.connectedComponents(white, connectivity=4)
    depth = cv2.distanceTransform(white, cv2.DIST_L2, 5)
    half_width = np.zeros(count)
    np.maximum.at(half_width, labels.ravel(), depth.ravel())
    free = (half_width[labels] > STRIPE_HALF_WIDTH) & (white > 0)
    pgm = np.where(free, 254, 0).astype(np.uint8)
    return np.pad(pgm, UNKNOWN_BAND, constant_values=205)


def main(argv=None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        print("usage: hm3d_maps.py IR_SIM_WHEEL OUT_DIR", file=sys.stderr)
        return 2
    wheel, out = Path(args[0]), Path(args[1])
    out.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(wheel) as z:
        names = sorted(n for n in z.namelist() if re.search(r"binary_map_generator_hm3d/hm3d_\d+\.png$", n))
        if not names:
            print(f"no HM3D maps in {wheel}", file=sys.stderr)
            return 2
        for name in names:
            image = cv2.imdecode(np.frombuffer(z.read(name), np.uint8), cv2.IMREAD_GRAYSCALE)
            stem = Path(name).stem
            cv2.imwrite(str(out / f"{stem}.pgm"), plot_to_map(image))
            (out / f"{stem}.yaml").write_text(
                f"image: {stem}.pgm\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\nnegate: 0\n"
                "occupied_thresh: 0.65\nfree_thresh: 0.196\n"
            )
            print(out / f"{stem}.yaml")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""``benchmarks/hm3d_maps.py``: HM3D navmesh plots (hatched obstacles) -> map_server maps."""

from __future__ import annotations

import zipfile

import cv2
import numpy as np
import pytest

from gridmerge import load_map


@pytest.fixture(scope="module")
def hm3d(benchmark_script):
    return benchmark_script("hm3d_maps")


def _plot() -> np.ndarray:
    """A plot as ir-sim draws one: white figure margin, black frame, a free room, and an
    obstacle outlined in black and hatched with diagonal lines 25 px apart."""
    img = np.full((300, 400), 255, np.uint8)
    cv2.rectangle(img, (20, 30), (380, 270), 0, 2)  # the plot's frame
    cv2.rectangle(img, (200, 60), (360, 240), 0, 2)  # an obstacle ...
    for c in range(-400, 800, 25):  # ... hatched inside
        cv2.line(img[62:239, 202:359], (c, 0), (c - 300, 300), 0, 1)
    return img


def test_rooms_free_obstacles_solid_unknown_around(hm3d):
    pgm = hm3d.plot_to_map(_plot())
    band = hm3d.UNKNOWN_BAND
    assert pgm.shape == (243 + 2 * band, 363 + 2 * band)  # the frame (2 px lines), and the band
    assert (pgm[:band] == 205).all() and (pgm[:, -band:] == 205).all()
    inner = pgm[band:-band, band:-band]  # the frame's pixels: x 19..381, y 29..271
    assert (inner[35:205, 185:335] == 0).all()  # the obstacle, hatch stripes included, is solid
    room = inner[10:230, 10:170]
    assert (room == 254).all()
    assert set(np.unique(pgm)) == {0, 205, 254}


def test_converts_every_map_of_the_wheel(hm3d, tmp_path):
    wheel = tmp_path / "ir_sim-0-py3-none-any.whl"
    ok, png = cv2.imencode(".png", _plot())
    with zipfile.ZipFile(wheel, "w") as z:
        for k in (1, 2):
            z.writestr(f"irsim/world/map/binary_map_generator_hm3d/hm3d_{k}.png", png.tobytes())
        z.writestr("irsim/world/map/cave.png", png.tobytes())  # not an HM3D map
    out = tmp_path / "maps"
    assert hm3d.main([str(wheel), str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["hm3d_1.pgm", "hm3d_1.yaml", "hm3d_2.pgm", "hm3d_2.yaml"]
    g = load_map(out / "hm3d_1.yaml")
    assert g.resolution == pytest.approx(0.05)
    assert g.free().sum() > 0.3 * g.known.sum() and g.occupied().sum() > 0.3 * g.known.sum()
    empty = tmp_path / "empty.whl"
    with zipfile.ZipFile(empty, "w") as z:
        z.writestr("irsim/__init__.py", "")
    assert hm3d.main([str(empty), str(tmp_path / "none")]) == 2
    assert hm3d.main([]) == 2

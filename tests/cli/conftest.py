"""Fixtures of the command-line tests: sample maps written as map_server files."""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from gridmerge import OccupancyGrid, load_map, save_map
from gridmerge import samples

#: Frames of the saved maps: both differ from the defaults, so that a CLI that ignored
#: (or overrode) a YAML's resolution or origin would report wrong metric poses. b's cells
#: are 0.95 of a's, as in the paper's Table I, so both maps agree on the size of the world.
A_RESOLUTION, A_ORIGIN = 0.1, (-4.0, 1.5, 0.1)
B_RESOLUTION, B_ORIGIN = 0.095, (2.0, -3.0, 0.25)

#: Cells of the buildings of the negative pair.
NEGATIVE_SHAPE = (240, 320)


@dataclass
class SampleMaps:
    folder: Path
    a: OccupancyGrid  # as the CLI reads them back from the files
    b: OccupancyGrid
    truth: np.ndarray  # (3, 3): b pixels -> a pixels

    def copy_to(self, dest: Path, *names: str) -> Path:
        """Copy the named maps (YAML + image) into ``dest``; returns ``dest``."""
        dest.mkdir(parents=True, exist_ok=True)
        for name in names or ("a", "b"):
            for suffix in (".yaml", ".pgm"):
                shutil.copy2(self.folder / f"{name}{suffix}", dest / f"{name}{suffix}")
        return dest


@pytest.fixture(scope="session")
def sample_maps(tmp_path_factory) -> SampleMaps:
    """a.yaml/b.yaml: the Table I pair (alignable); neg_a.yaml/neg_b.yaml: two different
    buildings (nothing to merge), on 240 x 320 cells: these tests check what the program
    does with a declined pair, and the smaller maps are declined in a quarter of the time
    of the default 480 x 640 (the search's rules are tested in ``tests/test_align.py``)."""
    folder = tmp_path_factory.mktemp("maps")
    a, b, truth = samples.table1_pair(0)
    save_map(a.replace(resolution=A_RESOLUTION, origin=A_ORIGIN), folder / "a.yaml")
    save_map(b.replace(resolution=B_RESOLUTION, origin=B_ORIGIN), folder / "b.yaml")
    na, nb = samples.negative_pair(0, shape=NEGATIVE_SHAPE)
    save_map(na, folder / "neg_a.yaml")
    save_map(nb, folder / "neg_b.yaml")
    return SampleMaps(folder, load_map(folder / "a.yaml"), load_map(folder / "b.yaml"), np.asarray(truth, dtype=float))


@pytest.fixture
def work(tmp_path, sample_maps) -> Path:
    """A fresh folder holding copies of a.yaml/a.pgm and b.yaml/b.pgm."""
    return sample_maps.copy_to(tmp_path / "work", "a", "b")

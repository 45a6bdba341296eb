"""gridmerge: merge the occupancy grid maps of several robots into one map.

The maps' relative rotation, translation and scale are found from SIFT keypoints
("A Novel Map Merging Methodology for Multi-Robot Systems"), checked against the maps
themselves, and the maps are fused cell by cell.

>>> import gridmerge
>>> from gridmerge import samples
>>> a, b, truth = samples.table1_pair()
>>> result = gridmerge.align(a, b)
>>> result.success
True
"""

from .align import AlignOptions, AlignResult, align
from .errors import GridMergeError, LimitExceededError, MapFormatError, OutputError
from .grid import OccupancyGrid
from .io import load_map, save_map
from .merge import MergeResult, Merger, merge
from .transforms import AffineTransform, FailedEstimation, ScaledRotationTransform, SimilarityTransform

__version__ = "0.1.0"

__all__ = [
    "OccupancyGrid",
    "load_map",
    "save_map",
    "align",
    "AlignOptions",
    "AlignResult",
    "merge",
    "MergeResult",
    "Merger",
    "AffineTransform",
    "SimilarityTransform",
    "ScaledRotationTransform",
    "FailedEstimation",
    "GridMergeError",
    "MapFormatError",
    "LimitExceededError",
    "OutputError",
    "__version__",
]
from . import baselines as _baselines  # registers the baseline methods

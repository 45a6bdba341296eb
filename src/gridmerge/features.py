"""Keypoints and descriptors on occupancy grids (the paper's section III.A).

A feature extractor is three separate parts, each swappable:

* a *renderer* turns an :class:`~gridmerge.grid.OccupancyGrid` into an 8-bit image (and a
  mask of where features may lie);
* a *detector* finds keypoints in that image;
* a *descriptor* describes each keypoint with a vector.

:class:`SIFT` (OpenCV's, with the paper's parameters) is both a detector and a
descriptor; :class:`ORB` is the binary alternative m-explore uses. Any object with
``detect(image, mask)`` / ``compute(image, keypoints)`` plugs in.

Examples
--------
>>> import numpy as np
>>> from gridmerge.features import FeatureExtractor
>>> grid_data = np.full((120, 160), np.nan)
>>> grid_data[20:100, 20:140] = 0.0
>>> grid_data[20:100, 20:23] = grid_data[20:100, 137:140] = 1.0
>>> grid_data[20:23, 20:140] = grid_data[97:100, 20:140] = 1.0
>>> grid_data[50:60, 60:75] = 1.0
>>> from gridmerge.grid import OccupancyGrid
>>> feats = FeatureExtractor()(OccupancyGrid(grid_data))
>>> feats.descriptors.shape[1], feats.xy.shape[1]
(128, 2)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Protocol, Sequence, runtime_checkable

import cv2
import numpy as np

from .grid import OccupancyGrid
from .limits import DEFAULT_LIMITS

__all__ = [
    "Features",
    "Detector",
    "Descriptor",
    "Renderer",
    "GreyRenderer",
    "SIFT",
    "ORB",
    "FeatureExtractor",
    "PAPER_CONTRAST_THRESHOLD",
    "PAPER_EDGE_THRESHOLD",
    "MIN_IMAGE_SIDE",
]

#: The paper's keypoint contrast threshold (III.A.2), passed to OpenCV's SIFT.
PAPER_CONTRAST_THRESHOLD = 0.02
#: Lowe's edge-rejection ratio r = 10 (OpenCV's ``edgeThreshold``).
PAPER_EDGE_THRESHOLD = 10.0


@dataclass(frozen=True)
class Features:
    """Keypoints of one map and their descriptors.

    Attributes
    ----------
    xy : (N, 2) float array
        Keypoint positions in image pixels (x = column, y = row).
    size : (N,) float array
        Keypoint diameters in pixels (the scale of the feature).
    angle : (N,) float array
        Orientations in degrees (OpenCV's convention), ``-1`` when not assigned.
    response : (N,) float array
        Detector responses (contrast).
    descriptors : (N, D) array
        ``float32`` for SIFT-like descriptors, ``uint8`` bytes for binary ones.
    binary : bool
        Whether descriptors are compared by Hamming distance.
    capped : bool
        Whether keypoints were dropped to respect a maximum count.
    blurred : Features or None
        Keypoints of the same map drawn blurred, found ahead for the ``"hybrid"`` method's
        second look (:attr:`gridmerge.align.AlignOptions.second_look`) when many maps
        are merged; ``None``: found when needed.
    """

    xy: np.ndarray
    size: np.ndarray
    angle: np.ndarray
    response: np.ndarray
    descriptors: np.ndarray
    binary: bool = False
    capped: bool = False
    blurred: "Features | None" = None

    def __len__(self) -> int:
        return int(self.xy.shape[0])

    @classmethod
    def empty(cls, binary: bool = False) -> "Features":
        """No keypoints (for methods that use none)."""
        return cls.from_cv((), None, binary=binary)

    @classmethod
    def from_cv(
        cls, keypoints: Sequence[cv2.KeyPoint], descriptors, binary: bool, capped: bool = False, offset=(0.0, 0.0)
    ) -> "Features":
        """From OpenCV keypoints found in an image whose pixel (0, 0) is ``offset`` in the map."""
        n = len(keypoints)
        if descriptors is None or n == 0:
            dim, dtype = (32, np.uint8) if binary else (128, np.float32)
            descriptors = np.zeros((0, dim), dtype=dtype)
            keypoints = ()
        return cls(
            xy=np.array([k.pt for k in keypoints], dtype=float).reshape(-1, 2) + np.asarray(offset, dtype=float),
            size=np.array([k.size for k in keypoints], dtype=float),
            angle=np.array([k.angle for k in keypoints], dtype=float),
            response=np.array([k.response for k in keypoints], dtype=float),
            descriptors=np.asarray(descriptors),
            binary=binary,
            capped=capped,
        )


@runtime_checkable
class Detector(Protocol):
    """Finds keypoints: ``detect(image, mask) -> list[cv2.KeyPoint]``."""

    def detect(self, image: np.ndarray, mask: np.ndarray | None = None) -> Sequence[cv2.KeyPoint]: ...


@runtime_checkable
class Descriptor(Protocol):
    """Describes keypoints: ``compute(image, keypoints) -> (keypoints, (N, D) array)``."""

    binary: bool

    def compute(self, image: np.ndarray, keypoints: Sequence[cv2.KeyPoint]) -> tuple[Sequence[cv2.KeyPoint], np.ndarray | None]: ...


@runtime_checkable
class Renderer(Protocol):
    """Turns a grid into ``(image (H, W) uint8, mask (H, W) uint8 or None)`` for a detector."""

    def __call__(self, grid: OccupancyGrid) -> tuple[np.ndarray, np.ndarray | None]: ...


@dataclass(frozen=True)
class GreyRenderer:
    """The paper's view of a map: occupied black, free white, unknown mid-grey.

    Parameters
    ----------
    unknown : int
        Grey level of unknown cells.
    blur_sigma : float
        Standard deviation (cells) of an optional Gaussian blur; 0 keeps the raw levels.
    """

    unknown: int = 127
    blur_sigma: float = 0.0

    def __call__(self, grid: OccupancyGrid) -> tuple[np.ndarray, np.ndarray | None]:
        img = grid.render(unknown=self.unknown)
        if self.blur_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), self.blur_sigma)
        return img, None


class _OpenCVFeature:
    binary = False

    def __init__(self, impl):
        self._impl = impl

    def detect(self, image, mask=None):
        return self._impl.detect(image, mask)

    def compute(self, image, keypoints):
        return self._impl.compute(image, list(keypoints))


class SIFT(_OpenCVFeature):
    """OpenCV's SIFT with the paper's parameters as defaults (detector and descriptor).

    Parameters
    ----------
    contrast_threshold : float
        Rejects low-contrast DoG extrema (the paper: 0.02; OpenCV's default is 0.04).
    edge_threshold : float
        Edge rejection ratio of the Hessian (Lowe's r = 10).
    sigma : float
        Gaussian of the first octave.
    n_octave_layers : int
        DoG layers per octave.
    max_features : int
        0 keeps all; otherwise the strongest ``max_features`` keypoints.

    Notes
    -----
    OpenCV assigns every orientation peak within 80 % of the highest one (the paper's
    rule) and computes 4 x 4 x 8 = 128-dimensional descriptors; those are fixed in OpenCV.
    """

    def __init__(
        self,
        contrast_threshold: float = PAPER_CONTRAST_THRESHOLD,
        edge_threshold: float = PAPER_EDGE_THRESHOLD,
        sigma: float = 1.6,
        n_octave_layers: int = 3,
        max_features: int = 0,
    ):
        self.params = dict(
            contrast_threshold=contrast_threshold,
            edge_threshold=edge_threshold,
            sigma=sigma,
            n_octave_layers=n_octave_layers,
            max_features=max_features,
        )
        super().__init__(
            cv2.SIFT_create(
                nfeatures=int(max_features),
                nOctaveLayers=int(n_octave_layers),
                contrastThreshold=float(contrast_threshold),
                edgeThreshold=float(edge_threshold),
                sigma=float(sigma),
            )
        )

    def detect_and_compute(self, image, mask=None):
        """``detect`` then ``compute`` in one pass over the scale space (the same
        keypoints and descriptors, a fifth less time)."""
        return self._impl.detectAndCompute(image, mask)

    def __repr__(self) -> str:
        return "SIFT(" + ", ".join(f"{k}={v!r}" for k, v in self.params.items()) + ")"


class ORB(_OpenCVFeature):
    """OpenCV's ORB (binary descriptors), as used by m-explore's map merger."""

    binary = True

    def __init__(self, max_features: int = 5000, fast_threshold: int = 20):
        self.params = dict(max_features=max_features, fast_threshold=fast_threshold)
        super().__init__(cv2.ORB_create(nfeatures=int(max_features), fastThreshold=int(fast_threshold)))

    def __repr__(self) -> str:
        return "ORB(" + ", ".join(f"{k}={v!r}" for k, v in self.params.items()) + ")"


class FeatureExtractor:
    """Renderer + detector + descriptor: ``extractor(grid) -> Features``.

    Parameters
    ----------
    detector : Detector, optional
        Default :class:`SIFT` with the paper's parameters.
    descriptor : Descriptor, optional
        Default: the detector itself.
    renderer : Renderer, optional
        Default :class:`GreyRenderer`.
    max_keypoints : int
        Keep at most this many keypoints (the strongest responses); 0 keeps all. Bounds
        time and memory on noisy maps. Default: :data:`gridmerge.limits.DEFAULT_LIMITS`.
    margin : int
        Features are computed on the bounding box of the known cells grown by this many
        cells (maps are often mostly unknown); coordinates are those of the whole map.
    max_image_pixels : int
        Largest image (pixels of that bounding box) given to the detector; 0 for no
        limit. SIFT's scale space needs about 220 bytes per pixel, so a larger map is
        detected and described at the reduced resolution that fits (area averaging),
        and its keypoints are mapped back to the map's pixels. Default:
        :data:`gridmerge.limits.DEFAULT_LIMITS`.
    work_pixels : int
        Like ``max_image_pixels``, but a choice of speed rather than a safety limit: a
        larger image is detected at reduced resolution without marking the features as
        capped (0: full resolution). Refinement against the maps restores precision.

    Notes
    -----
    ``Features.capped`` is ``True`` when either cap changed the result (keypoints
    dropped, or the image reduced). Images thinner than :data:`MIN_IMAGE_SIDE` pixels
    have no keypoints (OpenCV's detectors fail on them).
    """

    def __init__(
        self,
        detector=None,
        descriptor=None,
        renderer=None,
        max_keypoints: int = DEFAULT_LIMITS.max_keypoints,
        margin: int = 24,
        max_image_pixels: int = DEFAULT_LIMITS.max_feature_pixels,
        work_pixels: int = 0,
    ):
        self.detector = SIFT() if detector is None else detector
        self.descriptor = self.detector if descriptor is None else descriptor
        self.renderer = GreyRenderer() if renderer is None else renderer
        self.max_keypoints = int(max_keypoints)
        self.margin = int(margin)
        self.max_image_pixels = int(max_image_pixels)
        self.work_pixels = int(work_pixels)

    def __call__(self, grid: OccupancyGrid) -> Features:
        binary = bool(getattr(self.descriptor, "binary", False))
        x0 = y0 = 0
        box = grid.known_bounds(self.margin)
        if box is not None and type(self.renderer) is GreyRenderer and self.renderer.blur_sigma <= 0:
            # Cell by cell: rendering the box alone gives the same pixels, at its cost.
            x0, y0, x1, y1 = box
            image, mask = _grey(grid.data[y0:y1, x0:x1], self.renderer.unknown), None
        else:
            image, mask = self.renderer(grid)
            if box is not None:
                x0, y0, x1, y1 = box
                image = np.ascontiguousarray(image[y0:y1, x0:x1])
                mask = None if mask is None else np.ascontiguousarray(mask[y0:y1, x0:x1])
        if min(image.shape[:2]) < MIN_IMAGE_SIDE:
            return Features.empty(binary=binary)
        limits = [v for v in (self.max_image_pixels, self.work_pixels) if v > 0]
        capped = bool(self.max_image_pixels) and image.shape[0] * image.shape[1] > self.max_image_pixels
        image, mask, zoom = _fit_pixels(image, mask, min(limits, default=0))
        both = getattr(self.detector, "detect_and_compute", None) if self.descriptor is self.detector else None
        keypoints = desc = None
        if both is not None:
            keypoints, desc = both(image, mask)
            if self.max_keypoints and len(keypoints) > self.max_keypoints:
                keypoints = desc = None  # capped: described below, as the capped set alone
            else:
                keypoints = list(keypoints)
        if keypoints is None:
            keypoints = list(self.detector.detect(image, mask))
            if self.max_keypoints and len(keypoints) > self.max_keypoints:
                order = np.argsort([-k.response for k in keypoints], kind="stable")[: self.max_keypoints]
                keypoints = [keypoints[i] for i in sorted(order)]
                capped = True
            keypoints, desc = self.descriptor.compute(image, keypoints)
        if zoom is None:
            return Features.from_cv(keypoints or (), desc, binary=binary, capped=capped, offset=(x0, y0))
        feats = Features.from_cv(keypoints or (), desc, binary=binary, capped=capped)
        # Back from the reduced image's pixels (centres at integers) to the map's.
        zx, zy = zoom
        xy = (feats.xy + 0.5) * np.array([zx, zy]) - 0.5 + np.array([x0, y0], dtype=float)
        return replace(feats, xy=xy, size=feats.size * math.sqrt(zx * zy))

    def __repr__(self) -> str:
        return (
            f"FeatureExtractor(detector={self.detector!r}, renderer={self.renderer!r}, "
            f"max_keypoints={self.max_keypoints}, max_image_pixels={self.max_image_pixels}, work_pixels={self.work_pixels})"
        )


def _grey(data: np.ndarray, unknown: int) -> np.ndarray:
    """:meth:`OccupancyGrid.render` of a block of cells."""
    img = np.rint((1.0 - np.nan_to_num(data, nan=0.0)) * 255.0).astype(np.uint8)
    img[np.isnan(data)] = unknown
    return img


#: Images with fewer rows or columns than this have no keypoints.
MIN_IMAGE_SIDE = 3


def _fit_pixels(image: np.ndarray, mask, max_pixels: int):
    """``image`` (and ``mask``) reduced to at most ``max_pixels`` pixels, and the zoom
    ``(zx, zy)`` from the reduced pixels to the original ones (``None`` if unchanged)."""
    h, w = image.shape[:2]
    if not max_pixels or h * w <= max_pixels:
        return image, mask, None
    f = math.sqrt(h * w / max_pixels)
    nw, nh = max(1, int(w / f)), max(1, int(h / f))
    while nw * nh > max_pixels:  # rounding
        nw, nh = max(1, nw - 1), max(1, nh - 1)
    small = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_AREA)
    small_mask = None if mask is None else cv2.resize(mask, (nw, nh), interpolation=cv2.INTER_NEAREST)
    return small, small_mask, (w / nw, h / nh)

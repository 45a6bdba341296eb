"""Baseline alignment methods, reproduced from their authors' code and papers.

Both are registered with :func:`gridmerge.align.register_method` when gridmerge is imported,
so ``gridmerge.align(a, b, method="orb")`` and ``gridmerge merge --method hough`` work. They
decide success by **their own rule** (``Method.verified`` is False): gridmerge's
verification is still computed and reported in the result, but it does not veto them.
``AlignResult.confidence`` is the method's own score: m-explore's confidence for ``"orb"``
(not bounded by 1; the merge needs ``>= 1.0``), the acceptance index for ``"hough"``. Both
are deterministic (they draw no random numbers; OpenCV's RANSAC seeds itself).

``"orb"`` -- m-explore's ``multirobot_map_merge`` (Horner, 2016; ROS 1 ``hrnr/m-explore``
and ROS 2 ``robo-friends/m-explore-ros2``, package ``map_merge``, ``combine_grids``)
    * image: the ``nav_msgs/OccupancyGrid`` int8 data viewed as an 8-bit image, rows in ROS
      order (bottom row first): free ``0``, occupied ``100``, unknown ``-1`` -> ``255``
      (``MergingPipeline::feed`` wraps the message's data in a ``CV_8UC1`` ``cv::Mat``);
    * features: ``cv::ORB::create()`` with OpenCV's defaults (500 keypoints, FAST threshold
      20, 8 levels, scale factor 1.2), one of the pipeline's ``FeatureType`` choices
      (``chooseFeatureFinder``; the node itself hard-codes AKAZE, the original 2016 pipeline
      used ``OrbFeaturesFinder``);
    * matching: ``cv::detail::AffineBestOf2NearestMatcher`` with its defaults,
      ``match_conf = 0.3``: 2-nearest-neighbour ratio test ``d1 < (1 - 0.3) d2`` from a to b,
      then from b to a (pairs not already found are added), Hamming distance;
    * estimation: with at least 6 matches (``num_matches_thresh1``),
      ``cv::estimateAffinePartial2D`` (RANSAC, 3 px, 2000 iterations, 0.99, 10 refinement
      iterations) and the confidence of Brown & Lowe's panorama stitching,
      ``inliers / (8 + 0.3 * matches)``;
    * decision: ``cv::detail::leaveBiggestComponent`` keeps the pair when its confidence is
      ``>= estimation_confidence``, whose default is ``1.0`` (``map_merge.cpp``).
``"hough"`` -- Carpin, "Fast and accurate map merging for multi-robot systems", Autonomous
Robots 25 (2008), following his ``mapmerge`` library (``get_hypothesis``)
    * the Hough transform of the occupied cells, its Hough spectrum
      ``HS(theta) = sum_rho HT(rho, theta)^2``, and the circular cross-correlation of the two
      spectra: its highest local maxima are the rotation candidates (each also + 180 deg,
      since a spectrum has period 180 deg);
    * for each rotation, the translation from the cross-correlations of the projections of
      the occupied cells ("X- and Y-spectra"), taken along the dominant direction of map a
      (the maximum of its spectrum), as the library does by first turning map a by it;
    * every (rotation, translation) hypothesis is scored by Birk & Carpin's acceptance index
      and the best one is kept when its index reaches :data:`HOUGH_MIN_ACCEPTANCE`.
    It assumes both maps have the same resolution: its transforms have scale 1.

Examples
--------
>>> import gridmerge
>>> from gridmerge import samples
>>> a, b, truth = samples.robot_pair(0, scale=1.0, rotation_deg=37)
>>> r = gridmerge.align(a, b, method="hough")
>>> r.success, round(r.rotation_deg), r.scale
(True, 37, 1.0)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from .align import AlignOptions, Estimate, Method, register_method
from .features import ORB, FeatureExtractor
from .fuse import warp_values
from .grid import OCCUPIED_THRESHOLD, OccupancyGrid
from .transforms import AffineTransform, SimilarityTransform
from .verify import acceptance_index

__all__ = [
    "MEXPLORE_MATCH_CONF",
    "MEXPLORE_MIN_MATCHES",
    "MEXPLORE_CONFIDENCE_THRESHOLD",
    "HOUGH_MIN_ACCEPTANCE",
    "RosGridRenderer",
    "RosRowOrder",
    "mexplore_extractor",
    "best_of_2_nearest",
    "mexplore_confidence",
    "hough_spectrum",
    "HoughParams",
    "hough_estimator",
    "ORB_METHOD",
    "HOUGH_METHOD",
]

# ------------------------------------------------------------------ m-explore (orb)

#: ``match_conf`` of ``cv::detail::AffineBestOf2NearestMatcher`` (its default, kept by m-explore).
MEXPLORE_MATCH_CONF = 0.3
#: ``num_matches_thresh1``: fewer matches and no transform is estimated (confidence 0).
MEXPLORE_MIN_MATCHES = 6
#: ``estimation_confidence`` parameter of the ``map_merge`` node (default 1.0).
MEXPLORE_CONFIDENCE_THRESHOLD = 1.0
# cv::estimateAffinePartial2D's defaults, which the matcher uses.
_RANSAC_THRESHOLD = 3.0
_RANSAC_ITERS = 2000
_RANSAC_CONFIDENCE = 0.99
_REFINE_ITERS = 10
#: Unknown cells beyond this many of the known ones are left out of the image: ORB finds
#: nothing in uniform cells, and its border exclusion (31 px at each of 8 levels, up to
#: 31 * 1.2^7 = 111 px) then falls on unknown cells, as on a full-size ROS map.
_MEXPLORE_MARGIN = 128


@dataclass(frozen=True)
class RosGridRenderer:
    """m-explore's image of a map: the ROS int8 cell values as 8-bit grey levels.

    Free cells are ``0``, occupied ``100`` (``round(100 p)`` in between) and unknown cells,
    ``-1`` in ROS, ``255``. Rows are gridmerge's (top row first); pair it with
    :class:`RosRowOrder` to detect in ROS row order as m-explore does.
    """

    def __call__(self, grid: OccupancyGrid) -> tuple[np.ndarray, None]:
        img = np.rint(np.nan_to_num(grid.data, nan=0.0) * 100.0).astype(np.uint8)
        img[~grid.known] = 255
        return img, None


def _flip_keypoint(k: cv2.KeyPoint, height: int) -> cv2.KeyPoint:
    angle = k.angle if k.angle < 0 else (360.0 - k.angle) % 360.0
    return cv2.KeyPoint(k.pt[0], height - 1.0 - k.pt[1], k.size, angle, k.response, k.octave, k.class_id)


class RosRowOrder:
    """Runs a detector/descriptor on the image turned upside down (ROS rows: bottom first).

    ``nav_msgs/OccupancyGrid`` stores the bottom row first, and m-explore hands those bytes
    to OpenCV as they are, so its image is gridmerge's flipped vertically. Keypoints are
    reported back in gridmerge's rows (``y -> H - 1 - y``, ``angle -> -angle``).
    """

    def __init__(self, inner):
        self.inner = inner
        self.binary = bool(getattr(inner, "binary", False))

    def detect(self, image: np.ndarray, mask: np.ndarray | None = None):
        h = image.shape[0]
        flipped_mask = None if mask is None else np.ascontiguousarray(mask[::-1])
        return [_flip_keypoint(k, h) for k in self.inner.detect(np.ascontiguousarray(image[::-1]), flipped_mask)]

    def compute(self, image: np.ndarray, keypoints: Sequence[cv2.KeyPoint]):
        h = image.shape[0]
        kps, desc = self.inner.compute(np.ascontiguousarray(image[::-1]), [_flip_keypoint(k, h) for k in keypoints])
        return [_flip_keypoint(k, h) for k in kps], desc

    def __repr__(self) -> str:
        return f"RosRowOrder({self.inner!r})"


def mexplore_extractor(options: AlignOptions | None = None) -> FeatureExtractor:
    """m-explore's features: OpenCV's default ORB on the ROS image of the grid."""
    opts = options or AlignOptions()
    return FeatureExtractor(
        RosRowOrder(ORB(max_features=500, fast_threshold=20)),
        renderer=RosGridRenderer(),
        max_keypoints=opts.max_keypoints,
        margin=_MEXPLORE_MARGIN,
    )


def best_of_2_nearest(desc1: np.ndarray, desc2: np.ndarray, match_conf: float = MEXPLORE_MATCH_CONF) -> np.ndarray:
    """The matches of OpenCV's ``BestOf2NearestMatcher`` between two descriptor sets.

    A keypoint of set 1 is matched to its nearest neighbour in set 2 when that one is
    closer than ``(1 - match_conf)`` times the second nearest; then the same from set 2 to
    set 1, adding the pairs not found yet. Distances are Hamming distances for ``uint8``
    (binary) descriptors, Euclidean otherwise. Exact search (OpenCV uses FLANN's LSH index,
    an approximation of it).

    Returns
    -------
    (K, 2) int array
        ``[index in desc1, index in desc2]``, the 1->2 matches first.

    Examples
    --------
    >>> d1 = np.array([[0b1111], [0b0000]], dtype=np.uint8)
    >>> d2 = np.array([[0b0000], [0b1110], [0b1111]], dtype=np.uint8)
    >>> best_of_2_nearest(d1, d2).tolist()  # [0, 1] only passes the test from 2 to 1
    [[0, 2], [1, 0], [0, 1]]
    """
    d1 = np.asarray(desc1)
    d2 = np.asarray(desc2)
    if len(d1) < 2 or len(d2) < 2:
        return np.zeros((0, 2), dtype=int)
    norm = cv2.NORM_HAMMING if d1.dtype == np.uint8 else cv2.NORM_L2
    if norm == cv2.NORM_L2:
        d1, d2 = d1.astype(np.float32), d2.astype(np.float32)
    matcher = cv2.BFMatcher(norm)
    ratio = 1.0 - float(match_conf)
    out: list[tuple[int, int]] = []
    seen: set[tuple[int, int]] = set()
    for m in matcher.knnMatch(d1, d2, k=2):
        if len(m) == 2 and m[0].distance < ratio * m[1].distance:
            out.append((m[0].queryIdx, m[0].trainIdx))
            seen.add(out[-1])
    for m in matcher.knnMatch(d2, d1, k=2):
        if len(m) == 2 and m[0].distance < ratio * m[1].distance:
            pair = (m[0].trainIdx, m[0].queryIdx)
            if pair not in seen:
                out.append(pair)
    return np.array(out, dtype=int).reshape(-1, 2)


def mexplore_confidence(inliers: int, matches: int) -> float:
    """Brown & Lowe's confidence of a pairwise match, as m-explore's matcher computes it.

    >>> mexplore_confidence(20, 40)
    1.0
    """
    return float(inliers) / (8.0 + 0.3 * float(matches))


def _as_transform(matrix: np.ndarray) -> AffineTransform:
    try:
        return SimilarityTransform(matrix)
    except ValueError:
        return AffineTransform(matrix)


def _estimate_orb(a, b, fa, fb, opts: AlignOptions, rng) -> Estimate:
    # OpenCV's RANSAC here seeds its own generator (fixed seed): deterministic, rng unused.
    # m-explore matches its grids as images 0 and 1, i.e. a -> b; b's transform into a is
    # the inverse of that homography (what MatchPairsBody stores for the dual pair).
    pairs = best_of_2_nearest(fa.descriptors, fb.descriptors, MEXPLORE_MATCH_CONF)
    src, dst = fb.xy[pairs[:, 1]], fa.xy[pairs[:, 0]]
    n = len(pairs)
    details: dict = {
        "feature": "ORB",
        "match_conf": MEXPLORE_MATCH_CONF,
        "confidence_threshold": MEXPLORE_CONFIDENCE_THRESHOLD,
        "matches": n,
    }
    none = np.zeros(n, dtype=bool)
    if n < MEXPLORE_MIN_MATCHES:
        details.update(mexplore_confidence=0.0, inliers=0)
        msg = f"declined: {n} matches, m-explore estimates no transform below {MEXPLORE_MIN_MATCHES} (confidence 0)"
        return Estimate(None, none, src, dst, msg, details, success=False, confidence=0.0)
    h, mask = cv2.estimateAffinePartial2D(
        dst.astype(np.float32),
        src.astype(np.float32),
        method=cv2.RANSAC,
        ransacReprojThreshold=_RANSAC_THRESHOLD,
        maxIters=_RANSAC_ITERS,
        confidence=_RANSAC_CONFIDENCE,
        refineIters=_REFINE_ITERS,
    )
    if h is None:
        details.update(mexplore_confidence=0.0, inliers=0)
        return Estimate(None, none, src, dst, "declined: no partial affine transform found (confidence 0)", details, success=False, confidence=0.0)
    inl = mask.ravel().astype(bool)
    conf = mexplore_confidence(int(inl.sum()), n)
    details.update(mexplore_confidence=conf, inliers=int(inl.sum()), a_to_b=h.tolist())
    a_to_b = np.vstack([h, [0.0, 0.0, 1.0]])
    if not (np.isfinite(a_to_b).all() and abs(np.linalg.det(a_to_b[:2, :2])) > 1e-9):
        # m-explore would invert it regardless; a singular or non-finite model is no merge.
        msg = f"declined: degenerate transform (zero scale), m-explore confidence {conf:.2f}"
        return Estimate(None, inl, src, dst, msg, details, success=False, confidence=conf)
    transform = _as_transform(np.linalg.inv(a_to_b))
    success = conf >= MEXPLORE_CONFIDENCE_THRESHOLD
    msg = "" if success else f"declined: m-explore confidence {conf:.2f} below its threshold {MEXPLORE_CONFIDENCE_THRESHOLD}"
    return Estimate(transform, inl, src, dst, msg, details, success=success, confidence=conf)


# ------------------------------------------------------------------- Carpin (hough)

#: Acceptance index the best hypothesis needs (Birk & Carpin's ``agr / (agr + dis)``).
#:
#: Carpin's ``mapmerge`` library returns its hypotheses ranked by the index and leaves the
#: decision to the caller; the index is 1 for a perfect merge. The value is our choice,
#: the lowest round number above every wrong merge we measured: merges of different
#: buildings (``samples.negative_pair``) and of scaled pairs score 0.92-0.94, because free
#: space dominates the overlap. Correct merges of the sample maps score 0.997-0.999; of the
#: noisier real maps (Halmstad HIH) 0.92-0.95, so the index alone declines some of those.
HOUGH_MIN_ACCEPTANCE = 0.95


@dataclass(frozen=True)
class HoughParams:
    """Settings of the ``"hough"`` baseline.

    Attributes
    ----------
    theta_step_deg : float
        Angular resolution of the Hough transform and of the rotation search (Carpin: 1).
    rho_step : float
        Distance resolution of the Hough transform, cells.
    rotations : int
        Local maxima of the spectra's cross-correlation kept as rotation candidates (each
        is also tried turned by 180 degrees).
    translations : int
        Local maxima kept per axis of the projections' cross-correlations.
    max_points : int
        Occupied cells used for the spectrum at most; beyond, every k-th one (Carpin's
        ``hough_increment``).
    min_acceptance : float
        The decision threshold on the acceptance index.
    """

    theta_step_deg: float = 0.5
    rho_step: float = 1.0
    rotations: int = 4
    translations: int = 2
    max_points: int = 20000
    min_acceptance: float = HOUGH_MIN_ACCEPTANCE


_HOUGH_CHUNK = 2048


def _occupied_xy(grid: OccupancyGrid) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        rows, cols = np.nonzero(grid.data > OCCUPIED_THRESHOLD)
    return np.stack([cols, rows], axis=1).astype(float)


def hough_spectrum(points: np.ndarray, theta_step_deg: float = 0.5, rho_step: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Hough spectrum ``HS(theta) = sum_rho HT(rho, theta)^2`` of a set of points.

    ``theta`` is the direction of the lines' normal, ``x cos(theta) + y sin(theta) = rho``,
    over ``[0, 180)`` degrees (the spectrum has period 180 degrees).

    Parameters
    ----------
    points : (N, 2) float array
        ``(x, y)`` of the occupied cells.
    theta_step_deg, rho_step : float
        Resolution of the transform.

    Returns
    -------
    thetas_deg : (T,) float array
    spectrum : (T,) float array
        Normalised to a maximum of 1 (all zeros without points).

    Examples
    --------
    >>> pts = np.array([[x, 5.0] for x in range(50)])      # a horizontal wall
    >>> th, hs = hough_spectrum(pts, theta_step_deg=1.0)
    >>> float(th[np.argmax(hs)])                           # its normal points along y
    90.0
    """
    n_theta = int(round(180.0 / float(theta_step_deg)))
    thetas = np.arange(n_theta) * (180.0 / n_theta)
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(pts) == 0:
        return thetas, np.zeros(n_theta)
    pts = pts - pts.min(axis=0)
    rad = np.deg2rad(thetas)
    cos, sin = np.cos(rad) / rho_step, np.sin(rad) / rho_step
    reach = int(math.ceil(float(np.hypot(*pts.max(axis=0))) / rho_step)) + 1
    n_rho = 2 * reach + 1
    offsets = np.arange(n_theta, dtype=np.int64) * n_rho + reach
    ht = np.zeros(n_theta * n_rho)
    for k in range(0, len(pts), _HOUGH_CHUNK):  # bounded memory: chunk x n_theta votes at a time
        chunk = pts[k : k + _HOUGH_CHUNK]
        rho = chunk[:, :1] * cos[None, :] + chunk[:, 1:] * sin[None, :]
        ht += np.bincount((np.rint(rho).astype(np.int64) + offsets[None, :]).ravel(), minlength=n_theta * n_rho)
    ht = ht.reshape(n_theta, n_rho)
    hs = (ht * ht).sum(axis=1)
    top = hs.max()
    return thetas, hs / top if top > 0 else hs


def _circular_xcorr(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``c[k] = sum_m a[m] b[m - k]`` (indices modulo the length): peaks where a = b shifted by k."""
    return np.fft.irfft(np.fft.rfft(a) * np.conj(np.fft.rfft(b)), n=len(a))


def _xcorr_full(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Linear cross-correlation: ``c[j] = sum_n a[n + j - (len(b) - 1)] b[n]``."""
    n = len(a) + len(b) - 1
    nfft = 1 << max(1, (n - 1).bit_length())
    c = np.fft.irfft(np.fft.rfft(a, nfft) * np.fft.rfft(b[::-1], nfft), nfft)[:n]
    return c


def _peaks(c: np.ndarray, count: int, circular: bool) -> list[float]:
    """Positions (sub-sample, parabolic) of the ``count`` highest local maxima of ``c``."""
    n = len(c)
    if n == 0:
        return []
    if circular:
        left, right = np.roll(c, 1), np.roll(c, -1)
    else:
        left = np.concatenate([[-np.inf], c[:-1]])
        right = np.concatenate([c[1:], [-np.inf]])
    cand = np.flatnonzero((c > left) & (c >= right))
    if len(cand) == 0:
        cand = np.array([int(np.argmax(c))])
    order = cand[np.argsort(-c[cand], kind="stable")][:count]
    out = []
    for i in order:
        l, r = (i - 1) % n, (i + 1) % n
        if not circular and (i == 0 or i == n - 1):
            out.append(float(i))
            continue
        den = c[l] - 2.0 * c[i] + c[r]
        delta = 0.5 * (c[l] - c[r]) / den if den < 0 else 0.0
        out.append(float(i) + float(np.clip(delta, -0.5, 0.5)))
    return out


def _axis_shifts(pa: np.ndarray, qb: np.ndarray, axis: np.ndarray, count: int) -> list[float]:
    """Shifts ``s`` along ``axis`` that line up the projections: ``pa . axis ~ qb . axis + s``."""
    ra, rb = pa @ axis, qb @ axis
    oa, ob = math.floor(ra.min()), math.floor(rb.min())
    ha = np.bincount(np.rint(ra - oa).astype(np.int64)).astype(float)
    hb = np.bincount(np.rint(rb - ob).astype(np.int64)).astype(float)
    c = _xcorr_full(ha, hb)
    return [oa - ob + (j - (len(hb) - 1)) for j in _peaks(c, count, circular=False)]


def _rotation(deg: float) -> np.ndarray:
    t = math.radians(deg)
    return np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])


def hough_estimator(params: HoughParams | None = None):
    """The estimator of the ``"hough"`` method with other settings, for :class:`Method`.

    >>> from gridmerge.align import Method
    >>> m = Method("hough-0.9", hough_estimator(HoughParams(min_acceptance=0.9)), None, verified=False)
    """
    p = params or HoughParams()

    def estimate(a, b, fa, fb, opts: AlignOptions, rng) -> Estimate:
        return _estimate_hough(a, b, opts, p)

    return estimate


def _estimate_hough(a: OccupancyGrid, b: OccupancyGrid, opts: AlignOptions, p: HoughParams) -> Estimate:
    # Deterministic: Carpin's randomized Hough transform is not used, so no rng is needed.
    empty = np.zeros((0, 2))
    none = np.zeros(0, dtype=bool)
    pa, pb = _occupied_xy(a), _occupied_xy(b)
    details: dict = {"occupied_cells": [len(pa), len(pb)], "min_acceptance": p.min_acceptance}
    if len(pa) < 2 or len(pb) < 2:
        which = "a" if len(pa) < 2 else "b"
        return Estimate(None, none, empty, empty, f"declined: map {which} has no walls (occupied cells) to match", details, success=False, confidence=0.0)

    step_a = max(1, math.ceil(len(pa) / p.max_points))
    step_b = max(1, math.ceil(len(pb) / p.max_points))
    thetas, hs_a = hough_spectrum(pa[::step_a], p.theta_step_deg, p.rho_step)
    _, hs_b = hough_spectrum(pb[::step_b], p.theta_step_deg, p.rho_step)
    dtheta = thetas[1] - thetas[0]
    # Dominant wall normal of a: the projections are taken along it and across it.
    phi = math.radians(float(thetas[int(np.argmax(hs_a))]))
    u = np.array([math.cos(phi), math.sin(phi)])
    v = np.array([-math.sin(phi), math.cos(phi)])

    cc = _circular_xcorr(hs_a, hs_b)
    rotations = []
    for k in _peaks(cc, p.rotations, circular=True):
        deg = (k * dtheta) % 180.0
        rotations += [deg, deg + 180.0]

    hypotheses = []
    for deg in rotations:
        r = _rotation(deg)
        qb = pb @ r.T
        for su in _axis_shifts(pa, qb, u, p.translations):
            for sv in _axis_shifts(pa, qb, v, p.translations):
                t = su * u + sv * v
                m = np.array([[r[0, 0], r[0, 1], t[0]], [r[1, 0], r[1, 1], t[1]]])
                warped = warp_values(b.data, m, a.shape, interpolation="nearest")
                ai, agr, dis = acceptance_index(a.data, warped)
                hypotheses.append((deg, t, ai, agr, dis))
    # Carpin ranks hypotheses by the acceptance index alone; one that shares fewer cells
    # than options.min_overlap_cells has no meaningful index and is left out.
    usable = [h for h in hypotheses if h[3] + h[4] >= opts.min_overlap_cells and math.isfinite(h[2])]
    ranked = sorted(usable, key=lambda h: (-h[2], -h[3]))
    details["dominant_direction_deg"] = math.degrees(phi)
    details["hypotheses"] = [
        {"rotation_deg": round(d % 360.0, 4), "translation": [round(float(x), 3) for x in t],
         # None: no cell known in both (the index is undefined)
         "acceptance_index": round(float(ai), 5) if math.isfinite(ai) else None, "agreement": agr, "disagreement": dis}
        for d, t, ai, agr, dis in sorted(hypotheses, key=lambda h: (-(h[2] if math.isfinite(h[2]) else -1.0), -h[3]))
    ]
    if not ranked:
        return Estimate(None, none, empty, empty, f"declined: no hypothesis shares {opts.min_overlap_cells} known cells with map a", details, success=False, confidence=0.0)
    deg, t, ai, agr, dis = ranked[0]
    transform = SimilarityTransform(rotation=math.radians(deg % 360.0), translation=t)
    details["acceptance_index"] = float(ai)
    success = bool(ai >= p.min_acceptance)
    msg = "" if success else f"declined: best acceptance index {ai:.3f} below {p.min_acceptance}"
    return Estimate(transform, none, empty, empty, msg, details, success=success, confidence=float(ai))


# ------------------------------------------------------------------- registration

#: m-explore's multirobot_map_merge (ORB, 2-NN matching, partial affine RANSAC, confidence >= 1).
ORB_METHOD = register_method(
    Method(
        "orb",
        _estimate_orb,
        mexplore_extractor,
        verified=False,
        description="baseline: m-explore's map_merge (ORB, BestOf2Nearest, partial affine RANSAC, confidence >= 1.0)",
    )
)
#: Carpin (2008): Hough spectra for the rotation, projections for the translation, acceptance index.
HOUGH_METHOD = register_method(
    Method(
        "hough",
        hough_estimator(),
        None,
        verified=False,
        description="baseline: Carpin 2008 (Hough spectrum rotation, projection translation, acceptance index; scale 1)",
    )
)

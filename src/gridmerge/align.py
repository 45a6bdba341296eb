"""Aligning two maps: features, matches, a robust transform, refinement, verification.

:func:`align` is the entry point. It returns an :class:`AlignResult` whose ``success`` is
``False`` (with a ``message`` saying why) whenever the evidence for the transform is too
weak: a wrong merge is worse than no merge.

Methods
-------
``"hybrid"`` (default)
    Candidate transforms from two independent sources: SIFT keypoints (the paper's
    parameters; each of a keypoint's 3 nearest neighbours is a candidate match, and each
    match proposes a whole similarity from the keypoints' orientations and sizes), and the
    maps' walls (wall-direction histograms for the rotation, FFT correlation of wall images
    for the translation, :mod:`gridmerge.correlate`). All are scored by wall agreement, the
    best distinct ones refined to sub-pixel precision against the cells of both maps (then
    polished by ICP on the walls where that makes them agree clearly better, and again
    from there while it does), and
    the winner's confidence combines its wall agreement with how clearly it beats every
    clearly different pose (repeated structure makes them close): the other candidates
    that move the shared part of b by 25 px or more, and the winner itself shifted by
    40 px in 24 directions (a pose held by one wall fits as well shifted along it). A
    pose about to be taken whose scale is off the maps' resolution ratio (by more than
    half a percent) is judged again with itself brought to the ratio and refined, when
    that removes a third of the walls' disagreement (a refinement from a start a few
    percent off can stop in a fit of one part of the maps). A pose whose scale disagrees
    with the maps' resolutions by more than 15 % is declined.
    The wall correlation
    runs in two forms: first overlap-seeking (shared free space weighs much, so its poses
    share large explored areas, where wall agreement judges well); when that pose is not
    confident enough, wall-led (shared free space weighs little: it finds the right pose
    of maps that share a small part far more often, but also poses that agree by chance
    on a small part; besides the wall directions' rotations it tries the one most keypoint
    matches vote for). The wall-led candidates are ranked by wall agreement weighed by the
    walls compared and the share of the maps overlapped, every pose of the first search
    counts as a rival, and the winner replaces the first one only when it is more
    confident and its walls agree on at least 75 % of the overlap (or, on noisy maps that
    miss walls, on 50 % when no clearly different pose scores half as much). The best keypoint
    candidate is judged first, alone: when it settles the pose beyond doubt (confidence
    at least ``AlignOptions.keypoints_first``, walls agreeing on 75 % of the overlap, no
    clearly different keypoint candidate above 60 % of its score), the wall correlation
    is skipped (a settled pose off the resolutions' ratio is judged at the ratio too, as
    above). Otherwise SIFT looks at both maps a second time, drawn blurred (walls
    wider, corners rounder: other keypoints on fragmentary walls), and the matches of
    those keypoints add candidates whose scale the maps' resolutions allow
    (``AlignOptions.second_look``). The two maps' keypoints are found in parallel; a helper thread prepares
    the maps for scoring and refinement while the keypoints are matched, and verifies
    each settled pose while its rivals are sought.
    The search takes the map that covers more ground as its reference, whichever order
    the maps come in (``AlignOptions.search_from``): swapping the maps inverts the
    transform and keeps the decision. A pose the full search takes is polished once more
    on the walls in its search's own frame (within 3 px, when its walls agree on half
    and agree no less after), then in the frame of the map that was not its search's
    reference, where that makes them agree clearly better there and no worse in the
    search's frame. Last, once taken, it is moved halfway towards its polish by ICP on
    the walls of the maps as given (not despeckled), in the finer map's frame, when that
    polish moves b's corners 4 px at most and the pose there is still taken
    (``details["midway"]``): the smoothed cells' optimum and the raw walls' are each off
    the truth their own way on a few dozen wall cells. Then, unless its walls agree on
    98 % of the overlap already, it is moved to the pose near it (every turn within 2
    degrees and shift within 20 px, at its scale and, when that is off the resolutions'
    ratio, at the ratio, each polished by ICP) whose walls agree best, when they agree
    there by 2 points more and on 75 % at least, the overlap holds 30 wall cells of each
    map or more, and the pose is still taken (``details["widened"]``): a search's pose
    10-20 px off, held by walls that coincide with the wrong ones, lies beyond ICP's
    reach.
``"sift"``
    The keypoint candidates alone, verified and refined the same way.
``"ransac"``
    SIFT keypoints, FLANN matching with Lowe's ratio test, RANSAC (MSAC scoring, local
    optimisation) for a similarity transform, least squares on the inliers, then sub-pixel
    refinement against the cells of both maps.
``"paper"``
    The paper as written: SIFT, nearest-neighbour matching by Euclidean distance, and the
    5-parameter transform ``T(dx, dy) R(theta) S(sx, sy)`` as the mean of the cluster of
    similar 3-point solutions. No refinement.

All are verified against the maps (:mod:`gridmerge.verify`); baselines registered by
:mod:`gridmerge.baselines` (``"orb"``, ``"hough"``) decide by their own rules.

Examples
--------
>>> import gridmerge
>>> from gridmerge import samples
>>> a, b, truth = samples.table1_pair()
>>> r = gridmerge.align(a, b)
>>> r.success, round(r.rotation_deg, 1), round(r.scale, 3)
(True, 30.0, 0.95)
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from collections import Counter
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import MappingProxyType
from typing import Callable

import numpy as np

from .errors import GridMergeError
from .estimate import MatchEvidence, match_evidence, paper_consensus, ransac, similarity_hypotheses
from .features import FeatureExtractor, Features, GreyRenderer, SIFT
from .grid import OccupancyGrid
from .io.jsonable import finite
from .matching import knn, match_nn, match_smnn, match_snn
from .parallel import opencv_threads_split
from .refine import WallICP, chamfer_polish, prepare_fields, refine_direct, wall_search
from .transforms import AffineTransform, SimilarityTransform, corner_error, pixel_to_metric
from .correlate import correlation_hypotheses, match_rotation, rotation_candidates
from .verify import Crossing, Slide, Verification, WallScorer, chance_wall_agreement, crossing, despeckle, slide, verify

__all__ = ["AlignOptions", "AlignResult", "align", "METHODS", "Method", "Estimate", "register_method", "default_extractor", "ANY_SCALE", "reference_first"]


@dataclass(frozen=True)
class AlignOptions:
    """Settings of :func:`align`. Every field has a working default.

    Attributes
    ----------
    ratio : float
        Lowe's ratio test threshold (``"ransac"``).
    neighbours : int
        Candidate matches per keypoint of a (``"sift"``).
    max_matches : int
        Candidate matches kept at most, the most distinctive first (``"sift"``; bounds time).
    max_proposals : int
        Matches that propose a transform, the most distinctive first (``"sift"``).
    hypotheses : int
        Candidate transforms verified against the maps (``"sift"``).
    wall_tolerance : float
        Distance (a's cells) within which walls of the two maps count as one.
    mutual : bool
        Keep only mutual nearest neighbours as well.
    matcher : {"flann", "brute"}
        FLANN kd-trees (approximate, fast) or exhaustive search.
    residual_threshold : float
        RANSAC inlier threshold, in a's pixels.
    max_trials : int
        RANSAC samples at most.
    min_scale, max_scale : float
        Plausible range of the scale between the maps (a's pixels per b's pixel).
    refine : bool
        Refine against the maps' cells (``"sift"``).
    paper_samples : int
        Random 3-point samples of the paper's consensus (``"paper"``).
    min_inliers : int
        Decline with fewer inlier correspondences.
    min_acceptance : float
        Decline below this acceptance index.
    min_wall_agreement : float
        Decline when fewer walls than this share coincide in the overlap.
    min_wall_agreement_matched : float
        The same, for a pose that the keypoint matches confirm far beyond chance
        (``"hybrid"``; :func:`gridmerge.estimate.match_evidence`): real maps that bend
        leave right poses' walls agreeing on 33-48 % (Halmstad E5).
    min_overlap_cells : int
        Decline when the maps share fewer known cells.
    min_overlap_walls : int
        Decline when either map has fewer occupied cells in the overlap
        (:attr:`~gridmerge.verify.Verification.walls_a`, ``walls_b``, counted in the
        cells of the map the search took as its reference): the wall agreement is the
        mean of the two maps' shares of walls matched, and a share of a handful of cells
        is no evidence. A simulated pair of two distant parts of one building (seed 4,
        pair 49) was merged at confidence 0.77, its overlap open floor holding 6 wall
        cells of one map, all matched, and 30 of the other, 7 matched. Right merges can
        rest on little: simulated pair 50 of seed 3 is merged right with 18 of one map's
        (at 20 it was declined). docs/benchmarks.md, eighteenth session; "The decline
        threshold" counts what higher values decline (``--min-overlap-walls`` on the
        command line).
    few_walls : int or None
        A pose taken on fewer wall cells than this in the overlap, the two maps'
        together (``walls_a + walls_b``, counted as for ``min_overlap_walls``), carries
        a warning (:attr:`AlignResult.warnings`): its confidence does not count how much
        wall it rests on, and in the benchmark's runs of simulated and HM3D maps one such
        merge in seven was wrong or joined two different places, against one in three
        hundred of those on more; on real maps of a few rooms (``halmstad-partial``) all
        five were (docs/benchmarks.md, "Poses on few walls"). The decision does not
        change; ``None`` or 0: no warning.
    min_wall_share : float
        Decline when, of either map's occupied cells in the overlap, fewer than this share
        lie within the tolerance of the other map's walls
        (:attr:`~gridmerge.verify.Verification.matched_a` / ``walls_a``, ``matched_b`` /
        ``walls_b``): the wall agreement is their mean, and a small map whose few walls
        all lie on a large map's walls reaches half of it while the large map's walls
        cross its rooms: fresh simulated seed 13, pair 19 (two places) was merged at
        confidence 0.70 so, 52 of the small map's 53 walls matched and 69 of the large
        one's 1116 (6 %). Right merges' lower share was 0.50 or more on simulated seeds
        0-18, 0.26 or more on Halmstad's bent maps. docs/benchmarks.md, thirty-second
        session.
    min_confidence : float
        Decline below this confidence (CLI ``--min-confidence``; docs/benchmarks.md, "The
        decline threshold", measures what lower values merge, rightly and wrongly).
    max_slide : float or None
        Decline a pose that the walls do not fix: when b, slid along the walls the two
        maps share (their main direction in the overlap) by 0.15 of the overlap's size
        (the square root of its cells) either way, keeps more than this share of its wall
        agreement on both sides (:func:`gridmerge.verify.slide`;
        ``result.details["slide"]`` records it for every pose otherwise taken). A pose
        held by one straight wall or one corridor, the rest of b on a's unknown cells,
        agrees nearly as well anywhere along it: the maps cannot say where b lies along
        that line, and maps of two places fitted by chance look like that. Walls slid off
        the other map's known cells do not count against the pose, so an overlap that
        is one closed elongated room keeps much of its agreement too. Measured on the
        stored runs' 1401 taken poses (right ones keep at most 0.64) and on HM3D seeds
        9-20 run with it (one false merge and one right merge declined):
        docs/benchmarks.md, forty-third session. ``None`` skips the test (CLI
        ``--max-slide``).
    max_crossing : float or None
        Decline a pose resting on fewer than 3000 wall cells in the overlap (both maps'
        together, counted in the finer map's cells) when more than this share of them
        stand inside the other map's open space: deeper than 5 cells from any of its
        walls or unknown cells (:func:`gridmerge.verify.crossing`;
        ``result.details["crossing"]`` records ``share`` and ``walls`` for every pose
        that reaches the test; ``share`` is ``None`` on 3000 wall cells or more, not
        judged). Maps of two places fitted room on room have walls across each other's
        rooms. Measured on the stored runs' 1964 taken poses: the six poses of simulated
        and HM3D maps above 0.2 were all wrong (0.25-0.39), the right ones reached 0.17;
        on HM3D seeds 25-26, never run before, it declined three false merges (0.20-0.34,
        confidence 0.81-1.0) and one wrong merge. Real maps of one building differ
        (furniture, doors, glass, bending): Halmstad's right poses reach 0.54, all on
        8700 wall cells or more, and on windows cut from them (small real overlaps)
        right poses reach 0.23, so a few such merges are lost. docs/benchmarks.md,
        forty-fourth session. ``None`` skips the test (CLI ``--max-crossing``).
    unsure_walls : int or None
        Decline a pose of confidence below 0.8 (:data:`SURE_CONFIDENCE`) that rests on
        fewer wall cells than this in the overlap (both maps' together, despeckled, as
        ``result.verification`` counts them in a's cells). The confidence's wall term was
        calibrated on whole buildings, where walls agreeing on half of a building are far
        beyond chance; on a few rooms of a repetitive building, a chance pose agrees as
        well. Measured: of the 1964 poses the stored runs took (simulated, HM3D homes,
        Halmstad), every right one below 0.8 is a whole Halmstad building on 11 000 wall
        cells or more; on ``halmstad-partial`` (real maps of part of a building each),
        seeds 0-2, 9 of the 15 wrong or false merges lay below 0.8 on fewer than 10 000,
        and 3 of the 68 right ones. docs/benchmarks.md, forty-fifth session. ``None``
        skips the test (CLI ``--unsure-walls``).
    few_walls_agreement : float or None
        Decline a pose resting on fewer than :data:`FEW_WALLS_EVIDENCE` (200) wall cells
        in the overlap (both maps' together, as ``result.verification`` counts them)
        whose walls agree on less than this share of them, whatever its confidence (whose
        wall term is full from 70 %). Where the two maps share only a few walls, the
        walls of a right pose lie on each other (on the stored runs' 424 right poses on
        fewer than 200 wall cells, 4 agree on less than 75 %, the least 70 %), while a
        chance fit of two places, or of the wrong part, lays a few walls on walls and the
        rest beside them (8 of the 27 wrong or false merges there agree on 61-72 %).
        docs/benchmarks.md, sixty-first session. ``None`` skips the test (CLI
        ``--few-walls-agreement``).
    max_keypoints : int
        Strongest keypoints kept per map (bounds time and memory).
    feature_pixels : int
        Keypoints are detected on at most this many pixels (a larger known area is
        detected at reduced resolution, then refined at full resolution); 0: always full.
    keypoints_first : float
        ``"hybrid"``: judge the best keypoint hypothesis alone first, and skip the wall
        correlation when it gives at least this confidence, its walls agree on at least
        75 % of the overlap and no clearly different keypoint hypothesis scores above 60 %
        of its score; 0 always searches both.
    scale_prior : float
        ``"hybrid"`` (and the re-verification of known poses when merging): strength with
        which the refinement pulls the scale towards the maps' resolution ratio, in units
        of the information the cells give on the scale, for candidates already within 3 %
        of that ratio; 0 estimates the scale from the cells alone. The cells constrain the
        scale least of the four parameters, and SLAM maps know their resolution. Default
        1 (measured 2026-11-29 against 0, docs/benchmarks.md): simulated seed 0, 46 of 48
        pairs merged and 46 precise instead of 45 and 43 (seed 1: 42 and 42 instead of 43
        and 42; the pair lost sits at the wall-led ratio's threshold, 0.802 against 0.8),
        median corner error 0.13 px instead of 0.27; Halmstad 71 of 97 instead of 70,
        the same 4 of 56 cross-building pairs merged, the E5 fleet 82 of 91 instead of 83,
        simulated fleets more precise (16 robots: worst 0.46 px instead of 0.74). 4
        (``--trust-resolution``) pulls harder, for maps whose resolutions are exact. Where
        the cells contradict the ratio the refinement's fit gets worse and it is refused
        (the candidate stays unrefined).
    max_scale_disagreement : float or None
        Decline a pose whose scale disagrees with the maps' resolution ratio by more than
        this fraction (0.15: outside 0.87-1.15 times the ratio; the ratio is b's
        resolution over a's, the scale the maps' own metadata gives). SLAM maps know
        their resolution: the Halmstad Tango maps drift against each other by at most
        5 % (annotated scales 0.95-1.04) and the simulated robots' metadata is exact,
        while real maps of two different buildings were merged at scales 0.85 and 2 to 3
        (4 of the 11 false merges of the Halmstad cross-building pairs). Such poses are
        still searched, and compete as rivals: without them, other wrong poses win more
        clearly (measured). ``None`` accepts any scale within ``min_scale`` and
        ``max_scale``, for maps whose resolutions are unknown or wrong (CLI
        ``--any-scale``).
    one_sided_confidence : float or None
        ``"hybrid"``: a pose found with a confidence below this is sought again from the
        other map's side (that map as the reference; first the search takes the one
        :attr:`search_from` names). When that search's pose is the same
        merge (it moves the part of b the two maps share by less than 40 px, median; maps
        that bend leave the two sides' poses of one merge up to 34 px apart, Halmstad E5),
        the pair takes the more confident of the two, with its confidence. When it is
        another pose, or none, the pose is one-sided: it is declined below this
        confidence. Maps of different places fit by chance from one side only: the four
        Halmstad cross-building pairs that one search merged (confidence 0.56-0.75) are
        fit 110-550 px away from the other side, and none of the 56 is merged now (2
        were with the maps swapped, at 0.83 and 0.99, until :attr:`search_from` made the
        order irrelevant). Most right poses of real pairs are
        found from both sides; two Halmstad ones found from one side only, at 0.57 and
        0.67, are declined (docs/benchmarks.md, ninth session). Pairs declined anyway
        whose best pose shares under 10 % of the smaller map are not sought again.
        A pose only the walls found (no keypoint proposed it, their matches do not confirm
        it) is not confirmed by the same pose from the other side at confidence 0: seen
        from there its walls disagree or a clearly different pose fits as well
        (docs/benchmarks.md, thirty-second session).
        When the first side declines outright (below :attr:`min_confidence`) and the
        other side finds another pose at this confidence or more, that pose is taken if
        it clearly beats the first side's best (walls agreeing on at least twice the
        share, counted in the first side's frame): the first side found no fit at all,
        not a rival fit (docs/benchmarks.md, thirty-third session); and if its overlap
        holds at least 40 wall cells of the two maps (thirty-ninth session).
        ``None`` searches from the reference's side only: pairs below this take half the
        time. CLI
        ``--one-sided-confidence``.
        :func:`gridmerge.merge` with three maps or more searches its pairs from one side
        and, after placing the maps, searches from both sides the alignments that lie on
        no loop of the map graph (a loop checks the others).
    search_from : {"larger", "a"}
        Which map the search takes as its reference, for the methods that may choose
        (:attr:`Method.order_free`: ``"hybrid"``). ``"larger"`` (default): the map with
        more known area (square metres; ties broken by the maps' cells), whichever order
        they come in, so ``align(b, a)`` gives ``align(a, b)``'s decision with the
        transform inverted; ``result.details["searched_from"]`` says which map it was, and
        the ``verification`` is counted in that map's cells. The search's steps are not
        symmetric (which map's keypoints seek partners, which map slides over the other),
        so with ``"a"`` the order of the maps can change the outcome: 5 of the 97
        Halmstad sensor pairs merged in one order only, and 2 of the 56 cross-building
        pairs were merged wrongly with the maps swapped (docs/benchmarks.md, fifteenth
        session).
    wall_led : bool
        ``"hybrid"``: when the first, overlap-seeking wall search gives no confident pose,
        search again with the wall-led correlation (:mod:`gridmerge.correlate`), which
        finds maps that share a small part far more often; it costs about 0.4 s more on
        such pairs (and on pairs that do not overlap at all: a fleet of 8 robots merges in
        1.4 times the time). ``False`` skips it.
    second_look : float
        ``"hybrid"``: when the keypoints-first stage does not settle the pose, SIFT looks
        at both maps again (as the search sees them: cut to their known cells, isolated
        hits made unknown) drawn blurred by a Gaussian of this many cells, and the matches of
        those keypoints add pose hypotheses to the search (those whose scale the maps'
        resolutions allow, :attr:`max_scale_disagreement`). Blurred walls are wider and
        their corners rounder, so the detector finds other keypoints on fragmentary
        walls; the first keypoints still give the keypoint evidence. It keeps at most
        5000 keypoints per map, detected on at most 400 000 pixels (fewer when
        :attr:`feature_pixels` is lower). It costs about 0.1 s per 1585 x 1585 map, on
        the pairs that reach it; 0 skips it.
        (docs/benchmarks.md, thirteenth session, measures it.)
    coarse_look : int
        ``"hybrid"``: when the search declines, it searches again with keypoints detected
        on at most this many pixels (instead of :attr:`feature_pixels`), and takes that
        search's pose if it is accepted (``result.details["coarse_look"]`` tells). Real
        maps' fragmentary walls and noise give other keypoints at another detection
        resolution, and a pose the first keypoints missed may be among theirs: on the
        Halmstad sensor pairs, 5 more of 97 merged (90), none wrongly, none of the 56
        cross-building pairs (docs/benchmarks.md, sixteenth session). Pairs whose maps'
        keypoint images are no larger than this (nothing would change), and pairs whose
        declined pose shares less than 10 % of the smaller map (maps that do not overlap,
        most pairs of a fleet), are not searched again. Declined pairs take up to about
        twice the time (the second search reuses the first one's wall scores,
        refinements, ICP polishes and correlation peaks); 0 never searches again. :func:`gridmerge.merge` with three maps or more
        searches again only the declined pairs of the maps its placement leaves out.
    """

    ratio: float = 0.8
    neighbours: int = 3
    max_matches: int = 6000
    max_proposals: int = 1500
    hypotheses: int = 6
    wall_tolerance: float = 3.0
    mutual: bool = False
    matcher: str = "flann"
    residual_threshold: float = 3.0
    max_trials: int = 5000
    min_scale: float = 0.2
    max_scale: float = 5.0
    refine: bool = True
    paper_samples: int = 4000
    min_inliers: int = 8
    min_acceptance: float = 0.7
    min_wall_agreement: float = 0.4
    min_wall_agreement_matched: float = 0.3
    min_overlap_cells: int = 100
    min_overlap_walls: int = 10
    few_walls: int | None = 50
    min_wall_share: float = 0.15
    min_confidence: float = 0.5
    max_slide: float | None = 0.75
    max_crossing: float | None = 0.2
    unsure_walls: int | None = 10000
    few_walls_agreement: float | None = 0.75
    max_keypoints: int = 20000
    feature_pixels: int = 400_000
    keypoints_first: float = 0.9
    scale_prior: float = 1.0
    max_scale_disagreement: float | None = 0.15
    one_sided_confidence: float | None = 0.8
    wall_led: bool = True
    second_look: float = 1.5
    search_from: str = "larger"
    coarse_look: int = 200_000


#: :class:`AlignOptions` fields for maps whose resolutions are unknown or wrong (a
#: blueprint, images of unknown pixel size; CLI ``--any-scale``): any scale is accepted and
#: the refinement does not pull the scale towards the resolutions' ratio.
ANY_SCALE = MappingProxyType({"max_scale_disagreement": None, "scale_prior": 0.0})


@dataclass
class AlignResult:
    """The outcome of :func:`align`: b's transform into a, and how far to trust it.

    Attributes
    ----------
    success : bool
        ``True`` when the maps were aligned with enough confidence.
    transform : AffineTransform or None
        Maps b's image pixels to a's image pixels; ``None`` when declined.
    candidate : AffineTransform or None
        The best transform found, even when declined (for diagnosis only).
    metric_transform : AffineTransform or None
        ``transform`` between the maps' metric frames (b's metres -> a's metres).
    confidence : float
        In ``[0, 1]``.
    acceptance_index : float
        Birk & Carpin's index over the overlap (``nan`` without overlap).
    inliers : int
        Correspondences consistent with the transform.
    matches : int
        Correspondences after matching.
    keypoints : tuple of int
        Keypoints found in a and in b.
    method : str
    message : str
        Why the alignment was declined, or a short summary.
    elapsed_s : float
        Wall time of the alignment.
    verification : Verification or None
        The agreement the decision was made on, counted in the reference map's cells
        (``details["searched_from"]``: ``"a"`` or ``"b"``, for the order-free methods).
    inlier_xy : (K, 2, 2) float array
        Inlier correspondences ``[[xb, yb], [xa, ya]]`` (for plots).
    details : dict
        Method-specific diagnostics (JSON-ready).
    warnings : list of str
        What a user should know about a taken pose that passed every decline rule: that
        it rests on few walls (:attr:`AlignOptions.few_walls`). Empty when declined.
    """

    success: bool
    transform: AffineTransform | None
    candidate: AffineTransform | None
    metric_transform: AffineTransform | None
    confidence: float
    acceptance_index: float
    inliers: int
    matches: int
    keypoints: tuple[int, int]
    method: str
    message: str
    elapsed_s: float = 0.0
    verification: Verification | None = None
    inlier_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)), repr=False)
    details: dict = field(default_factory=dict, repr=False)
    warnings: list[str] = field(default_factory=list)

    def __bool__(self) -> bool:
        return self.success

    # -------------------------------------------------------------- accessors
    @property
    def matrix(self) -> np.ndarray | None:
        """``(2, 3)`` float array mapping b's image pixels to a's, or ``None`` when declined."""
        return None if self.transform is None else self.transform.matrix

    @property
    def rotation_deg(self) -> float:
        t = self.transform or self.candidate
        return math.nan if t is None else math.degrees(t.rotation)

    @property
    def scale(self) -> float:
        t = self.transform or self.candidate
        return math.nan if t is None else t.scale

    @property
    def metric(self) -> dict | None:
        """b's map frame in a's: ``{"x", "y", "yaw", "scale"}`` (metres, radians)."""
        m = self.metric_transform
        if m is None or self.transform is None:
            return None
        x, y = m.translation
        return {"x": float(x), "y": float(y), "yaw": float(m.rotation), "scale": float(m.scale)}

    # ------------------------------------------------------------ save/load
    def to_dict(self) -> dict:
        """A JSON-ready dictionary (the CLI's ``--json`` output)."""
        t = self.transform
        d: dict = {
            "success": bool(self.success),
            "method": self.method,
            "message": self.message,
            "matrix": None if t is None else t.matrix.tolist(),
            "rotation_deg": None if t is None else math.degrees(t.rotation),
            "scale": None if t is None else t.scale,
        }
        if t is not None and not isinstance(t, SimilarityTransform):
            sx, sy = t.scale_xy
            d["scale_x"], d["scale_y"] = sx, sy
        d["translation_px"] = None if t is None else t.translation.tolist()
        d["metric"] = self.metric
        d["confidence"] = _finite_or_none(self.confidence)
        d["acceptance_index"] = _finite_or_none(self.acceptance_index)
        d["inliers"] = int(self.inliers)
        d["matches"] = int(self.matches)
        d["keypoints"] = [int(k) for k in self.keypoints]
        d["elapsed_s"] = float(self.elapsed_s)
        d["verification"] = None if self.verification is None else self.verification.to_dict()
        d["transform"] = None if t is None else t.to_dict()
        d["candidate"] = None if self.candidate is None else self.candidate.to_dict()
        d["metric_transform"] = None if self.metric_transform is None else self.metric_transform.to_dict()
        d["details"] = finite(self.details)  # a copy, NaN (a method's undefined index) as None
        d["warnings"] = list(self.warnings)
        return d

    def to_json(self, **kwargs) -> str:
        return json.dumps(self.to_dict(), **kwargs)

    @classmethod
    def from_dict(cls, d: dict) -> "AlignResult":
        """Rebuild a result saved with :meth:`to_dict` (inlier coordinates are not saved)."""

        def tr(key):
            return None if d.get(key) is None else AffineTransform.from_dict(d[key])

        v = d.get("verification")
        return cls(
            success=bool(d["success"]),
            transform=tr("transform"),
            candidate=tr("candidate"),
            metric_transform=tr("metric_transform"),
            confidence=_none_to_nan(d.get("confidence")),
            acceptance_index=_none_to_nan(d.get("acceptance_index")),
            inliers=int(d.get("inliers", 0)),
            matches=int(d.get("matches", 0)),
            keypoints=tuple(d.get("keypoints", (0, 0))),  # type: ignore[arg-type]
            method=d.get("method", ""),
            message=d.get("message", ""),
            elapsed_s=float(d.get("elapsed_s", 0.0)),
            verification=None if v is None else Verification(**{k: _none_to_nan(x) if k in ("acceptance_index", "wall_agreement") else x for k, x in v.items()}),
            details=d.get("details", {}),
            warnings=list(d.get("warnings", [])),
        )

    def save(self, path) -> None:
        """Write :meth:`to_dict` as JSON (atomically)."""
        from .io.atomic import atomic_write

        atomic_write(Path(path), (self.to_json(indent=2) + "\n").encode())

    @classmethod
    def load(cls, path) -> "AlignResult":
        return cls.from_dict(json.loads(Path(path).read_text()))


def _finite_or_none(v):
    return None if v is None or not math.isfinite(v) else float(v)


def _none_to_nan(v):
    return math.nan if v is None else float(v)


def default_extractor(options: AlignOptions | None = None) -> FeatureExtractor:
    """The feature extractor of the built-in methods: SIFT with the paper's parameters."""
    opts = options or AlignOptions()
    return FeatureExtractor(SIFT(), max_keypoints=opts.max_keypoints, work_pixels=opts.feature_pixels)


# ---------------------------------------------------------------- estimators
@dataclass
class Estimate:
    """What a method's estimator returns to :func:`align`.

    Attributes
    ----------
    transform : AffineTransform or None
        b's cropped-map pixels -> a's cropped-map pixels (the maps given to the estimator).
    inliers : (N,) bool array
        Which correspondences support ``transform``.
    src, dst : (N, 2) float arrays
        The correspondences (b's points, a's points).
    message : str
        Why no transform was found (when ``transform`` is None).
    details : dict
        JSON-ready diagnostics.
    verification : Verification, optional
        The estimator's own verification of ``transform``, reused by :func:`align`.
    success, confidence : bool, float, optional
        The decision of a method that judges itself (``Method.verified`` is False).
    matched : bool
        ``confidence`` comes from the keypoint matches, which confirm the transform far
        beyond chance: its walls need only agree on ``min_wall_agreement_matched``.
    one_sided : str
        Why the transform is declined although its confidence passes: the search from
        b's side found another pose, and its confidence is below
        ``AlignOptions.one_sided_confidence`` ("" otherwise).
    slid : tuple, optional
        ``(pose, slide)``: :func:`gridmerge.verify.slide` of ``pose`` on these maps,
        computed while the search went on; :func:`align` reuses it when ``pose`` is
        ``transform`` (the same object).
    """

    transform: AffineTransform | None
    inliers: np.ndarray
    src: np.ndarray
    dst: np.ndarray
    message: str = ""
    details: dict = field(default_factory=dict)
    verification: Verification | None = None
    success: bool | None = None
    confidence: float | None = None
    matched: bool = False
    one_sided: str = ""
    slid: tuple | None = None




@dataclass(frozen=True)
class Method:
    """An alignment method for :func:`align`.

    Attributes
    ----------
    name : str
    estimate : callable
        ``estimate(a, b, features_a, features_b, options, rng) -> Estimate``.
    extractor : callable or None
        ``extractor(options) -> FeatureExtractor``; ``None`` for methods that use no keypoints.
    verified : bool
        ``True``: gridmerge's verification decides success (our methods). ``False``: the
        method decides by its own rule (baselines, reproduced as their authors wrote them);
        the verification is still computed and reported.
    description : str
    prepare : callable or None
        ``prepare(grid, features, options) -> features``: what the estimator may use of
        one map besides its keypoints, found once per map ahead of the alignments when
        :func:`gridmerge.merge` merges three maps or more (``"hybrid"``: the keypoints of
        the map drawn blurred, which most of a fleet's pairs ask for); ``None``: nothing.
    order_free : bool
        ``True``: with ``AlignOptions.search_from="larger"`` (the default), :func:`align`
        searches with the map that covers more ground as the reference, whichever order
        the maps come in, so that ``align(b, a)`` is ``align(a, b)`` inverted
        (``"hybrid"``). ``False``: the search takes a as the reference (the baselines, as
        their authors wrote them).
    coarse_look : bool
        ``True``: a declined search is searched again with keypoints detected on fewer
        pixels (:attr:`AlignOptions.coarse_look`; ``"hybrid"``). Its ``estimate`` takes a
        keyword ``memory`` as well: what the first search learned about the maps, for the
        second.
    midway : bool
        ``True``: a taken pose the search judged by the walls (not one the keypoints
        settled alone) is moved halfway towards its polish by ICP on the maps' raw walls
        (:func:`_midway`; ``"hybrid"``). ``False``: the pose is the estimator's.
    widen : bool
        ``True``: a taken pose is moved, last, to the pose near it (within 2 degrees
        and 20 px) whose walls agree best, when they agree clearly better there than at
        the pose and it is still taken (:func:`_widened`; ``"hybrid"``).
    chamfer : bool
        ``True``: a taken pose the walls judged, whose walls agree on
        :data:`_CHAMFER_AGREEMENT` of the overlap or more, is moved, last, halfway
        towards where the walls' distance fields say they coincide, when it is still
        taken there (:func:`_chamfered`; ``"hybrid"``).
    """

    name: str
    estimate: Callable
    extractor: Callable[[AlignOptions], FeatureExtractor] | None = None
    verified: bool = True
    description: str = ""
    prepare: Callable[[OccupancyGrid, Features, AlignOptions], Features] | None = None
    order_free: bool = False
    coarse_look: bool = False
    midway: bool = False
    widen: bool = False
    chamfer: bool = False


def register_method(method: Method) -> Method:
    """Make ``method`` available to :func:`align`, :func:`gridmerge.merge` and the CLI by name."""
    METHODS[method.name] = method
    return method


def _scale_ok(opts: AlignOptions) -> Callable[[AffineTransform], bool]:
    def ok(model: AffineTransform) -> bool:
        sx, sy = model.scale_xy
        return opts.min_scale <= sx <= opts.max_scale and opts.min_scale <= sy <= opts.max_scale

    return ok


def _scale_disagreement(t: AffineTransform, a: OccupancyGrid, b: OccupancyGrid) -> float:
    """How far ``t``'s scale is from the maps' resolution ratio, as a fraction (0.15:
    1.15 times the ratio, or 1 / 1.15 of it)."""
    s = t.scale
    if not (math.isfinite(s) and s > 0):
        return math.inf
    return math.expm1(abs(math.log(s * a.resolution / b.resolution)))


def _correspondences(fa: Features, fb: Features, pairs: np.ndarray):
    # Transforms map b -> a: source points in b, destination points in a.
    return fb.xy[pairs[:, 1]], fa.xy[pairs[:, 0]]


def _estimate_ransac(a, b, fa, fb, opts: AlignOptions, rng) -> Estimate:
    matcher = match_smnn if opts.mutual else match_snn
    _, pairs = matcher(fa.descriptors, fb.descriptors, ratio=opts.ratio, method=opts.matcher)
    src, dst = _correspondences(fa, fb, pairs)
    if len(src) < 2:
        return Estimate(None, np.zeros(len(src), bool), src, dst, "too few matches")
    model, inl = ransac(
        (src, dst),
        SimilarityTransform,
        2,
        opts.residual_threshold,
        rng=rng,
        max_trials=opts.max_trials,
        is_model_valid=_scale_ok(opts),
    )
    if model is None:
        return Estimate(None, inl, src, dst, "no consistent transform among the matches")
    details: dict = {}
    if opts.refine and inl.sum() >= 2:
        refined, report = refine_direct(a, b, model, reference="finer")
        details["refine"] = {
            "accepted": report.accepted,
            "iterations": report.iterations,
            "points": report.points,
            "shift_px": report.shift_px,
        }
        if report.accepted:
            model = refined
            inl = model.residuals(src, dst) < opts.residual_threshold
    return Estimate(model, inl, src, dst, details=details)


def _candidate_matches(fa: Features, fb: Features, opts: AlignOptions, threads: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(pairs, rank)``: ``(M, 2)`` int pairs ``(index in a, index in b)``, each keypoint
    of a with its ``opts.neighbours`` nearest in b, the most distinctive first (at most
    ``opts.max_matches``), and each pair's neighbour rank (0: the nearest). ``threads``:
    as :func:`gridmerge.matching.knn`'s."""
    # Every keypoint of a gets its k nearest neighbours in b: on real maps the right
    # match is often not the nearest, and the ratio test would throw it away.
    dists, idxs = knn(fa.descriptors, fb.descriptors, opts.neighbours, method=opts.matcher, threads=threads)
    ia, rank = np.nonzero(idxs >= 0)
    # Distinctiveness of each candidate: its distance over the next neighbour's (Lowe's
    # ratio for the nearest); 1 when there is no next neighbour.
    nxt = np.minimum(rank + 1, dists.shape[1] - 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(np.isfinite(dists[ia, nxt]) & (nxt > rank), dists[ia, rank] / np.maximum(dists[ia, nxt], 1e-12), 1.0)
    order = np.argsort(ratio, kind="stable")[: opts.max_matches]
    ia, rank = ia[order], rank[order]
    return np.stack([ia, idxs[ia, rank]], axis=1), rank


def _keypoint_hypotheses(fa: Features, fb: Features, opts: AlignOptions, threads: int | None = None):
    """Similarity hypotheses from oriented keypoint matches, the matches themselves
    (``src``, ``dst`` and their ``(index in a, index in b)`` pairs), and the rotation
    (degrees) and size ratio each keypoint's nearest match proposes. ``threads``: as
    :func:`gridmerge.matching.knn`'s."""
    pairs, rank = _candidate_matches(fa, fb, opts, threads)
    src, dst = _correspondences(fa, fb, pairs)
    angle = np.deg2rad(fa.angle[pairs[:, 0]] - fb.angle[pairs[:, 1]])
    scale = fa.size[pairs[:, 0]] / np.maximum(fb.size[pairs[:, 1]], 1e-9)
    votes = (np.degrees(angle[rank == 0]), scale[rank == 0])
    if len(src) < 2:
        return [], src, dst, pairs, votes
    # The most distinctive matches propose; every match votes.
    propose = np.zeros(len(src), dtype=bool)
    propose[: opts.max_proposals] = True
    hyps = similarity_hypotheses(
        src, dst, angle, scale, proposals=propose,
        threshold=opts.residual_threshold,
        max_hypotheses=opts.hypotheses,
        min_scale=opts.min_scale,
        max_scale=opts.max_scale,
    )
    return hyps, src, dst, pairs, votes


def _estimate_sift(a, b, fa, fb, opts: AlignOptions, rng) -> Estimate:
    hyps, src, dst, _, _ = _keypoint_hypotheses(fa, fb, opts)
    if len(src) < 2:
        return Estimate(None, np.zeros(len(src), bool), src, dst, "too few matches")
    if not hyps:
        return Estimate(None, np.zeros(len(src), bool), src, dst, "no consistent transform among the matches")
    def score(model, inl, support):
        v = verify(a, b, model, tolerance=opts.wall_tolerance)
        return (_evidence(int(inl.sum()), 2) * _full_wall(v), model, inl, v, support)

    # Verify every hypothesis as it is, then refine only the most promising ones.
    scored = sorted((score(h.transform, h.inliers, h.support) for h in hyps), key=lambda t: -t[0])
    if opts.refine:
        fields: dict = {}
        for k in range(min(_REFINE_TOP, len(scored))):
            _, model, inl, _, support = scored[k]
            refined, report = refine_direct(a, b, model, cache=fields, reference="finer")
            if report.accepted:
                scored[k] = score(refined, refined.residuals(src, dst) < opts.residual_threshold, support)
    scored.sort(key=lambda t: -t[0])
    best = scored[0]
    details = {
        "matches_per_keypoint": opts.neighbours,
        "hypotheses": [
            {"score": round(s, 4), "support": sup, "wall_agreement": _finite_or_none(v.wall_agreement),
             "rotation_deg": round(math.degrees(m.rotation), 3), "scale": round(m.scale, 5)}
            for s, m, _, v, sup in scored
        ],
        "runner_up_ratio": (scored[1][0] / best[0]) if len(scored) > 1 and best[0] > 0 else 0.0,
    }
    return Estimate(best[1], best[2], src, dst, details=details, verification=best[3])


def _candidate_scales(a: OccupancyGrid, b: OccupancyGrid, hyps, limit: int = 3) -> list[float]:
    """Scales worth a correlation search: the maps' resolution ratio and the keypoints' best."""
    scales = [b.resolution / a.resolution]
    for h in hyps:
        s = h.transform.scale
        if len(scales) >= limit:
            break
        if all(abs(math.log(s / t)) > math.log(1.03) for t in scales):
            scales.append(s)
    return scales


class _SecondLook:
    """The keypoints of two maps drawn blurred (:attr:`AlignOptions.second_look`),
    found when first asked for, once for both sides' searches; ``known``: those found
    ahead (:attr:`Features.blurred`, in the maps' pixels), or ``None``."""

    def __init__(self, a: OccupancyGrid, b: OccupancyGrid, opts: AlignOptions, known=(None, None), *,
                 _found: list | None = None, _flip: bool = False):
        self._a, self._b, self._opts, self._known = a, b, opts, known
        self._found = [] if _found is None else _found  # shared with the swapped view
        self._flip = _flip

    def features(self) -> tuple[Features, Features]:
        """``(a's, b's)`` blurred keypoints."""
        if not self._found:
            ka, kb = self._known
            if ka is None and kb is None:
                found = _extract_both(_blurred_extractor(self._opts), _blurred_extractor(self._opts), self._a, self._b)
            else:
                found = (ka if ka is not None else _blurred_extractor(self._opts)(self._a),
                         kb if kb is not None else _blurred_extractor(self._opts)(self._b))
            self._found.append(found)
        fa, fb = self._found[0]
        return (fb, fa) if self._flip else (fa, fb)

    def swapped(self) -> "_SecondLook":
        """The same keypoints for the search from b's side."""
        return _SecondLook(self._a, self._b, self._opts, self._known, _found=self._found, _flip=not self._flip)


#: The most keypoints the second look keeps per map (the strongest), and the most pixels
#: it detects them on (also when ``AlignOptions.feature_pixels`` is 0): it only proposes
#: poses, which are refined at full resolution. Real maps stay far below the keypoint
#: cap (at most 1342 on the Halmstad maps, 2511 on the simulated ones, seeds 0-2); two
#: 2000 x 2000 maps of pure noise at full resolution cost 15 s of CPU more without them.
_SECOND_LOOK_KEYPOINTS = 5000
_SECOND_LOOK_PIXELS = 400_000


def _blurred_extractor(opts: AlignOptions) -> FeatureExtractor:
    cap = min(opts.max_keypoints, _SECOND_LOOK_KEYPOINTS) if opts.max_keypoints > 0 else _SECOND_LOOK_KEYPOINTS
    pixels = min(opts.feature_pixels, _SECOND_LOOK_PIXELS) if opts.feature_pixels > 0 else _SECOND_LOOK_PIXELS
    return FeatureExtractor(SIFT(), renderer=GreyRenderer(blur_sigma=opts.second_look),
                            max_keypoints=cap, work_pixels=pixels)


def _look_twice(grid: OccupancyGrid, features: Features, opts: AlignOptions) -> Features:
    """``features`` with the blurred keypoints of ``grid`` as the hybrid search finds them
    (the map cut to its known cells, isolated hits made unknown; in the map's pixels)."""
    if opts.second_look <= 0:
        return features
    crop, offset = _working_map(grid)
    return replace(features, blurred=_shifted(_blurred_extractor(opts)(crop), offset))


def _keypoint_image_pixels(grid: OccupancyGrid, margin: int) -> int:
    """Pixels of the image the default extractor detects ``grid``'s keypoints in (its
    known cells' bounding box plus ``margin``), before any reduction."""
    box = grid.known_bounds(margin)
    if box is None:
        return 0
    x0, y0, x1, y1 = box
    return int((x1 - x0) * (y1 - y0))


def _coarser(grid: OccupancyGrid, opts: AlignOptions) -> bool:
    """Whether :attr:`AlignOptions.coarse_look`'s search detects ``grid``'s keypoints on
    fewer pixels than the first search (otherwise it would find the same ones)."""
    pixels = int(opts.coarse_look)
    if pixels <= 0 or 0 < opts.feature_pixels <= pixels:
        return False
    return _keypoint_image_pixels(grid, default_extractor(opts).margin) > pixels


def _coarse_options(opts: AlignOptions) -> AlignOptions:
    """The options of :attr:`AlignOptions.coarse_look`'s search."""
    return replace(opts, feature_pixels=int(opts.coarse_look), coarse_look=0)


def _second_look_hypotheses(a: OccupancyGrid, b: OccupancyGrid, ga: Features, gb: Features, opts: AlignOptions,
                            threads: int | None = None) -> list:
    """The pose hypotheses of the blurred keypoints ``ga``, ``gb`` whose scale the maps'
    resolutions allow (all when any scale is). ``threads``: as :func:`gridmerge.matching.knn`'s."""
    hyps = _keypoint_hypotheses(ga, gb, opts, threads)[0]
    if opts.max_scale_disagreement is None:
        return hyps
    return [h for h in hyps if not _scale_ruled_out(_scale_disagreement(h.transform, a, b), opts)]


@dataclass
class _SearchMemory:
    """What a search from one side of one pair of maps (cut as :func:`working_maps`
    cuts them) learns that depends on the maps and a pose only, kept for a second
    search of the same maps (:attr:`AlignOptions.coarse_look` searches again with other
    keypoints; most of its other candidates are the first search's): nothing random,
    so the second search decides exactly as it would have alone. Scores, refinements,
    polishes and verifications of poses, and the correlation's coarse images (about
    200 px) with a's spectra: 24 MB for both sides of a 1585 x 1585 pair, none of the
    maps' full-resolution images (the scorer, the refinement's fields and the polish's
    tables are made again when needed).
    """

    quick: dict = field(default_factory=dict)  # pose -> (wall agreement, weighed, shared, weight of the agreement)
    refined: dict = field(default_factory=dict)  # (pose, reach) -> its refinement (or the pose)
    verified: dict = field(default_factory=dict)  # pose -> Verification
    polished: dict = field(default_factory=dict)  # pose -> its polish by ICP (whatever the score)
    correlations: dict = field(default_factory=dict)  # the correlation's coarse images and peaks


class _PairMemory:
    """The two sides' :class:`_SearchMemory` of one pair of maps, given in one order:
    what :func:`align`'s first search hands to its coarser look (:func:`_coarse_look`).
    A memory of other cuts of the maps starts afresh."""

    def __init__(self):
        self._cut: tuple | None = None
        self._sides: dict[bool, _SearchMemory] = {}

    def of(self, oa: np.ndarray, ob: np.ndarray, a: OccupancyGrid, b: OccupancyGrid) -> "_PairMemory":
        """This memory, for the working maps ``a``, ``b`` cut at ``oa``, ``ob``
        (forgotten first when it was of other cuts)."""
        cut = (tuple(np.asarray(oa).tolist()), tuple(np.asarray(ob).tolist()), a.shape, b.shape, a.resolution, b.resolution)
        if cut != self._cut:
            self._cut, self._sides = cut, {}
        return self

    def side(self, reverse: bool) -> _SearchMemory:
        """The memory of the search from a's side, or from b's when ``reverse``."""
        return self._sides.setdefault(reverse, _SearchMemory())


class _Judge:
    """Scores, refines and ranks candidate transforms of one pair of maps, remembering
    what it has computed (the keypoints-first stage and the full search share it, and
    with ``memory`` a second search of the same maps: :class:`_SearchMemory`)."""

    def __init__(self, a: OccupancyGrid, b: OccupancyGrid, opts: AlignOptions, *,
                 pool: ThreadPoolExecutor | None = None, memory: _SearchMemory | None = None):
        self.a, self.b, self.opts = a, b, opts
        self.memory = memory = _SearchMemory() if memory is None else memory
        self.pool = pool  # a helper thread, or None
        self._scorer: Future | None = None  # made, or being made, by one of the threads
        self._scorer_lock = threading.Lock()
        self._scorer_task: Future | None = None
        self._fields: Future | None = None
        self.box = b.corners()
        self._quick: dict = memory.quick
        self._refinements: dict = memory.refined
        self._verified: dict = memory.verified
        self._known_b: np.ndarray | None = None  # a sample of b's known cells (rival)
        self._shared: dict = {}  # pose -> that sample moved into a, and which land on a's known cells
        self._icp: WallICP | None = None
        self._polished: dict = memory.polished
        self._same: dict = {}  # pose -> the refined candidates it beat that are the same merge
        self._rivals: dict = {}  # pose -> (weighed, [(score, pose) of its rivals]) (decide)
        self._slides: dict = {}  # pose -> Future of its slide (settle's ``slide_ahead``)

    def release(self) -> None:
        """Let go of the scorer, the refinement's fields and the polish's tables (the
        judge still measures and verifies poses and remembers what it found; it refines no
        new pose, and scoring a new one makes the scorer again)."""
        for f in (self._fields, self._scorer_task):
            if f is not None:
                f.result()  # a task of the helper thread ends before its result is dropped
        self._scorer = self._fields = self._scorer_task = None
        self._icp = None

    def correlations(self, **kwargs) -> list:
        """:func:`gridmerge.correlate.correlation_hypotheses` of the maps with ``kwargs``,
        each rotation's peaks computed once (the memory keeps them)."""
        return correlation_hypotheses(self.a, self.b, cache=self.memory.correlations, **kwargs)

    def _later(self, fn, *args) -> Future:
        """``fn(*args)`` in the helper thread, or now without one."""
        return _done(fn(*args)) if self.pool is None else self.pool.submit(fn, *args)

    def prepare(self) -> None:
        """Start making what every candidate will need: the refinement's fields for the
        maps' resolution ratio (the usual scale), then the wall scorer, in the helper
        thread when there is one. The judge waits for the fields when it first refines;
        it makes the scorer itself when it needs it before the helper has started it.
        Which thread is free first depends on the matching, which the judge's thread
        does meanwhile: on the 1585 x 1585 speed pair FLANN takes 0.13 s and the
        hypotheses 0.06 s, against the fields' 0.12 s and the scorer's 0.04 s (the helper
        makes both); the exact matcher takes 0.04 s (the judge makes the scorer)."""

        def fields() -> dict:
            cache: dict = {}
            if self.opts.refine:
                prepare_fields(self.a, self.b, cache, scale=self.b.resolution / self.a.resolution, reference="finer")
            return cache

        self._scorer = None
        self._fields = self._later(fields)
        self._scorer_task = self._later(self._make_scorer)

    def _make_scorer(self) -> None:
        """Make the wall scorer unless another thread has started it."""
        with self._scorer_lock:
            if self._scorer is not None:
                return
            claimed = self._scorer = Future()
        try:
            claimed.set_result(WallScorer(self.a, self.b, tolerance=self.opts.wall_tolerance))
        except BaseException as e:
            claimed.set_exception(e)
            raise

    @property
    def blas_threads(self) -> int | None:
        """BLAS threads for this thread's matrix products while the helper thread works
        (:func:`gridmerge.matching.knn`'s ``threads``): one core fewer; ``None`` (the
        library's choice) without a helper."""
        return None if self.pool is None else max(1, (os.cpu_count() or 1) - 1)

    @property
    def scorer(self) -> WallScorer:
        """The wall scorer (made here when no thread has started it)."""
        self._make_scorer()
        return self._scorer.result()

    @property
    def fields(self) -> dict:
        """The refinement's cache (:func:`refine_direct` fills it further)."""
        return self._fields.result()

    @staticmethod
    def _key(t: AffineTransform) -> bytes:
        return np.asarray(t.params, dtype=float).tobytes()

    def quick(self, t: AffineTransform) -> float:
        """Wall agreement of ``t`` (the scorer's sample)."""
        return self._score(t)[0]

    def weighed(self, t: AffineTransform) -> float:
        """Wall agreement of ``t`` weighed by how much it rests on: discounted when it
        compares few walls or shares little of the maps (a pose that barely touches the
        other map can agree perfectly on a handful of walls), and mildly (fourth root)
        by the shared part, so that among equally agreeing poses the one explaining more
        of the maps wins."""
        return self._score(t)[1]

    def tolerant(self, t: AffineTransform, weighed: bool = False) -> float:
        """:meth:`quick` (with ``weighed``, :meth:`weighed`) with walls coinciding within
        :data:`_TOLERANT_PX` instead of the scorer's tolerance: how well an unrefined
        pose a few pixels off would agree once refined."""
        k = (self._key(t), "tolerant")
        if k not in self._quick:
            q = self.scorer(t, tolerance=_TOLERANT_PX)
            self._quick[k] = (q.wall_agreement, q.wall_agreement * _support(q))
        return self._quick[k][1 if weighed else 0]

    def shared(self, t: AffineTransform) -> float:
        """About the share of the smaller map that ``t`` overlaps (the scorer's sample)."""
        return self._score(t)[2]

    def _score(self, t: AffineTransform) -> tuple[float, float, float, float]:
        k = self._key(t)
        if k not in self._quick:
            q = self.scorer(t)
            weight = _support(q)
            self._quick[k] = (q.wall_agreement, q.wall_agreement * weight, q.shared, weight)
        return self._quick[k]

    def _refined(self, t: AffineTransform, max_shift: float | None = None):
        """``t`` refined against the maps (or ``t`` itself when the refinement is not
        accepted) within ``max_shift`` (default :data:`_REFINE_REACH`); one refinement
        per transform and reach, whatever the score (the memory keeps it: a refinement
        draws nothing at random, so any search of these maps would find the same)."""
        max_shift = _REFINE_REACH if max_shift is None else max_shift
        k = (self._key(t), max_shift)
        if k not in self._refinements:
            refined, report = refine_direct(self.a, self.b, t, cache=self.fields, max_shift=max_shift,
                                            scale_prior=scale_prior(self.a, self.b, t, self.opts), reference="finer")
            self._refinements[k] = refined if report.accepted else t
        return self._refinements[k]

    def polished(self, t: AffineTransform, score) -> tuple[float, AffineTransform]:
        """``(score, pose)``: refined pose ``t`` polished by ICP on the walls
        (:class:`gridmerge.refine.WallICP`) when that raises ``score`` by
        :data:`_POLISH_GAIN` and moves b's corners no farther than :data:`_POLISH_REACH`,
        and polished again from there on the same terms (:data:`_POLISH_ROUNDS`,
        :data:`_POLISHES_REACH`); ``t`` and its score otherwise. With the maps'
        resolutions trusted, only poses within the refinement's scale prior range of their
        ratio are polished.

        The refinement matches smoothed occupancy. Where walls are thin and noisy (a
        resolution change, spurious and missed hits) or the maps bend (Tango maps), its
        optimum can lie a few pixels from where the walls coincide, and walls one or two
        cells thick then agree on a fraction of the overlap: the right pose looks no better
        than a chance one."""
        value, start = score(t), t
        for _ in range(_POLISH_ROUNDS):
            p = self._polish(t)
            if p is None or self.far_apart(p, start, _POLISHES_REACH):
                break
            gained = score(p)
            if not gained > value * (1.0 + _POLISH_GAIN):
                break
            value, t = gained, p
        return value, t

    def _polish(self, t: AffineTransform) -> AffineTransform | None:
        """``t`` polished by ICP on the walls (once per pose), or ``None`` where the polish
        may not move it: farther than :data:`_POLISH_REACH`, or, with the maps'
        resolutions trusted, from a scale off their ratio by more than the refinement's
        scale prior allows."""
        # (ICP keeps the pose's scale: off the maps' resolution ratio by more than the
        # refinement's prior allows, it would fit the walls of one part at a wrong scale:
        # simulated pair 3 of seed 2, a keypoint pose 7 % off in scale rose to confidence
        # 0.7, 25 px from the truth, and the search stopped there. :meth:`_icp_polish`.)
        p = self._icp_polish(t)
        return None if p is None or self.far_apart(p, t, _POLISH_REACH) else p

    def _icp_polish(self, t: AffineTransform) -> AffineTransform | None:
        """``t`` polished by ICP on the walls (once per pose), however far it moves;
        ``None`` where the scale rule of :meth:`_polish` forbids."""
        if not _icp_keeps_scale(_scale_disagreement(t, self.a, self.b), self.opts):
            return None
        k = self._key(t)
        if k not in self._polished:
            self._polished[k] = self.wall_icp().polish(SimilarityTransform(t.params))
        return self._polished[k]

    def beyond_reach(self, t: AffineTransform) -> AffineTransform | None:
        """``t``'s ICP polish when it moves b's corners farther than a polish may
        (:data:`_POLISH_REACH`); ``None`` when it does not, or when ``t`` may not be
        polished."""
        if not self.opts.refine:
            return None
        p = self._icp_polish(t)
        return p if p is not None and self.far_apart(p, t, _POLISH_REACH) else None

    def polished_wall(self, t: AffineTransform) -> float:
        """The full wall agreement of ``t`` polished by ICP on the walls, whatever the
        polish gains on the scorer's sample (0 where the polish may not move ``t``:
        :meth:`_polish`). :meth:`polished` replaces a refined pose only when the polish
        gains :data:`_POLISH_GAIN`, so that the pose stays where the smoothed cells put
        it; but whether its walls agree is better judged where they coincide."""
        if not self.opts.refine:
            return 0.0
        p = self._polish(t)
        return 0.0 if p is None else _full_wall(self._verify(p))

    def wall_icp(self, *, swapped: bool = False) -> WallICP:
        """The ICP on the maps' walls (:class:`gridmerge.refine.WallICP`), made when first
        needed; ``swapped``: with b as its reference, from the same nearest-wall tables."""
        if self._icp is None:
            self._icp = WallICP(self.a, self.b)
        return self._icp.swapped() if swapped else self._icp

    def _verify(self, t: AffineTransform) -> Verification:
        k = self._key(t)
        if k not in self._verified:
            self._verified[k] = verify(self.a, self.b, t, tolerance=self.opts.wall_tolerance)
        return self._verified[k]

    def settle(self, candidates: list[tuple[AffineTransform, str]], *, slide_ahead: bool = False):
        """``(wall, best, kind, runner_up, verification)`` of the best of ``candidates``,
        refined alone: a quick look (:meth:`decide` reuses its refinement). The
        runner-up is the best unrefined score of a clearly different candidate.

        ``slide_ahead``: the helper thread also slides the best pose along the walls
        (:func:`gridmerge.verify.slide`, for :meth:`slid`) while its rivals are scored:
        for a pose that may be taken at once (the keypoints-first stage), whose slide
        :func:`align` would otherwise measure alone afterwards."""
        scored = sorted(((self.quick(t), t, kind) for t, kind in candidates), key=lambda c: -c[0])
        wall, best, kind = scored[0]
        if self.opts.refine:
            best = self._refined(best)
            wall = self.quick(best)
        verification = self._later(self._verify, best)  # while its rivals are sought
        if slide_ahead and self.opts.max_slide is not None:
            k = self._key(best)
            if k not in self._slides:
                self._slides[k] = self._later(self._slide, best)
        runner_up = max((w for w, t, _ in scored if self.far_apart(best, t, _OTHER_POSE_PX)), default=0.0)
        runner_up = max(runner_up, self.shifted(best, self.quick))
        return wall, best, kind, runner_up, verification.result()

    def _slide(self, t: AffineTransform) -> Slide | None:
        return _slide_test(self.a, self.b, t, self.opts, self._verify(t))

    def slid(self, t: AffineTransform) -> tuple | None:
        """``(t, slide of t)`` when :meth:`settle` slid ``t`` ahead (:attr:`Estimate.slid`),
        ``None`` otherwise."""
        f = self._slides.get(self._key(t))
        return None if f is None else (t, f.result())

    def shifted(self, t: AffineTransform, score) -> float:
        """The best ``score`` of :meth:`ring`'s poses: the nearest clearly different
        poses, which the candidates need not include. A pose held by structure that does
        not fix it (one straight wall, a corridor, a room matched into a larger open
        space) scores nearly as well shifted along it."""
        return max((score(s) for s in self.ring(t)), default=0.0)

    @staticmethod
    def ring(t: AffineTransform) -> list[AffineTransform]:
        """``t`` shifted by :data:`_OTHER_POSE_PX` in :data:`_SHIFT_DIRECTIONS` directions."""
        return [AffineTransform(p) for p in _ring(t.params, _OTHER_POSE_PX, _SHIFT_DIRECTIONS)]

    def nudged(self, t: AffineTransform) -> list[AffineTransform]:
        """``t`` shifted by :data:`_NUDGE_PX` in :data:`_NUDGE_DIRECTIONS` directions, the
        :data:`_NUDGE_REFINED` whose walls come nearest the other map's (within half that
        shift) refined (within :data:`_REFINE_REACH`): a better pose that ``t``'s own
        refinement could not reach from where it started (one room of a map slid along
        another by a wall's length)."""
        starts = [SimilarityTransform(p) for p in _ring(t.params, _NUDGE_PX, _NUDGE_DIRECTIONS)]
        near = [self.scorer(s, tolerance=_NUDGE_PX / 2.0).wall_agreement for s in starts]
        order = sorted(range(len(starts)), key=lambda i: -near[i])[:_NUDGE_REFINED]
        return [self._refined(starts[i]) for i in order]

    def climbed(self, t: AffineTransform) -> list[AffineTransform]:
        """:meth:`nudged` poses of ``t``, and while the best of them scores more than the
        pose it came from, the nudged poses of that one (at most :data:`_NUDGE_ROUNDS`
        rounds): a room slid by more than one nudge along a wall (simulated pair 52 of
        seed 1 searched from b's side: the first nudge moved its pose from farther off to
        26 px off, the second to the truth)."""
        found: list[AffineTransform] = []
        score = self.quick(t)
        for _ in range(_NUDGE_ROUNDS):
            poses = self.nudged(t)
            found += poses
            top = max(poses, key=self.quick, default=None)
            if top is None or self.quick(top) <= score:
                break
            t, score = top, self.quick(top)
        return found

    def rescaled(self, t: AffineTransform) -> list[AffineTransform]:
        """``t`` brought to the maps' resolution ratio (scaled about the centre of the
        part of b it lays on a's known cells, so that part stays in place) and refined
        (within :data:`_REFINE_REACH`); ``[]`` when ``t`` is within
        :data:`_RESCALE_FROM` of the ratio, or the resolutions are not trusted
        (``max_scale_disagreement=None``). The refinement pulls a candidate's scale
        towards the ratio, but from a start a few percent off it can stop in a fit of
        one part of the maps at the wrong scale: simulated pair 46 of seed 6, a keypoint
        pose 2.3 % off in scale, its walls agreeing on 76 %, was merged 15.5 px off at
        b's corners; brought to the ratio and refined, 0.5 px and 99 %."""
        if self.opts.max_scale_disagreement is None or _scale_disagreement(t, self.a, self.b) <= _RESCALE_FROM:
            return []
        p, on = self._shared_part(t)
        if not on.any():
            return []
        centre = p[on].mean(axis=0)
        factor = (self.b.resolution / self.a.resolution) / SimilarityTransform(t.params).scale
        about = SimilarityTransform(translation=centre) @ SimilarityTransform(scale=factor) @ SimilarityTransform(translation=-centre)
        return [self._refined(SimilarityTransform(about.params @ t.params))]

    def turned(self, t: AffineTransform) -> list[AffineTransform]:
        """``t`` turned by :data:`_TURN_DEG` about the centre of the part of b it lays on
        a's known cells, each refined (within :data:`_WALL_LED_REACH`)."""
        p, on = self._shared_part(t)
        if not on.any():
            return []
        centre = p[on].mean(axis=0)
        out = []
        for deg in _TURN_DEG:
            turn = SimilarityTransform(translation=centre) @ SimilarityTransform(rotation=math.radians(deg)) @ SimilarityTransform(translation=-centre)
            start = SimilarityTransform.from_estimate(self.box, AffineTransform(turn.params @ t.params)(self.box))
            if start:
                out.append(self._refined(start, max_shift=_WALL_LED_REACH))
        return out

    def _shared_part(self, t: AffineTransform) -> tuple[np.ndarray, np.ndarray]:
        """A sample of b's known cells moved by ``t`` into a, and which of them land on
        a's known cells (once per pose: :meth:`rival` asks for the same best pose against
        every candidate)."""
        k = self._key(t)
        if k in self._shared:
            return self._shared[k]
        if self._known_b is None:
            # About _RIVAL_CELLS of them, on a regular grid: no list of all known cells
            # (a 3000 x 3000 map of noise has 9 million).
            known = self.b.known
            step = max(1, int(math.sqrt(np.count_nonzero(known) / _RIVAL_CELLS)))
            self._known_b = np.argwhere(known[::step, ::step])[:, ::-1].astype(float) * step
        p = self._known_b @ t.params[:2, :2].T + t.params[:2, 2]
        h, w = self.a.shape
        on = (p[:, 0] >= 0) & (p[:, 0] < w - 0.5) & (p[:, 1] >= 0) & (p[:, 1] < h - 0.5)
        idx = np.rint(p[on]).astype(np.int64)
        on[on] = self.a.known[idx[:, 1], idx[:, 0]]
        self._shared[k] = (p, on)
        return p, on

    def corners_apart(self, s: AffineTransform, t: AffineTransform) -> float:
        """How far apart (a's pixels) ``s`` and ``t`` put b's corners, at most."""
        return float(np.hypot(*(s(self.box) - t(self.box)).T).max())

    def far_apart(self, s: AffineTransform, t: AffineTransform, px: float) -> bool:
        return bool(self.corners_apart(s, t) >= px)

    def rival(self, best: AffineTransform, t: AffineTransform) -> bool:
        """Whether ``t`` is another answer than ``best``: clearly apart at b's corners, and
        moving nearly all of the part of b that ``best`` lays on a's known cells (all but
        :data:`_RIVAL_QUANTILE` of it) by at least :data:`_RIVAL_OVERLAP_PX`. A pose
        turned a few degrees about a point of the overlap moves b's far corners a lot but
        the shared part near that point little: with maps that bend, it is the same merge
        fitted to another part of them, and scores nearly as well."""
        if not self.far_apart(best, t, _OTHER_POSE_PX):
            return False
        return self.moved(best, t, _RIVAL_QUANTILE) >= _RIVAL_OVERLAP_PX

    def moved(self, best: AffineTransform, t: AffineTransform, quantile: float = 0.5) -> float:
        """How far (a's pixels) ``t`` moves the part of b that ``best`` lays on a's known
        cells from where ``best`` lays it: the median, or another ``quantile``, of the
        distances; ``inf`` when ``best`` lays none there."""
        p, on = self._shared_part(best)
        if not on.any():
            return math.inf
        q = self._known_b[on] @ t.params[:2, :2].T + t.params[:2, 2]
        return float(np.quantile(np.hypot(*(q - p[on]).T), quantile))

    def decide(self, candidates: list[tuple[AffineTransform, str]], *, weighed: bool = False, rivals=()):
        """``(score, best, kind, runner_up, verification)`` of the best candidate.

        Candidates are ranked by :meth:`quick` or, with ``weighed``, by :meth:`weighed`;
        the most promising distinct ones are refined and polished (:meth:`polished`) and
        scored again. ``rivals`` (transforms) are further poses the runner-up is looked
        for among.
        """
        opts = self.opts
        score = self.weighed if weighed else self.quick
        scored = sorted(((score(t), t, kind) for t, kind in candidates), key=lambda c: -c[0])
        # Refine the most promising distinct candidates against the maps and score them again.
        chosen: list[list] = []  # [score, transform, kind]
        reach = _WALL_LED_REACH if weighed else _REFINE_REACH

        def refine_best(ranked, n: int, label: str = "{}") -> None:
            """Refine (and polish) the ``n`` first of ``ranked`` apart from those chosen."""
            taken = 0
            for value, t, kind in ranked:
                if taken >= n:
                    break
                if any(not self.far_apart(c[1], t, _SAME_POSE_PX) for c in chosen):
                    continue
                if opts.refine:
                    t = self._refined(t, max_shift=reach)
                    value, t = self.polished(t, score)
                chosen.append([value, t, label.format(kind)])
                taken += 1

        refine_best(scored, _WALL_LED_REFINE_TOP if weighed else _REFINE_TOP)
        if opts.refine:
            # A few more: the best by their walls within a coarse cell's tolerance. A
            # correlation peak lies a coarse cell or more from its pose, and on thin,
            # noisy walls its unrefined score is that of a chance pose: in the simulated
            # hard tier's pair 21 of seed 22, a peak 9 px from the truth ranked 17th of
            # 27 (walls agreeing on 8 %; on 90 % once refined, 0.9 px from the truth).
            tolerant = sorted(((self.tolerant(t, weighed), t, kind) for _, t, kind in scored), key=lambda c: -c[0])
            refine_best(tolerant, _TOLERANT_REFINE, f"{{}} (ranked by its walls within {_TOLERANT_PX:g} px)")
        chosen.sort(key=lambda c: -c[0])
        value, best, kind = chosen[0]
        verification = self._later(self._verify, best)  # while its rivals are sought
        # The refined candidates it beat are rivals or the same merge (:meth:`same_merge`).
        beaten = [(w, t, k, self.rival(best, t)) for w, t, k in chosen[1:]]
        self._same[self._key(best)] = [(t, k) for _, t, k, apart in beaten if not apart]
        # The best score of a clearly different pose: repeated structure makes it close to the best.
        others = [(w, t) for w, t, _ in scored if self.rival(best, t)]
        others += [(w, t) for w, t, _, apart in beaten if apart]
        others += [(score(t), t) for t in rivals if self.rival(best, t)]
        others += [(score(t), t) for t in self.ring(best)]
        self._rivals[self._key(best)] = (weighed, others)  # (not the bound method: no cycle)
        runner_up = max((w for w, _ in others), default=0.0)
        return value, best, kind, runner_up, verification.result()

    def in_full(self, best: AffineTransform, ratio: float) -> tuple[float, AffineTransform, float]:
        """``(score, pose, runner_up)``: :meth:`decide`'s winner ``best`` and its rivals
        measured again in full. Each pose is refined from as far as the wall-led search
        refines (and polished, when its walls agree better so) and scored as
        :meth:`weighed` scores it, but with its walls' agreement verified in full
        instead of the scorer's sample. Measured: ``best``, then its rivals (and ``best``
        shifted, :meth:`ring`) whose score exceeds ``ratio`` times the lower of
        ``best``'s two scores, best first, at most :data:`_REMEASURED_RIVALS`; the
        others count as scored: only rivals too weak to matter at ``ratio`` are left
        unmeasured. The winner may change; ``runner_up`` is the best score of a pose
        clearly different from it (:meth:`rival`).

        The scorer's sample weighs a pose by the part of the maps it shares, and a pose
        sharing more can come near the right one's score with its walls agreeing far
        less (simulated pair 2 of seed 4: 0.528 against 0.538, its walls agreeing on 53 %
        against 77 %)."""
        weighed, others = self._rivals[self._key(best)]
        score = self.weighed if weighed else self.quick
        measured: list[tuple[float, AffineTransform]] = []

        def measure(t: AffineTransform) -> None:
            full = _full_wall(self._verify(t))
            p = self._polish(t) if self.opts.refine else None
            if p is not None and (polished := _full_wall(self._verify(p))) > full:
                t, full = p, polished
            measured.append((full * self._score(t)[3], t))

        measure(best)
        above = ratio * min(score(best), measured[0][0])
        rest = []
        for w, t in sorted(others, key=lambda c: -c[0]):
            if w <= above or len(measured) > _REMEASURED_RIVALS:
                rest.append((w, t))
                continue
            r = self._refined(t, _WALL_LED_REACH) if self.opts.refine else t
            if all(self.far_apart(m, r, _SAME_POSE_PX) for _, m in measured):
                measure(r)  # (a rival refined onto a pose measured already is that pose)
        value, top = max(measured, key=lambda c: c[0])
        runner_up = max((w for w, t in measured + rest if self.rival(top, t)), default=0.0)
        return value, top, runner_up

    def same_merge(self, best: AffineTransform) -> list[tuple[AffineTransform, str]]:
        """The refined candidates that ``best`` beat when :meth:`decide` chose it and that
        are not its rivals (:meth:`rival`): the same merge, fitted to another part of maps
        that bend; ``(pose, kind)``, best score first."""
        return list(self._same.get(self._key(best), []))


def _support(q) -> float:
    """The weight :meth:`_Judge.weighed` gives a scorer's verdict ``q``: discounted below
    :data:`_MIN_WALLS_COMPARED` walls compared and :data:`_MIN_SHARED` shared, and by the
    fourth root of the shared part."""
    support = min(1.0, q.walls_compared / _MIN_WALLS_COMPARED) * min(1.0, q.shared / _MIN_SHARED)
    return support * min(1.0, q.shared) ** 0.25


def _degrees_apart(u: float, v: float) -> float:
    """How far apart two rotations modulo 180 degrees are (0 to 90)."""
    d = abs(u - v) % 180.0
    return min(d, 180.0 - d)


def _removes_disagreement(new: float, old: float, share: float) -> bool:
    """Whether a wall agreement of ``new`` removes at least ``share`` of the
    disagreement that ``old`` leaves (half: :data:`_NUDGE_HALVES`; a pose brought to the
    resolutions' scale: :data:`_RESCALE_GAIN`)."""
    return 1.0 - new <= (1.0 - old) * (1.0 - share)


def _ring(params: np.ndarray, px: float, n: int) -> list[np.ndarray]:
    """``(3, 3)`` matrices: ``params`` followed by a shift of ``px`` (a's pixels) in each
    of ``n`` directions evenly around the circle, the first along +x."""
    angles = [2.0 * math.pi * k / n for k in range(n)]
    return [SimilarityTransform(translation=(px * math.cos(u), px * math.sin(u))).params @ params for u in angles]


def _estimate_hybrid(a, b, fa, fb, opts: AlignOptions, rng, memory: _PairMemory | None = None) -> Estimate:
    # No random choice: ``rng`` is not drawn from (the same maps and options give the
    # same result whatever the seed).
    # The judge's helper thread makes its tools, which need only the maps, while the
    # keypoints are matched and the first candidates scored, and verifies the poses it
    # settles on while their rivals are sought (OpenCV and numpy leave the interpreter
    # while they work).
    if (os.cpu_count() or 1) < 2:
        return _both_sides(a, b, fa, fb, opts, None, memory)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="gridmerge-judge") as pool:
        return _both_sides(a, b, fa, fb, opts, pool, memory)


def _both_sides(a, b, fa, fb, opts: AlignOptions, pool, memory: _PairMemory | None = None) -> Estimate:
    """The search from a's side; below ``opts.one_sided_confidence``, judged with the
    search from b's side as well (:attr:`AlignOptions.one_sided_confidence`). A's side
    declined (:func:`_declines`), b's side's pose is taken when b's side would take it
    alone, it clearly beats a's side's best (:func:`_as_rival`) and its overlap holds
    walls enough (``_MIN_WALLS_COMPARED`` of the two maps together).

    ``details["other_side"]`` describes the search from b's side: its ``confidence``,
    how far its pose moves the shared part (``moved_px``), its ``source``, whether it is
    the ``same_pose`` and whether it was ``taken``; when it was, the details are its own
    and ``details["first_side"]`` holds a's side's confidence and source (and, for
    another pose, its best pose's ``wall_agreement``, with ``rival_crossed`` when that
    pose kept b's side's out by its mean but one map's walls crossing the other's free
    space there made it a lesser rival)."""
    memory = _PairMemory() if memory is None else memory
    judge = _Judge(a, b, opts, pool=pool, memory=memory.side(False))
    second = _SecondLook(a, b, opts, (fa.blurred, fb.blurred)) if opts.second_look > 0 else None
    forward = _hybrid_search(judge, fa, fb, second)
    tau = opts.one_sided_confidence
    own = forward.confidence or 0.0
    if tau is None or forward.transform is None or own >= tau:
        return _finished(forward, judge, reverse=False)
    if own < opts.min_confidence and judge.shared(forward.transform) < _HOPELESS_SHARED:
        # Declined, and sharing too little for the same merge found from b's side to be
        # taken (most pairs of a fleet, which do not overlap): not sought again.
        return forward
    # From b's side, with a memory of its own; the first search's tools are let go
    # first (two maps' worth of fields and tables).
    judge.release()
    reverse = _hybrid_search(_Judge(b, a, opts, pool=pool, memory=memory.side(True)), fb, fa,
                             None if second is None else second.swapped())
    other = reverse.confidence or 0.0
    back = None if reverse.transform is None else reverse.transform.inverse
    moved = math.inf if back is None else judge.moved(forward.transform, back)
    note = {"confidence": round(other, 4), "moved_px": round(moved, 1) if math.isfinite(moved) else None,
            "source": reverse.details.get("source")}
    if moved < _OTHER_POSE_PX and other <= _CONFIRMING and not _has_keypoint_support(forward):
        # The same merge, but the other side gives it no confidence at all (its walls do
        # not agree there, or a clearly different pose fits as well), and only the walls
        # found it: the same evidence seen twice, the second time rejected, is no second
        # view. Fresh simulated seed 18, pair 50 (two robots in E5_02, 65 wall cells of
        # the source seen by both) was merged 12.4 px off at 0.75 so, found by the walls
        # alone; the first search had found it one-sided (the other side's pose 65 px
        # away), the search on fewer pixels then found it again, its other side 26 px
        # away at confidence 0. Poses the keypoints proposed or confirm keep the rule
        # (sensor-to-layout pairs of Halmstad: right merges at 0.54-0.61 whose other side
        # gives 0, their poses proposed by the blurred maps' keypoints).
        forward.details["other_side"] = {**note, "same_pose": True, "taken": False, "confirms": False}
        forward.one_sided = (f"declined: found from one map's side only (from the other's the search finds the same "
                             f"pose, but at confidence {other:.2f}); a one-sided pose needs confidence {tau:g} "
                             f"(has {own:.2f})")
        return forward
    if moved < _OTHER_POSE_PX:
        # The same merge from both sides: the more confident side's pose and confidence.
        if other <= own:
            forward.details["other_side"] = {**note, "same_pose": True, "taken": False}
            return _finished(forward, judge, reverse=False)
        return _other_side_taken(forward, reverse, back, judge, {**note, "same_pose": True})
    if back is not None and other >= tau and _declines(forward, judge, opts):
        # a's side declines (its confidence is too low, or its pose fails a rule on its
        # own merits: _declines) and b's finds a pose it would take from its side alone:
        # the pose a search from b's side first would give (which map is searched from is
        # a convention: AlignOptions.search_from). Taken when it clearly beats the best
        # pose a's side found, a's side's best measured as its rival (its walls agree on
        # at most _CLEAR_RATIO of the share of b's pose, both counted in a's frame; where
        # one map's walls mostly cross the other's free space, by that map's share:
        # _as_rival): a's side found no fit, rather than fits as good as b's pose. A
        # small map fits a large building by chance in many places, and from the small
        # map's side such a fit can look sure: the apartment HIH_01 laid into the office
        # E5_01 at 0.99 (walls 70 %), E5_01's best pose agreeing on 44 %; E5_09's on 52 %
        # against 61 %.
        # The simulated positives so taken agreed on 80-97 %, a's side's best on 9-18 %
        # (docs/benchmarks.md, thirty-third session). Every decline rule still applies.
        # The pose overrules a's side's search, so it must rest on walls enough for the
        # scorer to count a pose fully (_MIN_WALLS_COMPARED wall cells of the two maps
        # together in the overlap, as the scorer's walls_compared sums them): fresh
        # simulated seed 22, pair 12 (16 wall cells of the source seen by both) was
        # merged 24.6 px off at 1.0 on 22 + 11 wall cells; seed 5's pair 51 is merged
        # rightly (2.6 px) by the coarser look on 31 + 99 (thirty-ninth session; 40 of
        # *each* map lost it).
        first = _verified(forward, judge)
        theirs = judge._verify(back)
        enough = theirs.walls_a + theirs.walls_b >= _MIN_WALLS_COMPARED
        bar = _CLEAR_RATIO * _full_wall(theirs)
        if enough and _as_rival(first, opts) <= bar:
            # Recorded where the crossing decided: measured by its mean, a's best would have kept it out.
            crossed = {"rival_crossed": True} if _full_wall(first) > bar else {}
            return _other_side_taken(forward, reverse, back, judge, {**note, "same_pose": False},
                                     wall_agreement=round(_full_wall(first), 4), **crossed)
    forward.details["other_side"] = {**note, "same_pose": False}
    where = "no pose" if back is None else f"a pose {moved:.0f} px away" if math.isfinite(moved) else "a pose that shares nothing with it"
    forward.one_sided = (f"declined: found from one map's side only (from the other's the search finds {where}); "
                         f"a one-sided pose needs confidence {tau:g} (has {own:.2f})")
    return forward


def _other_side_taken(forward: Estimate, reverse: Estimate, back, judge: _Judge, note: dict, **first_side) -> Estimate:
    """The search from b's side's pose ``back`` (its transform inverted, in a's frame)
    taken, with its own details and confidence; ``details["other_side"]`` is ``note``
    marked taken and ``details["first_side"]`` holds a's side's confidence and source
    and ``first_side``'s further entries."""
    details = {**reverse.details, "other_side": {**note, "taken": True},
               "first_side": {"confidence": round(forward.confidence or 0.0, 4), "source": forward.details.get("source"),
                              **first_side}}
    taken = Estimate(back, reverse.inliers, reverse.dst, reverse.src, details=details, verification=judge._verify(back),
                     confidence=reverse.confidence or 0.0, matched=reverse.matched)
    return _finished(taken, judge, reverse=True)


def _verified(est: Estimate, judge: _Judge) -> Verification:
    """``est``'s verification, or its pose verified by ``judge``."""
    return est.verification or judge._verify(est.transform)


def _declines(est: Estimate, judge: _Judge, opts: AlignOptions) -> bool:
    """Whether the search whose best pose is ``est`` declines it: a confidence below
    :attr:`AlignOptions.min_confidence`, or a pose :func:`_decline_reason` declines on its
    own merits (its walls, its scale ...) whatever its confidence, or one that
    :func:`_unsure_reason`, :func:`_few_walls_reason` or :func:`_crossing_reason` declines (the slide test, the last
    and costliest rule, is not asked). Fresh simulated seed 62's pair 20: a's side's best,
    at twice the resolutions' scale, had 0.69, and only one map's walls agreed there."""
    own = est.confidence or 0.0
    if own < opts.min_confidence:
        return True
    v = _verified(est, judge)
    if not _taken_by(est, opts, _scale_disagreement(est.transform, judge.a, judge.b))(v):
        return True
    # And the rules :func:`align` applies after the search, on the same maps: a pose below
    # SURE_CONFIDENCE on fewer than ``unsure_walls`` overlap wall cells, or whose walls
    # stand in the other map's rooms, is declined whatever the other side finds. HM3D
    # seed 41's pair 40: a's side's best (585 px off, confidence 0.57, 35 % of its walls
    # crossing b's rooms) kept b's side's pose (the truth, 1.0, walls 99.6 %) out as
    # one-sided, and the pair was declined.
    if _unsure_reason(v, own, opts) or _few_walls_reason(v, opts):
        return True
    crossed = _crossing_test(judge.a, judge.b, est.transform, opts)
    return crossed is not None and bool(_crossing_reason(crossed, opts))


def _as_rival(v: Verification, opts: AlignOptions) -> float:
    """A's side's best pose measured as the rival of the pose b's side found
    (:func:`_both_sides`): its walls' agreement, or, where one map's walls mostly cross
    the other's free space there (fewer than :attr:`AlignOptions.min_wall_share` of them
    on the other's walls, a pose :func:`_merit_reason` declines on its own), that map's
    share: walls one map denies are no fit as good as another pose's. Fresh simulated
    seed 62's pair 20 was declined so: a's side's best, at twice the resolutions' scale,
    agreed on 52 % as the mean of 90 % and 14 %, and b's side's pose (0.1 px from the
    truth, walls 99 %) did not beat it twice over."""
    denied = _denied_share(v, opts)
    return _full_wall(v) if denied is None else denied


def _has_keypoint_support(est: Estimate) -> bool:
    """Whether keypoint matches proposed ``est``'s pose or confirm it: evidence other
    than the walls' agreement."""
    return est.matched or str(est.details.get("source", "")).startswith("keypoints")


def _finished(est: Estimate, judge: _Judge, *, reverse: bool) -> Estimate:
    """``est`` with the pose it takes polished by ICP on the walls, first in its own
    search's frame (:func:`_polished_home`), then in the other map's
    (:func:`_polished_across`); ``reverse``: the pose is the search from b's side."""
    return _polished_across(_polished_home(est, judge, reverse=reverse), judge, reverse=reverse)


def _taken_by(est: Estimate, opts: AlignOptions, scale_off: float) -> Callable[[Verification], bool]:
    """Whether ``est``'s search would take a pose so verified (every decline rule passed)."""

    def taken(v: Verification) -> bool:
        return not _decline_reason(0, v, est.confidence or 0.0, opts, need_inliers=False, scale_off=scale_off, matched=est.matched)

    return taken


def _in_search_frame(t: AffineTransform, reverse: bool) -> SimilarityTransform:
    """The pose ``t`` (b -> a) as its search found it: b -> a, or a -> b when
    ``reverse`` (the search from b's side)."""
    return SimilarityTransform(np.asarray(t.params if not reverse else t.inverse.params, dtype=float))


def _polishable(est: Estimate, judge: _Judge) -> float | None:
    """The scale disagreement of ``est``'s pose when it may be polished (a pose taken by
    a search that refines, not one settled without judging the walls, and at a scale
    the ICP may keep: see :meth:`_Judge.polished`), ``None`` otherwise."""
    opts = judge.opts
    t = est.transform
    if (t is None or est.verification is None or not opts.refine or est.one_sided
            or str(est.details.get("walls", "")).startswith("skipped")):
        return None
    scale_off = _scale_disagreement(t, judge.a, judge.b)
    if not _icp_keeps_scale(scale_off, opts):
        return None
    if not _taken_by(est, opts, scale_off)(est.verification):
        return None
    return scale_off


def _polished_home(est: Estimate, judge: _Judge, *, reverse: bool) -> Estimate:
    """``est`` with its pose polished once more by ICP on the walls in its own search's
    frame (a's; b's when ``reverse``), when its walls agree on at least
    :data:`_FINISH_WALLS` already.

    The search polishes a refined pose only when that raises its wall agreement by
    :data:`_POLISH_GAIN` (a test meant to tell a right pose from a chance one, not to
    place it): a pose whose walls agree well is left where the smoothed cells' optimum
    put it, often 1-3 px from where the walls coincide. Here the ICP's pose is kept
    when it moves b's corners no farther than :data:`_FINISH_REACH`, does not lower the
    walls' agreement (a's frame) and is still taken, so the decision does not change.
    ``details["polished_home"]`` says how far it moved and the agreements before and
    after."""
    scale_off = _polishable(est, judge)
    if scale_off is None or est.verification.wall_agreement < _FINISH_WALLS:
        return est
    t = est.transform
    polished = judge.wall_icp(swapped=reverse).polish(_in_search_frame(t, reverse))
    pose = polished.inverse if reverse else polished  # b -> a
    moved = judge.corners_apart(pose, t)
    if moved > _FINISH_REACH or moved == 0.0:
        return est
    verification = judge._verify(pose)
    if verification.wall_agreement < est.verification.wall_agreement or not _taken_by(est, judge.opts, scale_off)(verification):
        return est
    walls = [round(est.verification.wall_agreement, 4), round(verification.wall_agreement, 4)]
    details = {**est.details, "polished_home": {"moved_px": round(moved, 2), "walls": walls}}
    return replace(est, transform=pose, verification=verification, details=details)


def _polished_across(est: Estimate, judge: _Judge, *, reverse: bool) -> Estimate:
    """``est`` with its pose polished by ICP on the walls in the frame of the map that
    was not the reference of the search that found it (a's frame when ``reverse``: the
    pose is the search from b's side; b's otherwise), when that helps.

    A search refines and polishes its poses in its reference's pixels, with radii and a
    wall tolerance of its reference's cells. Where the other map's cells are much finer
    or coarser, or its walls thin and noisy, the polish can stop a few pixels short of
    where the other map's walls lie on the reference's (simulated pair 40 of seed 2:
    found from b's side, 8 px off with a's walls agreeing on 26 %; polished in a's
    frame, 0.2 px and 68 %). Only a pose the search takes is polished (one that passes
    every decline rule, and not settled by its keypoints alone: those agree on 75 % of
    their walls already), and it must still pass them polished, so the decision does not
    change; the polish is kept only when it raises the wall
    agreement in its frame by :data:`_POLISH_GAIN` (relatively), does not lower it in
    the search's frame, and moves b's corners no farther than :data:`_POLISH_REACH`.
    The frames follow the search's reference, so the order the maps are given in does
    not matter. The confidence stays the search's. ``details["polished_across"]`` says
    how far the pose moved and the wall agreements before and after (the search's frame,
    then the other's)."""
    opts = judge.opts
    t = est.transform
    scale_off = _polishable(est, judge)
    if scale_off is None:
        return est
    taken = _taken_by(est, opts, scale_off)
    ref, other = (judge.b, judge.a) if reverse else (judge.a, judge.b)
    found = _in_search_frame(t, reverse)  # other -> ref
    inv = found.inverse  # ref -> other: the pose seen from the other map
    polished = judge.wall_icp(swapped=not reverse).polish(inv)
    back = polished.inverse  # other -> ref
    pose = polished if reverse else back  # b -> a
    moved = judge.corners_apart(pose, t)  # a's pixels, at b's corners
    if moved > _POLISH_REACH:
        return est

    def walls(frame: OccupancyGrid, u: AffineTransform) -> float:
        # In a's frame, the judge's verification (remembered: the pose's own is needed last).
        if frame is judge.a:
            return judge._verify(u).wall_agreement
        return verify(judge.b, judge.a, u, tolerance=opts.wall_tolerance).wall_agreement

    there = (walls(other, inv), walls(other, polished))
    if not there[1] > there[0] * (1.0 + _POLISH_GAIN):
        return est
    here = (walls(ref, found), walls(ref, back))
    if here[1] < here[0]:
        return est
    verification = judge._verify(pose)
    if not taken(verification):
        return est  # the decision is the search's: polishing only moves a pose it takes
    walls = [round(here[0], 4), round(here[1], 4), round(there[0], 4), round(there[1], 4)]
    details = {**est.details, "polished_across": {"moved_px": round(moved, 1), "walls": walls}}
    return replace(est, transform=pose, verification=verification, details=details)


def _hybrid_search(judge: _Judge, fa: Features, fb: Features, second: "_SecondLook | None" = None) -> Estimate:
    """One side's search (a is the reference); ``second`` gives the maps' blurred
    keypoints (:attr:`AlignOptions.second_look`) when the keypoints do not settle the pose."""
    a, b, opts = judge.a, judge.b, judge.opts
    judge.prepare()
    hyps, src, dst, pairs, votes = _keypoint_hypotheses(fa, fb, opts, judge.blas_threads)
    details: dict = {}
    if hyps and opts.keypoints_first > 0:
        # Keypoints first: when their hypotheses alone settle the pose beyond doubt, the
        # wall correlation has nothing to add (and costs a third of the search).
        first = [(h.transform, "keypoints") for h in hyps]
        wall, best, kind, runner_up, v = judge.settle(first, slide_ahead=True)
        full_wall = _full_wall(v)
        ratio, confidence = _judged(wall, runner_up, v)
        settled = _settles(confidence, full_wall, ratio, opts)
        if settled and opts.refine:
            # A settled pose off the maps' resolution ratio may fit one part of the maps at
            # a wrong scale, as in the full search below (:meth:`_Judge.rescaled`): judge
            # again with it brought to the ratio when that removes a third of the walls'
            # disagreement. Fresh simulated pair 23 of seed 38 (b's cells 0.83 of a's) was
            # settled 2.2 % off in scale, walls agreeing on 86 % (quick score), 15.4 px off
            # at b's corners; brought to the ratio and refined, 97 % and 0.7 px.
            rescaled = _at_the_ratio(judge, best, wall, kind)
            if rescaled:
                wall, best, kind, runner_up, v = judge.settle(first + rescaled, slide_ahead=True)
                full_wall = _full_wall(v)
                ratio, confidence = _judged(wall, runner_up, v)
                settled = _settles(confidence, full_wall, ratio, opts)
        if settled:
            inl = _inliers(best, src, dst, opts)
            details = {
                "source": kind,
                "candidates": len(hyps),
                "walls": "skipped: the keypoints settled the pose",
                "wall_agreement_quick": round(wall, 4),
                "runner_up": round(runner_up, 4),
                "runner_up_ratio": round(ratio, 4),
            }
            return Estimate(best, inl, src, dst, details=details, verification=v, confidence=confidence, slid=judge.slid(best))
        details["keypoints_first"] = {"confidence": round(confidence, 4), "wall_agreement": round(full_wall, 4), "runner_up_ratio": round(ratio, 4)}
    keypoints = [(h.transform, "keypoints") for h in hyps]
    if second is not None:
        # A second look, on blurred maps: poses whose keypoints the grey levels did not
        # give (its matches are not evidence: the first keypoints' matches judge).
        extra = _second_look_hypotheses(a, b, *second.features(), opts, judge.blas_threads)
        details["second_look"] = {"hypotheses": len(extra)}
        hyps = hyps + extra
        keypoints += [(h.transform, "keypoints (second look)") for h in extra]
    scales = _candidate_scales(a, b, hyps)
    # First the overlap-seeking correlation (shared free space weighs much): its best
    # poses are those with large shared explored areas, where the wall agreement judges
    # well. ``scales[0]`` is the maps' resolution ratio, the others the keypoints' scales.
    rotations = rotation_candidates(a, b)  # the wall directions', for both wall searches
    wide = judge.correlations(scales=scales, rotations=rotations, free_agreement=_OVERLAP_SEEKING)
    wide = sorted(wide, key=lambda h: -h.score)[:_WIDE_HYPOTHESES]
    candidates = keypoints + [(h.transform, "walls") for h in wide]
    if not candidates:
        return Estimate(None, np.zeros(len(src), bool), src, dst, "no candidate transform (no walls, no keypoint matches)", details)
    wall, best, kind, runner_up, v = judge.decide(candidates)
    ratio, confidence = _judged(wall, runner_up, v)
    if confidence >= opts.min_confidence and opts.refine:
        # Before taking it: a clearly better pose may lie just beyond the refinement's
        # reach (a room of one map slid by a wall's length along the other's: simulated
        # pair 52 of seed 1 was merged 26 px off at confidence 1.0, its walls agreeing on
        # 87 %, the truth on 97 %). If the pose shifted by 20 px and refined scores a
        # tenth more, judge again with those poses. Only a pose that would be taken is
        # nudged: the search for a better fit raises chance poses too (on the Halmstad
        # cross-building pairs, a declined one to 0.51 when all poses were nudged).
        # Where the pose agrees well already (simulated pair 52 of seed 1 searched from
        # b's side: 89 % polished, 36 px off), a tenth more is out of reach: removing
        # half of the disagreement is as clear (a nudged pose 7.6 px off at 96 %).
        nudged = [(t, "walls (nudged)") for t in judge.climbed(best)]
        top = max(judge.quick(t) for t, _ in nudged)
        if top > wall * (1.0 + _NUDGE_GAIN) or _removes_disagreement(top, wall, _NUDGE_HALVES):
            candidates = candidates + nudged
            wall, best, kind, runner_up, v = judge.decide(candidates)
            ratio, confidence = _judged(wall, runner_up, v)
        # And a pose whose scale is off the maps' resolution ratio may have stopped in a
        # fit of one part of the maps: judge again with it brought to the ratio
        # (:meth:`_Judge.rescaled`) when that removes at least a third of the walls'
        # disagreement (:data:`_RESCALE_GAIN`). Real maps' scales drift against each other
        # (Halmstad's Tango maps by up to 5 %): there the rescaled pose agreed 1-6 % better,
        # in one part of the maps, and fitted the annotated points worse (E5_03-E5_06: 8.4
        # -> 13.6 px); at simulated pair 46 of seed 6 it removed 93 % of the disagreement,
        # at HM3D seed 28's pair 32 (4.5 % off in scale, 17.9 px at b's corners) 36 %.
        rescaled = _at_the_ratio(judge, best, wall, kind, v)
        if rescaled:
            candidates = candidates + rescaled
            (there, there_kind), = rescaled
            wall, best, kind, runner_up, v = _decided_in_full(
                judge, candidates, there, there_kind, lambda kept: _rescaled_wins(judge, there, kept))
            ratio, confidence = _judged(wall, runner_up, v)
        # And a pose taken on walls agreeing below the settled bar may lie turned about the
        # shared part from where they coincide, farther at b's corners than a polish may
        # move it (held-out simulated pair 35 of seed 8: 0.7 degrees off, walls 50 %, b's
        # far corners 17.5 px off; ICP on the walls from it: 0.2 px off, 88 %). When ICP
        # finds walls agreeing on the settled bar and far better, judge again with that pose.
        if confidence >= opts.min_confidence and _full_wall(v) < _SETTLED_WALL:
            beyond = judge.beyond_reach(best)
            beyond_wall = _full_wall(judge._verify(beyond)) if beyond is not None else 0.0
            if beyond_wall >= max(_SETTLED_WALL, _full_wall(v) + _UNSETTLED_GAIN):
                beyond_kind = f"{kind} (polished beyond reach)"
                candidates = candidates + [(beyond, beyond_kind)]
                wall, best, kind, runner_up, v = _decided_in_full(
                    judge, candidates, beyond, beyond_kind, lambda kept: beyond_wall >= _full_wall(kept) + _UNSETTLED_GAIN)
                ratio, confidence = _judged(wall, runner_up, v)
    # A pose at a scale the maps' resolutions rule out will be declined whatever its
    # confidence (:func:`_decline_reason`), so it neither spares the wall-led search nor
    # sets the confidence its winner must beat. The first search's candidates include
    # the keypoints' scales: HM3D seed 52's pair 32 was declined with such a pose (118 %
    # off, confidence 0.77) while the wall-led search finds the truth (0.1 px, 1.0).
    scale_off = _scale_disagreement(best, a, b)
    ruled_out = _scale_ruled_out(scale_off, opts)
    bar = 0.0 if ruled_out else confidence
    if (confidence < opts.min_confidence or ruled_out) and opts.wall_led:
        # Then the wall-led correlation, which finds the right pose far more often when
        # the maps share little, but also poses that agree by chance on a small part:
        # its candidates are ranked by agreement weighed by what it rests on, every pose
        # seen so far is a rival, and its winner must agree as clearly as a settled
        # keypoint pose (on the simulated set most right poses agree on 85 % or more,
        # wrong ones on 17-65 %) on a real part of the maps (its right poses share
        # 20-56 % of the smaller map; chance poses in repetitive buildings, agreeing on
        # 82 % of the walls, 5-12 %), or, on noisy maps, beat every clearly different
        # pose twice over (Halmstad's right poses never do: corridors repeat).
        # Its candidates come from cells several pixels wide: they are refined from
        # farther (``_WALL_LED_REACH``), more of them (``_WALL_LED_REFINE_TOP``).
        # It trusts the maps' resolutions: at the keypoints' scales it only added poses
        # that agree by chance (one at scale 0.28 between two 0.05 m maps of a fleet).
        # Its rotations: the wall directions' candidates, and the centre of the window
        # of rotations the keypoint matches vote for most, unless one of those is
        # within a degree of it (its offsets scan that window). On noisy, resampled
        # maps the direction histograms can peak 2-5 degrees off, beyond the offsets
        # tried around them; most matches are wrong there, but the right ones agree
        # (simulated pairs 32 and 51 of seed 1 are found only with it).
        voted = match_rotation(*votes, scales[0])
        if voted is not None and all(_degrees_apart(voted, r) > 1.0 for r in rotations):
            rotations = rotations + [voted]
        # Its candidates: the correlation's best peaks; when those do not settle the pose,
        # as many more of its peaks as the walls rank best (:meth:`_Judge.weighed`, as
        # the judging ranks them). The correlation of coarse cells ranks its peaks poorly
        # where the maps share little (simulated pair 27 of seed 4: its 20 best peaks all
        # lay 40 px or more from the truth, the nearest its 35th; the walls rank that one
        # first); the walls rank an unrefined peak far from its optimum poorly, and their
        # best peaks, judged first, can leave the right one unrefined (seed 2's pair 18 is
        # merged from a peak among the correlation's best; judged with the walls' best
        # from the start, it was declined).
        pool = judge.correlations(scales=scales[:1], rotations=rotations, fine_deg=_WALL_LED_FINE_DEG,
                                  peaks=_WALL_LED_PEAKS, max_hypotheses=_WALL_LED_POOL)
        walls = _best_peaks(pool, _WALL_LED_OWN_PEAKS, _WALL_LED_OWN_HYPOTHESES)
        details["overlap_seeking"] = {"confidence": round(confidence, 4), "wall_agreement": round(_full_wall(v), 4), "runner_up_ratio": round(ratio, 4),
                                      "scale_off": round(scale_off, 4)}
        # Poses far below that share cannot be accepted: they are not refined (maps
        # that do not overlap at all, most pairs of a fleet, end here at little cost).
        led = [(t, kind) for t, kind in keypoints + [(h.transform, "walls (wall-led)") for h in walls] if judge.shared(t) >= _HOPELESS_SHARED]
        earlier = [t for t, _ in candidates]
        in_full: set = set()  # winners taken on their rivals measured in full

        def judged_led(poses):
            """The wall-led winner of ``poses``, its ratio and confidence, and whether it
            may replace the first search's pose."""
            second = judge.decide(poses, weighed=True, rivals=earlier)
            ratio2, confidence2 = _judged(second[0], second[3], second[4])
            wall2, shared2 = _full_wall(second[4]), second[4].overlap_fraction
            if wall2 < _SETTLED_WALL and confidence2 > bar:
                # Its walls as polished, whatever the polish gains on the scorer's sample
                # (sought only where they may decide: below both wall bars' higher, for a
                # winner that could be taken): simulated pair 55 of seed 5 (noisy, b's
                # cells 1.4 times a's) was refined to 3 px off, where its walls agreed on
                # 73 %; polished, 0.2 px off and 87 %.
                wall2 = max(wall2, judge.polished_wall(second[1]))
            passes = _wall_led_passes(wall2, shared2, ratio2)
            if not passes and _wall_led_passes(wall2, shared2, 0.0) and second[0] > 0:
                # Only its rivals stop it: the winner and its rivals measured again in full
                # (:meth:`_Judge.in_full`). The sample can rank a pose sharing more of the
                # maps near the right one, or above it, with its walls agreeing far less
                # (simulated pair 2 of seed 4). Taken only as clearly as any other winner.
                value3, top3, runner3 = judge.in_full(second[1], _CLEAR_RATIO)
                v3 = judge._verify(top3)
                ratio3 = runner3 / value3 if value3 > 0 else 1.0
                passes = _wall_led_passes(max(_full_wall(v3), judge.polished_wall(top3)), v3.overlap_fraction, ratio3)
                if passes:
                    kind3 = second[2] if top3 is second[1] else "walls (wall-led, measured in full)"
                    second = (value3, top3, kind3, runner3, v3)
                    ratio2, confidence2 = _judged(value3, runner3, v3)
                    in_full.add(judge._key(top3))
            return second, ratio2, confidence2, confidence2 > bar and passes

        def led_search(poses):
            """:func:`judged_led` of ``poses``, and of those and the winner turned when
            that fits better; ``(poses judged, winner, ratio, confidence, taken)``."""
            second, ratio2, confidence2, taken = judged_led(poses)
            if taken:
                # Before taking it: its candidates come from a few rotations, and the same
                # merge turned a few degrees about the shared part may fit better (the
                # refinement does not turn that far). If so, judge again with those poses.
                turned = [(t, "walls (wall-led, turned)") for t in judge.turned(second[1])]
                if turned and max(judge.weighed(t) for t, _ in turned) > second[0]:
                    poses = poses + turned
                    second, ratio2, confidence2, taken = judged_led(poses)
            return poses, second, ratio2, confidence2, taken

        taken = False
        if led:
            led, second, ratio2, confidence2, taken = led_search(led)
        if not taken:
            chosen = {id(h) for h in walls}
            ranked = sorted((h for h in pool if id(h) not in chosen and judge.shared(h.transform) >= _HOPELESS_SHARED),
                            key=lambda h: -judge.weighed(h.transform))
            more = [(h.transform, "walls (wall-led, ranked by the walls)") for h in ranked[:_WALL_LED_BY_WALLS]]
            if more:
                led, second, ratio2, confidence2, taken = led_search(led + more)
        if taken:
            wall, best, kind, runner_up, v = second
            ratio, confidence = ratio2, confidence2
            if judge._key(best) in in_full:
                details["measured_in_full"] = True
        candidates = candidates + led
    inl = _inliers(best, src, dst, opts)
    # The ambiguity is judged on the quick scores (all candidates have one), the walls on
    # the full verification of the winner.
    details.update({
        "source": kind,
        "candidates": len(candidates),
        "wall_agreement_quick": round(wall, 4),
        "runner_up": round(runner_up, 4),
        "runner_up_ratio": round(ratio, 4),
    })
    # Second, independent evidence: the keypoint matches. Maps that bend against each
    # other leave a right pose's walls agreeing no better than a chance pose's, and
    # repeated corridors make its rivals score nearly as well; but the matches of
    # distinctive places still agree with the right pose far beyond chance.
    poses = [t for t, _ in candidates]
    matched = _matched(judge, best, poses, fa, fb, pairs, src, dst, confidence)
    if matched is None:
        return Estimate(best, inl, src, dst, details=details, verification=v, confidence=confidence)
    details["keypoint_evidence"] = _evidence_details(*matched)
    taken = matched[2] > confidence and _full_wall(v) >= opts.min_wall_agreement_matched
    reached = max(confidence, matched[2] if taken else 0.0)
    if reached < opts.min_confidence:
        # The same merge fitted to another part of maps that bend scores nearly as well on
        # the walls, and the keypoint matches may support it where they do not support
        # the winner (Halmstad E5_12-E5_14: a pose moving b's shared part 43 px from the
        # winner's, walls agreeing on 34 % against 36 %, 7 places agreeing with it against
        # 5). The most confident such pose stands for the merge.
        other = _same_merge_matched(judge, best, poses, fa, fb, pairs, src, dst, reached)
        if other is not None:
            t, other_kind, vt, other_matched = other
            details["same_merge"] = {"instead_of": details["source"], "moved_px": round(judge.moved(best, t), 1),
                                     "keypoint_evidence": details["keypoint_evidence"]}
            details.update(source=other_kind, keypoint_evidence=_evidence_details(*other_matched))
            best, v, matched, taken = t, vt, other_matched, True
            inl = _inliers(best, src, dst, opts)
    if taken:
        details["confirmed_by"] = _confirmed_by(matched[0])
        return Estimate(best, inl, src, dst, details=details, verification=v, confidence=matched[2], matched=True)
    return Estimate(best, inl, src, dst, details=details, verification=v, confidence=confidence)


def _decided_in_full(judge: _Judge, candidates: list, pose: AffineTransform, pose_kind: str,
                     better: Callable[[Verification], bool]):
    """:meth:`_Judge.decide` on ``candidates``, among them ``pose`` (found as
    ``pose_kind``), which a rule measured in full and judges again: when the judging keeps
    another pose of the same merge (no rival of ``pose``) and ``better(v)`` says, from
    the kept pose's verification ``v``, that ``pose`` fits clearly better in full,
    ``pose`` is taken. The judging ranks by the scorer's sample of wall cells, which on
    a coarse b can prefer the pose the full measure finds far worse: HM3D seed 39's pair
    51 (b's cells 1.92 times a's), a pose 2 degrees off scored 97.6 % on the sample and
    67.5 % in full, the same merge polished beyond reach 89.7 % and 90.9 %; fresh HM3D
    seed 53's pair 10 (:func:`_rescaled_wins`). Returns ``decide``'s
    ``(wall, best, kind, runner_up, v)``, with ``pose`` in it when taken."""
    wall, best, kind, runner_up, v = judge.decide(candidates)
    if better(v) and not judge.rival(best, pose):
        best, kind, v = pose, pose_kind, judge._verify(pose)
        wall = judge.quick(pose)
    return wall, best, kind, runner_up, v


def _at_the_ratio(judge: _Judge, best: AffineTransform, wall: float, kind: str,
                  v: Verification | None = None) -> list[tuple[AffineTransform, str]]:
    """``[(pose, kind)]``: ``best`` (of quick score ``wall``, found as ``kind``) brought to
    the maps' resolution ratio and refined (:meth:`_Judge.rescaled`), when that removes
    :data:`_RESCALE_GAIN` of the walls' disagreement on the scorer's sample or, given
    ``best``'s verification ``v``, in full (:func:`_rescaled_wins`); ``[]`` otherwise."""
    rescaled = judge.rescaled(best)
    if not rescaled:
        return []
    if _removes_disagreement(judge.quick(rescaled[0]), wall, _RESCALE_GAIN) or (
            v is not None and _rescaled_wins(judge, rescaled[0], v)):
        return [(rescaled[0], f"{kind} (at the resolutions' scale)")]
    return []


def _rescaled_wins(judge: _Judge, rescaled: AffineTransform, v: Verification) -> bool:
    """Whether the pose ``rescaled`` (:meth:`_Judge.rescaled`) removes
    :data:`_RESCALE_GAIN` of the walls' disagreement that the pose verified as ``v``
    leaves, both measured in full (every wall cell, :func:`gridmerge.verify.verify`).
    The scorer's sample of cell centres can rank the two the other way round on a coarse
    b: fresh HM3D seed 53's pair 10 (b's cells 1.97 times a's) was merged 15.8 px off, 2.7
    % off in scale, its walls agreeing on 94 % on the sample and 76 % in full; brought to
    the ratio and refined, 93.6 % and 91.5 % (3.0 px)."""
    return _removes_disagreement(_full_wall(judge._verify(rescaled)), _full_wall(v), _RESCALE_GAIN)


def _settles(confidence: float, full_wall: float, ratio: float, opts: AlignOptions) -> bool:
    """Whether the keypoints' best pose settles the search (no wall correlation):
    confidence ``AlignOptions.keypoints_first``, walls agreeing on :data:`_SETTLED_WALL`
    of the overlap, and no clearly different pose above :data:`_SETTLED_RATIO` of its score."""
    return confidence >= opts.keypoints_first and full_wall >= _SETTLED_WALL and ratio <= _SETTLED_RATIO


def _wall_led_passes(wall: float, shared: float, ratio: float) -> bool:
    """Whether a wall-led winner whose walls agree on ``wall`` (full verification) over
    ``shared`` of the smaller map, its clearly different rivals scoring ``ratio`` of its
    score, may be taken (its confidence aside); with ``ratio`` 0, whether its walls alone
    would let it.

    Settled: walls agreeing on :data:`_SETTLED_WALL` over :data:`_WALL_LED_MIN_SHARED`,
    and every clearly different pose beaten by a fifth (:data:`_WALL_LED_RATIO`, the
    ambiguity term at its full value): an apartment's room laid onto an office's room
    agreed on 77 % of the walls of a 24 % overlap, beating rivals by 17 %. Or clear:
    noisy maps miss walls (at the truth of the simulated hard tier, 12 % missed and
    spurious hits, walls agree on 48-75 %), and a pose twice as good as any other
    (:data:`_CLEAR_RATIO`) needs :data:`_CLEAR_WALL` over :data:`_CLEAR_SHARED`."""
    settled = wall >= _SETTLED_WALL and shared >= _WALL_LED_MIN_SHARED and ratio <= _WALL_LED_RATIO
    clear = ratio <= _CLEAR_RATIO and wall >= _CLEAR_WALL and shared >= _CLEAR_SHARED
    return settled or clear


def _best_peaks(pool: list, peaks: int, n: int) -> list:
    """The ``n`` best hypotheses of ``pool`` (:func:`correlation_hypotheses`' list of one
    scale, best first) counting only the ``peaks`` best of each rotation: what
    ``correlation_hypotheses(..., peaks=peaks, max_hypotheses=n)`` returns."""
    taken: Counter = Counter()
    out = []
    for h in pool:
        if taken[h.rotation_deg] < peaks:
            taken[h.rotation_deg] += 1
            out.append(h)
            if len(out) == n:
                break
    return out


def _inliers(t: AffineTransform, src: np.ndarray, dst: np.ndarray, opts: AlignOptions) -> np.ndarray:
    """``(N,)`` bool array: which matches ``(src, dst)`` pose ``t`` explains within
    ``opts.residual_threshold``."""
    return t.residuals(src, dst) < opts.residual_threshold if len(src) else np.zeros(0, bool)


def _evidence_details(evidence: MatchEvidence, rival: float | None, confidence: float) -> dict:
    """``details["keypoint_evidence"]`` of :func:`_matched`'s result."""
    out = {**evidence.to_dict(), "confidence": round(confidence, 4)}
    if rival is not None:
        out["rival_significance"] = round(rival, 3)
    return out


def _same_merge_matched(judge: _Judge, best: AffineTransform, poses: list[AffineTransform], fa: Features, fb: Features,
                        pairs: np.ndarray, src: np.ndarray, dst: np.ndarray, confidence: float):
    """``(pose, kind, verification, matched)`` of the refined candidate that ``best`` beat
    and that is the same merge (:meth:`_Judge.same_merge`) whose keypoint evidence
    (:func:`_matched`, its rivals weighed) gives the highest confidence above
    ``confidence``, with walls agreeing on ``min_wall_agreement_matched`` at least; ``None``
    when there is none."""
    found = None
    for t, kind in judge.same_merge(best):
        m = _matched(judge, t, poses, fa, fb, pairs, src, dst, confidence)
        if m is None or m[2] <= confidence:
            continue
        vt = judge._verify(t)
        if _full_wall(vt) < judge.opts.min_wall_agreement_matched:
            continue
        found, confidence = (t, kind, vt, m), m[2]
    return found


def _matched(judge: _Judge, best: AffineTransform, candidates: list[AffineTransform], fa: Features, fb: Features,
             pairs: np.ndarray, src: np.ndarray, dst: np.ndarray, confidence: float) -> tuple[MatchEvidence, float | None, float] | None:
    """``(evidence, rival significance, confidence)`` of ``best`` from the keypoint matches
    (:func:`gridmerge.estimate.match_evidence`), or ``None`` without matches; the rival
    significance is ``None`` when it was not needed.

    The confidence rises from 0 at significance :data:`_MATCHED_FROM` (above what chance
    reached on maps of different places, real and simulated, and on any candidate the
    search tried) to 1 :data:`_MATCHED_SPAN` decades above it, and is held down as much
    by the most significant clearly different candidate (:meth:`_Judge.rival`), whose
    significance is counted on the matches that ``best`` misses by at least
    :data:`_RIVAL_OVERLAP_PX`: two poses that different matches support are two answers
    (repeated places). Matches ``best`` misses by less are the same answer on maps that
    bend: the same merge turned a few degrees or scaled a few percent fits another part
    of such maps better, moves the shared part enough to count as a rival, and is
    supported by that part's matches (Halmstad E5_06-E5_12: turned 9 degrees, more
    significant than the pose itself, and both right). The rivals are scored only when
    the pose's own evidence could raise ``confidence``.
    ``src``, ``dst``: the matches' points (b's, a's) of ``pairs``.
    """
    if len(pairs) == 0:
        return None
    oriented = _oriented(fa, fb)
    evidence = _pose_evidence(fa, fb, pairs, best, oriented)
    own = _own_confidence(evidence)
    if own <= confidence:
        return evidence, None, own
    others = pairs[best.residuals(src, dst) >= _RIVAL_OVERLAP_PX]
    rival = max((_pose_evidence(fa, fb, others, t, oriented).significance for t in candidates if judge.rival(best, t)), default=0.0)
    apart = _ramp((evidence.significance - rival) / _MATCHED_SPAN)
    return evidence, rival, math.sqrt(own * apart)


def _matched_alone(fa: Features, fb: Features, t: AffineTransform, opts: AlignOptions) -> tuple[MatchEvidence, float] | None:
    """``(evidence, confidence)`` of pose ``t`` (b's pixels -> a's, the features' frames)
    from the keypoint matches alone, with no rival to weigh (:func:`_matched` without
    them): for a pose known without a search, whose ambiguity its source settled (a
    pose predicted through other maps' confident alignments, or this pair's own earlier
    alignment, re-verified after a map grew). ``None`` without keypoints."""
    if fa is None or fb is None or len(fa) == 0 or len(fb) == 0:
        return None
    pairs, _ = _candidate_matches(fa, fb, opts)
    if len(pairs) == 0:
        return None
    evidence = _pose_evidence(fa, fb, pairs, t, _oriented(fa, fb))
    return evidence, _own_confidence(evidence)


def _pose_evidence(fa: Features, fb: Features, pairs: np.ndarray, t: AffineTransform, oriented: dict) -> MatchEvidence:
    """:func:`gridmerge.estimate.match_evidence` of pose ``t`` with this module's radius
    and separation; ``oriented``: :func:`_oriented` of the features."""
    return match_evidence(fa.xy, fb.xy, pairs, t, radius=_MATCH_RADIUS, separation=_MATCH_SEPARATION, **oriented)


def _own_confidence(evidence: MatchEvidence) -> float:
    """0 at significance :data:`_MATCHED_FROM`, 1 :data:`_MATCHED_SPAN` decades above."""
    return _ramp((evidence.significance - _MATCHED_FROM) / _MATCHED_SPAN)


def _oriented(fa: Features, fb: Features) -> dict:
    """:func:`gridmerge.estimate.match_evidence`'s orientation and size arguments, when
    every keypoint of both maps has an orientation (SIFT's do; -1 means none)."""
    if (fa.angle < 0).any() or (fb.angle < 0).any():
        return {}
    return {"angles": (fa.angle, fb.angle), "sizes": (fa.size, fb.size)}


def _confirmed_by(evidence: MatchEvidence) -> str:
    return f"the keypoint matches: {evidence.consistent} places agree, where chance gives {evidence.expected:.1f}"


def _ramp(x: float) -> float:
    return min(1.0, max(0.0, x))


def scale_prior(a: OccupancyGrid, b: OccupancyGrid, t: AffineTransform, opts: AlignOptions):
    """``refine_direct``'s ``scale_prior`` for candidate ``t`` of maps a and b: the maps'
    resolution ratio with ``opts.scale_prior``'s strength, when ``t``'s scale is within 3 %
    of that ratio; ``None`` otherwise (maps whose resolutions are wrong are not pulled)."""
    if opts.scale_prior <= 0 or _scale_disagreement(t, a, b) > _SCALE_PRIOR_RANGE - 1.0:
        return None
    return (b.resolution / a.resolution, float(opts.scale_prior))


def _full_wall(v: Verification) -> float:
    """The verification's wall agreement, 0 when there was nothing to compare."""
    return v.wall_agreement if math.isfinite(v.wall_agreement) else 0.0


def _judged(score: float, runner_up: float, v: Verification) -> tuple[float, float]:
    """``(runner-up ratio, confidence)`` of a judged pose: its quick ``score``, the best
    score of a clearly different pose, and its full verification."""
    ratio = runner_up / score if score > 0 else 1.0
    return ratio, _structural_confidence(_full_wall(v), ratio)


def _structural_confidence(wall: float, runner_up_ratio: float) -> float:
    """Confidence from the maps' structure: how well walls agree, and how clearly the
    chosen pose beats every clearly different pose (repeated corridors make them close).

    Both terms run from 0 to 1: walls from 35 % to 70 % agreement (simulated maps of
    different places reach about 40 %; real maps of two buildings, fitted by chance, up to
    77 %), the runner-up from 100 % to 80 % of the best score; the confidence is their
    geometric mean. Calibrated on the Halmstad sensor pairs and on simulated negatives
    (docs/benchmarks.md): at 0.5, no wrong merge there beyond two near misses; of the
    56 Halmstad cross-building pairs, added later, 4 pass it.
    """
    w = min(1.0, max(0.0, (wall - 0.35) / 0.35))
    d = min(1.0, max(0.0, (1.0 - runner_up_ratio) / _AMBIGUITY_SPAN))
    return math.sqrt(w * d)


def _estimate_paper(a, b, fa, fb, opts: AlignOptions, rng) -> Estimate:
    _, pairs = match_nn(fa.descriptors, fb.descriptors, method=opts.matcher)
    src, dst = _correspondences(fa, fb, pairs)
    model, report = paper_consensus(src, dst, rng=rng, n_samples=opts.paper_samples, min_scale=opts.min_scale, max_scale=opts.max_scale)
    details = {"samples": report.samples, "cluster_size": report.cluster_size}
    if model is None:
        return Estimate(None, np.zeros(len(src), bool), src, dst, "no consistent transform among the matches", details)
    inl = model.residuals(src, dst) < opts.residual_threshold
    return Estimate(model, inl, src, dst, details=details)


#: Alignment methods by name (see :class:`Method` and :func:`register_method`).
METHODS: dict[str, Method] = {}
register_method(Method("hybrid", _estimate_hybrid, default_extractor, description="keypoint and wall-correlation hypotheses, verified and refined (default)",
                       prepare=_look_twice, order_free=True, coarse_look=True, midway=True,
                       widen=True, chamfer=True))
register_method(Method("sift", _estimate_sift, default_extractor, description="keypoint hypotheses verified against the maps, refined"))
register_method(Method("ransac", _estimate_ransac, default_extractor, description="SIFT, ratio test, RANSAC, least squares, refinement"))
register_method(Method("paper", _estimate_paper, default_extractor, description="the paper's estimator: consensus of 3-point 5-parameter solutions"))


def _evidence(inliers: int, min_samples: int) -> float:
    """From 0 (a minimal sample explains itself) towards 1 with more inliers."""
    return 1.0 - math.exp(-max(0, inliers - min_samples) / 6.0)


def _confidence(inliers: int, v: Verification | None, min_samples: int) -> float:
    if v is None or not math.isfinite(v.acceptance_index):
        return 0.0
    evidence = _evidence(inliers, min_samples)
    acc = min(1.0, max(0.0, (v.acceptance_index - 0.5) / 0.5))
    return float(evidence * math.sqrt(acc * _full_wall(v)))


def align(
    a: OccupancyGrid,
    b: OccupancyGrid,
    *,
    method: str = "hybrid",
    options: AlignOptions | None = None,
    rng=0,
    features: tuple[Features | None, Features | None] | None = None,
    extractor: FeatureExtractor | None = None,
    **overrides,
) -> AlignResult:
    """Find the transform that moves map ``b`` onto map ``a``.

    Parameters
    ----------
    a, b : OccupancyGrid
        The maps; the result places b in a's frame. The default method searches with
        the larger map as its reference whichever order they come in
        (:attr:`AlignOptions.search_from`), so swapping them gives the inverse transform
        and the same decision.
    method : str
        ``"hybrid"`` (default), ``"sift"``, ``"ransac"``, ``"paper"`` or a registered
        baseline; see the module's documentation.
    options : AlignOptions, optional
        Settings; keyword ``overrides`` change single fields (``align(a, b, ratio=0.7)``).
    rng : int or numpy.random.Generator
        Seed of every random choice: the same seed gives the same result. The default
        method makes none (any seed gives its result); the baselines' RANSAC and the
        paper's consensus draw from it.
    features : (Features or None, Features or None), optional
        Precomputed features of a and b (reused when merging many maps).
    extractor : FeatureExtractor, optional
        Replaces the default SIFT extractor (e.g. with ORB, or another renderer).

    Returns
    -------
    AlignResult
        ``result.transform`` maps b's image pixels ``(x = column, y = row)`` to a's;
        ``result.success`` is ``False`` when the alignment was declined.
    """
    if method not in METHODS:
        raise GridMergeError(f"unknown alignment method {method!r} (use one of {', '.join(METHODS)})")
    opts = replace(options or AlignOptions(), **overrides)
    if opts.search_from not in ("larger", "a"):
        raise GridMergeError(f"unknown search_from {opts.search_from!r} (use 'larger' or 'a')")
    if METHODS[method].verified:
        t0 = time.perf_counter()
        for name, g in (("a", a), ("b", b)):
            # (A map of fewer cells than an overlap needs is declined for that instead.)
            share = chance_wall_agreement(g, opts.wall_tolerance) if g.data.size >= opts.min_overlap_cells else 0.0
            if share >= _WALLS_EVERYWHERE:
                return _walls_everywhere(name, share, method, opts, time.perf_counter() - t0)
    # Two threads of its own, each calling OpenCV: OpenCV's threads get half the cores.
    with opencv_threads_split(2):
        result = _align(a, b, method, opts, rng, features, extractor)
    return with_warnings(result, opts) if METHODS[method].verified else result


def few_walls_warning(v: Verification | None, opts: AlignOptions) -> str | None:
    """The warning that a pose verified as ``v`` rests on fewer wall cells of the
    overlap than :attr:`AlignOptions.few_walls` (the two maps' together), or ``None``."""
    if not opts.few_walls or v is None or v.walls_a is None or v.walls_b is None:
        return None
    total = int(v.walls_a) + int(v.walls_b)
    if total >= opts.few_walls:
        return None
    return (f"the pose rests on few walls: {int(v.walls_a)} + {int(v.walls_b)} wall cells of the two maps in the overlap "
            f"(under {opts.few_walls}); its confidence does not count them, and in the benchmark one such merge in seven "
            f"was wrong, more on real maps of a few rooms: check it (docs/benchmarks.md, \"Poses on few walls\")")


def with_warnings(result: AlignResult, opts: AlignOptions) -> AlignResult:
    """``result`` with :attr:`AlignResult.warnings` filled: for a taken pose, the
    warning of :func:`few_walls_warning` (once); a declined result unchanged."""
    if not result.success:
        return result
    note = few_walls_warning(result.verification, opts)
    return result if note is None or note in result.warnings else replace(result, warnings=[*result.warnings, note])


#: What makes a map walls everywhere (the end of the messages that say so).
_WALLS_EVERYWHERE_CAUSES = ("noise, or its values read wrongly (free and occupied swapped, or unknown read as occupied: "
                           "negate, thresholds)?")


def _walls_everywhere(name: str, share: float, method: str, opts: AlignOptions, elapsed: float) -> AlignResult:
    """The declined result of maps one of which, ``name``, has walls near ``share`` of
    its known cells (:func:`gridmerge.verify.chance_wall_agreement`): the walls that
    judge every pose would agree with any pose there, so no pose can be told right; not
    searched (dense noise took half a minute to be declined so)."""
    message = (f"declined: map {name} is walls everywhere ({share:.0%} of its known cells lie within "
               f"{opts.wall_tolerance:g} cells of an occupied one; maps of buildings: under 45 %), so its walls agree with "
               f"any pose: {_WALLS_EVERYWHERE_CAUSES}")
    return AlignResult(success=False, transform=None, candidate=None, metric_transform=None, confidence=0.0,
                       acceptance_index=math.nan, inliers=0, matches=0, keypoints=(0, 0), method=method, message=message,
                       elapsed_s=elapsed, details={"walls_everywhere": {"map": name, "share": round(share, 4)}})


def _align(a: OccupancyGrid, b: OccupancyGrid, method: str, opts: AlignOptions, rng, features, extractor,
           memory: _PairMemory | None = None) -> AlignResult:
    """:func:`align` with its options checked; ``memory``: what a first search of the
    same maps, in the same order, learned (for :attr:`Method.coarse_look`'s second search)."""
    t0 = time.perf_counter()
    spec = METHODS[method]
    if spec.order_free and opts.search_from == "larger":
        if not reference_first(a, b):
            # b is the reference: its search, inverted.
            swapped = _align(b, a, method, replace(opts, search_from="a"), rng,
                             None if features is None else (features[1], features[0]), extractor)
            return _inverted(swapped, a, b, time.perf_counter() - t0)
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    if spec.coarse_look and memory is None:
        memory = _PairMemory()
    ext = extractor or (spec.extractor(opts) if spec.extractor is not None else None)
    fa, fb = features if features is not None else (None, None)
    cut = None
    if fa is None and fb is None and ext is not None and extractor is None:
        # Both maps' features at once, each with its own extractor (OpenCV releases the
        # interpreter while it works): a third less wall time on two cores. The working
        # maps need no keypoints: they are cut while b's are still being found.
        fa, fb, cut = _extract_both(ext, spec.extractor(opts), a, b,
                                    also=lambda: working_maps(a, b, despeckled=spec.verified))
    fa = fa if fa is not None else (ext(a) if ext is not None else Features.empty())
    fb = fb if fb is not None else (ext(b) if ext is not None else Features.empty())
    ca, oa, cb, ob = cut if cut is not None else working_maps(a, b, despeckled=spec.verified)
    remembered = {} if memory is None else {"memory": memory.of(oa, ob, ca, cb)}
    est = spec.estimate(ca, cb, _shifted(fa, -oa), _shifted(fb, -ob), opts, gen, **remembered)
    in_cut = est.transform
    slide_note = crossing_note = None
    if est.transform is not None:
        est.transform = crop_to_full(est.transform, oa, ob)
        est.src = est.src + ob
        est.dst = est.dst + oa
    n_inl = int(est.inliers.sum())
    v = None
    message = est.message
    conf = 0.0

    def declined(verification: Verification, t: AffineTransform) -> str:
        # The decline rules of a verified method's pose, with this search's confidence
        # (the pose as the search took it, or moved halfway by _midway).
        return _decline_reason(n_inl, verification, conf, opts, need_inliers=not by_structure,
                               scale_off=_scale_disagreement(t, a, b), matched=est.matched, runner_up_ratio=ratio)

    if est.transform is not None:
        v = est.verification or (
            verify(despeckle(a), despeckle(b), est.transform, tolerance=opts.wall_tolerance)
            if spec.verified
            else verify(a, b, est.transform, tolerance=opts.wall_tolerance)
        )
        if spec.verified:
            by_structure = est.confidence is not None
            conf = float(est.confidence) if by_structure else _confidence(n_inl, v, est.transform.min_samples)
            ratio = est.details.get("runner_up_ratio") if by_structure and not est.matched else None
            message = declined(v, est.transform) or est.one_sided
            # On the search's maps (cut, and despeckled as the search saw them).
            crossed = None if message else _crossing_test(ca, cb, in_cut, opts)
            if crossed is not None:
                crossing_note = {"share": _finite_or_none(round(crossed.share, 4)), "walls": crossed.walls}
                message = _crossing_reason(crossed, opts)
            if not message:
                message = _unsure_reason(v, conf, opts) or _few_walls_reason(v, opts)
            if not message and opts.max_slide is not None:
                if est.slid is not None and est.slid[0] is in_cut:  # measured by the search meanwhile
                    slid = est.slid[1]
                else:
                    slid = _slide_test(ca, cb, in_cut, opts, est.verification)
                if slid is not None:
                    slide_note = {"px": round(slid.distance, 1), "kept": round(slid.kept, 4)}
                    message = _slide_reason(slid, opts)
        else:
            conf = float(est.confidence or 0.0)
            message = "" if est.success else (est.message or "declined by the method's own rule")
    success = est.transform is not None and not message
    details = dict(est.details)

    def move_taken(pose: AffineTransform, key: str, note: dict) -> None:
        # A taken pose moved after the decision (b's cut -> a's cut), when the decline
        # rules and the few-walls rule would take it there too: the pose, its
        # verification and details[key] = note.
        nonlocal v
        checked = verify(ca, cb, pose, tolerance=opts.wall_tolerance)
        if not declined(checked, pose) and not _few_walls_reason(checked, opts):
            est.transform = crop_to_full(pose, oa, ob)
            v = checked
            details[key] = note

    # A pose a search of the walls judged, at a scale ICP may keep: the polishes' poses.
    walls_judged = success and spec.verified and opts.refine and _midway_applies(est, a, b, opts)
    if walls_judged and spec.midway:
        halfway = _midway(a, b, in_cut)
        if halfway is not None:
            pose, moved = halfway
            move_taken(pose, "midway", {"polish_px": round(moved, 2)})
    if success and spec.verified and spec.widen and opts.refine:
        cut_pose = full_to_crop(est.transform, oa, ob)
        trusted = opts.max_scale_disagreement is not None
        wider = _widened(ca, cb, cut_pose, b.resolution / a.resolution if trusted else None)
        if wider is not None:
            pose, walls = wider
            move_taken(pose, "widened", {"moved_px": round(corner_error(pose, cut_pose, cb.shape), 2),
                                         "walls": [round(w, 4) for w in walls]})
    if walls_judged and spec.chamfer and v.wall_agreement >= _CHAMFER_AGREEMENT:
        polished = _chamfered(ca, cb, full_to_crop(est.transform, oa, ob))
        if polished is not None:
            pose, moved = polished
            move_taken(pose, "chamfer", {"polish_px": round(moved, 2)})
    if crossing_note is not None:
        details["crossing"] = crossing_note
    if slide_note is not None:
        details["slide"] = slide_note
    if spec.order_free:
        details["searched_from"] = "a"
    details["features_capped"] = bool(fa.capped or fb.capped)
    inlier_xy = np.stack([est.src[est.inliers], est.dst[est.inliers]], axis=1) if n_inl else np.zeros((0, 2, 2))
    result = AlignResult(
        success=success,
        transform=est.transform if success else None,
        candidate=est.transform,
        metric_transform=pixel_to_metric(est.transform, b, a) if est.transform is not None else None,
        confidence=conf,
        acceptance_index=math.nan if v is None else v.acceptance_index,
        inliers=n_inl,
        matches=int(len(est.src)),
        keypoints=(len(fa), len(fb)),
        method=method,
        message=message or _taken_message(n_inl, v if spec.verified else None, conf, est.details),
        elapsed_s=time.perf_counter() - t0,
        verification=v,
        inlier_xy=inlier_xy,
        details=details,
    )
    if not success and spec.coarse_look and extractor is None:
        result = _coarse_look(result, a, b, fa, fb, method, opts, rng, t0, memory)
    return result


def _coarse_look(first: AlignResult, a, b, fa: Features, fb: Features, method: str, opts: AlignOptions, rng, t0: float,
                 memory: _PairMemory | None = None) -> AlignResult:
    """``first``, a declined alignment, searched again with keypoints detected on at
    most ``opts.coarse_look`` pixels (:attr:`AlignOptions.coarse_look`): that search's
    result if it is accepted, ``first`` otherwise; ``details["coarse_look"]`` tells.
    ``fa``, ``fb``: the maps' first keypoints (kept for a map whose keypoints would not
    change). Not searched again when ``first``'s pose shares too little for any pose of
    these maps to be taken (most pairs of a fleet, which do not overlap), or when
    neither map's keypoints would change."""
    v = first.verification
    if first.success or v is None or not v.overlap_fraction >= _HOPELESS_SHARED:
        return first
    larger = [_coarser(g, opts) for g in (a, b)]
    if not any(larger):
        return first  # the keypoints would be the same
    # A map whose image is no larger keeps its keypoints; the others' are found anew.
    coarse = tuple(None if big else f for f, big in zip((fa, fb), larger))
    # The same reference as the first search (``search_from`` is "a" when this is that
    # search's own reference's side; "larger" chooses it again).
    # The first search's memory: most of this search's candidates other than the
    # keypoints' are that search's, scored and refined already.
    second = _align(a, b, method, _coarse_options(opts), rng, coarse, None, memory)
    elapsed = time.perf_counter() - t0
    pixels = int(opts.coarse_look)
    if second.success:
        note = {"pixels": pixels, "first_confidence": round(first.confidence, 4), "first_message": first.message}
        return replace(second, elapsed_s=elapsed, message=second.message + " (second search, keypoints on fewer pixels)",
                       details={**second.details, "coarse_look": note})
    note = {"pixels": pixels, "confidence": round(second.confidence, 4), "message": second.message}
    return replace(first, elapsed_s=elapsed, details={**first.details, "coarse_look": note})


def reference_first(a: OccupancyGrid, b: OccupancyGrid) -> bool:
    """Whether ``a`` is the reference of an order-free search (``AlignOptions.search_from``
    ``"larger"``): the map with more known area (square metres), then with more known
    cells, more occupied cells, more rows and columns; between maps equal in all of
    these, the one whose cells' bytes come first. ``reference_first(a, b)`` and
    ``reference_first(b, a)`` differ unless the maps are the same.

    >>> import numpy as np
    >>> from gridmerge import OccupancyGrid
    >>> small = OccupancyGrid(np.zeros((4, 4)))
    >>> large = OccupancyGrid(np.zeros((3, 8)))
    >>> reference_first(large, small), reference_first(small, large)
    (True, False)
    """
    ka, kb = _reference_key(a), _reference_key(b)
    if ka != kb:
        return ka > kb
    return a.data.tobytes() <= b.data.tobytes()


def _reference_key(g: OccupancyGrid) -> tuple:
    known = int(np.count_nonzero(g.known))
    return (known * float(g.resolution) ** 2, known, int(np.count_nonzero(g.occupied())), g.shape, float(g.resolution))


def _inverted(r: AlignResult, a: OccupancyGrid, b: OccupancyGrid, elapsed_s: float) -> AlignResult:
    """``r``, the alignment of ``a`` onto ``b``, as the alignment of ``b`` onto ``a``:
    the same decision, the transforms inverted, the pairs of per-map values swapped. The
    verification stays the one the decision was made on (counted in b's cells; its
    per-map wall counts swapped, and a taken pose's message says them in that order)."""
    inverse = None if r.candidate is None else r.candidate.inverse
    v = None if r.verification is None else r.verification.swapped()
    message = r.message
    if r.success and v is not None:
        # A taken pose's message counts each map's walls: in a, b order (whatever follows
        # it, e.g. the coarser look's note, stays).
        message = message.replace(_walls_clause(r.inliers, r.verification), _walls_clause(r.inliers, v), 1)
    return replace(
        r,
        message=message,
        transform=inverse if r.success else None,
        candidate=inverse,
        metric_transform=None if inverse is None else pixel_to_metric(inverse, b, a),
        keypoints=(r.keypoints[1], r.keypoints[0]),
        elapsed_s=elapsed_s,
        inlier_xy=r.inlier_xy[:, ::-1].copy(),
        verification=v,
        details={**r.details, "searched_from": "b"},
    )


_CROP_MARGIN = 8
#: How far :attr:`AlignOptions.max_slide`'s test slides b, as a fraction of the square
#: root of the overlap's cells.
_SLIDE_FRACTION = 0.15
#: :attr:`AlignOptions.unsure_walls`: below this confidence a pose needs that many overlap
#: wall cells.
SURE_CONFIDENCE = 0.8
#: :attr:`AlignOptions.few_walls_agreement`: poses resting on fewer overlap wall cells
#: than this (both maps' together) need that wall agreement.
FEW_WALLS_EVIDENCE = 200

#: :attr:`AlignOptions.max_crossing`: a wall counts as crossing the other map's open
#: space this many cells (the finer map's) inside it, and the test judges poses resting
#: on fewer wall cells in the overlap than the evidence bound (both maps' together).
#: Real maps of one building differ (furniture moved, doors, glass, bending): Halmstad's
#: right poses have up to 54 % of their walls so, but on 8700 wall cells and more; the
#: chance fits it declines rest on 119-860 (2400 in a test's procedural building).
#: docs/benchmarks.md, forty-fourth session.
_CROSSING_DEPTH = 5.0
_CROSSING_EVIDENCE = 3000
#: Hypotheses refined against the maps (the best by their unrefined score).
_REFINE_TOP = 3
#: ... and this many more, the best by their walls within :data:`_TOLERANT_PX` (a's
#: pixels) of the other map's (:meth:`_Judge.tolerant`), in every :meth:`_Judge.decide`.
#: docs/benchmarks.md, fiftieth session.
_TOLERANT_REFINE = 2
_TOLERANT_PX = 8.0
#: The keypoints-first stage of the hybrid method ends the search only when the full
#: verification's wall agreement reaches this and no clearly different pose scores
#: above this share of the winner's score (besides ``AlignOptions.keypoints_first``).
_SETTLED_WALL = 0.75
_SETTLED_RATIO = 0.6
#: A map whose walls lie within the wall tolerance of this share of its known cells or more
#: (:func:`gridmerge.verify.chance_wall_agreement`) agrees with any pose as well as a
#: settled search's winner must: such maps are declined unsearched. Maps of buildings: 0.1
#: to 0.45 (the largest of the simulated set's seeds 0-6 0.44, a map resampled coarser;
#: Halmstad's 0.17); noise and maps whose free and occupied values are swapped: near 1.
_WALLS_EVERYWHERE = _SETTLED_WALL
#: The scale prior applies to candidates whose scale is within this factor of the maps'
#: resolution ratio (the cells already agree with the maps' metadata).
_SCALE_PRIOR_RANGE = 1.03
#: Shared free space's weight in the first, overlap-seeking wall correlation (see
#: :mod:`gridmerge.correlate`), and the hypotheses it keeps (all scales together).
_OVERLAP_SEEKING = 0.0625
_WIDE_HYPOTHESES = 20
#: Share of the smaller map a pose of the second, wall-led search must overlap.
_WALL_LED_MIN_SHARED = 0.15
#: Poses sharing less than this (before refinement, which moves them a little) cannot
#: reach ``_WALL_LED_MIN_SHARED``: the wall-led search does not refine them, and a
#: declined pose sharing less is not sought again from b's side, nor with coarser
#: keypoints (:attr:`AlignOptions.coarse_look`).
_HOPELESS_SHARED = _WALL_LED_MIN_SHARED - 0.05
#: ... and no clearly different pose may score above this share of its score.
_WALL_LED_RATIO = 0.8
#: The wall-led search's pose is also taken, with less wall agreement, when no clearly
#: different pose scores above ``_CLEAR_RATIO`` of its score, its walls agree on
#: ``_CLEAR_WALL`` and it overlaps ``_CLEAR_SHARED`` of the smaller map (noisy maps: see
#: ``_estimate_hybrid``).
_CLEAR_RATIO = 0.5
_CLEAR_WALL = 0.5
_CLEAR_SHARED = 0.2
#: A pose that would be taken on walls below the settled bar is judged again with its ICP
#: polish beyond the polish's reach when that reaches the bar and this much more.
_UNSETTLED_GAIN = 0.2
#: Rotations tried around each direction candidate by the wall-led search (degrees): with
#: two candidates 6 degrees apart (as the direction histograms give), no rotation between
#: them is more than 1 degree from one tried.
_WALL_LED_FINE_DEG = (-2.0, -1.0, 0.0, 1.0, 2.0)
#: Hypotheses of the wall-led search refined against the maps.
_WALL_LED_REFINE_TOP = 6
#: The wall-led search's correlation peaks per rotation (all kept, up to the pool's size);
#: its candidates are the :data:`_WALL_LED_OWN_HYPOTHESES` best of them by the
#: correlation, counting :data:`_WALL_LED_OWN_PEAKS` per rotation (the correlation's own
#: defaults), then, when those do not settle the pose, :data:`_WALL_LED_BY_WALLS` more
#: that the walls rank best.
_WALL_LED_PEAKS = 12
_WALL_LED_POOL = 1000
_WALL_LED_OWN_PEAKS = 3
_WALL_LED_OWN_HYPOTHESES = 20
_WALL_LED_BY_WALLS = 20
#: How far (a's pixels at b's corners) a refinement may move a candidate: keypoint and
#: overlap-seeking candidates are close to their pose or wrong; the wall-led search's
#: come from a correlation of cells several pixels wide, 10-35 px off (the refinement's
#: damped steps converge from there).
_REFINE_REACH = 12.0
_WALL_LED_REACH = 30.0
#: A pose polished by ICP on the walls replaces the refined one only when it scores this
#: much more (relatively): near the refinement's optimum the two differ by noise, and the
#: smoothed cells, which use every known cell, are the more precise (simulated pair 40 of
#: seed 0: ICP scored 4 % more and lay 2.2 px from the truth, the refinement 0.9 px).
_POLISH_GAIN = 0.1
#: How far (a's pixels, at b's corners) polishing may move a pose: as far as a refinement
#: may. Farther, ICP has slid to another fit, not to where the refinement stopped short
#: (in a simulated fleet of 8 robots a chance pose slid 15 px and rose from 0.37 to 0.49,
#: enough to be merged; Halmstad's right poses moved 2-7 px, one 12.3 px).
_POLISH_REACH = _REFINE_REACH
#: Polishes of one pose at most, each from where the last stopped and kept when it gains
#: :data:`_POLISH_GAIN` and each within :data:`_POLISH_REACH`, all together within
#: :data:`_POLISHES_REACH` of the refined pose: ICP on thin, noisy walls can stop in a fit
#: of one part on its way (simulated pair 32 of seed 78: refined 12.3 px from the truth,
#: polished to 5.4 px, walls agreeing on 51 %; polished again, 0.2 px and 99.6 %).
_POLISH_ROUNDS = 3
_POLISHES_REACH = 1.5 * _POLISH_REACH
#: A taken pose whose walls agree on this share is polished in its own search's frame
#: once more (:func:`_polished_home`), ...
_FINISH_WALLS = 0.5
#: ... and the polish kept only when it moves b's corners no farther than this (a's
#: pixels): a finishing touch, not a new pose (unbounded, it moved right poses of E5's
#: bent Tango maps 5-10 px to where one part's walls coincide, and made them wrong).
_FINISH_REACH = 3.0
#: A taken pose the walls found is moved halfway to its polish by ICP on the raw walls
#: when that polish moves b's corners no farther than this (:func:`_midway`; a's pixels).
_MIDWAY_REACH = 4.0
#: Wall cells (the two maps together, as sampled by the scorer) a candidate must compare
#: for its quick score to count fully; also the floor (the two maps' wall cells in the
#: overlap, counted in full) of a pose taken from the second map's side alone
#: (:func:`_both_sides`).
_MIN_WALLS_COMPARED = 40
#: ... and share of the smaller map it must overlap.
_MIN_SHARED = 0.05
#: A pose only the walls found, and the search from the other map's side finds again at
#: no more than this confidence, is not found from both sides (:func:`_both_sides`).
_CONFIRMING = 0.0
#: Two candidate transforms closer than this (b's corners, a's pixels) are one pose.
_SAME_POSE_PX = 10.0
#: ... and farther than this, two clearly different poses (for the ambiguity check).
_OTHER_POSE_PX = 40.0
#: Rivals of a wall-led winner measured again in full at most (:meth:`_Judge.in_full`).
_REMEASURED_RIVALS = 8
#: Turns (degrees) about the shared part tried before a wall-led pose is taken.
_TURN_DEG = (-4.0, -2.0, 2.0, 4.0)
#: Before the first search's pose is taken, it is shifted by this much (a's pixels;
#: beyond the refinement's reach, short of a clearly different pose) in
#: ``_NUDGE_DIRECTIONS`` directions, the ``_NUDGE_REFINED`` most promising are refined,
#: and a pose scoring more than ``_NUDGE_GAIN`` above it (relative), or removing
#: ``_NUDGE_HALVES`` of its walls' disagreement (a pose agreeing on 90 % cannot rise by a
#: tenth), is judged with the candidates.
_NUDGE_HALVES = 0.5
_NUDGE_PX = 20.0
_NUDGE_DIRECTIONS = 8
_NUDGE_REFINED = 2
_NUDGE_GAIN = 0.1
#: Rounds of nudges at most, each from the best pose of the last (:meth:`_Judge.climbed`).
_NUDGE_ROUNDS = 3
#: A taken pose whose scale is off the maps' resolution ratio by more than this fraction
#: is also judged brought to the ratio (:meth:`_Judge.rescaled`).
_RESCALE_FROM = 0.005
#: ... and taken into the judgement when it removes at least this share of the walls'
#: disagreement (quick score). Half until the forty-sixth session; on the Halmstad pairs
#: the rescaled pose removes at most 13 % (of the 29 sensor poses off the ratio:
#: E5_10-E5_11, where it also lies nearer the annotated points; none of the 7 blueprint
#: poses gains), on HM3D seed 28's pair 32 36 %.
_RESCALE_GAIN = 1.0 / 3.0
#: Directions in which the best pose is shifted by _OTHER_POSE_PX to look for a rival.
_SHIFT_DIRECTIONS = 24
#: Keypoint evidence (:func:`_matched`): a match agrees with a pose within this many of
#: a's pixels (bending maps), and agreeing keypoints this close to a counted one do not count.
_MATCH_RADIUS = 8.0
_MATCH_SEPARATION = 20.0
#: Significance (-log10 of the chance probability) from which the matches add confidence,
#: and the decades over which it grows to 1. A match agrees with a pose in position and in
#: its keypoints' orientations and sizes. The final poses of maps of different places
#: reached at most 4.2 (56 Halmstad cross-building pairs; 24 simulated negatives: 2.2),
#: wrong final poses of real pairs 3.7; but a search tries hundreds of poses, and chance
#: candidates among them (never chosen) reached 5.2 on the cross-building pairs. Right
#: Halmstad poses: 0-47 (median 7).
_MATCHED_FROM = 5.0
_MATCHED_SPAN = 2.0
#: A clearly different pose is a rival of the best only when it moves the part of b the
#: best lays on a by this much (a's pixels): less is the same merge up to the bending of
#: real maps (hand fits of the Halmstad pairs leave 5-15 px; its protocol tolerates 20 px).
_RIVAL_OVERLAP_PX = 25.0
#: ... all of that part but this share (until the tenth session, half of it: the median.
#: The runner-ups of three right Halmstad poses declined as ambiguous were the same merge
#: fitted to another part of the bending maps, 12-19 px from the annotations, whose
#: shared part moved 30-34 px (median) and much less near where the two poses cross).
_RIVAL_QUANTILE = 0.1
#: b's known cells sampled for those distances.
_RIVAL_CELLS = 3000


def _extract_both(ext_a: FeatureExtractor, ext_b: FeatureExtractor, a: OccupancyGrid, b: OccupancyGrid, also=None):
    """``(ext_a(a), ext_b(b))``, the two in parallel threads when there is a core for each.

    With ``also`` (a function of no arguments), ``(ext_a(a), ext_b(b), also())``: ``also``
    runs in this thread once a's keypoints are found, while b's may still be sought."""
    if (os.cpu_count() or 1) < 2:
        found = ext_a(a), ext_b(b)
        return found if also is None else (*found, also())
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="gridmerge-features") as pool:
        job = pool.submit(ext_b, b)
        fa = ext_a(a)
        if also is None:
            return fa, job.result()
        extra = also()
        return fa, job.result(), extra


def _done(value) -> Future:
    """A future already holding ``value``."""
    f: Future = Future()
    f.set_result(value)
    return f


def _midway_applies(est: Estimate, a: OccupancyGrid, b: OccupancyGrid, opts: AlignOptions) -> bool:
    """Whether :func:`_midway` may move ``est``'s taken pose: one a search of the walls
    judged and refined (not one the keypoints settled alone), at a scale the ICP may
    keep (within the refinement's scale prior range of the resolutions' ratio when
    they are trusted; :meth:`_Judge._polish`)."""
    if str(est.details.get("walls", "")).startswith("skipped"):
        return False
    return _icp_keeps_scale(_scale_disagreement(est.transform, a, b), opts)


def _midway(a: OccupancyGrid, b: OccupancyGrid, t: AffineTransform) -> tuple[SimilarityTransform, float] | None:
    """``(pose, moved)``: the pose halfway between ``t`` (b's cut -> a's cut, the cuts of
    :func:`working_maps`) and its polish by ICP on the walls of the
    maps as given (not despeckled), in the frame of the map with the finer cells (a's
    when they are as fine), with ``moved`` how far that polish put b's corners (the
    cut's, a's pixels) from ``t``; ``None`` when the polish does not move them or moves
    them farther than :data:`_MIDWAY_REACH`.

    The search places a pose where the smoothed cells agree best (refined, then
    polished where that clearly raises the walls' agreement); ICP on the raw walls
    places it where the wall cells lie nearest each other. On a few dozen wall cells the
    two optima lie 1-4 px apart at b's far corners, each off the truth its own way (the
    smoothing spreads walls over free space; isolated hits, which despeckling drops,
    still pin the walls' ends): halfway between them is nearer the truth more often than
    either. The finer map's frame pins the walls the more finely (in the coarser map's
    frame, or in the search's reference's, the simulated set gained half as many
    precise poses net, and lost more: docs/benchmarks.md, sixtieth session)."""
    ra, _ = _working_map(a, despeckled=False)  # working_maps' cuts, not despeckled
    rb, _ = _working_map(b, despeckled=False)
    found = SimilarityTransform(np.asarray(t.params, dtype=float))
    if b.resolution < a.resolution * (1.0 - 1e-9):  # b's cells are the finer: its frame
        polished = WallICP(rb, ra).polish(found.inverse).inverse
    else:
        polished = WallICP(ra, rb).polish(found)
    return _halfway(found, polished, rb.shape, _MIDWAY_REACH)


def _halfway(found: SimilarityTransform, polished: SimilarityTransform, shape, reach: float
             ) -> tuple[SimilarityTransform, float] | None:
    """``(pose, moved)``: the pose halfway between ``found`` and ``polished`` (b's pixels
    -> a's), with ``moved`` how far ``polished`` puts the corners of b (``shape``) from
    ``found``; ``None`` when it does not move them or moves them farther than ``reach``."""
    moved = corner_error(polished, found, shape)
    if moved == 0.0 or moved > reach:
        return None
    # Matrices of the form [[c, -s], [s, c]] are closed under averaging: the mean of two
    # similarities is the similarity that puts every point halfway between their images.
    return SimilarityTransform((found.params + polished.params) / 2.0), moved


#: Distance (a's cells) within which two walls count as one when :func:`_widened`
#: compares poses: finer than the decision's (``AlignOptions.wall_tolerance``), so that a
#: pose a few pixels off its walls scores lower than one on them.
_WIDEN_TOLERANCE = 2.0
#: Walls' agreement (within :data:`_WIDEN_TOLERANCE`) at which :func:`_widened` leaves a
#: pose as it is.
_WIDEN_ENOUGH = 0.98
#: How much better (walls' agreement within :data:`_WIDEN_TOLERANCE`) the pose
#: :func:`_widened` finds must agree, and the wall cells of each map in the overlap
#: (at the pose it starts from) it needs: on fewer walls, or for less, a pose that agrees
#: better lies off the truth about as often as nearer it.
_WIDEN_GAIN = 0.02
_WIDEN_WALLS = 30
#: The walls' agreement (within :data:`_WIDEN_TOLERANCE`) the pose :func:`_widened` finds
#: must reach: on real maps that bend, where no pose lays most walls on walls, the best
#: one near a pose follows one part's walls (Halmstad's sensor pairs: 37 poses moved 5-46
#: px, to 35-72 %, one right merge made wrong).
_WIDEN_AGREEMENT = 0.75
#: Wall cells of each map that :func:`_widened`'s candidates are polished on at most (the
#: winner is then polished on all of them).
_WIDEN_POINTS = 3000
#: A pose whose scale is this far (a fraction) or more from the maps' resolution ratio
#: (and within the refinement's prior range of it) is searched at the ratio too, by
#: :func:`_widened`.
_WIDEN_RESCALE = 0.003


def _widened(a: OccupancyGrid, b: OccupancyGrid, t: AffineTransform, ratio: float | None = None
             ) -> tuple[SimilarityTransform, tuple[float, float]] | None:
    """``(pose, (before, after))``: the pose near ``t`` (b's cut -> a's cut, the
    despeckled cuts of :func:`working_maps`) whose walls agree best, with the walls'
    agreement (:func:`gridmerge.verify.verify` within :data:`_WIDEN_TOLERANCE`) at ``t``
    and there; ``None`` when no pose near ``t`` agrees by :data:`_WIDEN_GAIN` better than
    ``t`` itself and on :data:`_WIDEN_AGREEMENT` of the overlap at least, when ``t``'s
    walls agree on :data:`_WIDEN_ENOUGH` of the overlap already, or when the overlap holds
    fewer than :data:`_WIDEN_WALLS` wall cells of either map.

    The search and its polishes stop where the walls nearest the pose coincide; a pose
    10-20 px or a degree off the truth, where the walls of a corridor or of a room's
    other side coincide with the wrong ones, stays there. The candidates are
    :func:`gridmerge.refine.wall_search`'s (every turn within 2 degrees and shift within
    20 px, ranked by b's wall cells landing on a's walls), each polished by ICP on the
    walls (:class:`gridmerge.refine.WallICP`, on at most :data:`_WIDEN_POINTS` wall cells
    of each map; the winner then on all) at ``t``'s scale and, when ``ratio`` (b's
    resolution over a's; ``None`` when the resolutions are not trusted) lies
    :data:`_WIDEN_RESCALE` or more from ``t``'s scale (and within the refinement's prior
    range of it), at the ratio too: ICP keeps a scale, and 1.5 % off is 15 px at the far
    side of a map 1000 cells wide.

    Measured on the poses the benchmark's stored runs took (simulated seeds 51-121, HM3D
    39-66; docs/benchmarks.md, sixty-second session): of the 111 taken 2 px or more off
    the truth, it put 14 within 2 px and 4 of the 16 wrong ones within 10 px, and made one
    right one wrong (3.8 px off, then 11 px, on 53 wall cells); of 650 others, none was
    moved more than 2 px off. Without the floors (:data:`_WIDEN_GAIN`,
    :data:`_WIDEN_WALLS`) it put 5 more within 2 px, but moved 6 of the 650 past 2 px and
    made 2 more right poses wrong. :data:`_WIDEN_AGREEMENT` keeps it off the Halmstad
    pairs, which bend. Re-run on the benchmark seeds where it moved a stored pose
    (simulated 100, 103, 105, 108, 118; HM3D 40, 42, 44, 55, 57, 59, 61, 63, 66): 3 wrong
    merges made right, 10 poses within 2 px, 1 moved out of it, none made wrong."""
    found = SimilarityTransform(np.asarray(t.params, dtype=float))
    # Not for a pose whose walls agree nearly everywhere (most poses the keypoints settle:
    # a 1585 x 1585 speed pair pays this one check, about 8 ms).
    at = verify(a, b, found, tolerance=_WIDEN_TOLERANCE)
    before = at.wall_agreement
    if not before < _WIDEN_ENOUGH or min(at.walls_a, at.walls_b) < _WIDEN_WALLS:
        return None
    scales = (1.0,)
    if ratio is not None:
        off = ratio / found.scale
        if _WIDEN_RESCALE <= abs(off - 1.0) <= _SCALE_PRIOR_RANGE - 1.0:
            scales = (1.0, off)
    starts = wall_search(a, b, found, tolerance=_WIDEN_TOLERANCE, scales=scales)
    if not starts:
        return None
    icp = WallICP(a, b)
    quick = icp.thinned(_WIDEN_POINTS)
    best, best_walls = None, before
    for start in starts:
        pose = quick.polish(start)
        walls = verify(a, b, pose, tolerance=_WIDEN_TOLERANCE).wall_agreement
        if walls > best_walls:
            best, best_walls = pose, walls
    if best is None or best_walls < max(before + _WIDEN_GAIN, _WIDEN_AGREEMENT):
        return None
    if quick is not icp:  # the winner polished on every wall cell, if that agrees no worse
        pose = icp.polish(best)
        walls = verify(a, b, pose, tolerance=_WIDEN_TOLERANCE).wall_agreement
        if walls >= best_walls:
            best, best_walls = pose, walls
    return best, (before, best_walls)


#: Farthest (a's pixels, at b's corners) :func:`_chamfered`'s polish may move a pose: a
#: polish, not a search.
_CHAMFER_REACH = 4.0
#: The walls' agreement (the decision's tolerance) below which a taken pose is not
#: polished by :func:`_chamfered`: on real maps that bend, where no pose lays most walls
#: on walls, a polish follows one part's walls (Halmstad E5_09-E5_12, taken at 71 %, 0.6
#: px past its protocol's line; no simulated or HM3D pose below it changed its class).
_CHAMFER_AGREEMENT = 0.75


def _chamfered(a: OccupancyGrid, b: OccupancyGrid, t: AffineTransform) -> tuple[SimilarityTransform, float] | None:
    """``(pose, moved)``: the pose halfway between ``t`` (b's cut -> a's cut, the
    despeckled cuts of :func:`working_maps`) and its polish by
    :func:`gridmerge.refine.chamfer_polish`, with ``moved`` how far the polish put b's
    corners (a's pixels) from ``t``; ``None`` when the polish did not move them or moved
    them farther than :data:`_CHAMFER_REACH`.

    The polish lays the walls on each other's distance fields, between cells; on a few
    dozen wall cells its optimum, like the search's and ICP's (:func:`_midway`), lies a
    pixel or two off the truth its own way. Measured on the poses the benchmark's stored
    runs took (simulated seeds 51-131, HM3D 39-68; docs/benchmarks.md, sixty-third
    session), of the poses the walls judged: the polish itself put 25 more within 2 px
    and 19 out of it (the homes lost 5 net) and made 2 right poses wrong; halfway put 12
    more within 2 px and 4 out of it, made 2 wrong ones right and 1 right one wrong."""
    found = SimilarityTransform(np.asarray(t.params, dtype=float))
    return _halfway(found, chamfer_polish(a, b, found), b.shape, _CHAMFER_REACH)


def working_maps(a: OccupancyGrid, b: OccupancyGrid, *, despeckled: bool = True):
    """The maps as the verified methods judge them: ``(ca, oa, cb, ob)``.

    Each map cut to its known cells (plus a margin: real maps are mostly unknown), with
    the cut's pixel offset, and with isolated hits made unknown when ``despeckled`` (not
    walls to judge by). Map transforms between the cuts back with :func:`crop_to_full`.
    """
    ca, oa = _working_map(a, despeckled)
    cb, ob = _working_map(b, despeckled)
    return ca, oa, cb, ob


def _working_map(grid: OccupancyGrid, despeckled: bool = True) -> tuple[OccupancyGrid, np.ndarray]:
    """One map of :func:`working_maps`: its cut and the cut's pixel offset."""
    crop, offset = grid.crop_known(_CROP_MARGIN)
    return (despeckle(crop) if despeckled else crop), offset


def crop_to_full(t: AffineTransform, oa: np.ndarray, ob: np.ndarray) -> AffineTransform:
    """``t`` between the cuts of :func:`working_maps` (b's cut -> a's cut) as a transform
    between the whole maps' pixels, of the same kind."""
    return type(t)((SimilarityTransform(translation=oa) @ t @ SimilarityTransform(translation=-ob)).params)


def full_to_crop(t: AffineTransform, oa: np.ndarray, ob: np.ndarray) -> AffineTransform:
    """The inverse operation of :func:`crop_to_full`."""
    return type(t)((SimilarityTransform(translation=-oa) @ t @ SimilarityTransform(translation=ob)).params)


def _shifted(f: Features, offset: np.ndarray) -> Features:
    if not offset.any():
        return f
    return replace(f, xy=f.xy + offset, blurred=None if f.blurred is None else _shifted(f.blurred, offset))


def _taken_message(inliers: int, v: Verification | None, conf: float, details: dict) -> str:
    """The message of a taken pose: what it rests on (its keypoint inliers, or the walls
    alone, and how many wall cells of each map agree in the overlap, as ``v`` counts
    them) and its confidence. A pose the walls' search found has no keypoint inliers;
    saying only that would hide what it rests on, and a pose on a few dozen wall cells
    is a different claim from one on thousands.

    Examples
    --------
    >>> v = Verification(1.0, 100, 0, 0.88, 500, 0.3, walls_a=18, walls_b=28, matched_a=18, matched_b=21)
    >>> _taken_message(0, v, 1.0, {})
    'aligned on the walls alone (no keypoint inliers): they agree on 88% of the overlap (18 of 18 and 21 of 28 wall cells), confidence 1.00'
    >>> _taken_message(66, None, 0.93, {})
    'aligned with 66 inliers, confidence 0.93'
    """
    head = f"aligned with {inliers} inliers" if inliers else "aligned on the walls alone (no keypoint inliers)"
    return f"{head}{_walls_clause(inliers, v)}, confidence {conf:.2f}" + _confirmed_note(details)


def _walls_clause(inliers: int, v: Verification | None) -> str:
    """The part of :func:`_taken_message` that counts each map's walls, in a, b order
    ("" when ``v`` does not count them)."""
    counts = "" if v is None else v.wall_counts()
    if not counts:
        return ""
    return f": {'walls' if inliers else 'they'} agree on {v.wall_agreement:.0%} of the overlap ({counts})"


def _confirmed_note(details: dict) -> str:
    """What a message adds when the keypoint matches confirmed the pose."""
    return f" (confirmed by {details['confirmed_by']})" if "confirmed_by" in details else ""


def _icp_keeps_scale(scale_off: float, opts: AlignOptions) -> bool:
    """Whether ICP on the walls (which keeps a pose's scale) may polish a pose whose
    scale is that far from the maps' resolution ratio (:func:`_scale_disagreement`):
    within the refinement's scale prior range of it, or any scale when the resolutions
    are not trusted (:attr:`AlignOptions.max_scale_disagreement` ``None``). Off the
    ratio, it would fit one part's walls at a wrong scale (:meth:`_Judge._polish`)."""
    return opts.max_scale_disagreement is None or scale_off <= _SCALE_PRIOR_RANGE - 1.0


def _scale_ruled_out(scale_off: float, opts: AlignOptions) -> bool:
    """Whether a scale that far from the maps' resolution ratio (:func:`_scale_disagreement`)
    is declined (:attr:`AlignOptions.max_scale_disagreement`)."""
    return opts.max_scale_disagreement is not None and scale_off > opts.max_scale_disagreement * (1 + 1e-9)


def _decline_reason(inliers: int, v: Verification, conf: float, opts: AlignOptions, need_inliers: bool = True,
                    scale_off: float = 0.0, matched: bool = False, runner_up_ratio: float | None = None) -> str:
    """Why a verified pose is declined ("" when it is not); ``scale_off``: its scale's
    disagreement with the maps' resolution ratio (:func:`_scale_disagreement`);
    ``matched``: the keypoint matches confirm it (:attr:`Estimate.matched`);
    ``runner_up_ratio``: the best clearly different pose's score over its own, when its
    confidence comes from the maps' structure (:func:`_structural_confidence`), so that a
    confidence too low for that reason says so (:func:`_ambiguity_note`).

    A pose declined on its own merits (its walls, its confidence ...) says so first: the
    best of poses that all fail is often at a chance scale (for 46 of the 72 pairs of
    maps of two different places of simulated seeds 7-12), and "the scale disagrees;
    --any-scale" would send the user after the resolutions. Only a pose that would be
    taken but for its scale names the option."""
    reason = _merit_reason(inliers, v, conf, opts, need_inliers, matched, runner_up_ratio)
    if not _scale_ruled_out(scale_off, opts):
        return reason
    if reason:
        return f"{reason}; nor does its scale agree with the maps' resolutions ({scale_off:.0%} off)"
    return (f"declined: the scale disagrees with the maps' resolutions by {scale_off:.0%} "
            f"(at most {opts.max_scale_disagreement:.0%}; --any-scale when they are unknown)")


def _crossing_test(a: OccupancyGrid, b: OccupancyGrid, t: AffineTransform, opts: AlignOptions) -> Crossing | None:
    """The crossing test of :attr:`AlignOptions.max_crossing` on the search's maps
    (``None`` when the rule is off): the one call :func:`align` and a first side that
    asks whether ``align`` would decline its pose (:func:`_declines`) make."""
    if opts.max_crossing is None:
        return None
    return crossing(a, b, t, depth=_CROSSING_DEPTH, max_walls=_CROSSING_EVIDENCE)


def _slide_test(a: OccupancyGrid, b: OccupancyGrid, t: AffineTransform, opts: AlignOptions,
                verification: Verification | None) -> Slide | None:
    """The slide test of :attr:`AlignOptions.max_slide` on the search's maps: the one
    call both :func:`align` and the judge's look-ahead (:meth:`_Judge.settle`) make, so
    that a slide measured ahead is the one ``align`` would measure."""
    return slide(a, b, t, tolerance=opts.wall_tolerance, fraction=_SLIDE_FRACTION, verification=verification)


def _crossing_reason(crossed: Crossing, opts: AlignOptions) -> str:
    """Why a pose whose walls cross the other map's rooms so (:func:`gridmerge.verify.crossing`)
    is declined ("" when it is not: :attr:`AlignOptions.max_crossing`, which is set)."""
    if crossed.walls >= _CROSSING_EVIDENCE or not crossed.share > opts.max_crossing:  # NaN: not counted
        return ""
    return (f"declined: {crossed.share:.0%} of the overlap's walls ({crossed.deep} of {crossed.walls} cells) "
            f"stand inside the other map's open space, at most {opts.max_crossing:.0%} on fewer than "
            f"{_CROSSING_EVIDENCE} wall cells: walls across its rooms")


def _unsure_reason(v: Verification, conf: float, opts: AlignOptions) -> str:
    """Why a pose below :data:`SURE_CONFIDENCE` on so few overlap walls is declined (""
    when it is not: :attr:`AlignOptions.unsure_walls`)."""
    if opts.unsure_walls is None or conf >= SURE_CONFIDENCE or v.walls_a is None or v.walls_b is None:
        return ""
    walls = v.walls_a + v.walls_b
    if walls >= opts.unsure_walls:
        return ""
    shown = math.floor(conf * 100) / 100  # 0.7996 reads 0.79, below the bar it is judged by
    return (f"declined: confidence {shown:.2f} on {walls} overlap wall cells; below {SURE_CONFIDENCE} a pose needs "
            f"{opts.unsure_walls} (a building's walls agreeing in part, not a few rooms')")


def _few_walls_reason(v: Verification, opts: AlignOptions) -> str:
    """Why a pose whose walls agree so little on so few overlap wall cells is declined
    ("" when it is not: :attr:`AlignOptions.few_walls_agreement`)."""
    if opts.few_walls_agreement is None or v.walls_a is None or v.walls_b is None:
        return ""
    walls = v.walls_a + v.walls_b
    if walls >= FEW_WALLS_EVIDENCE or not v.wall_agreement < opts.few_walls_agreement:  # NaN: other rules judge
        return ""
    shown = math.floor(v.wall_agreement * 100) / 100  # 74.6 % reads 74 %, below the bar it is judged by
    return (f"declined: walls agree on {shown:.0%} of the overlap, on only {walls} wall cells of the two maps; "
            f"on fewer than {FEW_WALLS_EVIDENCE} a pose needs {opts.few_walls_agreement:.0%} (a few walls of two "
            f"places, or of the wrong part, agree in part by chance)")


def _slide_reason(slid: Slide, opts: AlignOptions) -> str:
    """Why a pose so slid (:func:`gridmerge.verify.slide`) is declined ("" when it is
    not: :attr:`AlignOptions.max_slide`, which is set)."""
    if slid.kept <= opts.max_slide:
        return ""
    return (f"declined: the walls do not fix the pose: slid {slid.distance:.0f} px along them either way, "
            f"it keeps {slid.kept:.0%} of its wall agreement (at most {opts.max_slide:.0%})")


def _wall_shares(v: Verification) -> tuple[float, float] | None:
    """Each map's share of its walls in the overlap that lie on the other's walls
    (``None`` when a verification saved before they were counted, or one without walls,
    does not tell)."""
    if v.matched_a is None or v.matched_b is None or not v.walls_a or not v.walls_b:
        return None
    return v.matched_a / v.walls_a, v.matched_b / v.walls_b


def _denied_share(v: Verification, opts: AlignOptions) -> float | None:
    """The lesser of the two maps' wall shares (:func:`_wall_shares`) when it is under
    :attr:`AlignOptions.min_wall_share` (one map's walls mostly cross the other's free
    space there), ``None`` otherwise."""
    shares = _wall_shares(v)
    if shares is not None and min(shares) < opts.min_wall_share:
        return min(shares)
    return None


def _merit_reason(inliers: int, v: Verification, conf: float, opts: AlignOptions, need_inliers: bool,
                  matched: bool, runner_up_ratio: float | None = None) -> str:
    """:func:`_decline_reason` of a pose, its scale aside."""
    if need_inliers and inliers < opts.min_inliers:
        return f"declined: only {inliers} inlier matches (need {opts.min_inliers})"
    if v.overlap_cells < opts.min_overlap_cells:
        return f"declined: the maps share only {v.overlap_cells} known cells (need {opts.min_overlap_cells})"
    if not math.isfinite(v.acceptance_index) or v.acceptance_index < opts.min_acceptance:
        return f"declined: acceptance index {v.acceptance_index:.2f} below {opts.min_acceptance}"
    if v.walls_a is not None and v.walls_b is not None and min(v.walls_a, v.walls_b) < opts.min_overlap_walls:
        return (f"declined: the overlap holds only {min(v.walls_a, v.walls_b)} wall cells of one map "
                f"(need {opts.min_overlap_walls} of each to judge the walls)")
    floor = opts.min_wall_agreement_matched if matched else opts.min_wall_agreement
    if not math.isfinite(v.wall_agreement) or v.wall_agreement < floor:
        return f"declined: walls agree on {v.wall_agreement:.0%} of the overlap (need {floor:.0%})"
    denied = _denied_share(v, opts)
    if denied is not None:
        return (f"declined: only {denied:.0%} of one map's walls in the overlap lie on the other's walls "
                f"(need {opts.min_wall_share:.0%} of each; the rest cross the other's free space)")
    if conf < opts.min_confidence:
        return f"declined: confidence {conf:.2f} below {opts.min_confidence}" + _ambiguity_note(runner_up_ratio)
    return ""


#: :func:`_structural_confidence`'s ambiguity term falls from 1 to 0 over the last this
#: much of the runner-up ratio: above ``_AMBIGUOUS_RATIO`` it is below its full value.
_AMBIGUITY_SPAN = 0.2
_AMBIGUOUS_RATIO = 1.0 - _AMBIGUITY_SPAN


def _ambiguity_note(runner_up_ratio: float | None) -> str:
    """What a confidence lowered by a rival pose owes to it, for a decline message: ""
    unless a clearly different pose scores more than :data:`_AMBIGUOUS_RATIO` of the
    pose's own score.

    Examples
    --------
    >>> _ambiguity_note(0.95)
    ' (a clearly different pose fits 95% as well: repeated structure, or too little shared to tell)'
    >>> _ambiguity_note(1.3)  # a quick score can beat the refined pose's
    ' (a clearly different pose fits as well or better: repeated structure, or too little shared to tell)'
    >>> _ambiguity_note(0.5), _ambiguity_note(None)
    ('', '')
    """
    if runner_up_ratio is None or not runner_up_ratio > _AMBIGUOUS_RATIO:
        return ""
    fits = f"{runner_up_ratio:.0%} as well" if runner_up_ratio < 0.995 else "as well or better"
    return f" (a clearly different pose fits {fits}: repeated structure, or too little shared to tell)"

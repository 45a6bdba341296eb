"""Scoring one alignment against the truth, and summaries over many.

One :class:`Record` per case and method:

* **success**: aligned and b's image within ``SUCCESS_PX`` (10) pixels of the truth, by the
  *corner error*: the largest distance, in a's pixels, between the four corners of b's
  image mapped by the estimate and by the truth (:func:`gridmerge.transforms.corner_error`).
  The Halmstad pairs use their data set's protocol instead: aligned and the median, over
  the annotated points, of ``|T(points_b) - points_a|`` at most
  ``max(20, 2 * fit_median_residual_px)``;
* **precise**: a success within ``PRECISE_PX`` (2) pixels (undefined, ``None``, on the
  Halmstad pairs, whose maps bend against each other by more than that);
* **declined**: the method did not align the maps (a method that raised an exception
  counts as declined, with the exception in ``error``);
* **wrong**: aligned but not a success; on a negative pair every alignment is wrong, a
  **false merge**.

Peak memory is the :mod:`tracemalloc` peak around the call, in MB: it sees numpy's arrays
and Python's objects but misses memory that native code (OpenCV, FLANN) allocates by
itself, so it is a lower bound. The process's maximum resident set size (``max_rss_mb``,
monotone over a run) is recorded too.

Examples
--------
>>> import numpy as np
>>> from gridmerge.bench.metrics import judge
>>> truth = np.eye(3)
>>> judge(np.eye(3), truth, (100, 100), positive=True)["success"]
True
>>> judge(None, truth, (100, 100), positive=True)["declined"]
True
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import Iterable, Optional, Sequence

import numpy as np

from ..io.jsonable import finite
from ..transforms import AffineTransform, corner_error

__all__ = [
    "SUCCESS_PX",
    "PRECISE_PX",
    "Record",
    "judge",
    "halmstad_point_error",
    "ecc_reference",
    "evaluate",
    "summarize",
    "shared_walls_group",
    "SHARED_WALL_GROUPS",
    "TIMING_FIELDS",
]

#: Corner error (a's pixels) within which an alignment is a success.
SUCCESS_PX = 10.0
#: The groups of simulated positive pairs by the wall cells both robots saw
#: (``meta["shared_walls"]``, in cells of the source map): ``(label, lower bound)``.
SHARED_WALL_GROUPS = (("under 50", 0), ("50-199", 50), ("200-999", 200), ("1000 or more", 1000))
#: Corner error within which a success is precise.
PRECISE_PX = 2.0
#: Fields of a record that vary from run to run (everything else is reproducible).
TIMING_FIELDS = ("wall_s", "align_s", "peak_mb", "max_rss_mb")


@dataclass
class Record:
    """The outcome of one method on one case (one line of ``cases.jsonl``).

    Attributes
    ----------
    method, case_id, dataset, tier : str
    positive : bool
        The maps show one place (``False``: negative pair).
    aligned : bool
        The method returned a transform (``AlignResult.success``).
    success, declined, wrong, false_merge : bool
    precise : bool or None
        ``None`` where undefined (Halmstad).
    corner_error_px : float or None
        Of the returned transform (``None`` when declined or on negatives).
    candidate_corner_error_px : float or None
        Of the best candidate, even when declined (shows whether declines were right).
    candidate_success : bool or None
        Whether the best candidate would have been a success (``None`` without a
        candidate or on negatives): a declined pair with a successful candidate was
        declined too cautiously.
    rotation_error_deg, translation_error_px, scale_error : float or None
        Rotation difference (wrapped to [-180, 180), absolute); distance between the
        images of b's centre; ``|scale / true scale - 1|``.
    point_error_px, threshold_px : float or None
        Halmstad protocol: median point error and the success threshold.
    estimate : dict or None
        ``rotation_deg``, ``scale``, ``tx``, ``ty`` and ``matrix`` (2x3) of the returned
        transform.
    confidence, acceptance_index : float or None
    inliers : int
    message, error : str
    wall_s : float
        Wall time of the ``align`` call (with tracemalloc running).
    align_s : float
        ``AlignResult.elapsed_s``.
    peak_mb, max_rss_mb : float or None
    a_shape, b_shape : list of int
    cells : int
        Cells of both maps.
    overlap, rotation_deg, scale, noise : float or None
        Of the case (from its ``meta``).
    shared_walls : int or None
        Simulated positive pairs: the source's cells both robots saw as walls (``meta``).
    source : str or None
    verification : dict or None
        ``AlignResult.verification`` as a dict: the agreement the decision was made on.
    details : dict or None
        ``AlignResult.details``: the method's own diagnostics (which search found the
        pose, its rivals, ...), for reading why a case went as it did.
    """

    method: str
    case_id: str
    dataset: str
    tier: str
    positive: bool
    aligned: bool = False
    success: bool = False
    precise: Optional[bool] = False
    declined: bool = False
    wrong: bool = False
    false_merge: bool = False
    corner_error_px: Optional[float] = None
    candidate_corner_error_px: Optional[float] = None
    candidate_success: Optional[bool] = None
    rotation_error_deg: Optional[float] = None
    translation_error_px: Optional[float] = None
    scale_error: Optional[float] = None
    point_error_px: Optional[float] = None
    threshold_px: Optional[float] = None
    estimate: Optional[dict] = None
    confidence: Optional[float] = None
    acceptance_index: Optional[float] = None
    inliers: int = 0
    message: str = ""
    error: str = ""
    wall_s: float = 0.0
    align_s: float = 0.0
    peak_mb: Optional[float] = None
    max_rss_mb: Optional[float] = None
    a_shape: list = field(default_factory=list)
    b_shape: list = field(default_factory=list)
    cells: int = 0
    overlap: Optional[float] = None
    shared_walls: Optional[int] = None
    rotation_deg: Optional[float] = None
    scale: Optional[float] = None
    noise: Optional[float] = None
    source: Optional[str] = None
    verification: Optional[dict] = None
    details: Optional[dict] = None

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "Record":
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})


def _params(t) -> Optional[np.ndarray]:
    if t is None:
        return None
    if isinstance(t, AffineTransform):
        return t.params
    m = np.asarray(t, dtype=float)
    if m.shape == (2, 3):
        m = np.vstack([m, [0.0, 0.0, 1.0]])
    return m


def _rotation_deg(m: np.ndarray) -> float:
    return math.degrees(math.atan2(m[1, 0] - m[0, 1], m[0, 0] + m[1, 1]))


def _scale(m: np.ndarray) -> float:
    return float(math.sqrt(abs(np.linalg.det(m[:2, :2]))))


def _wrap_deg(d: float) -> float:
    return (d + 180.0) % 360.0 - 180.0


def _finite(v) -> Optional[float]:
    return None if v is None or not math.isfinite(float(v)) else float(v)


def halmstad_point_error(transform, points_a, points_b) -> float:
    """Median over the annotated points of ``|T(points_b[i]) - points_a[i]|``, pixels."""
    m = _params(transform)
    pb = np.asarray(points_b, dtype=float)
    pa = np.asarray(points_a, dtype=float)
    mapped = pb @ m[:2, :2].T + m[:2, 2]
    return float(np.median(np.hypot(*(mapped - pa).T)))


def ecc_reference(a, b, start, *, iterations: int = 60) -> np.ndarray:
    """A reference pose for a real pair without annotated truth: b's pixels -> a's, the
    affine transform OpenCV's ECC fits to every cell's grey value, from ``start``.

    Both maps are drawn as grey images (free 0, occupied 1, unknown 0.5), each blurred
    by about a's cell (at least half its own), and ECC (``cv2.findTransformECC``,
    ``MOTION_AFFINE``, a's known cells as the mask) maximises their correlation. It uses
    no keypoints, walls or refinement of ours, but it is a fit, not a truth: it needs a
    ``start`` within a few pixels, and its own optimum is only as good as the maps agree.

    Parameters
    ----------
    a, b : OccupancyGrid
    start : (3, 3) float array or transform
        b's pixels -> a's pixels, near the answer.
    iterations : int
        ECC iterations at most (it also stops when the warp changes by less than 1e-6).

    Returns
    -------
    (3, 3) float array
    """
    import cv2

    def grey(g, sigma):
        return cv2.GaussianBlur(np.where(np.isnan(g.data), 0.5, g.data).astype(np.float32), (0, 0), sigma)

    px = b.resolution / a.resolution  # a's cells per b cell
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, int(iterations), 1e-6)
    warp = np.asarray(_params(start), np.float32)[:2].copy()
    _, warp = cv2.findTransformECC(grey(b, max(0.5, 1.0 / px)), grey(a, max(0.5, px / 2.0)), warp, cv2.MOTION_AFFINE,
                                   criteria, a.known.astype(np.uint8), 1)
    return np.vstack([warp, [0.0, 0.0, 1.0]]).astype(float)


def judge(
    estimate,
    truth,
    b_shape: Sequence[int],
    *,
    positive: bool,
    candidate=None,
    protocol: Optional[dict] = None,
) -> dict:
    """Score one transform (b pixels -> a pixels) against the truth.

    Parameters
    ----------
    estimate : AffineTransform, (2, 3) or (3, 3) array, or None
        The returned transform; ``None`` when the method declined.
    truth : (3, 3) array or None
        ``None`` on negative pairs.
    b_shape : (int, int)
        ``(H, W)`` of map b (the corners of the corner error).
    positive : bool
    candidate : transform, optional
        The best candidate even when declined.
    protocol : dict, optional
        Halmstad: ``points_a``, ``points_b``, ``threshold_px``.

    Returns
    -------
    dict
        The scoring fields of :class:`Record`.
    """
    e = _params(estimate)
    t = _params(truth)
    out: dict = {
        "aligned": e is not None,
        "success": False,
        "precise": None if protocol is not None else False,
        "declined": e is None,
        "wrong": False,
        "false_merge": False,
        "corner_error_px": None,
        "candidate_corner_error_px": None,
        "candidate_success": None,
        "rotation_error_deg": None,
        "translation_error_px": None,
        "scale_error": None,
        "point_error_px": None,
        "threshold_px": None if protocol is None else float(protocol["threshold_px"]),
        "estimate": None,
    }
    if e is not None:
        out["estimate"] = {
            "rotation_deg": _rotation_deg(e),
            "scale": _scale(e),
            "tx": float(e[0, 2]),
            "ty": float(e[1, 2]),
            "matrix": e[:2].tolist(),
        }
    c = _params(candidate)
    if t is not None and c is not None:
        out["candidate_corner_error_px"] = _finite(corner_error(c, t, b_shape))
    if positive and c is not None:
        if protocol is not None:
            pe = halmstad_point_error(c, protocol["points_a"], protocol["points_b"])
            out["candidate_success"] = bool(math.isfinite(pe) and pe <= float(protocol["threshold_px"]))
        elif out["candidate_corner_error_px"] is not None:
            out["candidate_success"] = out["candidate_corner_error_px"] <= SUCCESS_PX
    if not positive:
        out["wrong"] = out["false_merge"] = e is not None
        return out
    if e is None:
        return out
    if t is not None:
        ce = corner_error(e, t, b_shape)
        out["corner_error_px"] = _finite(ce)
        out["rotation_error_deg"] = abs(_wrap_deg(_rotation_deg(e) - _rotation_deg(t)))
        h, w = b_shape[:2]
        centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0, 1.0])
        out["translation_error_px"] = float(np.hypot(*((e @ centre)[:2] - (t @ centre)[:2])))
        out["scale_error"] = abs(_scale(e) / _scale(t) - 1.0)
    if protocol is not None:
        pe = halmstad_point_error(e, protocol["points_a"], protocol["points_b"])
        out["point_error_px"] = _finite(pe)
        out["success"] = bool(math.isfinite(pe) and pe <= float(protocol["threshold_px"]))
    else:
        ce = out["corner_error_px"]
        out["success"] = ce is not None and ce <= SUCCESS_PX
        out["precise"] = ce is not None and ce <= PRECISE_PX
    out["wrong"] = not out["success"]
    return out


def evaluate(case, result, *, wall_s: float = 0.0, peak_mb=None, max_rss_mb=None, error: str = "") -> Record:
    """The :class:`Record` of ``result`` (an :class:`~gridmerge.align.AlignResult`, or
    ``None`` when the method raised ``error``) on ``case``
    (:class:`~gridmerge.bench.datasets.Case`)."""
    meta = case.meta
    protocol = meta if meta.get("protocol") == "halmstad" else None
    estimate = None if result is None or not result.success else result.transform
    candidate = None if result is None else result.candidate
    scores = judge(estimate, case.truth, case.b.shape, positive=case.positive, candidate=candidate, protocol=protocol)
    return Record(
        method="" if result is None else result.method,
        case_id=case.id,
        dataset=case.dataset,
        tier=case.tier,
        positive=bool(case.positive),
        **scores,
        confidence=None if result is None else _finite(result.confidence),
        acceptance_index=None if result is None else _finite(result.acceptance_index),
        inliers=0 if result is None else int(result.inliers),
        message="" if result is None else str(result.message),
        error=error,
        wall_s=float(wall_s),
        align_s=0.0 if result is None else float(result.elapsed_s),
        peak_mb=_finite(peak_mb),
        max_rss_mb=_finite(max_rss_mb),
        a_shape=list(case.a.shape),
        b_shape=list(case.b.shape),
        cells=int(case.a.data.size + case.b.data.size),
        overlap=_finite(meta.get("overlap")),
        shared_walls=None if meta.get("shared_walls") is None else int(meta["shared_walls"]),
        rotation_deg=_finite(meta.get("rotation_deg")),
        scale=_finite(meta.get("scale")),
        noise=_finite(meta.get("noise")),
        source=meta.get("source"),
        verification=None if result is None or result.verification is None else result.verification.to_dict(),
        # A method's own diagnostics may hold NaN (an index of no shared cell): null in JSON.
        details=None if result is None else finite(dict(result.details)),
    )


# ------------------------------------------------------------------ summaries
def _rate(k: int, n: int) -> Optional[float]:
    return None if n == 0 else k / n


def _quantile(values: list, q: float) -> Optional[float]:
    v = [x for x in values if x is not None and math.isfinite(x)]
    return None if not v else float(np.quantile(np.asarray(v, dtype=float), q))


def _group(records: Sequence[dict]) -> dict:
    pos = [r for r in records if r["positive"]]
    neg = [r for r in records if not r["positive"]]
    succ = [r for r in pos if r["success"]]
    prec = [r for r in pos if r["precise"] is not None]
    halm = any(r.get("threshold_px") is not None for r in pos)
    errs = [r["point_error_px"] if halm else r["corner_error_px"] for r in succ]
    return {
        "cases": len(records),
        "positives": len(pos),
        "negatives": len(neg),
        "success": len(succ),
        "success_rate": _rate(len(succ), len(pos)),
        "precise": sum(bool(r["precise"]) for r in prec),
        "precise_rate": _rate(sum(bool(r["precise"]) for r in prec), len(prec)),
        "declined": sum(r["declined"] for r in pos),
        "declined_rate": _rate(sum(r["declined"] for r in pos), len(pos)),
        "declined_right_candidate": sum(bool(r["declined"] and r.get("candidate_success")) for r in pos),
        "wrong": sum(r["wrong"] for r in pos),
        "wrong_rate": _rate(sum(r["wrong"] for r in pos), len(pos)),
        "false_merges": sum(r["false_merge"] for r in neg),
        "false_merge_rate": _rate(sum(r["false_merge"] for r in neg), len(neg)),
        "errors": sum(bool(r.get("error")) for r in records),
        "error_measure": "median point error (px)" if halm else "corner error (px)",
        "median_error_px": _quantile(errs, 0.5),
        "p90_error_px": _quantile(errs, 0.9),
        "median_time_s": _quantile([r["wall_s"] for r in records], 0.5),
        "p90_time_s": _quantile([r["wall_s"] for r in records], 0.9),
        "max_time_s": _quantile([r["wall_s"] for r in records], 1.0),
        "median_peak_mb": _quantile([r.get("peak_mb") for r in records], 0.5),
        "max_peak_mb": _quantile([r.get("peak_mb") for r in records], 1.0),
    }


def _environment(record: dict) -> Optional[str]:
    """The Halmstad environment of a record of a Halmstad data set (``"E5"``, or
    ``"E5+HIH"`` for a cross pair), ``None`` for other data sets."""
    source = record.get("source") or ""
    if not record["dataset"].startswith("halmstad") or not source.startswith("halmstad:"):
        return None
    return source.split(":", 1)[1]


def shared_walls_group(n: Optional[int]) -> Optional[str]:
    """The label of :data:`SHARED_WALL_GROUPS` that ``n`` shared wall cells fall in
    (``None`` for ``None``).

    >>> shared_walls_group(53), shared_walls_group(1000)
    ('50-199', '1000 or more')
    """
    if n is None:
        return None
    return [label for label, lo in SHARED_WALL_GROUPS if n >= lo][-1]


def summarize(records: Iterable) -> list:
    """Summary rows per method and dataset (``tier = "all"``), per method, dataset and
    tier (when a dataset has more than one tier), for the Halmstad data sets per method,
    dataset and environment (``tier`` the environment's name, ``by = "environment"``;
    when a data set has more than one), and for positive pairs that record their shared
    walls (the simulated ones) per method, dataset and :data:`SHARED_WALL_GROUPS` group
    (``tier`` its label, ``by = "shared walls"``; positives only: the success of pairs
    that share little structure, which the overlap of known cells does not tell).

    Each row: ``method``, ``dataset``, ``tier`` and the counts and rates of
    :func:`_group`: ``success_rate`` (over positive pairs), ``precise_rate``,
    ``declined_rate``, ``wrong_rate``, ``false_merge_rate`` (over negative pairs),
    median and 90th percentile of the error of the successes, median time, peak memory.
    """
    recs = [r.to_dict() if isinstance(r, Record) else dict(r) for r in records]
    methods = list(dict.fromkeys(r["method"] for r in recs))
    datasets = list(dict.fromkeys(r["dataset"] for r in recs))
    rows = []
    for ds in datasets:
        tiers = list(dict.fromkeys(r["tier"] for r in recs if r["dataset"] == ds))
        for m in methods:
            sel = [r for r in recs if r["dataset"] == ds and r["method"] == m]
            if not sel:
                continue
            rows.append({"method": m, "dataset": ds, "tier": "all", **_group(sel)})
            if len(tiers) > 1:
                for t in tiers:
                    sub = [r for r in sel if r["tier"] == t]
                    if sub:
                        rows.append({"method": m, "dataset": ds, "tier": t, **_group(sub)})
            envs = list(dict.fromkeys(e for e in map(_environment, sel) if e is not None))
            if len(envs) > 1:
                for e in envs:
                    sub = [r for r in sel if _environment(r) == e]
                    rows.append({"method": m, "dataset": ds, "tier": e, "by": "environment", **_group(sub)})
            walled = [r for r in sel if r["positive"] and r.get("shared_walls") is not None]
            for label, _ in SHARED_WALL_GROUPS if walled else ():
                sub = [r for r in walled if shared_walls_group(r["shared_walls"]) == label]
                if sub:
                    rows.append({"method": m, "dataset": ds, "tier": label, "by": "shared walls", **_group(sub)})
    return rows

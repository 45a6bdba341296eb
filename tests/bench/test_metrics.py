"""Scoring hand-made results."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from gridmerge import OccupancyGrid, samples
from gridmerge.align import AlignResult
from gridmerge.bench.datasets import Case
from gridmerge.bench.metrics import PRECISE_PX, SUCCESS_PX, Record, ecc_reference, evaluate, judge, summarize
from gridmerge.transforms import SimilarityTransform, corner_error
from gridmerge.verify import Verification

SHAPE = (200, 300)
TRUTH = np.array(
    [[0.9 * math.cos(0.5), -0.9 * math.sin(0.5), 40.0], [0.9 * math.sin(0.5), 0.9 * math.cos(0.5), -12.0], [0, 0, 1.0]]
)


def _shifted(dx: float) -> np.ndarray:
    return np.array([[1.0, 0, dx], [0, 1.0, 0], [0, 0, 1.0]]) @ TRUTH


def test_perfect_transform_is_a_precise_success():
    s = judge(TRUTH, TRUTH, SHAPE, positive=True)
    assert s["aligned"] and s["success"] and s["precise"]
    assert not s["declined"] and not s["wrong"] and not s["false_merge"]
    assert s["corner_error_px"] == pytest.approx(0.0, abs=1e-9)
    assert s["rotation_error_deg"] == pytest.approx(0.0, abs=1e-9)
    assert s["scale_error"] == pytest.approx(0.0, abs=1e-12)
    assert s["estimate"]["scale"] == pytest.approx(0.9)
    assert s["estimate"]["rotation_deg"] == pytest.approx(math.degrees(0.5))


def test_five_pixels_off_is_a_success_but_not_precise():
    s = judge(_shifted(5.0), TRUTH, SHAPE, positive=True)
    assert s["corner_error_px"] == pytest.approx(5.0)
    assert s["translation_error_px"] == pytest.approx(5.0)
    assert s["success"] and not s["precise"] and not s["wrong"]
    assert PRECISE_PX < 5.0 <= SUCCESS_PX


def test_fifty_pixels_off_is_wrong():
    s = judge(_shifted(50.0), TRUTH, SHAPE, positive=True)
    assert s["aligned"] and not s["success"] and not s["precise"] and s["wrong"] and not s["declined"]
    assert s["corner_error_px"] == pytest.approx(50.0)


def test_rotation_error_counts_at_the_corners():
    rot = np.array([[math.cos(0.01), -math.sin(0.01), 0], [math.sin(0.01), math.cos(0.01), 0], [0, 0, 1.0]])
    s = judge(TRUTH @ rot, TRUTH, SHAPE, positive=True)
    assert s["rotation_error_deg"] == pytest.approx(math.degrees(0.01))
    # The corner farthest from b's origin moves by 0.9 * 0.01 * |(299, 199)|.
    assert s["corner_error_px"] == pytest.approx(0.9 * 2 * math.sin(0.005) * math.hypot(299, 199), rel=1e-6)


def test_declined():
    s = judge(None, TRUTH, SHAPE, positive=True, candidate=_shifted(3.0))
    assert s["declined"] and not s["aligned"] and not s["success"] and not s["wrong"]
    assert s["corner_error_px"] is None
    assert s["candidate_corner_error_px"] == pytest.approx(3.0)
    assert s["candidate_success"] is True
    assert judge(None, TRUTH, SHAPE, positive=True, candidate=_shifted(30.0))["candidate_success"] is False
    assert judge(None, TRUTH, SHAPE, positive=True)["candidate_success"] is None


def test_negative_pairs():
    merged = judge(TRUTH, None, SHAPE, positive=False)
    assert merged["false_merge"] and merged["wrong"] and not merged["success"]
    declined = judge(None, None, SHAPE, positive=False)
    assert declined["declined"] and not declined["false_merge"] and not declined["wrong"]


def test_halmstad_protocol():
    pts_b = np.array([[10.0, 10.0], [100.0, 40.0], [50.0, 150.0], [200.0, 20.0]])
    pts_a = pts_b @ TRUTH[:2, :2].T + TRUTH[:2, 2]
    proto = {"points_a": pts_a.tolist(), "points_b": pts_b.tolist(), "threshold_px": 20.0}
    ok = judge(_shifted(15.0), TRUTH, SHAPE, positive=True, protocol=proto)
    assert ok["success"] and ok["point_error_px"] == pytest.approx(15.0) and ok["precise"] is None
    bad = judge(_shifted(25.0), TRUTH, SHAPE, positive=True, protocol=proto)
    assert not bad["success"] and bad["wrong"]


def _case(positive=True):
    a = OccupancyGrid(np.zeros((50, 60)))
    b = OccupancyGrid(np.zeros(SHAPE))
    meta = {"tier": "easy", "overlap": 0.6, "rotation_deg": 28.6, "scale": 0.9, "noise": 0.0, "source": "test"}
    return Case("t/0", "simulated", a, b, TRUTH if positive else None, positive, meta)


def _result(matrix, success=True):
    t = None if matrix is None else SimilarityTransform(matrix)
    return AlignResult(
        success=success, transform=t if success else None, candidate=t, metric_transform=None, confidence=0.9,
        acceptance_index=0.95, inliers=30, matches=100, keypoints=(10, 10), method="sift", message="ok", elapsed_s=0.5,
        verification=Verification(0.95, 95, 5, 0.8, 100, 0.6, 12, 10, 9, 8), details={"source": "walls"},
    )


def test_evaluate_builds_a_record():
    rec = evaluate(_case(), _result(_shifted(5.0)), wall_s=0.6, peak_mb=12.0, max_rss_mb=300.0)
    assert isinstance(rec, Record)
    assert rec.success and not rec.precise and rec.method == "sift" and rec.tier == "easy"
    assert rec.cells == 50 * 60 + SHAPE[0] * SHAPE[1] and rec.b_shape == list(SHAPE)
    assert rec.overlap == 0.6 and rec.wall_s == 0.6 and rec.align_s == 0.5 and rec.peak_mb == 12.0
    assert Record.from_dict(rec.to_dict()) == rec
    assert rec.details == {"source": "walls"} and rec.verification["walls_a"] == 12
    declined = evaluate(_case(), _result(_shifted(1.0), success=False))
    assert declined.declined and declined.candidate_corner_error_px == pytest.approx(1.0)
    crashed = evaluate(_case(), None, error="ValueError: boom")
    assert crashed.declined and crashed.error == "ValueError: boom"
    false_merge = evaluate(_case(positive=False), _result(TRUTH))
    assert false_merge.false_merge


def test_a_methods_nan_diagnostics_are_written_as_null():
    # A baseline's details may hold NaN (Carpin's index of a hypothesis sharing no known
    # cell); the results are strict JSON, so the record holds None there, and a run of
    # an hour is not lost to one value (the thirty-fifth session's run stopped on it).
    from dataclasses import replace

    from gridmerge.bench.runner import _dumps

    details = {"hypotheses": [{"acceptance_index": float("nan"), "shift": (1.0, np.float64("inf"))}], "n": 2}
    rec = evaluate(_case(), replace(_result(_shifted(1.0)), details=details))
    line = _dumps(rec.to_dict())
    assert json.loads(line)["details"] == {"hypotheses": [{"acceptance_index": None, "shift": [1.0, None]}], "n": 2}
    assert math.isnan(details["hypotheses"][0]["acceptance_index"])  # the result's own details untouched


def test_summaries():
    recs = [
        evaluate(_case(), _result(TRUTH), wall_s=1.0),
        evaluate(_case(), _result(_shifted(5.0)), wall_s=2.0),
        evaluate(_case(), _result(_shifted(50.0)), wall_s=3.0),
        evaluate(_case(), _result(None, success=False), wall_s=4.0),
        evaluate(_case(positive=False), _result(TRUTH), wall_s=5.0),
        evaluate(_case(positive=False), _result(None, success=False), wall_s=6.0),
    ]
    for r in recs:
        r.method = "m"
    rows = summarize(recs)
    assert len(rows) == 1  # one tier and negatives share the tier "easy" here
    r = rows[0]
    assert (r["positives"], r["negatives"]) == (4, 2)
    assert r["success_rate"] == 0.5 and r["precise_rate"] == 0.25
    assert r["declined_rate"] == 0.25 and r["wrong_rate"] == 0.25
    assert r["declined_right_candidate"] == 0  # the declined one had no candidate
    assert r["false_merge_rate"] == 0.5 and r["false_merges"] == 1
    assert r["median_error_px"] == pytest.approx(2.5)
    assert r["median_time_s"] == pytest.approx(3.5)


def _walled(n, success):
    case = _case()
    case.meta["shared_walls"] = n
    return evaluate(case, _result(TRUTH if success else _shifted(50.0)))


def test_simulated_positives_are_summed_up_by_the_walls_they_share():
    """Positive pairs that record their shared walls get a row per group of
    ``SHARED_WALL_GROUPS``, in its order, under ``by = "shared walls"``; negatives and
    pairs without the field stay out of it."""
    from gridmerge.bench.metrics import shared_walls_group

    recs = [_walled(20, False), _walled(49, True), _walled(50, True), _walled(5000, True),
            evaluate(_case(positive=False), _result(None, success=False)), evaluate(_case(), _result(TRUTH))]
    assert recs[0].shared_walls == 20 and recs[-1].shared_walls is None
    assert Record.from_dict(recs[0].to_dict()) == recs[0]
    rows = [r for r in summarize(recs) if r.get("by") == "shared walls"]
    assert [r["tier"] for r in rows] == ["under 50", "50-199", "1000 or more"]
    assert [(r["positives"], r["success"], r["negatives"]) for r in rows] == [(2, 1, 0), (1, 1, 0), (1, 1, 0)]
    assert [shared_walls_group(n) for n in (0, 49, 50, 199, 200, 999, 1000)] == [
        "under 50", "under 50", "50-199", "50-199", "200-999", "200-999", "1000 or more"]
    assert shared_walls_group(None) is None
    # Without the field (Halmstad, paper): no such rows.
    assert not [r for r in summarize(recs[4:]) if r.get("by") == "shared walls"]


def test_swapped_simulated_runs_are_explained_and_plotted_like_simulated_ones():
    """``simulated-swapped`` records get the simulated tables' notes and the simulated
    plots (their success against shared walls and overlap)."""
    from gridmerge.bench.report import results_markdown
    from gridmerge.bench.runner import BenchRun

    recs = [_walled(20, False), _walled(500, True)]
    for r in recs:
        r.dataset = "simulated-swapped"
    rows = summarize(recs)
    run = BenchRun(None, {"seed": 0, "methods": ["sift"], "datasets": []}, [r.to_dict() for r in recs], {"rows": rows})
    md = results_markdown(run)
    assert "## simulated-swapped by shared walls" in md and "Shared walls: cells of the source map" in md
    pytest.importorskip("matplotlib")
    from gridmerge.bench.plots import make_plots

    dicts = [r.to_dict() for r in recs]
    plotted = make_plots(dicts, ["sift"])["success_vs_shared_walls.png"]
    assert plotted != make_plots([{**d, "dataset": "halmstad"} for d in dicts], ["sift"])["success_vs_shared_walls.png"]


def test_compare_cases_lists_changed_outcomes_and_moved_errors():
    from gridmerge.bench import report

    def rec(case, **kw):
        base = {"method": "m", "case_id": case, "positive": True, "success": True, "wrong": False, "false_merge": False,
                "declined": False, "confidence": 0.9, "corner_error_px": 1.0, "point_error_px": None}
        return {**base, **kw}

    before = [rec("s/0"), rec("s/1"), rec("s/2"), rec("h/0", point_error_px=12.0, corner_error_px=300.0),
              rec("n/0", positive=False, success=False, declined=True, corner_error_px=None), rec("gone")]
    after = [rec("s/0", corner_error_px=1.5),  # moved by 0.5 px: not listed
             rec("s/1", success=False, wrong=True, corner_error_px=40.0),
             rec("s/2", corner_error_px=4.0),  # moved by 3 px
             rec("h/0", point_error_px=19.0, corner_error_px=300.0),  # Halmstad: the point error moved
             rec("n/0", positive=False, success=False, false_merge=True, corner_error_px=None), rec("new")]
    text = report.compare_cases(before, after)
    assert "Cases in both runs: 5; outcome changed: 2; outcome kept, error moved by more than 1 px: 2." in text
    changed, moved = text.split("### Changed outcome")[1].split("### Error moved")
    assert "| `m` | s/1 | right → wrong | 0.90 → 0.90 | 1.0 → 40.0 |" in changed
    assert "| `m` | n/0 | declined → false merge |" in changed
    assert moved.index("h/0") < moved.index("s/2") and "s/0" not in moved and "gone" not in text
    assert [report.outcome(r) for r in after[1:5]] == ["wrong", "right", "right", "false merge"]
    same = report.compare_cases(before, before)
    assert "outcome changed: 0; outcome kept, error moved by more than 1 px: 0." in same and "###" not in same


@pytest.mark.parametrize("scale", [1.0, 1.5, 0.7])
def test_the_ecc_reference_finds_a_known_pose_from_a_start_off(scale):
    """The reference for real pairs without annotated truth, on robot maps whose truth is
    known: from a start 7 px off, within 1 px of it (0.3-0.7 px)."""
    a, b, truth = samples.robot_pair(0, scale=scale)
    t = SimilarityTransform(truth)
    start = SimilarityTransform(rotation=t.rotation + 0.01, scale=t.scale * 1.003, translation=t.translation + [2.5, -2.0])
    assert corner_error(start, t, b.shape) > 6.0
    ref = ecc_reference(a, b, start)
    assert ref.shape == (3, 3) and corner_error(ref, t, b.shape) < 1.0
    # A 2 x 3 start is taken as well.
    np.testing.assert_allclose(ecc_reference(a, b, start.params[:2]), ref)


def test_time_plot_labels_its_log_axes_in_plain_numbers():
    """A short log axis (0.15 to 4 million cells) is labelled at 1, 2 and 5 of each
    decade in plain numbers; matplotlib's default labelled its minor ticks in powers of
    ten, overlapping one another."""
    pytest.importorskip("matplotlib")
    from gridmerge.bench.plots import _plain_log_ticks, _plt

    plt = _plt()
    fig, ax = plt.subplots()
    ax.set_xscale("log")
    ax.set_xlim(0.15, 4.0)
    _plain_log_ticks(ax.xaxis)
    fig.canvas.draw()

    def shown(minor):
        lo, hi = ax.get_xlim()
        return [t.get_text() for t in ax.get_xticklabels(minor=minor) if lo <= t.get_position()[0] <= hi and t.get_text()]

    major, minor = shown(False), shown(True)
    plt.close(fig)
    assert major == ["0.2", "0.5", "1", "2"] and minor == []

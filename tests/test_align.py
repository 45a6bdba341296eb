import importlib
import json
import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

import gridmerge
from gridmerge import AlignResult, OccupancyGrid, align, samples
from gridmerge.bench.metrics import ecc_reference
from gridmerge.transforms import ScaledRotationTransform, SimilarityTransform, corner_error
from gridmerge.features import Features
from gridmerge.align import AlignOptions
from gridmerge.verify import Verification
import gridmerge.verify as verify_module

#: The module (the package's ``align`` name is the function).
align_module = importlib.import_module("gridmerge.align")

# Simulated benchmark pairs named by number below are those of the set as built until
# 2026-11-30 (``see_through=0``: scanner rays stopped at a source's unknown cells), the
# pairs these mechanisms were found on.

@pytest.mark.parametrize("first", ["helper", "judge"])
def test_the_wall_scorer_is_made_once_by_whichever_thread_is_free_first(monkeypatch, first):
    from concurrent.futures import ThreadPoolExecutor
    import threading

    module = importlib.import_module("gridmerge.align")
    a, b, _ = samples.robot_pair(0)
    made = []
    real = module.WallScorer
    held = threading.Event()

    def counted(*args, **kwargs):
        made.append(threading.current_thread().name)
        return real(*args, **kwargs)

    monkeypatch.setattr(module, "WallScorer", counted)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="helper") as pool:
        if first == "judge":
            pool.submit(held.wait, 5)  # the helper is busy: the judge makes the scorer
        judge = module._Judge(a, b, module.AlignOptions(), pool=pool)
        judge.prepare()
        if first == "helper":
            judge._scorer_task.result()  # the helper has made it before the judge asks
        scorer = judge.scorer
        held.set()
        judge.release()
    assert len(made) == 1 and made[0].startswith("helper" if first == "helper" else "MainThread")
    assert scorer.tolerance == module.AlignOptions().wall_tolerance

def test_the_slide_measured_while_the_keypoints_settle_is_the_one_align_uses(monkeypatch):
    # The judge's helper thread slides the pose the keypoints settle while its rivals
    # are scored; align takes that measurement instead of sliding the pose again, and
    # only for that very pose.
    module = importlib.import_module("gridmerge.align")
    a, b, _ = samples.robot_pair(0)
    calls = []
    real = module.slide

    def counted(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(module, "slide", counted)
    ahead = align(a, b)
    assert ahead.success and ahead.details["walls"].startswith("skipped")  # settled by the keypoints
    assert len(calls) == 1
    monkeypatch.setattr(module._Judge, "slid", lambda self, t: None)  # not handed over
    calls.clear()
    again = align(a, b)
    assert len(calls) == 2  # slid ahead, then again by align
    assert again.details["slide"] == ahead.details["slide"]
    np.testing.assert_array_equal(again.transform.params, ahead.transform.params)


# The paper's Table I: exact 30 deg, (-86, -36) px, 0.95; its estimate was off by
# 0.09 deg, 0.21 px (x), 0.11 px (y) and 0.0003 in scale.
TABLE1_DEG, TABLE1_PX, TABLE1_SCALE = 0.09, 0.21, 0.0003


@pytest.fixture(scope="module")
def table1():
    return samples.table1_pair(0)


@pytest.fixture(scope="module")
def table1_result(table1):
    a, b, _ = table1
    return align(a, b)


# Declining maps of two places is the longest search (both sides, then the coarser
# look): the sample negative pair's default alignment is shared by the tests that only
# read it (one per worker: these tests run on one, ``xdist_group``).
NEGATIVE = pytest.mark.xdist_group("negative-pair")


@pytest.fixture(scope="module")
def negative():
    return samples.negative_pair(0)


@pytest.fixture(scope="module")
def negative_declined(negative):
    return align(*negative, rng=0)


@pytest.fixture(scope="module")
def negative_first_search(negative):
    """The first search alone (``coarse_look=0``)."""
    return align(*negative, rng=0, coarse_look=0)


def _errors(t, truth):
    dth = abs(math.degrees(t.rotation) - math.degrees(math.atan2(truth[1, 0], truth[0, 0])))
    dxy = np.abs(t.translation - truth[:2, 2])
    return dth, dxy, abs(t.scale - math.hypot(truth[0, 0], truth[1, 0]))


def test_default_method_beats_table_1(table1, table1_result):
    _, b, truth = table1
    r = table1_result
    assert r.success and isinstance(r.transform, SimilarityTransform)
    dth, dxy, ds = _errors(r.transform, truth)
    assert dth <= TABLE1_DEG and dxy.max() <= TABLE1_PX and ds <= TABLE1_SCALE
    # ... and by a wide margin: sub-pixel refinement against the maps.
    assert corner_error(r.transform, truth, b.shape) < 0.1
    assert r.confidence > 0.9 and r.acceptance_index > 0.95 and r.inliers >= 20


@pytest.mark.parametrize("seed", [1, 2])
def test_table_1_with_other_buildings(seed):
    a, b, truth = samples.table1_pair(seed)
    r = align(a, b, rng=seed)
    dth, dxy, ds = _errors(r.transform, truth)
    assert r.success and dth <= TABLE1_DEG and dxy.max() <= TABLE1_PX and ds <= TABLE1_SCALE


def test_ransac_method_beats_table_1(table1):
    a, b, truth = table1
    r = align(a, b, method="ransac")
    dth, dxy, ds = _errors(r.transform, truth)
    assert r.success and dth <= TABLE1_DEG and dxy.max() <= TABLE1_PX and ds <= TABLE1_SCALE


def test_paper_method_recovers_table_1(table1):
    # The paper's estimator as written (mean of a cluster of 3-point solutions, no
    # refinement) lands close to Table I but is not as precise as our default.
    a, b, truth = table1
    r = align(a, b, method="paper")
    assert r.success and isinstance(r.transform, ScaledRotationTransform)
    dx, dy, th, sx, sy = r.transform.parameters
    assert abs(math.degrees(th) - 30) < 0.1
    assert abs(dx + 86) < 1.0 and abs(dy + 36) < 1.0
    assert abs(sx - 0.95) < 2e-3 and abs(sy - 0.95) < 2e-3
    assert corner_error(r.transform, truth, b.shape) < 1.5
    assert r.to_dict()["scale_x"] == pytest.approx(sx)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_simulated_robot_pairs_align_precisely(seed):
    a, b, truth = samples.robot_pair(seed)
    r = align(a, b, rng=seed)
    assert r.success
    assert corner_error(r.transform, truth, b.shape) < 2.0


@pytest.mark.parametrize("seed, method", [
    # The defaults' case reads the shared alignment: in its group.
    pytest.param(s, m, marks=NEGATIVE) if (s, m) == (0, "hybrid") else (s, m)
    for m in ("hybrid", "sift", "ransac", "paper") for s in range(4)
])
def test_maps_of_different_places_are_declined(seed, method, request):
    if (seed, method) == (0, "hybrid"):  # the defaults
        r = request.getfixturevalue("negative_declined")
    else:
        a, b = samples.negative_pair(seed)
        r = align(a, b, method=method, rng=seed)
    assert not r.success and r.transform is None and r.matrix is None
    assert r.message.startswith("declined") or "no consistent" in r.message or "too few" in r.message
    assert r.confidence < 0.5
    # Their best pose is often at a chance scale too; the message must not send the user
    # after the maps' resolutions (--any-scale) when no pose would be taken at any scale.
    assert "--any-scale" not in r.message


def test_same_seed_same_result(table1):
    a, b, _ = table1
    r1, r2 = align(a, b, rng=3), align(a, b, rng=3)
    np.testing.assert_array_equal(r1.matrix, r2.matrix)


@pytest.mark.parametrize("pair", ["robots", pytest.param("different places", marks=NEGATIVE)])
def test_threads_change_nothing(monkeypatch, request, pair):
    # align runs work ahead and aside in helper threads when there are two cores; the
    # results must be those of running everything in turn, to the last bit.
    if pair == "robots":
        a, b = samples.robot_pair(1)[:2]
        threaded = align(a, b, rng=0)
    else:
        a, b = request.getfixturevalue("negative")
        threaded = request.getfixturevalue("negative_declined")
    monkeypatch.setattr("os.cpu_count", lambda: 1)
    serial = align(a, b, rng=0)
    assert threaded.candidate is not None
    np.testing.assert_array_equal(threaded.candidate.params, serial.candidate.params)
    assert (threaded.success, threaded.confidence, threaded.details) == (serial.success, serial.confidence, serial.details)
    assert threaded.verification == serial.verification


def test_metric_transform_maps_points_between_map_frames(table1, table1_result):
    a, b, truth = table1
    r = table1_result
    # A cell of b, its metric coordinates in b's frame, moved by the metric transform,
    # must be the metric coordinates of the same place in a.
    p_b = np.array([[100.0, 50.0], [400.0, 200.0]])
    in_a = a.pixel_to_metric(r.transform(p_b))
    np.testing.assert_allclose(r.metric_transform(b.pixel_to_metric(p_b)), in_a, atol=1e-9)
    m = r.metric
    assert set(m) == {"x", "y", "yaw", "scale"}
    # b's resolution is a's / 0.95 here, so the metric scale is ~1 and the yaw is -30 deg
    # (image y points down, ROS y up).
    assert m["scale"] == pytest.approx(1.0, abs=1e-3)
    assert math.degrees(m["yaw"]) == pytest.approx(-30.0, abs=0.05)


def test_result_round_trips_through_json(tmp_path, table1_result):
    r = table1_result
    path = tmp_path / "r.json"
    r.save(path)
    back = AlignResult.load(path)
    assert back.success and back.inliers == r.inliers
    np.testing.assert_allclose(back.matrix, r.matrix)
    d = json.loads(path.read_text())
    for key in ("success", "matrix", "rotation_deg", "scale", "translation_px", "metric", "confidence", "acceptance_index", "inliers", "elapsed_s"):
        assert key in d
    # JSON-ready means strict JSON: a method's NaN diagnostic (an undefined index) is null.
    odd = replace(r, details={**r.details, "index": math.nan})
    assert json.loads(odd.to_json(allow_nan=False))["details"]["index"] is None


def test_inputs_are_not_modified(table1):
    a, b, _ = table1
    before = a.data.copy(), b.data.copy()
    align(a, b)
    np.testing.assert_array_equal(a.data, before[0])
    np.testing.assert_array_equal(b.data, before[1])


def test_blank_maps_are_declined_not_crashed():
    blank = OccupancyGrid(np.zeros((60, 60)))
    unknown = OccupancyGrid(np.full((60, 60), np.nan))
    for x, y in [(blank, blank), (unknown, unknown), (blank, unknown)]:
        r = align(x, y)
        assert not r.success and r.matrix is None


def test_unknown_method_is_an_error(table1):
    a, b, _ = table1
    with pytest.raises(gridmerge.GridMergeError):
        align(a, b, method="magic")


@pytest.mark.shared
def test_real_apartment_maps_hih_01_02(shared_data):
    pairs = json.loads((shared_data / "halmstad" / "HIH_pairs.json").read_text())["pairs"]
    pair = next(p for p in pairs if (p["a"], p["b"]) == ("HIH_01", "HIH_02"))
    a = gridmerge.load_map(shared_data / "halmstad" / "HIH" / "HIH_01.png")
    b = gridmerge.load_map(shared_data / "halmstad" / "HIH" / "HIH_02.png")
    r = align(a, b)
    assert r.success
    err = np.median(np.hypot(*(r.transform(np.array(pair["points_b"])) - np.array(pair["points_a"])).T))
    # The data set's scoring protocol: within max(20 px, 2 x the hand-fit residual).
    assert err <= max(20.0, 2 * pair["fit_median_residual_px"])


@pytest.mark.shared
def test_real_apartment_maps_all_sensor_pairs_merge_and_none_wrongly(shared_data):
    pairs = json.loads((shared_data / "halmstad" / "HIH_pairs.json").read_text())["pairs"]
    maps = {}
    for pair in (p for p in pairs if p["kind"] == "sensor"):
        for name in (pair["a"], pair["b"]):
            if name not in maps:
                maps[name] = gridmerge.load_map(shared_data / "halmstad" / "HIH" / f"{name}.png")
        r = align(maps[pair["a"]], maps[pair["b"]])
        assert r.success, (pair["a"], pair["b"], r.message)
        err = np.median(np.hypot(*(r.transform(np.array(pair["points_b"])) - np.array(pair["points_a"])).T))
        assert err <= max(20.0, 2 * pair["fit_median_residual_px"]), (pair["a"], pair["b"], err)


@pytest.mark.shared
@pytest.mark.parametrize("swap", [False, True])
def test_real_maps_of_two_resolutions_are_merged_to_scale(shared_data, swap):
    """Willow Garage at 0.05 and at 0.1 m per cell (ros-planning's navigation
    tutorials; cropped differently and turned 0.75 degrees against each other): a real
    pair of maps whose cells differ in size, one of m-explore's users' complaints. No
    annotated truth: the pose every cell's grey value fits best (ECC), from which ours
    is 0.6 px (b's corners, a's pixels); the resolutions' ratio holds to 0.1 %."""
    fine = gridmerge.load_map(shared_data / "ros_maps" / "willow-full-0.05.yaml")
    coarse = gridmerge.load_map(shared_data / "ros_maps" / "willow-full.yaml")
    a, b = (coarse, fine) if swap else (fine, coarse)
    r = align(a, b)
    assert r.success and r.confidence >= 0.9, r.message
    assert abs(r.metric_transform.scale - 1.0) < 1e-3
    ecc = ecc_reference(a, b, r.transform)
    assert abs(math.hypot(*ecc[:2, 0]) * a.resolution / b.resolution - 1.0) < 5e-4  # ECC's scale: the ratio's
    assert corner_error(r.transform, ecc, b.shape) < 1.0


@NEGATIVE
def test_keypoints_first_skips_the_walls_only_when_settled(negative_declined):
    a, b, truth = samples.robot_pair(0)
    quick = align(a, b, rng=0)
    full = align(a, b, rng=0, keypoints_first=0)
    assert quick.success and full.success
    assert "walls" not in full.details and full.details["candidates"] > quick.details["candidates"]
    if "walls" in quick.details:  # settled by the keypoints: the same pose as the full search
        assert quick.confidence >= 0.9 and quick.verification.wall_agreement >= 0.75
        assert corner_error(quick.transform, full.transform, b.shape) < 0.5
    assert corner_error(quick.transform, truth, b.shape) < 2.0
    # A negative pair is never settled early.
    r = negative_declined
    assert not r.success and "walls" not in r.details


@NEGATIVE
def test_the_second_look_is_taken_only_when_the_keypoints_do_not_settle(monkeypatch, negative, negative_declined):
    from gridmerge.align import _SecondLook

    looks = []
    features = _SecondLook.features
    monkeypatch.setattr(_SecondLook, "features", lambda self: looks.append(self) or features(self))
    # Settled by the keypoints: no second look, nothing extracted.
    a, b, _ = samples.table1_pair(0)
    r = align(a, b, rng=0)
    assert r.success and "walls" in r.details and "second_look" not in r.details and not looks
    # Maps of two places are never settled: the blurred keypoints add their hypotheses
    # (details["second_look"] is written where the look ran), the pair is still declined,
    # and 0 turns the second look off (the first search alone shows it).
    r = negative_declined
    assert not r.success and r.details["second_look"]["hypotheses"] >= 0
    on = align(*negative, rng=0, coarse_look=0)
    assert "second_look" in on.details and looks
    looks.clear()
    off = align(*negative, rng=0, second_look=0, coarse_look=0)
    assert not off.success and "second_look" not in off.details and not looks


def test_the_second_look_finds_the_keypoints_once_for_both_sides(monkeypatch):
    from gridmerge.align import AlignOptions, _SecondLook

    align_module = importlib.import_module("gridmerge.align")
    a, b = samples.negative_pair(0)
    calls = []
    extract = align_module._extract_both
    monkeypatch.setattr(align_module, "_extract_both", lambda *args: calls.append(args) or extract(*args))
    look = _SecondLook(a, b, AlignOptions())
    fa, fb = look.features()
    ra, rb = look.swapped().features()
    assert (ra, rb) == (fb, fa) and ra is fb and len(calls) == 1
    assert len(fa) and len(fb)
    # They are keypoints of the blurred maps: not those the search starts with.
    plain = align_module.default_extractor()(a)
    assert len(plain) != len(fa) or not np.array_equal(plain.xy, fa.xy)


@NEGATIVE
def test_blurred_keypoints_found_ahead_are_those_the_search_finds(monkeypatch, negative, negative_first_search):
    # merge finds each map's blurred keypoints once (Method.prepare); align then uses them,
    # and they are the ones the search would find itself on the maps it works on.
    from gridmerge.align import METHODS, AlignOptions, _blurred_extractor, _shifted, default_extractor, working_maps

    a, b = negative
    opts = AlignOptions()
    fa = METHODS["hybrid"].prepare(a, default_extractor(opts)(a), opts)
    fb = METHODS["hybrid"].prepare(b, default_extractor(opts)(b), opts)
    ca, oa, cb, ob = working_maps(a, b)
    for f, crop, offset in ((fa, ca, oa), (fb, cb, ob)):
        ahead, found = _shifted(f, -offset).blurred, _blurred_extractor(opts)(crop)
        np.testing.assert_allclose(ahead.xy, found.xy)
        np.testing.assert_array_equal(ahead.descriptors, found.descriptors)
    # Given ahead, nothing is extracted during the alignment, and the result is the same
    # (the pair is declined: without the coarser look's search, which finds keypoints of
    # its own, blurred ones too, as a fleet's first searches do).
    lazy = negative_first_search
    assert "second_look" in lazy.details

    def no_extractor(opts):
        raise AssertionError("the blurred keypoints were found again")

    monkeypatch.setattr(importlib.import_module("gridmerge.align"), "_blurred_extractor", no_extractor)
    ahead = align(a, b, rng=0, features=(fa, fb), coarse_look=0)
    assert (ahead.success, ahead.confidence, ahead.details) == (lazy.success, lazy.confidence, lazy.details)


def test_the_second_look_adds_only_scales_the_resolutions_allow():
    from gridmerge.align import AlignOptions, _keypoint_hypotheses, _SecondLook, _scale_disagreement, _second_look_hypotheses

    a, b, truth = samples.table1_pair(0)  # b is a's map at 0.95 of its scale, same resolution
    opts = AlignOptions()
    fa, fb = _SecondLook(a, b, opts).features()
    every = _keypoint_hypotheses(fa, fb, opts)[0]
    kept = _second_look_hypotheses(a, b, fa, fb, opts)
    assert kept and all(_scale_disagreement(h.transform, a, b) <= 0.15 for h in kept)
    assert any(corner_error(h.transform, truth, b.shape) < 2.0 for h in kept)
    assert [h.transform for h in _second_look_hypotheses(a, b, fa, fb, replace(opts, max_scale_disagreement=None))] == [h.transform for h in every]
    # b's metadata claiming twice a's cell size rules the true scale out.
    coarse = b.replace(resolution=2 * a.resolution)
    assert not any(corner_error(h.transform, truth, b.shape) < 2.0 for h in _second_look_hypotheses(a, coarse, fa, fb, opts))


@pytest.mark.shared
def test_wall_led_search_aligns_what_the_overlap_seeking_one_cannot(shared_data):
    # Simulated benchmark pair 41 (seed 0): two robots in the Halmstad E5 office sharing
    # half their maps, whose explored areas have similar shapes elsewhere. The first,
    # overlap-seeking correlation offers no confident pose; the wall-led one does. (The
    # second look's candidates let the first search find it: without them here.)
    from gridmerge.bench import datasets

    case = datasets.simulated(n=60, seed=0, data_dir=shared_data, see_through=0)[41]
    r = align(case.a, case.b, rng=0, second_look=0)
    assert r.details["overlap_seeking"]["confidence"] < 0.5
    assert r.success and r.details["source"] == "walls (wall-led)"
    assert corner_error(r.transform, case.truth, case.b.shape) < 2.0
    # Its message says what it rests on: the walls (its 2 keypoint inliers are no evidence).
    v = r.verification
    assert f"({v.matched_a} of {v.walls_a} and {v.matched_b} of {v.walls_b} wall cells)" in r.message
    # Without the second search the first look declines it from both sides; the coarser
    # look finds it (since a pose is polished again where a polish stopped: the
    # fifty-seventh session).
    alone = align(case.a, case.b, rng=0, wall_led=False, second_look=0)
    assert alone.details["coarse_look"]["first_confidence"] < 0.5
    assert alone.success and "fewer pixels" in alone.message
    assert corner_error(alone.transform, case.truth, case.b.shape) < 2.0
    r = align(case.a, case.b, rng=0)
    assert r.success and corner_error(r.transform, case.truth, case.b.shape) < 2.0


@pytest.mark.shared
def test_a_first_pose_at_a_scale_the_resolutions_rule_out_does_not_end_the_search(shared_data):
    # Simulated pair 50 of seed 71 (HIH_04, b's cells as large as a's): the first,
    # overlap-seeking search's best pose is at a keypoints' scale more than 15 % off the
    # resolutions' ratio, with confidence above the decline threshold. Such a pose is
    # declined for its scale whatever its confidence; it used to spare the wall-led
    # search too, and the pair was declined. The wall-led search finds the truth.
    from gridmerge.bench import datasets

    case = datasets.simulated(n=60, seed=71, data_dir=shared_data)[50]
    r = align(case.a, case.b, rng=0)
    first = r.details["overlap_seeking"]
    assert first["confidence"] >= 0.5 and first["scale_off"] > AlignOptions().max_scale_disagreement
    assert r.success and r.details["source"].startswith("walls (wall-led")
    assert corner_error(r.transform, case.truth, case.b.shape) < 2.0


@pytest.mark.shared
def test_the_rotation_keypoints_vote_for_finds_what_wall_directions_miss(shared_data, monkeypatch):
    # Simulated benchmark pair 32 (seed 1, hard tier: 12 % noise, b at 0.65 of a's cell
    # size, 32 % overlap): the wall directions' rotation candidates are 4.6 degrees off the
    # truth, beyond the wall-led search's offsets; the window of rotations the keypoint
    # matches vote for most holds it.
    from gridmerge.bench import datasets

    case = datasets.simulated(n=60, seed=1, data_dir=shared_data, see_through=0)[32]
    r = align(case.a, case.b, rng=0)
    assert r.success and r.details["source"] == "walls (wall-led)"
    assert corner_error(r.transform, case.truth, case.b.shape) < 10.0
    # Without the vote the pair is declined.
    monkeypatch.setattr(importlib.import_module("gridmerge.align"), "match_rotation", lambda *args, **kwargs: None)
    assert not align(case.a, case.b, rng=0).success


def test_scale_prior_applies_near_the_resolution_ratio_only():
    from gridmerge.align import AlignOptions, scale_prior

    a = OccupancyGrid(np.zeros((10, 10)), resolution=0.05)
    b = OccupancyGrid(np.zeros((10, 10)), resolution=0.06)
    near = SimilarityTransform(rotation=0.3, scale=1.2 * 1.02)
    far = SimilarityTransform(rotation=0.3, scale=1.2 * 1.05)
    on = AlignOptions(scale_prior=4.0)
    assert scale_prior(a, b, near, on) == (pytest.approx(1.2), 4.0)
    assert scale_prior(a, b, far, on) is None  # the maps' resolutions may be wrong
    assert scale_prior(a, b, near, AlignOptions()) == (pytest.approx(1.2), 1.0)  # on by default
    assert scale_prior(a, b, near, AlignOptions(scale_prior=0.0)) is None


@pytest.mark.shared
def test_scale_prior_pulls_a_simulated_merge_to_the_resolution_ratio(shared_data):
    # Simulated pair 12 (seed 0): b at 1.37 times a's resolution. Both poses are precise
    # (before the simulator put walls where robot a sees them, the cells alone left the
    # scale 0.5 % off there); the prior brings the scale nearer the exact ratio.
    from gridmerge.bench import datasets

    case = datasets.simulated(n=60, seed=0, data_dir=shared_data, see_through=0)[12]
    with_prior = align(case.a, case.b, rng=0, scale_prior=4.0)
    without = align(case.a, case.b, rng=0, scale_prior=0.0)
    assert with_prior.success and without.success
    ratio = case.b.resolution / case.a.resolution
    assert abs(with_prior.transform.scale - ratio) < abs(without.transform.scale - ratio)
    assert corner_error(with_prior.transform, case.truth, case.b.shape) < 1.0
    assert corner_error(without.transform, case.truth, case.b.shape) < 2.0


@pytest.mark.shared
def test_the_default_scale_prior_makes_a_noisy_merge_precise(shared_data):
    # Simulated pair 23 (seed 0): a Tango map's thick walls at 1.46 times a's resolution.
    # The cells alone fit best 2 px off (beyond "precise"); the default prior holds the
    # scale at the resolutions' ratio and the merge is within 1 px.
    from gridmerge.bench import datasets

    case = datasets.simulated(n=60, seed=0, data_dir=shared_data, see_through=0)[23]
    default = align(case.a, case.b, rng=0)
    cells_only = align(case.a, case.b, rng=0, scale_prior=0.0)
    assert default.success and cells_only.success
    assert corner_error(default.transform, case.truth, case.b.shape) < 1.0
    assert corner_error(cells_only.transform, case.truth, case.b.shape) > 1.5


def _turn_about(centre, deg: float) -> SimilarityTransform:
    """A turn by ``deg`` degrees about the point ``centre`` (x, y)."""
    c = np.asarray(centre, dtype=float)
    return SimilarityTransform(translation=c) @ SimilarityTransform(rotation=math.radians(deg)) @ SimilarityTransform(translation=-c)


def test_a_pose_turned_about_the_overlap_is_no_rival():
    """Turned 6 degrees about the shared part, a pose moves b's far corners well beyond
    40 px but the shared part little: the same merge for maps that bend, not another
    answer. Shifted by 60 px it is one."""
    from gridmerge.align import AlignOptions, _Judge

    a, b, truth = samples.robot_pair(0)
    best = SimilarityTransform(truth)
    judge = _Judge(a, b, AlignOptions())
    # The centre of the part of b that lands on a's known cells, in a's pixels.
    cells = np.argwhere(b.known)[:, ::-1].astype(float)
    p = best(cells)
    inside = (p[:, 0] >= 0) & (p[:, 0] < a.width - 1) & (p[:, 1] >= 0) & (p[:, 1] < a.height - 1)
    p = p[inside]
    p = p[a.known[np.rint(p[:, 1]).astype(int), np.rint(p[:, 0]).astype(int)]]
    cx, cy = np.median(p, axis=0)
    turned = _turn_about((cx, cy), 6.0) @ best
    shifted = SimilarityTransform(translation=(60.0, 0.0)) @ best
    assert judge.far_apart(best, turned, 40.0) and judge.far_apart(best, shifted, 40.0)
    assert not judge.rival(best, turned)
    assert judge.rival(best, shifted)
    assert not judge.rival(best, best)


def test_a_pose_turned_about_one_end_of_the_overlap_is_no_rival():
    """The same merge fitted to the other end of maps that bend: turned about one end of
    the shared part, a pose moves its far end, and its median, beyond 25 px but the part
    near that end little. It is no rival; turned ten times as far it is, and so is a pose
    that moves every part of the overlap."""
    from gridmerge.align import AlignOptions, _Judge

    a, b, truth = samples.robot_pair(0)
    best = SimilarityTransform(truth)
    judge = _Judge(a, b, AlignOptions())
    p, on = judge._shared_part(best)
    p = p[on]
    axis = np.linalg.svd(p - p.mean(axis=0), full_matrices=False)[2][0]
    along = (p - p.mean(axis=0)) @ axis
    end = p[np.argmin(along)]
    reach = np.median(np.hypot(*(p - end).T))
    deg = math.degrees(35.0 / reach)  # moves the median 35 px
    turned = _turn_about(end, deg) @ best
    moved = np.hypot(*(turned(judge._known_b[on]) - p).T)
    assert np.median(moved) > 25.0 > np.quantile(moved, 0.1)  # a rival by its median
    assert judge.far_apart(best, turned, 40.0)
    assert not judge.rival(best, turned)
    assert judge.rival(best, _turn_about(end, 10 * deg) @ best)
    assert judge.rival(best, SimilarityTransform(translation=(0.0, 45.0)) @ best)


def test_a_nudged_pose_reaches_the_truth_that_refining_does_not():
    """From a pose 26 px off, the refinement (12 px reach) stays off; shifted by 20 px
    towards the truth and refined, the pose is the truth, and it scores higher."""
    from gridmerge.align import AlignOptions, _Judge

    a, b, truth = samples.robot_pair(0)
    judge = _Judge(a, b, AlignOptions())
    judge.prepare()
    start = SimilarityTransform(SimilarityTransform(translation=(26.0, 0.0)).params @ truth)
    alone = judge._refined(start)
    assert corner_error(alone, truth, b.shape) > 5.0
    nudged = judge.nudged(start)
    errors = [corner_error(t, truth, b.shape) for t in nudged]
    assert min(errors) < 1.0
    assert judge.quick(nudged[int(np.argmin(errors))]) > 1.1 * judge.quick(alone)


@pytest.mark.parametrize("shift", [(40.0, 0.0), (0.0, 45.0)])
def test_nudges_climb_to_a_pose_beyond_one_nudge(shift):
    """Farther than one nudge and a refinement reach (20 + 12 px), the nudges climb: the
    best nudged pose is nudged again while it improves, and reaches the truth."""
    from gridmerge.align import AlignOptions, _Judge

    a, b, truth = samples.robot_pair(0)
    judge = _Judge(a, b, AlignOptions())
    judge.prepare()
    start = SimilarityTransform(SimilarityTransform(translation=shift).params @ truth)
    assert min(corner_error(t, truth, b.shape) for t in judge.nudged(start)) > 10.0
    climbed = judge.climbed(start)
    best = max(climbed, key=judge.quick)
    assert corner_error(best, truth, b.shape) < 1.0 and judge.quick(best) > 2 * judge.quick(start)
    # It stops where no nudge improves: from the truth, one round.
    assert len(judge.climbed(SimilarityTransform(truth))) == len(judge.nudged(SimilarityTransform(truth)))


@pytest.mark.shared
def test_a_room_slid_along_a_wall_is_nudged_to_the_truth(shared_data):
    # Simulated pair 52 (seed 1): one room, the same in both maps. The overlap-seeking
    # search's pose slid 26 px along a wall (walls agree on 87 %), was refined in place
    # and taken with confidence 1.0; the truth (97 %) lay beyond the refinement's reach.
    # From b's side (b is the larger map, the reference by default) the first nudge
    # left the pose 26 px off; the second reaches the truth.
    from gridmerge.bench import datasets

    case = datasets.simulated(n=60, seed=1, data_dir=shared_data, see_through=0)[52]
    for reference in ("larger", "a"):
        r = align(case.a, case.b, rng=0, search_from=reference)
        assert r.success and corner_error(r.transform, case.truth, case.b.shape) < 2.0
    assert r.details["searched_from"] == "a" and align(case.a, case.b, rng=0).details["searched_from"] == "b"


def _inverse_of(r1, r2) -> bool:
    return np.allclose(r1.candidate.params @ r2.candidate.params, np.eye(3), atol=1e-9)


@pytest.mark.parametrize("pair", ["table1", "robots", pytest.param("different places", marks=NEGATIVE)])
def test_swapping_the_maps_inverts_the_transform_and_keeps_the_decision(pair, request):
    """The default search takes the larger map as its reference whichever order the maps
    come in: ``align(b, a)`` is ``align(a, b)`` inverted, declined alike."""
    from gridmerge.align import reference_first

    if pair == "table1":
        a, b, _ = samples.table1_pair(0)
    elif pair == "robots":
        a, b, _ = samples.robot_pair(1)
    else:
        a, b = request.getfixturevalue("negative")
    assert reference_first(a, b) != reference_first(b, a)
    r1 = request.getfixturevalue("negative_declined") if pair == "different places" else align(a, b, rng=0)
    r2 = align(b, a, rng=0)
    assert r1.success == r2.success == (pair != "different places")
    assert _inverse_of(r1, r2)
    assert (r1.confidence, r1.inliers, r1.matches) == (r2.confidence, r2.inliers, r2.matches)
    assert r1.keypoints == r2.keypoints[::-1]
    v1, v2 = r1.verification, r2.verification
    assert v1 == replace(v2, walls_a=v2.walls_b, walls_b=v2.walls_a,  # per-map counts swapped
                         matched_a=v2.matched_b, matched_b=v2.matched_a)
    if r1.success:
        # A taken pose's message names each map's walls in the order the maps were given.
        for r, v in ((r1, v1), (r2, v2)):
            assert f"({v.matched_a} of {v.walls_a} and {v.matched_b} of {v.walls_b} wall cells)" in r.message
        assert v1.walls_a != v1.walls_b and r1.message != r2.message
    else:
        assert r1.message == r2.message
    d1, d2 = dict(r1.details), dict(r2.details)  # r1 may be shared: not changed
    assert {d1.pop("searched_from"), d2.pop("searched_from")} == {"a", "b"} and d1 == d2
    assert np.array_equal(r1.inlier_xy, r2.inlier_xy[:, ::-1])
    if r1.success:
        assert np.allclose(r1.metric_transform.params @ r2.metric_transform.params, np.eye(3), atol=1e-9)
    # The same with the maps' features given (as merge gives them).
    from gridmerge.align import AlignOptions, default_extractor

    ext = default_extractor(AlignOptions())
    fa, fb = ext(a), ext(b)
    r3 = align(b, a, rng=0, features=(fb, fa))
    assert _inverse_of(r1, r3) and r3.confidence == r1.confidence


def test_the_larger_map_is_the_reference_whatever_the_order():
    """By known area first (square metres: a coarser map covers more per cell), then by
    cells; maps equal in all of those by their bytes, so exactly one of two different
    maps is the reference."""
    from gridmerge.align import reference_first

    fine = OccupancyGrid(np.zeros((10, 10)), resolution=0.05)
    coarse = OccupancyGrid(np.zeros((6, 6)), resolution=0.1)  # 36 cells, but 0.36 m2 against 0.25
    assert reference_first(coarse, fine) and not reference_first(fine, coarse)
    one, other = np.zeros((4, 4)), np.zeros((4, 4))
    one[0, 0] = other[3, 3] = 1.0
    g1, g2 = OccupancyGrid(one), OccupancyGrid(other)
    assert reference_first(g1, g2) != reference_first(g2, g1)
    assert reference_first(g1, OccupancyGrid(one.copy()))
    partly = one.copy()
    partly[2, :] = np.nan
    assert reference_first(g1, OccupancyGrid(partly)) and not reference_first(OccupancyGrid(partly), g1)


def test_the_reference_can_be_the_first_map():
    """``search_from="a"`` searches with a as the reference in either order (the order of
    the maps may then change the outcome); anything else is refused."""
    from gridmerge.errors import GridMergeError

    a, b, _ = samples.table1_pair(0)
    r1, r2 = align(a, b, rng=0, search_from="a"), align(b, a, rng=0, search_from="a")
    assert r1.success and r2.success and r1.details["searched_from"] == r2.details["searched_from"] == "a"
    with pytest.raises(GridMergeError, match="unknown search_from"):
        align(a, b, search_from="b")


@pytest.mark.parametrize("method", ["hybrid", "sift"])
def test_a_scale_the_resolutions_rule_out_is_declined_unless_any_scale(method):
    """b's resolution says 0.1 m/cell where it is really 0.05: the maps' metadata says
    scale 2, their cells about 1. By default no pose that far from the resolutions is
    accepted, and the message says why and what to do; with
    ``max_scale_disagreement=None`` the cells' scale is taken and the merge is right."""
    from gridmerge.align import _scale_disagreement

    a, b, truth = samples.robot_pair(0)
    liar = b.replace(resolution=2 * b.resolution)
    r = align(a, liar, rng=0, method=method)
    assert not r.success and "--any-scale" in r.message
    # The cells' pose is found, and declined for its scale alone.
    assert corner_error(r.candidate, truth, b.shape) < 1.0 and _scale_disagreement(r.candidate, a, liar) > 0.9
    free = align(a, liar, rng=0, method=method, max_scale_disagreement=None)
    assert free.success and corner_error(free.transform, truth, b.shape) < 1.0
    # With its true resolution, the same map merges by default.
    assert align(a, b, rng=0, method=method).success


def test_a_pose_is_rivalled_by_itself_shifted_along_what_does_not_fix_it():
    """The nearest clearly different poses (the best shifted by 40 px) are rivals even
    when no candidate proposed them: a map of one long wall fits as well shifted along
    it, a room's map does not."""
    from gridmerge.align import AlignOptions, _Judge

    wall = np.full((200, 400), np.nan, np.float32)
    wall[60:120, 10:390] = 0.0
    wall[120, 10:390] = 1.0
    a = OccupancyGrid(wall)
    b = OccupancyGrid(wall[50:130, 100:300].copy())
    judge = _Judge(a, b, AlignOptions())
    judge.prepare()
    at = SimilarityTransform(translation=(100, 50))
    assert judge.shifted(at, judge.quick) >= 0.95 * judge.quick(at)

    ra, rb, truth = samples.robot_pair(0)
    judge = _Judge(ra, rb, AlignOptions())
    judge.prepare()
    t = SimilarityTransform(truth)
    assert judge.shifted(t, judge.quick) < 0.6 * judge.quick(t)


@pytest.mark.shared
@pytest.mark.parametrize("a_name, b_name", [("HIH_02", "E5_02"), ("E5_07", "HIH_01")])
def test_real_maps_of_two_buildings_that_fit_by_chance_are_declined(shared_data, a_name, b_name):
    """HIH_02 - E5_02: the apartment laid into the office's open space; its walls agree on
    55 % and no proposed pose came close, but shifted by 40 px it agrees nearly as well.
    E5_07 - HIH_01: an apartment room laid onto an office room by the wall-led search
    (walls agree on 77 % of a 24 % overlap), beating every other pose by only 17 %.
    Both declined."""
    from gridmerge.io import load_map

    folder = shared_data / "halmstad"
    load = lambda name: load_map(folder / name.split("_")[0] / f"{name}.png")  # noqa: E731
    r = align(load(a_name), load(b_name), rng=0)
    assert not r.success


def test_a_pose_judged_on_a_handful_of_one_maps_walls_is_declined():
    """The wall agreement is the mean of the two maps' shares of matched walls; a share
    of a handful of cells is no evidence, whatever the rest says."""
    from gridmerge.align import AlignOptions, _decline_reason
    from gridmerge.verify import Verification

    opts = AlignOptions()
    few = Verification(0.9996, 56386, 24, 0.617, 56410, 0.25, 6, 30)
    assert _decline_reason(0, few, 0.77, opts, need_inliers=False) == (
        "declined: the overlap holds only 6 wall cells of one map (need 10 of each to judge the walls)")
    assert _decline_reason(0, replace(few, walls_a=30, walls_b=6), 0.77, opts, need_inliers=False).startswith(
        "declined: the overlap holds only 6 wall cells")
    assert _decline_reason(0, replace(few, walls_a=10), 0.77, opts, need_inliers=False) == ""
    # Results saved before the counts were recorded are judged as before.
    assert _decline_reason(0, replace(few, walls_a=None, walls_b=None), 0.77, opts, need_inliers=False) == ""
    assert _decline_reason(0, few, 0.77, replace(opts, min_overlap_walls=5), need_inliers=False) == ""


def test_a_pose_whose_one_maps_walls_cross_the_others_rooms_is_declined():
    """Fresh simulated seed 13, pair 19 (two places): a small map's 53 walls in the
    overlap lay on the large map's walls, 52 of them, while 1047 of the large map's 1116
    crossed the small map's free space; the mean of the two shares, 52 %, passed."""
    from gridmerge.align import AlignOptions, _decline_reason
    from gridmerge.verify import Verification

    opts = AlignOptions()
    one_sided = Verification(0.984, 67841, 1087, 0.52, 68928, 0.9995, 1116, 53, 69, 52)
    assert _decline_reason(0, one_sided, 0.7, opts, need_inliers=False) == (
        "declined: only 6% of one map's walls in the overlap lie on the other's walls "
        "(need 15% of each; the rest cross the other's free space)")
    assert _decline_reason(0, replace(one_sided, matched_a=400), 0.7, opts, need_inliers=False) == ""
    assert _decline_reason(0, one_sided, 0.7, replace(opts, min_wall_share=0.0), need_inliers=False) == ""
    # Results saved before the matched cells were counted are judged as before.
    assert _decline_reason(0, replace(one_sided, matched_a=None, matched_b=None), 0.7, opts, need_inliers=False) == ""


@pytest.mark.shared
def test_a_small_map_fitted_inside_a_large_ones_free_space_is_declined(shared_data):
    """Fresh simulated seed 13, pair 19 (HIH_01 and E5_13): the search on fewer pixels
    fitted the small map inside the large one's rooms at confidence 0.70; its walls
    cross the small map's free space, and it is declined for that."""
    from gridmerge.bench import datasets

    case = datasets.simulated(n=60, seed=13, data_dir=shared_data)[19]
    assert not case.positive
    r = align(case.a, case.b, rng=0)
    assert not r.success
    assert "of one map's walls in the overlap lie on the other's" in r.details["coarse_look"]["message"]


@pytest.mark.shared
def test_a_walls_only_pose_the_other_side_gives_no_confidence_is_one_sided(shared_data, monkeypatch):
    """Fresh simulated seed 18, pair 50 (two robots in E5_02, 65 wall cells of the source
    seen by both): the wall-led search took a pose 12.4 px off at 0.75, one-sided; the
    search on fewer pixels found it again, and the search from b's side found the same
    pose at confidence 0, which let it through. Now that is no confirmation. (Since the
    fiftieth session the judging also refines the peaks whose walls lie near, and finds
    the truth: shown with those refinements off; and since the fifty-fourth session,
    isolated hits made unknown, the pair is merged without them too: shown on the maps
    with those hits freed.)"""
    from gridmerge.bench import datasets

    _isolated_hits_freed(monkeypatch)
    case = datasets.simulated(n=60, seed=18, data_dir=shared_data)[50]
    r = align(case.a, case.b, rng=0)
    assert r.success and corner_error(r.transform, case.truth, case.b.shape) < 2.0
    assert r.details["source"].endswith("(ranked by its walls within 8 px)")
    monkeypatch.setattr(importlib.import_module("gridmerge.align"), "_TOLERANT_REFINE", 0)
    r = align(case.a, case.b, rng=0)
    assert not r.success and r.message.startswith("declined: found from one map's side only")
    assert "the same pose, but at confidence 0.00" in r.details["coarse_look"]["message"]


def test_a_first_side_that_align_would_decline_as_unsure_lets_the_other_sides_pose_in(monkeypatch):
    # Stubbed searches on the sample pair: a's side's best pose lies 42 px off (its walls
    # agree on 24 %, enough for this test's floor) at confidence 0.6; b's side finds the
    # truth at 1.0. Below 0.8 a pose needs a building's walls (unsure_walls), so align
    # would decline a's side's pose whatever b's side found: a's side declines, and b's
    # side's pose, which beats a's best twice over, is taken (HM3D seed 41's pair 40).
    # Before, a's side's pose counted as taken and the pair was declined as one-sided.
    a, b, truth = samples.robot_pair(0)
    ca, oa, cb, ob = align_module.working_maps(a, b)
    right = align_module.full_to_crop(SimilarityTransform(truth), oa, ob)
    chance = SimilarityTransform(translation=(30.0, 30.0)) @ right
    none = np.zeros((0, 2))

    def search(judge, fa, fb, second=None):
        reverse = judge.a is cb
        return align_module.Estimate(right.inverse if reverse else chance, np.zeros(0, bool), none, none,
                                     details={"source": "stub"}, confidence=1.0 if reverse else 0.6)

    monkeypatch.setattr(align_module, "_hybrid_search", search)
    opts = AlignOptions(min_wall_agreement=0.2, second_look=0)
    assert align_module._unsure_reason(verify_module.verify(ca, cb, chance, tolerance=opts.wall_tolerance), 0.6, opts)
    est = align_module._both_sides(ca, cb, Features.empty(), Features.empty(), opts, None)
    assert est.details["other_side"]["taken"] and est.confidence == 1.0
    assert corner_error(align_module.crop_to_full(est.transform, oa, ob), truth, b.shape) < 1.0
    # Without the rule, a's side's pose stands, and b's side's is not taken.
    est = align_module._both_sides(ca, cb, Features.empty(), Features.empty(), replace(opts, unsure_walls=None), None)
    assert not est.details["other_side"].get("taken") and est.one_sided.startswith("declined: found from one map's side only")


@pytest.mark.shared
def test_maps_of_two_places_whose_overlap_holds_few_walls_are_declined(shared_data):
    """Simulated seed 4, pair 49: two distant parts of Halmstad E5_08, whose best pose lays
    a room of b onto open floor of a (walls agree on 62 %: all 6 of a's walls in the
    overlap matched, 7 of b's 30). It was merged at confidence 0.77; declined now, for
    the handful of a's walls the agreement rests on."""
    from gridmerge.bench import datasets

    case = datasets.simulated(n=60, seed=4, data_dir=shared_data)[49]
    assert not case.positive
    r = align(case.a, case.b, rng=0)
    assert not r.success and "wall cells of one map" in r.message
    v = r.verification
    assert min(v.walls_a, v.walls_b) < 10 <= max(v.walls_a, v.walls_b)


@pytest.mark.shared
def test_a_right_merge_resting_on_few_walls_is_still_taken(shared_data):
    """Simulated seed 3, pair 50: a small overlap of two HIH_01 robots (36 wall cells of
    the source seen by both), merged right although the search's frame holds only 18-30
    wall cells of one map in the overlap (as its pose is polished): the floor of
    ``min_overlap_walls`` is below that."""
    from gridmerge.bench import datasets

    case = datasets.simulated(n=60, seed=3, data_dir=shared_data)[50]
    r = align(case.a, case.b, rng=0)
    assert r.success and corner_error(r.transform, case.truth, case.b.shape) < 2.0
    v = r.verification
    assert min(v.walls_a, v.walls_b) < 30


@pytest.mark.shared
def test_the_wall_led_search_adds_the_peaks_the_walls_rank_best(shared_data):
    """Simulated seed 4, pair 27 (two robots in HIH_01, 37 % overlap, 96 wall cells of the
    source seen by both): the wall correlation's 20 best peaks all lie 30 px or more from
    the truth, the nearest ranked 35th by the correlation; the walls' weighed agreement
    ranks it first. Declined until the wall-led search, its correlation's best peaks not
    settling the pose, judged the peaks the walls rank best too."""
    from gridmerge.align import _WALL_LED_FINE_DEG, AlignOptions, _Judge, full_to_crop, working_maps
    from gridmerge.bench import datasets
    from gridmerge.correlate import correlation_hypotheses, rotation_candidates

    case = datasets.simulated(n=60, seed=4, data_dir=shared_data)[27]
    r = align(case.a, case.b, rng=0)
    assert r.success and corner_error(r.transform, case.truth, case.b.shape) < 2.0
    assert r.details["source"] == "walls (wall-led, ranked by the walls)"
    ca, oa, cb, ob = working_maps(case.a, case.b)
    truth = SimilarityTransform(full_to_crop(SimilarityTransform(case.truth), oa, ob).params)
    kw = dict(scales=[cb.resolution / ca.resolution], rotations=rotation_candidates(ca, cb), fine_deg=_WALL_LED_FINE_DEG)
    errors = [corner_error(h.transform, truth, cb.shape) for h in correlation_hypotheses(ca, cb, **kw)]
    assert len(errors) == 20 and min(errors) > 30
    pool = correlation_hypotheses(ca, cb, **kw, peaks=12, max_hypotheses=1000)
    judge = _Judge(ca, cb, AlignOptions())
    judge.prepare()
    top = max(pool, key=lambda h: judge.weighed(h.transform))
    assert corner_error(top.transform, truth, cb.shape) < 10


def test_a_pose_a_few_pixels_off_scores_as_the_truth_within_the_tolerant_walls():
    """:meth:`_Judge.tolerant` counts walls within 8 px: a pose 5 px off the truth, whose
    walls agree on little more than half at the scorer's tolerance (those parallel to the
    shift), agrees there about as well as the truth, which a wider tolerance cannot lower."""
    from gridmerge.align import AlignOptions, _Judge, full_to_crop, working_maps

    a, b, truth = samples.robot_pair(1)
    ca, oa, cb, ob = working_maps(a, b)
    at = SimilarityTransform(full_to_crop(SimilarityTransform(truth), oa, ob).params)
    off = SimilarityTransform(translation=(5.0, 0.0)) @ at
    judge = _Judge(ca, cb, AlignOptions())
    judge.prepare()
    assert judge.quick(at) > 0.9 and judge.tolerant(at) >= judge.quick(at)
    assert judge.quick(off) < 0.7 * judge.quick(at)
    assert judge.tolerant(off) > 0.9 * judge.tolerant(at)
    assert judge.tolerant(off, weighed=True) > judge.weighed(off)


@pytest.mark.shared
def test_a_peak_the_walls_rank_low_unrefined_is_refined_when_its_walls_lie_near(shared_data):
    """Fresh simulated seed 7, pair 55 (two robots in the Willow Garage map, 197 wall
    cells of the source seen by both, b's cells 1.4 times a's, 12 % noise): among the
    overlap-seeking correlation's peaks one lies 7 px from the truth, but unrefined its
    thin, noisy walls agree on 9 %, sixth of 27 candidates, and the three refined were
    others: the pair was declined. Its walls lie within 8 px of the other map's: refined
    as one of the two more that so rank best, it is the truth, merged within 2 px."""
    from gridmerge.bench import datasets

    case = datasets.simulated(n=60, seed=7, data_dir=shared_data)[55]
    r = align(case.a, case.b, rng=0)
    assert r.success, r.message
    assert corner_error(r.transform, case.truth, case.b.shape) < 2.0
    assert r.details["source"].endswith("(ranked by its walls within 8 px)")


@pytest.mark.shared
def test_the_wall_led_search_judges_the_correlations_best_peaks_first(shared_data, monkeypatch):
    """Simulated seed 2, pair 18 (a corridor of E5_03, 35 wall cells seen by both): merged
    from a peak among the correlation's best, which the walls, unrefined, rank below
    others; judged together with the walls' best peaks from the start, it was not
    refined and the pair was declined. (With isolated hits made unknown, since the
    fifty-fourth session, it is merged 3.9 px off: checked on the maps it was made for.)
    The search's pose is 0.7 px off; moved halfway to its polish on the raw walls
    (sixtieth session), 2.1 px: one of the few poses that step puts past 2 px."""
    from gridmerge.bench import datasets

    _isolated_hits_freed(monkeypatch)
    case = datasets.simulated(n=60, seed=2, data_dir=shared_data)[18]
    r = align(case.a, case.b, rng=0)
    assert r.success and corner_error(r.transform, case.truth, case.b.shape) < 3.0
    assert r.details["source"].startswith("walls (wall-led") and "ranked by the walls" not in r.details["source"]


def test_the_wall_led_search_takes_the_correlations_own_best_peaks_from_its_pool():
    """``_best_peaks`` of the wall-led search's pool (12 peaks per rotation) gives the
    correlation's own candidates (3 peaks per rotation, 20 best), in order."""
    from gridmerge.align import _WALL_LED_FINE_DEG, _best_peaks, working_maps
    from gridmerge.correlate import correlation_hypotheses, rotation_candidates

    a, b, _ = samples.robot_pair(1)
    ca, _, cb, _ = working_maps(a, b)
    kw = dict(scales=[cb.resolution / ca.resolution], rotations=rotation_candidates(ca, cb), fine_deg=_WALL_LED_FINE_DEG)
    own = correlation_hypotheses(ca, cb, **kw)
    pool = correlation_hypotheses(ca, cb, **kw, peaks=12, max_hypotheses=1000)
    assert len(pool) > 2 * len(own) and len(own) == 20
    best = _best_peaks(pool, 3, 20)
    assert [h.score for h in best] == [h.score for h in own]
    assert all(np.allclose(h.transform.params, g.transform.params) for h, g in zip(best, own))
    assert len(_best_peaks(pool, 1, 100)) == len({h.rotation_deg for h in pool})


def test_a_pose_off_the_resolutions_scale_is_brought_back_to_it():
    """A pose 2.5 % off the maps' resolution ratio in scale (about the shared part, which
    stays nearly in place): brought to the ratio and refined, it is the truth again. Not
    for a pose already within half a percent, nor when the resolutions are not trusted."""
    from gridmerge.align import ANY_SCALE, AlignOptions, _Judge

    a, b, truth = samples.robot_pair(1)
    judge = _Judge(a, b, AlignOptions())
    judge.prepare()
    p, on = judge._shared_part(SimilarityTransform(truth))
    centre = p[on].mean(axis=0)
    grow = SimilarityTransform(translation=centre) @ SimilarityTransform(scale=1.025) @ SimilarityTransform(translation=-centre)
    off = SimilarityTransform(grow.params @ truth)
    assert corner_error(off, truth, b.shape) > 5
    (found,) = judge.rescaled(off)
    assert abs(found.scale - b.resolution / a.resolution) < 0.002 * found.scale
    assert corner_error(found, truth, b.shape) < 1.0 and judge.quick(found) > judge.quick(off)
    assert judge.rescaled(SimilarityTransform(truth)) == []
    trusting_nothing = _Judge(a, b, replace(AlignOptions(), **ANY_SCALE))
    trusting_nothing.prepare()
    assert trusting_nothing.rescaled(off) == []


def test_a_rescaled_pose_is_judged_when_it_removes_a_third_of_the_disagreement():
    """HM3D seed 28's pair 32 (forty-sixth session): the pose 4.5 % off in scale agrees on
    0.797 (quick score), brought to the ratio 0.871, a third of the disagreement removed
    (36 %), not half: it is judged with the candidates now. Nudged poses still need half."""
    from gridmerge.align import _NUDGE_HALVES, _RESCALE_GAIN, _removes_disagreement

    assert _removes_disagreement(0.871, 0.797, _RESCALE_GAIN)
    assert not _removes_disagreement(0.871, 0.797, _NUDGE_HALVES)
    assert not _removes_disagreement(0.551, 0.485, _RESCALE_GAIN)  # Halmstad E5_10-E5_11: 13 %
    assert _removes_disagreement(0.9, 0.8, _NUDGE_HALVES) and not _removes_disagreement(0.89, 0.8, _NUDGE_HALVES)


@pytest.mark.shared
def test_a_keypoint_pose_stopped_at_a_wrong_scale_is_merged_at_the_resolutions_scale(shared_data):
    """Simulated seed 6, pair 46 (two robots in Halmstad E5_05, b at 1.2 times a's cell
    size): the winning keypoint pose, refined, kept a scale 2.3 % off the maps' ratio,
    its walls agreeing on 76 %; merged 15.5 px off at b's corners (wrong) until the pose
    was also judged brought to the ratio (0.5 px, walls 99 %)."""
    from gridmerge.bench import datasets

    case = datasets.simulated(n=60, seed=6, data_dir=shared_data)[46]
    r = align(case.a, case.b, rng=0)
    assert r.success and corner_error(r.transform, case.truth, case.b.shape) < 2.0
    assert "resolutions' scale" in r.details["source"]


@pytest.mark.shared
def test_a_pose_the_keypoints_settle_off_the_resolutions_scale_is_brought_to_it(shared_data):
    """Fresh simulated seed 38, pair 23 (Halmstad E5_04, b's cells 0.83 of a's, 5 % noise):
    the keypoints settled a pose 2.2 % off the maps' ratio in scale, walls agreeing on 86 %
    (quick score), 15.4 px off at b's corners (wrong), before the full search's check of
    the scale could run. Settled poses are now judged brought to the ratio too: 0.7 px,
    and still settled by the keypoints."""
    from gridmerge.bench import datasets

    case = datasets.simulated(n=60, seed=38, data_dir=shared_data)[23]
    r = align(case.a, case.b, rng=0)
    assert r.success and corner_error(r.transform, case.truth, case.b.shape) < 2.0
    assert r.details["source"] == "keypoints (at the resolutions' scale)"
    assert r.details["walls"] == "skipped: the keypoints settled the pose"


def test_a_pose_turned_a_few_degrees_about_the_shared_part_is_found_again():
    """The wall-led search's candidates come from a few rotations; before its pose is
    taken, the same merge turned by 2 and 4 degrees about the shared part is refined
    too: from a pose 4 degrees off, one of them is the truth again."""
    from gridmerge.align import AlignOptions, _Judge

    a, b, truth = samples.robot_pair(0)
    judge = _Judge(a, b, AlignOptions())
    judge.prepare()
    p, on = judge._shared_part(SimilarityTransform(truth))
    cx, cy = p[on].mean(axis=0)
    off = SimilarityTransform(_turn_about((cx, cy), 4.0).params @ truth)
    assert corner_error(off, truth, b.shape) > 20
    found = judge.turned(off)
    assert len(found) == 4
    assert min(corner_error(t, truth, b.shape) for t in found) < 1.0


def _e5_pair(shared_data, a_name: str, b_name: str):
    """``(annotation, a, b)`` of an annotated Halmstad E5 sensor pair."""
    pairs = json.loads((shared_data / "halmstad" / "E5_pairs.json").read_text())["pairs"]
    pair = next(p for p in pairs if (p["a"], p["b"]) == (a_name, b_name))
    e5 = shared_data / "halmstad" / "E5"
    return pair, gridmerge.load_map(e5 / f"{a_name}.png"), gridmerge.load_map(e5 / f"{b_name}.png")


def _within_protocol(t, pair) -> bool:
    """The data set's protocol: the annotated points' median distance within max(20 px,
    twice the hand fit's residual)."""
    err = np.median(np.hypot(*(t(np.array(pair["points_b"])) - np.array(pair["points_a"])).T))
    return bool(err <= max(20.0, 2 * pair["fit_median_residual_px"]))


@pytest.mark.shared
@pytest.mark.parametrize("a_name, b_name", [("E5_08", "E5_12"), ("E5_01", "E5_12")])
def test_real_maps_that_bend_are_merged_on_the_keypoint_matches_evidence(shared_data, monkeypatch, a_name, b_name):
    """Two Tango maps of the E5 office that bend against each other: at the right pose
    their walls agree on only 38-41 % (chance poses between buildings reach 56 %) and
    repeated corridors score nearly as well, so the maps' structure alone declines them.
    Their keypoint matches agree with the pose far beyond chance (significance 6.8 and
    12.5, against at most 3 for maps of different places): merged, within the data set's
    protocol; declined without that evidence."""
    import importlib

    align_module = importlib.import_module("gridmerge.align")
    pair, a, b = _e5_pair(shared_data, a_name, b_name)
    r = align(a, b, rng=0)
    assert r.success, r.message
    assert r.details["confirmed_by"].startswith("the keypoint matches")
    assert r.details["keypoint_evidence"]["significance"] > 5.0
    assert "confirmed by the keypoint matches" in r.message
    assert _within_protocol(r.transform, pair)
    monkeypatch.setattr(align_module, "_matched", lambda *args: None)
    # (E5_01 - E5_12 is also merged on its structure alone, at 0.56, by the second look's
    # pose: declined without the evidence when there is no second look.)
    assert not align(a, b, rng=0, second_look=0).success


def test_the_judge_remembers_which_beaten_candidates_are_the_same_merge():
    # Of the candidates a decision beat, the same merge slid 15 px (it moves b's shared
    # part less than a rival must) is offered; a pose 100 px away is a rival and is not.
    from gridmerge.align import AlignOptions, _Judge

    a, b, truth = samples.robot_pair(0, scale=1.0, rotation_deg=40)
    truth = SimilarityTransform(truth)
    near = SimilarityTransform(translation=(15.0, 0.0)) @ truth
    far = SimilarityTransform(translation=(0.0, 100.0)) @ truth
    judge = _Judge(a, b, AlignOptions(refine=False))
    judge.prepare()
    _, best, kind, _, _ = judge.decide([(far, "walls"), (near, "walls (near)"), (truth, "keypoints")])
    assert best is truth and kind == "keypoints"
    assert judge.rival(truth, far) and not judge.rival(truth, near)
    assert judge.same_merge(truth) == [(near, "walls (near)")]
    assert judge.same_merge(near) == []  # not a pose any decision chose


@pytest.mark.shared
def test_real_maps_that_bend_are_merged_at_the_same_merges_pose_the_matches_support(shared_data, monkeypatch):
    """Halmstad E5_12-E5_14: the walls' best pose (a second-look pose) agrees with 5
    places of the keypoint matches, too few to confirm it; the same merge fitted to
    another part of the bending maps, 43 px from it at b's shared part and with walls
    agreeing nearly as well, agrees with 7 (significance 7.1): merged at that pose,
    within the data set's protocol. Without looking at the same merge's other poses,
    declined (by this search: the coarser look's keypoints find the pair too)."""
    pair, a, b = _e5_pair(shared_data, "E5_12", "E5_14")
    r = align(a, b, rng=0)
    assert r.success, r.message
    assert r.details["same_merge"]["instead_of"] == "keypoints (second look)"
    assert r.details["keypoint_evidence"]["significance"] > r.details["same_merge"]["keypoint_evidence"]["significance"]
    assert _within_protocol(r.transform, pair)
    monkeypatch.setattr(importlib.import_module("gridmerge.align")._Judge, "same_merge", lambda self, best: [])
    assert not align(a, b, rng=0, coarse_look=0).success


def test_a_refined_pose_is_polished_onto_the_walls_at_the_maps_scale_only(monkeypatch):
    from gridmerge.align import AlignOptions, _Judge
    from gridmerge.refine import WallICP

    a, b, truth = samples.robot_pair(0, scale=1.0, rotation_deg=40)
    truth = SimilarityTransform(truth)
    judge = _Judge(a, b, AlignOptions())
    judge.prepare()
    off = SimilarityTransform(rotation=truth.rotation + 0.004, scale=truth.scale, translation=truth.translation + [5.0, -4.0])
    value, polished = judge.polished(off, judge.quick)
    assert corner_error(polished, truth, b.shape) < 0.5 < 5.0 < corner_error(off, truth, b.shape)
    assert value == judge.quick(polished) > 1.1 * judge.quick(off)
    # Walls that already agree within the tolerance gain too little to move it.
    near = SimilarityTransform(rotation=truth.rotation + 0.004, scale=truth.scale, translation=truth.translation + [2.5, -2.0])
    assert judge.polished(near, judge.quick)[1] is near
    # A pose whose scale is 7 % off the maps' resolution ratio is not polished, unless
    # the resolutions are not trusted (--any-scale).
    calls = []
    monkeypatch.setattr(WallICP, "polish", lambda self, t, **kw: calls.append(t) or t)
    scaled = SimilarityTransform(rotation=truth.rotation, scale=truth.scale * 1.07, translation=truth.translation)
    assert judge.polished(scaled, judge.quick) == (judge.quick(scaled), scaled) and not calls
    anyscale = _Judge(a, b, AlignOptions(max_scale_disagreement=None))
    anyscale.prepare()
    assert anyscale.polished(scaled, anyscale.quick)[1] is scaled and len(calls) == 1
    monkeypatch.undo()
    # A pose already where the walls are is kept: the refinement's is the more precise.
    assert judge.polished(truth, judge.quick)[1] is truth


def test_a_taken_pose_is_polished_in_the_other_maps_frame():
    # The pose a search takes is polished once more in the frame of the map that was not
    # its reference (b's for a's search, a's for b's), when that raises the walls'
    # agreement there and lowers it nowhere; declined and keypoint-settled poses are not.
    from gridmerge.align import AlignOptions, Estimate, _Judge, _polished_across

    a, b, truth = samples.robot_pair(0, scale=0.6, rotation_deg=40)
    truth = SimilarityTransform(truth)
    judge = _Judge(a, b, AlignOptions())
    off = SimilarityTransform(rotation=truth.rotation + 0.004, scale=truth.scale, translation=truth.translation + [4.0, -3.0])
    none = np.zeros((0, 2))

    def estimate(t, confidence=1.0, j=judge, **details):
        return Estimate(t, np.zeros(0, bool), none, none, details=details, confidence=confidence, verification=j._verify(t))

    out = _polished_across(estimate(off), judge, reverse=False)
    assert corner_error(out.transform, truth, b.shape) < 1.0 < 4.0 < corner_error(off, truth, b.shape)
    moved, walls = out.details["polished_across"]["moved_px"], out.details["polished_across"]["walls"]
    assert 4.0 < moved < 8.0 and walls[1] >= walls[0] and walls[3] > 1.1 * walls[2]
    assert out.verification.wall_agreement == pytest.approx(judge._verify(out.transform).wall_agreement)
    # From b's side: the pose it found (a -> b) is polished in a's frame; b -> a comes back.
    other = _Judge(b, a, AlignOptions())
    rev = _polished_across(estimate(off.inverse, j=other), other, reverse=True)
    assert corner_error(rev.transform.inverse, truth, b.shape) < 1.0
    for kept in (estimate(off, confidence=0.3), estimate(off, walls="skipped: the keypoints settled the pose"),
                 estimate(truth)):
        assert _polished_across(kept, judge, reverse=False) is kept


def test_a_taken_pose_whose_walls_agree_is_polished_in_its_searchs_frame(monkeypatch):
    # A taken pose 2 px off whose walls agree on 73-84 % (the search's polish gains too
    # little to move it) is polished in its own search's frame: onto the truth. Not
    # farther than _FINISH_REACH, not when its walls agree on less than _FINISH_WALLS,
    # and never a declined pose or one the keypoints settled.
    import importlib

    from gridmerge.align import AlignOptions, Estimate, _Judge, _polished_home

    a, b, truth = samples.robot_pair(0, scale=1.0, rotation_deg=40)
    truth = SimilarityTransform(truth)
    judge = _Judge(a, b, AlignOptions())
    none = np.zeros((0, 2))

    def estimate(t, confidence=1.0, **details):
        return Estimate(t, np.zeros(0, bool), none, none, details=details, confidence=confidence, verification=judge._verify(t))

    for off in ([1.5, -1.0], [2.0, 1.0]):
        t = SimilarityTransform(rotation=truth.rotation + 0.002, scale=truth.scale, translation=truth.translation + off)
        assert 1.5 < corner_error(t, truth, b.shape) < 3.0
        for reverse in (False, True):  # searched from a's side, or from b's (polished in b's frame)
            out = _polished_home(estimate(t), judge, reverse=reverse)
            assert corner_error(out.transform, truth, b.shape) < 0.1
            home = out.details["polished_home"]
            assert 1.5 < home["moved_px"] < 3.0 and home["walls"][1] > 0.95 > home["walls"][0]
            assert out.verification.wall_agreement == pytest.approx(home["walls"][1], abs=1e-4)
    far = SimilarityTransform(rotation=truth.rotation + 0.002, scale=truth.scale, translation=truth.translation + [4.0, -3.0])
    near = SimilarityTransform(rotation=truth.rotation + 0.002, scale=truth.scale, translation=truth.translation + [1.5, -1.0])
    for kept in (estimate(far), estimate(near, confidence=0.3), estimate(near, walls="skipped: the keypoints settled the pose")):
        assert _polished_home(kept, judge, reverse=False) is kept
    monkeypatch.setattr(importlib.import_module("gridmerge.align"), "_FINISH_WALLS", 0.9)
    kept = estimate(near)
    assert _polished_home(kept, judge, reverse=False) is kept


@pytest.mark.shared
def test_a_pose_found_from_b_side_is_precise_in_either_order(shared_data):
    # Simulated pair 40 of seed 2 (Willow Garage, hard tier: b at 0.66 of a's cell size,
    # 12 % noise, 23 % overlap): found from b's side, which a's search confirms. With
    # point-to-point ICP it was 8 px off, a's walls agreeing on 26 % (at 2 px), until
    # polished in a's frame (seventeenth session); the search's own polish, pairs that
    # face the same way fitted point to plane, now puts it within 1 px. Either order of
    # the maps gives the same pose. (With OpenCV 5.1's warps, whose bilinear weights
    # differ from 5.0's in the last bits, the first side's wall-led search finds it
    # clearly by itself; when it does not, the other side's pose must be the one taken.)
    from gridmerge.align import AlignOptions
    from gridmerge.bench import datasets

    case = datasets.simulated(n=60, seed=2, data_dir=shared_data, see_through=2)[40]
    r = align(case.a, case.b, rng=0)
    assert r.success, r.message
    other = r.details.get("other_side")
    if other is None:  # settled from the first side: only a confident pose skips the other
        assert r.confidence >= AlignOptions().one_sided_confidence
    else:
        assert other["taken"]
    assert corner_error(r.transform, case.truth, case.b.shape) < 1.0
    s = align(case.b, case.a, rng=0)
    assert s.confidence == r.confidence
    assert np.allclose(s.transform.inverse.params, r.transform.params, atol=1e-6)


def _coarse_field_refinement(monkeypatch):
    """``align``'s refinements with the first map as the field at every level, as before
    the twenty-sixth session (``refine_direct``'s ``reference="a"``): on the pairs below
    they stop a few pixels off, which the polish on the walls was made for (the finer
    map's field now brings them within 1-2 px by itself)."""
    mod = importlib.import_module("gridmerge.align")
    refine = mod.refine_direct
    monkeypatch.setattr(mod, "refine_direct", lambda a, b, t, **kw: refine(a, b, t, **{**kw, "reference": "a"}))


def _isolated_hits_freed(monkeypatch):
    """``align``'s working maps with their isolated hits made free, as before the
    fifty-fourth session (they are made unknown now, :func:`gridmerge.verify.despeckle`).
    Freed, a wall seen sparsely put free space where the other map has its wall, and the
    true pose's walls agreed less: the pairs below needed the rules they show then, and
    several no longer do (docs/benchmarks.md, fifty-fourth session). The checks keep the
    maps the rules were made for."""
    mod = importlib.import_module("gridmerge.align")
    unknown = mod.despeckle

    def freed(grid):
        out = unknown(grid)
        if out is grid:
            return grid
        return grid.replace(data=np.where(np.isnan(out.data) & ~np.isnan(grid.data), 0.0, out.data))

    monkeypatch.setattr(mod, "despeckle", freed)


@pytest.mark.shared
def test_polishing_on_the_walls_merges_a_noisy_pair_at_another_resolution(shared_data, monkeypatch):
    # Simulated pair 2 of seed 1 (hard tier: b at 0.7 of a's cell size, 12 % spurious and
    # missed hits, 25 % overlap), searched from a's side: with a's field at every level
    # the refinement of the right candidate stops 3 px off, where the thin walls agree
    # on 22 %; polished on the walls, 0.5 px. (By default b, the larger map, is the
    # reference, and from its side the right pose is not found: the pair is declined.)
    from gridmerge.bench import datasets

    _coarse_field_refinement(monkeypatch)
    case = datasets.simulated(n=60, seed=1, data_dir=shared_data, see_through=0)[2]
    r = align(case.a, case.b, rng=0, search_from="a")
    assert r.success, r.message
    assert corner_error(r.transform, case.truth, case.b.shape) < 2.0
    monkeypatch.setattr(importlib.import_module("gridmerge.align")._Judge, "polished", lambda self, t, score: (score(t), t))
    assert not align(case.a, case.b, rng=0, search_from="a").success


@pytest.mark.shared
def test_a_wall_led_pose_is_judged_by_its_walls_as_polished(shared_data, monkeypatch):
    # Simulated pair 55 of seed 5 (hard tier: b's cells 1.38 times a's, 12 % spurious and
    # missed hits, 30 % overlap), searched from b's side (its known area is larger): the
    # wall-led search refines its right pose to 3 px off, where the thin walls agree on
    # 73 %, less than a settled pose needs (75 %); polished by ICP on the walls it lies
    # 0.2 px off and they agree on 87 %, but the polish gains too little on the scorer's
    # sample (5 %) to replace the refined pose. The settled test takes the walls as
    # polished: the pose is merged, and polished once taken. Judged on the refined
    # pose's walls, the pair is declined (also after the coarser look, which the check
    # leaves out for time). (With the finer map's field at the refinement's last level
    # the refined pose itself is settled; the check keeps the refinement it was made for.
    # Measured again in full with its rivals, the pose is polished too and settled: the
    # check leaves that second measure out. With isolated hits made unknown, since the
    # fifty-fourth session, the refined pose's walls settle it: checked on the maps with
    # those hits freed.)
    from gridmerge.bench import datasets

    _coarse_field_refinement(monkeypatch)
    _isolated_hits_freed(monkeypatch)
    case = datasets.simulated(n=60, seed=5, data_dir=shared_data)[55]
    r = align(case.a, case.b, rng=0)
    assert r.success, r.message
    assert corner_error(r.transform, case.truth, case.b.shape) < 2.0
    judge = importlib.import_module("gridmerge.align")._Judge
    monkeypatch.setattr(judge, "in_full", lambda self, best, ratio: (0.0, best, 1.0))
    assert align(case.a, case.b, rng=0, coarse_look=0).success  # the polished walls alone settle it
    monkeypatch.setattr(judge, "polished_wall", lambda self, t: 0.0)
    # (From the first side alone: since the thirty-third session the other side's sure
    # pose is taken when the first side finds no fit, and that search finds it too.)
    assert not align(case.a, case.b, rng=0, coarse_look=0, one_sided_confidence=None).success


@pytest.mark.shared
def test_a_wall_led_winner_and_its_rivals_are_measured_in_full(shared_data, monkeypatch):
    # Simulated pair 2 of seed 4 (hard tier: b's cells 1.9 times a's, noisy, 47 wall cells
    # seen by both robots), searched from b's side: on the scorer's sample, which weighs
    # a pose by the part of the maps it shares, a pose sharing 40 % of the smaller map
    # wins (walls agreeing on 53 %) and the right one, sharing 24 % (77 % polished),
    # comes close: neither is clear. Measured again in full, the right pose is the
    # winner, clear of every other, and merged. Without that second measure the pair is
    # declined (the coarser look, left out for time, declines it too).
    from gridmerge.bench import datasets

    case = datasets.simulated(n=60, seed=4, data_dir=shared_data)[2]
    r = align(case.a, case.b, rng=0)
    assert r.success, r.message
    assert r.details.get("measured_in_full")
    assert corner_error(r.transform, case.truth, case.b.shape) < 3.0
    monkeypatch.setattr(importlib.import_module("gridmerge.align")._Judge, "in_full", lambda self, best, ratio: (0.0, best, 1.0))
    assert not align(case.a, case.b, rng=0, coarse_look=0).success


@pytest.mark.shared
def test_polishing_on_the_walls_merges_real_maps_that_bend(shared_data, monkeypatch):
    # Halmstad E5_06-E5_09: Tango maps that bend against each other. Refined on the
    # smoothed cells, the right pose's walls agree on 40 % and a clearly different pose
    # scores nearly as well (confidence 0.31); polished on the walls, it is merged within
    # the data set's protocol. (Searched from E5_09's side too, the same merge is found
    # even unpolished: the polish is judged from E5_06's side alone.)
    pair, a, b = _e5_pair(shared_data, "E5_06", "E5_09")
    r = align(a, b, rng=0, one_sided_confidence=None)
    assert r.success, r.message
    assert _within_protocol(r.transform, pair)
    assert _within_protocol(align(a, b, rng=0).transform, pair)
    monkeypatch.setattr(importlib.import_module("gridmerge.align")._Judge, "polished", lambda self, t, score: (score(t), t))
    assert not align(a, b, rng=0, one_sided_confidence=None, coarse_look=0).success


def test_polishing_does_not_slide_a_chance_pose_into_a_merge(monkeypatch):
    # Robots 6 and 7 of the simulated fleet of 8 (seed 0), a procedural building whose
    # rooms repeat: ICP slides a chance pose 15 px, to walls that agree on 47 % instead
    # of 37 %, enough for confidence 0.59 and a merge 1100 px off. Polishing stops at a
    # refinement's reach. (The search from robot 7's side finds another pose, 157 px
    # away: the slid pose would be one-sided, and declined as such too.)
    from gridmerge.bench.fleet import simulate_fleet

    align_module = importlib.import_module("gridmerge.align")
    fleet = simulate_fleet(8, 0)
    a, b = fleet.maps[5], fleet.maps[6]
    assert not align(a, b, rng=0).success
    monkeypatch.setattr(align_module, "_POLISH_REACH", 30.0)
    r = align(a, b, rng=0, search_from="a", one_sided_confidence=None, max_crossing=None, unsure_walls=None)
    assert r.success and corner_error(r.transform, fleet.relative(5, 6), b.shape) > 100
    r = align(a, b, rng=0, search_from="a", max_crossing=None, unsure_walls=None)
    assert not r.success and "found from one map's side only" in r.message
    # The slid pose's walls cross robot 6's rooms too (38 % of 2397 cells, as measured with
    # isolated hits freed).
    r = align(a, b, rng=0, search_from="a", one_sided_confidence=None, unsure_walls=None)
    assert not r.success and "stand inside the other map's open space" in r.message
    # And at confidence 0.55 it rests on 2367 wall cells (2397 with isolated hits freed),
    # not a building's.
    r = align(a, b, rng=0, search_from="a", one_sided_confidence=None, max_crossing=None)
    assert not r.success and "on 2367 overlap wall cells; below 0.8" in r.message


def _one_side(transform, confidence, source="walls"):
    from gridmerge.align import Estimate

    empty = np.zeros((0, 2))
    return Estimate(transform, np.zeros(0, bool), empty, empty, details={"source": source, "runner_up_ratio": 0.5},
                    confidence=confidence)


@pytest.mark.parametrize("other_conf, other_far, expect", [
    (0.9, False, "theirs"),  # the same merge, surer from b's side: its pose and confidence
    (0.3, False, "ours"),  # the same merge, less sure from b's side
    (0.9, True, "one-sided"),  # another pose from b's side, however sure
    (None, None, "one-sided"),  # nothing from b's side
])
def test_a_pose_below_the_one_sided_confidence_is_sought_from_both_sides(monkeypatch, other_conf, other_far, expect):
    """Below ``one_sided_confidence`` the search runs again with b as the reference. The
    same merge from both sides (within 40 px on the shared part) takes the more confident
    side's pose; another pose, or none, leaves the pose one-sided: declined, saying why."""
    align_module = importlib.import_module("gridmerge.align")
    a, b, truth = samples.table1_pair(0)
    ours = SimilarityTransform(truth)
    shift = 60.0 if other_far else 5.0
    theirs = SimilarityTransform(translation=(shift, 0.0)) @ ours
    calls = []

    def search(judge, fa, fb, second=None):
        calls.append(judge.a is a)
        if judge.a is a:
            return _one_side(ours, 0.6)
        if other_conf is None:
            return _one_side(None, 0.0)
        return _one_side(SimilarityTransform(np.linalg.inv(theirs.params)), other_conf, "keypoints")

    monkeypatch.setattr(align_module, "_hybrid_search", search)
    opts = align_module.AlignOptions()
    fa = fb = Features.empty()
    est = align_module._both_sides(a, b, fa, fb, opts, np.random.default_rng(0), None)
    assert calls == [True, False]
    if expect == "theirs":
        # b's side's pose, 5 px off the walls, then polished in a's frame (the frame its
        # search did not take as reference) onto them.
        assert est.confidence == 0.9 and est.details["polished_across"]["moved_px"] == pytest.approx(5.0, abs=1.0)
        assert corner_error(est.transform, truth, b.shape) < 1.0 < 4.0 < corner_error(theirs, truth, b.shape)
        assert est.details["source"] == "keypoints" and est.details["other_side"]["taken"] and not est.one_sided
        assert est.details["other_side"]["confidence"] == 0.9 and est.details["first_side"] == {"confidence": 0.6, "source": "walls"}
        assert est.verification is not None
    elif expect == "ours":
        assert est.confidence == 0.6 and est.transform is ours and not est.one_sided
        assert est.details["other_side"]["same_pose"] and est.details["other_side"]["moved_px"] == pytest.approx(5.0, abs=0.5)
    else:
        assert est.transform is ours and est.confidence == 0.6
        assert est.one_sided.startswith("declined: found from one map's side only") and "needs confidence 0.8" in est.one_sided
        assert ("no pose" in est.one_sided) == (other_conf is None)
    # Sure enough from one side, or asked to search from a's side only: one search.
    calls.clear()
    assert align_module._both_sides(a, b, fa, fb, replace_opts(opts, one_sided_confidence=0.55), np.random.default_rng(0), None) is not None
    assert calls == [True]
    calls.clear()
    est = align_module._both_sides(a, b, fa, fb, replace_opts(opts, one_sided_confidence=None), np.random.default_rng(0), None)
    assert calls == [True] and not est.one_sided


@pytest.mark.parametrize("a_side", ["no fit", "declined on its merits", "a rival fit", "unsure"])
def test_a_sure_pose_of_the_second_side_is_taken_when_the_first_found_no_fit(monkeypatch, a_side):
    """A's side declines; b's side finds a pose at 0.9, 300 px from a's best.
    "no fit": a's best lies where nothing agrees (walls under half of the truth's share),
    b's side's pose is the Table I one: taken, polished, with a's side's best recorded.
    "declined on its merits": the same at a confidence of 0.6 for a's best, whose walls
    fail the wall floor: a's side declines as well, and b's side's pose is taken. "a
    rival fit": a's best is the truth itself, declined at 0.3 (as ambiguous), and b's
    side's pose is the chance one: it clearly beats nothing, so a one-sided decline, as
    before. "unsure": a's side gave the truth 0.6, above ``min_confidence``, a pose it
    would take: two different poses, one-sided."""
    align_module = importlib.import_module("gridmerge.align")
    a, b, truth = samples.table1_pair(0)
    right = SimilarityTransform(truth)
    far = SimilarityTransform(translation=(300.0, 40.0)) @ right
    ours, theirs, own = {"no fit": (far, right, 0.0), "declined on its merits": (far, right, 0.6),
                         "a rival fit": (right, far, 0.3), "unsure": (right, far, 0.6)}[a_side]

    def search(judge, fa, fb, second=None):
        judge.prepare()  # as the search does first
        if judge.a is a:
            return _one_side(ours, own)
        return _one_side(SimilarityTransform(np.linalg.inv(theirs.params)), 0.9)

    monkeypatch.setattr(align_module, "_hybrid_search", search)
    est = align_module._both_sides(a, b, Features.empty(), Features.empty(), align_module.AlignOptions(), None)
    side = est.details["other_side"]
    assert not side["same_pose"] and side["moved_px"] > 100
    if ours is far:
        assert side["taken"] and est.confidence == 0.9 and not est.one_sided
        assert corner_error(est.transform, truth, b.shape) < 1.0
        first = est.details["first_side"]
        assert first["confidence"] == own and first["wall_agreement"] <= 0.5 * est.verification.wall_agreement
    else:
        assert not side.get("taken") and est.transform is ours and est.confidence == own
        assert est.one_sided.startswith("declined: found from one map's side only (from the other's the search finds a pose")


@pytest.mark.parametrize("b_share", [0.10, 0.60])
def test_a_first_side_pose_one_map_s_walls_deny_is_no_rival(monkeypatch, b_share):
    """A's side declines with a best pose whose walls agree on 52.5 % as a mean: 95 % of
    a's walls in the overlap on b's, and ``b_share`` of b's on a's. B's side finds the
    Table I pose at 0.9 (walls about 95 %), which is not twice 52.5 %. With b's share at
    10 %, under ``min_wall_share`` (15 %), b's walls mostly cross a's free space at a's
    best: it is no fit, measured as a rival by that share, and b's side's pose is taken
    (``first_side["rival_crossed"]``). With 60 % it is a rival fit and the pose stays
    one-sided."""
    from gridmerge.verify import Verification

    align_module = importlib.import_module("gridmerge.align")
    a, b, truth = samples.table1_pair(0)
    right = SimilarityTransform(truth)
    far = SimilarityTransform(translation=(300.0, 40.0)) @ right
    walls_b = 700
    matched_b = round(b_share * walls_b)
    matched_a = round((2 * 0.525 - matched_b / walls_b) * 100)
    crossing = Verification(0.98, 10_000, 200, (matched_a / 100 + matched_b / walls_b) / 2, 10_200, 0.5,
                            walls_a=100, walls_b=walls_b, matched_a=matched_a, matched_b=matched_b)

    def search(judge, fa, fb, second=None):
        judge.prepare()
        if judge.a is a:
            est = _one_side(far, 0.0)
            est.verification = crossing
            return est
        return _one_side(SimilarityTransform(np.linalg.inv(right.params)), 0.9)

    monkeypatch.setattr(align_module, "_hybrid_search", search)
    est = align_module._both_sides(a, b, Features.empty(), Features.empty(), align_module.AlignOptions(), None)
    side = est.details["other_side"]
    assert crossing.wall_agreement == pytest.approx(0.525, abs=0.01)
    assert est.verification is crossing or est.verification.wall_agreement > 0.9
    if b_share < 0.15:
        assert side["taken"] and not est.one_sided and est.confidence == 0.9
        assert corner_error(est.transform, truth, b.shape) < 1.0
        assert est.details["first_side"]["rival_crossed"] and est.details["first_side"]["wall_agreement"] == pytest.approx(0.525, abs=0.01)
    else:
        assert not side.get("taken") and est.transform is far and est.one_sided


def replace_opts(opts, **kw):
    import dataclasses

    return dataclasses.replace(opts, **kw)


@pytest.mark.parametrize("b_side", ["finds it", "finds nothing"])
def test_align_takes_the_surer_side_or_declines_a_one_sided_pose(monkeypatch, b_side):
    """Through ``align``: a's side made unsure of the Table I pose (0.7), b's side finding
    it surely: merged at b's side's confidence; b's side finding nothing: declined, with
    the reason in the message, and the pose kept as the candidate."""
    align_module = importlib.import_module("gridmerge.align")
    a, b, truth = samples.table1_pair(0)
    real = align_module._hybrid_search
    calls = []

    def search(judge, fa, fb, second=None):
        calls.append(judge)
        if len(calls) == 1:  # a's side
            est = real(judge, fa, fb)
            est.confidence = 0.7
            return est
        if b_side == "finds nothing":
            return _one_side(None, 0.0)
        return real(judge, fa, fb)

    monkeypatch.setattr(align_module, "_hybrid_search", search)
    r = align(a, b, rng=0, coarse_look=0)  # one search (from both sides), not the coarser look's
    assert len(calls) == 2 and calls[1].a.shape != calls[0].a.shape  # b's side: b is the reference
    assert corner_error(r.candidate, SimilarityTransform(truth), b.shape) < 1.0
    if b_side == "finds it":
        assert r.success and r.confidence > 0.8 and r.details["other_side"] == {**r.details["other_side"], "taken": True, "same_pose": True}
    else:
        assert not r.success and r.confidence == 0.7
        assert r.message.startswith("declined: found from one map's side only (from the other's the search finds no pose)")
    calls.clear()
    assert align(a, b, rng=0, one_sided_confidence=None).success and len(calls) == 1


@pytest.mark.shared
def test_a_sure_pose_from_the_second_side_alone_is_not_taken(shared_data):
    """E5_01 - HIH_01, an office and an apartment: searched from E5_01's side (the first,
    the larger map's known part) nothing is found; from HIH_01's, the apartment laid into
    the office at confidence 0.99. Taking a pose found surely from the second side alone
    (as one found from the first would be) merged two Halmstad cross-building pairs (0.99,
    0.88) and one pair 21 px off (0.98), for two right poses of simulated pairs and one of
    Halmstad (docs/benchmarks.md, twenty-first session). Such a pose is taken now only when
    it clearly beats the first side's best; here E5_01's best agrees on 44 % of its walls,
    the apartment's pose on 69 %: a rival fit, and the pose stays one-sided."""
    from gridmerge.io import load_map

    folder = shared_data / "halmstad"
    a, b = load_map(folder / "E5" / "E5_01.png"), load_map(folder / "HIH" / "HIH_01.png")
    for r in (align(a, b, rng=0), align(b, a, rng=0)):
        assert not r.success
        side = r.details["other_side"]
        assert side["confidence"] > 0.8 and not side["same_pose"] and not side.get("taken")


@pytest.mark.shared
def test_a_pose_found_only_from_the_second_side_is_taken_when_the_first_finds_no_fit(shared_data):
    """Fresh simulated seed 16, pair 13 (two robots in Halmstad, 53 wall cells of the
    source seen by both, b's cells 0.62 of a's, 12 % noise): from the larger map's side
    the best pose agrees on 18 % of its walls and is declined; from the other side the
    search finds the truth at confidence 1.0. It was declined as one-sided; now b's
    side's pose is merged, within 2 px."""
    from gridmerge.bench import datasets

    case = datasets.simulated(n=60, seed=16, data_dir=shared_data)[13]
    r = align(case.a, case.b, rng=0)
    assert r.success, r.message
    assert corner_error(r.transform, case.truth, case.b.shape) < 2.0
    side, first = r.details["other_side"], r.details["first_side"]
    assert side["taken"] and not side["same_pose"] and first["confidence"] < 0.5
    assert first["wall_agreement"] <= 0.5 * r.verification.wall_agreement


@pytest.mark.shared
def test_a_first_pose_at_twice_the_resolutions_scale_keeps_no_search_from_the_truth(shared_data):
    """Fresh simulated seed 62, pair 20 (two robots in a procedural building, 84 wall
    cells of the source seen by both, b's cells 1.10 times a's): from the larger map's
    side the first search's best pose lays b at twice the resolutions' scale (confidence
    0.69), where 90 % of a's walls in the overlap lie on b's but 14 % of b's on a's; the
    truth agrees on 99 %. It was declined as one-sided; the fifty-sixth session took the
    other side's pose (that side's pose counted as a rival by its 14 %: the stubbed test
    of ``rival_crossed`` above). Since the fifty-ninth session a pose at a scale the
    resolutions rule out ends no search: the larger map's side's wall-led search finds
    the truth itself."""
    from gridmerge.bench import datasets

    case = datasets.simulated(n=60, seed=62, data_dir=shared_data)[20]
    r = align(case.a, case.b, rng=0)
    assert r.success, r.message
    assert corner_error(r.transform, case.truth, case.b.shape) < 2.0
    first = r.details["overlap_seeking"]
    assert first["confidence"] >= 0.5 and first["scale_off"] > 0.9
    assert r.details["source"].startswith("walls (wall-led") and "other_side" not in r.details


@pytest.mark.shared
def test_a_pose_from_the_second_side_alone_needs_walls_enough(shared_data, monkeypatch):
    """Fresh simulated seed 22, pair 12 (two robots in Halmstad, 16 wall cells of the
    source seen by both): from the larger map's side the best pose agrees on 23 % of its
    walls; from the other side a pose 194 px away agrees on 89 %, but over 22 and 11 wall
    cells, and is 24.6 px from the truth. A pose that overrules the first side's search
    must hold at least 40 wall cells of the two maps in the overlap; this one is declined.
    (With isolated hits made unknown, since the fifty-fourth session, the other side's
    best pose is not sure at all: checked on the maps the rule was made for.)"""
    from gridmerge.bench import datasets

    _isolated_hits_freed(monkeypatch)
    case = datasets.simulated(n=60, seed=22, data_dir=shared_data)[12]
    r = align(case.a, case.b, rng=0)
    assert not r.success
    side = r.details["other_side"]
    assert side["confidence"] >= 0.8 and not side["same_pose"] and not side.get("taken")
    assert "first_side" not in r.details


@pytest.mark.shared
def test_two_buildings_fit_from_one_side_only_are_declined(shared_data):
    """HIH_04 - E5_12: the apartment laid into the office's open space at confidence 0.75
    from the apartment's side; from the office's side the best pose lies over 200 px away.
    Declined as one-sided; merged when searched from the apartment's side only. (By
    default the search takes the office, the larger map, as its reference, and its pose
    is declined anyway; in either order, the search being order-free:
    test_swapping_the_maps_inverts_the_transform_and_keeps_the_decision.)"""
    from gridmerge.io import load_map

    folder = shared_data / "halmstad"
    a, b = load_map(folder / "HIH" / "HIH_04.png"), load_map(folder / "E5" / "E5_12.png")
    r = align(a, b, rng=0, search_from="a")
    assert not r.success and "found from one map's side only" in r.message
    assert r.details["other_side"]["moved_px"] > 100 and not r.details["other_side"]["same_pose"]
    assert align(a, b, rng=0, search_from="a", one_sided_confidence=None, unsure_walls=None).success
    # At confidence 0.75 on 9872 overlap wall cells, it is not a building's worth either.
    r = align(a, b, rng=0, search_from="a", one_sided_confidence=None)
    assert not r.success and "on 9872 overlap wall cells; below 0.8" in r.message
    assert not align(a, b, rng=0).success


@pytest.mark.shared
@pytest.mark.parametrize("a_name, b_name", [("E5_06", "E5_13"), ("E5_09", "E5_12")])
def test_real_maps_merged_on_a_pose_the_blurred_maps_keypoints_give(shared_data, a_name, b_name):
    """Two E5 pairs whose right pose none of the grey levels' keypoint matches or wall
    correlations proposes (declined at 0.30 and 0.00): the keypoints of the maps drawn
    blurred propose it, and it wins. Within the protocol; declined without the second look
    (and without the coarser look, whose keypoints find E5_06-E5_13 too).
    Searched from a's side (E5_12 is the larger map of the second pair: from its side,
    by default, the pair is declined)."""
    pair, a, b = _e5_pair(shared_data, a_name, b_name)
    r = align(a, b, rng=0, search_from="a")
    assert r.success, r.message
    assert r.details["source"] == "keypoints (second look)" and r.details["second_look"]["hypotheses"] > 0
    assert _within_protocol(r.transform, pair)
    assert not align(a, b, rng=0, search_from="a", second_look=0, coarse_look=0).success


@pytest.mark.shared
def test_the_second_look_merges_a_simulated_pair_sharing_few_walls(shared_data, monkeypatch):
    # Simulated benchmark pair 8 (seed 0): 50-199 wall cells seen by both robots; the
    # truth's walls agree on 92 %, but no candidate came near it before the second look
    # (without it, the coarser look's search finds it too, and so does the search from
    # the other map's side, whose sure pose is taken: the check searches one side).
    # With isolated hits made unknown (since the fifty-fourth session) the first search
    # finds it too: checked on the maps with those hits freed, as the look was made for.
    from gridmerge.bench import datasets

    _isolated_hits_freed(monkeypatch)
    case = datasets.simulated(n=60, seed=0, data_dir=shared_data, see_through=0)[8]
    r = align(case.a, case.b, rng=0)
    assert r.success and corner_error(r.transform, case.truth, case.b.shape) < 2.0
    assert not align(case.a, case.b, rng=0, second_look=0, coarse_look=0, one_sided_confidence=None).success


@pytest.mark.shared
def test_real_maps_merged_from_the_side_that_finds_them_surely(shared_data, monkeypatch):
    """E5_06 - E5_12: from E5_06's side the right pose's walls agree on 34 % and its
    keypoint matches are weak (declined); from E5_12's side the same pose (2.5 px apart on
    the shared part) is confirmed by its keypoint matches. Merged within the protocol.
    From E5_06's side alone, declined (the coarser look's search finds it too). With
    isolated hits made unknown (since the fifty-fourth session) E5_06's side merges it
    by itself: checked on the maps with those hits freed."""
    _isolated_hits_freed(monkeypatch)
    pair, a, b = _e5_pair(shared_data, "E5_06", "E5_12")
    r = align(a, b, rng=0)
    assert r.success, r.message
    assert r.details["other_side"]["taken"] and r.details["other_side"]["moved_px"] < 10
    assert _within_protocol(r.transform, pair)
    assert not align(a, b, rng=0, one_sided_confidence=None, coarse_look=0).success


def test_the_second_look_is_bounded_whatever_the_first_keypoints_may_use():
    # It only proposes poses: at most 5000 keypoints on at most 400 000 pixels, also when
    # the first keypoints are uncapped (a map of pure noise would otherwise cost seconds).
    from gridmerge.align import AlignOptions, _blurred_extractor

    uncapped = _blurred_extractor(AlignOptions(max_keypoints=0, feature_pixels=0))
    assert (uncapped.max_keypoints, uncapped.work_pixels) == (5000, 400_000)
    tighter = _blurred_extractor(AlignOptions(max_keypoints=300, feature_pixels=100_000))
    assert (tighter.max_keypoints, tighter.work_pixels) == (300, 100_000)
    assert tighter.renderer.blur_sigma == 1.5


@NEGATIVE
def test_a_declined_pair_is_searched_again_with_coarser_keypoints(monkeypatch, negative, negative_declined, negative_first_search):
    # The negative sample pair (two 0.3 M-pixel keypoint images) is declined; the second
    # search, with keypoints detected on at most 200k pixels, is declined too and says so.
    na, nb = negative
    r = negative_declined
    assert not r.success and r.transform is None
    look = r.details["coarse_look"]
    assert look["pixels"] == 200_000 and look["message"].startswith("declined") and 0.0 <= look["confidence"] < 0.5
    # It searched with keypoints of its own, detected on fewer pixels.
    align_module = importlib.import_module("gridmerge.align")
    searched = []
    real = align_module._align

    def spy(a, b, method, opts, *args):
        searched.append(opts)
        return real(a, b, method, opts, *args)

    monkeypatch.setattr(align_module, "_align", spy)
    again = align_module._coarse_look(r, na, nb, *_plain_features(na, nb), "hybrid", align_module.AlignOptions(), 0, 0.0)
    assert [o.feature_pixels for o in searched] == [200_000] and searched[0].coarse_look == 0
    assert again.details["coarse_look"] == look and again.message == r.message
    # 0 turns it off; maps whose keypoint images are no larger are not searched again.
    assert "coarse_look" not in negative_first_search.details
    assert "coarse_look" not in align(na, nb, rng=0, coarse_look=400_000).details
    # Nor is a pair that is accepted.
    a, b, _ = samples.table1_pair(0)
    assert "coarse_look" not in align(a, b, rng=0).details


def test_the_coarser_look_reuses_what_the_first_search_learned(monkeypatch):
    """The second search of a declined pair is handed the first search's memory: the
    poses both searches judge (the wall correlation's, mostly) are scored and refined
    once, and the second search decides as it would have alone (nothing in the search
    is random)."""
    from gridmerge.verify import WallScorer

    align_module = importlib.import_module("gridmerge.align")
    opts = align_module.AlignOptions()
    na, nb = samples.negative_pair(0)
    fa, fb = _plain_features(na, nb)
    memory = align_module._PairMemory()
    first = align_module._align(na, nb, "hybrid", replace(opts, coarse_look=0), 0, (fa, fb), None, memory)
    assert not first.success
    assert all(len(memory.side(side).quick) > 100 for side in (False, True))  # both sides were searched
    calls = {"scored": 0, "refined": 0}
    scorer, refine = WallScorer.__call__, align_module.refine_direct

    def scored(*args, **kw):
        calls["scored"] += 1
        return scorer(*args, **kw)

    def refined(*args, **kw):
        calls["refined"] += 1
        return refine(*args, **kw)

    monkeypatch.setattr(WallScorer, "__call__", scored)
    monkeypatch.setattr(align_module, "refine_direct", refined)

    def coarse_look(m):
        calls.update(scored=0, refined=0)
        r = align_module._coarse_look(first, na, nb, fa, fb, "hybrid", opts, 0, 0.0, m)
        return r.details["coarse_look"], dict(calls)

    alone, fresh = coarse_look(align_module._PairMemory())
    again, reused = coarse_look(memory)
    assert again == alone and alone["message"].startswith("declined")
    assert reused["scored"] < 0.5 * fresh["scored"]
    # Once more with the same memory: every pose is known, nothing is scored or refined
    # (on these maps the coarser keypoints lead to poses of their own: the first search's
    # refinements are not asked for again, but on real pairs many are).
    assert fresh["refined"] > 0
    assert coarse_look(memory) == (alone, {"scored": 0, "refined": 0})


def test_the_default_method_gives_the_same_result_whatever_the_seed():
    """Nothing in the hybrid search is drawn at random (the refinement's cells are an
    evenly spread subset): a user's seed cannot turn a merge into another."""
    a, b, truth = samples.robot_pair(0)
    results = [align(a, b, rng=seed) for seed in (0, 12345, np.random.default_rng(7))]
    assert results[0].success and corner_error(results[0].transform, truth, b.shape) < 1.0
    for r in results[1:]:
        np.testing.assert_array_equal(r.transform.params, results[0].transform.params)
        assert (r.confidence, r.message) == (results[0].confidence, results[0].message)


def _plain_features(a, b):
    from gridmerge.align import default_extractor

    return default_extractor()(a), default_extractor()(b)


@pytest.mark.shared
@pytest.mark.parametrize("a_name, b_name, coarse", [("E5_03", "E5_11", True), ("E5_10", "E5_13", False)])
def test_real_maps_merged_by_the_search_with_coarser_keypoints(shared_data, a_name, b_name, coarse):
    """Two E5 pairs declined by the search with keypoints on 400k pixels (confidence 0.38)
    and merged within the protocol by the second one, on 200k, in either order. (The
    second search runs only when the first declined: the message and
    ``first_confidence`` say so, with no need to search again with ``coarse_look=0``.)
    Since a pose is polished again where a polish stopped (fifty-seventh session), the
    first search merges E5_10-E5_13 itself (confidence 0.62), within the protocol too."""
    pair, a, b = _e5_pair(shared_data, a_name, b_name)
    r = align(a, b, rng=0)
    assert r.success, r.message
    if coarse:
        assert r.details["coarse_look"]["first_confidence"] < 0.5 and "fewer pixels" in r.message
    else:
        assert "coarse_look" not in r.details
    assert _within_protocol(r.transform, pair)
    swapped = align(b, a, rng=0)
    assert swapped.success and np.allclose(swapped.transform.params, r.transform.inverse.params)


@pytest.mark.shared
def test_a_pose_turned_about_the_overlap_is_judged_again_polished_beyond_reach(shared_data):
    # Simulated pair 35 of seed 8 (E5, medium tier, b 2000 x 888 cells at 0.77 of a's cell
    # size): the full search took a pose 0.7 degrees off at confidence 0.71, its walls
    # agreeing on 50 % and b's far corners 17.5 px from the truth (a wrong merge). ICP on
    # the walls from it reaches the truth (walls 88 %) but moves those corners farther than
    # a polish may; judged again with that pose, the search takes it.
    from gridmerge.bench import datasets

    case = datasets.simulated(n=60, seed=8, data_dir=shared_data, see_through=2)[35]
    r = align(case.a, case.b, rng=0)
    assert r.success and r.details["source"].endswith("(polished beyond reach)"), r.details
    assert corner_error(r.transform, case.truth, case.b.shape) < 2.0


def test_a_taken_pose_records_how_its_walls_fix_it_and_max_slide_declines():
    """Every pose otherwise taken is slid along its shared walls
    (:attr:`AlignOptions.max_slide`); a right pose in rooms loses much of its agreement,
    and a limit below what it keeps declines it, saying why."""
    a, b, truth = samples.robot_pair(0)
    r = align(a, b)
    assert r.success
    kept = r.details["slide"]["kept"]
    assert 0.0 < kept <= 0.75 and r.details["slide"]["px"] > 0
    strict = align(a, b, max_slide=kept / 2)
    assert not strict.success and strict.message.startswith("declined: the walls do not fix the pose")
    assert strict.candidate is not None
    np.testing.assert_allclose(strict.candidate.params, r.transform.params)
    free = align(a, b, max_slide=None)
    assert free.success and "slide" not in free.details
    np.testing.assert_allclose(free.transform.params, r.transform.params)


def _furnished(b, rng, pieces: int = 6):
    """``b`` with ``pieces`` 13-cell walls put across its open space (deeper than 8 cells
    inside it): what the other robot's map has never seen."""
    d = b.data.copy()
    free = np.nan_to_num(d, nan=1.0) < 0.2
    depth = cv2.distanceTransform(free.view(np.uint8), cv2.DIST_L2, 5)
    ys, xs = np.nonzero(depth > 8)
    for k in rng.choice(len(ys), pieces, replace=False):
        d[ys[k], max(0, xs[k] - 6) : xs[k] + 7] = 1.0
    return OccupancyGrid(d, resolution=b.resolution, origin=b.origin)


def test_a_taken_pose_records_walls_across_the_other_maps_rooms_and_max_crossing_declines():
    """Every pose otherwise taken counts the overlap's walls standing deep inside the other
    map's open space (:attr:`AlignOptions.max_crossing`): a share above the limit
    declines a pose that rests on fewer than 3000 wall cells, saying why."""
    a, b, truth = samples.robot_pair(1, shape=(200, 260))
    b = _furnished(b, np.random.default_rng(0))
    r = align(a, b)
    assert r.success and corner_error(r.transform, truth, b.shape) < 2.0
    share, walls = r.details["crossing"]["share"], r.details["crossing"]["walls"]
    assert 0.0 < share <= 0.2 and 0 < walls < 3000
    strict = align(a, b, max_crossing=share / 2)
    assert not strict.success and "stand inside the other map's open space" in strict.message
    np.testing.assert_allclose(strict.candidate.params, r.transform.params)
    free = align(a, b, max_crossing=None)
    assert free.success and "crossing" not in free.details
    np.testing.assert_allclose(free.transform.params, r.transform.params)


def test_max_crossing_does_not_judge_a_pose_on_many_walls():
    from gridmerge.verify import crossing, despeckle

    # Real maps of one building differ (furniture moved, doors, glass): a pose resting on
    # 3000 wall cells or more is not judged by its crossing walls.
    a, b, truth = samples.robot_pair(3, shape=(200, 260))
    b = _furnished(b, np.random.default_rng(0))
    r = align(a, b, max_crossing=0.0)
    assert r.success and corner_error(r.transform, truth, b.shape) < 2.0
    assert r.details["crossing"]["walls"] >= 3000 and r.details["crossing"]["share"] is None  # not judged
    assert crossing(despeckle(a), despeckle(b), r.transform).share > 0.0  # though some walls cross


def test_unsure_walls_needs_a_buildings_walls_below_a_sure_confidence():
    """Below confidence 0.8 a pose must rest on :attr:`AlignOptions.unsure_walls` overlap
    wall cells (both maps'); a sure pose is not judged so, whatever its walls."""
    from gridmerge.align import SURE_CONFIDENCE, AlignOptions, _unsure_reason
    from gridmerge.verify import Verification

    opts = AlignOptions()
    v = Verification(0.95, 900, 50, 0.6, 20000, 0.5, walls_a=4000, walls_b=3000, matched_a=2400, matched_b=1800)
    reason = _unsure_reason(v, 0.65, opts)
    assert reason == ("declined: confidence 0.65 on 7000 overlap wall cells; below 0.8 a pose needs 10000 "
                      "(a building's walls agreeing in part, not a few rooms')")
    assert _unsure_reason(v, SURE_CONFIDENCE, opts) == ""
    assert "confidence 0.79 on" in _unsure_reason(v, 0.7999, opts)  # not "0.80 ... below 0.8"
    assert _unsure_reason(replace(v, walls_a=7000), 0.65, opts) == ""  # 10000 walls
    assert _unsure_reason(v, 0.65, replace(opts, unsure_walls=None)) == ""
    assert _unsure_reason(replace(v, walls_a=None), 0.65, opts) == ""  # an old verification: not counted

    a, b, truth = samples.robot_pair(1, shape=(200, 260))
    r = align(a, b, unsure_walls=10**9)
    assert r.success and r.confidence >= SURE_CONFIDENCE and corner_error(r.transform, truth, b.shape) < 2.0


def test_a_pose_on_few_walls_needs_them_to_agree_closely():
    """On fewer than :data:`FEW_WALLS_EVIDENCE` overlap wall cells (both maps'), a pose
    whose walls agree on less than :attr:`AlignOptions.few_walls_agreement` is declined,
    whatever its confidence; on more, or agreeing enough, it is not judged so."""
    from gridmerge.align import FEW_WALLS_EVIDENCE, AlignOptions, _few_walls_reason
    from gridmerge.verify import Verification

    opts = AlignOptions()
    assert opts.few_walls_agreement == 0.75 and FEW_WALLS_EVIDENCE == 200
    v = Verification(0.99, 9000, 20, 0.7465, 9020, 0.3, walls_a=59, walls_b=50, matched_a=42, matched_b=39)
    assert _few_walls_reason(v, opts) == (
        "declined: walls agree on 74% of the overlap, on only 109 wall cells of the two maps; on fewer than 200 a "
        "pose needs 75% (a few walls of two places, or of the wrong part, agree in part by chance)")
    assert _few_walls_reason(replace(v, wall_agreement=0.75), opts) == ""
    assert _few_walls_reason(replace(v, walls_a=150), opts) == ""  # 200 wall cells: not judged so
    assert _few_walls_reason(replace(v, wall_agreement=math.nan), opts) == ""  # no walls: other rules judge
    assert _few_walls_reason(replace(v, walls_a=None), opts) == ""  # an old verification: not counted
    assert _few_walls_reason(v, replace(opts, few_walls_agreement=None)) == ""
    assert _few_walls_reason(v, replace(opts, few_walls_agreement=0.0)) == ""


@pytest.mark.shared
def test_a_chance_fit_on_few_walls_is_declined_and_a_close_one_is_not(shared_data):
    """Simulated seed 104's negative pair 14 (two parts of the Halmstad office E5_04): the
    wall-led search lays a hall of one on a hall of the other, 61 % of 65 + 38 overlap wall
    cells agreeing, at confidence 0.86; it was merged. Seed 101's pair 43: a right pose on
    41 + 44 wall cells agreeing on 75 % is still taken."""
    from gridmerge.bench import datasets

    neg = datasets.simulated(n=60, seed=104, data_dir=shared_data)[14]
    assert not neg.positive
    r = align(neg.a, neg.b, rng=0)
    assert not r.success and "on fewer than 200 a pose needs 75%" in r.message
    assert r.confidence > 0.5  # the confidence alone would have taken it
    assert align(neg.a, neg.b, rng=0, few_walls_agreement=None).success  # as before the rule
    pos = datasets.simulated(n=60, seed=101, data_dir=shared_data)[43]
    r = align(pos.a, pos.b, rng=0)
    v = r.verification
    assert r.success and v.walls_a + v.walls_b < 200 and v.wall_agreement >= 0.75
    assert corner_error(r.transform, pos.truth, pos.b.shape) < 2.0


@pytest.mark.shared
def test_unsure_walls_declines_a_chance_pose_on_a_few_rooms_of_real_maps(shared_data):
    """Two robots' maps of a few rooms each in two real sessions of the E5 office
    (halmstad-partial, seed 1, case 46): the default method's best pose lies 117 px from
    the annotated points at confidence 0.52 on 8007 overlap wall cells. Whole buildings'
    right poses below 0.8 rest on 11 000 or more: declined."""
    from gridmerge.bench import datasets
    from gridmerge.bench.metrics import halmstad_point_error

    case = datasets.halmstad_partial(n=47, seed=1, data_dir=shared_data)[46]
    cv2.setRNGSeed(1)
    r = align(case.a, case.b, rng=1)
    assert not r.success and "on 8007 overlap wall cells; below 0.8 a pose needs 10000" in r.message
    assert halmstad_point_error(r.candidate, case.meta["points_a"], case.meta["points_b"]) > 100
    cv2.setRNGSeed(1)
    loose = align(case.a, case.b, rng=1, unsure_walls=None)
    assert loose.success and loose.confidence < 0.8
    # The same pose, taken (and then moved halfway to its polish on the raw walls: at
    # most half of _MIDWAY_REACH).
    assert corner_error(loose.transform, r.candidate, case.b.shape) < align_module._MIDWAY_REACH / 2


def _room(d: np.ndarray, x0: int, y0: int) -> None:
    """A 100 x 100 room with a door, a stub wall and a shelf drawn into ``d`` at (x0, y0)."""
    d[y0 : y0 + 100, x0 : x0 + 100] = 0.0
    d[[y0, y0 + 99], x0 : x0 + 100] = 1.0
    d[y0 : y0 + 100, [x0, x0 + 99]] = 1.0
    d[y0 + 99, x0 + 20 : x0 + 35] = 0.0  # the door
    d[y0 + 30 : y0 + 60, x0 + 60] = 1.0  # a stub wall
    d[y0 + 70, x0 + 10 : x0 + 40] = 1.0  # a shelf


def test_a_confidence_lowered_by_a_rival_pose_says_so():
    """Map a holds two identical rooms, map b one of them: b fits either room as well, and
    the decline says that a clearly different pose fits as well (a bare "confidence 0.00"
    would not tell the user whether the walls or the ambiguity failed)."""
    from gridmerge.align import AlignOptions, _merit_reason
    from gridmerge.verify import Verification

    a = np.full((140, 300), np.nan)
    _room(a, 20, 20)
    _room(a, 180, 20)
    b = np.full((120, 120), np.nan)
    _room(b, 10, 10)
    r = align(OccupancyGrid(a), OccupancyGrid(b), rng=0)
    assert not r.success and r.confidence < 0.5
    assert r.details["runner_up_ratio"] > 0.95
    assert r.message.startswith("declined: confidence") and "a clearly different pose fits" in r.message
    # Either room is the candidate: b's door side on a's door side.
    assert r.candidate is not None and min(corner_error(r.candidate, SimilarityTransform(translation=(dx, 10)), b.shape)
                                           for dx in (10, 170)) < 2.0

    # Without a rival above 80 % of its score, a low confidence is its walls': no note.
    v = Verification(0.99, 9000, 100, 0.9, 10000, 0.5, walls_a=300, walls_b=300, matched_a=270, matched_b=270)
    assert _merit_reason(0, v, 0.3, AlignOptions(), False, False, 0.5) == "declined: confidence 0.30 below 0.5"
    assert _merit_reason(0, v, 0.3, AlignOptions(), False, False, None) == "declined: confidence 0.30 below 0.5"
    assert "fits 90% as well" in _merit_reason(0, v, 0.3, AlignOptions(), False, False, 0.9)
    assert "fits as well or better" in _merit_reason(0, v, 0.0, AlignOptions(), False, False, 1.17)


def test_a_pose_is_polished_again_where_the_last_polish_stopped():
    """ICP on thin, noisy walls can stop in a fit of one part on its way: a polished pose
    that a further polish raises by a tenth is polished again (at most ``_POLISH_ROUNDS``
    times, each step within ``_POLISH_REACH`` and all within ``_POLISHES_REACH`` of the
    start); a polish that gains less, or would carry the pose beyond that, is not kept."""
    module = importlib.import_module("gridmerge.align")

    a, b, truth = samples.robot_pair(0)
    judge = module._Judge(a, b, module.AlignOptions())
    start = SimilarityTransform(truth)

    def shifted(px):
        return SimilarityTransform(SimilarityTransform(translation=(px, 0.0)).params @ truth)

    step = 7.0
    scores = {0.0: 0.5, 7.0: 0.6, 14.0: 0.7, 21.0: 0.9}

    def score(t):
        return scores[round(float(t.params[0, 2] - truth[0, 2]))]

    def polish(t):  # each polish moves the pose 7 px along x
        return shifted(float(t.params[0, 2] - truth[0, 2]) + step)

    judge._polish = polish
    assert step <= module._POLISH_REACH and 2 * step <= module._POLISHES_REACH < 3 * step <= module._POLISH_ROUNDS * step
    value, pose = judge.polished(start, score)
    assert value == 0.7 and pose.params[0, 2] == pytest.approx(truth[0, 2] + 14.0)  # 21 px is beyond reach
    scores[14.0] = 0.65  # under a tenth more than 0.6: the second polish is not kept
    value, pose = judge.polished(start, score)
    assert value == 0.6 and pose.params[0, 2] == pytest.approx(truth[0, 2] + 7.0)
    judge._polish = lambda t: None  # a pose that may not be polished stays
    assert judge.polished(start, score) == (0.5, start)


@pytest.mark.shared
def test_a_pose_the_polish_left_halfway_is_polished_again(shared_data):
    """Fresh simulated seed 78, pair 32 (Halmstad, noisy, b's cells 0.63 of a's, 540 wall
    cells of each map in the overlap): the best candidate is refined to 12.3 px from the
    truth and polished to 5.4 px, where its walls agree on 51 %; polished again from there
    it is 0.2 px from the truth, walls agreeing on 99.6 %. Merged 5.4 px off before."""
    from gridmerge.bench import datasets

    case = datasets.simulated(n=60, seed=78, data_dir=shared_data)[32]
    r = align(case.a, case.b, rng=0)
    assert r.success, r.message
    assert corner_error(r.transform, case.truth, case.b.shape) < 1.0
    assert r.verification.wall_agreement > 0.9


def _judged_at_the_truth():
    """The first sample pair judged as the search judges it: ``(module, a, b, truth, judge,
    right, centre)``, with ``right`` the truth between the working maps' cuts and
    ``centre`` (x, y) the median of the part of b it lays on a's known cells."""
    module = importlib.import_module("gridmerge.align")
    a, b, truth = samples.robot_pair(0)
    ca, oa, cb, ob = module.working_maps(a, b)
    right = module.full_to_crop(SimilarityTransform(truth), oa, ob)
    judge = module._Judge(ca, cb, module.AlignOptions())
    p, on = judge._shared_part(right)
    return module, a, b, truth, judge, right, np.median(p[on], axis=0)


def test_a_pose_polished_beyond_reach_is_taken_when_the_sample_prefers_a_worse_one(monkeypatch):
    """The rule for a pose polished beyond reach measures walls in full; the judging
    ranks by the scorer's sample, which on a coarse b can score a pose 2 degrees off
    above the truth (HM3D seed 39's pair 51: 97.6 % on the sample, 67.5 % in full). When
    the judging keeps a pose whose walls agree far less in full than the same merge
    polished beyond reach, the latter is taken. Here the judging is made to prefer a
    pose turned 2 degrees about the shared part (walls agreeing on 50 % in full, the
    truth on 99 %), whatever it is offered."""
    module, a, b, truth, judge, right, centre = _judged_at_the_truth()
    turned = SimilarityTransform(_turn_about(tuple(centre), 2.0).params @ right.params)
    v_turned, v_right = judge._verify(turned), judge._verify(right)
    assert module._full_wall(v_turned) + module._UNSETTLED_GAIN <= module._full_wall(v_right)
    assert judge.far_apart(turned, right, module._POLISH_REACH) and not judge.rival(turned, right)

    decided = []

    def decide(self, candidates, **kwargs):  # the sample's verdict: the turned pose
        decided.append(len(candidates))
        return 0.97, turned, "walls", 0.2, self._verify(turned)

    monkeypatch.setattr(module._Judge, "decide", decide)
    monkeypatch.setattr(module._Judge, "climbed", lambda self, t: [t])  # no better pose nearby
    monkeypatch.setattr(module._Judge, "beyond_reach", lambda self, t: right if t is turned else None)
    r = align(a, b, rng=0, keypoints_first=0, wall_led=False, search_from="a", coarse_look=0)
    assert len(decided) >= 2  # judged again with the pose polished beyond reach
    assert r.success, r.message
    assert r.details["source"].endswith("(polished beyond reach)")
    assert corner_error(r.transform, truth, b.shape) < 1.0


def test_a_pose_brought_to_the_ratio_is_taken_when_the_sample_prefers_a_worse_one(monkeypatch):
    """A pose off the maps' resolution ratio is judged again brought to the ratio when
    that removes a third of the walls' disagreement, on the scorer's sample or in full;
    the judging ranks by the sample, which on a coarse b can score a pose off in scale
    above the truth (fresh HM3D seed 53's pair 10: 94 % on the sample, 76 % in full, the
    pose at the ratio 93.6 % and 91.5 %). When the judging keeps the pose off the ratio,
    the one at the ratio, measured in full the better fit of the same merge, is taken.
    Here the judging is made to prefer b scaled 2 % about the shared part (walls agreeing
    on 71 % in full, the truth on 99 %) at a saturated sample score (no pose can beat it
    there), whatever it is offered."""
    module, a, b, truth, judge, right, centre = _judged_at_the_truth()
    about = SimilarityTransform(translation=centre) @ SimilarityTransform(scale=1.02) @ SimilarityTransform(translation=-centre)
    off = SimilarityTransform(about.params @ right.params)
    v_off, v_right = judge._verify(off), judge._verify(right)
    assert module._removes_disagreement(module._full_wall(v_right), module._full_wall(v_off), module._RESCALE_GAIN)
    assert not judge.rival(off, right)

    decided = []

    def decide(self, candidates, **kwargs):  # the sample's verdict: the pose off the ratio
        decided.append(len(candidates))
        return 0.9999, off, "walls", 0.2, self._verify(off)

    monkeypatch.setattr(module._Judge, "decide", decide)
    monkeypatch.setattr(module._Judge, "climbed", lambda self, t: [t])  # no better pose nearby
    monkeypatch.setattr(module._Judge, "rescaled", lambda self, t: [right] if t is off else [])
    monkeypatch.setattr(module._Judge, "beyond_reach", lambda self, t: None)
    r = align(a, b, rng=0, keypoints_first=0, wall_led=False, search_from="a", coarse_look=0)
    assert len(decided) >= 2  # judged again with the pose at the ratio
    assert r.success, r.message
    assert r.details["source"].endswith("(at the resolutions' scale)")
    assert corner_error(r.transform, truth, b.shape) < 1.0


# ------------------------------------------------------------ poses on few walls
def test_a_pose_on_few_walls_is_taken_with_a_warning_that_counts_them(table1, table1_result):
    # The Table I pair's pose rests on thousands of wall cells: no warning by default.
    # Asked to warn below more walls than its overlap holds, the same decision carries a
    # warning that gives the two maps' counts and the threshold; 0 turns it off.
    a, b, _ = table1
    v = table1_result.verification
    assert table1_result.success and table1_result.warnings == []
    total = v.walls_a + v.walls_b
    assert total >= AlignOptions().few_walls
    flagged = align(a, b, few_walls=total + 1)
    assert flagged.success and flagged.confidence == table1_result.confidence
    np.testing.assert_allclose(flagged.matrix, table1_result.matrix)
    (note,) = flagged.warnings
    assert f"{v.walls_a} + {v.walls_b} wall cells" in note and f"under {total + 1}" in note
    assert align(a, b, few_walls=total).warnings == []
    assert align(a, b, few_walls=0).warnings == []


def test_few_walls_warning_needs_a_taken_pose_and_its_counts(table1_result):
    opts = AlignOptions(few_walls=50)
    few = Verification(0.99, 100, 1, 0.95, 5000, 0.3, walls_a=20, walls_b=29, matched_a=19, matched_b=28)
    enough = replace(few, walls_b=30)
    unknown = replace(few, walls_a=None, walls_b=None)
    assert "20 + 29 wall cells" in align_module.few_walls_warning(few, opts)
    assert align_module.few_walls_warning(enough, opts) is None
    assert align_module.few_walls_warning(unknown, opts) is None  # a result saved before the counts were
    assert align_module.few_walls_warning(few, AlignOptions(few_walls=None)) is None
    taken = replace(table1_result, verification=few)
    once = align_module.with_warnings(taken, opts)
    assert len(once.warnings) == 1 and align_module.with_warnings(once, opts).warnings == once.warnings
    declined = replace(taken, success=False, transform=None)
    assert align_module.with_warnings(declined, opts).warnings == []
    # The warnings travel with the result.
    back = AlignResult.from_dict(json.loads(once.to_json()))
    assert back.warnings == once.warnings


@pytest.mark.parametrize("scale", [0.8, 1.25])
def test_a_wall_led_pose_is_moved_halfway_to_its_polish_on_the_raw_walls(scale):
    # _midway: the pose halfway between a taken pose and its ICP polish on the walls of
    # the maps as given, in the frame of the map with the finer cells (b's at scale 0.8,
    # a's at 1.25): every point of b lands halfway between its two images, nearer the
    # truth than the pose; nothing when the polish would move b's corners farther than
    # _MIDWAY_REACH.
    from gridmerge.align import _MIDWAY_REACH, _midway, full_to_crop, working_maps
    from gridmerge.refine import WallICP

    a, b, truth = samples.robot_pair(0, scale=scale, rotation_deg=25)
    assert (b.resolution < a.resolution) == (scale < 1.0)
    truth = SimilarityTransform(truth)
    ca, oa, cb, ob = working_maps(a, b)
    off = SimilarityTransform(rotation=truth.rotation + 0.003, scale=truth.scale, translation=truth.translation + [1.5, -1.0])
    t = full_to_crop(off, oa, ob)
    frames = []
    real_init = WallICP.__init__

    def init(self, ref, other, **kw):
        frames.append(ref.shape)
        real_init(self, ref, other, **kw)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(WallICP, "__init__", init)
        out = _midway(a, b, t)
    assert frames == [cb.shape if scale < 1.0 else ca.shape]  # the finer map is the ICP's reference
    assert out is not None
    pose, moved = out
    ra, rb = a.crop_known(align_module._CROP_MARGIN)[0], b.crop_known(align_module._CROP_MARGIN)[0]  # the raw cuts
    found = SimilarityTransform(t.params)
    polished = WallICP(rb, ra).polish(found.inverse).inverse if scale < 1.0 else WallICP(ra, rb).polish(found)
    pts = np.array([[0.0, 0.0], [cb.shape[1] - 1.0, 0.0], [40.0, 77.0], [0.0, cb.shape[0] - 1.0]])
    assert np.allclose(pose(pts), (t(pts) + polished(pts)) / 2.0)
    assert moved == pytest.approx(corner_error(polished, t, cb.shape))  # at b's cut's corners
    assert 0.0 < moved <= _MIDWAY_REACH
    truth_cut = full_to_crop(truth, oa, ob)
    assert corner_error(pose, truth_cut, cb.shape) < corner_error(t, truth_cut, cb.shape)
    # Beyond the reach: the pose stays (None).
    far = full_to_crop(SimilarityTransform(rotation=truth.rotation, scale=truth.scale, translation=truth.translation + [6.0, 5.0]), oa, ob)
    assert _midway(a, b, far) is None


def test_the_halfway_pose_keeps_the_decision_and_skips_keypoint_settled_poses(monkeypatch):
    # align moves a taken pose of the walls' search halfway (details["midway"]), only
    # when the pose there is still taken by the decline rules (its verification is the
    # one reported); a pose the keypoints settled alone is not moved.
    a, b, truth = samples.robot_pair(0, scale=0.8, rotation_deg=25)
    searched = AlignOptions(keypoints_first=0)  # the walls' search judges every pose
    seen = []
    real = align_module._midway

    def spy(*args):
        out = real(*args)
        seen.append(out)
        return out

    monkeypatch.setattr(align_module, "_midway", spy)
    monkeypatch.setattr(align_module, "_chamfered", lambda *args: None)  # the halfway pose, last
    r = align(a, b, rng=0, options=searched)
    assert r.success and len(seen) == 1 and seen[0] is not None
    assert r.details["midway"]["polish_px"] == pytest.approx(seen[0][1], abs=0.01)
    assert r.verification.wall_agreement == pytest.approx(
        verify_module.verify(*align_module.working_maps(a, b)[::2], seen[0][0], tolerance=searched.wall_tolerance).wall_agreement)
    # A halfway pose the rules would decline (its walls meet nothing) is not taken.
    away = SimilarityTransform(translation=[500.0, 500.0])
    monkeypatch.setattr(align_module, "_midway", lambda *args: (away, 1.0))
    kept = align(a, b, rng=0, options=searched)
    assert kept.success and "midway" not in kept.details
    assert corner_error(kept.transform, truth, b.shape) < 2.0
    # The keypoints settle this pair by default: its pose is not moved; nor are the
    # poses of the other methods (the paper's estimator stays the paper's).
    settled = align(a, b, rng=0)
    assert settled.details["walls"].startswith("skipped") and "midway" not in settled.details
    monkeypatch.setattr(align_module, "_midway", real)
    for method in ("sift", "paper"):
        other = align(a, b, method=method, rng=0, options=searched)
        assert other.success and "midway" not in other.details


def test_a_pose_off_its_walls_is_moved_to_the_pose_near_it_where_they_agree():
    # _widened: from 12-28 px off (beyond ICP's reach), the pose whose walls agree best
    # within 2 degrees and 20 px, polished: on the truth; nothing for a pose on its walls.
    from gridmerge.align import _widened, crop_to_full, full_to_crop, working_maps

    a, b, truth = samples.robot_pair(0)
    truth = SimilarityTransform(truth)
    ca, oa, cb, ob = working_maps(a, b)
    for dx, dy, turn in [(8.0, 6.0, 0.015), (0.0, 0.0, 0.03)]:
        off = SimilarityTransform(rotation=truth.rotation + turn, scale=truth.scale, translation=truth.translation + [dx, dy])
        out = _widened(ca, cb, full_to_crop(off, oa, ob))
        assert out is not None
        pose, (before, after) = out
        assert before < 0.5 and after > 0.95
        assert corner_error(crop_to_full(pose, oa, ob), truth, b.shape) < 0.5
    on = _widened(ca, cb, full_to_crop(crop_to_full(pose, oa, ob), oa, ob))
    assert on is None
    # Not when the better pose agrees by less than _WIDEN_GAIN more, nor on fewer than
    # _WIDEN_WALLS wall cells of either map in the overlap.
    t = full_to_crop(off, oa, ob)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(align_module, "_WIDEN_GAIN", 1.0)
        assert _widened(ca, cb, t) is None
    with pytest.MonkeyPatch.context() as mp:
        walls = verify_module.verify(ca, cb, t, tolerance=align_module._WIDEN_TOLERANCE)
        mp.setattr(align_module, "_WIDEN_WALLS", min(walls.walls_a, walls.walls_b) + 1)
        assert _widened(ca, cb, t) is None
        mp.setattr(align_module, "_WIDEN_WALLS", min(walls.walls_a, walls.walls_b))
        assert _widened(ca, cb, t) is not None


def test_a_pose_is_searched_at_the_resolutions_ratio_when_its_scale_is_off_it():
    from gridmerge.align import _widened, crop_to_full, full_to_crop, working_maps

    a, b, truth = samples.robot_pair(0, scale=0.8, rotation_deg=25)
    truth = SimilarityTransform(truth)
    ratio = b.resolution / a.resolution
    assert truth.scale == pytest.approx(ratio)
    ca, oa, cb, ob = working_maps(a, b)
    off = full_to_crop(SimilarityTransform(rotation=truth.rotation, scale=truth.scale * 1.015,
                                           translation=truth.translation + [3.0, -2.0]), oa, ob)
    pose, _ = _widened(ca, cb, off, ratio)
    assert pose.scale == pytest.approx(ratio, rel=1e-6)
    assert corner_error(crop_to_full(pose, oa, ob), truth, b.shape) < 0.5
    kept = _widened(ca, cb, off)  # resolutions not trusted: the scale stays
    assert kept is None or kept[0].scale == pytest.approx(off.scale, rel=1e-6)


def test_align_moves_a_taken_pose_to_where_its_walls_agree_and_keeps_the_decision(monkeypatch):
    # A taken pose 12 px off (here: the halfway pose, made so) is moved to the truth
    # (details["widened"]; the verification reported is the new pose's); a widened pose
    # the decline rules would refuse is not taken; the other methods are not widened.
    a, b, truth = samples.robot_pair(0)
    truth = SimilarityTransform(truth)
    searched = AlignOptions(keypoints_first=0)
    ca, oa, cb, ob = align_module.working_maps(a, b)
    off = SimilarityTransform(rotation=truth.rotation + 0.015, scale=truth.scale, translation=truth.translation + [8.0, 6.0])
    monkeypatch.setattr(align_module, "_midway", lambda *args: (align_module.full_to_crop(off, oa, ob), 1.0))
    r = align(a, b, rng=0, options=searched)
    assert r.success and "midway" in r.details and "widened" in r.details
    assert corner_error(r.transform, truth, b.shape) < 0.5
    before, after = r.details["widened"]["walls"]
    assert before < 0.5 and after > 0.95
    assert r.details["widened"]["moved_px"] > 10.0
    assert r.verification.wall_agreement == pytest.approx(
        verify_module.verify(ca, cb, align_module.full_to_crop(r.transform, oa, ob), tolerance=searched.wall_tolerance).wall_agreement)
    # A widened pose the rules decline is not taken: the pose stays where it was.
    away = SimilarityTransform(translation=[500.0, 500.0])
    monkeypatch.setattr(align_module, "_widened", lambda *args: (away, (0.4, 0.9)))
    monkeypatch.setattr(align_module, "_chamfered", lambda *args: None)  # the pose as the widening left it
    kept = align(a, b, rng=0, options=searched)
    assert kept.success and "widened" not in kept.details
    assert corner_error(kept.transform, off, b.shape) < 1e-6
    for method in ("sift", "paper"):
        other = align(a, b, method=method, rng=0, options=searched)
        assert "widened" not in other.details


def test_align_moves_a_pose_the_walls_judged_halfway_to_its_chamfer_polish(monkeypatch):
    # A taken pose 1.5 px off (the halfway pose, made so) is moved, last, halfway towards
    # its polish on the walls' distance fields, which lies on the truth
    # (details["chamfer"]; the verification reported is the new pose's); a pose the
    # decline rules would refuse there is not taken; a pose the keypoints settled, and
    # the other methods' poses, are not moved.
    a, b, truth = samples.robot_pair(0)
    truth = SimilarityTransform(truth)
    searched = AlignOptions(keypoints_first=0)
    ca, oa, cb, ob = align_module.working_maps(a, b)
    off = SimilarityTransform(rotation=truth.rotation + 0.002, scale=truth.scale, translation=truth.translation + [1.0, -1.0])
    start = corner_error(off, truth, b.shape)
    assert start > 1.2
    monkeypatch.setattr(align_module, "_midway", lambda *args: (align_module.full_to_crop(off, oa, ob), 1.0))
    monkeypatch.setattr(align_module, "_widened", lambda *args: None)
    r = align(a, b, rng=0, options=searched)
    assert r.success and "midway" in r.details and "chamfer" in r.details
    assert corner_error(r.transform, truth, b.shape) < 0.5 * start + 0.15  # halfway to the truth
    cut = align_module.full_to_crop  # polish_px: at the corners of b's cut
    assert r.details["chamfer"]["polish_px"] == pytest.approx(
        2.0 * corner_error(cut(r.transform, oa, ob), cut(off, oa, ob), cb.shape), abs=0.01)
    assert r.verification.wall_agreement == pytest.approx(
        verify_module.verify(ca, cb, align_module.full_to_crop(r.transform, oa, ob), tolerance=searched.wall_tolerance).wall_agreement)
    # Not for a pose whose walls agree on less than _CHAMFER_AGREEMENT (maps that bend).
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(align_module, "_CHAMFER_AGREEMENT", r.verification.wall_agreement + 0.01)
        below = align(a, b, rng=0, options=searched)
        assert below.success and "chamfer" not in below.details
    # A moved pose the rules decline is not taken: the pose stays where it was.
    away = SimilarityTransform(translation=[500.0, 500.0])
    monkeypatch.setattr(align_module, "_chamfered", lambda *args: (away, 1.0))
    kept = align(a, b, rng=0, options=searched)
    assert kept.success and "chamfer" not in kept.details
    assert corner_error(kept.transform, off, b.shape) < 1e-6
    settled = align(a, b, rng=0)  # the keypoints settle this pair by default
    assert settled.details["walls"].startswith("skipped") and "chamfer" not in settled.details
    for method in ("sift", "paper"):
        other = align(a, b, method=method, rng=0, options=searched)
        assert "chamfer" not in other.details


def test_the_chamfer_step_goes_halfway_and_not_far(monkeypatch):
    from gridmerge.align import _chamfered, full_to_crop, working_maps

    a, b, truth = samples.robot_pair(0)
    truth = SimilarityTransform(truth)
    ca, oa, cb, ob = working_maps(a, b)
    truth_cut = full_to_crop(truth, oa, ob)
    off = SimilarityTransform(translation=[1.5, 0.0]) @ truth_cut
    pose, moved = _chamfered(ca, cb, off)
    assert 1.0 < moved < 2.0
    assert corner_error(pose, off, cb.shape) == pytest.approx(moved / 2.0, rel=1e-3)
    assert corner_error(pose, truth_cut, cb.shape) < 1.0
    far = SimilarityTransform(translation=[6.0, 0.0]) @ off
    monkeypatch.setattr(align_module, "chamfer_polish", lambda a, b, t: far)
    assert _chamfered(ca, cb, off) is None  # 6 px: farther than _CHAMFER_REACH
    monkeypatch.setattr(align_module, "chamfer_polish", lambda a, b, t: t)
    assert _chamfered(ca, cb, off) is None  # not moved

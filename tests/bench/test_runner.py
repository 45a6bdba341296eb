"""A tiny end-to-end benchmark run, its files, reproducibility, compare, and the CLI."""

from __future__ import annotations

import argparse
import json

import pytest

from gridmerge.bench import datasets, runner
from gridmerge.bench.metrics import shared_walls_group
from gridmerge.bench.plots import PLOTS
from gridmerge.cli import bench as cli_bench
from gridmerge.errors import GridMergeError, OutputError


def _tiny():
    """One easy positive and one negative small simulated pair, and the Table I case."""
    sim = datasets.simulated(n=2, seed=1, negatives=0.5, sources=("building",), building_shapes=((360, 480),))
    return [sim, datasets.paper()]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    base = tmp_path_factory.mktemp("bench")
    calls = []
    r1 = runner.run(
        ["sift", "no-such-method"], _tiny(), seed=3, out_dir=base / "run1",
        progress=lambda done, total, label: calls.append((done, total, label)),
    )
    r2 = runner.run("sift", _tiny(), seed=3, out_dir=base / "run2", plots=False)
    return r1, r2, calls


def test_run_writes_every_file(runs):
    r1, _, calls = runs
    out = r1.out_dir
    for name in runner.FILES:
        assert (out / name).is_file(), name
    for name in PLOTS:
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
    assert not (out / "cases.jsonl.partial").exists()
    lines = (out / "cases.jsonl").read_text().splitlines()
    assert len(lines) == 3  # 3 cases x 1 registered method
    recs = [json.loads(line) for line in lines]
    assert [r["case_id"] for r in recs] == ["simulated/0000", "simulated/0001", "paper/table1-seed0"]
    assert all(r["method"] == "sift" for r in recs)
    assert recs[2]["success"] and recs[2]["precise"]  # the paper's experiment
    assert not recs[1]["positive"]
    assert all(r["wall_s"] > 0 and r["peak_mb"] > 0 for r in recs)
    assert calls[0] == (0, 3, "simulated/0000 sift") and calls[-1] == (3, 3, "")

    summary = json.loads((out / "summary.json").read_text())
    assert any("no-such-method" in w for w in summary["warnings"])
    assert {(r["dataset"], r["tier"]) for r in summary["rows"]} >= {("simulated", "all"), ("simulated", "easy"), ("simulated", "negative"), ("paper", "all")}
    assert summary["table1"]["paper"]["rotation_deg"] == 29.91
    config = json.loads((out / "config.json").read_text())
    assert config["seed"] == 3 and config["methods"] == ["sift"] and config["skipped_methods"] == ["no-such-method"]
    for key in ("platform", "cpu_count", "python", "numpy", "opencv"):
        assert config["machine"][key]
    md = (out / "results.md").read_text()
    assert "| simulated | `sift` |" in md and "Table I" in md and "no-such-method" in md and "29.91" in md
    # The simulated positive (case 0) is also summed up by the walls both robots saw.
    walls = recs[0]["shared_walls"]
    assert walls > 0 and recs[1]["shared_walls"] is None
    assert "## simulated by shared walls" in md and f"| {shared_walls_group(walls)} | `sift` |" in md


def test_run_is_reproducible_and_loads_back(runs):
    r1, r2, _ = runs
    assert r1.reproducible_records() == r2.reproducible_records()
    loaded = runner.BenchRun.load(r1.out_dir)
    assert loaded.records == r1.records
    assert loaded.summary == r1.summary
    assert loaded.row("sift", "paper")["success_rate"] == 1.0


def test_compare(runs):
    r1, r2, _ = runs
    text = runner.compare(r1.out_dir, r2.out_dir)
    assert text.startswith("# Benchmark comparison")
    assert "| paper | all | `sift` |" in text
    assert "100.0 % → 100.0 % (=)" in text
    # A changed summary shows up as a difference.
    row = next(r for r in r2.summary["rows"] if r["dataset"] == "paper")
    changed = runner.BenchRun(r2.out_dir, r2.config, r2.records, {**r2.summary, "rows": [{**row, "success_rate": 0.0}]})
    text = runner.compare(r1, changed)
    assert "100.0 % → 0.0 % (-100.0 pt)" in text
    # Rows of one run only are named by method and data set (not tier by tier).
    assert "\nOnly in run 1: `sift` on simulated.\n" in text and "Only in run 2" not in text
    # Case by case: the same seed gives the same cases; a changed case is listed.
    assert "Cases in both runs: 3; outcome changed: 0; outcome kept, error moved by more than 1 px: 0." in text
    recs = [dict(r) for r in r2.records]
    recs[2].update(success=False, declined=True, confidence=0.2)  # the paper's case, now declined
    text = runner.compare(r1, runner.BenchRun(r2.out_dir, r2.config, recs, r2.summary))
    assert "Cases in both runs: 3; outcome changed: 1;" in text and "| `sift` | paper/table1-seed0 | right → declined |" in text
    # Another seed draws other simulated pairs under the same ids: only the others are compared.
    text = runner.compare(r1, runner.BenchRun(r2.out_dir, {**r2.config, "seed": 4}, recs, r2.summary))
    assert "Cases in both runs: 1; outcome changed: 1;" in text and "seeds differ (3 and 4)" in text


def test_run_refuses_to_overwrite_results(runs, tmp_path):
    r1, _, _ = runs
    with pytest.raises(OutputError):
        runner.run("paper", [datasets.paper()], out_dir=r1.out_dir)
    with pytest.raises(GridMergeError, match="no registered method"):
        runner.run(["nope"], [datasets.paper()], out_dir=tmp_path / "x")
    with pytest.raises(GridMergeError):
        runner.BenchRun.load(tmp_path)


def test_a_failing_method_is_recorded_not_fatal(tmp_path, monkeypatch):
    from gridmerge.align import METHODS, Method

    def boom(*args, **kwargs):
        raise RuntimeError("kaput")

    monkeypatch.setitem(METHODS, "boom", Method("boom", boom, None))
    r = runner.run(["boom"], [datasets.paper()], out_dir=tmp_path / "r", plots=False, memory=False)
    rec = r.records[0]
    assert rec["declined"] and not rec["success"] and rec["error"] == "RuntimeError: kaput"
    assert r.row("boom", "paper")["errors"] == 1


def test_a_case_whose_resolutions_are_unknown_is_aligned_at_any_scale():
    """Layout pairs (a blueprint of unknown pixel size) say ``resolutions_known: False``;
    the runner then aligns them as a user would with --any-scale."""
    from gridmerge import samples

    a, b, truth = samples.robot_pair(0)
    liar = b.replace(resolution=2 * b.resolution)  # a resolution that does not hold
    known = datasets.Case("t/known", "t", a, liar, truth, True, {"tier": "t"})
    unknown = datasets.Case("t/unknown", "t", a, liar, truth, True, {"tier": "t", "resolutions_known": False})
    declined, _, _, _ = runner._align_measured(known, "hybrid", 0, False)
    aligned, _, _, _ = runner._align_measured(unknown, "hybrid", 0, False)
    assert not declined.success and "--any-scale" in declined.message
    assert aligned.success


def test_a_case_whose_resolutions_are_unknown_gets_no_scale_prior(monkeypatch):
    """Nor does the refinement pull the scale towards a ratio that means nothing."""
    import importlib

    from gridmerge import samples

    align_module = importlib.import_module("gridmerge.align")
    seen = []
    real = align_module.align
    monkeypatch.setattr(align_module, "align", lambda *args, **kw: seen.append(kw) or real(*args, **kw))
    a, b, truth = samples.robot_pair(0)
    for meta in ({"tier": "t"}, {"tier": "t", "resolutions_known": False}):
        runner._align_measured(datasets.Case("t/x", "t", a, b, truth, True, meta), "hybrid", 0, False)
    assert "scale_prior" not in seen[0]  # the default
    assert seen[1]["scale_prior"] == 0.0 and seen[1]["max_scale_disagreement"] is None


# ------------------------------------------------------------------------ CLI
def _parser():
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true")
    common.add_argument("--seed", type=int, default=0)  # as the main parser's common options
    p = argparse.ArgumentParser(prog="gridmerge")
    sub = p.add_subparsers(dest="command")
    cli_bench.add_parser(sub, [common])
    return p


def test_cli_run_and_compare(tmp_path, capsys):
    p = _parser()
    out1, out2 = tmp_path / "r1", tmp_path / "r2"
    args = p.parse_args(["bench", "--dataset", "paper", "--quick", "--methods", "paper,nope", "--out", str(out1), "--no-plots"])
    assert cli_bench.run(args) == 0
    captured = capsys.readouterr()
    assert "paper" in captured.out and f"results: {out1}" in captured.out
    assert "'nope' is not registered" in captured.err
    assert "[" not in captured.err  # no progress bar: stderr is not a terminal
    assert json.loads((out1 / "config.json").read_text())["memory"] is True  # peak memory measured by default
    args = p.parse_args(["bench", "run", "--dataset", "paper", "--quick", "--methods", "paper", "--out", str(out2), "--no-plots", "--progress", "--seed", "1"])
    assert cli_bench.run(args) == 0
    captured = capsys.readouterr()
    assert "1/1" in captured.err
    assert json.loads((out2 / "config.json").read_text())["seed"] == 1
    # An existing results folder needs --force.
    with pytest.raises(OutputError):
        cli_bench.run(p.parse_args(["bench", "--dataset", "paper", "--quick", "--methods", "paper", "--out", str(out2), "--no-plots"]))
    assert cli_bench.run(p.parse_args(["bench", "--dataset", "paper", "--quick", "--methods", "paper", "--out", str(out2), "--no-plots", "--force"])) == 0
    capsys.readouterr()
    assert cli_bench.run(p.parse_args(["bench", "compare", str(out1), str(out2)])) == 0
    assert "| paper | all | `paper` |" in capsys.readouterr().out
    with pytest.raises(GridMergeError):
        cli_bench.run(p.parse_args(["bench", "compare", str(out1), str(tmp_path / "absent")]))


def test_cli_options_without_parents():
    p = argparse.ArgumentParser(prog="gridmerge")
    sub = p.add_subparsers(dest="command")
    cli_bench.add_parser(sub)
    args = p.parse_args(["bench", "--quick", "--seed", "4", "run", "--n", "3", "--dataset", "simulated", "--dataset", "halmstad"])
    assert (args.bench_quick, args.bench_seed, args.bench_n, args.bench_datasets) == (True, 4, 3, ["simulated", "halmstad"])
    args = p.parse_args(["bench"])
    assert args.bench_datasets is None and args.bench_seed == 0 and args.bench_plots and args.bench_memory
    assert not p.parse_args(["bench", "--no-memory"]).bench_memory
    assert not p.parse_args(["bench", "run", "--no-memory"]).bench_memory


def test_all_skips_the_halmstad_pairs_when_the_folder_has_none(tmp_path):
    """A data folder without annotated Halmstad maps runs the other data sets, and says so."""
    from gridmerge.bench.runner import _resolve_datasets

    sets, notes = _resolve_datasets("all", seed=0, n=1, quick=True, data_dir=tmp_path)
    assert [ds.name for ds in sets] == ["simulated", "paper"]
    assert notes == [f"{name} skipped: no annotated maps in {tmp_path / 'halmstad'}" for name in ("halmstad", "halmstad-partial")]


def test_dataset_names_choose_halmstad_environments(tmp_path, capsys):
    """``--dataset halmstad:ENV`` runs those environments; a bad name is one line."""
    import cv2
    import numpy as np

    root = tmp_path / "halmstad"
    for env in ("AA", "BB"):
        (root / env).mkdir(parents=True)
        img = np.full((30, 40), 127, np.uint8)
        img[5:25, 5:35] = 255
        img[5, 5:35] = 0
        for k in (1, 2):
            cv2.imwrite(str(root / env / f"{env}_{k:02d}.png"), img)
        pair = {"a": f"{env}_01", "b": f"{env}_02", "kind": "sensor", "points_a": [[1.0, 1.0]], "points_b": [[1.0, 1.0]],
                "fit_b_to_a": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], "fit_median_residual_px": 1.0}
        (root / f"{env}_pairs.json").write_text(json.dumps({"pairs": [pair]}))
    one = datasets.load("halmstad:BB", data_dir=tmp_path)
    assert [one[k].id for k in range(len(one))] == ["halmstad/BB_01-BB_02"]
    both = datasets.load("halmstad:AA+BB", data_dir=tmp_path)
    assert len(both) == 2 + 4  # two sensor pairs, 2 x 2 cross pairs
    assert cli_bench._dataset_name("halmstad:AA+BB") == "halmstad:AA+BB"
    for bad in ("halmstad:", "halmstad:AA+", "simulation"):
        with pytest.raises(argparse.ArgumentTypeError):
            cli_bench._dataset_name(bad)
    from gridmerge.cli.main import main

    code = main(["bench", "--dataset", "halmstad:CC", "--data", str(tmp_path), "--out", str(tmp_path / "run"), "--methods", "orb"])
    err = capsys.readouterr().err
    assert code not in (0, 1) and "CC_pairs.json" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "run" / "cases.jsonl").exists()


def test_swapped_dataset_names():
    for ok in ("halmstad-swapped", "simulated-swapped", "halmstad:E5-swapped", "paper-swapped"):
        assert cli_bench._dataset_name(ok) == ok
    for bad in ("all-swapped", "-swapped", "nothing-swapped"):
        with pytest.raises(argparse.ArgumentTypeError):
            cli_bench._dataset_name(bad)


# ------------------------------------------------------------- options
def test_options_reach_gridmerge_methods_only(monkeypatch):
    """``options`` change our methods' AlignOptions; a baseline keeps its own rule; a
    blueprint case still gets any scale."""
    import importlib

    from gridmerge import samples

    align_module = importlib.import_module("gridmerge.align")
    seen = []
    real = align_module.align
    monkeypatch.setattr(align_module, "align", lambda *args, **kw: seen.append(kw) or real(*args, **kw))
    a, b, truth = samples.robot_pair(0)
    case = datasets.Case("t/x", "t", a, b, truth, True, {"tier": "t"})
    blueprint = datasets.Case("t/y", "t", a, b, truth, True, {"tier": "t", "resolutions_known": False})
    options = {"min_confidence": 0.9, "one_sided_confidence": 0.95}
    runner._align_measured(case, "hybrid", 0, False, options)
    runner._align_measured(case, "orb", 0, False, options)
    runner._align_measured(blueprint, "hybrid", 0, False, options)
    assert seen[0]["min_confidence"] == 0.9 and seen[0]["one_sided_confidence"] == 0.95
    assert "min_confidence" not in seen[1] and "one_sided_confidence" not in seen[1]
    assert seen[2]["min_confidence"] == 0.9 and seen[2]["scale_prior"] == 0.0


def test_a_run_with_options_records_and_applies_them(runs, tmp_path):
    _, default, _ = runs  # sift on the tiny cases, seed 3, default options
    strict = runner.run("sift", _tiny(), seed=3, out_dir=tmp_path / "strict", plots=False, memory=False,
                        options={"min_confidence": 0.9995})
    assert strict.config["options"] == {"min_confidence": 0.9995}
    assert default.config["options"] == {}
    assert "`min_confidence` = 0.9995" in (tmp_path / "strict" / "results.md").read_text()
    # The same candidates, judged against the higher threshold.
    for d, s in zip(default.records, strict.records):
        assert d["case_id"] == s["case_id"] and d["confidence"] == s["confidence"]
        assert s["aligned"] == (d["aligned"] and d["confidence"] >= 0.9995)
    assert any(d["aligned"] and not s["aligned"] for d, s in zip(default.records, strict.records))
    text = runner.compare(default, strict)
    assert "run 1 defaults; run 2 `min_confidence` = 0.9995" in text
    assert "Options of" not in runner.compare(default, default)


def test_options_must_be_align_options(tmp_path):
    with pytest.raises(GridMergeError, match="min_confidance"):
        runner.run("sift", [datasets.paper()], out_dir=tmp_path / "x", options={"min_confidance": 0.4})
    assert not (tmp_path / "x").exists()


def test_cli_decline_thresholds(tmp_path):
    p = _parser()
    args = p.parse_args(["bench", "--min-confidence", "0.4", "run", "--one-sided-confidence", "0.7"])
    assert (args.bench_min_confidence, args.bench_one_sided_confidence) == (0.4, 0.7)
    for bad in ("1.2", "-1", "x"):
        with pytest.raises(SystemExit):
            p.parse_args(["bench", "--min-confidence", bad])
    out = tmp_path / "r"
    args = p.parse_args(["bench", "--dataset", "paper", "--quick", "--methods", "paper", "--out", str(out), "--no-plots",
                         "--min-confidence", "0.7"])
    assert cli_bench.run(args) == 0
    assert json.loads((out / "config.json").read_text())["options"] == {"min_confidence": 0.7}


def test_cli_simulates_the_robots_in_the_users_maps(tmp_path, capsys):
    """``--source-map`` (repeatable) makes the simulated pairs of those maps; the run
    names them; a missing file or a data set that does not simulate is one line."""
    import cv2
    import numpy as np

    from gridmerge import save_map, samples
    from gridmerge.cli.main import main

    one = save_map(samples.building(21, (360, 480)), tmp_path / "one.yaml")
    two = tmp_path / "two.png"
    cv2.imwrite(str(two), samples.building(22, (360, 480)).render(unknown=205))
    tiny = tmp_path / "tiny.png"
    room = np.zeros((60, 60), np.uint8)
    room[5:55, 5:55] = 254
    cv2.imwrite(str(tiny), room)  # one room: no two distant parts for a negative pair
    out = tmp_path / "run"
    code = main(["bench", "--dataset", "simulated", "--n", "2", "--methods", "orb", "--no-plots", "--no-memory",
                 "--source-map", str(one), "--source-map", str(two), "--out", str(out)])
    assert code == 0
    capsys.readouterr()
    config = json.loads((out / "config.json").read_text())
    (sim,) = config["datasets"]
    assert [m["path"] for m in sim["params"]["source_maps"]] == [str(one.resolve()), str(two.resolve())]
    cases = [json.loads(line) for line in (out / "cases.jsonl").read_text().splitlines()]
    assert len(cases) == 2 and {c["source"] for c in cases} <= {"file:" + str(one.resolve()), "file:" + str(two.resolve())}
    assert "source maps one.yaml two.png" in (out / "results.md").read_text()
    for args, message in (
        (["--dataset", "simulated", "--source-map", str(tmp_path / "nope.yaml")], "source map not found"),
        (["--dataset", "paper", "--source-map", str(one)], "for the simulated data set only"),
        (["--dataset", "simulated", "--n", "5", "--source-map", str(tiny)], "too small for a negative pair"),
    ):
        code = main(["bench", *args, "--methods", "orb", "--no-plots", "--out", str(tmp_path / "bad")])
        err = capsys.readouterr().err
        assert code not in (0, 1) and message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
        assert not (tmp_path / "bad").exists()  # refused before the results folder is made


@pytest.fixture(scope="module")
def named_run(tmp_path_factory):
    """A run whose data sets were given by name (simulated in a map file, and Table I)."""
    from gridmerge import save_map, samples

    base = tmp_path_factory.mktemp("named")
    source = save_map(samples.building(31, (360, 480)), base / "office.yaml")
    bench = runner.run("orb,sift", ["simulated", "paper"], seed=2, n=3, quick=True, out_dir=base / "run", plots=False,
                       memory=False, source_maps=[source])
    return bench, source


def test_a_case_is_built_again_and_aligned_as_the_run_did(named_run):
    bench, source = named_run
    case = runner.rebuild_case(bench.out_dir, "simulated/0002")
    original = datasets.simulated(n=3, seed=2, source_maps=[source])[2]
    assert case.a == original.a and case.b == original.b and case.meta == original.meta
    assert runner.rebuild_case(bench, "paper/table1-seed0").id == "paper/table1-seed0"
    for cid in ("simulated/0000", "simulated/0002"):
        rec = next(r for r in bench.records if r["case_id"] == cid and r["method"] == "sift")
        _, result = runner.replay(bench, cid, "sift")
        assert result.confidence == rec["confidence"]
        if rec["estimate"] is not None:
            assert result.matrix.tolist() == rec["estimate"]["matrix"]
    with pytest.raises(GridMergeError, match="no case"):
        runner.rebuild_case(bench, "simulated/0099")
    with pytest.raises(GridMergeError, match="was not run"):
        runner.replay(bench, "simulated/0000", "hybrid")


def test_a_case_of_a_data_set_given_as_an_object_is_not_passed_off(runs):
    r1, _, _ = runs  # its simulated set was built with its own shapes, not by name
    with pytest.raises(GridMergeError, match="differs|cannot be built"):
        runner.rebuild_case(r1, "simulated/0000")


def test_cli_bench_case_writes_the_maps_and_the_replay(named_run, tmp_path, capsys):
    from gridmerge import load_map
    from gridmerge.cli.main import main

    bench, _ = named_run
    out = tmp_path / "case"
    assert main(["bench", "case", str(bench.out_dir), "simulated/0000", "--method", "sift", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "simulated/0000" in printed and "sift:" in printed
    case = runner.rebuild_case(bench, "simulated/0000")
    assert load_map(out / "a.yaml") == case.a and load_map(out / "b.yaml") == case.b
    info = json.loads((out / "case.json").read_text())
    rec = next(r for r in bench.records if r["case_id"] == "simulated/0000" and r["method"] == "sift")
    assert info["replayed"]["confidence"] == rec["confidence"] and info["positive"] is True
    assert len(info["records"]) == 2 and info["truth_b_to_a"] is not None
    assert (out / "merge.png").is_file() == rec["aligned"]
    # The maps on each other at the truth, and at the replayed pose (or declined candidate).
    for name in ("truth.png", "pose.png"):
        assert (out / name).read_bytes().startswith(b"\x89PNG\r\n\x1a\n") and f"picture: {out / name}" in printed
    assert main(["bench", "case", str(bench.out_dir), "simulated/0000", "--out", str(out)]) == 2  # files there: --force
    assert main(["bench", "case", str(bench.out_dir), "simulated/0000", "--out", str(out), "--force"]) == 0
    assert main(["bench", "case", str(bench.out_dir), "halmstad/X-Y", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "no case 'halmstad/X-Y'" in err and "Traceback" not in err


def test_moved_source_maps_are_found_by_name_and_checked_by_their_cells(named_run, tmp_path):
    import shutil

    from gridmerge import save_map, samples

    bench, source = named_run
    moved = tmp_path / "moved"
    moved.mkdir()
    for suffix in (".yaml", ".pgm"):
        shutil.copy2(source.with_suffix(suffix), moved / source.with_suffix(suffix).name)
    case = runner.rebuild_case(bench, "simulated/0001", maps_dir=moved)
    assert case.b == runner.rebuild_case(bench, "simulated/0001").b
    other = tmp_path / "other"
    other.mkdir()
    save_map(samples.building(32, (360, 480)), other / source.name)  # same name, another building
    with pytest.raises(GridMergeError, match="not the one the run used"):
        runner.rebuild_case(bench, "simulated/0001", maps_dir=other)
    with pytest.raises(GridMergeError, match="source map not found"):
        runner.rebuild_case(bench, "simulated/0001", maps_dir=tmp_path / "nowhere")


def test_cli_bend_is_one_line_when_wrong(tmp_path, capsys):
    """``--bend PX`` bends the simulated set's robot b maps (datasets.simulated); a
    negative bend, or bending a data set that does not simulate, is one line and no
    results folder."""
    from gridmerge.cli.main import main

    for args, message in (
        (["--dataset", "simulated", "--bend", "-1"], "0 or more"),
        (["--dataset", "paper", "--bend", "2"], "for the simulated data set only"),
    ):
        code = main(["bench", *args, "--methods", "orb", "--no-plots", "--out", str(tmp_path / "bad")])
        err = capsys.readouterr().err
        assert code not in (0, 1) and message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
        assert not (tmp_path / "bad").exists()

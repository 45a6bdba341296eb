"""The CI slice of the benchmark, through the real command line: small and fast, but it
asserts what the default method achieves on it."""

import json

from gridmerge.cli.main import main


def test_quick_simulated_slice_default_method(tmp_path):
    out = tmp_path / "run"
    # (--no-memory: tracing every allocation makes the calls 1.7x slower.)
    code = main(["bench", "--quick", "--dataset", "simulated", "--dataset", "paper", "--methods", "hybrid", "--out", str(out),
                 "--no-plots", "--no-memory"])
    assert code == 0
    assert json.loads((out / "config.json").read_text())["memory"] is False
    assert "hybrid" in (out / "summary.json").read_text()
    records = [json.loads(line) for line in (out / "cases.jsonl").read_text().splitlines()]
    pos = [r for r in records if r["dataset"] == "simulated" and r["positive"]]
    neg = [r for r in records if r["dataset"] == "simulated" and not r["positive"]]
    assert pos and neg
    assert sum(r["success"] for r in pos) >= len(pos) - 1  # the quick slice is easy and medium
    assert not any(r["aligned"] for r in neg)  # no false merge
    assert all(r["peak_mb"] is None and r["wall_s"] > 0 for r in records)
    paper = [r for r in records if r["dataset"] == "paper"]
    assert paper and all(r["precise"] for r in paper)

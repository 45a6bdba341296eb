"""``gridmerge bench fleet``: fleet timings, the incremental update, real fleets."""

import json

import pytest

from gridmerge.bench.datasets import resolve_data_dir
from gridmerge.bench.fleet import halmstad_fleet, simulate_fleet
from gridmerge.cli.main import main


def test_fleet_simulator_gives_exact_truth_and_own_frames():
    fleet = simulate_fleet(3, seed=1, shape=(400, 500), scales=(1.0, 0.5, 2.0))
    assert [m.resolution for m in fleet.maps] == pytest.approx([0.05, 0.025, 0.1])
    assert len({round(r, 3) for r in fleet.meta["rotations_deg"]}) == 3
    # Same seed, same fleet.
    again = simulate_fleet(3, seed=1, shape=(400, 500), scales=(1.0, 0.5, 2.0))
    for m, n in zip(fleet.maps, again.maps):
        assert m == n


def test_bench_fleet_command_writes_its_results(tmp_path, capsys):
    out = tmp_path / "fleet"
    code = main(["bench", "fleet", "--robots", "2,3", "--workers", "1", "--no-halmstad", "--out", str(out)])
    assert code == 0
    d = json.loads((out / "fleet.json").read_text())
    assert [r["robots"] for r in d["rows"]] == [2, 3]
    assert all(r["placed"] == r["robots"] and r["max_error_px"] <= 2.0 for r in d["rows"])
    u = d["update"]
    assert u["robots"] == 3 and u["features_computed"] == 1 and u["pairs_searched"] == 0
    assert "Update of one map" in (out / "fleet.md").read_text()
    assert main(["bench", "fleet", "--robots", "2", "--out", str(out)]) == 2  # results there: --force
    assert main(["bench", "fleet", "--robots", "0", "--out", str(tmp_path / "x")]) == 2


@pytest.mark.shared
def test_the_apartment_maps_merge_as_one_fleet():
    if resolve_data_dir() is None:
        pytest.skip("needs ../shared/data")
    r = halmstad_fleet("HIH")
    assert r["placed"] == r["maps"] == 4 and r["wrong"] == 0 and r["right"] == r["pairs"] == 6


def test_real_fleets_are_every_environment_of_the_folder_smallest_first(tmp_path):
    import cv2
    import numpy as np

    from gridmerge.bench.fleet import _halmstad_fleets

    root = tmp_path / "halmstad"
    for env, names in {"BIG": ["BIG_1", "BIG_2", "BIG_10"], "AA": ["AA_01", "AA_02", "AA_03"], "SMALL": ["SMALL_01", "SMALL_02"]}.items():
        (root / env).mkdir(parents=True)
        (root / f"{env}_pairs.json").write_text('{"pairs": []}')
        for name in names:
            cv2.imwrite(str(root / env / f"{name}.png"), np.full((8, 8), 255, np.uint8))
    assert _halmstad_fleets(tmp_path) == ["SMALL", "AA", "BIG"]
    (tmp_path / "other").mkdir()
    assert _halmstad_fleets(tmp_path / "other") == []  # a data folder without Halmstad maps


def test_bench_fleet_in_a_map_file(tmp_path, capsys):
    """``--source`` takes a map file as well as a source map's name."""
    from gridmerge import save_map, samples

    path = save_map(samples.building(5, (400, 500)), tmp_path / "office.yaml")
    out = tmp_path / "fleet"
    code = main(["bench", "fleet", "--robots", "2", "--workers", "1", "--no-halmstad", "--source", str(path), "--out", str(out)])
    assert code == 0
    d = json.loads((out / "fleet.json").read_text())
    assert d["rows"][0]["robots"] == 2 and d["rows"][0]["placed"] == 2
    assert str(path.resolve()) in json.dumps(d)
    assert main(["bench", "fleet", "--robots", "2", "--source", str(tmp_path / "nope.yaml"), "--out", str(tmp_path / "x")]) == 2

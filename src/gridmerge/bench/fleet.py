"""Simulated fleets: N robots explore one building, each mapping in its own frame.

The benchmark's pair generator (:mod:`gridmerge.bench.datasets`), extended to a team:
viewpoints in the source map's free space are shared out among ``n`` robots (each robot
takes the viewpoints of its own part of the building, grown so that neighbouring robots
see some of the same rooms), and each robot ray-casts what its laser sees and maps it in
its own frame: any rotation, a shift, and cells ``scale`` times the source's (its
``resolution`` says so). The ground truth of every map is exact.

Examples
--------
>>> from gridmerge.bench.fleet import simulate_fleet
>>> fleet = simulate_fleet(3, seed=0, shape=(300, 400))
>>> len(fleet.maps), [m.name for m in fleet.maps]
(3, ['robot1', 'robot2', 'robot3'])
>>> fleet.relative(0, 1).shape          # robot2's pixels -> robot1's pixels
(3, 3)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

from .. import samples
from ..grid import OccupancyGrid
from ..transforms import corner_error
from .datasets import SEE_THROUGH, _World, _robot_in_frame, source_map

__all__ = ["Fleet", "FleetBenchmark", "simulate_fleet", "placement_errors", "earlier_version", "benchmark"]


@dataclass
class Fleet:
    """Maps of a simulated team, with their exact ground truth.

    Attributes
    ----------
    maps : list of OccupancyGrid
        Robot ``k``'s map, named ``robot{k+1}``, in its own frame.
    to_source : list of (3, 3) float array
        Robot ``k``'s image pixels -> the source map's image pixels.
    source : OccupancyGrid
        The map the robots explored.
    meta : dict
        How the fleet was made (rotations, scales, viewpoints per robot).
    """

    maps: list[OccupancyGrid]
    to_source: list[np.ndarray]
    source: OccupancyGrid
    meta: dict = field(default_factory=dict)

    def relative(self, i: int, j: int) -> np.ndarray:
        """(3, 3) float array: robot ``j``'s pixels -> robot ``i``'s pixels."""
        return np.linalg.inv(self.to_source[i]) @ self.to_source[j]


def _homes(vps: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` viewpoints spread over the building (farthest-point sampling)."""
    first = int(rng.integers(len(vps)))
    chosen = [first]
    d = np.hypot(*(vps - vps[first]).T)
    for _ in range(n - 1):
        k = int(np.argmax(d))
        chosen.append(k)
        d = np.minimum(d, np.hypot(*(vps - vps[k]).T))
    return vps[chosen]


def simulate_fleet(
    n: int = 8,
    seed: int = 0,
    *,
    source: Optional[str | OccupancyGrid] = None,
    shape: Sequence[int] = (600, 800),
    share: float = 0.6,
    scales: Optional[Sequence[float]] = None,
    noise: float = 0.0,
    data_dir=None,
    see_through: int = SEE_THROUGH,
) -> Fleet:
    """Maps of ``n`` robots that explored one building together.

    Parameters
    ----------
    n : int
        Robots (at least 1).
    seed : int
        Seed of everything: the building (when procedural), viewpoints, frames, noise.
    source : str or OccupancyGrid, optional
        The building: a map, or the name of a benchmark source map
        (:func:`gridmerge.bench.datasets.source_names`, e.g. ``"willow"``); default a
        procedural building of ``shape`` (``samples.building(seed, shape)``).
    share : float
        How far each robot's part reaches into its neighbours': a viewpoint belongs to
        every robot whose home is at most ``1 + share`` times as far as the nearest home.
    scales : sequence of float, optional
        Each robot's cell size over the source's (its map's resolution is the source's
        times it); default 1 for all. E.g. ``(0.4, 1, 2)`` for 0.02, 0.05 and 0.1 m/cell
        robots in a 0.05 m/cell building.
    noise : float
        Missed wall hits (spurious hits ``noise / 50``), as in the benchmark's tiers.
    see_through : int
        Unknown cells of the source a scanner ray crosses
        (:data:`gridmerge.bench.datasets.SEE_THROUGH`; 0: the fleets as built until
        2026-11-30).

    Returns
    -------
    Fleet
    """
    if n < 1:
        raise ValueError(f"a fleet needs at least one robot, got {n}")
    rng = np.random.default_rng([int(seed), int(n), 11])
    if source is None:
        grid = samples.building(seed, shape)
        label = f"building{seed}"
    elif isinstance(source, OccupancyGrid):
        grid, label = source, source.name or "source"
    else:
        grid, label = source_map(source, data_dir), source
    world = _World(grid, label, see_through)
    k = int(np.clip(round(world.area / 2500.0), 6 * n, 40 * n))
    vps = samples.random_viewpoints(grid, k, rng=rng, region=world.region, clearance=5.0)
    homes = _homes(vps, n, rng)
    dist = np.hypot(vps[:, None, 0] - homes[None, :, 0], vps[:, None, 1] - homes[None, :, 1])
    nearest = dist.min(axis=1, keepdims=True)
    member = dist <= (1.0 + share) * nearest + 1e-9
    scale_list = list(scales) if scales is not None else [1.0] * n
    if len(scale_list) != n:
        raise ValueError(f"{len(scale_list)} scales for {n} robots")
    maps, to_source, rotations, counts = [], [], [], []
    for r in range(n):
        mine = vps[member[:, r]]
        if len(mine) < 3:  # a robot sees at least its three viewpoints nearest home
            mine = vps[np.argsort(dist[:, r])[:3]]
        rot = float(rng.uniform(-180.0, 180.0))
        b, M, _ = _robot_in_frame(world, mine, rng, rotation_deg=rot, scale=float(scale_list[r]), noise=noise)
        maps.append(b.replace(name=f"robot{r + 1}"))
        to_source.append(M)
        rotations.append(rot)
        counts.append(int(len(mine)))
    meta = {"source": label, "seed": int(seed), "rotations_deg": rotations, "scales": scale_list, "views": counts,
            "share": share, "noise": noise}
    return Fleet(maps, to_source, grid, meta)


def placement_errors(fleet: Fleet, transforms: Sequence, reference: int = 0) -> list[Optional[float]]:
    """Each map's placement error: the corner error (reference pixels) of its transform
    relative to the reference's, against the truth; ``None`` for unplaced maps.

    ``transforms`` are the merge's (:attr:`gridmerge.MergeResult.transforms`): each map's
    pixels -> the merged map's pixels.
    """
    ref = transforms[reference]
    out: list[Optional[float]] = []
    for k, t in enumerate(transforms):
        if t is None or ref is None:
            out.append(None)
            continue
        est = np.linalg.inv(ref.params) @ t.params
        out.append(float(corner_error(est, fleet.relative(reference, k), fleet.maps[k].shape)))
    return out


def earlier_version(grid: OccupancyGrid, keep: float = 0.7, direction_deg: float = 0.0) -> OccupancyGrid:
    """What ``grid`` looked like earlier in its robot's run: only the known cells of the
    first ``keep`` of its extent along ``direction_deg`` (image axes), cut to what it
    knows. Like a growing SLAM map, the earlier version is smaller, its origin differs,
    and every cell keeps its metric coordinates.
    """
    known = grid.known
    ys, xs = np.nonzero(known)
    if len(xs) == 0:
        return grid
    t = math.radians(direction_deg)
    proj = xs * math.cos(t) + ys * math.sin(t)
    cut = proj.min() + keep * (proj.max() - proj.min())
    data = grid.data.copy()
    drop = proj > cut
    data[ys[drop], xs[drop]] = np.nan
    earlier, _ = grid.replace(data=data).crop_known(10)
    return earlier


# ------------------------------------------------------------------ benchmark
@dataclass
class FleetBenchmark:
    """Merge time and placement accuracy of fleets of several sizes (``gridmerge bench fleet``).

    Attributes
    ----------
    rows : list of dict
        One per (robots, workers): ``robots``, ``workers``, ``merge_s``, ``placed``,
        ``max_error_px``, ``median_error_px``, ``pairs_searched``, ``pairs_predicted``,
        ``speedup`` (over one worker).
    update : dict
        One robot of the largest fleet of at most 8 re-merged after its map grew:
        ``full_s`` (first merge, the robot's earlier map), ``update_s`` (the re-merge),
        ``fraction`` and the work counters.
    config : dict
    """

    rows: list
    update: dict
    config: dict
    real: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"config": self.config, "rows": self.rows, "update": self.update, "real": self.real}

    def to_markdown(self) -> str:
        lines = [
            "| robots | workers | merge (s) | speed-up | placed | max error (px) | median error (px) | pairs searched | pairs verified at a predicted pose |",
            "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
        ]
        for r in self.rows:
            lines.append(
                f"| {r['robots']} | {r['workers']} | {r['merge_s']:.2f} | {r['speedup']:.2f} | {r['placed']}/{r['robots']} | "
                f"{_fmt(r['max_error_px'])} | {_fmt(r['median_error_px'])} | {r['pairs_searched']} | {r['pairs_predicted']} |"
            )
        u = self.update
        if u:
            lines += [
                "",
                f"Update of one map among {u['robots']} (its map grew from {u['earlier_cells']} to {u['cells']} cells): "
                f"full merge {u['full_s']:.2f} s, incremental re-merge {u['update_s']:.2f} s "
                f"(**{100 * u['fraction']:.0f} %** of the full merge); features recomputed {u['features_computed']}, "
                f"pairs searched {u['pairs_searched']}, re-verified {u['pairs_reverified']}, reused {u['pairs_reused']}; "
                f"max placement error after the update {_fmt(u['max_error_px'])} px.",
            ]
        if self.real:
            lines += [
                "",
                "Real fleets: every sensor map of a Halmstad environment merged at once, judged on the annotated pairs "
                "(the data set's protocol, on each pair's relative transform in the merged map):",
                "",
                "| environment | maps | placed | annotated pairs | right | wrong | not placed | alignments dropped by the loops | merge (s) |",
                "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
            ]
            for r in self.real:
                lines.append(
                    f"| {r['environment']} | {r['maps']} | {r['placed']} | {r['pairs']} | {r['right']} | {r['wrong']} | "
                    f"{r['not_placed']} | {r['dropped_edges']} | {r['merge_s']:.1f} |"
                )
            wrong = [f"{x['a']}-{x['b']} ({x['error_px']:.0f} px, tolerance {x['tolerance_px']:.0f})"
                     for r in self.real for x in r["per_pair"] if x["outcome"] == "wrong"]
            if wrong:
                lines += ["", "Pairs outside the tolerance: " + ", ".join(wrong) + "."]
        return "\n".join(lines) + "\n"

    def save(self, folder) -> None:
        """Write ``fleet.json`` and ``fleet.md`` into ``folder`` (atomically each)."""
        import json
        from pathlib import Path

        from ..io.atomic import atomic_write

        out = Path(folder)
        out.mkdir(parents=True, exist_ok=True)
        atomic_write(out / "fleet.json", (json.dumps(self.to_dict(), indent=2) + "\n").encode())
        atomic_write(out / "fleet.md", self.to_markdown().encode())


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.2f}"


def benchmark(
    robots: Sequence[int] = (2, 4, 8, 16),
    workers: Sequence[int] = (1, 2),
    *,
    seed: int = 0,
    source: Optional[str | OccupancyGrid] = None,
    shape: Sequence[int] = (800, 1100),
    progress=None,
    halmstad: Optional[Sequence[str]] = None,
    data_dir=None,
) -> FleetBenchmark:
    """Time fleet merges of each size with each number of workers, and one update.

    Parameters
    ----------
    robots : sequence of int
        Fleet sizes; each fleet is :func:`simulate_fleet` ``(n, seed, source=source)``.
    halmstad : sequence of str, optional
        Halmstad environments merged as real fleets (:func:`halmstad_fleet`), when the
        shared data is there. Default: every one in it
        (:func:`gridmerge.bench.datasets.halmstad_environments`; HIH and E5), the
        smallest fleet first; ``()`` for none.
    workers : sequence of int
        Process-pool sizes (1: serial).
    source, shape
        The building (default a procedural one of ``shape``).
    progress : callable, optional
        ``progress(done, total, label)``.
    """
    import time

    from ..merge import Merger, merge
    from ..parallel import executor_for

    rows = []
    total = len(robots) * len(workers) + 1
    done = 0
    fleets = {}
    for n in robots:
        fleets[n] = simulate_fleet(n, seed, source=source, shape=shape)
        base = None
        for w in workers:
            if progress is not None:
                progress(done, total, f"{n} robots, {w} worker(s)")
            with executor_for(w) as ex:
                if w > 1:  # start the pool's processes before timing
                    ex.map(abs, list(range(w)))
                t0 = time.perf_counter()
                r = merge(fleets[n].maps, rng=seed, executor=ex)
                dt = time.perf_counter() - t0
            done += 1
            errors = [e for e in placement_errors(fleets[n], r.transforms) if e is not None] if r.success else []
            base = dt if base is None else base
            rows.append({
                "robots": n,
                "workers": w,
                "merge_s": round(dt, 3),
                "speedup": round(base / dt, 3) if dt > 0 else None,
                "placed": len(errors),
                "max_error_px": round(max(errors), 3) if errors else None,
                "median_error_px": round(float(np.median(errors)), 3) if errors else None,
                "pairs_searched": r.stats.pairs_searched,
                "pairs_predicted": r.stats.pairs_predicted,
            })
    # One map of the fleet grows: the incremental re-merge against a full one.
    n_up = max([n for n in robots if n <= 8] or [min(robots)])
    fl = fleets[n_up]
    k = n_up // 2
    earlier = earlier_version(fl.maps[k], keep=0.6, direction_deg=30.0)
    if progress is not None:
        progress(done, total, f"update of one map among {n_up}")
    merger = Merger(rng=seed)
    for j, g in enumerate(fl.maps):
        merger.update(earlier if j == k else g)
    t0 = time.perf_counter()
    merger.merge()
    full = time.perf_counter() - t0
    merger.update(fl.maps[k])
    t0 = time.perf_counter()
    r = merger.merge()
    upd = time.perf_counter() - t0
    errors = [e for e in placement_errors(fl, r.transforms) if e is not None] if r.success else []
    update = {
        "robots": n_up,
        "map": fl.maps[k].name,
        "earlier_cells": int(earlier.known.sum()),
        "cells": int(fl.maps[k].known.sum()),
        "full_s": round(full, 3),
        "update_s": round(upd, 3),
        "fraction": round(upd / full, 4) if full > 0 else None,
        "placed": len(errors),
        "max_error_px": round(max(errors), 3) if errors else None,
        **{key: getattr(r.stats, key) for key in ("features_computed", "pairs_searched", "pairs_reverified", "pairs_reused", "pairs_predicted")},
    }
    if progress is not None:
        progress(total, total, "")
    import os
    import platform

    real = []
    from .datasets import resolve_data_dir

    if halmstad is None:
        halmstad = _halmstad_fleets(data_dir)
    if halmstad and resolve_data_dir(data_dir) is not None:
        for env in halmstad:
            if progress is not None:
                progress(total, total + 1, f"Halmstad {env} fleet")
            real.append(halmstad_fleet(env, data_dir=data_dir, seed=seed))
    config = {"robots": list(robots), "workers": list(workers), "seed": seed, "source": fleets[robots[0]].meta["source"],
              "shape": list(shape), "machine": platform.machine(), "cpus": os.cpu_count(), "python": platform.python_version()}
    return FleetBenchmark(rows, update, config, real)


def _halmstad_fleets(data_dir) -> list:
    """Every Halmstad environment of the data folder, the one with fewest sensor maps first."""
    from .datasets import _sensor_stems, halmstad_environments, resolve_data_dir

    d = resolve_data_dir(data_dir)
    if d is None:
        return []
    return sorted(halmstad_environments(d), key=lambda env: (len(_sensor_stems(d / "halmstad", env)), env))


def halmstad_fleet(env: str = "E5", *, data_dir=None, seed: int = 0, executor=None, progress=None) -> dict:
    """Merge every sensor map of a Halmstad environment at once, as one fleet.

    Scored on the annotated pairs with the data set's protocol (median point error at
    most ``max(20, 2 x fit_median_residual_px)``): for every annotated sensor pair whose
    two maps were both placed, the merge's relative transform ``T_a^-1 T_b`` is judged;
    a pair with a map left unplaced is *not placed*, never wrong.

    Returns
    -------
    dict
        ``maps``, ``placed``, ``unplaced`` (names), ``pairs`` (annotated sensor pairs),
        ``right``, ``wrong``, ``not_placed``, ``merge_s``, ``per_pair`` (list of dicts).
    """
    import json
    import time
    from pathlib import Path

    from ..io import load_map
    from ..merge import merge
    from .datasets import _sensor_stems, resolve_data_dir
    from .metrics import halmstad_point_error

    root = resolve_data_dir(data_dir)
    if root is None:
        raise FileNotFoundError("the Halmstad maps need ../shared/data (see --data)")
    folder = Path(root) / "halmstad"
    spec = json.loads((folder / f"{env}_pairs.json").read_text())
    stems = _sensor_stems(folder, env)
    maps = [load_map(folder / env / f"{s}.png").replace(name=s) for s in stems]
    t0 = time.perf_counter()
    r = merge(maps, rng=seed, executor=executor, progress=progress)
    dt = time.perf_counter() - t0
    index = {s: k for k, s in enumerate(stems)}
    rows = []
    for p in spec["pairs"]:
        if p["kind"] != "sensor":
            continue
        ka, kb = index[p["a"]], index[p["b"]]
        ta, tb = r.transforms[ka], r.transforms[kb]
        row = {"a": p["a"], "b": p["b"]}
        if ta is None or tb is None:
            row["outcome"] = "not placed"
        else:
            err = halmstad_point_error(np.linalg.inv(ta.params) @ tb.params, p["points_a"], p["points_b"])
            tol = max(20.0, 2.0 * float(p["fit_median_residual_px"]))
            row.update(error_px=round(err, 2), tolerance_px=tol, outcome="right" if err <= tol else "wrong")
        rows.append(row)
    count = {o: sum(1 for x in rows if x["outcome"] == o) for o in ("right", "wrong", "not placed")}
    return {
        "environment": env,
        "maps": len(maps),
        "placed": len(r.placed),
        "unplaced": list(r.unplaced),
        "pairs": len(rows),
        "right": count["right"],
        "wrong": count["wrong"],
        "not_placed": count["not placed"],
        "merge_s": round(dt, 2),
        "dropped_edges": len(r.graph.dropped) if r.graph is not None else 0,
        "per_pair": rows,
    }

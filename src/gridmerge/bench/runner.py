"""Running the benchmark: every method on every case, results written to a folder.

:func:`run` aligns each case with each method exactly as a user would (``gridmerge.align(a,
b, method=m, rng=seed)``, no per-method tuning), scores it (:mod:`.metrics`) and writes the
results folder:

``cases.jsonl``
    One :class:`~gridmerge.bench.metrics.Record` per case and method, as JSON lines
    (written as the run goes to ``cases.jsonl.partial``, renamed at the end).
``summary.json``
    Summary rows per method, data set and tier; the Table I comparison; warnings.
``results.md``
    The same as Markdown tables.
``config.json``
    Methods, data sets, seed, versions, machine.
``*.png``
    Plots (:data:`gridmerge.bench.plots.PLOTS`), when matplotlib is installed.

A run is reproducible to the number for a seed, timings and memory aside: cases are built
from the seed, every method gets ``rng=seed``, and OpenCV's own generator (used by FLANN's
randomized kd-trees) is reset with ``cv2.setRNGSeed(seed)`` before every call.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
import tracemalloc
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Callable, Optional, Sequence, Union

import cv2
import numpy as np

from .. import __version__
from ..errors import GridMergeError, OutputError
from ..io import atomic_write
from . import datasets as _datasets
from .metrics import TIMING_FIELDS, evaluate, summarize
from .report import compare_summaries, results_markdown

__all__ = ["BenchRun", "run", "compare", "rebuild_case", "replay", "resolve_methods", "FILES"]

#: Files of a results folder (besides the plots).
FILES = ("cases.jsonl", "summary.json", "results.md", "config.json")

#: ``progress(done, total, label)``: called before each alignment (``done`` finished so
#: far) and once at the end (``done == total``, label ``""``).
Progress = Callable[[int, int, str], None]


@dataclass
class BenchRun:
    """A benchmark run: its configuration, records and summary.

    Attributes
    ----------
    out_dir : Path or None
    config : dict
    records : list of dict
        One per case and method (:meth:`~gridmerge.bench.metrics.Record.to_dict`).
    summary : dict
        ``rows`` (:func:`~gridmerge.bench.metrics.summarize`), ``table1``,
        ``warnings``, ``notes``.
    """

    out_dir: Optional[Path]
    config: dict
    records: list
    summary: dict

    @property
    def warnings(self) -> list:
        return list(self.summary.get("warnings", []))

    @property
    def rows(self) -> list:
        return list(self.summary.get("rows", []))

    def row(self, method: str, dataset: str, tier: str = "all") -> Optional[dict]:
        """The summary row of one method on one data set (and tier), or ``None``."""
        for r in self.rows:
            if (r["method"], r["dataset"], r["tier"]) == (method, dataset, tier):
                return r
        return None

    def reproducible_records(self) -> list:
        """The records without their timing and memory fields (equal for equal seeds)."""
        return [{k: v for k, v in r.items() if k not in TIMING_FIELDS} for r in self.records]

    @classmethod
    def load(cls, path) -> "BenchRun":
        """Read a results folder written by :func:`run`."""
        p = Path(path)
        if not p.is_dir():
            raise GridMergeError(f"not a benchmark results folder: {p}")
        try:
            config = json.loads((p / "config.json").read_text())
            summary = json.loads((p / "summary.json").read_text())
            lines = (p / "cases.jsonl").read_text().splitlines()
            records = [json.loads(line) for line in lines if line.strip()]
        except FileNotFoundError as exc:
            raise GridMergeError(f"not a benchmark results folder ({Path(exc.filename).name} missing): {p}") from None
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise GridMergeError(f"broken benchmark results in {p}: {exc}") from None
        return cls(p, config, records, summary)


def resolve_methods(methods: Union[str, Sequence[str], None]) -> tuple[list, list]:
    """``(registered, skipped)``: the method names that :func:`gridmerge.align` knows, and
    the others. ``None`` or ``"all"``: every registered method."""
    from ..align import METHODS

    if methods is None or methods == "all" or list(methods) == ["all"]:
        return list(METHODS), []
    names = [m.strip() for m in (methods.split(",") if isinstance(methods, str) else methods)]
    names = [m for m in dict.fromkeys(names) if m]
    return [m for m in names if m in METHODS], [m for m in names if m not in METHODS]


def _resolve_datasets(datasets, *, seed, n, quick, data_dir, source_maps=None, bend=0.0) -> tuple[list, list]:
    """``(Dataset list, notes)``; ``"all"`` skips the Halmstad pairs when the data is absent."""
    items = [datasets] if isinstance(datasets, (str, _datasets.Dataset)) else list(datasets)
    out, notes = [], []
    names_seen = set()
    for item in items:
        if isinstance(item, _datasets.Dataset):
            out.append(item)
            continue
        names = list(_datasets.DATASETS) if item == "all" else [item]
        for name in names:
            if name in names_seen:
                continue
            names_seen.add(name)
            real = name in ("halmstad", "halmstad-partial")
            if real and item == "all" and _datasets.resolve_data_dir(data_dir) is None:
                notes.append(f"{name} skipped: shared data not found at {_datasets.default_data_dir()}")
                continue
            if real and item == "all" and not _datasets.halmstad_environments(data_dir):
                notes.append(f"{name} skipped: no annotated maps in {_datasets.resolve_data_dir(data_dir) / 'halmstad'}")
                continue
            sized = _datasets.unswapped(name) in _datasets.SEEDED
            out.append(_datasets.load(name, seed=seed, n=n if sized else None, quick=quick, data_dir=data_dir,
                                      source_maps=source_maps, bend=bend))
    return out, notes


def _descriptions(names) -> dict:
    from ..align import METHODS

    return {m: getattr(METHODS[m], "description", "") for m in names}


def _max_rss_mb() -> Optional[float]:
    try:
        import resource
    except ImportError:  # Windows
        return None
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / (1024.0 * 1024.0) if sys.platform == "darwin" else rss / 1024.0


def _align_measured(case, method: str, seed: int, memory: bool, options=None):
    """``(result or None, wall_s, peak_mb, error)`` of one alignment; ``options``
    (AlignOptions overrides) apply to gridmerge's own methods only."""
    from ..align import ANY_SCALE, METHODS, align

    cv2.setRNGSeed(int(seed))
    started_here = False
    base = 0
    if memory:
        if tracemalloc.is_tracing():
            tracemalloc.reset_peak()
            base = tracemalloc.get_traced_memory()[0]
        else:
            tracemalloc.start()
            started_here = True
    error = ""
    result = None
    t0 = time.perf_counter()
    try:
        # A map whose resolution is unknown (a blueprint) is aligned as a user would: at any scale.
        overrides = dict(options or {}) if METHODS[method].verified else {}
        if not case.meta.get("resolutions_known", True):
            overrides.update(ANY_SCALE)
        result = align(case.a, case.b, method=method, rng=seed, **overrides)
    except (KeyboardInterrupt, SystemExit):
        raise
    except Exception as exc:  # noqa: BLE001 - a failing method is a result, not the end of the run
        error = f"{type(exc).__name__}: {' '.join(str(exc).split())}"
    finally:
        wall = time.perf_counter() - t0
        peak = None
        if memory:
            peak = (tracemalloc.get_traced_memory()[1] - base) / 1e6
            if started_here:
                tracemalloc.stop()
    return result, wall, peak, error


def _check_options(options: Optional[dict]) -> dict:
    """``options`` as a plain dict, every key an :class:`~gridmerge.align.AlignOptions` field."""
    from ..align import AlignOptions

    options = dict(options or {})
    known = {f.name for f in fields(AlignOptions)}
    unknown = sorted(k for k in options if k not in known)
    if unknown:
        raise GridMergeError(f"not AlignOptions fields: {', '.join(unknown)}")
    return options


def _machine() -> dict:
    info = {
        "platform": platform.platform(),
        "machine": platform.machine(),
        "processor": platform.processor() or None,
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "opencv_threads": cv2.getNumThreads(),
        "gridmerge": __version__,
    }
    try:
        import matplotlib

        info["matplotlib"] = matplotlib.__version__
    except ImportError:
        info["matplotlib"] = None
    return info


def _table1(records: list) -> dict:
    """The paper's Table I next to each method's estimate on the Table I case(s)."""
    rows = []
    for r in records:
        if r["dataset"] != "paper":
            continue
        e = r.get("estimate")
        rows.append(
            {
                "method": r["method"],
                "case_id": r["case_id"],
                "aligned": r["aligned"],
                "rotation_deg": None if e is None else e["rotation_deg"],
                "x": None if e is None else e["tx"],
                "y": None if e is None else e["ty"],
                "scale": None if e is None else e["scale"],
                "corner_error_px": r["corner_error_px"],
            }
        )
    return {**_datasets.PAPER_TABLE1, "methods": rows} if rows else {}


def _jsonable(v):
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    raise TypeError(f"not JSON serializable: {type(v).__name__}")


def _dumps(obj, **kw) -> str:
    return json.dumps(obj, default=_jsonable, allow_nan=False, **kw)


def run(
    methods: Union[str, Sequence[str], None],
    datasets: Union[str, Sequence, None] = "all",
    *,
    seed: int = 0,
    out_dir,
    progress: Optional[Progress] = None,
    n: Optional[int] = None,
    quick: bool = False,
    data_dir=None,
    plots: bool = True,
    memory: bool = True,
    overwrite: bool = False,
    options: Optional[dict] = None,
    source_maps: Optional[Sequence] = None,
    bend: float = 0.0,
) -> BenchRun:
    """Run every method on every case and write the results folder.

    Parameters
    ----------
    methods : str, sequence of str, or None
        Method names (or one comma-separated string); ``None``/``"all"``: every
        registered method. Names that :data:`gridmerge.align.METHODS` does not know are
        skipped with a warning in the results.
    datasets : str, Dataset, or a sequence of them
        ``"simulated"``, ``"halmstad"``, ``"halmstad-partial"``, ``"paper"``, ``"all"``
        (the four; the two Halmstad sets are skipped with a note when the shared data is
        absent), ``"halmstad:E5"`` or
        ``"halmstad:E5+HIH"`` (some environments, :func:`~gridmerge.bench.datasets.load`), or
        :class:`~gridmerge.bench.datasets.Dataset` objects.
    seed : int
        Seed of the simulated cases and of every alignment.
    out_dir : path
        The results folder (created; an existing folder must not hold results unless
        ``overwrite``).
    progress : callable, optional
        ``progress(done, total, label)`` (see :data:`Progress`); library code prints
        nothing.
    n : int, optional
        Number of simulated cases (default 60, 6 with ``quick``).
    quick : bool
        A small, fast slice of every data set (CI).
    data_dir : path, optional
        The shared data folder (default ``../shared/data`` when it exists).
    plots : bool
        Write the PNG plots (needs matplotlib; skipped with a warning without it).
    memory : bool
        Measure the peak memory of each call with tracemalloc. Tracing slows the calls
        (and so their recorded times): on the quick simulated slice, ``hybrid`` 1.7x,
        ``sift`` 1.5x, ``orb`` about 1.6x (thirty-sixth session).
    overwrite : bool
        Replace the results in an existing folder.
    options : dict, optional
        :class:`~gridmerge.align.AlignOptions` fields to change for gridmerge's own
        methods (``Method.verified``), e.g. ``{"min_confidence": 0.4}`` to measure another
        decline threshold; the baselines keep their authors' rules. Recorded in
        ``config.json`` and named in ``results.md``.
    source_maps : sequence of path, optional
        Map files to simulate the robots in, instead of the shared data's source maps
        (the ``simulated`` data set only; :func:`~gridmerge.bench.datasets.simulated`).
        Their paths and digests are recorded in ``config.json``.
    bend : float
        Bend robot b's maps of the ``simulated`` data set by up to this many source cells
        (:func:`~gridmerge.bench.datasets.simulated`; 0: as they were). Recorded in
        ``config.json``.

    Returns
    -------
    BenchRun

    Raises
    ------
    GridMergeError
        No registered method, unknown data set, Halmstad asked for without its data.
    OutputError
        The folder holds results and ``overwrite`` is false, or cannot be written.
    """
    options = _check_options(options)
    registered, skipped = resolve_methods(methods)
    warnings = [f"method {m!r} is not registered (gridmerge.align.METHODS): skipped" for m in skipped]
    if not registered:
        raise GridMergeError(f"no registered method among {', '.join(skipped) or 'the methods given'}")
    sets, notes = _resolve_datasets("all" if datasets is None else datasets, seed=seed, n=n, quick=quick, data_dir=data_dir,
                                    source_maps=source_maps, bend=bend)
    if not sets:
        raise GridMergeError("no data set to run")
    simulates = any(_datasets.unswapped(ds.name) == "simulated" for ds in sets)
    if source_maps is not None and not simulates:
        raise GridMergeError("source maps are for the simulated data set only: run it (--dataset simulated)")
    if bend and not simulates:
        raise GridMergeError("bending is for the simulated data set only: run it (--dataset simulated)")
    for ds in sets:
        notes.extend(ds.notes)

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise OutputError(f"results folder {out} is a file")
    if out.is_dir() and not overwrite and any((out / f).exists() for f in FILES + ("cases.jsonl.partial",)):
        raise OutputError(f"results folder {out} already holds results; choose another or overwrite")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create results folder {out}: {exc.strerror or exc}") from None

    total = sum(len(ds) for ds in sets) * len(registered)
    started = time.time()
    config = {
        "seed": int(seed),
        "methods": registered,
        "method_descriptions": _descriptions(registered),
        "skipped_methods": skipped,
        "datasets": [{"name": ds.name, "cases": len(ds), "notes": ds.notes, "params": ds.params} for ds in sets],
        "n": n,
        "quick": bool(quick),
        "data_dir": None if _datasets.resolve_data_dir(data_dir) is None else str(_datasets.resolve_data_dir(data_dir)),
        "memory": bool(memory),
        "options": options,
        "machine": _machine(),
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(started)),
    }

    records: list = []
    partial = out / "cases.jsonl.partial"
    done = 0
    with open(partial, "w", encoding="utf-8") as fh:
        for ds in sets:
            for case in ds:
                for m in registered:
                    if progress is not None:
                        progress(done, total, f"{case.id} {m}")
                    result, wall, peak, error = _align_measured(case, m, seed, memory, options)
                    rec = evaluate(case, result, wall_s=wall, peak_mb=peak, max_rss_mb=_max_rss_mb(), error=error)
                    rec.method = m
                    d = rec.to_dict()
                    records.append(d)
                    fh.write(_dumps(d) + "\n")
                    fh.flush()
                    done += 1
    if progress is not None:
        progress(done, total, "")

    config["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    config["duration_s"] = round(time.time() - started, 3)
    summary = {
        "rows": summarize(records),
        "table1": _table1(records),
        "warnings": warnings,
        "notes": notes,
    }
    bench = BenchRun(out, config, records, summary)
    if plots:
        try:
            from .plots import make_plots

            for name, png in make_plots(records, registered).items():
                atomic_write(out / name, png)
        except ImportError:
            summary["warnings"].append("plots skipped: matplotlib is not installed (pip install 'gridmerge[plot]')")
    atomic_write(out / "cases.jsonl", "".join(_dumps(r) + "\n" for r in records).encode())
    partial.unlink()
    atomic_write(out / "summary.json", (_dumps(summary, indent=2) + "\n").encode())
    atomic_write(out / "config.json", (_dumps(config, indent=2) + "\n").encode())
    atomic_write(out / "results.md", results_markdown(bench).encode())
    return bench


def compare(run1: Union[BenchRun, str, os.PathLike], run2: Union[BenchRun, str, os.PathLike]) -> str:
    """Markdown: the summary differences between two runs (``run2 - run1``), then the
    cases whose outcome changed or whose error moved
    (:func:`~gridmerge.bench.report.compare_summaries`)."""
    r1 = run1 if isinstance(run1, BenchRun) else BenchRun.load(run1)
    r2 = run2 if isinstance(run2, BenchRun) else BenchRun.load(run2)
    return compare_summaries(r1, r2)


def rebuild_case(run: Union[BenchRun, str, os.PathLike], case_id: str, maps_dir=None) -> _datasets.Case:
    """The case ``case_id`` of a results folder, built again from its ``config.json``
    (seed, data sets, source maps, data folder), to look at a failure or run it again.

    Cases are built from the seed, so the maps are those the run aligned; the rebuilt
    case is checked against the run's record (its maps' shapes, and for simulated cases
    its source and overlap).

    Parameters
    ----------
    run : BenchRun or path
    case_id : str
        As in ``cases.jsonl``, e.g. ``"simulated/0042"`` or ``"halmstad/E5_03-E5_12"``.
    maps_dir : path, optional
        Where the run's source maps (``--source-map``) are now, found by file name;
        default: the paths the run recorded. Either way each map must have the cells
        the run recorded (their SHA-256).

    Returns
    -------
    Case

    Raises
    ------
    GridMergeError
        No such case in the run; the run's data sets cannot be built again (given to
        :func:`run` as objects built otherwise, a data folder that has changed, source
        maps missing or changed).
    """
    bench = run if isinstance(run, BenchRun) else BenchRun.load(run)
    records = [r for r in bench.records if r.get("case_id") == case_id]
    if not records:
        raise GridMergeError(f"no case {case_id!r} in {bench.out_dir}")
    cfg = bench.config
    seed, data_dir = int(cfg.get("seed", 0)), cfg.get("data_dir")
    for entry in cfg.get("datasets", []):
        name = entry["name"]
        base = _datasets.unswapped(name)
        if base not in _datasets.DATASETS:
            continue
        params = entry.get("params") or {}
        sources, bend = params.get("source_maps"), float(params.get("bend", 0.0))
        maps = [m["path"] if maps_dir is None else Path(maps_dir) / Path(m["path"]).name for m in sources] if sources else None
        if base in _datasets.SEEDED:
            head, _, number = case_id.partition("/")
            if head != name or not number.isdigit():
                continue
            ds = _datasets.load(name, seed=seed, n=int(entry["cases"]), data_dir=data_dir, source_maps=maps, bend=bend)
            for was, now in zip(sources or [], ds.params.get("source_maps", [])):
                if was.get("cells_sha256") != now["cells_sha256"]:
                    raise GridMergeError(f"source map {now['path']} is not the one the run used (its cells differ)")
            case = ds[int(number)]
        else:
            # Halmstad's cases are named by their maps; the run may have used a slice.
            ds = _datasets.load(name, seed=seed, data_dir=data_dir)
            case = next((c for c in ds if c.id == case_id), None)
            if case is None:
                continue
        _check_rebuilt(case, records[0], bench.out_dir)
        return case
    raise GridMergeError(f"case {case_id!r} of {bench.out_dir} cannot be built again from its config.json "
                         "(its data set was not given by name)")


def _check_rebuilt(case, record: dict, where) -> None:
    same = list(case.a.shape) == list(record.get("a_shape") or []) and list(case.b.shape) == list(record.get("b_shape") or [])
    if same and _datasets.unswapped(case.dataset) in _datasets.SEEDED:
        def source(name):  # a map file may have moved (rebuild_case's maps_dir): its name and cells count
            return Path(name[len(_datasets.FILE_PREFIX):]).name if str(name).startswith(_datasets.FILE_PREFIX) else name

        same = source(case.meta.get("source")) == source(record.get("source")) and case.meta.get("overlap") == record.get("overlap")
    if not same:
        raise GridMergeError(f"case {case.id!r} built again differs from the one {where} aligned "
                             "(a data set built otherwise, or changed maps)")


def replay(run: Union[BenchRun, str, os.PathLike], case_id: str, method: str, maps_dir=None):
    """Align one case of a results folder again with ``method`` exactly as the run did
    (its seed, OpenCV's seed, its decline options, any scale for maps of unknown
    resolution). Returns ``(case, AlignResult)``; the result's pose and confidence are
    those recorded (timings aside). ``maps_dir``: as :func:`rebuild_case`.

    Raises
    ------
    GridMergeError
        As :func:`rebuild_case`; a method the run did not use; a method that fails.
    """
    bench = run if isinstance(run, BenchRun) else BenchRun.load(run)
    if method not in bench.config.get("methods", []):
        raise GridMergeError(f"method {method!r} was not run in {bench.out_dir} (it ran {', '.join(bench.config.get('methods', []))})")
    case = rebuild_case(bench, case_id, maps_dir)
    result, _, _, error = _align_measured(case, method, int(bench.config.get("seed", 0)), False, bench.config.get("options"))
    if result is None:
        raise GridMergeError(f"{method} failed on {case_id}: {error}")
    return case, result

"""``gridmerge bench``: run the benchmark suite, compare two runs.

::

    gridmerge bench [run] [--dataset simulated|halmstad|halmstad-partial|paper|all ...] [--methods sift,ransac,...]
                          [--n N] [--seed S] [--quick] [--out DIR] [--data DIR] [--progress] [--force]
                          [--min-confidence C] [--one-sided-confidence C] [--max-slide C] [--max-crossing C]
                          [--source-map MAP ...] [--bend PX]
    gridmerge bench compare RUN1 RUN2
    gridmerge bench case RUN CASE_ID --out DIR [--method M] [--maps DIR]

The command line wires this module in with :func:`add_parser` and calls :func:`run`.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..errors import GridMergeError
from . import _decline

__all__ = ["add_parser", "run", "ProgressBar"]

EXIT_OK = 0
EXIT_BAD_INPUT = 2

_DATASET_CHOICES = ("simulated", "halmstad", "halmstad-partial", "paper", "all")


def _dataset_name(text: str) -> str:
    """``--dataset``'s value: ``all``, or a name :func:`gridmerge.bench.datasets.check_name`
    knows (``halmstad:ENV[+ENV...]``, ``-swapped``)."""
    if text == "all":
        return text
    from ..bench.datasets import check_name

    try:
        check_name(text)
    except GridMergeError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


class _BenchUsageError(GridMergeError):
    pass


def _taken(parser: argparse.ArgumentParser, flag: str) -> Optional[str]:
    """The destination of ``flag`` if ``parser`` already has it (from a parent), else None."""
    action = getattr(parser, "_option_string_actions", {}).get(flag)
    return None if action is None else action.dest


def _cells_float(text: str) -> float:
    """argparse type: a finite number of cells, 0 or more (``--bend``)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (np.isfinite(value) and value >= 0.0):
        raise argparse.ArgumentTypeError(f"must be a number of cells, 0 or more, got {text!r}")
    return value


def _run_options(p: argparse.ArgumentParser, suppress: bool) -> dict:
    """Add the options of ``bench run`` to ``p``.

    With ``suppress``, absent options leave the values parsed before them alone (the
    options are accepted both before and after the word ``run``). An option that a parent
    parser already defines (say ``--seed``) is not redefined: the parent's is used, and
    the returned alias maps our destination to the parent's.
    """
    aliases = {}

    def add(flag: str, dest: str, default, **kw):
        other = _taken(p, flag)
        if other is not None:
            aliases[dest] = other
            return
        p.add_argument(flag, dest=dest, default=argparse.SUPPRESS if suppress else default, **kw)

    add(
        "--dataset",
        "bench_datasets",
        None,
        action="append",
        type=_dataset_name,
        metavar="NAME",
        help="data set to run: simulated, halmstad, halmstad-partial, paper or all (default: all), or halmstad:ENV[+ENV...] for some "
        "of the Halmstad folder's environments (halmstad:E5, halmstad:E5+HIH); NAME-swapped runs a data set "
        "with the two maps of every pair swapped (halmstad-swapped); repeatable",
    )
    add(
        "--methods",
        "bench_methods",
        None,
        metavar="M1,M2",
        help="comma-separated alignment methods (default: every registered one); unregistered names are skipped with a warning",
    )
    add("--n", "bench_n", None, type=int, metavar="N",
        help="number of simulated and halmstad-partial cases (default 60; 6 and 3 with --quick)")
    add("--seed", "bench_seed", 0, type=int, metavar="S", help="seed of the cases and of every alignment (default 0)")
    add("--quick", "bench_quick", False, action="store_true", help="a small, fast slice of every data set (CI)")
    add("--out", "bench_out", None, metavar="DIR", help="results folder (default: bench-YYYYmmdd-HHMMSS)")
    add("--data", "bench_data", None, metavar="DIR", help="shared data folder (default: ../shared/data next to the project)")
    add("--source-map", "bench_source_maps", None, action="append", metavar="MAP",
        help="a map file (map_server YAML, PGM or PNG) to simulate the robots in, instead of the shared data's maps "
        "(the simulated data set only); repeatable: each simulated pair draws one of them")
    add("--bend", "bench_bend", 0.0, type=_cells_float, metavar="PX",
        help="bend robot b's simulated maps by up to PX source cells, as two SLAM sessions' maps bend against each "
        "other (the simulated data set only; default 0: as they were)")
    add("--progress", "bench_progress", False, action="store_true", help="show a progress bar on stderr even when it is not a terminal")
    add("--force", "bench_force", False, action="store_true", help="replace the results in an existing folder")
    add("--no-plots", "bench_plots", True, action="store_false", help="do not draw the PNG plots")
    add("--no-memory", "bench_memory", True, action="store_false",
        help="do not measure each call's peak memory (tracemalloc, which makes the calls about 1.5-1.7x slower)")
    for flag, name in _decline.FLAGS.items():
        add(flag, "bench_" + name, None, type=_decline.type_of(name), metavar=_decline.metavar(name),
            help=_decline.help_text(name) + "; gridmerge's own methods only, the baselines keep their rules")
    return aliases


def add_parser(subparsers, parents: Sequence[argparse.ArgumentParser] = ()) -> argparse.ArgumentParser:
    """Add the ``bench`` sub-command (with ``run``, the default, and ``compare``).

    Parameters
    ----------
    subparsers
        The ``add_subparsers()`` object of the ``gridmerge`` parser.
    parents : sequence of ArgumentParser
        Parsers whose options ``bench`` and its sub-commands share (e.g. ``--debug``). When
        a parent already defines one of bench's options (e.g. ``--seed``), the parent's is
        used.

    Returns
    -------
    argparse.ArgumentParser
        The ``bench`` parser.
    """
    parents = list(parents)
    p = subparsers.add_parser(
        "bench",
        parents=parents,
        help="benchmark the alignment methods (accuracy, robustness, speed)",
        description="Run every alignment method on simulated pairs with exact truth, the annotated Halmstad "
        "pairs and the paper's Table I experiment, and write a results folder (cases.jsonl, summary.json, "
        "results.md, config.json, plots). 'bench compare RUN1 RUN2' shows the differences of two runs.",
    )
    aliases = _run_options(p, suppress=False)
    p.set_defaults(bench_command="run", bench_run1=None, bench_run2=None, bench_aliases=aliases)
    sub = p.add_subparsers(dest="bench_command", metavar="{run,compare,case,fleet}")
    pr = sub.add_parser("run", parents=parents, help="run the benchmark (default)", description="Run the benchmark.")
    _run_options(pr, suppress=True)
    pc = sub.add_parser(
        "compare",
        parents=parents,
        help="compare two runs: their summaries, then case by case",
        description="Print a Markdown table of the summary differences between two results folders (RUN2 - RUN1), "
        "then the cases whose outcome changed and those whose error moved by more than 1 px.",
    )
    pc.add_argument("bench_run1", metavar="RUN1", help="results folder of the first run")
    pc.add_argument("bench_run2", metavar="RUN2", help="results folder of the second run")
    pk = sub.add_parser(
        "case",
        parents=parents,
        help="write one case of a run as map files, and align it again as the run did",
        description="Build one case of a results folder again from its config.json and write its two maps "
        "(a.yaml, b.yaml), case.json (truth, description, the run's records of it), truth.png (the maps "
        "drawn on each other at the truth, the walls that agree black) and, with --method, that method's "
        "alignment again (the same pose and confidence as recorded), pose.png (the maps at its pose, or "
        "at its declined candidate) and merge.png.",
    )
    pk.add_argument("bench_case_run", metavar="RUN", help="results folder")
    pk.add_argument("bench_case_id", metavar="CASE_ID", help="a case_id of its cases.jsonl, e.g. simulated/0042")
    pk.add_argument("--out", dest="bench_case_out", required=True, metavar="DIR", help="folder to write into")
    pk.add_argument("--method", dest="bench_case_method", default=None, metavar="M", help="align the case again with this method")
    pk.add_argument("--maps", dest="bench_case_maps", default=None, metavar="DIR",
                    help="folder holding the run's --source-map files now (found by name, checked by their cells)")
    pk.add_argument("--force", dest="bench_case_force", action="store_true", help="replace files in an existing folder")
    pf = sub.add_parser(
        "fleet",
        parents=parents,
        help="time fleet merges (2 to 16 robots, serial and parallel) and an incremental update",
        description="Simulate fleets of robots exploring one building, merge each with 1 and more workers, "
        "and re-merge one grown map incrementally; writes fleet.json and fleet.md into --out.",
    )
    pf.add_argument("--robots", dest="fleet_robots", default="2,4,8,16", metavar="N1,N2", help="fleet sizes (default 2,4,8,16)")
    pf.add_argument("--workers", dest="fleet_workers", default="1,2", metavar="W1,W2", help="process-pool sizes (default 1,2)")
    pf.add_argument("--source", dest="fleet_source", default=None, metavar="NAME",
                    help="building: a benchmark source map name (e.g. willow), a map file (map_server YAML, PGM or PNG), "
                    "or none for a procedural one (default)")
    pf.add_argument("--out", dest="fleet_out", default=None, metavar="DIR", help="results folder (default: bench-fleet-YYYYmmdd-HHMMSS)")
    pf.add_argument("--data", dest="fleet_data", default=None, metavar="DIR", help="shared data folder (for --source and the Halmstad fleets)")
    pf.add_argument("--no-halmstad", dest="fleet_halmstad", action="store_false", help="skip the real Halmstad fleets (every environment of the data folder: HIH, E5)")
    if _taken(pf, "--seed") is None:
        pf.add_argument("--seed", dest="fleet_seed", type=int, default=0, metavar="S", help="seed of the fleets and merges (default 0)")
    pf.add_argument("--progress", dest="fleet_progress", action="store_true", help="show a progress bar even when stderr is not a terminal")
    pf.add_argument("--force", dest="fleet_force", action="store_true", help="replace the results in an existing folder")
    return p


class ProgressBar:
    """A one-line progress bar on a stream (stderr), redrawn at most 10 times a second."""

    def __init__(self, stream=None, width: int = 28):
        self.stream = sys.stderr if stream is None else stream
        self.width = width
        self.t0 = time.monotonic()
        self._last = 0.0
        self._shown = False

    def __call__(self, done: int, total: int, label: str) -> None:
        now = time.monotonic()
        if done < total and now - self._last < 0.1 and self._shown:
            return
        self._last = now
        frac = done / total if total else 1.0
        fill = int(round(self.width * frac))
        elapsed = now - self.t0
        eta = f", {elapsed / done * (total - done):.0f} s left" if 0 < done < total else ""
        line = f"\r[{'#' * fill}{'.' * (self.width - fill)}] {done}/{total} {elapsed:.0f} s{eta} {label}"
        self.stream.write(line[:118].ljust(118) if done < total else line.rstrip() + "\n")
        self.stream.flush()
        self._shown = True


def _default_out() -> Path:
    return Path(time.strftime("bench-%Y%m%d-%H%M%S"))


def _value(args, dest: str, default=None):
    dest = (getattr(args, "bench_aliases", None) or {}).get(dest, dest)
    return getattr(args, dest, default)


def _cmd_run(args) -> int:
    from ..bench import runner

    for dest, default in (
        ("bench_datasets", None), ("bench_methods", None), ("bench_n", None), ("bench_seed", 0),
        ("bench_quick", False), ("bench_out", None), ("bench_data", None), ("bench_progress", False),
        ("bench_force", False), ("bench_plots", True), ("bench_memory", True), ("bench_source_maps", None),
        ("bench_bend", 0.0), *(("bench_" + name, None) for name in _decline.FLAGS.values()),
    ):
        setattr(args, dest, _value(args, dest, default))

    datasets = args.bench_datasets or ["all"]
    if "all" in datasets:
        datasets = ["all"]
    if args.bench_n is not None and args.bench_n < 0:
        raise _BenchUsageError(f"--n must be >= 0, got {args.bench_n}")
    methods = args.bench_methods
    if methods is not None and not [m for m in methods.split(",") if m.strip()]:
        raise _BenchUsageError("--methods needs at least one method name")
    out = Path(args.bench_out) if args.bench_out else _default_out()
    show = bool(args.bench_progress) or sys.stderr.isatty()
    bar: Optional[ProgressBar] = ProgressBar() if show else None
    bench = runner.run(
        methods,
        datasets,
        seed=args.bench_seed,
        out_dir=out,
        progress=bar,
        n=args.bench_n,
        quick=args.bench_quick,
        data_dir=args.bench_data,
        plots=args.bench_plots,
        memory=args.bench_memory,
        overwrite=args.bench_force,
        options=_decline.overrides({name: getattr(args, "bench_" + name) for name in _decline.FLAGS.values()}),
        source_maps=args.bench_source_maps,
        bend=args.bench_bend,
    )
    for w in bench.warnings:
        print(f"gridmerge: warning: {w}", file=sys.stderr)
    _print_summary(bench)
    print(f"results: {out}")
    return EXIT_OK


def _print_summary(bench) -> None:
    rows = [r for r in bench.rows if r["tier"] == "all"]
    if not rows:
        return
    header = f"{'data set':<16} {'method':<10} {'pairs':>5} {'success':>8} {'declined':>8} {'wrong':>6} {'false':>6} {'med err':>8} {'med s':>6}"
    print(header)
    for r in rows:
        def pct(v):
            return "-" if v is None else f"{100 * v:.0f}%"

        err = "-" if r["median_error_px"] is None else f"{r['median_error_px']:.2f}"
        t = "-" if r["median_time_s"] is None else f"{r['median_time_s']:.2f}"
        print(
            f"{r['dataset']:<16} {r['method']:<10} {r['cases']:>5} {pct(r['success_rate']):>8} {pct(r['declined_rate']):>8} "
            f"{pct(r['wrong_rate']):>6} {pct(r['false_merge_rate']):>6} {err:>8} {t:>6}"
        )


def _cmd_compare(args) -> int:
    from ..bench import runner

    sys.stdout.write(runner.compare(args.bench_run1, args.bench_run2))
    return EXIT_OK


def _cmd_case(args) -> int:
    import json

    from ..bench import runner
    from ..io import atomic_write, save_map

    out = Path(args.bench_case_out)
    names = ("a.yaml", "b.yaml", "case.json", "merge.png", "pose.png", "truth.png")
    if out.exists() and not out.is_dir():
        raise _BenchUsageError(f"{out} is a file")
    if not args.bench_case_force and any((out / n).exists() for n in names):
        raise _BenchUsageError(f"{out} holds a case already; use --force to replace it")
    bench = runner.BenchRun.load(args.bench_case_run)
    method = args.bench_case_method
    if method is not None:
        case, result = runner.replay(bench, args.bench_case_id, method, args.bench_case_maps)
    else:
        case, result = runner.rebuild_case(bench, args.bench_case_id, args.bench_case_maps), None
    out.mkdir(parents=True, exist_ok=True)
    save_map(case.a, out / "a.yaml")
    save_map(case.b, out / "b.yaml")
    info = {
        "case_id": case.id,
        "dataset": case.dataset,
        "positive": case.positive,
        "truth_b_to_a": None if case.truth is None else np.asarray(case.truth).tolist(),
        "meta": case.meta,
        "run": str(bench.out_dir),
        "seed": bench.config.get("seed"),
        "records": [r for r in bench.records if r.get("case_id") == case.id],
    }
    if result is not None:
        info["replayed"] = {"method": method, "success": bool(result.success), "confidence": float(result.confidence),
                            "matrix": None if result.matrix is None else np.asarray(result.matrix).tolist(),
                            "message": result.message}
    atomic_write(out / "case.json", (json.dumps(info, indent=2, default=str) + "\n").encode())
    print(f"{case.id}: {'positive' if case.positive else 'negative'} pair; wrote {out / 'a.yaml'}, {out / 'b.yaml'}, {out / 'case.json'}")
    if case.truth is not None:
        # The two maps on each other at the truth (no title: OpenCV alone writes it).
        import cv2

        from ..plot import alignment_overlay

        img, _ = alignment_overlay(case.a, case.b, np.asarray(case.truth))
        ok, png = cv2.imencode(".png", np.ascontiguousarray(img[:, :, ::-1]))
        if ok:
            atomic_write(out / "truth.png", png.tobytes())
            print(f"picture: {out / 'truth.png'} (the maps at the truth)")
    if result is not None:
        print(f"{method}: {result.message}")
        try:
            from ..plot import plot_alignment, plot_merge, save_plot

            if result.success or result.candidate is not None:
                save_plot(plot_alignment(case.a, case.b, result), out / "pose.png")
                print(f"picture: {out / 'pose.png'} (the maps at the method's {'pose' if result.success else 'declined candidate'})")
            if result.success:
                save_plot(plot_merge(case.a, case.b, result, _merged(case.a, case.b, result.transform)), out / "merge.png")
                print(f"picture: {out / 'merge.png'}")
        except GridMergeError as e:  # matplotlib missing
            print(f"gridmerge: warning: pictures skipped: {e}", file=sys.stderr)
    return EXIT_OK


def _merged(a, b, transform):
    """a and b fused on one canvas, b placed by ``transform`` (the picture of a replay)."""
    from ..grid import OccupancyGrid
    from ..merge import fuse_on_canvas
    from ..transforms import SimilarityTransform

    fused, _ = fuse_on_canvas([a, b], [SimilarityTransform(), transform])
    return OccupancyGrid(fused, resolution=a.resolution)


def _int_list(text: str, what: str) -> list:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise _BenchUsageError(f"{what} must be comma-separated whole numbers, got {text!r}") from None
    if not values or min(values) < 1:
        raise _BenchUsageError(f"{what} must be whole numbers >= 1, got {text!r}")
    return values


def _cmd_fleet(args) -> int:
    from ..bench import fleet
    from ..bench.datasets import file_source, source_map

    robots = _int_list(args.fleet_robots, "--robots")
    workers = _int_list(args.fleet_workers, "--workers")
    out = Path(args.fleet_out) if args.fleet_out else Path(time.strftime("bench-fleet-%Y%m%d-%H%M%S"))
    if (out / "fleet.json").exists() and not args.fleet_force:
        raise _BenchUsageError(f"{out} holds results already; use --force to replace them")
    name = args.fleet_source
    if name not in (None, "building") and Path(name).is_file():
        name = file_source(name)  # a map file, not a source map's name
    source = None if name in (None, "building") else source_map(name, args.fleet_data)
    bar = ProgressBar() if (args.fleet_progress or sys.stderr.isatty()) else None
    seed = getattr(args, "fleet_seed", None)
    if seed is None:  # a parent parser's --seed
        seed = getattr(args, "seed", 0) or 0
    result = fleet.benchmark(robots, workers, seed=seed, source=source, progress=bar,
                             halmstad=None if args.fleet_halmstad else (), data_dir=args.fleet_data)
    result.save(out)
    sys.stdout.write(result.to_markdown())
    print(f"results: {out}")
    return EXIT_OK


def run(args) -> int:
    """Run ``gridmerge bench`` with parsed ``args``; returns the exit code (0 done).

    Errors raise :class:`~gridmerge.errors.GridMergeError` (one-line messages), which the
    command line reports with exit code 2.
    """
    command = getattr(args, "bench_command", None) or "run"
    if command == "compare":
        return _cmd_compare(args)
    if command == "fleet":
        return _cmd_fleet(args)
    if command == "case":
        return _cmd_case(args)
    return _cmd_run(args)

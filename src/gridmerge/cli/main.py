"""The ``gridmerge`` command: a thin layer that parses arguments and calls the library.

Exit codes: 0 done, 1 declined (the maps could not be aligned confidently), 2 bad input
or usage (one line on stderr; the traceback only with ``--debug``), 130 interrupted
(Ctrl-C), 143 terminated (SIGTERM); an interrupted run leaves no partial file
(docs/limits.md).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import traceback
from dataclasses import fields
from pathlib import Path
from typing import Sequence

from .. import __version__
from ..align import ANY_SCALE, METHODS, align
from ..errors import GridMergeError, LimitExceededError, OutputError
from ..fuse import FUSION_RULES
from ..grid import DEFAULT_RESOLUTION
from ..io import SAVE_MODES, load_map, save_map
from ..io.jsonable import finite
from ..io.map_server import YAML_SUFFIXES, yaml_image_path
from ..limits import DEFAULT_LIMITS, Limits, extractor_for
from ..merge import PAIR_STRATEGIES, SCALE_CHECKS, merge
from ..parallel import keep_freed_memory
from ..samples import SAMPLE_KINDS, sample_outputs, write_sample
from . import _decline
from . import bench as bench_cli

__all__ = ["main", "EXIT_OK", "EXIT_DECLINED", "EXIT_BAD_INPUT"]

EXIT_OK = 0
EXIT_DECLINED = 1
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143
#: The reader of our standard output went away (``gridmerge ... | head``): 128 + SIGPIPE,
#: as a shell tool killed by the signal would end, and nothing printed.
EXIT_BROKEN_PIPE = 141
#: ``AlignOptions.scale_prior`` of ``--trust-resolution``.
_SCALE_PRIOR = 4.0


class _UsageError(GridMergeError):
    pass


class _Terminated(BaseException):
    """SIGTERM, raised like KeyboardInterrupt so that partial outputs are removed."""


def _on_sigterm(signum, frame):
    raise _Terminated


def _count(text: str) -> int:
    """A positive integer, also written as 2e8 or 200_000_000."""
    try:
        value = float(text) if any(c in text for c in ".eE") else int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (isinstance(value, int) or (math.isfinite(value) and value == int(value))) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive whole number, got {text!r}")
    return int(value)


def _factor(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a number > 0, got {text!r}")
    return value


_LIMIT_HELP = {
    "max_pixels": "cells of one input image or array",
    "max_yaml_bytes": "size of a map YAML file",
    "max_keypoints": "keypoints kept per map (the strongest)",
    "max_feature_pixels": "pixels keypoints are detected in (larger maps are detected at reduced resolution)",
    "max_canvas_cells": "cells of the merged map",
    "max_canvas_factor": "merged cells per input cell",
}


def _add_limits(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("limits (docs/limits.md)")
    for f in fields(Limits):
        group.add_argument(
            "--" + f.name.replace("_", "-"),
            dest=f.name,
            type=_factor if f.name == "max_canvas_factor" else _count,
            default=None,
            metavar="X" if f.name == "max_canvas_factor" else "N",
            help=f"{_LIMIT_HELP[f.name]} (default {getattr(DEFAULT_LIMITS, f.name)})",
        )


def _verified_methods() -> str:
    """The methods whose success gridmerge's verification decides (the decline thresholds'), comma-separated."""
    return ", ".join(m for m, spec in METHODS.items() if spec.verified)


def _add_decline(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group(f"decline thresholds (methods {_verified_methods()})")
    for flag, name in _decline.FLAGS.items():
        group.add_argument(flag, dest=name, type=_decline.type_of(name), default=None, metavar=_decline.metavar(name),
                           help=_decline.help_text(name))


def _decline_options(args) -> dict:
    """AlignOptions of the decline thresholds (--min-confidence, --one-sided-confidence,
    --max-slide, --max-crossing, --unsure-walls); a usage error with a method that declines by its own rule."""
    given = _decline.overrides({name: getattr(args, name, None) for name in _decline.FLAGS.values()})
    if given and not METHODS[args.method].verified:
        flags = [f for f, name in _decline.FLAGS.items() if name in given]
        raise _UsageError(f"{' and '.join(flags)}: the {args.method} baseline declines by its own rule; "
                          f"use {'them' if len(flags) > 1 else 'it'} with a gridmerge method ({_verified_methods()})")
    return given


def _limits(args) -> Limits:
    return DEFAULT_LIMITS.replace(**{f.name: getattr(args, f.name, None) for f in fields(Limits)})


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line instead of usage + message
        raise _UsageError(f"{message} (see '{self.prog} --help')")


def _parser() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true", help="show the traceback of errors")
    common.add_argument(
        "--image-resolution",
        dest="image_resolution",
        type=float,
        default=None,
        metavar="R",
        help=f"resolution (m/cell) of maps given as bare images or .npy (default {DEFAULT_RESOLUTION}); "
        "a map_server YAML or a bag keeps its own",
    )
    common.add_argument("--method", choices=sorted(METHODS), default="hybrid", help="alignment method (default: hybrid)")
    common.add_argument("--seed", type=int, default=0, help="seed of every random choice (default 0)")
    resolutions = common.add_mutually_exclusive_group()
    resolutions.add_argument(
        "--trust-resolution",
        action="store_true",
        help="the maps' resolutions are exact (laser SLAM maps): pull the refined scale harder towards "
        "their ratio (AlignOptions.scale_prior = 4; default 1)",
    )
    resolutions.add_argument(
        "--any-scale",
        action="store_true",
        help="the maps' resolutions are unknown or wrong: accept any scale between them, not only "
        "within 15 %% of their resolutions' ratio, and do not pull the scale towards it "
        "(AlignOptions.max_scale_disagreement = None, scale_prior = 0)",
    )
    common.add_argument("--json", action="store_true", help="print the result as one JSON object")
    _add_decline(common)
    _add_limits(common)

    p = _Parser(prog="gridmerge", description="Merge occupancy grid maps of several robots.")
    p.add_argument("--version", action="version", version=f"gridmerge {__version__}")
    p.add_argument("--debug", action="store_true", help=argparse.SUPPRESS)
    sub = p.add_subparsers(dest="command", parser_class=_Parser, metavar="COMMAND")

    pa = sub.add_parser(
        "align",
        parents=[common],
        help="find the transform from map B to map A",
        description="Find the transform that moves map B onto map A. Exit 0 aligned, 1 declined, 2 bad input.",
    )
    pa.add_argument("a", metavar="A", help="reference map (map_server .yaml, .pgm/.png, or .npy)")
    pa.add_argument("b", metavar="B", help="map to align onto A")
    pa.add_argument("--resolution", dest="image_resolution", type=float, default=argparse.SUPPRESS, help="same as --image-resolution")
    pa.add_argument("--plot", metavar="PNG",
                    help="also write a picture of the two maps drawn on each other at the pose (a declined pair: at its "
                    "best candidate pose), the walls that agree in black: what the pose rests on")
    pa.add_argument("--force", action="store_true", help="overwrite an existing --plot file")

    pm = sub.add_parser(
        "merge",
        parents=[common],
        help="merge two or more maps (files or ROS bags) into one map_server map",
        description="Merge maps into the metric frame of the first (or --reference). Maps are map_server "
        "YAMLs, images, .npy arrays, or ROS 1/ROS 2 bags (the last nav_msgs/OccupancyGrid of each topic). "
        "Exit 0 merged (maps that overlap no other are reported unplaced), 1 no two maps could be merged "
        "(no output written), 2 bad input.",
    )
    pm.add_argument("maps", nargs="+", metavar="MAP", help="maps or bags; together at least two maps")
    pm.add_argument("-o", "--output", required=True, metavar="OUT.yaml", help="merged map (map_server YAML; the image is written beside it)")
    pm.add_argument("--topic", action="append", default=None, metavar="TOPIC",
                    help="OccupancyGrid topic to read from the bags (repeat for several; default: every OccupancyGrid topic)")
    pm.add_argument("--reference", metavar="NAME", default=None,
                    help="the map whose frame the merged map keeps: a path or topic as given (default: the first map)")
    pm.add_argument("--resolution", type=float, default=None, metavar="R",
                    help="resolution (m/cell) of the merged map (default: the finest of the merged maps)")
    pm.add_argument("--fusion", choices=FUSION_RULES, default="average", help="cell fusion rule (default: average, the paper's eq. 9)")
    pm.add_argument("--pairs", choices=PAIR_STRATEGIES, default="auto",
                    help="pairs to align: all, or auto (all up to 8 maps, the likeliest beyond; default)")
    pm.add_argument("--scale-check", choices=SCALE_CHECKS, default="warn",
                    help="a pair whose scale disagrees with the maps' resolutions: warn (default), reject it, or off")
    pm.add_argument("--workers", type=_count, default=None, metavar="N", help="align pairs in N local processes (default 1)")
    pm.add_argument("--scheduler", default=None, metavar="ADDRESS", help="align pairs on a Dask cluster (tcp://host:8786)")
    pm.add_argument("--save-mode", choices=SAVE_MODES, default="trinary", help="image mode of the output (default: trinary, as map_saver)")
    pm.add_argument("--plot", metavar="PNG", help="also write a picture of the matches and the merged map")
    pm.add_argument("--out-bag", metavar="BAG", default=None,
                    help="also write the merged map (/map) and each map's transform (/tf_static, map -> NAME/map) "
                    "into a new bag: a .bag file is ROS 1, anything else a ROS 2 bag folder")
    pm.add_argument("--bag-storage", choices=("sqlite3", "mcap"), default="sqlite3", help="storage of a ROS 2 --out-bag (default sqlite3)")
    pm.add_argument("--progress", action="store_true", help="show progress on stderr even when it is not a terminal")
    pm.add_argument("--force", action="store_true", help="overwrite existing output files")
    ps = sub.add_parser(
        "sample",
        help="write a sample pair of maps to try the other commands on",
        description="Write a.yaml/a.pgm and b.yaml/b.pgm (and truth.json) into FOLDER.",
    )
    ps.add_argument("folder", metavar="FOLDER", help="an existing folder")
    ps.add_argument("--kind", choices=SAMPLE_KINDS, default="robots", help="robots (default): two robots in one building; table1: the paper's experiment; different: two buildings; "
                    "fleet: eight robots of one building and one of another, as map files and a ROS 1 bag")
    ps.add_argument("--seed", type=int, default=0, help="building seed (default 0)")
    ps.add_argument("--force", action="store_true", help="overwrite existing files")
    ps.add_argument("--debug", action="store_true", help="show the traceback of errors")
    debug = argparse.ArgumentParser(add_help=False)
    debug.add_argument("--debug", action="store_true", help="show the traceback of errors")
    bench_cli.add_parser(sub, parents=[debug])
    return p


def _same_file(p: Path, q: Path) -> bool:
    try:
        return p.resolve() == q.resolve() or (p.exists() and q.exists() and os.path.samefile(p, q))
    except (OSError, ValueError):  # ValueError: NUL bytes or surrogates in a name
        return False


def _input_files(paths: Sequence[str], limits: Limits) -> list[Path]:
    """The input paths and, for map_server YAMLs, the images they name."""
    files = []
    for s in paths:
        files.append(Path(s))
        image = yaml_image_path(s, max_yaml_bytes=limits.max_yaml_bytes)  # None if broken: load_map says why
        if image is not None:
            files.append(image)
    return files


def _check_output(path: Path, inputs: list[Path], force: bool, what: str) -> None:
    if not path.parent.is_dir():
        raise OutputError(f"{what} folder does not exist: {path.parent}")
    if path.is_dir():
        raise OutputError(f"{what} {path} is a directory")
    for q in inputs:
        if _same_file(path, q):
            raise OutputError(f"{what} {path} is one of the inputs; choose another name")
    if path.exists() and not force:
        raise OutputError(f"{what} {path} exists; use --force to overwrite it")


def _load_all(paths: Sequence[str], resolution: float | None, limits: Limits):
    # --resolution is for bare images and .npy files; a YAML's own resolution is kept.
    return [
        load_map(p, resolution=None if Path(p).suffix.lower() in YAML_SUFFIXES else resolution, limits=limits)
        for p in paths
    ]


def _print_json(obj) -> None:
    sys.stdout.write(json.dumps(finite(obj), indent=2, allow_nan=False) + "\n")


def _capped_note(result, limits: Limits) -> str:
    if not (result.details or {}).get("features_capped"):
        return ""
    return (
        f"note: keypoints were capped (at most {limits.max_keypoints} per map, detected in at most "
        f"{limits.max_feature_pixels} pixels; see --max-keypoints, --max-feature-pixels)"
    )


def _walls_line(result) -> str:
    """What a taken pose's walls say: how many of each map's wall cells in the overlap
    lie on the other's ("" when the result does not count them)."""
    v = result.verification
    counts = "" if v is None else v.wall_counts(("A", "B"))
    return f"walls agree on {v.wall_agreement:.0%} of the overlap: {counts}" if counts else ""


def _scale_options(args) -> dict:
    """AlignOptions of --trust-resolution and --any-scale (neither: the defaults)."""
    if args.any_scale:
        return dict(ANY_SCALE)
    return {"scale_prior": _SCALE_PRIOR} if args.trust_resolution else {}


def _cmd_align(args) -> int:
    decline = _decline_options(args)
    limits = _limits(args)
    if args.plot:
        from ..plot import require_matplotlib

        require_matplotlib()
        _check_output(Path(args.plot), _input_files([args.a, args.b], limits), args.force, "plot")
    a, b = _load_all([args.a, args.b], args.image_resolution, limits)
    extractor = extractor_for(args.method, limits)
    r = align(a, b, method=args.method, rng=args.seed, max_keypoints=limits.max_keypoints, extractor=extractor,
              **_scale_options(args), **decline)
    if args.plot:
        from ..plot import plot_alignment, save_plot

        save_plot(plot_alignment(a, b, r), args.plot)
    if args.json:
        _print_json(r.to_dict())
        return EXIT_OK if r.success else EXIT_DECLINED
    if r.success:
        t = r.transform
        m = r.metric or {}
        print(f"aligned: rotation {r.rotation_deg:.3f} deg, scale {r.scale:.5f}, translation ({t.translation[0]:.2f}, {t.translation[1]:.2f}) px")
        print(f"metric (B's frame in A's): x {m['x']:.3f} m, y {m['y']:.3f} m, yaw {m['yaw']:.5f} rad, scale {m['scale']:.5f}")
        print(f"confidence {r.confidence:.2f}, acceptance index {r.acceptance_index:.3f}, {r.inliers} inliers of {r.matches} matches, {r.elapsed_s:.2f} s")
        if _walls_line(r):
            print(_walls_line(r))
        if "confirmed_by" in r.details:
            print(f"confirmed by {r.details['confirmed_by']}")
    else:
        print(f"not aligned: {r.message}")
    if args.plot:
        print(f"wrote {args.plot}")
    if _capped_note(r, limits):
        print(_capped_note(r, limits))
    for w in r.warnings:
        print(f"gridmerge: warning: {w}", file=sys.stderr)
    return EXIT_OK if r.success else EXIT_DECLINED


def _read_inputs(args, limits: Limits):
    """The maps named on the command line: files, and every chosen topic of every bag.

    Returns ``(maps, names, child_frames)``; a map from a bag is named by its topic
    (``BAG:TOPIC`` when several bags hold that topic), a file by its path as given.
    """
    from ..io.bags import bag_topics, child_frame_for, is_bag, read_bag_maps

    bags = [p for p in args.maps if is_bag(p)]
    if args.topic and not bags:
        raise _UsageError("--topic selects maps of ROS bags, but no input is a bag")
    wanted: dict = {p: args.topic for p in bags}
    if args.topic and len(bags) > 1:
        # Several bags: each gives the chosen topics it has; every topic must be somewhere.
        have = {p: {t for t, _, _ in bag_topics(p)} for p in bags}
        for t in args.topic:
            if not any(t in h or "/" + t.lstrip("/") in h for h in have.values()):
                raise _UsageError(f"topic {t} is in none of the bags")
        wanted = {p: [t for t in args.topic if t in have[p] or "/" + t.lstrip("/") in have[p]] for p in bags}
    entries = []  # (map, name, child frame)
    topics_seen: dict = {}
    for p in args.maps:
        if p in bags:
            if wanted[p] == []:
                continue
            for grid in read_bag_maps(p, wanted[p], limits=limits):
                topics_seen.setdefault(grid.name, []).append(p)
                entries.append((grid, p, grid.name))
        else:
            entries.append((_load_all([p], args.image_resolution, limits)[0], p, None))
    maps, names, frames = [], [], []
    for k, (grid, path, topic) in enumerate(entries):
        if topic is None:
            name, frame = path, f"robot{k + 1}/map"
        else:
            name = topic if len(topics_seen[topic]) == 1 else f"{path}:{topic}"
            frame = child_frame_for(topic) if len(topics_seen[topic]) == 1 else f"robot{k + 1}/map"
        if frame == "map" or frame in frames:  # "map" is the merged map's own frame
            frame = f"robot{k + 1}/map"
        maps.append(grid)
        names.append(name)
        frames.append(frame)
    return maps, names, frames


def _cmd_merge(args) -> int:
    out = Path(args.output)
    if out.suffix.lower() not in YAML_SUFFIXES:
        raise _UsageError(f"the output must be a map_server .yaml file, got {out}")
    decline = _decline_options(args)
    if args.resolution is not None and not (math.isfinite(args.resolution) and args.resolution > 0):
        raise _UsageError(f"--resolution must be a number > 0, got {args.resolution}")
    limits = _limits(args)
    from ..io.bags import is_bag

    if len(args.maps) < 2 and not any(is_bag(p) for p in args.maps):
        raise _UsageError("merge needs at least two maps")
    inputs = _input_files([p for p in args.maps if not is_bag(p)], limits) + [Path(p) for p in args.maps if is_bag(p)]
    _check_output(out, inputs, args.force, "output")
    _check_output(out.with_suffix(".pgm"), inputs, args.force, "output image")
    if args.plot:
        from ..plot import require_matplotlib

        require_matplotlib()
        _check_output(Path(args.plot), inputs, args.force, "plot")
    if args.out_bag:
        bag = Path(args.out_bag)
        if not bag.parent.is_dir():
            raise OutputError(f"bag folder does not exist: {bag.parent}")
        if any(_same_file(bag, q) for q in inputs):
            raise OutputError(f"bag {bag} is one of the inputs; choose another name")
        if bag.exists() and not args.force:
            raise OutputError(f"bag {bag} exists; use --force to overwrite it")
    maps, names, frames = _read_inputs(args, limits)
    if len(maps) < 2:
        raise _UsageError(f"merge needs at least two maps, got {len(maps)}")
    reference = 0
    if args.reference is not None:
        if args.reference not in names:
            raise _UsageError(f"--reference {args.reference!r} is not one of the maps: {', '.join(names)}")
        reference = names.index(args.reference)
    show = bool(args.progress) or sys.stderr.isatty()
    progress = None
    if show and not args.json:
        bar = bench_cli.ProgressBar()

        def progress(stage, done, total):
            bar(done, total, stage)

    from ..parallel import executor_for

    with executor_for(args.workers, args.scheduler) as executor:
        result = merge(
            maps, method=args.method, fusion=args.fusion, rng=args.seed, limits=limits, names=names,
            reference=reference, resolution=args.resolution, pairs=args.pairs, scale_check=args.scale_check,
            executor=executor, progress=progress, **_scale_options(args), **decline,
        )
    if result.success:
        if args.out_bag:
            _write_out_bag(Path(args.out_bag), result, frames, args)
        try:
            save_map(result.grid, out, mode=args.save_mode)  # type: ignore[arg-type]
        except BaseException:
            if args.out_bag:
                _remove_tree(Path(args.out_bag))
            raise
        if args.plot:
            from ..plot import plot_fleet, plot_merge, save_plot

            if len(maps) > 2:  # every map, and where each went in the merged map
                png = plot_fleet(result)
            else:  # the matches between the two maps, and the merged map
                best = next(p for p in result.pairs if p.used)
                png = plot_merge(maps[best.i], maps[best.j], best.result, result.grid)  # type: ignore[arg-type]
            save_plot(png, args.plot)
    if not args.json:
        for w in result.warnings:
            print(f"gridmerge: warning: {w}", file=sys.stderr)
    if args.json:
        d = result.to_dict()
        d["output"] = str(out) if result.success else None
        d["out_bag"] = str(args.out_bag) if result.success and args.out_bag else None
        _print_json(d)
    elif result.success:
        wrote = [str(out)] + ([args.plot] if args.plot else []) + ([args.out_bag] if args.out_bag else [])
        print(f"{result.message}; wrote {', '.join(wrote)}")
        for k, name in enumerate(result.names):
            m = result.metric(k)
            if m is None:
                continue
            conf = result.confidences[k]
            print(f"  {name}: x {m['x']:.3f} m, y {m['y']:.3f} m, yaw {m['yaw']:.5f} rad, scale {m['scale']:.5f}, confidence {conf:.2f}")
    else:
        print(f"not merged: {result.message}")
    if not args.json:
        note = next((_capped_note(al, limits) for al in result.alignments if al is not None and _capped_note(al, limits)), "")
        if note:
            print(note)
    return EXIT_OK if result.success else EXIT_DECLINED


def _write_out_bag(path: Path, result, frames, args) -> None:
    from ..io.bags import BagTransform, write_bag

    transforms = []
    for k in result.placed:
        m = result.metric(k)
        transforms.append(BagTransform(frames[k], m["x"], m["y"], m["yaw"]))
    fmt = "ros1" if path.suffix.lower() == ".bag" else "ros2"
    write_bag(path, result.grid, transforms, format=fmt, storage=args.bag_storage, overwrite=bool(args.force))


def _remove_tree(path: Path) -> None:
    import shutil

    if path.is_dir():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists():
        path.unlink()


def _cmd_sample(args) -> int:
    folder = Path(args.folder)
    for name in sample_outputs(args.kind):
        _check_output(folder / name, [], args.force, "output")
    written = write_sample(folder, args.kind, args.seed)
    print("wrote " + ", ".join(str(p) for p in written.values()))
    return EXIT_OK


_COMMANDS = {"align": _cmd_align, "merge": _cmd_merge, "sample": _cmd_sample, "bench": bench_cli.run}


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit code.

    Run as the program (``argv`` None: the ``gridmerge`` command, ``python -m
    gridmerge``), it first lets the allocator keep large freed blocks
    (:func:`gridmerge.parallel.keep_freed_memory`): the process is gridmerge's own, and
    a merge of many maps or a benchmark run aligns one pair after another. Called with
    ``argv`` from another program, it leaves that program's allocator alone."""
    if argv is None:
        keep_freed_memory()
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv
    if hasattr(sys.stdout, "reconfigure"):
        sys.stdout.reconfigure(errors="backslashreplace")  # undecodable file names
    previous = None
    try:
        previous = _catch_sigterm()
        args = _parser().parse_args(argv)
        if args.command is None:
            raise _UsageError(f"a command is needed: {', '.join(_COMMANDS)}")
        return _COMMANDS[args.command](args)
    except KeyboardInterrupt:
        print("gridmerge: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except _Terminated:
        print("gridmerge: terminated", file=sys.stderr)
        return EXIT_TERMINATED
    except SystemExit as exc:  # --help and --version
        return int(exc.code or 0) if isinstance(exc.code, int) else 0
    except BrokenPipeError:
        # Whatever was being written to a file is complete or not there (files are
        # written atomically); only the printout is cut. Python's final flush of stdout
        # would fail again: point it at the null device.
        _silence_stdout()
        return EXIT_BROKEN_PIPE
    except Exception as exc:  # noqa: BLE001 - every error ends as one line
        if debug:  # the traceback, then the usual line and exit code (not Python's 1 = "declined")
            traceback.print_exc()
        if isinstance(exc, GridMergeError):
            msg = str(exc)
            limit = getattr(exc, "limit", None) if isinstance(exc, LimitExceededError) else None
            if limit:
                msg += f"; see --{limit.replace('_', '-')}"
        elif isinstance(exc, MemoryError):
            msg = "out of memory (see docs/limits.md)"
        elif isinstance(exc, OSError):
            msg = f"{exc.strerror or exc}" + (f": {exc.filename}" if getattr(exc, "filename", None) else "")
        else:
            msg = f"unexpected {type(exc).__name__}: {exc} (run with --debug for the traceback)"
        print(f"gridmerge: error: {' '.join(msg.split())}", file=sys.stderr)
        return EXIT_BAD_INPUT
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _silence_stdout() -> None:
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):  # no real file behind sys.stdout (tests)
        pass


def _catch_sigterm():
    """Turn SIGTERM into an exception (main thread only); returns the previous handler."""
    try:
        return signal.signal(signal.SIGTERM, _on_sigterm)
    except (ValueError, OSError, AttributeError):  # not the main thread, or no SIGTERM
        return None


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

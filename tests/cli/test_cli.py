"""End-to-end tests of the ``gridmerge`` program, run as a real subprocess.

Every test runs ``python -m gridmerge ...`` (the same code as the ``gridmerge`` console
script) and checks what a user sees: the exit code (0 done, 1 declined, 2 bad input),
stdout (JSON or text), stderr (one line on errors, no traceback unless ``--debug``) and
the files left in the folder (the output, or nothing at all; inputs never change).

Every run of the module is declared once in the module-scoped ``runs`` fixture and they
run side by side, four at a time: each costs about 0.4 s of imports, alignments and
merges of the Table I pair 1-3 s, the declined pair 2-6 s of CPU.
Each run that writes has its own folder, so the runs cannot disturb one another.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import math
import os
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pytest

import gridmerge
from gridmerge import OccupancyGrid, load_map, save_map
from gridmerge.fuse import FUSION_RULES

#: The module (the package's ``align`` name is the function).
align_module = importlib.import_module("gridmerge.align")

#: A subprocess never takes longer than this (a hang fails one test, not the suite). A
#: guard against hangs only: the runs share the CPUs (four at a time, next to the other
#: test workers), and on a slow, busy machine a declined pair took over 100 s.
TIMEOUT_S = 600

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


# --------------------------------------------------------------------- helpers
def _command(args) -> list:
    return [sys.executable, "-m", "gridmerge", *map(str, args)]


def _env() -> dict:
    env = dict(os.environ)
    env.setdefault("MPLBACKEND", "Agg")
    return env


@dataclass
class Job:
    """One declared run of the program."""

    args: list
    cwd: Path
    log: Path
    before: dict = field(default_factory=dict)  # snapshot of cwd when it was declared
    skip: str = ""  # reason to skip the tests of this run (its set-up was impossible)
    proc: subprocess.Popen | None = None
    result: subprocess.CompletedProcess | None = None
    started: float = 0.0


class Runner:
    """Runs the declared jobs side by side, at most ``limit`` at a time, in the order
    declared (a job asked for is started next); :meth:`get` waits for one job, starting
    others as slots free up. :meth:`close` kills the jobs still running."""

    def __init__(self, logs: Path, limit: int):
        self.logs, self.limit = logs, limit
        self.jobs: dict[str, Job] = {}
        self.pending: list[str] = []

    def add(self, key: str, args, cwd: Path, skip: str = "") -> Job:
        assert key not in self.jobs, key
        job = Job([str(a) for a in args], Path(cwd), self.logs / f"{len(self.jobs):03d}-{re.sub(r'[^A-Za-z0-9_-]', '_', key)}", snapshot(cwd), skip)
        self.jobs[key] = job
        if not skip:
            self.pending.append(key)
        return job

    def _running(self) -> list[Job]:
        return [j for j in self.jobs.values() if j.proc is not None and j.result is None]

    def _reap(self, job: Job, wait: bool) -> None:
        if job.proc is None or job.result is not None:
            return
        if wait:
            try:
                job.proc.wait(timeout=max(1.0, TIMEOUT_S - (time.monotonic() - job.started)))
            except subprocess.TimeoutExpired:
                job.proc.kill()
                job.proc.wait()
        elif job.proc.poll() is None:
            return
        out = Path(f"{job.log}.out").read_text(errors="replace")
        err = Path(f"{job.log}.err").read_text(errors="replace")
        job.result = subprocess.CompletedProcess(job.proc.args, job.proc.returncode, out, err)

    def _pump(self) -> None:
        for job in self._running():
            self._reap(job, wait=False)
        while self.pending and len(self._running()) < self.limit:
            job = self.jobs[self.pending.pop(0)]
            with open(f"{job.log}.out", "wb") as out, open(f"{job.log}.err", "wb") as err:
                job.proc = subprocess.Popen(
                    _command(job.args), cwd=str(job.cwd), env=_env(), stdin=subprocess.DEVNULL, stdout=out, stderr=err
                )
            job.started = time.monotonic()

    def get(self, key: str) -> Job:
        job = self.jobs[key]
        if job.skip:
            pytest.skip(job.skip)
        if key in self.pending:  # wanted now: start it next
            self.pending.remove(key)
            self.pending.insert(0, key)
        while job.result is None:
            self._pump()
            if job.result is not None:
                break
            if job.proc is not None and time.monotonic() - job.started > TIMEOUT_S:
                self._reap(job, wait=True)  # kills it
            else:
                time.sleep(0.01)
        return job

    def close(self) -> None:
        self.pending.clear()
        for job in self._running():
            job.proc.kill()
            job.proc.wait()


def snapshot(folder: Path) -> dict:
    """``{relative path: sha256}`` of everything below ``folder``, hidden files included
    (directories as ``"<dir>"``)."""
    out = {}
    for p in sorted(Path(folder).rglob("*")):
        rel = p.relative_to(folder).as_posix()
        out[rel] = "<dir>" if p.is_dir() and not p.is_symlink() else hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def describe(proc: subprocess.CompletedProcess) -> str:
    return f"exit {proc.returncode}\n--- stdout ---\n{proc.stdout[-3000:]}\n--- stderr ---\n{proc.stderr[-3000:]}"


def assert_one_line_error(proc: subprocess.CompletedProcess, code: int = 2, contains: str | None = None) -> str:
    """The contract for errors: exit ``code``, nothing on stdout, exactly one non-empty
    line on stderr, starting with ``gridmerge: error:``, and no traceback."""
    assert proc.returncode == code, describe(proc)
    assert "Traceback" not in proc.stderr, describe(proc)
    assert proc.stdout == "", describe(proc)
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and proc.stderr.endswith("\n"), describe(proc)
    line = lines[0]
    assert line.startswith("gridmerge: error: ") and line[len("gridmerge: error: "):].strip(), describe(proc)
    if contains is not None:
        assert contains.lower() in line.lower(), describe(proc)
    return line


def parse_json(proc: subprocess.CompletedProcess) -> dict:
    """stdout must be exactly one JSON object (json.loads refuses trailing text)."""
    d = json.loads(proc.stdout)
    assert isinstance(d, dict), proc.stdout[:200]
    return d


def corner_error(matrix, truth: np.ndarray, shape) -> float:
    """Largest distance (a pixels) between the images of b's corners under both transforms."""
    h, w = shape
    corners = np.array([[-0.5, -0.5, 1], [w - 0.5, -0.5, 1], [w - 0.5, h - 0.5, 1], [-0.5, h - 0.5, 1]], float)
    m = np.asarray(matrix, dtype=float)
    assert m.shape == (2, 3)
    return float(np.hypot(*(corners @ m.T - corners @ truth[:2].T).T).max())


def metric_matrix(metric: dict) -> np.ndarray:
    """The (3, 3) similarity of a ``{"x", "y", "yaw", "scale"}`` pose."""
    c, s = metric["scale"] * math.cos(metric["yaw"]), metric["scale"] * math.sin(metric["yaw"])
    return np.array([[c, -s, metric["x"]], [s, c, metric["y"]], [0.0, 0.0, 1.0]])


def metric_error(metric: dict, a: OccupancyGrid, b: OccupancyGrid, truth: np.ndarray) -> float:
    """Largest distance (metres, in a's frame) between where the reported metric pose puts
    points of b and where they truly are: ``a.pixel_to_metric(truth(p))``."""
    h, w = b.shape
    xs, ys = np.meshgrid(np.linspace(0, w - 1, 7), np.linspace(0, h - 1, 5))
    p_b = np.stack([xs.ravel(), ys.ravel()], axis=1)
    true_a_px = p_b @ truth[:2, :2].T + truth[:2, 2]
    expected = a.pixel_to_metric(true_a_px)
    m = metric_matrix(metric)
    reported = b.pixel_to_metric(p_b) @ m[:2, :2].T + m[:2, 2]
    return float(np.hypot(*(reported - expected).T).max())


def check_a_kept(merged: OccupancyGrid, a: OccupancyGrid) -> None:
    """a's cells keep their value at the same metric place of the merged map.

    Cells of a go through a's metric frame into the merged map's pixels, where they must
    fall exactly on cell centres. Free cells far from walls (7 x 7 neighbourhood free)
    must be free there, and a's occupied cells occupied: walls are 2-4 cells thick, so a
    placement one cell off keeps only about 88 % of them.
    """
    deep_free = cv2.erode(a.free().astype(np.uint8), np.ones((7, 7), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
    occupied = a.occupied()
    assert deep_free.sum() > 1000 and occupied.sum() > 1000
    for mask, what in ((deep_free, "free cells far from walls"), (occupied, "occupied cells")):
        rows, cols = np.nonzero(mask)
        px_a = np.stack([cols, rows], axis=1).astype(float)
        px_m = merged.metric_to_pixel(a.pixel_to_metric(px_a))
        # The merged map keeps a's cells: same resolution, whole-cell offset.
        assert np.abs(px_m - np.rint(px_m)).max() < 1e-6
        c, r = np.rint(px_m).astype(int).T
        assert (c >= 0).all() and (r >= 0).all() and (c < merged.width).all() and (r < merged.height).all()
        values = merged.data[r, c]
        kept = np.mean(values == 0.0) if mask is deep_free else np.mean(values > 0.65)
        assert kept >= 0.98, f"only {kept:.1%} of a's {what} kept"


# -------------------------------------------------------------- bad-input set-ups
def _write(name, data):
    def setup(folder: Path):
        p = folder / name
        p.write_bytes(data) if isinstance(data, bytes) else p.write_text(data)

    return setup


def _mkdir(name):
    return lambda folder: (folder / name).mkdir()


def _random_png(folder):
    (folder / "noise.png").write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())


def _truncated_pgm(folder):
    data = (folder / "a.pgm").read_bytes()
    (folder / "trunc.pgm").write_bytes(data[: len(data) // 3])


def _npy(name, array):
    return lambda folder: np.save(folder / name, array)


def _symlink(folder):
    try:
        os.symlink("a.yaml", folder / "link.yaml")
    except (OSError, NotImplementedError, AttributeError):
        return "symbolic links are not available"


def _hardlink(folder):
    try:
        os.link(folder / "a.yaml", folder / "hard.yaml")
    except (OSError, NotImplementedError, AttributeError):
        return "hard links are not available"


def _old_output(folder):
    (folder / "out.yaml").write_text("old\n")
    (folder / "out.pgm").write_bytes(b"old")


def _nothing(folder):
    pass


# (id, setup(folder) -> None or a reason to skip, arguments, a piece of the expected
# error line). Each runs in a folder holding a.yaml, a.pgm, b.yaml and b.pgm.
BAD_INPUT = [
    ("missing-file", _nothing, ["merge", "a.yaml", "missing.yaml", "-o", "out.yaml"], "missing.yaml"),
    ("directory", _mkdir("dir.yaml"), ["merge", "a.yaml", "dir.yaml", "-o", "out.yaml"], "dir.yaml"),
    ("directory-no-suffix", _mkdir("maps"), ["align", "a.yaml", "maps"], "maps"),
    ("random-bytes-png", _random_png, ["merge", "a.yaml", "noise.png", "-o", "out.yaml"], "noise.png"),
    ("truncated-pgm", _truncated_pgm, ["merge", "a.yaml", "trunc.pgm", "-o", "out.yaml"], "trunc.pgm"),
    ("binary-yaml", _write("bin.yaml", b"\x00\x01\x02\xff" * 50), ["merge", "a.yaml", "bin.yaml", "-o", "out.yaml"], "bin.yaml"),
    ("yaml-syntax", _write("bad.yaml", "image: [a.pgm\nresolution: 0.05\n"), ["merge", "a.yaml", "bad.yaml", "-o", "out.yaml"], "bad.yaml"),
    ("yaml-no-image", _write("noimg.yaml", "resolution: 0.05\norigin: [0, 0, 0]\n"), ["merge", "a.yaml", "noimg.yaml", "-o", "out.yaml"], "image"),
    ("yaml-no-resolution", _write("nores.yaml", "image: a.pgm\norigin: [0, 0, 0]\n"), ["merge", "a.yaml", "nores.yaml", "-o", "out.yaml"], "resolution"),
    ("yaml-image-missing", _write("gone.yaml", "image: gone.pgm\nresolution: 0.05\n"), ["merge", "a.yaml", "gone.yaml", "-o", "out.yaml"], "gone.pgm"),
    ("empty-npy-0x0", _npy("empty.npy", np.zeros((0, 0))), ["merge", "a.yaml", "empty.npy", "-o", "out.yaml"], "empty"),
    ("empty-npy-0x5", _npy("empty.npy", np.zeros((0, 5))), ["merge", "a.yaml", "empty.npy", "-o", "out.yaml"], "empty"),
    ("npy-1d", _npy("line.npy", np.zeros(10)), ["align", "a.yaml", "line.npy"], "line.npy"),
    ("unknown-extension", _write("map.txt", "hello\n"), ["align", "a.yaml", "map.txt"], "map.txt"),
    ("resolution-zero", _nothing, ["align", "a.pgm", "b.pgm", "--resolution", "0"], "resolution"),
    ("resolution-not-a-number", _nothing, ["align", "a.pgm", "b.pgm", "--resolution", "fine"], "resolution"),
    ("output-folder-missing", _nothing, ["merge", "a.yaml", "b.yaml", "-o", "nowhere/out.yaml"], "nowhere"),
    ("plot-folder-missing", _nothing, ["merge", "a.yaml", "b.yaml", "-o", "out.yaml", "--plot", "nowhere/p.png"], "nowhere"),
    ("output-not-yaml", _nothing, ["merge", "a.yaml", "b.yaml", "-o", "out.png"], "yaml"),
    ("output-is-directory", _mkdir("out.yaml"), ["merge", "a.yaml", "b.yaml", "-o", "out.yaml", "--force"], "directory"),
    ("single-map", _nothing, ["merge", "a.yaml", "-o", "out.yaml"], "two maps"),
    ("output-is-input", _nothing, ["merge", "a.yaml", "b.yaml", "-o", "a.yaml"], "input"),
    ("output-is-input-force", _nothing, ["merge", "a.yaml", "b.yaml", "-o", "./a.yaml", "--force"], "input"),
    ("output-image-is-input", _nothing, ["merge", "a.yaml", "b.yaml", "-o", "a.yml", "--force"], "input"),
    ("output-symlink-to-input", _symlink, ["merge", "a.yaml", "b.yaml", "-o", "link.yaml", "--force"], "input"),
    ("output-hardlink-to-input", _hardlink, ["merge", "a.yaml", "b.yaml", "-o", "hard.yaml", "--force"], "input"),
    ("plot-is-input", _nothing, ["merge", "a.yaml", "b.yaml", "-o", "out.yaml", "--plot", "b.pgm", "--force"], "input"),
    ("output-exists", _old_output, ["merge", "a.yaml", "b.yaml", "-o", "out.yaml"], "--force"),
    ("output-image-exists", _write("out.pgm", b"P5\n1 1\n255\n\x00"), ["merge", "a.yaml", "b.yaml", "-o", "out.yaml"], "--force"),
    ("plot-exists", _write("p.png", b"old"), ["merge", "a.yaml", "b.yaml", "-o", "out.yaml", "--plot", "p.png"], "--force"),
    ("align-plot-exists", _write("p.png", b"old"), ["align", "a.yaml", "b.yaml", "--plot", "p.png"], "--force"),
    ("align-plot-is-input", _nothing, ["align", "a.yaml", "b.yaml", "--plot", "b.pgm", "--force"], "input"),
    ("align-plot-folder-missing", _nothing, ["align", "a.yaml", "b.yaml", "--plot", "nowhere/p.png"], "nowhere"),
    ("unknown-option", _nothing, ["align", "a.yaml", "b.yaml", "--frobnicate"], "--frobnicate"),
    ("unknown-method", _nothing, ["align", "a.yaml", "b.yaml", "--method", "magic"], "magic"),
    ("unknown-fusion", _nothing, ["merge", "a.yaml", "b.yaml", "-o", "out.yaml", "--fusion", "min"], "min"),
    ("unknown-command", _nothing, ["stitch", "a.yaml", "b.yaml"], "stitch"),
    ("no-command", _nothing, [], "command"),
    ("align-one-map", _nothing, ["align", "a.yaml"], "required"),
    ("merge-without-output", _nothing, ["merge", "a.yaml", "b.yaml"], "-o"),
    ("sample-exists", _nothing, ["sample", "."], "--force"),
    ("sample-folder-missing", _nothing, ["sample", "nowhere"], "nowhere"),
    ("sample-unknown-kind", _mkdir("empty"), ["sample", "empty", "--kind", "moon"], "moon"),
    ("min-confidence-above-one", _nothing, ["align", "a.yaml", "b.yaml", "--min-confidence", "1.5"], "0 to 1"),
    ("min-confidence-negative", _nothing, ["merge", "a.yaml", "b.yaml", "-o", "out.yaml", "--min-confidence", "-0.1"], "0 to 1"),
    ("one-sided-not-a-number", _nothing, ["align", "a.yaml", "b.yaml", "--one-sided-confidence", "high"], "high"),
    ("min-confidence-nan", _nothing, ["align", "a.yaml", "b.yaml", "--min-confidence", "nan"], "0 to 1"),
    ("max-slide-above-one", _nothing, ["align", "a.yaml", "b.yaml", "--max-slide", "2"], "0 to 1"),
    ("max-slide-with-baseline", _nothing, ["align", "a.yaml", "b.yaml", "--method", "orb", "--max-slide", "0.5"], "own rule"),
    ("max-crossing-negative", _nothing, ["merge", "a.yaml", "b.yaml", "-o", "out.yaml", "--max-crossing", "-1"], "0 to 1"),
    ("max-crossing-with-baseline", _nothing, ["align", "a.yaml", "b.yaml", "--method", "hough", "--max-crossing", "0.5"], "own rule"),
    ("unsure-walls-negative", _nothing, ["align", "a.yaml", "b.yaml", "--unsure-walls", "-5"], "0 or more"),
    ("unsure-walls-fraction", _nothing, ["merge", "a.yaml", "b.yaml", "-o", "out.yaml", "--unsure-walls", "0.5"], "whole number"),
    ("unsure-walls-with-baseline", _nothing, ["align", "a.yaml", "b.yaml", "--method", "orb", "--unsure-walls", "5"], "own rule"),
    ("overlap-walls-negative", _nothing, ["align", "a.yaml", "b.yaml", "--min-overlap-walls", "-3"], "0 or more"),
    ("few-walls-agreement-above-one", _nothing, ["align", "a.yaml", "b.yaml", "--few-walls-agreement", "1.2"], "0 to 1"),
    ("few-walls-agreement-with-baseline", _nothing, ["align", "a.yaml", "b.yaml", "--method", "orb", "--few-walls-agreement", "0.5"], "own rule"),
    ("overlap-walls-with-baseline", _nothing, ["merge", "a.yaml", "b.yaml", "-o", "out.yaml", "--method", "orb", "--min-overlap-walls", "5"], "own rule"),
    # The baselines decline by their authors' rules: a threshold would be silently ignored.
    ("threshold-with-baseline", _nothing, ["align", "a.yaml", "b.yaml", "--method", "orb", "--min-confidence", "0.4"], "own rule"),
    ("merge-threshold-with-baseline", _nothing,
     ["merge", "a.yaml", "b.yaml", "-o", "out.yaml", "--method", "hough", "--one-sided-confidence", "0.6"], "own rule"),
]

OTHER_FUSIONS = [f for f in FUSION_RULES if f != "average"]


# ------------------------------------------------------------------- the runs
@pytest.fixture(scope="module")
def runs(sample_maps, tmp_path_factory):
    """Every run of this module, declared here and started in the background."""
    base = tmp_path_factory.mktemp("runs")
    logs = base / "_logs"
    logs.mkdir()
    runner = Runner(logs, limit=4)

    def folder(key, *maps):
        return sample_maps.copy_to(base / key, *(maps or ("a", "b")))

    # The slow runs first, so that they start at once.
    # --resolution 0.1: a's own (the default would be b's finer 0.095 m/cell).
    runner.add("merge", ["merge", "a.yaml", "b.yaml", "-o", "out.yaml", "--plot", "p.png", "--json", "--fusion", "average", "--resolution", "0.1"], folder("merge"))
    runner.add("align-json", ["align", "a.yaml", "b.yaml", "--json"], sample_maps.folder)
    runner.add("align-trust", ["align", "a.yaml", "b.yaml", "--json", "--trust-resolution"], sample_maps.folder)
    runner.add("align-any", ["align", "a.yaml", "b.yaml", "--json", "--any-scale"], sample_maps.folder)
    runner.add("align-trust-any", ["align", "a.yaml", "b.yaml", "--any-scale", "--trust-resolution"], sample_maps.folder)
    liar = folder("liar")  # b.yaml's resolution twice what its cells are
    text = (liar / "b.yaml").read_text()
    assert "resolution: 0.095" in text
    (liar / "b.yaml").write_text(text.replace("resolution: 0.095", "resolution: 0.19"))
    runner.add("align-liar", ["align", "a.yaml", "b.yaml"], liar)
    runner.add("align-liar-any", ["align", "a.yaml", "b.yaml", "--json", "--any-scale"], liar)
    for fusion in OTHER_FUSIONS:
        runner.add(f"fusion-{fusion}", ["merge", "a.yaml", "b.yaml", "-o", "out.yaml", "--fusion", fusion, "--json", "--resolution", "0.1"], folder(f"fusion-{fusion}"))
    runner.add("merge-raw", ["merge", "a.yaml", "b.yaml", "-o", "out.yaml", "--save-mode", "raw", "--resolution", "0.1"], folder("merge-raw"))
    f = folder("merge-force")
    _old_output(f)
    runner.add("merge-force", ["merge", "a.yaml", "b.yaml", "-o", "out.yaml", "--force"], f)
    runner.add("merge-negative", ["merge", "neg_a.yaml", "neg_b.yaml", "-o", "out.yaml", "--plot", "p.png"], folder("merge-negative", "neg_a", "neg_b"))
    runner.add("align-text", ["align", "a.yaml", "b.yaml", "--plot", "p.png"], folder("align-text"))
    runner.add("align-negative-plot", ["align", "neg_a.yaml", "neg_b.yaml", "--plot", "p.png"], folder("align-negative-plot", "neg_a", "neg_b"))
    runner.add("align-negative", ["align", "neg_a.yaml", "neg_b.yaml", "--json"], sample_maps.folder)
    runner.add("align-paper", ["align", "a.yaml", "b.yaml", "--json", "--method", "paper"], sample_maps.folder)
    runner.add("align-sift", ["align", "a.yaml", "b.yaml", "--json", "--method", "sift"], sample_maps.folder)
    runner.add("align-sift-strict", ["align", "a.yaml", "b.yaml", "--json", "--method", "sift", "--min-confidence", "1"], sample_maps.folder)
    runner.add("merge-sift-strict", ["merge", "a.yaml", "b.yaml", "-o", "out.yaml", "--method", "sift", "--min-confidence", "1"], folder("merge-sift-strict"))
    runner.add("align-slide-strict", ["align", "a.yaml", "b.yaml", "--json", "--max-slide", "0"], sample_maps.folder)
    runner.add("align-crossing-strict", ["align", "a.yaml", "b.yaml", "--json", "--max-crossing", "0"], sample_maps.folder)
    runner.add("align-overlap-walls-strict", ["align", "a.yaml", "b.yaml", "--json", "--min-overlap-walls", "100000"], sample_maps.folder)
    runner.add("align-negative-any-confidence", ["align", "neg_a.yaml", "neg_b.yaml", "--json", "--min-confidence", "0", "--one-sided-confidence", "0"],
               sample_maps.folder)
    f = folder("merge-unknown", "a")
    save_map(OccupancyGrid(np.full((120, 160), np.nan)), f / "unknown.yaml")
    runner.add("merge-unknown", ["merge", "a.yaml", "unknown.yaml", "-o", "out.yaml", "--json"], f)
    # Quick ones.
    for key, setup, args, _ in BAD_INPUT:
        f = folder(f"bad-{key}")
        runner.add(f"bad-{key}", args, f, skip=setup(f) or "")
    runner.add("debug", ["merge", "a.yaml", "missing.yaml", "-o", "out.yaml", "--debug"], folder("debug"))
    f = base / "sample"
    f.mkdir()
    runner.add("sample", ["sample", ".", "--kind", "table1"], f)
    runner.add("version", ["--version"], base)
    for args in (["--help"], ["align", "--help"], ["merge", "--help"]):
        runner.add("help-" + "-".join(args), args, base)
    yield runner
    runner.close()


# ---------------------------------------------------------------------- basics
def test_python_m_gridmerge_runs(runs):
    proc = runs.get("version").result
    assert proc.returncode == 0, describe(proc)
    assert proc.stdout.strip() == f"gridmerge {gridmerge.__version__}"
    assert proc.stderr == ""


def test_console_script_on_path(tmp_path):
    exe = shutil.which("gridmerge")
    if exe is None:
        pytest.skip("the gridmerge console script is not installed on PATH")
    proc = subprocess.run([exe, "--version"], cwd=tmp_path, capture_output=True, text=True, timeout=TIMEOUT_S, stdin=subprocess.DEVNULL)
    assert proc.returncode == 0, describe(proc)
    assert proc.stdout.strip() == f"gridmerge {gridmerge.__version__}"


def test_a_reader_that_stops_early_ends_the_command_quietly(tmp_path):
    # `gridmerge sample DIR | head -0`: the pipe's reading end is closed before the
    # command prints its summary line; the files it wrote before are complete.
    read, write = os.pipe()
    os.close(read)
    try:
        proc = subprocess.run(_command(["sample", "."]), cwd=tmp_path, stdout=write, stderr=subprocess.PIPE,
                              stdin=subprocess.DEVNULL, text=True, timeout=TIMEOUT_S, env=_env())
    finally:
        os.close(write)
    assert proc.returncode == 141, proc.stderr
    assert proc.stderr == ""
    assert gridmerge.load_map(tmp_path / "a.yaml").shape == gridmerge.load_map(tmp_path / "a.pgm").shape


@pytest.mark.parametrize("args", [["--help"], ["align", "--help"], ["merge", "--help"]], ids=["top", "align", "merge"])
def test_help(args, runs):
    proc = runs.get("help-" + "-".join(args)).result
    assert proc.returncode == 0, describe(proc)
    assert proc.stdout.startswith("usage: gridmerge")
    assert proc.stderr == ""
    if args[0] == "--help":
        assert "align" in proc.stdout and "merge" in proc.stdout
    if args[0] == "merge":
        for option in ("--output", "--fusion", "--plot", "--force", "--save-mode", "--json"):
            assert option in proc.stdout



def test_decline_help_states_the_rules_fixed_values(monkeypatch):
    # The help of --unsure-walls and --max-crossing quotes values the flags do not set
    # (the confidence that spares a pose, the walls that exempt one): read from align,
    # so that the help follows a change of either.
    from gridmerge.cli import _decline

    monkeypatch.setattr(align_module, "SURE_CONFIDENCE", 0.85)
    monkeypatch.setattr(align_module, "_CROSSING_EVIDENCE", 2500)
    assert "confidence below 0.85 resting" in _decline.help_text("unsure_walls")
    assert "fewer than 2500 overlap wall cells" in _decline.help_text("max_crossing")
    monkeypatch.setattr(align_module, "FEW_WALLS_EVIDENCE", 150)
    assert "fewer than 150 overlap wall cells" in _decline.help_text("few_walls_agreement")


def test_only_the_program_lets_the_allocator_keep_freed_memory(monkeypatch, capsys):
    # gridmerge run as the program owns its process; main([...]) called by another
    # program leaves that program's allocator alone.
    from gridmerge.cli import main as cli_main

    calls = []
    monkeypatch.setattr(cli_main, "keep_freed_memory", lambda: calls.append(1) or True)
    assert cli_main.main(["--version"]) == 0
    assert calls == []
    monkeypatch.setattr(sys, "argv", ["gridmerge", "--version"])
    assert cli_main.main() == 0
    assert calls == [1]
    assert "gridmerge" in capsys.readouterr().out

# ----------------------------------------------------------------------- align
ALIGN_KEYS = {
    "success", "matrix", "rotation_deg", "scale", "translation_px", "metric",
    "confidence", "acceptance_index", "inliers", "elapsed_s",
}


def test_align_json_success(runs):
    proc = runs.get("align-json").result
    assert proc.returncode == 0, describe(proc)
    assert proc.stderr == ""
    d = parse_json(proc)
    assert ALIGN_KEYS <= d.keys()
    assert d["success"] is True
    assert d["method"] == "hybrid"  # the default method
    assert isinstance(d["inliers"], int) and d["inliers"] >= 8
    assert 0.5 <= d["confidence"] <= 1.0
    assert 0.7 <= d["acceptance_index"] <= 1.0
    assert isinstance(d["elapsed_s"], float) and 0 < d["elapsed_s"] < TIMEOUT_S


def test_align_json_transform_matches_truth(runs, sample_maps):
    d = parse_json(runs.get("align-json").result)
    err = corner_error(d["matrix"], sample_maps.truth, sample_maps.b.shape)
    assert err < 0.5, f"corner error {err:.3f} px"
    assert d["rotation_deg"] == pytest.approx(30.0, abs=0.1)
    assert d["scale"] == pytest.approx(0.95, abs=0.002)
    assert d["translation_px"] == pytest.approx(np.asarray(d["matrix"])[:, 2].tolist())
    assert d["translation_px"] == pytest.approx([-86.0, -36.0], abs=0.5)


def test_align_json_metric_uses_the_yaml_frames(runs, sample_maps):
    """x, y, yaw, scale: b's map frame in a's, from the YAMLs' resolutions and origins."""
    a, b, truth = sample_maps.a, sample_maps.b, sample_maps.truth
    m = parse_json(runs.get("align-json").result)["metric"]
    assert set(m) == {"x", "y", "yaw", "scale"}
    # b's cells are 0.95 of a's and the pixel scale is 0.95: the world has one size.
    assert m["scale"] == pytest.approx(1.0, abs=0.002)
    # +30 deg between the images (rows down) is -30 deg between the map frames (y up);
    # then b's frame is turned by its origin's yaw, a's by its own.
    expected_yaw = a.origin[2] - math.radians(30.0) - b.origin[2]
    assert m["yaw"] == pytest.approx(expected_yaw, abs=math.radians(0.1))
    # (x, y): where the origin of b's map frame lies in a's map frame.
    origin_b_in_a = a.pixel_to_metric(b.metric_to_pixel([[0.0, 0.0]]) @ truth[:2, :2].T + truth[:2, 2])[0]
    assert [m["x"], m["y"]] == pytest.approx(origin_b_in_a.tolist(), abs=0.5 * a.resolution)
    err = metric_error(m, a, b, truth)
    assert err < 0.5 * a.resolution, f"metric error {err:.4f} m"


def test_trust_resolution_pulls_the_metric_scale_to_one(runs, sample_maps):
    # The sample maps' resolutions are exact. By default the refinement pulls the scale
    # towards their ratio (metric scale, b's world over a's, nearer 1 than from the cells
    # alone, as --any-scale leaves it); --trust-resolution pulls harder; the pose is at
    # least as close to the truth.
    cells_only = parse_json(runs.get("align-any").result)["metric"]
    default = parse_json(runs.get("align-json").result)["metric"]
    trusted = parse_json(runs.get("align-trust").result)["metric"]
    assert abs(default["scale"] - 1.0) < abs(cells_only["scale"] - 1.0)
    assert abs(trusted["scale"] - 1.0) <= abs(default["scale"] - 1.0) + 1e-6
    a, b, truth = sample_maps.a, sample_maps.b, sample_maps.truth
    assert metric_error(default, a, b, truth) <= metric_error(cells_only, a, b, truth) + 1e-3
    assert metric_error(trusted, a, b, truth) <= metric_error(default, a, b, truth) + 1e-3


def test_min_confidence_moves_the_decline_threshold(runs):
    # sift aligns the sample pair at a confidence just under 1: asked for 1, the same
    # candidate is declined, with the threshold named; merge then writes nothing.
    default = parse_json(runs.get("align-sift").result)
    assert default["success"] and 0.5 <= default["confidence"] < 1.0
    proc = runs.get("align-sift-strict").result
    assert proc.returncode == 1, describe(proc)
    strict = parse_json(proc)
    assert not strict["success"] and strict["transform"] is None
    assert strict["confidence"] == pytest.approx(default["confidence"])
    assert strict["candidate"] == default["candidate"]
    assert "below 1" in strict["message"]
    merged = runs.get("merge-sift-strict")
    assert merged.result.returncode == 1, describe(merged.result)
    assert not (merged.cwd / "out.yaml").exists() and not (merged.cwd / "out.pgm").exists()


def test_max_slide_declines_a_pose_its_walls_do_not_fix_as_asked(runs):
    # The default pose of the sample pair records how much of its wall agreement it keeps
    # slid along its walls; asked to keep none, the same candidate is declined, saying why.
    default = parse_json(runs.get("align-json").result)
    assert default["success"] and 0.0 < default["details"]["slide"]["kept"] <= 0.75
    proc = runs.get("align-slide-strict").result
    assert proc.returncode == 1, describe(proc)
    strict = parse_json(proc)
    assert not strict["success"] and strict["candidate"] == default["candidate"]
    assert strict["message"].startswith("declined: the walls do not fix the pose") and "at most 0%" in strict["message"]


def test_max_crossing_is_recorded_and_spares_a_pose_on_many_walls(runs):
    # The sample pair's pose rests on thousands of wall cells, none across the other
    # map's rooms: asked to allow no crossing wall at all, it is merged the same.
    default = parse_json(runs.get("align-json").result)
    assert default["success"] and default["details"]["crossing"]["walls"] >= 3000
    proc = runs.get("align-crossing-strict").result
    assert proc.returncode == 0, describe(proc)
    strict = parse_json(proc)
    assert strict["success"] and strict["transform"] == default["transform"]
    assert strict["details"]["crossing"] == default["details"]["crossing"]


def test_min_overlap_walls_declines_a_pose_on_fewer_walls_whatever_its_confidence(runs):
    # The sample pair's pose, merged at confidence 1.0 on thousands of wall cells of each
    # map, is declined when asked for more walls than its overlap holds; the message
    # says how many it holds and how many were asked for.
    default = parse_json(runs.get("align-json").result)
    assert default["success"] and default["confidence"] == 1.0
    proc = runs.get("align-overlap-walls-strict").result
    assert proc.returncode == 1, describe(proc)
    strict = parse_json(proc)
    held = min(default["verification"]["walls_a"], default["verification"]["walls_b"])
    assert not strict["success"] and strict["candidate"] == default["candidate"]
    assert strict["message"] == f"declined: the overlap holds only {held} wall cells of one map (need 100000 of each to judge the walls)"


def test_no_threshold_merges_maps_of_two_places(runs):
    # The thresholds are not the only guard: maps of two different buildings are still
    # declined with every confidence accepted (their walls do not agree).
    proc = runs.get("align-negative-any-confidence").result
    assert proc.returncode == 1, describe(proc)
    d = parse_json(proc)
    assert not d["success"] and "walls agree" in d["message"]


def test_trust_resolution_and_any_scale_together_are_one_usage_error(runs):
    proc = runs.get("align-trust-any").result
    assert proc.returncode == 2, describe(proc)
    assert "not allowed with argument" in proc.stderr and "Traceback" not in proc.stderr


def test_a_resolution_that_contradicts_the_cells_is_declined_unless_any_scale(runs):
    proc = runs.get("align-liar").result
    assert proc.returncode == 1, describe(proc)
    assert "--any-scale" in proc.stdout + proc.stderr and "Traceback" not in proc.stderr
    free = runs.get("align-liar-any").result
    assert free.returncode == 0, describe(free)
    d = parse_json(free)
    # The cells' scale (0.95), not the resolutions' (1.9); so the metric scale is 0.5.
    assert d["success"] and d["transform"]["scale"] == pytest.approx(0.95, abs=0.01)
    assert d["metric"]["scale"] == pytest.approx(0.5, abs=0.01)


def test_align_text(runs):
    proc = runs.get("align-text").result
    assert proc.returncode == 0, describe(proc)
    assert proc.stderr == ""
    assert not proc.stdout.lstrip().startswith("{")
    found = re.search(r"rotation (-?[\d.]+) deg, scale ([\d.]+)", proc.stdout)
    assert found, proc.stdout
    assert float(found.group(1)) == pytest.approx(30.0, abs=0.1)
    assert float(found.group(2)) == pytest.approx(0.95, abs=0.002)
    assert re.search(r"metric .*scale 1\.00", proc.stdout), proc.stdout
    assert "inliers" in proc.stdout and "confidence" in proc.stdout
    # What the pose rests on: each map's wall cells in the overlap, and how many agree.
    walls = re.search(r"walls agree on (\d+)% of the overlap: (\d+) of A's (\d+) and (\d+) of B's (\d+) wall cells", proc.stdout)
    assert walls, proc.stdout
    share, ma, wa, mb, wb = (int(g) for g in walls.groups())
    assert 0 < ma <= wa and 0 < mb <= wb and share >= 90
    assert share == round(100 * (ma / wa + mb / wb) / 2)
    # --plot: a picture of the maps on each other at the pose.
    job = runs.get("align-text")
    assert "wrote p.png" in proc.stdout
    _assert_png(job.cwd / "p.png")


def _assert_png(path):
    data = path.read_bytes()
    assert data.startswith(PNG_SIGNATURE)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None and img.shape[0] > 100 and img.shape[1] > 100


def test_align_plot_of_a_declined_pair(runs):
    # Declined (exit 1), and the picture is written all the same: the candidate pose the
    # maps were judged at, and why it was declined.
    job = runs.get("align-negative-plot")
    proc = job.result
    assert proc.returncode == 1, describe(proc)
    assert proc.stdout.startswith("not aligned: ") and "wrote p.png" in proc.stdout
    _assert_png(job.cwd / "p.png")


def test_align_paper_method(runs, sample_maps):
    proc = runs.get("align-paper").result
    assert proc.returncode == 0, describe(proc)
    d = parse_json(proc)
    assert d["success"] is True and d["method"] == "paper"
    assert d["scale_x"] == pytest.approx(0.95, abs=0.005)
    assert d["scale_y"] == pytest.approx(0.95, abs=0.005)
    assert d["rotation_deg"] == pytest.approx(30.0, abs=0.3)
    err = corner_error(d["matrix"], sample_maps.truth, sample_maps.b.shape)
    assert err < 2.0, f"corner error {err:.3f} px"
    assert metric_error(d["metric"], sample_maps.a, sample_maps.b, sample_maps.truth) < 2.0 * sample_maps.a.resolution


def test_align_negative_pair_declines(runs):
    proc = runs.get("align-negative").result
    assert proc.returncode == 1, describe(proc)
    assert proc.stderr == ""
    d = parse_json(proc)
    assert d["success"] is False
    assert d["matrix"] is None and d["metric"] is None and d["translation_px"] is None
    assert d["message"]


def test_align_leaves_the_inputs_alone(runs, sample_maps):
    for key in ("align-json", "align-text", "align-paper", "align-negative"):
        runs.get(key)
    assert snapshot(sample_maps.folder) == runs.jobs["align-json"].before


# ----------------------------------------------------------------------- merge
def test_merge_json(runs, sample_maps):
    job = runs.get("merge")
    proc = job.result
    assert proc.returncode == 0, describe(proc)
    assert proc.stderr == ""
    d = parse_json(proc)
    assert d["success"] is True and d["fusion"] == "average"
    assert d["output"] == "out.yaml"
    assert d["unplaced"] == []
    assert [m["name"] for m in d["maps"]] == ["a.yaml", "b.yaml"]
    assert all(m["placed"] for m in d["maps"])
    assert d["maps"][1]["parent"] == 0
    assert d["maps"][1]["rotation_deg"] == pytest.approx(30.0, abs=0.1)
    # The merged map is in a's metric frame, so b's pose there is its pose in a.
    err = metric_error(d["maps"][1]["metric"], sample_maps.a, sample_maps.b, sample_maps.truth)
    assert err < 0.5 * sample_maps.a.resolution
    merged = load_map(job.cwd / "out.yaml")
    assert d["merged"]["width"] == merged.width and d["merged"]["height"] == merged.height
    assert d["merged"]["resolution"] == pytest.approx(merged.resolution)
    assert d["merged"]["origin"] == pytest.approx(list(merged.origin))


def test_merge_files(runs, sample_maps):
    job = runs.get("merge")
    assert job.result.returncode == 0, describe(job.result)
    # Exactly the outputs were added (no temporary file left), the inputs are unchanged.
    after = snapshot(job.cwd)
    assert set(after) == set(job.before) | {"out.yaml", "out.pgm", "p.png"}
    assert {k: after[k] for k in job.before} == job.before
    text = (job.cwd / "out.yaml").read_text()
    assert "image: out.pgm" in text and "mode: trinary" in text
    assert (job.cwd / "out.pgm").read_bytes().startswith(b"P5")
    merged = load_map(job.cwd / "out.yaml")
    a = sample_maps.a
    assert merged.resolution == a.resolution  # asked for with --resolution
    assert merged.origin[2] == pytest.approx(a.origin[2])
    # b reaches beyond a's image (its top-left corner lands at (-86, -36) in a).
    assert merged.height > a.height and merged.width > a.width
    pixels = set(np.unique(cv2.imread(str(job.cwd / "out.pgm"), cv2.IMREAD_UNCHANGED)).tolist())
    assert pixels <= {0, 205, 254}  # map_saver's trinary values


def test_merge_keeps_a_in_place(runs, sample_maps):
    job = runs.get("merge")
    assert job.result.returncode == 0, describe(job.result)
    check_a_kept(load_map(job.cwd / "out.yaml"), sample_maps.a)


def test_merge_plot_is_png(runs):
    job = runs.get("merge")
    assert job.result.returncode == 0, describe(job.result)
    data = (job.cwd / "p.png").read_bytes()
    assert data.startswith(PNG_SIGNATURE)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None and img.shape[0] > 100 and img.shape[1] > 100


@pytest.mark.parametrize("fusion", OTHER_FUSIONS)
def test_merge_fusion_rules(fusion, runs, sample_maps):
    job = runs.get(f"fusion-{fusion}")
    assert job.result.returncode == 0, describe(job.result)
    d = parse_json(job.result)
    assert d["success"] is True and d["fusion"] == fusion
    check_a_kept(load_map(job.cwd / "out.yaml"), sample_maps.a)


def test_merge_save_mode_raw(runs, sample_maps):
    job = runs.get("merge-raw")
    proc = job.result
    assert proc.returncode == 0, describe(proc)
    assert proc.stderr == ""
    assert "wrote out.yaml" in proc.stdout
    assert "mode: raw" in (job.cwd / "out.yaml").read_text()
    values = set(np.unique(cv2.imread(str(job.cwd / "out.pgm"), cv2.IMREAD_UNCHANGED)).tolist())
    assert values <= set(range(101)) | {255}
    assert 255 in values and values & set(range(1, 100))  # unknown and blended cells
    merged = load_map(job.cwd / "out.yaml")
    assert ((merged.data > 0) & (merged.data < 1)).any()
    check_a_kept(merged, sample_maps.a)


def test_merge_force_overwrites(runs, sample_maps):
    """With --force an existing output is replaced (without it: see test_bad_input)."""
    job = runs.get("merge-force")
    assert job.result.returncode == 0, describe(job.result)
    after = snapshot(job.cwd)
    assert set(after) == set(job.before)  # replaced in place, no temporary file left
    assert after["out.yaml"] != job.before["out.yaml"] and after["out.pgm"] != job.before["out.pgm"]
    assert {k: after[k] for k in ("a.yaml", "a.pgm", "b.yaml", "b.pgm")} == {
        k: job.before[k] for k in ("a.yaml", "a.pgm", "b.yaml", "b.pgm")
    }
    # Without --resolution: the finest of the inputs (b's 0.095 m/cell against a's 0.1).
    assert load_map(job.cwd / "out.yaml").resolution == min(sample_maps.a.resolution, sample_maps.b.resolution)


def test_merge_negative_pair_writes_nothing(runs):
    job = runs.get("merge-negative")
    proc = job.result
    assert proc.returncode == 1, describe(proc)
    assert proc.stderr == ""
    assert proc.stdout.startswith("not merged")
    assert snapshot(job.cwd) == job.before  # no output, no plot, no temporary file


def test_merge_all_unknown_map_declines(runs):
    """A map without a single known cell is valid input with nothing to align: declined
    (exit 1), not bad input, and nothing is written."""
    job = runs.get("merge-unknown")
    assert job.result.returncode == 1, describe(job.result)
    assert "Traceback" not in job.result.stderr
    d = parse_json(job.result)
    assert d["success"] is False and d["output"] is None
    assert snapshot(job.cwd) == job.before


# ------------------------------------------------------------------ bad input
@pytest.mark.parametrize("key, expected", [(c[0], c[3]) for c in BAD_INPUT], ids=[c[0] for c in BAD_INPUT])
def test_bad_input(key, expected, runs):
    job = runs.get(f"bad-{key}")
    assert_one_line_error(job.result, 2, expected)
    # Inputs byte-identical, no output, no temporary file.
    assert snapshot(job.cwd) == job.before


def test_debug_shows_traceback(runs):
    job = runs.get("debug")
    proc = job.result
    assert proc.returncode == 2, describe(proc)
    assert "Traceback (most recent call last)" in proc.stderr
    assert proc.stderr.splitlines()[-1].startswith("gridmerge: error: ")
    assert "missing.yaml" in proc.stderr.splitlines()[-1]
    assert snapshot(job.cwd) == job.before


# ---------------------------------------------------------------------- sample
def test_sample_writes_table1_pair(runs, sample_maps):
    job = runs.get("sample")
    assert job.result.returncode == 0, describe(job.result)
    assert job.result.stderr == ""
    assert set(snapshot(job.cwd)) == {"a.yaml", "a.pgm", "b.yaml", "b.pgm", "truth.json"}
    truth = np.asarray(json.loads((job.cwd / "truth.json").read_text())["b_to_a"])
    assert truth == pytest.approx(sample_maps.truth)
    a, b = load_map(job.cwd / "a.yaml"), load_map(job.cwd / "b.yaml")
    assert a.shape == sample_maps.a.shape and b.shape == sample_maps.b.shape


@pytest.mark.shared
def test_align_text_says_when_the_keypoint_matches_confirmed_the_pose(shared_data, tmp_path):
    """Two bending E5 maps whose walls agree on only 38 %: merged on the keypoint matches'
    evidence, and the summary says so (with 6 inliers, a confidence of 1.0 would puzzle)."""
    e5 = shared_data / "halmstad" / "E5"
    proc = subprocess.run(_command(["align", e5 / "E5_08.png", e5 / "E5_12.png"]), cwd=tmp_path, capture_output=True,
                          text=True, timeout=TIMEOUT_S, stdin=subprocess.DEVNULL, env=_env())
    assert proc.returncode == 0, describe(proc)
    assert re.search(r"^confirmed by the keypoint matches: \d+ places agree, where chance gives [\d.]+$", proc.stdout, re.M), proc.stdout


def test_align_prints_the_warnings_of_a_taken_pose_to_stderr(monkeypatch, capsys, sample_maps):
    # A pose taken on few walls is printed as aligned, its warning on stderr after it (in
    # process: the sample pair rests on many walls, so the threshold is raised here).
    from gridmerge.cli import main as cli_main

    real = cli_main.align
    monkeypatch.setattr(cli_main, "align", lambda *args, **kw: real(*args, few_walls=10**9, **kw))
    assert cli_main.main(["align", str(sample_maps.folder / "a.yaml"), str(sample_maps.folder / "b.yaml")]) == 0
    out, err = capsys.readouterr()
    assert out.startswith("aligned: ")
    assert re.fullmatch(r"gridmerge: warning: the pose rests on few walls: \d+ \+ \d+ wall cells .*\n", err), err

"""No data loss when a run is killed or interrupted.

Outputs are written to hidden temporary files next to their targets and renamed into
place only when complete (:mod:`gridmerge.io.atomic`). These tests kill real processes
in the middle of writing (a helper makes the write of one file stop half way, so the
kill lands there for sure) and check that every target is either absent, or byte for byte
the old file, or the complete new one; never torn. The only leftovers allowed are hidden
temporary files named ``.NAME.tmp-PID-N`` (and ``.NAME.bak-PID-N``), which no later run
renames over anything (docs/limits.md explains why they are not deleted automatically).
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from gridmerge import OccupancyGrid, load_map, save_map

pytestmark = pytest.mark.skipif(os.name != "posix", reason="POSIX signals")

#: A helper process: makes the N-th file written through gridmerge.io.atomic stop half
#: way (after flushing the first half to its temporary file), or makes the first
#: alignment of a merge stop, and says so by creating the READY file. Then it sleeps, to
#: be killed or interrupted by the test.
HELPER = r'''
import os, sys, time, types

ready, hook, mode, *rest = sys.argv[1:]

def stop_here():
    open(ready, "w").close()
    time.sleep(60)

if hook.startswith("write:"):
    import gridmerge.io.atomic as atomic
    slow_index = int(hook.split(":")[1])
    real_fdopen = os.fdopen
    calls = []

    class HalfWayFile:
        def __init__(self, fh):
            self._fh = fh
        def write(self, data):
            view = memoryview(data)
            self._fh.write(view[: len(view) // 2])
            self._fh.flush()
            stop_here()
            return self._fh.write(view[len(view) // 2 :])
        def __getattr__(self, name):
            return getattr(self._fh, name)
        def __enter__(self):
            return self
        def __exit__(self, *exc):
            return self._fh.__exit__(*exc)

    def fdopen(fd, *args, **kwargs):
        fh = real_fdopen(fd, *args, **kwargs)
        calls.append(fd)
        return HalfWayFile(fh) if len(calls) == slow_index else fh

    proxy = types.ModuleType("os")
    proxy.__dict__.update(os.__dict__)
    proxy.fdopen = fdopen
    atomic.os = proxy  # only gridmerge.io.atomic sees the slow file
elif hook == "align":
    import importlib
    merge_module = importlib.import_module("gridmerge.merge")
    real_align = merge_module.align
    def align(*args, **kwargs):
        stop_here()
        return real_align(*args, **kwargs)
    merge_module.align = align

if mode == "save":
    import numpy as np
    from gridmerge import OccupancyGrid, save_map
    seed, target = int(rest[0]), rest[1]
    save_map(OccupancyGrid(np.random.default_rng(seed).random((1200, 1500))), target, mode="raw")
else:
    from gridmerge.cli.main import main
    sys.exit(main(rest))
'''

LEFTOVER = re.compile(r"^\.(?P<target>.+)\.(tmp|bak)-\d+-\d+$")


def _default_sigint() -> None:
    """In the child: SIGINT as a user's Ctrl-C finds it. A test run started as a background
    job (CI) hands its children SIGINT ignored, and Python then never raises
    KeyboardInterrupt."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start_helper(folder: Path, hook: str, mode: str, *args, h) -> tuple[subprocess.Popen, Path]:
    script = folder.parent / f"helper-{folder.name}.py"
    script.write_text(HELPER)
    ready = folder.parent / f"ready-{folder.name}"
    proc = subprocess.Popen(
        [sys.executable, str(script), str(ready), hook, mode, *map(str, args)],
        cwd=folder,
        env=h.env(),
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_default_sigint,
    )
    return proc, ready


def _wait_for(ready: Path, proc: subprocess.Popen, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not ready.exists():
        if proc.poll() is not None:
            out, err = proc.communicate()
            pytest.fail(f"helper ended (exit {proc.returncode}) before the hook was reached\n{out}\n{err}")
        if time.monotonic() > deadline:
            proc.kill()
            pytest.fail("helper never reached the hook")
        time.sleep(0.01)


def _finish(proc: subprocess.Popen, sig: int) -> subprocess.CompletedProcess:
    proc.send_signal(sig)
    try:
        out, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def _leftovers(folder: Path, keep: set[str]) -> list[str]:
    """Names in ``folder`` other than ``keep``; each must be a hidden temporary file."""
    extra = sorted(p.name for p in folder.iterdir() if p.name not in keep)
    for name in extra:
        assert LEFTOVER.match(name), f"unexpected file {name!r} in {sorted(os.listdir(folder))}"
    return extra


def _percent_grid(seed: int, height: int, width: int, resolution: float) -> OccupancyGrid:
    """A grid of whole percentages (what a raw map_server image holds exactly)."""
    values = np.random.default_rng(seed).integers(-1, 101, width * height)
    return OccupancyGrid.from_ros(values, width, height, resolution)


# ------------------------------------------------------------ SIGKILL mid-write
@pytest.mark.parametrize("existing", [False, True], ids=["new-output", "replacing-output"])
@pytest.mark.parametrize("slow", [1, 2], ids=["during-image", "during-yaml"])
def test_sigkill_while_writing_leaves_old_file_or_nothing(tmp_path, existing, slow, h):
    """save_map writes the image, then the YAML, each to a temporary file; the process is
    SIGKILLed half way through one of them."""
    folder = tmp_path / "out"
    folder.mkdir()
    old = {}
    if existing:
        old_grid = _percent_grid(7, 40, 30, 0.1)
        save_map(old_grid, folder / "map.yaml", mode="raw")
        old = {p.name: p.read_bytes() for p in folder.iterdir()}
    proc, ready = _start_helper(folder, f"write:{slow}", "save", 1, "map.yaml", h=h)
    _wait_for(ready, proc)
    result = _finish(proc, signal.SIGKILL)
    assert result.returncode == -signal.SIGKILL

    if existing:
        assert {n: (folder / n).read_bytes() for n in old} == old  # byte-identical
        assert load_map(folder / "map.yaml") == old_grid
    else:
        assert not (folder / "map.yaml").exists() and not (folder / "map.pgm").exists()
    extra = _leftovers(folder, set(old))
    # The temporary files of the image (complete when the YAML was being written) and of
    # the file being written, half of it.
    assert len(extra) == slow
    torn = [n for n in extra if LEFTOVER.match(n).group("target") == ("map.pgm" if slow == 1 else "map.yaml")]
    assert len(torn) == 1

    # A later run is not disturbed by the leftovers, and never renames them into place.
    new_grid = _percent_grid(8, 20, 10, 0.2)
    save_map(new_grid, folder / "map.yaml", mode="raw")
    assert load_map(folder / "map.yaml") == new_grid
    assert _leftovers(folder, {"map.yaml", "map.pgm"}) == extra


def test_sigkill_of_real_merges_at_many_moments(tmp_path, pair_folder, h):
    """``gridmerge merge --force`` over an existing output, SIGKILLed at moments spread over
    a whole run: each output file is the old one or the complete new one."""
    import shutil

    def fresh(name: str) -> Path:
        folder = tmp_path / name
        folder.mkdir()
        for f in ("a.yaml", "a.pgm", "b.yaml", "b.pgm"):
            shutil.copy2(pair_folder / f, folder / f)
        save_map(OccupancyGrid(np.full((30, 40), 0.0)), folder / "out.yaml")
        return folder

    args = ["merge", "a.yaml", "b.yaml", "-o", "out.yaml", "--force"]
    ref = fresh("reference")
    old = {n: (ref / n).read_bytes() for n in ("out.yaml", "out.pgm")}
    start = time.monotonic()
    proc = h.run_cli(*args, cwd=ref)
    duration = time.monotonic() - start
    assert proc.returncode == 0, h.describe(proc)
    new = {n: (ref / n).read_bytes() for n in ("out.yaml", "out.pgm")}

    delays = np.linspace(0.3, 1.2 * duration, 6)
    runs = []
    for k, delay in enumerate(delays):
        folder = fresh(f"kill-{k}")
        runs.append((folder, subprocess.Popen(h.command(*args), cwd=folder, env=h.env(), stdin=subprocess.DEVNULL,
                                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL), delay))
    t0 = time.monotonic()
    for folder, p, delay in runs:
        time.sleep(max(0.0, t0 + delay - time.monotonic()))
        p.kill()
    for folder, p, delay in runs:
        p.wait(timeout=60)
        for name in ("out.yaml", "out.pgm"):
            data = (folder / name).read_bytes()
            assert data in (old[name], new[name]), f"{name} torn after a kill at {delay:.2f} s"
        _leftovers(folder, {"a.yaml", "a.pgm", "b.yaml", "b.pgm", "out.yaml", "out.pgm"})


# -------------------------------------------------------- Ctrl-C and SIGTERM
@pytest.mark.parametrize(
    "hook, sig, code, line",
    [
        ("align", signal.SIGINT, 130, "gridmerge: interrupted"),
        ("write:1", signal.SIGINT, 130, "gridmerge: interrupted"),
        ("write:2", signal.SIGINT, 130, "gridmerge: interrupted"),
        ("write:1", signal.SIGTERM, 143, "gridmerge: terminated"),
    ],
    ids=["sigint-mid-merge", "sigint-mid-image", "sigint-mid-yaml", "sigterm-mid-image"],
)
def test_interrupted_cli_exits_with_one_line_and_writes_nothing(tmp_path, pair_folder, hook, sig, code, line, h):
    import shutil

    folder = tmp_path / "work"
    folder.mkdir()
    for f in ("a.yaml", "a.pgm", "b.yaml", "b.pgm"):
        shutil.copy2(pair_folder / f, folder / f)
    before = h.snapshot(folder)
    proc, ready = _start_helper(folder, hook, "cli", "merge", "a.yaml", "b.yaml", "-o", "out.yaml", h=h)
    _wait_for(ready, proc)
    result = _finish(proc, sig)
    assert result.returncode == code, h.describe(result)
    assert result.stdout == ""
    assert result.stderr == line + "\n", h.describe(result)
    assert h.snapshot(folder) == before  # no output, no temporary file


def _catches_sigterm(pid: int) -> bool:
    """Whether the process has installed a SIGTERM handler (gridmerge's main() does)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    mask = next((int(l.split()[1], 16) for l in status.splitlines() if l.startswith("SigCgt:")), 0)
    return bool(mask & (1 << (signal.SIGTERM - 1)))


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs /proc")
def test_ctrl_c_of_the_real_command(tmp_path, pair_folder, h):
    """``python -m gridmerge merge``, interrupted as soon as its main() runs."""
    import shutil

    for f in ("a.yaml", "a.pgm", "b.yaml", "b.pgm"):
        shutil.copy2(pair_folder / f, tmp_path / f)
    before = h.snapshot(tmp_path)
    proc = subprocess.Popen(
        h.command("merge", "a.yaml", "b.yaml", "-o", "out.yaml"), cwd=tmp_path, env=h.env(),
        stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=_default_sigint,
    )
    deadline = time.monotonic() + 30
    while not _catches_sigterm(proc.pid):
        assert proc.poll() is None and time.monotonic() < deadline, "main() never started"
        time.sleep(0.005)
    result = _finish(proc, signal.SIGINT)
    if result.returncode == 0:  # the machine was fast enough to finish first: nothing to test
        pytest.skip("the merge finished before the signal")
    assert result.returncode == 130, h.describe(result)
    assert result.stderr == "gridmerge: interrupted\n" and result.stdout == ""
    assert h.snapshot(tmp_path) == before

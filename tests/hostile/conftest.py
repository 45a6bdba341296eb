"""Shared helpers of the hostile-input tests.

Hypothesis runs derandomized (the same examples on every run and every machine) with no
deadline: CI must not flake, and a single example may legitimately take a while on a
loaded machine. To search harder locally: ``HYPOTHESIS_PROFILE=explore`` (random, not
derandomized) and ``GRIDMERGE_HYPOTHESIS_SCALE=20`` (twenty times the examples).
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import tempfile

import pytest
from hypothesis import HealthCheck, settings
from hypothesis.configuration import set_hypothesis_home_dir

# Hypothesis keeps caches in .hypothesis/ of the working directory: not in the project.
set_hypothesis_home_dir(os.path.join(tempfile.gettempdir(), "gridmerge-hypothesis"))

settings.register_profile(
    "ci",
    derandomize=True,
    database=None,  # nothing written into the working tree
    deadline=None,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture, HealthCheck.data_too_large],
)
settings.register_profile(
    "explore",
    database=None,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture, HealthCheck.data_too_large],
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

#: A subprocess never runs longer than this (a hang fails one test, not the suite): a
#: guard against hangs, with room for a slow machine shared with the other test workers.
TIMEOUT_S = 300


def command(*args) -> list[str]:
    return [sys.executable, "-m", "gridmerge", *map(str, args)]


def env() -> dict:
    e = dict(os.environ)
    e.setdefault("MPLBACKEND", "Agg")
    return e


def run_cli(*args, cwd: Path, timeout: float = TIMEOUT_S) -> subprocess.CompletedProcess:
    """``python -m gridmerge ARGS`` in ``cwd``, text output captured."""
    return subprocess.run(
        command(*args), cwd=str(cwd), env=env(), capture_output=True, text=True, timeout=timeout, stdin=subprocess.DEVNULL
    )


def run_many(jobs, workers: int = 2) -> list[subprocess.CompletedProcess]:
    """Run ``[(args, cwd), ...]`` side by side; results in order."""
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(lambda job: run_cli(*job[0], cwd=job[1]), jobs))


def describe(proc: subprocess.CompletedProcess) -> str:
    return f"exit {proc.returncode}\n--- stdout ---\n{proc.stdout[-2000:]}\n--- stderr ---\n{proc.stderr[-2000:]}"


def assert_one_line_error(proc: subprocess.CompletedProcess, code: int = 2, *contains: str) -> str:
    """Exit ``code``, nothing on stdout, one line ``gridmerge: error: ...`` on stderr, no
    traceback, and every piece of ``contains`` in that line."""
    assert proc.returncode == code, describe(proc)
    assert "Traceback" not in proc.stderr, describe(proc)
    assert proc.stdout == "", describe(proc)
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and proc.stderr.endswith("\n"), describe(proc)
    assert lines[0].startswith("gridmerge: error: "), describe(proc)
    assert "unexpected" not in lines[0], describe(proc)  # every expected error has its own message
    for piece in contains:
        assert piece in lines[0], f"{piece!r} not in the error line\n{describe(proc)}"
    return lines[0]


def snapshot(folder: Path) -> dict:
    """``{relative path: sha256}`` of every file below ``folder``, hidden ones included."""
    out = {}
    for p in sorted(Path(folder).rglob("*")):
        if p.is_file() and not p.is_symlink():
            out[p.relative_to(folder).as_posix()] = hashlib.sha256(p.read_bytes()).hexdigest()
        else:
            out[p.relative_to(folder).as_posix()] = "<other>"
    return out


@pytest.fixture(scope="session")
def pair_folder(tmp_path_factory) -> Path:
    """a.yaml/a.pgm and b.yaml/b.pgm: the paper's Table I pair (aligns), saved once."""
    from gridmerge import save_map, samples

    folder = tmp_path_factory.mktemp("pair")
    a, b, _ = samples.table1_pair(0)
    save_map(a, folder / "a.yaml")
    save_map(b, folder / "b.yaml")
    return folder


@pytest.fixture(scope="session")
def h():
    """The helpers above, for the test modules (``--import-mode=importlib`` keeps
    conftest modules out of ``sys.path``)."""
    import types

    return types.SimpleNamespace(
        command=command,
        env=env,
        run_cli=run_cli,
        run_many=run_many,
        describe=describe,
        assert_one_line_error=assert_one_line_error,
        snapshot=snapshot,
        TIMEOUT_S=TIMEOUT_S,
    )

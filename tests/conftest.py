import os
from pathlib import Path

import pytest


@pytest.hookimpl(tryfirst=True)
def pytest_configure(config):
    # Run on pytest-xdist's workers (``-n auto``, the README's test command), pytest-benchmark
    # turns itself off and warns; the tests hold no benchmarks (``benchmarks/`` does, and
    # runs in one process): off without the warning.
    xdist = config.getoption("dist", "no") != "no" or os.environ.get("PYTEST_XDIST_WORKER")
    if xdist and hasattr(config.option, "benchmark_disable"):
        config.option.benchmark_disable = True


@pytest.fixture
def shared_data() -> Path:
    """The shared data folder (``../shared/data`` next to the project); skips when absent."""
    root = Path(__file__).resolve().parents[1].parent / "shared" / "data"
    if not root.is_dir():
        pytest.skip(f"shared data not found at {root}")
    return root

import os
import tempfile
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
    # The tests start a few hundred ``python -m gridmerge`` processes. Where bytecode is
    # not written (PYTHONDONTWRITEBYTECODE, as on the machines we test on), each compiled the
    # package again: about 0.2 s of CPU and half a second of wall time per process. They
    # keep their bytecode in a folder of the temporary directory instead, never in the
    # working tree. (This process is not affected: Python reads both settings at start.)
    if os.environ.get("PYTHONDONTWRITEBYTECODE") and not os.environ.get("PYTHONPYCACHEPREFIX"):
        os.environ.pop("PYTHONDONTWRITEBYTECODE")
        user = getattr(os, "getuid", lambda: 0)()
        os.environ["PYTHONPYCACHEPREFIX"] = os.path.join(tempfile.gettempdir(), f"gridmerge-test-pycache-{user}")


@pytest.fixture
def shared_data() -> Path:
    """The shared data folder (``../shared/data`` next to the project); skips when absent."""
    root = Path(__file__).resolve().parents[1].parent / "shared" / "data"
    if not root.is_dir():
        pytest.skip(f"shared data not found at {root}")
    return root


@pytest.fixture(scope="module")
def benchmark_script():
    """``benchmark_script(name)``: the module ``benchmarks/<name>.py`` (the scripts there are
    not a package), loaded from its file."""
    import importlib.util

    def load(name: str):
        path = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load

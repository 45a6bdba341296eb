from pathlib import Path

import pytest


@pytest.fixture
def shared_data() -> Path:
    """The shared data folder (``../shared/data`` next to the project); skips when absent."""
    root = Path(__file__).resolve().parents[1].parent / "shared" / "data"
    if not root.is_dir():
        pytest.skip(f"shared data not found at {root}")
    return root

"""Values ready for strict JSON (``allow_nan=False``): JSON has no NaN or infinity."""

from __future__ import annotations

import math

import numpy as np


def finite(obj):
    """``obj`` with every NaN or infinite float (numpy's too) replaced by ``None``,
    inside dicts, lists and tuples (tuples become lists); other values as they are.

    >>> finite({"index": float("nan"), "pose": (1.0, np.float64("inf")), "n": 3})
    {'index': None, 'pose': [1.0, None], 'n': 3}
    """
    if isinstance(obj, (float, np.floating)):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    return obj

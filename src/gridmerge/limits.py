"""Size limits that keep gridmerge's memory and time bounded, whatever the input.

Every limit has a default in :data:`DEFAULT_LIMITS`, used by the library when nothing
else is given, and can be changed per call (a :class:`Limits` passed to
:func:`gridmerge.load_map` or :func:`gridmerge.merge`, or the individual keyword
arguments) or on the command line (``--max-pixels``, ``--max-yaml-bytes``,
``--max-keypoints``, ``--max-feature-pixels``, ``--max-canvas-cells``,
``--max-canvas-factor``). ``docs/limits.md`` says what happens at each bound.

Examples
--------
>>> from gridmerge.limits import DEFAULT_LIMITS, Limits
>>> DEFAULT_LIMITS.max_pixels
100000000
>>> Limits(max_pixels=4_000_000).max_pixels
4000000
>>> Limits(max_keypoints=-1)
Traceback (most recent call last):
...
ValueError: max_keypoints must be a positive integer, got -1
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

__all__ = ["Limits", "DEFAULT_LIMITS", "extractor_for"]


@dataclass(frozen=True)
class Limits:
    """Bounds on inputs and intermediate results.

    Attributes
    ----------
    max_pixels : int
        Cells (``width * height``) of one input image or ``.npy`` array. Checked from the
        file's header before anything is decoded; larger inputs are refused
        (:class:`~gridmerge.errors.MapFormatError`, exit 2).
    max_yaml_bytes : int
        Size of a map_server YAML file (a real one is a few hundred bytes). Larger files
        are refused unparsed.
    max_keypoints : int
        Keypoints kept per map, the strongest first (bounds matching time and memory).
        The alignment reports ``details["features_capped"]`` when it dropped some.
    max_feature_pixels : int
        Pixels of the image a map's keypoints are detected in (the bounding box of its
        known cells). SIFT needs about 220 bytes per pixel; a larger map is detected at a
        reduced resolution that fits (and reported as ``features_capped``).
    max_canvas_cells : int
        Cells of a merged map; a merge that would need more is declined (exit 1).
        Fusing two maps takes about 40 bytes per merged cell; the default equals
        ``max_pixels``, so that every merged map can be read back.
    max_canvas_factor : float
        A merged map may also hold at most this many times the cells of all its inputs
        together (an absurd transform cannot blow up a small merge).
    """

    max_pixels: int = 100_000_000
    max_yaml_bytes: int = 64 * 1024
    max_keypoints: int = 20_000
    max_feature_pixels: int = 9_000_000
    max_canvas_cells: int = 100_000_000
    max_canvas_factor: float = 16.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "max_canvas_factor":
                ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0
                if not ok:
                    raise ValueError(f"{f.name} must be a finite number > 0, got {value!r}")
                object.__setattr__(self, f.name, float(value))
            else:
                if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
                    raise ValueError(f"{f.name} must be a positive integer, got {value!r}")

    def replace(self, **changes) -> "Limits":
        """A copy with some limits changed; ``None`` values keep the current limit."""
        current = {f.name: getattr(self, f.name) for f in fields(self)}
        unknown = set(changes) - set(current)
        if unknown:
            raise TypeError(f"unknown limit(s): {', '.join(sorted(unknown))}")
        current.update({k: v for k, v in changes.items() if v is not None})
        return Limits(**current)


#: The limits the library uses when none are given.
DEFAULT_LIMITS = Limits()


def extractor_for(method: str, limits: Limits, options=None):
    """The feature extractor of alignment ``method`` with ``limits`` applied.

    ``max_keypoints`` and ``max_feature_pixels`` replace the extractor's own caps; methods
    that use no keypoints give ``None``.
    """
    from dataclasses import replace

    from .align import METHODS, AlignOptions

    if method not in METHODS:
        from .errors import GridMergeError

        raise GridMergeError(f"unknown alignment method {method!r} (use one of {', '.join(METHODS)})")
    spec = METHODS[method]
    if spec.extractor is None:
        return None
    opts = replace(options or AlignOptions(), max_keypoints=limits.max_keypoints)
    extractor = spec.extractor(opts)
    if hasattr(extractor, "max_image_pixels"):
        extractor.max_image_pixels = limits.max_feature_pixels
    if hasattr(extractor, "max_keypoints"):
        extractor.max_keypoints = limits.max_keypoints
    return extractor

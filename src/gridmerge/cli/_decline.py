"""The decline thresholds on the command line: ``--min-confidence``,
``--one-sided-confidence``, ``--max-slide``, ``--max-crossing``, ``--unsure-walls``,
``--min-overlap-walls`` and ``--few-walls-agreement``, shared by ``align``, ``merge`` and ``bench``.

They set :class:`gridmerge.align.AlignOptions` fields of gridmerge's own methods (those
whose success the verification decides, :attr:`gridmerge.align.Method.verified`). The
baselines decline by their authors' rules, so asking for a threshold with one of them is
a usage error rather than a silent no-op. docs/benchmarks.md ("The decline threshold")
shows what lower thresholds merge, and what they merge wrongly.
"""

from __future__ import annotations

import argparse
import math

__all__ = ["FLAGS", "confidence", "cells", "help_text", "metavar", "overrides", "type_of"]

#: flag -> AlignOptions field.
FLAGS = {
    "--min-confidence": "min_confidence",
    "--one-sided-confidence": "one_sided_confidence",
    "--max-slide": "max_slide",
    "--max-crossing": "max_crossing",
    "--unsure-walls": "unsure_walls",
    "--min-overlap-walls": "min_overlap_walls",
    "--few-walls-agreement": "few_walls_agreement",
}

_HELP = {
    "min_confidence": "decline an alignment whose confidence is below C, 0 to 1 (default {d}); lower merges more "
    "pairs and risks wrong merges: docs/benchmarks.md, 'The decline threshold'",
    "one_sided_confidence": "a pose below C is searched again from the other map's side, and declined below C if "
    "that search does not find it too, 0 to 1 (default {d}; maps of different places fit by chance from one side)",
    "max_slide": "decline a pose that the walls do not fix: slid along the walls the maps share, either way, it keeps "
    "more than C of its wall agreement, 0 to 1 (default {d}; one straight wall or corridor holds a pose along it "
    "but not where on it); 1 declines only poses that both slid poses beat",
    "max_crossing": "decline a pose resting on fewer than {walls} overlap wall cells when more than C of them stand "
    "inside the other map's open space, 0 to 1 (default {d}; maps of two places laid room on room); 1 turns it off",
    "unsure_walls": "decline a pose of confidence below {sure:g} resting on fewer than N overlap wall cells (default {d}; "
    "a few rooms of a repetitive building agree in part by chance, a whole building does not); 0 turns it off",
    "few_walls_agreement": "decline a pose resting on fewer than {few} overlap wall cells (both maps') whose walls "
    "agree on less than C of them, whatever its confidence, 0 to 1 (default {d}; a few walls of two places agree in "
    "part by chance, a right pose's lie on each other); 0 turns it off",
    "min_overlap_walls": "decline a pose whose overlap holds fewer than N wall cells of either map, whatever its "
    "confidence (default {d}); higher declines more poses resting on a few walls, right and wrong: "
    "docs/benchmarks.md, 'The decline threshold'",
}


def confidence(text: str) -> float:
    """argparse type: a number from 0 to 1."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(value) and 0.0 <= value <= 1.0):
        raise argparse.ArgumentTypeError(f"must be a number from 0 to 1, got {text!r}")
    return value


def cells(text: str) -> int:
    """argparse type: a count of cells, 0 or more."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {text!r}")
    return value


#: Fields whose flag takes a count of cells (``N``); the others take a number from 0 to 1 (``C``).
_COUNTS = frozenset({"unsure_walls", "min_overlap_walls"})


def type_of(field: str):
    """The argparse type of a field's flag."""
    return cells if field in _COUNTS else confidence


def metavar(field: str) -> str:
    """The placeholder of a field's flag in the help."""
    return "N" if field in _COUNTS else "C"


def help_text(field: str) -> str:
    """The flag's help, with AlignOptions' default and the rules' fixed values (the
    confidence above which ``--unsure-walls`` spares a pose, the walls that exempt a pose
    from ``--max-crossing``, those below which ``--few-walls-agreement`` judges one), read
    from :mod:`gridmerge.align`."""
    from ..align import (
        _CROSSING_EVIDENCE,
        FEW_WALLS_EVIDENCE,
        SURE_CONFIDENCE,
        AlignOptions,
    )

    return _HELP[field].format(d=getattr(AlignOptions(), field), sure=SURE_CONFIDENCE, walls=_CROSSING_EVIDENCE,
                               few=FEW_WALLS_EVIDENCE)


def overrides(values: dict) -> dict:
    """``{AlignOptions field: value}`` of the thresholds given (``values``: field -> value
    or None when the flag was absent)."""
    return {f: v for f, v in values.items() if v is not None}


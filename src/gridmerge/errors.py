"""Exceptions raised by gridmerge.

Every error that a user's input can cause derives from :class:`GridMergeError`, so
callers (and the CLI) can tell expected failures from bugs. A *declined* alignment is
not an error: it is a result whose ``success`` is ``False``.
"""

from __future__ import annotations

__all__ = ["GridMergeError", "MapFormatError", "LimitExceededError", "InputTooLargeError", "OutputError"]


class GridMergeError(Exception):
    """Base class of every expected gridmerge error.

    The message is one line, meant for a user: it names the file and the field at fault
    where there is one.
    """


class MapFormatError(GridMergeError, ValueError):
    """A map file or map metadata is missing, unreadable or malformed."""

    def __init__(self, message: str, path: object | None = None, field: str | None = None):
        self.path = None if path is None else str(path)
        self.field = field
        parts = []
        if self.path:
            parts.append(_shorten(self.path))
        if field:
            parts.append(field)
        prefix = ": ".join(parts)
        super().__init__(f"{prefix}: {message}" if prefix else message)


def _shorten(text: str, limit: int = 240) -> str:
    """``text``, with its middle elided if longer than ``limit`` (keeps messages one short line)."""
    return text if len(text) <= limit else f"{text[: limit - 80]}...{text[-77:]}"


class LimitExceededError(GridMergeError):
    """An input or an intermediate result would exceed a configured size limit.

    ``limit`` names the :class:`gridmerge.limits.Limits` field at fault (e.g.
    ``"max_pixels"``), so that callers can say how to raise it.
    """

    limit: str | None = None


class InputTooLargeError(MapFormatError, LimitExceededError):
    """An input file is larger than a limit allows (refused before it is decoded)."""

    def __init__(self, message: str, path: object | None = None, field: str | None = None, limit: str | None = None):
        super().__init__(message, path=path, field=field)
        self.limit = limit


class OutputError(GridMergeError, OSError):
    """An output cannot be written where it was asked for."""

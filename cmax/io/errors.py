"""The exception that every event-file reader raises on malformed input."""
from __future__ import annotations

__all__ = ["FormatError"]


class FormatError(ValueError):
    """A file is not in the expected format, or is truncated or corrupt.

    Readers raise this (never an ``IndexError``, ``struct.error`` or a bare
    decoder exception) for any bytes they cannot decode; the message names the
    file and what was expected. It subclasses :class:`ValueError`.
    """

"""The engine's one exception base.

Every module raises its own subclass of :class:`EngineError` (``OdometryError``,
``KDError``, ...), with the offending value and where it came from in the message, so a caller
catches one type for "the engine refused this input" and a command line prints it as one line.
Most also derive from ``ValueError`` (bad values) or ``RuntimeError`` (a worker that failed),
so code that catches those keeps working.
"""

from __future__ import annotations


class EngineError(Exception):
    """Base of every error the engine raises on purpose."""

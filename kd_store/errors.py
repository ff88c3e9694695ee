"""The one exception type of the knowledge database."""

from __future__ import annotations

from core.errors import EngineError


class KDError(EngineError, ValueError):
    """Input the KD refuses, or a KD file it cannot use.

    The message always names the offending value and the frame (entity, event, relation,
    class or file) it came from. When a KD method raises it, nothing of that call was kept.
    """


class ResultTooLarge(KDError):
    """An untrusted query's result over its row or byte limit (kd_store.query.QueryLimits);
    the message names the limit and the query. A KDError, so callers that catch that still
    do; the HTTP API answers it with 413 instead of the 400 of a bad statement."""

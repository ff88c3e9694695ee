"""Input limits of the HTTP API (wm.serve): how large a request body may be (413 beyond) and
how often one client may ask (a token bucket per remote address, 429 beyond).

Both are plain ASGI middleware around the FastAPI application, so they act before a request
is routed, authorised or its body read: a body declared too large (``Content-Length``) is
refused unread, one sent without a length (chunked) is read only up to the limit. Sizes are
bytes; rates are requests per second of wall time.
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

from core.errors import EngineError


class LimitsError(EngineError, ValueError):
    """A request limit out of its range; names the limit and value."""


MB = 2**20

#: the ingest endpoints (ROS messages: a camera image or a point cloud is megabytes)
INGEST_PREFIX = "/v1/ingest"


@dataclass(frozen=True)
class ServeLimits:
    """Limits of the API. ``max_ingest_bytes``: a body under ``/v1/ingest`` (one ROS message, or
    a batch of them); ``max_json_bytes``: a body anywhere else (a What If request of 100 plans
    of 1000 waypoints is about 4 MB of JSON, hence not 64 kB); ``rate_per_s`` and ``burst``: each
    remote address may make ``burst`` requests at once and ``rate_per_s`` a second after that
    (None: no rate limit, the default); ``max_clients``: addresses whose buckets are kept (the
    least recently seen beyond that are forgotten, so memory stays bounded)."""

    max_ingest_bytes: int = 64 * MB
    max_json_bytes: int = 4 * MB
    rate_per_s: float | None = None
    burst: int = 100
    max_clients: int = 10_000

    def __post_init__(self) -> None:
        for name in ("max_ingest_bytes", "max_json_bytes", "burst", "max_clients"):
            if getattr(self, name) < 1:
                raise LimitsError(f"{name} {getattr(self, name)}: need at least 1")
        if self.rate_per_s is not None and not (
            math.isfinite(self.rate_per_s) and self.rate_per_s > 0
        ):
            raise LimitsError(f"rate_per_s {self.rate_per_s}: need a finite number > 0 (or None)")

    def max_body(self, path: str) -> int:
        """The largest body (bytes) a request to ``path`` may carry."""
        return self.max_ingest_bytes if path.startswith(INGEST_PREFIX) else self.max_json_bytes


class TokenBuckets:
    """One token bucket per key (a client's address): ``burst`` tokens at most, refilled at
    ``rate_per_s``; a request takes one. Thread-safe; at most ``max_clients`` buckets kept."""

    def __init__(self, rate_per_s: float, burst: int, max_clients: int = 10_000) -> None:
        self.rate, self.burst, self.max_clients = rate_per_s, float(burst), max_clients
        self._buckets: OrderedDict[str, tuple[float, float]] = OrderedDict()  # tokens, time s
        self._lock = threading.Lock()

    def take(self, key: str, now_s: float | None = None) -> float:
        """Take a token for ``key``: 0.0 when there was one, else the seconds until there is."""
        now = time.monotonic() if now_s is None else now_s
        with self._lock:
            tokens, then = self._buckets.pop(key, (self.burst, now))
            tokens = min(self.burst, tokens + (now - then) * self.rate)
            wait = 0.0 if tokens >= 1.0 else (1.0 - tokens) / self.rate
            self._buckets[key] = (tokens - 1.0 if wait == 0.0 else tokens, now)
            while len(self._buckets) > self.max_clients:  # forget the least recently seen
                self._buckets.popitem(last=False)
        return wait


async def _answer(send: Any, status: int, detail: str, headers: dict[str, str] | None = None):
    """A JSON error answer ``{"detail": ...}`` as the API's own errors are."""
    body = json.dumps({"detail": detail}).encode()
    head = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    head += [(k.encode(), v.encode()) for k, v in (headers or {}).items()]
    await send({"type": "http.response.start", "status": status, "headers": head})
    await send({"type": "http.response.body", "body": body})


class LimitsMiddleware:
    """ASGI middleware enforcing :class:`ServeLimits` (module docstring)."""

    def __init__(self, app: Any, limits: ServeLimits) -> None:
        self.app, self.limits = app, limits
        self.buckets = (
            TokenBuckets(limits.rate_per_s, limits.burst, limits.max_clients)
            if limits.rate_per_s is not None
            else None
        )

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        if self.buckets is not None:
            client = (scope.get("client") or ("unknown", 0))[0]
            wait = self.buckets.take(client)
            if wait > 0:
                await _answer(
                    send, 429,
                    f"client {client}: more than {self.limits.burst} requests at once or "
                    f"{self.limits.rate_per_s:g} a second; retry in {wait:.2f} s",
                    {"retry-after": str(max(1, math.ceil(wait)))},
                )  # fmt: skip
                return
        limit = self.limits.max_body(scope["path"])
        declared = _content_length(scope)
        if declared is not None and declared > limit:
            await _answer(send, 413, _too_large(scope["path"], declared, limit))
            return
        if declared is None and scope["method"] in ("POST", "PUT", "PATCH"):
            receive = await _bounded_body(scope, receive, send, limit)
            if receive is None:
                return
        await self.app(scope, receive, send)


def _content_length(scope: dict) -> int | None:
    for k, v in scope["headers"]:
        if k == b"content-length":
            try:
                return int(v)
            except ValueError:
                return None  # uvicorn refuses a malformed length itself
    return None


def _too_large(path: str, size: int | str, limit: int) -> str:
    return f"request body of {size} bytes to {path} is above the limit of {limit} bytes"


async def _bounded_body(scope: dict, receive: Any, send: Any, limit: int) -> Any | None:
    """A body sent without a length (chunked), read up to ``limit`` bytes: a ``receive`` that
    replays it to the application, or None after answering 413 (more than ``limit``)."""
    chunks, size = [], 0
    while True:
        message = await receive()
        if message["type"] != "http.request":  # the client went away
            return None
        chunks.append(message.get("body", b""))
        size += len(chunks[-1])
        if size > limit:
            await _answer(send, 413, _too_large(scope["path"], f"more than {size}", limit))
            return None
        if not message.get("more_body", False):
            break
    body, sent = b"".join(chunks), False

    async def replay() -> dict:
        nonlocal sent
        if sent:  # after the body only a disconnect can come
            return await receive()
        sent = True
        return {"type": "http.request", "body": body, "more_body": False}

    return replay

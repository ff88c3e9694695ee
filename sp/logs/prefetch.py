"""A log's frames decoded ahead in a child process.

Decoding ROS messages (CDR deserialisation in Python, chunk decompression, CRCs) costs a few
milliseconds of the reading process's CPU per LADAR sweep. :class:`FramePrefetcher` runs
``source.frames()`` in a forked child and hands the frames over in batches through a bounded
queue (pickled numpy arrays cost a copy, far less than decoding), so the process that
consumes them only unpickles. The frames and their order are exactly those of
``source.frames()``; the child's read statistics replace ``source.stats`` at the end.
"""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
import queue
import time
from collections.abc import Iterator
from typing import Any

from sp.logs.source import LogSource
from sp.logs.types import Frame

#: seconds between checks that the child is still alive while waiting for a batch
_POLL_S = 1.0


class PrefetchError(RuntimeError):
    """The decoding process stopped without finishing the log (names the log and the cause)."""


def _serve(source: LogSource, out: Any, batch_frames: int, kwargs: dict[str, Any]) -> None:
    """The child: decode, send batches, then ("end", stats, cpu_s) or ("error", exception)."""
    batch: list[Frame] = []
    try:
        for frame in source.frames(**kwargs):
            batch.append(frame)
            if len(batch) >= batch_frames:
                out.put(("frames", batch))
                batch = []
        if batch:
            out.put(("frames", batch))
        out.put(("end", source.stats, time.process_time()))
    except Exception as e:  # sent back: the consumer raises it where it reads
        out.put(("error", e))
    out.close()
    out.join_thread()


class FramePrefetcher:
    """Iterate ``source.frames(**kwargs)`` decoded by a child process, ``max_batches`` batches
    of ``batch_frames`` frames ahead. Start it before opening anything that runs threads
    (it forks). Use as a context manager, or :meth:`close` it: leaving early stops the child.

    ``decode_cpu_s`` is the child's CPU time once the log has been read to its end.
    """

    def __init__(
        self,
        source: LogSource,
        batch_frames: int = 16,
        max_batches: int = 4,
        **kwargs: Any,
    ) -> None:
        if batch_frames < 1 or max_batches < 1:
            raise PrefetchError(
                f"{source.path}: batch_frames {batch_frames} and max_batches {max_batches} "
                "must be >= 1"
            )
        self.source = source
        self.decode_cpu_s = 0.0
        # fork: the child reads with the source as it is (no re-import, no re-opening)
        ctx = mp.get_context("fork")
        self._queue = ctx.Queue(maxsize=max_batches)
        self._proc = ctx.Process(
            target=_serve,
            args=(source, self._queue, batch_frames, kwargs),
            daemon=True,
            name="log-decode",
        )
        self._proc.start()
        self._done = False

    def __iter__(self) -> Iterator[Frame]:
        while not self._done:
            kind, *payload = self._next_message()
            if kind == "frames":
                yield from payload[0]
            elif kind == "end":
                self._done = True
                for f in dataclasses.fields(payload[0]):
                    setattr(self.source.stats, f.name, getattr(payload[0], f.name))
                self.decode_cpu_s = float(payload[1])
            else:
                self._done = True
                raise payload[0]

    def _next_message(self) -> tuple[Any, ...]:
        while True:
            try:
                return self._queue.get(timeout=_POLL_S)
            except queue.Empty:
                if not self._proc.is_alive():
                    self._done = True
                    raise PrefetchError(
                        f"{self.source.path}: the decoding process stopped (exit code "
                        f"{self._proc.exitcode}) before the end of the log"
                    ) from None

    def close(self) -> None:
        """Stop the child (if it still runs) and release the queue."""
        self._done = True
        if self._proc.is_alive():
            self._proc.terminate()
        self._proc.join(timeout=5)
        self._queue.close()
        self._queue.cancel_join_thread()

    def __enter__(self) -> FramePrefetcher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

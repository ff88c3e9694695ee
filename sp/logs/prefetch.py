"""A log's frames decoded ahead in a child process.

Decoding ROS messages (CDR deserialisation in Python, chunk decompression, CRCs) costs a few
milliseconds of the reading process's CPU per LADAR sweep. :class:`FramePrefetcher` runs
``source.frames()`` in a forked child and hands the frames over in batches through a pipe
(pickled numpy arrays cost a copy, far less than decoding), so the process that
consumes them only unpickles. The frames and their order are exactly those of
``source.frames()``; the child's read statistics replace ``source.stats`` at the end.
"""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
import os
import pickle
import struct
import time
from collections.abc import Iterator
from typing import Any

from sp.logs.source import LogSource
from sp.logs.types import Frame

_HEADER = struct.Struct("<Q")  # byte length of the pickled message that follows


class PrefetchError(RuntimeError):
    """The decoding process stopped without finishing the log (names the log and the cause)."""


def _send(fd: int, message: object) -> None:
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    view = memoryview(_HEADER.pack(len(data)) + data)
    while view:
        view = view[os.write(fd, view) :]


def _receive(fd: int) -> object | None:
    """One message, or None at the end of the pipe (the child closed it, or died)."""
    head = _read_exact(fd, _HEADER.size)
    if head is None:
        return None
    body = _read_exact(fd, _HEADER.unpack(head)[0])
    return None if body is None else pickle.loads(body)


def _read_exact(fd: int, n: int) -> bytes | None:
    chunks, left = [], n
    while left:
        chunk = os.read(fd, min(left, 1 << 22))
        if not chunk:
            return None
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def _serve(source: LogSource, read_fd: int, fd: int, batch_frames: int, kwargs: dict) -> None:
    """The child: decode, send batches, then ("end", stats, cpu_s) or ("error", exception)."""
    os.close(read_fd)
    batch: list[Frame] = []
    try:
        for frame in source.frames(**kwargs):
            batch.append(frame)
            if len(batch) >= batch_frames:
                _send(fd, ("frames", batch))
                batch = []
        if batch:
            _send(fd, ("frames", batch))
        _send(fd, ("end", source.stats, time.process_time()))
    except Exception as e:  # sent back: the consumer raises it where it reads
        _send(fd, ("error", e))
    os.close(fd)


class FramePrefetcher:
    """Iterate ``source.frames(**kwargs)`` decoded by a child process, in batches of
    ``batch_frames`` frames through a pipe (the child runs ahead until the pipe is full).
    It forks: start it before anything in the process runs threads (a KD, a thread pool).
    Use as a context manager, or :meth:`close` it: leaving early stops the child. If the
    child dies (the pipe's end tells, no waiting), the rest of the log is decoded in this
    process, from the frame after the last one handed over, and ``source.stats`` says so.

    ``decode_cpu_s`` is the child's CPU time once the log has been read to its end.
    """

    def __init__(self, source: LogSource, batch_frames: int = 16, **kwargs: Any) -> None:
        if batch_frames < 1:
            raise PrefetchError(f"{source.path}: batch_frames {batch_frames} must be >= 1")
        self.source = source
        self.decode_cpu_s = 0.0
        self._kwargs = kwargs
        self._fd, write_fd = os.pipe()
        # fork: the child reads with the source as it is (no re-import, no re-opening)
        ctx = mp.get_context("fork")
        self._proc = ctx.Process(
            target=_serve,
            args=(source, self._fd, write_fd, batch_frames, kwargs),
            daemon=True,
            name="log-decode",
        )
        self._proc.start()
        os.close(write_fd)  # only the child writes: its exit ends the pipe
        self._done = False

    def __iter__(self) -> Iterator[Frame]:
        n_yielded = 0
        while not self._done:
            message = _receive(self._fd)
            if message is None:  # the child died: decode the rest here
                self._done = True
                self._proc.join(timeout=5)
                self.source.stats.note(
                    f"{self.source.path.name}: the decoding process stopped (exit code "
                    f"{self._proc.exitcode}) after {n_yielded} frames; read on in this process"
                )
                for i, frame in enumerate(self.source.frames(**self._kwargs)):
                    if i >= n_yielded:
                        yield frame
                return
            kind, *payload = message  # type: ignore[misc]
            if kind == "frames":
                for frame in payload[0]:
                    n_yielded += 1
                    yield frame
            elif kind == "end":
                self._done = True
                for f in dataclasses.fields(payload[0]):
                    setattr(self.source.stats, f.name, getattr(payload[0], f.name))
                self.decode_cpu_s = float(payload[1])
            else:
                self._done = True
                raise payload[0]

    def close(self) -> None:
        """Stop the child (if it still runs) and close the pipe."""
        self._done = True
        if self._proc.is_alive():
            self._proc.terminate()
        self._proc.join(timeout=5)
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> FramePrefetcher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

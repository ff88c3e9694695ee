"""A log's frames decoded ahead in a child process.

Decoding ROS messages (CDR deserialisation in Python, chunk decompression, CRCs) costs a few
milliseconds of the reading process's CPU per LADAR sweep. :class:`FramePrefetcher` runs
``source.frames()`` in a child interpreter and hands the frames over in batches through a
pipe (pickled numpy arrays cost a copy, far less than decoding), so the process that
consumes them only unpickles. The frames and their order are exactly those of
``source.frames()``; the child's read statistics replace ``source.stats`` at the end.

The child is a fresh interpreter (``python -c``), not a fork: a fork of a process that has run
threads (DuckDB, numba, BLAS, a test runner) inherits their objects without their threads,
and a garbage collection in the child that finalises one of them can crash it (seen: SIGSEGV
while collecting inside rosbags' type compiler). A fresh interpreter also never re-runs the
caller's ``__main__``. It opens the log anew as ``type(source)(source.path,
skip_corrupt=source.skip_corrupt)``, as :func:`~logs.source.open_log` does.

The child never outlives the consumer: on Linux the kernel kills it when the consumer's
process dies (:func:`core.process.die_with_parent`), and anywhere it exits when the pipe's
reading end is gone (its next write fails).
"""

from __future__ import annotations

import dataclasses
import os
import pickle
import queue
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from core.errors import EngineError
from core.process import die_with_parent
from logs.source import LogSource
from logs.types import LogMessage

_HEADER = struct.Struct("<Q")  # byte length of the pickled message that follows
_CHILD = "from logs.prefetch import _child_main; _child_main()"


class PrefetchError(EngineError, RuntimeError):
    """The decoding process stopped without finishing the log (names the log and the cause)."""


def _send(fd: int, message: object) -> None:
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    view = memoryview(_HEADER.pack(len(data)) + data)
    while view:
        view = view[os.write(fd, view) :]


def _receive_bytes(fd: int) -> bytes | None:
    """One pickled message, or None at the end of the pipe (the child closed it, or died)."""
    head = _read_exact(fd, _HEADER.size)
    if head is None:
        return None
    return _read_exact(fd, _HEADER.unpack(head)[0])


def _read_exact(fd: int, n: int) -> bytes | None:
    chunks, left = [], n
    while left:
        chunk = os.read(fd, min(left, 1 << 22))
        if not chunk:
            return None
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def _serve(source: LogSource, fd: int, batch_frames: int, kwargs: dict) -> None:
    """The child: decode, send batches, then ("end", stats, cpu_s) or ("error", exception)."""
    batch: list[LogMessage] = []
    try:
        for frame in source.frames(**kwargs):
            batch.append(frame)
            if len(batch) >= batch_frames:
                _send(fd, ("frames", batch))
                batch = []
        if batch:
            _send(fd, ("frames", batch))
        _send(fd, ("end", source.stats, time.process_time()))
    except BrokenPipeError:
        return  # the consumer is gone (closed early, or killed): no one left to tell
    except Exception as e:  # sent back: the consumer raises it where it reads
        _send(fd, ("error", e))


def _child_main() -> None:
    """The child interpreter's entry: the consumer's pid is its one argument (taken before
    the child started, so a consumer that died meanwhile is noticed); the request (source
    type, path, skip_corrupt, batch size, frame filters) comes pickled on stdin; messages go
    out on the original stdout, and anything else printed goes to stderr so it cannot
    corrupt the stream."""
    die_with_parent(int(sys.argv[1]))
    source_type, path, skip_corrupt, batch_frames, kwargs = pickle.load(sys.stdin.buffer)
    fd = os.dup(1)
    os.dup2(2, 1)
    try:
        _serve(source_type(path, skip_corrupt=skip_corrupt), fd, batch_frames, kwargs)
    finally:
        os.close(fd)


class FramePrefetcher:
    """Iterate ``source.frames(**kwargs)`` decoded by a child process, in batches of
    ``batch_frames`` frames through a pipe. A thread of this process drains the pipe into a
    queue of ``ahead_batches`` batches (reading releases the interpreter lock), so the child
    runs that far ahead instead of waiting on a full pipe whenever this process is busy.
    Use as a context manager, or :meth:`close` it: leaving early stops the child. If the
    child dies (the pipe's end tells, no waiting), the rest of the log is decoded in this
    process, from the frame after the last one handed over, and ``source.stats`` says so.

    ``decode_cpu_s`` is the child's CPU time once the log has been read to its end.
    """

    def __init__(
        self, source: LogSource, batch_frames: int = 16, ahead_batches: int = 8, **kwargs: Any
    ) -> None:
        if batch_frames < 1:
            raise PrefetchError(f"{source.path}: batch_frames {batch_frames} must be >= 1")
        if ahead_batches < 1:
            raise PrefetchError(f"{source.path}: ahead_batches {ahead_batches} must be >= 1")
        self.source = source
        self.decode_cpu_s = 0.0
        self._kwargs = kwargs
        request = (type(source), source.path, source.skip_corrupt, batch_frames, kwargs)
        self._proc = subprocess.Popen(
            [sys.executable, "-c", _CHILD, str(os.getpid())],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=_child_env(),
        )
        assert self._proc.stdin is not None and self._proc.stdout is not None
        try:
            pickle.dump(request, self._proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            self._proc.stdin.close()
        except BrokenPipeError:
            pass  # the child is gone already: the pipe's end tells __iter__
        self._fd = self._proc.stdout.fileno()
        self._done = False
        self._stop = threading.Event()
        self._bodies: queue.Queue[bytes | None] = queue.Queue(maxsize=ahead_batches)
        self._drain = threading.Thread(target=self._drain_pipe, name="log-decode-pipe")
        self._drain.daemon = True
        self._drain.start()

    def _drain_pipe(self) -> None:
        """The reading thread: pipe messages into the queue, then None at the pipe's end."""
        while True:
            body = _receive_bytes(self._fd)
            while not self._stop.is_set():
                try:
                    self._bodies.put(body, timeout=0.1)
                    break
                except queue.Full:
                    continue
            if body is None or self._stop.is_set():
                return

    def __iter__(self) -> Iterator[LogMessage]:
        n_yielded = 0
        while not self._done:
            body = self._bodies.get()
            if body is None:  # the child died: decode the rest here
                self._done = True
                code = self._wait()
                self.source.stats.note(
                    f"{self.source.path.name}: the decoding process stopped (exit code "
                    f"{code}) after {n_yielded} frames; read on in this process"
                )
                for i, frame in enumerate(self.source.frames(**self._kwargs)):
                    if i >= n_yielded:
                        yield frame
                return
            kind, *payload = pickle.loads(body)
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
        self._stop.set()
        if self._proc.poll() is None:
            self._proc.terminate()
        self._wait()
        self._drain.join(timeout=5)  # the child is gone: its pipe has ended
        if self._fd >= 0:
            assert self._proc.stdout is not None
            self._proc.stdout.close()
            self._fd = -1

    def _wait(self) -> int | None:
        """The child's exit code (negative: the signal that ended it), killing a child that
        does not end within 5 s of being asked to."""
        try:
            return self._proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            return self._proc.wait()

    def __enter__(self) -> FramePrefetcher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _child_env() -> dict[str, str]:
    """This environment, with the folder holding the ``sp`` package first on the child's
    path (so a source checkout that is not installed works too)."""
    root = str(Path(__file__).resolve().parents[2])
    path = os.environ.get("PYTHONPATH")
    return dict(os.environ, PYTHONPATH=root if not path else os.pathsep.join((root, path)))

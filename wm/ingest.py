"""Streaming ingest: a live node fed by clients over HTTP with raw ROS 2 messages, instead of a
log (``wm serve --ingest``).

    POST /v1/ingest?topic=/ladar/points&msgtype=sensor_msgs/msg/PointCloud2&t_ns=...
         body: the message's CDR bytes (application/octet-stream, as rosbag2 and MCAP store them)

    POST /v1/ingest/batch   body: a sequence of messages (:func:`pack_batch`), taken in order

``t_ns`` is the message's log time (int64 ns; what an MCAP message's ``log_time`` is); send
messages in log-time order, as a log reader would give them. ``kind`` (optional) is the
channel's ``frame_kind`` where the type alone is ambiguous (``ground_truth_pose`` for an
Odometry that is ground truth; a topic under ``/ground_truth`` says so too).

Each message is decoded as the MCAP reader decodes it (:class:`logs.mcap_log.CdrFrameDecoder`:
the same deserialisers, the same assembly of one instant's messages into frames), so a log
posted message by message gives the node the frames ``wm run`` gives it. The messages of one
log time become frames when a message of a later time arrives (or the node stops). Frames go
to the node's thread through a bounded queue (``queue_size`` frames).

Answers: 202 when the message was taken (``frames``: frames it completed; ``queued``; and
``dropped``: true when any of them found the queue full and was dropped, counted in
``/v1/status``). A drop is answered 202, not 503: the message was consumed (its instant's
camera intrinsics and box velocities are already applied), the frames dropped are those of the
previous instant, and a client that sent it again would duplicate it; a client that sees
``dropped`` should slow down. 202 with ``ignored`` for a known type no frame is made of (as a
log reader skips such topics); 400 for bytes that cannot be decoded as ``msgtype`` or a type
the standard definitions do not hold (naming the topic and type); 503 once the node stops.

Memory stays bounded under a flood: the queue holds at most ``queue_size`` frames, one log
time at most :data:`MAX_INSTANT_MESSAGES` messages (the assembler holds one instant), and a
body at most the ingest limit (:mod:`wm.limits`).
"""

from __future__ import annotations

import queue
import struct
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

from fastapi import FastAPI, HTTPException, Query, Request
from fastapi.concurrency import run_in_threadpool
from pydantic import BaseModel

from wm.serve import LiveNode, ServeError

#: messages one log time may hold (the assembler keeps an instant's messages until the next)
MAX_INSTANT_MESSAGES = 1024
#: the longest topic or type name taken
MAX_NAME_CHARS = 256


class _End:
    """The queue's last item: the input ended (a class, so that it is itself again when the
    queue crosses to the node's process)."""


_END = _End()
# a batch record's head: topic length, type length (u16), log time (int64 ns), data length (u32)
_RECORD = struct.Struct("<HHqI")


class IngestError(ServeError):
    """A message the ingest refuses (bad bytes, an unknown type); names the topic and type."""


@dataclass
class IngestCounts:
    """What the ingest has taken so far (messages and frames since the start)."""

    messages: int = 0  # messages taken (decoded, or ignored as no frame is made of them)
    ignored: int = 0  # of those, of a type no frame is made of
    undecodable: int = 0  # refused with a 400: bytes that are not a message of their type
    frames: int = 0  # frames the messages completed
    dropped: int = 0  # of those, dropped because the queue was full
    unframed: int = 0  # decoded messages no frame could be made of (named in ``problem``)
    problem: str = ""  # the latest such problem

    def json(self, queued: int, queue_size: int) -> dict:
        return {**self.__dict__, "queued": queued, "queue_size": queue_size}


class IngestAnswer(BaseModel):
    """The answer to one ingested message."""

    topic: str
    t_ns: int
    frames: int  # frames this message completed (of the instant before its own)
    queued: int  # frames waiting for the node after this message
    dropped: bool  # a frame it completed found the queue full and was dropped
    ignored: bool  # a known type no frame is made of


class IngestNode(LiveNode):
    """A world-model node fed by :meth:`ingest` instead of a log (module docstring).

    ``kd_path``: the KD file it writes (``":memory:"`` for none); ``queue_size``: frames
    waiting for the node at most (more are dropped and counted); ``process``: the node in a
    process of its own (:class:`~wm.serve.LiveNode`). Messages are decoded in this process
    either way; with ``process`` the queue is a :class:`multiprocessing.Queue` the node's
    process reads, so the decoding never takes the node's interpreter lock."""

    def __init__(
        self,
        kd_path: str | Path = ":memory:",
        config: Any | None = None,
        queue_size: int = 64,
        process: bool = False,
    ) -> None:
        if queue_size < 1:
            raise ServeError(f"ingest queue size {queue_size}: need at least 1")
        super().__init__(None, kd_path, config, rate=0.0, process=process)
        from logs.mcap_log import CdrFrameDecoder
        from logs.types import ReadStats

        self.queue_size = queue_size
        if process:  # bounded as the thread's queue: a put that finds it full raises Full
            import multiprocessing as mp

            self.queue: Any = mp.get_context("spawn").Queue(maxsize=queue_size)
        else:
            self.queue = queue.Queue(maxsize=queue_size)
        self.counts = IngestCounts()
        self.decoder = CdrFrameDecoder(ReadStats(), on_error=self._unframed)
        self._decode_lock = threading.Lock()  # the assembler keeps the order of the messages
        self._accepting = True
        self._instant = (-1, 0)  # the pending log time and its messages

    # --- the client side ------------------------------------------------------------------

    def ingest(
        self, topic: str, msgtype: str, data: bytes, t_ns: int, kind: str | None = None
    ) -> dict:
        """Decode one ROS 2 message (CDR ``data`` of ``msgtype`` on ``topic`` at log time
        ``t_ns``, int64 ns) and queue the frames it completes; the :class:`IngestAnswer`."""
        msgtype = _full_type(msgtype)
        with self._decode_lock:
            if not self._accepting or self.closed or (self.process and not self.running):
                raise ServeError("the live node is not taking messages (stopped)")
            role = self.decoder.role(topic, msgtype, kind)
            if role is None:
                _known_type(topic, msgtype)
                self.counts.messages += 1
                self.counts.ignored += 1
                return _answer(topic, t_ns, 0, self.queue.qsize(), False, True)
            self._count_instant(topic, msgtype, t_ns)
            msg = self._decode(topic, msgtype, data)
            frames = self.decoder.push(topic, role, msg, t_ns)
            self.counts.messages += 1
            dropped = self._enqueue(frames)
            return _answer(topic, t_ns, len(frames), self.queue.qsize(), dropped > 0, False)

    def _count_instant(self, topic: str, msgtype: str, t_ns: int) -> None:
        t, n = self._instant
        n = n + 1 if t == t_ns else 1
        if n > MAX_INSTANT_MESSAGES:
            raise IngestError(
                f"{topic} ({msgtype}) at t_ns {t_ns}: more than {MAX_INSTANT_MESSAGES} "
                "messages at one log time"
            )
        self._instant = (t_ns, n)

    def _decode(self, topic: str, msgtype: str, data: bytes) -> Any:
        _known_type(topic, msgtype)
        try:
            return self.decoder.decode(msgtype, data)
        except Exception as e:  # rosbags raises several types for bad bytes
            self.counts.undecodable += 1
            raise IngestError(
                f"{topic}: {len(data)} bytes cannot be decoded as {msgtype} (CDR): "
                f"{type(e).__name__}: {e}"
            ) from None

    def _enqueue(self, frames: list) -> int:
        """Queue ``frames`` for the node without waiting; those that find it full are dropped
        (the count)."""
        dropped = 0
        for frame in frames:
            try:
                self.queue.put_nowait(frame)
            except queue.Full:
                dropped += 1
        self.counts.frames += len(frames)
        self.counts.dropped += dropped
        return dropped

    def _unframed(self, problem: str) -> None:
        """A decoded message no frame could be made of (the assembler's complaint)."""
        self.counts.unframed += 1
        self.counts.problem = problem

    def status_extra(self) -> dict:
        return {"log": None, "ingest": self.counts.json(self.queue.qsize(), self.queue_size)}

    def spawn_args(self) -> dict[str, Any]:
        return {"kd_path": self.kd_path, "config": self.config, "queue_size": self.queue_size}

    # --- the node side --------------------------------------------------------------------

    def _open_source(self) -> None:
        return None

    def _replay(self, source: Any) -> None:
        """Feed the node what the queue brings until the input ends (or a stop without it)."""
        while True:
            try:
                frame = self.queue.get(timeout=0.1)
            except queue.Empty:
                if self._stop.is_set():
                    return
                continue
            if isinstance(frame, _End):
                break
            self._feed(frame)
        self._account(self._cycle(self.node.finish), 0.0)

    def end(self, timeout_s: float = 60.0) -> None:
        """The input ended: make frames of the last instant, let the node take every frame
        queued and finish (its KD flushed). Messages are refused from then on."""
        with self._decode_lock:
            if not self._accepting:
                return
            self._accepting = False
            tail = self.decoder.flush()
        self.counts.frames += len(tail)
        for item in [*tail, _END]:  # the node's thread takes them: waiting here is bounded
            try:
                self.queue.put(item, timeout=timeout_s if self._feeding() else 0.01)
            except queue.Full:
                self.counts.dropped += item is not _END
        self.wait(timeout_s)

    def stop(self, timeout_s: float = 30.0) -> None:
        """End the input (:meth:`end`: every frame taken reaches the node), then stop."""
        if self._feeding():
            self.end(timeout_s)
        super().stop(timeout_s)
        if self.process:  # frames left for a node that is gone must not hold up the exit
            self.queue.cancel_join_thread()
            self.queue.close()


def pack_batch(messages: list[tuple[str, str, bytes, int]]) -> bytes:
    """The body of ``POST /v1/ingest/batch`` for ``(topic, msgtype, cdr, t_ns)`` messages: per
    message, little-endian u16 topic length, u16 type length, int64 log time (ns), u32 data
    length, then the topic and type (UTF-8) and the CDR bytes."""
    out = []
    for topic, msgtype, data, t_ns in messages:
        t, m = topic.encode(), msgtype.encode()
        out += [_RECORD.pack(len(t), len(m), t_ns, len(data)), t, m, data]
    return b"".join(out)


def unpack_batch(body: bytes) -> list[tuple[str, str, memoryview, int]]:
    """The messages :func:`pack_batch` packed; IngestError naming the byte offset of a record
    cut short, a bad name or a negative time."""
    view, pos, out = memoryview(body), 0, []
    while pos < len(view):
        if pos + _RECORD.size > len(view):
            raise IngestError(f"batch record {len(out)} at byte {pos}: cut short in its head")
        nt, nm, t_ns, nd = _RECORD.unpack_from(view, pos)
        end = pos + _RECORD.size + nt + nm + nd
        if end > len(view):
            raise IngestError(
                f"batch record {len(out)} at byte {pos}: declares {nt + nm + nd} bytes, "
                f"{len(view) - pos - _RECORD.size} left"
            )
        names = bytes(view[pos + _RECORD.size : end - nd])
        try:
            topic, msgtype = names[:nt].decode(), names[nt:].decode()
        except UnicodeDecodeError:
            raise IngestError(f"batch record {len(out)} at byte {pos}: names not UTF-8") from None
        if not (topic and msgtype and t_ns >= 0):
            raise IngestError(
                f"batch record {len(out)} at byte {pos}: topic {topic!r}, type {msgtype!r}, "
                f"t_ns {t_ns}: need a topic, a type and t_ns >= 0"
            )
        out.append((topic, msgtype, view[end - nd : end], t_ns))
        pos = end
    return out


def _full_type(msgtype: str) -> str:
    """``pkg/Name`` as ``pkg/msg/Name`` (the ROS 2 spelling the type store knows)."""
    parts = msgtype.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else msgtype


def _known_type(topic: str, msgtype: str) -> None:
    """Refuse a type the standard definitions (ROS 2 Humble and vision_msgs) do not hold."""
    from logs.ros_types import typestore

    if msgtype not in typestore().fielddefs:
        raise IngestError(
            f"{topic}: message type {msgtype!r} is unknown (not a ROS 2 Humble or vision_msgs "
            "type, spelled pkg/msg/Name)"
        )


def _answer(topic: str, t_ns: int, frames: int, queued: int, dropped: bool, ignored: bool):
    return {"topic": topic, "t_ns": t_ns, "frames": frames, "queued": queued,
            "dropped": dropped, "ignored": ignored}  # fmt: skip


_OCTETS = {
    "requestBody": {
        "required": True,
        "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}},
    }
}

Name = Annotated[str, Query(min_length=1, max_length=MAX_NAME_CHARS)]


def add_ingest_routes(app: FastAPI, live: LiveNode) -> None:
    """``POST /v1/ingest`` on ``app`` when ``live`` is an :class:`IngestNode` (module
    docstring); nothing for a node replaying a log."""
    if not isinstance(live, IngestNode):
        return

    @app.post("/v1/ingest", status_code=202, openapi_extra=_OCTETS)
    async def ingest(
        request: Request,
        topic: Name,
        msgtype: Name,
        t_ns: Annotated[int, Query(ge=0, le=2**63 - 1)],
        kind: Annotated[str | None, Query(max_length=MAX_NAME_CHARS)] = None,
    ) -> IngestAnswer:
        """One ROS 2 message (CDR bytes as the body) of ``msgtype`` on ``topic`` at log time
        ``t_ns`` (int64 ns), decoded and queued for the node (module docstring of wm.ingest)."""
        data = await request.body()
        try:  # decoding takes milliseconds for a sweep: not on the event loop
            return await run_in_threadpool(live.ingest, topic, msgtype, data, t_ns, kind)
        except IngestError as e:
            raise HTTPException(400, str(e)) from None
        except ServeError as e:
            raise HTTPException(503, str(e)) from None

    @app.post("/v1/ingest/batch", status_code=202, openapi_extra=_OCTETS)
    async def ingest_batch(request: Request) -> BatchAnswer:
        """Messages packed by :func:`wm.ingest.pack_batch`, taken in order as ``/v1/ingest``
        takes each; a 400 names the first one refused (those before it were taken)."""
        data = await request.body()
        try:
            return await run_in_threadpool(_take_batch, live, data)
        except IngestError as e:
            raise HTTPException(400, str(e)) from None
        except ServeError as e:
            raise HTTPException(503, str(e)) from None


class BatchAnswer(BaseModel):
    """The answer to a batch: messages taken, frames they completed, frames dropped."""

    messages: int
    frames: int
    dropped: int
    queued: int


def _take_batch(live: IngestNode, body: bytes) -> dict:
    messages = unpack_batch(body)
    frames = dropped = 0
    for k, (topic, msgtype, data, t_ns) in enumerate(messages):
        before = live.counts.dropped
        try:
            ans = live.ingest(topic, msgtype, data, t_ns)
        except IngestError as e:
            raise IngestError(f"batch message {k} (of {len(messages)}; {k} taken): {e}") from None
        frames += ans["frames"]
        dropped += live.counts.dropped - before
    return {"messages": len(messages), "frames": frames, "dropped": dropped,
            "queued": live.queue.qsize()}  # fmt: skip

"""MCAP logs of ROS 2 messages: :class:`McapLogWriter` writes frames, :class:`McapLogSource`
reads them back (and any ROS 2 MCAP with ``cdr`` messages).

Files are standard MCAP (profile ``ros2``): schemas in ``ros2msg`` encoding with the full
ROS 2 message definitions, messages in ``cdr`` encoding, chunked with CRCs, fully indexed
(the tests read them with ``rosbags`` and with the ``mcap`` library's reader and ROS 2
decoder, which ROS 2 tooling builds on). How each frame maps to
messages and topics (and why box velocities travel on ``<topic>/velocities``) is in
:mod:`logs.ros_encode`. Each channel's metadata says the frame kind it carries
(``frame_kind``), so ground-truth poses and odometry, both nav_msgs/Odometry, stay apart.

Log time = publish time = the frame's ``t_ns`` (which must be >= 0); header stamps = ``t_ns``.

Chunks are uncompressed by default: point clouds and camera images barely shrink under LZ4
(zstd does better) while either costs several times the write time (``python -m bench
logs``); uncompressed chunks are also streamed to the file without holding messages in memory.
Choose with :class:`McapWriterConfig`. Each chunk carries a CRC, which is how damaged bytes
are found when reading. Closing fsyncs the file before the atomic rename (``durable``), so a
crash leaves either the old state or the complete log.

Reading walks the records itself (not the summary), so that a log cut short or with damaged
chunks can still be read with ``skip_corrupt=True``; chunks are merged in log-time order
assuming their start times do not decrease through the file (true for ours and for rosbag2
recordings; otherwise the few out-of-order messages show up as backwards timestamps).
Well-formed chunks are parsed in place (each message a memoryview of its chunk, the CRC by
ISA-L) and anything unusual is left to the ``mcap`` library's reading, so damaged input
fails or is skipped exactly as that reading has it; the rosbags typestore makes only the
deserialisers it uses (see :func:`_chunk_records` and :func:`_reading_typestore`).
"""

from __future__ import annotations

import enum
import functools
import heapq
import io
import os
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Chunk, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk

from logs.mcap_file import MAGIC, McapFileWriter, crc32
from logs.ros_decode import FrameAssembler
from logs.ros_encode import encode_frame
from logs.ros_types import (
    KIND_KEY,
    Role,
    frame_topic,
    frame_topics_of,
    role_of,
    ros2msg_schema,
)
from logs.source import LogSource, TopicInfo, topic_info
from logs.types import LogError, LogMessage, ReadStats

_FOOTER_SIZE = 1 + 8 + 8 + 8 + 4  # opcode, length, summary start, summary offset start, crc
_CHUNK_HEAD = struct.Struct("<QQQII")  # start, end time, uncompressed size, CRC, len(compression)
_U64 = struct.Struct("<Q")
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, length
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel, sequence, log time, publish time
_MESSAGE_INDEX_HEAD = struct.Struct("<HI")  # channel, byte length of its (time, offset) pairs

#: the most uncompressed bytes a chunk may declare: more is refused as corrupt, never allocated
MAX_CHUNK_BYTES = 1 << 30
#: ... nor more than this many times the file's size (floor: ``_CHUNK_SIZE_FLOOR``), since no
#: real chunk compresses that well
MAX_CHUNK_EXPANSION = 256
_CHUNK_SIZE_FLOOR = 64 << 20
#: how many of each channel's latest messages a repeat is looked for among
_RECENT_MESSAGES = 256


def chunk_size_limit(file_size: int) -> int:
    """The most uncompressed bytes a chunk of a file of ``file_size`` bytes may declare."""
    return min(MAX_CHUNK_BYTES, max(_CHUNK_SIZE_FLOOR, MAX_CHUNK_EXPANSION * file_size))


def _chunk_size_problem(body: bytes, limit: int) -> str | None:
    """Why a chunk record's declared uncompressed size cannot be right (None if it can be):
    above ``limit``, or (uncompressed) not the size of its data. Compressed data that says
    its own size (zstd, LZ4 frames) must agree, so nothing decompresses to more."""
    if len(body) < _CHUNK_HEAD.size:
        return None  # the reading names a short record
    size = _CHUNK_HEAD.unpack_from(body)[2]
    if size > limit:
        return f"declares {size} uncompressed bytes, above the limit of {limit}"
    name_len = _CHUNK_HEAD.unpack_from(body)[4]
    pos = _CHUNK_HEAD.size + name_len
    if pos + _U64.size > len(body):
        return None
    compression = bytes(body[_CHUNK_HEAD.size : pos])
    data = memoryview(body)[pos + _U64.size :]
    framed: int | None = None
    try:
        if compression == b"":
            framed = _U64.unpack_from(body, pos)[0]
        elif compression == b"zstd":
            import zstandard

            framed = zstandard.frame_content_size(data)
        elif compression == b"lz4":
            import lz4.frame

            framed = lz4.frame.get_frame_info(data).get("content_size") or None
    except Exception:  # damaged or unknown: the reading names it
        return None
    if framed is not None and framed >= 0 and framed != size:
        return f"declares {size} uncompressed bytes but its data holds {framed}"
    return None


def _index_count(body: bytes) -> int:
    """Messages a MESSAGE_INDEX record lists (0 if it is damaged)."""
    if len(body) < _MESSAGE_INDEX_HEAD.size:
        return 0
    n_bytes = _MESSAGE_INDEX_HEAD.unpack_from(body)[1]
    return min(n_bytes, len(body) - _MESSAGE_INDEX_HEAD.size) // 16


def _opcode_name(opcode: int) -> str:
    try:
        return Opcode(opcode).name
    except ValueError:
        return f"0x{opcode:02x}"


class Compression(enum.Enum):
    """Chunk compression of a written MCAP file."""

    NONE = "none"
    LZ4 = "lz4"
    ZSTD = "zstd"


_MCAP_COMPRESSION = {Compression.NONE: "", Compression.LZ4: "lz4", Compression.ZSTD: "zstd"}


@dataclass(frozen=True, slots=True)
class McapWriterConfig:
    """How :class:`McapLogWriter` lays out the file."""

    compression: Compression = Compression.NONE
    chunk_size_bytes: int = 4 * 1024 * 1024  # uncompressed bytes per chunk
    durable: bool = True  # fsync the file before the rename and the folder after it
    library: str = "rcs-worldmodel logs"


def _fsync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class McapLogWriter:
    """Writes sensor frames to an MCAP file of ROS 2 messages, atomically.

    Writes go to ``path + ".tmp"``; :meth:`close` (or leaving the ``with`` block normally)
    finishes the file and renames it to ``path``. Leaving the block by an exception removes the
    temporary file, so ``path`` is either a complete log or absent.

    >>> with McapLogWriter("run.mcap") as w:       # doctest: +SKIP
    ...     w.write(scan)                          # any logs.types frame
    ...     w.attach("scenario.yaml", text, "application/yaml")
    ...     w.add_metadata("scenario", {"seed": "7"})
    """

    def __init__(self, path: str | Path, config: McapWriterConfig | None = None) -> None:
        self.path = Path(path)
        self.config = config or McapWriterConfig()
        self._tmp = self.path.with_name(self.path.name + ".tmp")
        try:
            self._file = open(self._tmp, "wb")
        except OSError as exc:
            raise LogError(f"{self.path}: cannot write: {exc}") from exc
        self._writer = McapFileWriter(
            self._file,
            compression=_MCAP_COMPRESSION[self.config.compression],
            chunk_size=self.config.chunk_size_bytes,
            profile="ros2",
            library=self.config.library,
        )
        self._schema_ids: dict[str, int] = {}
        self._channel_ids: dict[tuple[str, str], int] = {}
        self._sequence = 0
        self._open = True
        self.messages_written = 0
        self.payload_bytes = 0  # serialised message bytes written (before chunk compression)

    def __enter__(self) -> McapLogWriter:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def _channel_id(self, topic: str, msgtype: str, kind: str) -> int:
        key = (topic, msgtype)
        cid = self._channel_ids.get(key)
        if cid is None:
            sid = self._schema_ids.get(msgtype)
            if sid is None:
                sid = self._writer.add_schema(msgtype, "ros2msg", ros2msg_schema(msgtype))
                self._schema_ids[msgtype] = sid
            cid = self._writer.add_channel(topic, "cdr", sid, {KIND_KEY: kind})
            self._channel_ids[key] = cid
        return cid

    def write(self, frame: LogMessage) -> None:
        """Write one frame (any :mod:`logs.types` frame) at log time ``frame.t_ns``."""
        self._check_open()
        t_ns = int(frame.t_ns)
        if t_ns < 0:
            raise LogError(f"{self.path}: {type(frame).__name__} t_ns={t_ns} < 0 (MCAP times)")
        for enc in encode_frame(frame):
            cid = self._channel_id(enc.topic, enc.msgtype, enc.kind)
            self._writer.add_message(cid, t_ns, t_ns, self._sequence, enc.parts)
            self._sequence += 1
            self.messages_written += 1
            self.payload_bytes += enc.nbytes

    def attach(self, name: str, data: bytes, media_type: str, t_ns: int = 0) -> None:
        """Attach a file (e.g. the scenario that made the log) to the log."""
        self._check_open()
        self._writer.add_attachment(name, media_type, bytes(data), int(t_ns))

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Add a named record of string key/value pairs."""
        self._check_open()
        bad = {k: v for k, v in data.items() if not (isinstance(k, str) and isinstance(v, str))}
        if bad:
            raise LogError(f"{self.path}: metadata {name!r} has non-string entries {bad}")
        self._writer.add_metadata(name, dict(data))

    def close(self) -> None:
        """Finish the file (summary, indexes) and rename it into place."""
        if not self._open:
            return
        self._open = False
        try:
            self._writer.finish()
            if self.config.durable:
                self._file.flush()
                os.fsync(self._file.fileno())
            self._file.close()
            os.replace(self._tmp, self.path)
            if self.config.durable:
                _fsync_dir(self.path.parent)
        except OSError as exc:
            raise LogError(f"{self.path}: cannot finish the log: {exc}") from exc

    def abort(self) -> None:
        """Drop the unfinished file."""
        if self._open:
            self._open = False
            self._file.close()
            self._tmp.unlink(missing_ok=True)

    def _check_open(self) -> None:
        if not self._open:
            raise LogError(f"{self.path}: the writer is closed")


# ------------------------------------------------------------------------------ reading


class _ViewReader:
    """``io.BytesIO.read`` over a memoryview from an offset, without copying what is not read:
    the stream the ``mcap`` record classes read a schema or channel from inside a chunk."""

    __slots__ = ("_pos", "_view")

    def __init__(self, view: memoryview, pos: int) -> None:
        self._view = view
        self._pos = pos

    def read(self, n: int = -1) -> bytes:
        end = len(self._view) if n < 0 else self._pos + n
        out = bytes(self._view[self._pos : end])
        self._pos += len(out)
        return out


def _chunk_data(body: bytes) -> tuple[int, memoryview] | None:
    """(message start time, uncompressed records) of a chunk record's body, checked against
    its CRC; None unless the chunk is well-formed (then the library's reading decides)."""
    if len(body) < _CHUNK_HEAD.size:
        return None
    start_t_ns, _, uncompressed_size, crc, name_len = _CHUNK_HEAD.unpack_from(body)
    pos = _CHUNK_HEAD.size + name_len
    if pos + _U64.size > len(body):
        return None
    compression = body[_CHUNK_HEAD.size : pos]
    (data_len,) = _U64.unpack_from(body, pos)
    pos += _U64.size
    if pos + data_len > len(body):
        return None
    view = memoryview(body)[pos : pos + data_len]
    try:  # the calls the mcap library makes, so the same bytes come out
        if compression == b"":
            data = view
        elif compression == b"zstd":
            import zstandard

            data = memoryview(zstandard.decompress(view, uncompressed_size))
        elif compression == b"lz4":
            import lz4.frame

            data = memoryview(lz4.frame.decompress(view))
        else:
            return None
    except Exception:  # missing codec, damaged data: as the library finds it
        return None
    if crc != 0 and crc32(data) != crc:
        return None
    return start_t_ns, data


def _chunk_records(body: bytes) -> tuple[int, list[Any]] | None:
    """(message start time, schemas, channels and messages) of a chunk record's body: what
    :func:`_chunk_records_reference` gives, or None where this might differ from it.

    The ``mcap`` library copies the chunk out of the record, then each message out of the
    chunk through a ``BytesIO`` read per field, and computes the CRC with zlib's: most of the
    reading time of a log of point clouds. Here the CRC is ISA-L's (the same values) and each
    message's data is a memoryview into the record, which rosbags deserialises without a
    copy (a frame's arrays are copies made by the decoders, so none refers to the record).
    Anything unusual (a record running past the chunk, a short message, an unknown
    compression, a CRC mismatch, a schema or channel whose fields do not fill its record)
    returns None, and the library's reading then gives the records or the error.
    """
    chunk = _chunk_data(body)
    if chunk is None:
        return None
    start_t_ns, data = chunk
    records: list[Any] = []
    pos, size = 0, len(data)
    while pos < size:
        if pos + _RECORD_HEAD.size > size:
            return None
        opcode, length = _RECORD_HEAD.unpack_from(data, pos)
        begin = pos + _RECORD_HEAD.size
        pos = begin + length
        if pos > size:
            return None
        if opcode == Opcode.MESSAGE:
            if length < _MESSAGE_HEAD.size:
                return None
            channel_id, sequence, log_time, publish_time = _MESSAGE_HEAD.unpack_from(data, begin)
            records.append(
                Message(
                    channel_id=channel_id,
                    log_time=log_time,
                    data=data[begin + _MESSAGE_HEAD.size : pos],  # memoryview, not bytes
                    publish_time=publish_time,
                    sequence=sequence,
                )
            )
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
            stream = ReadDataStream(_ViewReader(data, begin))
            try:
                record = (Schema if opcode == Opcode.SCHEMA else Channel).read(stream)
            except Exception:
                return None
            if stream.count != length:  # the library would go on from where its fields end
                return None
            records.append(record)
    return start_t_ns, records


def _chunk_records_reference(stream: ReadDataStream) -> tuple[int, list[Any]]:
    """The ``mcap`` library's reading of a chunk record (the reference of the tests, and the
    reading of chunks :func:`_chunk_records` leaves to it): raises for a damaged chunk."""
    chunk = Chunk.read(stream)
    return chunk.message_start_time, breakup_chunk(chunk, validate_crc=True)


def _reading_typestore() -> Any:
    """An empty rosbags typestore (``Stores.EMPTY``) that makes only CDR deserialisers.

    rosbags' own typestore makes thirteen functions for each message type it meets (sizes,
    serialisers, ROS 1 converters...) by generating and compiling Python source, about
    half a millisecond a sweep on a 10 s log; reading uses two of them. This one makes a
    deserialiser when a message of that byte order first needs it (the same code rosbags
    generates), and is rosbags' own where this rosbags lacks the parts it builds on.
    """
    make = _reading_typestore_factory()
    if make is None:  # pragma: no cover - a rosbags without those parts
        from rosbags.typesys import Stores, get_typestore

        return get_typestore(Stores.EMPTY)
    return make()


@functools.cache
def _reading_typestore_factory() -> Callable[[], Any] | None:
    """What makes :func:`_reading_typestore`'s store; None if this rosbags lacks its parts
    (rosbags is imported on first use: opening a log does not need it)."""
    try:
        from rosbags.serde.cdr import generate_deserialize_cdr
        from rosbags.typesys.base import normalize_fieldname
        from rosbags.typesys.store import Typestore
        from rosbags.typesys.stores import empty
    except ImportError:  # pragma: no cover
        return None

    class CdrMsgdef:
        """What deserialising CDR takes from a rosbags ``Msgdef`` (name, fields, class and
        the deserialiser of each byte order), each deserialiser generated on its first call.

        No ``__getattr__`` for that: a class with one is read without the interpreter's fast
        attribute path, and the generated code reads a definition's attributes for every
        nested message it deserialises.
        """

        __slots__ = ("_store", "cls", "deserialize_cdr_be", "deserialize_cdr_le", "fields", "name")

        def __init__(self, name: str, fields: Any, cls: type, store: Any) -> None:
            self.name, self.fields, self.cls, self._store = name, fields, cls, store
            self.deserialize_cdr_le = self._on_first_call("le")
            self.deserialize_cdr_be = self._on_first_call("be")

        def _on_first_call(self, endianness: str) -> Callable[..., Any]:
            def generate_and_call(rawdata: Any, pos: int, cls: type, typestore: Any) -> Any:
                func = generate_deserialize_cdr(self.fields, self._store, endianness)
                setattr(self, f"deserialize_cdr_{endianness}", func)
                return func(rawdata, pos, cls, typestore)

            return generate_and_call

    class CdrReadingTypestore(Typestore):
        """rosbags' Typestore whose message definitions are :class:`CdrMsgdef`, put in its
        cache as each type is registered (so its ``get_msgdef`` finds them there and makes
        none of its own)."""

        def __init__(self, base: Any) -> None:
            super().__init__(base)
            self._add_msgdefs()

        def register(self, typs: Any) -> None:
            super().register(typs)
            self._add_msgdefs()

        def _add_msgdefs(self) -> None:
            for typename in self.fielddefs.keys() - self.cache.keys():
                fields = [  # as rosbags' get_msgdef lists them
                    (normalize_fieldname(name), desc) for name, desc in self.fielddefs[typename][1]
                ]
                self.cache[typename] = CdrMsgdef(typename, fields, self.types[typename], self)

    return functools.partial(CdrReadingTypestore, empty)


def _ends_crc(data: bytes, n: int = 4096) -> int:
    """CRC32 of a message's first and last ``n`` bytes: tells two messages apart as well as
    the whole would (a sweep's stamp and header lead its bytes; many writers leave every
    sequence number 0) at a fixed cost, not a pass over megabytes of points."""
    return crc32(data[-n:], crc32(data[:n])) if len(data) > 2 * n else crc32(data)


def _chunk_fingerprint(body: bytes) -> tuple[int, ...]:
    """What tells a chunk record's bytes from another's: its header (times, size, CRC of the
    uncompressed records) and length, with the CRC of the record itself where the chunk was
    written without one."""
    head = _CHUNK_HEAD.unpack_from(body)[:4] if len(body) >= _CHUNK_HEAD.size else ()
    crc = head[3] if head and head[3] else crc32(body)
    return (*head[:3], crc, len(body))


@dataclass(slots=True)
class _ChunkMessages:
    """The messages of one chunk (or one loose message), with the chunk's start time."""

    start_t_ns: int
    messages: list[Message]


class CdrFrameDecoder:
    """ROS 2 CDR messages in, frames out: ``(topic, msgtype, cdr bytes, log time)`` become the
    frames :class:`McapLogSource` would read of them (the same deserialisers and the same
    :class:`~logs.ros_decode.FrameAssembler`), for a reader of files and for a live feed.

    Feed messages in log-time order: the messages of one instant (one log time) become frames
    when the next instant starts (:meth:`feed` returns them) or at :meth:`flush`. A message type
    is registered from its schema text (:meth:`register`, as a file gives it) or, when no schema
    came, from the standard ROS 2 Humble definitions (plus vision_msgs) the writer uses.
    Problems making a frame of a decoded message go to ``on_error`` (a :class:`LogError` when
    None); bytes that cannot be deserialised raise from :meth:`decode`.
    """

    def __init__(
        self,
        stats: ReadStats,
        kinds: tuple[type, ...] | None = None,
        topics: frozenset[str] | None = None,
        on_error: Callable[[str], None] | None = None,
        store: _CdrTypes | None = None,
    ) -> None:
        self.assembler = FrameAssembler(stats, kinds, on_error=on_error)
        self.topics = topics
        self.store = store if store is not None else _CdrTypes()
        self._roles: dict[tuple[str, str, str | None], Role | None] = {}

    def role(self, topic: str, msgtype: str, kind: str | None = None) -> Role | None:
        """What a message on ``topic`` of ``msgtype`` feeds (``kind``: the channel's
        ``frame_kind``, which tells ground truth from odometry), or None when no wanted frame
        comes of it (then it is not worth deserialising)."""
        key = (topic, msgtype, kind)
        if key not in self._roles:
            role = role_of(topic, msgtype, kind)
            wanted = self.assembler.wants(role) and (
                self.topics is None or frame_topic(topic, role) in self.topics
            )
            self._roles[key] = role if wanted else None
        return self._roles[key]

    def register(self, msgtype: str, text: str, encoding: str = "ros2msg") -> None:
        """Learn ``msgtype`` from its schema text (``ros2msg`` or ``ros2idl``)."""
        self.store.register(msgtype, text, encoding)

    def decode(self, msgtype: str, data: bytes | memoryview) -> Any:
        """The message ``data`` (CDR) holds; a type never registered is taken from the standard
        definitions (KeyError when there is none). Raises whatever rosbags raises for bad bytes."""
        if not self.store.knows(msgtype):
            self.register(msgtype, ros2msg_schema(msgtype).decode())
        return self.store.deserialize(data, msgtype)

    def push(self, topic: str, role: Role, message: Any, log_t_ns: int) -> list[LogMessage]:
        """Add a decoded message; returns the frames completed by the instant before it."""
        return self.assembler.push(topic, role, message, log_t_ns)

    def feed(
        self, topic: str, msgtype: str, data: bytes | memoryview, log_t_ns: int,
        kind: str | None = None,
    ) -> list[LogMessage]:  # fmt: skip
        """:meth:`decode` and :meth:`push` one message (none for a type frames do not carry)."""
        role = self.role(topic, msgtype, kind)
        if role is None:
            return []
        return self.push(topic, role, self.decode(msgtype, data), log_t_ns)

    def flush(self) -> list[LogMessage]:
        """The frames of the pending instant (at the end of the input)."""
        return self.assembler.flush()


class _CdrTypes:
    """The message types a reading has registered, in a :func:`_reading_typestore` made on
    first use."""

    def __init__(self) -> None:
        self._store: Any = None
        self._registered: set[str] = set()

    def knows(self, msgtype: str) -> bool:
        return msgtype in self._registered

    def register(self, msgtype: str, text: str, encoding: str) -> None:
        from rosbags.typesys import get_types_from_idl, get_types_from_msg

        if self._store is None:
            self._store = _reading_typestore()
        if encoding == "ros2msg":
            types = get_types_from_msg(text, msgtype)
        elif encoding == "ros2idl":
            types = get_types_from_idl(text)
        else:
            raise ValueError(f"schema {msgtype!r} has encoding {encoding!r}")
        self._store.register(types)
        self._registered.add(msgtype)

    def deserialize(self, data: bytes | memoryview, msgtype: str) -> Any:
        return self._store.deserialize_cdr(data, msgtype)


class McapLogSource(LogSource):
    """An MCAP file of ROS 2 ``cdr`` messages, read as sensor frames."""

    format_name = "MCAP (ROS 2 messages, cdr)"

    @classmethod
    def accepts(cls, path: Path) -> bool:
        if not path.is_file():
            return False
        if path.suffix == ".mcap":
            return True
        with open(path, "rb") as f:
            return f.read(len(MAGIC)) == MAGIC

    def __init__(self, path: str | Path, *, skip_corrupt: bool = False) -> None:
        super().__init__(path, skip_corrupt=skip_corrupt)
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._types = _CdrTypes()  # kept across readings: each type registered once
        # attachments and metadata, kept from the first pass over the file that met them
        self._extras: tuple[dict[str, bytes], dict[str, dict[str, str]]] | None = None
        try:
            size = self.path.stat().st_size
            with open(self.path, "rb") as f:
                head = f.read(len(MAGIC))
                f.seek(max(size - len(MAGIC), 0))
                tail = f.read(len(MAGIC))
        except OSError as exc:
            raise LogError(f"{self.path}: cannot read: {exc}") from exc
        if head != MAGIC:
            raise LogError(f"{self.path}: not an MCAP file (starts with {head!r})")
        self._size = size
        self._damaged: dict[str, str] = {}  # attachments and metadata left out: what -> why
        self._complete = size >= 2 * len(MAGIC) + _FOOTER_SIZE and tail == MAGIC
        if not self._complete:
            problem = f"ends without the MCAP footer after {size} bytes: truncated"
            if not skip_corrupt:
                self.fail(problem)
            self.stats.note(f"{self.path.name}: {problem}; reading what is there")

    # -------------------------------------------------------------- records
    def _records(self, fail: Callable[..., None]) -> Iterator[tuple[int, int, bytes]]:
        """(byte offset, opcode, body) of each top-level record up to the footer."""
        with open(self.path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            f.seek(len(MAGIC))
            while True:
                offset = f.tell()
                head = f.read(9)
                if len(head) < 9:
                    fail(f"ends at byte {offset} before the footer record: truncated")
                    return
                opcode, length = struct.unpack("<BQ", head)
                if length > size - offset - 9:
                    fail(
                        f"record {_opcode_name(opcode)} at byte {offset} claims {length} "
                        f"bytes but {size - offset - 9} remain: truncated or corrupt"
                    )
                    return
                yield offset, opcode, f.read(length)
                if opcode == Opcode.FOOTER:
                    return

    def _scan(self, fail: Callable[..., None]) -> Iterator[_ChunkMessages | Attachment | Metadata]:
        """Chunks (as their messages), loose messages, attachments and metadata, in file order.

        Schemas and channels are registered on the way. A chunk whose declared size is absurd
        is refused unread; a chunk whose bytes repeat an earlier chunk's (the same record
        twice) is a defect, left out whole when skipping. A damaged chunk's lost messages are
        counted from the message indexes after it. An attachment whose CRC does not match, or
        a damaged attachment or metadata record, is left out and named in
        :meth:`damaged_extras` (never fatal: they only serve scoring).
        """
        limit = chunk_size_limit(self._size)
        seen: dict[tuple[int, ...], int] = {}  # chunk fingerprint -> offset of its first copy
        failed: list[tuple[str, str, int]] = []  # a damaged chunk: problem, reason, messages

        def flush_failed() -> None:
            while failed:
                problem, reason, lost = failed.pop()
                fail(problem, reason=reason, lost=lost)

        for offset, opcode, body in self._records(fail):
            if opcode == Opcode.MESSAGE_INDEX and failed:
                failed[-1] = (failed[-1][0], failed[-1][1], failed[-1][2] + _index_count(body))
                continue
            flush_failed()
            stream = ReadDataStream(io.BytesIO(body))
            try:
                if opcode == Opcode.CHUNK:
                    size_problem = _chunk_size_problem(body, limit)
                    if size_problem is not None:
                        problem = f"record CHUNK at byte {offset} {size_problem}: corrupt"
                        failed.append((problem, "oversized chunk", 0))
                        continue
                    parsed = _chunk_records(body)
                    if parsed is None:  # unusual or damaged: the library's reading says what
                        parsed = _chunk_records_reference(stream)
                    start_t_ns, records = parsed
                    messages = [r for r in records if self._register(r)]
                    first = seen.setdefault(_chunk_fingerprint(body), offset)
                    if first != offset:
                        problem = self._repeat(offset, first, messages)
                        fail(problem, reason="duplicated chunk", lost=len(messages))
                        continue
                    yield _ChunkMessages(start_t_ns, messages)
                elif opcode == Opcode.MESSAGE:
                    message = Message.read(stream, len(body))
                    yield _ChunkMessages(message.log_time, [message])
                elif opcode == Opcode.SCHEMA:
                    self._register(Schema.read(stream))
                elif opcode == Opcode.CHANNEL:
                    self._register(Channel.read(stream))
                elif opcode in (Opcode.ATTACHMENT, Opcode.METADATA):
                    item = self._extra(offset, opcode, body)
                    if item is not None:
                        yield item
            except LogError:  # a defect named already (fail above)
                raise
            except Exception as exc:  # damaged bytes surface as many library errors
                what = f"{type(exc).__name__}: {exc}"
                problem = f"record {_opcode_name(opcode)} at byte {offset} is corrupt: {what}"
                if opcode != Opcode.CHUNK:
                    fail(problem, reason="corrupt record", lost=int(opcode == Opcode.MESSAGE))
                else:
                    failed.append((problem, "corrupt chunk", 0))
        flush_failed()

    def _repeat(self, offset: int, first: int, messages: list[Message]) -> str:
        topics = sorted({self._topic(m.channel_id) for m in messages})
        times = [m.log_time for m in messages] or [0]
        return (
            f"record CHUNK at byte {offset} repeats the chunk at byte {first} (duplicated: "
            f"{len(messages)} messages on {', '.join(topics)}, log times "
            f"{min(times)}..{max(times)} ns, again)"
        )

    def _topic(self, channel_id: int) -> str:
        channel = self._channels.get(channel_id)
        return channel.topic if channel is not None else f"channel {channel_id}"

    def _extra(self, offset: int, opcode: int, body: bytes) -> Attachment | Metadata | None:
        """An attachment (its CRC checked) or metadata record; None, named in
        :meth:`damaged_extras` and noted, when it is damaged."""
        where = f"{_opcode_name(opcode)} at byte {offset}"
        try:
            if opcode == Opcode.METADATA:
                return Metadata.read(ReadDataStream(io.BytesIO(body)))
            item = Attachment.read(ReadDataStream(io.BytesIO(body)))
            where = f"attachment {item.name!r} at byte {offset}"
            if len(body) < 4:
                raise ValueError("no CRC")
            (stored,) = struct.unpack_from("<I", body, len(body) - 4)
            computed = crc32(memoryview(body)[:-4])
            if stored != 0 and stored != computed:  # 0: written without a CRC
                raise ValueError(f"CRC mismatch (stored {stored:#010x}, data {computed:#010x})")
            return item
        except Exception as exc:
            problem = f"{where} is damaged: {exc}"
            key = where.split(" at byte")[0]
            if self._damaged.get(key) != problem:
                self._damaged[key] = problem
                self.stats.note(f"{self.path.name}: left out: {problem}")
            return None

    def damaged_extras(self) -> dict[str, str]:
        """Attachments and metadata left out as damaged: ``{"attachment 'terrain.npy'":
        why}`` (read with the attachments; metadata keyed ``METADATA`` as its name is in the
        damaged bytes)."""
        self._attachments_and_metadata()
        return dict(self._damaged)

    def _register(self, record: object) -> bool:
        """Keep schemas and channels; True for a message record."""
        if isinstance(record, Schema):
            self._schemas[record.id] = record
        elif isinstance(record, Channel):
            self._channels[record.id] = record
        return isinstance(record, Message)

    def _quiet_fail(self, problem: str, **counts: Any) -> None:
        if not self.skip_corrupt:
            self.fail(problem, **counts)

    def _messages(self) -> Iterator[Message]:
        """Messages in log-time order (ties in file order), merging chunks as they come.

        A message that repeats one of the latest on its channel (the same log and publish
        time, sequence number, length and bytes: a duplicated record) is a defect."""
        heap: list[tuple[int, int, Message]] = []
        seq = 0
        recent: dict[int, dict[tuple[int, ...], None]] = {}
        for item in self._scan(self.fail):
            if not isinstance(item, _ChunkMessages):
                continue
            while heap and heap[0][0] <= item.start_t_ns:
                message = heapq.heappop(heap)[2]
                if self._first_time(message, recent):
                    yield message
            for message in item.messages:
                heapq.heappush(heap, (message.log_time, seq, message))
                seq += 1
        while heap:
            message = heapq.heappop(heap)[2]
            if self._first_time(message, recent):
                yield message

    def _first_time(self, m: Message, recent: dict[int, dict[tuple[int, ...], None]]) -> bool:
        """False (after :meth:`fail`) for a repeat of one of its channel's latest messages."""
        key = (m.log_time, m.publish_time, m.sequence, len(m.data), _ends_crc(m.data))
        latest = recent.setdefault(m.channel_id, {})
        if key in latest:
            self.fail(
                f"{self._topic(m.channel_id)} message at log time {m.log_time} ns (sequence "
                f"{m.sequence}) repeats an earlier one: duplicated",
                reason="duplicated message",
                lost=1,
            )
            return False
        latest[key] = None
        if len(latest) > _RECENT_MESSAGES:
            del latest[next(iter(latest))]
        return True

    # -------------------------------------------------------------- decoding
    def _msgtype(self, channel: Channel) -> str:
        schema = self._schemas.get(channel.schema_id)
        return schema.name if schema is not None else ""

    def _deserialize(self, decoder: CdrFrameDecoder, channel: Channel, message: Message) -> Any:
        schema = self._schemas.get(channel.schema_id)
        if schema is None or channel.message_encoding != "cdr":
            raise ValueError(
                f"{channel.topic}: message encoding {channel.message_encoding!r} "
                f"with schema {schema.name if schema else None!r} is not ROS 2 cdr"
            )
        if not self._types.knows(schema.name):
            decoder.register(schema.name, schema.data.decode(), schema.encoding)
        return decoder.decode(schema.name, message.data)

    def _frames(
        self, kinds: tuple[type, ...] | None, topics: frozenset[str] | None
    ) -> Iterator[LogMessage]:
        decoder = CdrFrameDecoder(self.stats, kinds, topics, self.fail, self._types)
        roles: dict[int, Any] = {}
        for message in self._messages():
            channel = self._channels.get(message.channel_id)
            if channel is None:
                self.fail(
                    f"message at log time {message.log_time} has unknown channel",
                    reason="unknown channel",
                    lost=1,
                )
                continue
            if channel.id not in roles:
                kind = channel.metadata.get(KIND_KEY)
                roles[channel.id] = decoder.role(channel.topic, self._msgtype(channel), kind)
            role = roles[channel.id]
            if role is None:
                continue
            try:
                msg = self._deserialize(decoder, channel, message)
            except Exception as exc:  # rosbags raises several types for bad bytes
                self.fail(
                    f"{channel.topic} message at log time {message.log_time} cannot be "
                    f"decoded as {self._msgtype(channel)}: {exc}",
                    reason="undecodable message",
                    lost=1,
                )
                continue
            yield from decoder.push(channel.topic, role, msg, message.log_time)
        yield from decoder.flush()

    # -------------------------------------------------------------- the rest of the interface
    def _topics(self) -> list[TopicInfo]:
        times: dict[int, list[int]] = {}
        attachments: dict[str, bytes] = {}
        metadata: dict[str, dict[str, str]] = {}
        for item in self._scan(self.fail):  # info() runs once: its problems count in stats
            if isinstance(item, _ChunkMessages):
                for m in item.messages:
                    times.setdefault(m.channel_id, []).append(m.log_time)
            elif isinstance(item, Attachment):
                attachments[item.name] = item.data
            elif isinstance(item, Metadata):
                metadata[item.name] = dict(item.metadata)
        self._extras = attachments, metadata  # the same pass: no second read of the file
        by_topic: dict[tuple[str, str], list[int]] = {}
        for cid, channel in self._channels.items():
            key = (channel.topic, self._msgtype(channel))
            by_topic.setdefault(key, []).extend(times.get(cid, []))
        return [topic_info(topic, msgtype, t) for (topic, msgtype), t in by_topic.items()]

    def frame_topics(self) -> set[str]:
        return frame_topics_of((t.name, t.msgtype) for t in self.info().topics)

    def attachments(self) -> dict[str, bytes]:
        return dict(self._attachments_and_metadata()[0])

    def metadata(self) -> dict[str, dict[str, str]]:
        return {k: dict(v) for k, v in self._attachments_and_metadata()[1].items()}

    def _attachments_and_metadata(
        self,
    ) -> tuple[dict[str, bytes], dict[str, dict[str, str]]]:
        """Both from one pass over the file (or the one :meth:`info` made), kept."""
        if self._extras is None:
            attachments: dict[str, bytes] = {}
            metadata: dict[str, dict[str, str]] = {}
            for item in self._scan(self._quiet_fail):
                if isinstance(item, Attachment):
                    attachments[item.name] = item.data
                elif isinstance(item, Metadata):
                    metadata[item.name] = dict(item.metadata)
            self._extras = attachments, metadata
        return self._extras

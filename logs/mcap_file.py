"""The MCAP container, written with as few copies of the message bytes as possible.

The ``mcap`` library's Writer copies every message three or four times on its way to the file
(into a chunk buffer, out of it, into a record buffer, out of that). For logs of point clouds
and images that dominates the cost of logging, so this writer streams an uncompressed chunk:
each message's parts (which may include a frame's own image array) go straight to the file,
the chunk CRC is computed over them on the way, and the chunk's header, written as a
placeholder, is filled in when the chunk closes. Compressed chunks are gathered and go
through one compression pass. Small records (header, schemas, channels, indexes, summary,
footer) are serialised by the ``mcap`` library's record classes, so the layout is the
library's (MCAP spec v0: chunked, with message indexes, chunk indexes, statistics and summary
offsets); the tests read our files with the ``mcap`` reader (CRCs validated) and ``rosbags``.
"""

from __future__ import annotations

import struct
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import BinaryIO

from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

try:  # ISA-L's SIMD CRC-32 gives zlib's values (same polynomial), faster
    from isal.isal_zlib import crc32
except ImportError:  # pragma: no cover - isal is a declared dependency
    from zlib import crc32

MAGIC = b"\x89MCAP0\r\n"
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")  # opcode, length, channel, sequence, log, publish time
_MESSAGE_FIELDS = 2 + 4 + 8 + 8


def _record_bytes(*records: McapRecord) -> bytes:
    builder = RecordBuilder()
    for r in records:
        r.write(builder)
    return builder.end()


@dataclass(slots=True)
class _Chunk:
    """The chunk being written: CRC so far, per-channel message index, time span, and either
    its file offset (streamed, uncompressed) or its parts (compressed at the end)."""

    n_messages: int = 0
    size: int = 0  # uncompressed bytes of its records
    crc: int = 0
    start_t_ns: int = 0
    end_t_ns: int = 0
    file_offset: int = 0
    parts: list[bytes] = field(default_factory=list)  # compressed chunks only
    index: dict[int, list[tuple[int, int]]] = field(default_factory=lambda: defaultdict(list))


_CHUNK_FIELDS = struct.Struct("<BQQQQIIQ")  # opcode, length, start, end, size, crc, "", length


class McapFileWriter:
    """Writes an MCAP file to an open, seekable binary stream (which the caller closes).

    ``compression`` is "" (none), "lz4" or "zstd"; ``chunk_size`` is the uncompressed size at
    which a chunk is closed. Uncompressed chunks are streamed: each message goes to the file
    as it is added (its bytes are not kept) and the chunk's header is filled in when the chunk
    closes. Compressed chunks keep a copy of their messages until they are compressed.
    """

    def __init__(
        self, stream: BinaryIO, *, compression: str, chunk_size: int, profile: str, library: str
    ) -> None:
        if compression not in ("", "lz4", "zstd"):
            raise ValueError(f"MCAP compression {compression!r} is not one of '', lz4, zstd")
        self._f = stream
        self._compression = compression
        self._chunk_size = chunk_size
        self._offset = 0
        self._schemas: list[Schema] = []
        self._channels: list[Channel] = []
        self._chunk_indexes: list[ChunkIndex] = []
        self._attachment_indexes: list[AttachmentIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._counts: dict[int, int] = defaultdict(int)
        self._t_span: list[int] = []  # [first, last] log time over the file
        self._chunk = _Chunk()
        self._write(MAGIC)
        self._write(_record_bytes(Header(profile=profile, library=library)))

    def _write(self, data: bytes | memoryview) -> None:
        self._f.write(data)
        self._offset += len(data)

    def add_schema(self, name: str, encoding: str, data: bytes) -> int:
        self._close_chunk()  # top-level records go between chunks
        schema = Schema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=data)
        self._schemas.append(schema)
        self._write(_record_bytes(schema))
        return schema.id

    def add_channel(
        self, topic: str, message_encoding: str, schema_id: int, metadata: dict[str, str]
    ) -> int:
        self._close_chunk()
        channel = Channel(
            id=len(self._channels) + 1,
            topic=topic,
            message_encoding=message_encoding,
            schema_id=schema_id,
            metadata=metadata,
        )
        self._channels.append(channel)
        self._write(_record_bytes(channel))
        return channel.id

    def add_message(
        self,
        channel_id: int,
        log_time: int,
        publish_time: int,
        sequence: int,
        parts: Sequence[bytes | memoryview],
    ) -> None:
        """Add one message whose serialised bytes are ``parts`` joined (any byte buffers).

        Uncompressed, the parts are written before this returns; compressed, they are copied.
        """
        c = self._chunk
        size = sum(len(p) for p in parts)
        head = _MESSAGE_HEAD.pack(
            Opcode.MESSAGE, _MESSAGE_FIELDS + size, channel_id, sequence, log_time, publish_time
        )
        if c.n_messages == 0:
            c.start_t_ns = c.end_t_ns = log_time
            c.file_offset = self._offset
            if not self._compression:
                self._write(bytes(_CHUNK_FIELDS.size))  # filled in by _close_chunk
        c.start_t_ns, c.end_t_ns = min(c.start_t_ns, log_time), max(c.end_t_ns, log_time)
        c.index[channel_id].append((log_time, c.size))
        for part in (head, *parts):
            c.crc = crc32(part, c.crc)
            if self._compression:
                c.parts.append(bytes(part))
            else:
                self._write(part)
        c.size += len(head) + size
        c.n_messages += 1
        self._counts[channel_id] += 1
        span = self._t_span or [log_time, log_time]
        self._t_span = [min(span[0], log_time), max(span[1], log_time)]
        if c.size >= self._chunk_size:
            self._close_chunk()

    def _compress(self, raw: bytes) -> bytes:
        if self._compression == "lz4":
            import lz4.frame

            return lz4.frame.compress(raw)
        import zstandard

        return zstandard.ZstdCompressor().compress(raw)

    def _chunk_head(self, c: _Chunk, body_size: int) -> bytes:
        comp = self._compression.encode()
        fields = struct.pack("<QQQI", c.start_t_ns, c.end_t_ns, c.size, c.crc)
        fields += struct.pack("<I", len(comp)) + comp + struct.pack("<Q", body_size)
        return struct.pack("<BQ", Opcode.CHUNK, len(fields) + body_size) + fields

    def _close_chunk(self) -> None:
        c = self._chunk
        if c.n_messages == 0:
            return
        if self._compression:
            body = self._compress(b"".join(c.parts))
            self._write(self._chunk_head(c, len(body)))
            self._write(body)
            body_size = len(body)
        else:  # streamed: fill in the header written as zeros
            end, body_size = self._offset, c.size
            self._f.seek(c.file_offset)
            self._f.write(self._chunk_head(c, body_size))
            self._f.seek(end)
        chunk_length = self._offset - c.file_offset
        index_start = self._offset
        offsets = {}
        for channel_id, records in c.index.items():
            offsets[channel_id] = self._offset
            self._write(_record_bytes(MessageIndex(channel_id=channel_id, records=records)))
        self._chunk_indexes.append(
            ChunkIndex(
                message_start_time=c.start_t_ns,
                message_end_time=c.end_t_ns,
                chunk_start_offset=c.file_offset,
                chunk_length=chunk_length,
                message_index_offsets=offsets,
                message_index_length=self._offset - index_start,
                compression=self._compression,
                compressed_size=body_size,
                uncompressed_size=c.size,
            )
        )
        self._chunk = _Chunk()

    def add_attachment(self, name: str, media_type: str, data: bytes, log_time: int) -> None:
        self._close_chunk()
        record = Attachment(
            create_time=log_time, log_time=log_time, name=name, media_type=media_type, data=data
        )
        offset, raw = self._offset, _record_bytes(record)
        self._write(raw)
        self._attachment_indexes.append(
            AttachmentIndex(
                offset=offset,
                length=len(raw),
                create_time=log_time,
                log_time=log_time,
                data_size=len(data),
                name=name,
                media_type=media_type,
            )
        )

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._close_chunk()
        offset, raw = self._offset, _record_bytes(Metadata(name=name, metadata=data))
        self._write(raw)
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=len(raw), name=name))

    def finish(self) -> None:
        """Write the last chunk, the data end, the summary section and the footer."""
        self._close_chunk()
        self._write(_record_bytes(DataEnd(data_section_crc=0)))
        first, last = self._t_span or [0, 0]
        statistics = Statistics(
            message_count=sum(self._counts.values()),
            schema_count=len(self._schemas),
            channel_count=len(self._channels),
            attachment_count=len(self._attachment_indexes),
            metadata_count=len(self._metadata_indexes),
            chunk_count=len(self._chunk_indexes),
            message_start_time=first,
            message_end_time=last,
            channel_message_counts=dict(self._counts),
        )
        groups = [
            (Opcode.SCHEMA, self._schemas),
            (Opcode.CHANNEL, self._channels),
            (Opcode.STATISTICS, [statistics]),
            (Opcode.CHUNK_INDEX, self._chunk_indexes),
            (Opcode.ATTACHMENT_INDEX, self._attachment_indexes),
            (Opcode.METADATA_INDEX, self._metadata_indexes),
        ]
        summary_start = self._offset
        summary = b""
        offsets = []
        for opcode, records in groups:
            raw = _record_bytes(*records)
            offsets.append(
                SummaryOffset(
                    group_opcode=opcode,
                    group_start=summary_start + len(summary),
                    group_length=len(raw),
                )
            )
            summary += raw
        summary_offset_start = summary_start + len(summary)
        summary += _record_bytes(*offsets)
        footer_head = struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, summary_offset_start)
        crc = crc32(footer_head, crc32(summary))
        self._write(summary)
        footer = Footer(
            summary_start=summary_start, summary_offset_start=summary_offset_start, summary_crc=crc
        )
        self._write(_record_bytes(footer))
        self._write(MAGIC)

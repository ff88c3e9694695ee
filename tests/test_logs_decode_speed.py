"""The fast MCAP decoding path gives exactly the frames, stats and errors of the reference path.

Each piece replaced for speed kept its old form as ``*_reference``: the ``mcap`` library's
chunk reading (:func:`logs.mcap_log._chunk_records_reference`, also the engine's fallback),
rosbags' own typestore, and the test oracles ``decode_pointcloud2_reference`` and
``boxes_reference`` (``tests/kernel_reference/ros_decode_reference.py``). These tests read the
same logs both ways (fresh logs from the project's writer and from the ``mcap`` library's,
uncompressed and compressed, intact and damaged) and compare every array bit for bit, with its
dtype and shape, and every stat and error message; and decode PointCloud2 layouts the writer
never makes both ways.
"""

from __future__ import annotations

import dataclasses
import io
import struct
import zlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from kernel_reference.ros_decode_reference import boxes_reference, decode_pointcloud2_reference
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Message, Schema
from mcap.writer import CompressionType, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from core.geometry import GeometryError
from logs import (
    CameraFrame,
    Compression,
    GroundTruthPose,
    ImuFrame,
    LadarScan,
    LogError,
    McapLogWriter,
    McapWriterConfig,
    ObjectBoxes,
    OdometryFrame,
    ReadStats,
    TransformFrame,
    mcap_log,
    open_log,
    ros_decode,
)
from logs.ros_encode import encode_frame, serialize
from logs.ros_types import ros2msg_schema, typestore

PC2 = "sensor_msgs/msg/PointCloud2"
KINDS = (LadarScan, CameraFrame, OdometryFrame, GroundTruthPose, ImuFrame, TransformFrame)


# ------------------------------------------------------------------------------ helpers


@contextmanager
def reference_paths() -> Iterator[None]:
    """Every fast piece of MCAP decoding swapped for its reference, inside the block."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(mcap_log, "_chunk_records", lambda body: None)
        mp.setattr(mcap_log, "_reading_typestore", lambda: get_typestore(Stores.EMPTY))
        mp.setattr(ros_decode, "decode_pointcloud2", decode_pointcloud2_reference)
        mp.setattr(ros_decode.FrameAssembler, "_boxes", boxes_reference)
        yield


def read_log(path: Path, skip_corrupt: bool = False) -> tuple[Any, ...]:
    """("frames", frames, stats) of reading the whole log, or ("error", type, message)."""
    try:
        src = open_log(path, skip_corrupt=skip_corrupt)
        frames = list(src.frames())
    except Exception as exc:
        return "error", type(exc), str(exc)
    return "frames", frames, src.stats


def read_both(path: Path, skip_corrupt: bool = False) -> tuple[tuple[Any, ...], tuple[Any, ...]]:
    fast = read_log(path, skip_corrupt)
    with reference_paths():
        ref = read_log(path, skip_corrupt)
    return fast, ref


def assert_same(a: Any, b: Any, where: str = "") -> None:
    """Equal values: arrays bit for bit with dtype and shape; dataclasses field by field (by
    type name: two typestores make two classes of each message type)."""
    if dataclasses.is_dataclass(a):
        assert type(a).__qualname__ == type(b).__qualname__, f"{where}: {type(a)} != {type(b)}"
    else:
        assert type(a) is type(b), f"{where}: {type(a)} != {type(b)}"
    if isinstance(a, np.ndarray):
        assert a.dtype == b.dtype, f"{where}: dtype {a.dtype} != {b.dtype}"
        assert a.shape == b.shape, f"{where}: shape {a.shape} != {b.shape}"
        assert a.tobytes() == b.tobytes(), f"{where}: values differ"
    elif dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), f"{where}: {len(a)} items != {len(b)}"
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, float) and np.isnan(a):
        assert np.isnan(b), f"{where}: nan != {b}"
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


def assert_outcomes_same(fast: tuple[Any, ...], ref: tuple[Any, ...]) -> None:
    assert fast[0] == ref[0], (fast, ref)
    if fast[0] == "error":
        assert fast[1:] == ref[1:]
    else:
        assert_same(fast[1], ref[1], "frames")
        assert fast[2] == ref[2]  # ReadStats: counts and notes


def assert_owns_memory(frames: list[Any]) -> None:
    """No frame array is a read-only view into the log's bytes (the fast path's memoryviews)."""
    for frame in frames:
        for f in dataclasses.fields(frame):
            v = getattr(frame, f.name)
            if isinstance(v, np.ndarray):
                assert v.flags.writeable, f"{type(frame).__name__}.{f.name} is read-only"


def _rot(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    x, y, z, w = q / np.linalg.norm(q)
    T = np.eye(4)
    T[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    T[:3, 3] = rng.normal(0, 50, 3)
    return T


def make_frames(seed: int = 3, n_instants: int = 12) -> list[Any]:
    """Every kind of frame, in time order: scans with non-finite points (and an empty one),
    images with depth, odometry, truth, IMU, transforms and boxes (and an empty box set)."""
    rng = np.random.default_rng(seed)
    frames: list[Any] = [
        TransformFrame(0, "base_link", "ladar", _rot(rng), static=True),
        TransformFrame(0, "base_link", "camera", _rot(rng), static=True),
    ]
    for k in range(n_instants):
        t = (k + 1) * 100_000_000
        n = 0 if k == 5 else int(rng.integers(500, 3000))
        xyz = rng.normal(0, 20, (n, 3)).astype(np.float32)
        if n:
            bad = rng.choice(n, 9, replace=False)
            xyz[bad[:3], 0] = np.nan
            xyz[bad[3:6], rng.integers(0, 3, 3)] = np.inf
            xyz[bad[6:], 2] = -np.inf
        frames.append(
            LadarScan(
                t_ns=t,
                frame_id="ladar",
                points_xyz=xyz,
                intensity=rng.random(n).astype(np.float32),
                t_offset_ns=np.sort(rng.integers(0, 100_000_000, n)),
                ring=None if k == 7 else rng.integers(0, 64, n).astype(np.uint16),
            )
        )
        K = np.array([[200.0 + k, 0, 64], [0, 201.0, 48], [0, 0, 1]])
        image = rng.integers(0, 256, (96, 128), dtype=np.uint8)
        depth = rng.uniform(0.5, 80, (96, 128)).astype(np.float32)
        depth[rng.random((96, 128)) < 0.05] = np.nan
        frames.append(CameraFrame(t, "camera", image, K, depth=depth, dist=rng.normal(0, 0.1, 5)))
        rgb = rng.integers(0, 256, (40, 50, 3), dtype=np.uint8)
        frames.append(CameraFrame(t, "camera2", rgb, K, topic="/camera2"))
        for j in range(3):
            cov = rng.normal(size=(6, 6))
            frames.append(
                OdometryFrame(
                    t + j * 33_000_000,
                    "odom",
                    "base_link",
                    _rot(rng),
                    rng.normal(size=3),
                    rng.normal(size=3),
                    cov @ cov.T,
                    np.diag(rng.random(6)),
                )
            )
        frames.append(GroundTruthPose(t, "world", "base_link", _rot(rng)))
        orientation = None if k % 2 else rng.normal(size=4)
        frames.append(ImuFrame(t, "imu", rng.normal(size=3), rng.normal(size=3), orientation))
        frames.append(TransformFrame(t, "odom", "base_link", _rot(rng)))
        m = 0 if k == 3 else int(rng.integers(1, 30))
        frames.append(
            ObjectBoxes(
                t_ns=t,
                frame_id="world",
                ids=rng.integers(0, 1000, m),
                classes=[str(c) for c in rng.choice(["vehicle", "person", "pole"], m)],
                centers=rng.normal(0, 30, (m, 3)),
                sizes=rng.uniform(0.3, 5, (m, 3)),
                yaws=rng.uniform(-np.pi, np.pi, m),
                velocities=rng.normal(0, 3, (m, 3)),
            )
        )
    frames.sort(key=lambda f: f.t_ns)
    return frames


def write_log(path: Path, compression: Compression = Compression.NONE) -> Path:
    config = McapWriterConfig(compression=compression, chunk_size_bytes=96 * 1024)
    with McapLogWriter(path, config) as w:
        for frame in make_frames():
            w.write(frame)
    return path


def write_library_log(path: Path, compression: CompressionType) -> Path:
    """A log from the ``mcap`` library's writer, which puts schemas and channels in chunks."""
    with open(path, "wb") as f:
        w = Writer(f, compression=compression, chunk_size=64 * 1024)
        w.start(profile="ros2")
        channels: dict[tuple[str, str], int] = {}
        for frame in make_frames(seed=8, n_instants=6):
            for enc in encode_frame(frame):
                key = (enc.topic, enc.msgtype)
                if key not in channels:
                    sid = w.register_schema(enc.msgtype, "ros2msg", ros2msg_schema(enc.msgtype))
                    channels[key] = w.register_channel(enc.topic, "cdr", sid, {"kind": enc.kind})
                t = int(frame.t_ns)
                w.add_message(channels[key], t, serialize(enc), t)
        w.finish()
    return path


def top_records(data: bytes) -> list[tuple[int, int, bytes]]:
    """(offset, opcode, body) of each top-level record of an MCAP file's bytes."""
    pos, records = len(mcap_log.MAGIC), []
    while pos + 9 <= len(data):
        opcode, length = struct.unpack_from("<BQ", data, pos)
        records.append((pos, opcode, data[pos + 9 : pos + 9 + length]))
        if opcode == Opcode.FOOTER:
            break
        pos += 9 + length
    return records


def chunk_bodies(path: Path) -> list[bytes]:
    """The body of each top-level chunk record of an MCAP file."""
    return [body for _, opcode, body in top_records(path.read_bytes()) if opcode == Opcode.CHUNK]


def reference_chunk(body: bytes) -> tuple[Any, ...]:
    """("records", start, records) of the library's reading of a chunk, or ("error", ...)."""
    try:
        start, records = mcap_log._chunk_records_reference(ReadDataStream(io.BytesIO(body)))
    except Exception as exc:
        return "error", type(exc), str(exc)
    return "records", start, records


def assert_records_same(fast: list[Any], ref: list[Any]) -> None:
    assert [type(r) for r in fast] == [type(r) for r in ref]
    for a, b in zip(fast, ref, strict=True):
        for f in dataclasses.fields(a):
            x, y = getattr(a, f.name), getattr(b, f.name)
            if isinstance(x, memoryview):
                x = bytes(x)
            assert x == y, f"{type(a).__name__}.{f.name}"


# ------------------------------------------------------------------------------ whole logs


@pytest.fixture(scope="module")
def good_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_log(tmp_path_factory.mktemp("decode") / "good.mcap")


@pytest.mark.parametrize("compression", list(Compression))
def test_frames_equal_the_reference_path(tmp_path: Path, compression: Compression) -> None:
    path = write_log(tmp_path / f"log_{compression.value}.mcap", compression)
    fast, ref = read_both(path)
    assert fast[0] == "frames", fast
    frames, stats = fast[1], fast[2]
    assert {type(f) for f in frames} >= {*KINDS, ObjectBoxes}
    assert sum(isinstance(f, LadarScan) and f.n_points == 0 for f in frames) == 1
    assert stats.dropped_nonfinite_points == 9 * 11  # 9 in each non-empty scan
    assert_outcomes_same(fast, ref)
    assert_owns_memory(frames)


@pytest.mark.parametrize("compression", list(Compression))
def test_the_fast_chunk_reading_reads_our_chunks(
    good_log: Path, tmp_path: Path, monkeypatch, compression: Compression
) -> None:
    """The comparisons are not vacuous: no chunk of ours, compressed or not, is left to the
    library's reading."""
    path = good_log
    if compression is not Compression.NONE:
        path = write_log(tmp_path / "compressed.mcap", compression)
    assert len(chunk_bodies(path)) >= 4
    used: list[int] = []
    monkeypatch.setattr(
        mcap_log, "_chunk_records_reference", lambda stream: used.append(1) or (0, [])
    )
    fast = read_log(path)
    assert fast[0] == "frames" and not used
    assert len(fast[1]) == len(make_frames())


@pytest.mark.parametrize("compression", [CompressionType.NONE, CompressionType.ZSTD])
def test_chunks_with_schemas_and_channels_inside(tmp_path: Path, compression) -> None:
    path = write_library_log(tmp_path / "library.mcap", compression)
    bodies = chunk_bodies(path)
    assert len(bodies) >= 3
    n_schemas = 0
    for body in bodies:
        parsed = mcap_log._chunk_records(body)
        assert parsed is not None  # well-formed: read by the fast path
        ref = reference_chunk(body)
        assert ref[0] == "records" and parsed[0] == ref[1]
        assert_records_same(parsed[1], ref[2])
        n_schemas += sum(isinstance(r, Schema) for r in parsed[1])
    assert n_schemas >= 7  # the schemas are inside the chunks, and were read there
    fast, ref = read_both(path)
    assert fast[0] == "frames" and len(fast[1]) > 50
    assert_outcomes_same(fast, ref)


def test_damaged_logs_fail_and_skip_the_same_way(good_log: Path, tmp_path: Path) -> None:
    data = good_log.read_bytes()
    size = len(data)
    cases: dict[str, bytes] = {}
    for frac in (0.05, 0.2, 0.37, 0.5, 0.66, 0.81, 0.97):
        flipped = bytearray(data)
        at = int(size * frac)
        flipped[at : at + 16] = bytes(b ^ 0x5A for b in flipped[at : at + 16])
        cases[f"flip{frac}"] = bytes(flipped)
        cases[f"cut{frac}"] = data[: int(size * frac)]
    chunks = [offset for offset, opcode, _ in top_records(data) if opcode == Opcode.CHUNK]
    for name, at in (  # a byte of the second chunk's record: its length, then its fields
        ("record length", 1),
        ("start time", 9),
        ("uncompressed size", 9 + 16),
        ("crc", 9 + 24),
        ("compression length", 9 + 28),
        ("data length", 9 + 32),
    ):
        edited = bytearray(data)
        edited[chunks[1] + at] ^= 0x01
        cases[name] = bytes(edited)
    read_anyway = set()
    for name, content in cases.items():
        path = tmp_path / f"{name}.mcap"
        path.write_bytes(content)
        fast, ref = read_both(path)
        assert_outcomes_same(fast, ref)
        if fast[0] == "error":
            assert fast[1] is LogError and path.name in fast[2]
        else:
            read_anyway.add(name)
        fast, ref = read_both(path, skip_corrupt=True)
        assert_outcomes_same(fast, ref)
    # fields the reading does not depend on (a chunk's start time only orders the merge, its
    # uncompressed size only sizes a decompression, and a data length one past the record is
    # read short by the library, as our writer's data runs to the record's end)
    assert read_anyway <= {"start time", "uncompressed size", "data length"}


# ------------------------------------------------------------------------------ chunks


def _record(opcode: int, body: bytes) -> bytes:
    return struct.pack("<BQ", opcode, len(body)) + body


def _message(channel: int, t: int, data: bytes) -> bytes:
    return _record(Opcode.MESSAGE, struct.pack("<HIQQ", channel, 0, t, t) + data)


def _chunk(records: bytes, crc: int | None = None, compression: bytes = b"") -> bytes:
    crc = zlib.crc32(records) if crc is None else crc
    head = struct.pack("<QQQII", 5, 9, len(records), crc, len(compression)) + compression
    return head + struct.pack("<Q", len(records)) + records


def _schema(sid: int, name: str, tail: bytes = b"") -> bytes:
    text = b"int32 a"
    enc = b"ros2msg"
    body = struct.pack("<H", sid) + struct.pack("<I", len(name)) + name.encode()
    body += struct.pack("<I", len(enc)) + enc + struct.pack("<I", len(text)) + text
    return _record(Opcode.SCHEMA, body + tail)


def _channel(cid: int) -> bytes:
    body = struct.pack("<HH", cid, 1) + struct.pack("<I", 2) + b"/a" + struct.pack("<I", 3)
    body += b"cdr" + struct.pack("<I", 0)
    return _record(Opcode.CHANNEL, body)


GOOD = _schema(1, "a/msg/A") + _channel(1) + _message(1, 7, b"\0\1\0\0abcd") + _message(1, 8, b"")
CHUNKS: dict[str, tuple[bytes, bool]] = {  # name: (chunk body, read by the fast path)
    "plain": (_chunk(GOOD), True),
    "no crc": (_chunk(GOOD, crc=0), True),
    "unknown record": (_chunk(GOOD + _record(0x7F, b"xyz") + _message(1, 9, b"q")), True),
    "empty": (_chunk(b""), True),
    "bad crc": (_chunk(GOOD, crc=12345), False),
    "short message": (_chunk(GOOD + _record(Opcode.MESSAGE, b"\1\0\0\0")), False),
    "record past end": (_chunk(GOOD + _message(1, 9, b"abc")[:-2]), False),
    "record head cut": (_chunk(GOOD + b"\5\1"), False),
    "schema longer": (_chunk(_schema(1, "a/msg/A", tail=b"??") + _message(1, 7, b"")), False),
    "unknown compression": (_chunk(GOOD, compression=b"brotli"), False),
    "bad compression name": (_chunk(GOOD, compression=b"\xff\xfe"), False),
    "data past end": (_chunk(GOOD)[:-5], False),
    "head cut": (_chunk(GOOD)[:20], False),
}


@pytest.mark.parametrize("name", list(CHUNKS))
def test_unusual_chunks_are_left_to_the_library(name: str) -> None:
    body, fast_reads_it = CHUNKS[name]
    parsed = mcap_log._chunk_records(body)
    ref = reference_chunk(body)
    assert (parsed is not None) == fast_reads_it
    if parsed is not None:
        assert ref[0] == "records" and parsed[0] == ref[1]
        assert_records_same(parsed[1], ref[2])
        assert sum(isinstance(r, Message) for r in parsed[1]) >= (name != "empty")
        assert sum(isinstance(r, Channel) for r in parsed[1]) == (name != "empty")


# ------------------------------------------------------------------------------ PointCloud2


def _cloud_msg(
    layout: list[tuple[str, str, int]],
    point_step: int,
    n: int,
    *,
    height: int = 1,
    row_pad: int = 0,
    big: bool = False,
    seed: int = 0,
    nonfinite: bool = False,
) -> Any:
    """A rosbags PointCloud2 of ``n`` points a row whose fields are ``(name, numpy type,
    offset)``, with random values; ``row_pad`` bytes after each row."""
    codes = {"i1": 1, "u1": 2, "i2": 3, "u2": 4, "i4": 5, "u4": 6, "f4": 7, "f8": 8}
    order = ">" if big else "<"
    rng = np.random.default_rng(seed)
    dtype = np.dtype(
        {
            "names": [name for name, _, _ in layout],
            "formats": [order + t for _, t, _ in layout],
            "offsets": [o for _, _, o in layout],
            "itemsize": point_step,
        }
    )
    cloud = np.zeros(n * height, dtype)
    for name, t, _ in layout:
        if t.startswith("f"):
            values = rng.normal(0, 30, n * height)
            if nonfinite and name in "xyz" and n:
                values[rng.choice(n * height, max(1, n // 10), replace=False)] = np.nan
                values[rng.integers(0, n * height)] = np.inf
        else:
            info = np.iinfo(t)
            values = rng.integers(info.min, info.max, n * height, endpoint=True)
        cloud[name] = values
    rows = np.zeros((height, n * point_step + row_pad), np.uint8)
    rows[:, : n * point_step] = cloud.view(np.uint8).reshape(height, n * point_step)
    # the padding is not zeros: it must not leak into any field
    rows[:, n * point_step :] = rng.integers(0, 256, (height, row_pad), dtype=np.uint8)
    types = typestore().types
    fields = [
        types["sensor_msgs/msg/PointField"](name=name, offset=o, datatype=codes[t], count=1)
        for name, t, o in layout
    ]
    header = types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=12, nanosec=345), frame_id="ladar"
    )
    return types[PC2](
        header=header,
        height=height,
        width=n,
        fields=fields,
        is_bigendian=big,
        point_step=point_step,
        row_step=n * point_step + row_pad,
        data=rows.reshape(-1),
        is_dense=not nonfinite,
    )


STANDARD = [("x", "f4", 0), ("y", "f4", 4), ("z", "f4", 8), ("intensity", "f4", 12)]
CLOUDS: dict[str, Callable[[], Any]] = {
    "ours": lambda: _cloud_msg([*STANDARD, ("t", "u4", 16), ("ring", "u2", 20)], 22, 1000),
    "padded points": lambda: _cloud_msg([*STANDARD, ("t", "u4", 20), ("ring", "u2", 28)], 32, 700),
    "ouster": lambda: _cloud_msg(
        [
            *STANDARD,
            ("t", "u4", 20),
            ("reflectivity", "u2", 24),
            ("ring", "u2", 26),
            ("ambient", "u2", 28),
            ("range", "u4", 32),
        ],
        48,
        900,
    ),
    "xyz after intensity": lambda: _cloud_msg(
        [("intensity", "f4", 0), ("x", "f4", 4), ("y", "f4", 8), ("z", "f4", 12)], 16, 500
    ),
    "fields listed out of order": lambda: _cloud_msg(
        [
            ("ring", "u2", 16),
            ("z", "f4", 8),
            ("x", "f4", 0),
            ("intensity", "f4", 12),
            ("y", "f4", 4),
        ],
        18,
        400,
    ),
    "xyz not adjacent": lambda: _cloud_msg(
        [("x", "f4", 0), ("intensity", "f4", 4), ("y", "f4", 8), ("z", "f4", 12)], 16, 400
    ),
    "xyz reversed": lambda: _cloud_msg([("z", "f4", 0), ("y", "f4", 4), ("x", "f4", 8)], 12, 300),
    "float64 xyz": lambda: _cloud_msg(
        [("x", "f8", 0), ("y", "f8", 8), ("z", "f8", 16), ("time", "f8", 24)], 32, 600
    ),
    "int16 xyz": lambda: _cloud_msg([("x", "i2", 0), ("y", "i2", 2), ("z", "i2", 4)], 6, 300),
    "mixed xyz types": lambda: _cloud_msg(
        [("x", "f8", 0), ("y", "f4", 8), ("z", "i4", 12), ("offset_time", "u4", 16)], 20, 300
    ),
    "uint32 xyz": lambda: _cloud_msg(
        [("x", "u4", 0), ("y", "u4", 4), ("z", "u4", 8), ("laser_number", "u1", 12)], 13, 300
    ),
    "big-endian": lambda: _cloud_msg(
        [*STANDARD, ("t", "u4", 16), ("ring", "u2", 20)], 22, 800, big=True
    ),
    "big-endian float64": lambda: _cloud_msg(
        [("x", "f8", 0), ("y", "f8", 8), ("z", "f8", 16)], 24, 200, big=True
    ),
    "padded rows": lambda: _cloud_msg([*STANDARD, ("t", "u4", 16)], 20, 128, height=4, row_pad=12),
    "rows without padding": lambda: _cloud_msg(STANDARD, 16, 64, height=8),
    "non-finite points": lambda: _cloud_msg(
        [*STANDARD, ("t", "u4", 16), ("ring", "u2", 20)], 22, 1000, nonfinite=True
    ),
    "non-finite float64 in padded rows": lambda: _cloud_msg(
        [("x", "f8", 0), ("y", "f8", 8), ("z", "f8", 16)],
        24,
        50,
        height=3,
        row_pad=5,
        nonfinite=True,
    ),
    "no points": lambda: _cloud_msg([*STANDARD, ("t", "u4", 16), ("ring", "u2", 20)], 22, 0),
    "no rows": lambda: _cloud_msg(STANDARD, 16, 10, height=0),
}


def _decode_both(msg: Any) -> tuple[tuple[Any, ...], tuple[Any, ...]]:
    out = []
    for decode in (ros_decode.decode_pointcloud2, decode_pointcloud2_reference):
        stats = ReadStats()
        try:
            out.append(("scan", decode(msg, "/ladar/points", stats), stats))
        except Exception as exc:
            out.append(("error", type(exc), str(exc)))
    return out[0], out[1]


@pytest.mark.parametrize("name", list(CLOUDS))
def test_pointcloud2_layouts_decode_as_the_reference(name: str) -> None:
    msg = CLOUDS[name]()
    fast, ref = _decode_both(msg)
    assert fast[0] == "scan", fast
    assert_outcomes_same(fast, ref)
    scan, stats = fast[1], fast[2]
    assert scan.points_xyz.shape == (msg.width * msg.height - stats.dropped_nonfinite_points, 3)
    assert (stats.dropped_nonfinite_points > 0) == ("non-finite" in name)
    for f in ("points_xyz", "intensity", "t_offset_ns", "ring"):
        a = getattr(scan, f)
        if a is not None:  # new arrays that own their bytes, not views of the message
            assert a.flags.writeable and a.flags.c_contiguous
            assert not np.shares_memory(a, msg.data)


def test_pointcloud2_through_cdr_in_both_byte_orders() -> None:
    """Deserialised by the reading typestore from memoryviews (as the log reader does) and
    decoded, against rosbags' typestore from bytes and the reference decoder."""
    schema = get_types_from_msg(ros2msg_schema(PC2).decode(), PC2)
    fast_store, ref_store = mcap_log._reading_typestore(), get_typestore(Stores.EMPTY)
    fast_store.register(schema)
    ref_store.register(schema)
    for name in ("ours", "big-endian", "padded rows", "non-finite points", "no points"):
        for little in (True, False):
            raw = bytes(typestore().serialize_cdr(CLOUDS[name](), PC2, little_endian=little))
            assert raw[1] == little
            fast_msg = fast_store.deserialize_cdr(memoryview(raw), PC2)
            ref_msg = ref_store.deserialize_cdr(raw, PC2)
            fast_stats, ref_stats = ReadStats(), ReadStats()
            fast = ros_decode.decode_pointcloud2(fast_msg, "/p", fast_stats)
            ref = decode_pointcloud2_reference(ref_msg, "/p", ref_stats)
            assert_outcomes_same(("scan", fast, fast_stats), ("scan", ref, ref_stats))


def _malformed(edit: Callable[[Any], None]) -> Any:
    msg = CLOUDS["ours"]()
    edit(msg)
    return msg


MALFORMED: dict[str, Callable[[], Any]] = {
    "no z": lambda: _malformed(lambda m: m.fields.pop(2)),
    "data too short": lambda: _malformed(lambda m: setattr(m, "data", m.data[:-30])),
    "row_step short of the points": lambda: _malformed(lambda m: setattr(m, "row_step", 2190)),
    "row_step not whole points": lambda: _malformed(lambda m: setattr(m, "row_step", 2191)),
    "point_step too small": lambda: _malformed(lambda m: setattr(m, "point_step", 20)),
    "unknown datatype": lambda: _malformed(lambda m: setattr(m.fields[3], "datatype", 9)),
    "field past the point": lambda: _malformed(lambda m: setattr(m.fields[5], "offset", 21)),
    "width past the data": lambda: _malformed(lambda m: setattr(m, "width", 2000)),
    "rows short of the data": lambda: _malformed(
        lambda m: (setattr(m, "height", 2), setattr(m, "width", 500))
    ),
}


@pytest.mark.parametrize("name", list(MALFORMED))
def test_malformed_pointcloud2_fail_as_the_reference(name: str) -> None:
    fast, ref = _decode_both(MALFORMED[name]())
    assert_outcomes_same(fast, ref)
    if name != "width past the data":  # (that one reads fewer points than it claims)
        assert fast[0] == "error", fast


# ------------------------------------------------------------------------------ poses, boxes


class _V:
    def __init__(self, **kw: float) -> None:
        self.__dict__.update(kw)


def _rotation_numpy(q: np.ndarray) -> np.ndarray:
    """The rotation of ``q`` in numpy scalars, as ``quat_to_matrix`` computed it before its
    Python-float form: ``q / np.linalg.norm(q)``, then the entries."""
    x, y, z, w = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def test_poses_are_the_numpy_matrices_bit_for_bit() -> None:
    rng = np.random.default_rng(4)
    for scale in (1e-5, 1e-2, 1.0, 7.0, 1e4, 1e140):
        for _ in range(400):
            q = rng.normal(size=4) * scale
            if rng.random() < 0.2:  # axis-aligned ones, with exact zeros
                q[rng.choice(4, 3, replace=False)] = 0.0
            o = _V(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))
            p = _V(**dict(zip("xyz", (float(v) for v in rng.normal(0, 100, 3)), strict=True)))
            T = ros_decode._T_of(p, o)
            assert_same(T[:3, :3], _rotation_numpy(q), "R")
            assert_same(T[:3, 3], np.array([p.x, p.y, p.z]), "t")
            assert_same(T[3], np.array([0.0, 0.0, 0.0, 1.0]), "last row")


@pytest.mark.parametrize(
    "q", [(0, 0, 0, 0), (np.nan, 0, 0, 1), (0, np.inf, 0, 1), (1e200, 0, 0, 1), (1e-13, 0, 0, 0)]
)
def test_poses_without_rotation_fail(q: tuple[float, ...]) -> None:
    o, p = _V(x=q[0], y=q[1], z=q[2], w=q[3]), _V(x=0.0, y=0.0, z=0.0)
    with pytest.raises(GeometryError, match=r"has no rotation"), np.errstate(over="ignore"):
        ros_decode._T_of(p, o)


def test_boxes_are_the_reference_boxes(good_log: Path) -> None:
    """String track ids get the same integer ids in the same order both ways."""
    src = open_log(good_log)
    boxes = [m for m in src._messages() if src._channels[m.channel_id].topic.endswith("objects")]
    assert len(boxes) == 12
    decoder = mcap_log.CdrFrameDecoder(src.stats, None, None, src.fail, src._types)
    msgs = [src._deserialize(decoder, src._channels[m.channel_id], m) for m in boxes]
    for d in msgs[1].detections:
        d.id = f"car-{d.id}"  # not integers: mapped to ids in order of first appearance
    fast, ref = ros_decode.FrameAssembler(ReadStats()), ros_decode.FrameAssembler(ReadStats())
    n = 0
    for msg in msgs:
        a = fast._boxes(msg, "/ground_truth/objects")
        b = boxes_reference(ref, msg, "/ground_truth/objects")
        assert_same(a, b, "boxes")
        n += len(a)
    assert n > 50 and fast._track_ids == ref._track_ids and len(fast._track_ids) > 0


# ------------------------------------------------------------------------------ typestore


def _messages_of(path: Path) -> list[tuple[str, bytes]]:
    src = open_log(path)
    out = []
    for m in src._messages():
        channel = src._channels[m.channel_id]
        out.append((src._schemas[channel.schema_id].name, bytes(m.data)))
    return out


def test_reading_typestore_deserialises_as_rosbags(good_log: Path) -> None:
    """Every message of the log, in both byte orders and cut short, against rosbags' store."""
    src = open_log(good_log)
    list(src._messages())  # registers the schemas and channels
    fast_store, ref_store = mcap_log._reading_typestore(), get_typestore(Stores.EMPTY)
    for schema in src._schemas.values():
        types = get_types_from_msg(schema.data.decode(), schema.name)
        fast_store.register(types)
        ref_store.register(types)
    messages = _messages_of(good_log)
    assert len({name for name, _ in messages}) == 8
    humble = typestore()
    errors = 0
    for i, (name, raw) in enumerate(messages):
        big = humble.serialize_cdr(ref_store.deserialize_cdr(raw, name), name, little_endian=False)
        variants = [raw, bytes(big)]
        if i % 7 == 0:
            variants += [raw[: len(raw) // 2], raw[:3], raw[: len(raw) - 9]]
        for data in variants:
            out = []
            for store, buf in ((fast_store, memoryview(data)), (ref_store, data)):
                try:
                    out.append(("msg", store.deserialize_cdr(buf, name)))
                except Exception as exc:
                    out.append(("error", type(exc), str(exc)))
            assert out[0][0] == out[1][0], (name, out)
            if out[0][0] == "msg":
                assert_same(out[0][1], out[1][1], name)
            else:
                assert out[0] == out[1]
                errors += 1
    assert errors > 10
    # what makes it fast: only deserialisers were made, none of rosbags' other converters
    made = list(fast_store.cache.values())
    assert len(made) >= 20
    assert not any(hasattr(msgdef, "serialize_cdr_le") for msgdef in made)

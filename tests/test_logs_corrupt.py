"""Bad input: truncated and damaged logs, non-finite points, times going backwards, missing
topics and paths that are no log. Every failure is a LogError naming the file."""

from __future__ import annotations

import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import CompressionType, Writer

from logs import (
    Compression,
    LadarScan,
    LogError,
    McapLogWriter,
    McapWriterConfig,
    OdometryFrame,
    open_log,
)
from logs.ros_encode import encode_frame, serialize
from logs.ros_types import ros2msg_schema
from wm.campaign import chunks as _chunks
from wm.campaign import duplicate_chunk as _duplicate_chunk

N_SCANS = 40


def _scan(k: int, rng: np.random.Generator, n: int = 1000) -> LadarScan:
    return LadarScan(
        t_ns=(k + 1) * 100_000_000,
        frame_id="ladar",
        points_xyz=rng.normal(0, 10, (n, 3)).astype(np.float32),
        intensity=rng.random(n).astype(np.float32),
        t_offset_ns=np.sort(rng.integers(0, 100_000_000, n)),
        ring=rng.integers(0, 16, n).astype(np.uint16),
    )


@pytest.fixture(scope="module")
def good_log(tmp_path_factory) -> Path:
    """40 scans of 1000 points (16 kB each) in chunks of ~64 kB, uncompressed."""
    rng = np.random.default_rng(11)
    path = tmp_path_factory.mktemp("corrupt") / "good.mcap"
    config = McapWriterConfig(compression=Compression.NONE, chunk_size_bytes=64 * 1024)
    with McapLogWriter(path, config) as w:
        for k in range(N_SCANS):
            w.write(_scan(k, rng))
    return path


def _copy(src: Path, dst: Path, edit) -> Path:
    data = bytearray(src.read_bytes())
    dst.write_bytes(bytes(edit(data)))
    return dst


def test_truncated_log_is_named_and_skippable(good_log, tmp_path) -> None:
    cut = _copy(good_log, tmp_path / "cut.mcap", lambda d: d[: len(d) // 2])
    with pytest.raises(LogError, match=r"cut\.mcap.*truncated"):
        list(open_log(cut).frames())
    src = open_log(cut, skip_corrupt=True)
    assert 0 < src.info().topic("/ladar/points").count < N_SCANS
    assert src.stats.skipped_records == 1
    scans = list(src.frames())  # a second pass over the same damage counts it once
    assert src.stats.skipped_records == 1
    src = open_log(cut, skip_corrupt=True)
    scans = list(src.frames())
    assert 0 < len(scans) < N_SCANS
    assert src.stats.skipped_records >= 1
    assert any("truncated" in m for m in src.stats.messages)
    assert [s.t_ns for s in scans] == [(k + 1) * 100_000_000 for k in range(len(scans))]


def test_flipped_bytes_are_named_and_skippable(good_log, tmp_path) -> None:
    def flip(d: bytearray) -> bytearray:
        middle = len(d) // 2
        for i in range(middle, middle + 64):
            d[i] ^= 0xFF
        return d

    bad = _copy(good_log, tmp_path / "flipped.mcap", flip)
    with pytest.raises(LogError, match=r"flipped\.mcap.*corrupt"):
        list(open_log(bad).frames())
    src = open_log(bad, skip_corrupt=True)
    scans = list(src.frames())
    assert src.stats.skipped_records >= 1
    assert 0 < len(scans) < N_SCANS
    assert len({s.t_ns for s in scans}) == len(scans)


def test_nonfinite_points_are_dropped_and_counted(tmp_path) -> None:
    rng = np.random.default_rng(5)
    scan = _scan(0, rng, n=500)
    bad = rng.choice(500, 37, replace=False)
    scan.points_xyz[bad[:20], rng.integers(0, 3, 20)] = np.nan
    scan.points_xyz[bad[20:], 0] = np.inf
    path = tmp_path / "nan.mcap"
    with McapLogWriter(path) as w:
        w.write(scan)
    src = open_log(path)
    (back,) = list(src.frames())
    keep = np.ones(500, bool)
    keep[bad] = False
    assert src.stats.dropped_nonfinite_points == 37
    np.testing.assert_array_equal(back.points_xyz, scan.points_xyz[keep])
    np.testing.assert_array_equal(back.ring, scan.ring[keep])
    np.testing.assert_array_equal(back.t_offset_ns, scan.t_offset_ns[keep])


def test_backwards_header_stamps_are_reported(tmp_path) -> None:
    """A log whose odometry stamps jump back twice while the log times advance."""
    stamps = [10, 20, 30, 25, 40, 35, 50]
    path = tmp_path / "jumps.mcap"
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.NONE)
        w.start(profile="ros2")
        sid = w.register_schema(
            "nav_msgs/msg/Odometry", "ros2msg", ros2msg_schema("nav_msgs/msg/Odometry")
        )
        cid = w.register_channel("/odom", "cdr", sid)
        for k, stamp in enumerate(stamps):
            frame = OdometryFrame(stamp * 10**6, "odom", "base_link", np.eye(4))
            (enc,) = encode_frame(frame)
            data = serialize(enc)
            w.add_message(cid, (k + 1) * 10**7, data, (k + 1) * 10**7)
        w.finish()
    src = open_log(path)
    times = [f.t_ns // 10**6 for f in src.frames()]
    assert times == stamps
    assert src.stats.backwards_timestamps == 2
    assert len(src.stats.messages) == 2 and "/odom" in src.stats.messages[0]


def test_missing_topics_are_named(good_log) -> None:
    src = open_log(good_log)
    src.require_topics(["/ladar/points"])
    with pytest.raises(LogError, match=r"missing topics \['/ladar'\]"):
        src.require_topics(["/ladar"])
    with pytest.raises(LogError, match=r"good\.mcap: missing topics \['/camera', '/odom'\]"):
        src.require_topics(["/ladar/points", "/camera", "/odom"])


def test_unsupported_paths_list_the_formats(tmp_path) -> None:
    text = tmp_path / "notes.txt"
    text.write_text("not a log")
    with pytest.raises(
        LogError, match=r"notes\.txt: not a supported log(.|\n)*KITTI(.|\n)*7-Scenes"
    ):
        open_log(text)
    with pytest.raises(LogError, match="no such file"):
        open_log(tmp_path / "absent.mcap")
    fake = tmp_path / "fake.mcap"
    fake.write_bytes(b"PK\x03\x04 a zip file, not an MCAP")
    with pytest.raises(LogError, match=r"fake\.mcap: not an MCAP file"):
        open_log(fake)
    empty_dir = tmp_path / "empty"
    empty_dir.mkdir()
    with pytest.raises(LogError, match="Supported formats"):
        open_log(empty_dir)


# ---------------------------------------------------------------- defects found by position


@pytest.mark.parametrize("at_end", [False, True])
def test_a_duplicated_chunk_is_a_named_defect_and_skipped_whole(good_log, tmp_path, at_end):
    data = bytearray(good_log.read_bytes())
    first = _chunks(bytes(data))[2][0]
    edited, copy_at, n = _duplicate_chunk(data, 2, at_end)
    bad = tmp_path / "dup.mcap"
    bad.write_bytes(bytes(edited))
    with pytest.raises(LogError, match=rf"CHUNK at byte {copy_at} repeats the chunk at byte "
                       rf"{first} \(duplicated: {n} messages on /ladar/points"):  # fmt: skip
        list(open_log(bad).frames())
    src = open_log(bad, skip_corrupt=True)
    assert src.info().topic("/ladar/points").count == N_SCANS
    scans = list(src.frames())
    assert [s.t_ns for s in scans] == [(k + 1) * 100_000_000 for k in range(N_SCANS)]
    assert src.stats.skipped_records == 1 and src.stats.lost == {"duplicated chunk": n}
    assert src.stats.backwards_timestamps == 0 and len(src.defects) == 1


def test_a_repeated_loose_message_is_a_defect(tmp_path) -> None:
    path = tmp_path / "loose.mcap"
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.NONE, use_chunking=False)
        w.start(profile="ros2")
        sid = w.register_schema(
            "nav_msgs/msg/Odometry", "ros2msg", ros2msg_schema("nav_msgs/msg/Odometry")
        )
        cid = w.register_channel("/odom", "cdr", sid)
        for k in (1, 2, 3, 3, 4, 3):  # the third message three times, twice after others
            (enc,) = encode_frame(OdometryFrame(k * 10**7, "odom", "base_link", np.eye(4)))
            w.add_message(cid, k * 10**7, serialize(enc), k * 10**7, sequence=k)
        w.finish()
    with pytest.raises(LogError, match=r"/odom message at log time 30000000 ns .* duplicated"):
        list(open_log(path).frames())
    src = open_log(path, skip_corrupt=True)
    assert [f.t_ns // 10**7 for f in src.frames()] == [1, 2, 3, 4]
    assert src.stats.lost == {"duplicated message": 1}  # the same problem twice: one record
    assert src.stats.skipped_records == 1


def test_a_corrupt_chunk_counts_the_messages_it_held_once(good_log, tmp_path) -> None:
    data = bytearray(good_log.read_bytes())
    offset, length, n = _chunks(bytes(data))[3]
    for i in range(offset + length // 2, offset + length // 2 + 32):
        data[i] ^= 0xFF
    bad = tmp_path / "flip.mcap"
    bad.write_bytes(bytes(data))
    src = open_log(bad, skip_corrupt=True)
    src.info()
    scans = list(src.frames())
    list(src.frames())  # every pass meets it; it is counted once
    assert len(scans) == N_SCANS - n
    assert src.stats.skipped_records == 1 and src.stats.lost == {"corrupt chunk": n}


@pytest.mark.parametrize("declared", [2**40, 2**31])
def test_an_absurd_chunk_size_is_refused_unread(good_log, tmp_path, declared) -> None:
    data = bytearray(good_log.read_bytes())
    offset, _, n = _chunks(bytes(data))[1]
    struct.pack_into("<Q", data, offset + 9 + 16, declared)  # uncompressed size
    bad = tmp_path / "huge.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(
        LogError, match=rf"CHUNK at byte {offset} declares {declared} uncompressed bytes, above"
    ):
        list(open_log(bad).frames())
    src = open_log(bad, skip_corrupt=True)
    assert len(list(src.frames())) == N_SCANS - n
    assert src.stats.lost == {"oversized chunk": n}


def test_a_zstd_chunk_declaring_more_than_its_frame_holds_is_refused(tmp_path) -> None:
    rng = np.random.default_rng(3)
    path = tmp_path / "z.mcap"
    config = McapWriterConfig(compression=Compression.ZSTD, chunk_size_bytes=64 * 1024)
    with McapLogWriter(path, config) as w:
        for k in range(8):
            w.write(_scan(k, rng))
    data = bytearray(path.read_bytes())
    offset = _chunks(bytes(data))[0][0]
    (size,) = struct.unpack_from("<Q", data, offset + 9 + 16)
    struct.pack_into("<Q", data, offset + 9 + 16, 100 * size)
    path.write_bytes(bytes(data))
    with pytest.raises(LogError, match=rf"declares {100 * size} .* but its data holds {size}"):
        list(open_log(path).frames())


def test_an_attachment_crc_mismatch_is_named_never_fatal(tmp_path) -> None:
    rng = np.random.default_rng(4)
    path = tmp_path / "att.mcap"
    payload = bytes(range(256)) * 8
    with McapLogWriter(path) as w:
        w.attach("terrain.npy", payload, "application/x-npy")
        w.attach("notes.txt", b"fine", "text/plain")
        for k in range(3):
            w.write(_scan(k, rng))
    data = bytearray(path.read_bytes())
    at = bytes(data).index(payload) + 100
    data[at] ^= 0x01
    path.write_bytes(bytes(data))
    src = open_log(path)  # no skip_corrupt: scoring data never stops reading
    assert len(list(src.frames())) == 3
    assert src.attachments() == {"notes.txt": b"fine"}
    (why,) = src.damaged_extras().values()
    assert "attachment 'terrain.npy'" in why and "CRC mismatch" in why
    r = subprocess.run(
        [sys.executable, "-m", "wm.cli", "log-info", str(path), "--check"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert r.returncode == 2, r.stdout + r.stderr
    defects = [line for line in r.stdout.splitlines() if line.startswith("defect:")]
    assert len(defects) == 1 and "terrain.npy" in defects[0] and "CRC mismatch" in defects[0]


def test_log_info_check_lists_every_defect_and_fails(good_log, tmp_path) -> None:
    def check(path: Path) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, "-m", "wm.cli", "log-info", str(path), "--check"],
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip

    r = check(good_log)
    assert r.returncode == 0 and "check: no defects" in r.stdout, r.stderr
    data, copy_at, _ = _duplicate_chunk(bytearray(good_log.read_bytes()), 1)
    offset = _chunks(bytes(data))[5][0]
    struct.pack_into("<Q", data, offset + 9 + 16, 2**40)
    bad = tmp_path / "two.mcap"
    bad.write_bytes(bytes(data))
    r = check(bad)
    assert r.returncode == 2
    defects = [line for line in r.stdout.splitlines() if line.startswith("defect:")]
    assert len(defects) == 2
    assert f"CHUNK at byte {copy_at} repeats" in defects[0]
    assert f"CHUNK at byte {offset} declares" in defects[1]

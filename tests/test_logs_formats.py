"""The writer's encodings byte for byte, its indexes, its copy semantics; ROS 2 bag folders;
KITTI folders made here (bad files, NaN points, times.txt); bad ROS 1 bags."""

from __future__ import annotations

import shutil
import struct
import typing

import numpy as np
import pytest
from mcap.records import Chunk, Message, MessageIndex
from mcap.stream_reader import StreamReader, breakup_chunk
from test_logs_mcap import assert_same_frame, make_frames

import logs
from core.geometry import rpy_to_matrix, se3
from logs import (
    CameraFrame,
    Compression,
    LadarScan,
    LogError,
    LogMessage,
    McapLogWriter,
    McapWriterConfig,
    OdometryFrame,
    open_log,
)
from logs.kitti_log import KittiLogSource
from logs.ros_encode import encode_frame, serialize
from logs.ros_types import ODOMETRY, typestore
from logs.rosbag_log import RosbagLogSource


def test_odometry_packing_matches_the_rosbags_serialiser() -> None:
    rng = np.random.default_rng(2)
    odom = OdometryFrame(
        t_ns=1_234_567_891_011,
        frame_id="odom",
        child_frame_id="base_link_x",  # odd lengths exercise the padding
        T_parent_child=se3(rpy_to_matrix(0.1, -0.2, 2.9), [1.5, -2.0, 0.25]),
        twist_linear=rng.normal(size=3),
        twist_angular=rng.normal(size=3),
        pose_covariance=rng.normal(size=(6, 6)),
        twist_covariance=rng.normal(size=(6, 6)),
    )
    (enc,) = encode_frame(odom)
    ours = serialize(enc)
    store = typestore()
    msg = store.deserialize_cdr(ours, ODOMETRY)
    assert bytes(store.serialize_cdr(msg, ODOMETRY, little_endian=True)) == ours
    assert msg.child_frame_id == "base_link_x" and msg.header.stamp.nanosec == 567_891_011


@pytest.mark.parametrize("compression", [Compression.NONE, Compression.LZ4])
def test_message_indexes_point_at_their_messages(tmp_path, compression) -> None:
    path = tmp_path / "indexed.mcap"
    config = McapWriterConfig(compression=compression, chunk_size_bytes=20_000)
    with McapLogWriter(path, config) as w:
        for f in make_frames(seed=4):
            w.write(f)
    chunks = 0
    with open(path, "rb") as f:
        records = list(StreamReader(f, emit_chunks=True, validate_crcs=True).records)
    for k, record in enumerate(records):
        if not isinstance(record, Chunk):
            continue
        chunks += 1
        data = breakup_chunk(record, validate_crc=True)
        inner = {id(m): m for m in data if isinstance(m, Message)}
        indexes = [r for r in records[k + 1 :] if isinstance(r, MessageIndex)]
        raw = record.data if compression is Compression.NONE else None
        n_indexed = 0
        for index in indexes[: len({m.channel_id for m in inner.values()})]:
            for log_time, offset in index.records:
                n_indexed += 1
                if raw is not None:  # the offset is where the message record starts
                    opcode, _, channel_id = struct.unpack_from("<BQH", raw, offset)
                    assert opcode == 0x05 and channel_id == index.channel_id
                    assert struct.unpack_from("<Q", raw, offset + 15)[0] == log_time
        assert n_indexed == len(inner)
    assert chunks > 1


def test_arrays_changed_after_write_do_not_change_the_log(tmp_path) -> None:
    for compression in (Compression.NONE, Compression.ZSTD):
        frames = make_frames(seed=6)
        scan, cam = frames[1], frames[3]
        kept = (scan.points_xyz.copy(), cam.image.copy())
        path = tmp_path / f"mutated_{compression.value}.mcap"
        with McapLogWriter(path, McapWriterConfig(compression=compression)) as w:
            w.write(scan)
            w.write(cam)
            scan.points_xyz[:] = 0  # a sensor driver reusing its buffers
            cam.image[:] = 0
        back = list(open_log(path).frames())
        np.testing.assert_array_equal(back[0].points_xyz, kept[0])
        np.testing.assert_array_equal(back[1].image, kept[1])


def test_empty_scan_round_trips(tmp_path) -> None:
    empty = LadarScan(
        5,
        "ladar",
        np.zeros((0, 3), np.float32),
        np.zeros(0, np.float32),
        np.zeros(0, np.int64),
        np.zeros(0, np.uint16),
    )
    with McapLogWriter(tmp_path / "empty.mcap") as w:
        w.write(empty)
    (back,) = list(open_log(tmp_path / "empty.mcap").frames())
    assert_same_frame(empty, back)


def test_ros2_bag_folder_reads_through_rosbags(tmp_path) -> None:
    from rosbags.rosbag2 import Writer

    frames = make_frames(seed=8)
    folder = tmp_path / "bag2"
    store = typestore()
    with Writer(folder, version=9) as bag:
        connections = {}
        for frame in frames:
            for enc in encode_frame(frame):
                if enc.topic not in connections:
                    connections[enc.topic] = bag.add_connection(
                        enc.topic, enc.msgtype, typestore=store
                    )
                bag.write(connections[enc.topic], frame.t_ns, serialize(enc))
    src = open_log(folder)
    assert isinstance(src, RosbagLogSource) and src.format_name == "ROS 2 bag folder"
    back = list(src.frames())
    # ground truth in a bag is told apart by its /ground_truth topic (no channel metadata)
    assert [type(f) for f in back] == [type(f) for f in frames]
    for a, b in zip(frames, back, strict=True):
        assert_same_frame(a, b)
    assert src.info().topic("/camera/image").msgtype == "sensor_msgs/msg/Image"


def _kitti_folder(tmp_path, n_scans: int = 3):
    rng = np.random.default_rng(9)
    folder = tmp_path / "seq" / "velodyne"
    folder.mkdir(parents=True)
    scans = []
    for k in range(n_scans):
        xyzi = rng.normal(0, 10, (100 + k, 4)).astype(np.float32)
        xyzi.tofile(folder / f"{k:06d}.bin")
        scans.append(xyzi)
    return folder, scans


def test_kitti_times_nan_points_and_broken_scans(tmp_path) -> None:
    folder, scans = _kitti_folder(tmp_path)
    (folder.parent / "times.txt").write_text("0.0\n0.1035\n0.2071\n")
    scans[1][[3, 50], 2] = np.nan
    scans[1].tofile(folder / "000001.bin")
    np.arange(10, dtype=np.uint32).tofile(folder / "000000.label")
    src = open_log(folder.parent)
    assert isinstance(src, KittiLogSource) and src.info().notes == ()
    back = list(src.frames())
    assert [s.t_ns for s in back] == [0, 103_500_000, 207_100_000]
    assert src.stats.dropped_nonfinite_points == 2 and back[1].n_points == 99
    np.testing.assert_array_equal(back[2].points_xyz, scans[2][:, :3])
    with pytest.raises(LogError, match=r"000000\.label: 10 labels for a scan of 100 points"):
        src.labels(0)
    assert src.labels(1) is None
    with open(folder / "000002.bin", "ab") as f:
        f.write(b"\0\0\0")  # a scan cut mid-point
    with pytest.raises(LogError, match=r"000002\.bin: 1635 bytes is not a whole number of 16-"):
        list(open_log(folder).frames())
    src = open_log(folder, skip_corrupt=True)
    assert len(list(src.frames())) == 2 and src.stats.skipped_records == 1


def test_kitti_dataset_root_with_one_sequence_or_several(tmp_path) -> None:
    """The dataset's root opens when it holds one sequence; with several the error names them."""
    root = tmp_path / "kitti"
    rng = np.random.default_rng(2)
    for seq in ("00",):
        (root / "sequences" / seq / "velodyne").mkdir(parents=True)
        rng.normal(0, 10, (50, 4)).astype(np.float32).tofile(
            root / "sequences" / seq / "velodyne" / "000000.bin"
        )
    src = open_log(root)
    assert isinstance(src, KittiLogSource) and len(list(src.frames())) == 1
    (root / "sequences" / "07" / "velodyne").mkdir(parents=True)
    rng.normal(0, 10, (50, 4)).astype(np.float32).tofile(
        root / "sequences" / "07" / "velodyne" / "000000.bin"
    )
    with pytest.raises(LogError, match=r"several sequences \(00, 07\); pass one of them"):
        open_log(root)


@pytest.mark.real_data
def test_damaged_ros1_bag(real_data, tmp_path) -> None:
    original = real_data / "rosbag" / "robot_localization_test2.bag"
    data = bytearray(original.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 64] = bytes(b ^ 0xFF for b in data[middle : middle + 64])
    flipped = tmp_path / "flipped.bag"
    flipped.write_bytes(bytes(data))
    with pytest.raises(LogError, match=r"flipped\.bag: .*damaged"):
        list(open_log(flipped).frames())
    src = open_log(flipped, skip_corrupt=True)
    n = sum(1 for _ in src.frames())
    assert 0 < n < 6121 and src.stats.skipped_records == 1
    cut = tmp_path / "cut.bag"
    shutil.copyfile(original, cut)
    with open(cut, "r+b") as f:
        f.truncate(len(data) // 2)
    with pytest.raises(LogError, match=r"cut\.bag: cannot open as a ROS bag"):
        open_log(cut)


def test_foreign_images_without_camera_info_have_nan_intrinsics(tmp_path) -> None:
    from mcap.writer import Writer

    from logs.ros_types import IMAGE, ros2msg_schema

    path = tmp_path / "images_only.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2")
        cid = w.register_channel(
            "/cam/image", "cdr", w.register_schema(IMAGE, "ros2msg", ros2msg_schema(IMAGE))
        )
        for k in range(3):
            frame = CameraFrame(k, "cam", np.full((4, 5), k, np.uint8), np.eye(3))
            (enc,) = [e for e in encode_frame(frame) if e.topic.endswith("/image")]
            w.add_message(cid, k, serialize(enc), k)
        w.finish()
    src = open_log(path)
    frames = list(src.frames())
    assert [f.image[0, 0] for f in frames] == [0, 1, 2] and frames[0].topic == "/cam"
    assert all(np.isnan(f.K).all() and f.depth is None for f in frames)
    assert src.stats.messages == ["/cam/image: no CameraInfo before the image at t_ns=0; K NaN"]


def test_frame_is_a_deprecated_alias_of_log_message() -> None:
    """Users' code that imports ``Frame`` still gets the union of log messages."""
    assert logs.Frame is LogMessage and logs.types.Frame is LogMessage
    assert CameraFrame in typing.get_args(LogMessage)

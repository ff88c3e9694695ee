"""MCAP logs: frames of every kind survive a write and a read, and independent ROS tools
(rosbags, the mcap library with mcap_ros2) read our files with the standard message types."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from core.geometry import rpy_to_matrix, se3
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
    TransformFrame,
    format_log_info,
    open_log,
)

T0 = 1_700_000_000_000_000_000  # a realistic epoch time, ns


def _pose(rng: np.random.Generator) -> np.ndarray:
    return se3(rpy_to_matrix(*rng.uniform(-3, 3, 3)), rng.normal(0, 10, 3))


def make_frames(seed: int = 0) -> list:
    """One or two frames of every kind, random but seeded, in time order."""
    rng = np.random.default_rng(seed)
    n = 2000
    frames = [
        TransformFrame(0, "base_link", "ladar", _pose(rng), static=True, topic="/tf_static"),
        LadarScan(
            t_ns=T0,
            frame_id="ladar",
            points_xyz=rng.normal(0, 20, (n, 3)).astype(np.float32),
            intensity=rng.random(n).astype(np.float32),
            t_offset_ns=rng.integers(0, 100_000_000, n),
            ring=rng.integers(0, 32, n).astype(np.uint16),
        ),
        LadarScan(
            t_ns=T0 + 1,
            frame_id="ladar",
            points_xyz=rng.normal(0, 20, (7, 3)).astype(np.float32),
            intensity=rng.random(7).astype(np.float32),
            t_offset_ns=np.zeros(7, np.int64),
            ring=None,
            topic="/ladar2/points",
        ),
        CameraFrame(
            t_ns=T0 + 10,
            frame_id="camera",
            image=rng.integers(0, 256, (24, 32, 3), dtype=np.uint8),
            K=np.array([[300.0, 0, 16.5], [0, 310.0, 12.25], [0, 0, 1]]),
            depth=np.where(
                rng.random((24, 32)) < 0.1, np.nan, rng.uniform(0.5, 9, (24, 32))
            ).astype(np.float32),
            dist=rng.normal(0, 0.01, 5),
        ),
        CameraFrame(
            t_ns=T0 + 11,
            frame_id="ir",
            image=rng.integers(0, 256, (10, 12), dtype=np.uint8),
            K=np.array([[50.0, 0, 6], [0, 50.0, 5], [0, 0, 1]]),
            topic="/ir",
        ),
        OdometryFrame(
            t_ns=T0 + 20,
            frame_id="odom",
            child_frame_id="base_link",
            T_parent_child=_pose(rng),
            twist_linear=rng.normal(size=3),
            twist_angular=rng.normal(size=3),
            pose_covariance=rng.normal(size=(6, 6)),
            twist_covariance=rng.normal(size=(6, 6)),
        ),
        ImuFrame(T0 + 30, "imu", rng.normal(size=3), rng.normal(size=3), None),
        ImuFrame(
            T0 + 31, "imu", rng.normal(size=3), rng.normal(size=3), np.array([0, 0, 0.6, 0.8])
        ),
        TransformFrame(T0 + 40, "odom", "base_link", _pose(rng)),
        GroundTruthPose(T0 + 50, "world", "base_link", _pose(rng)),
        ObjectBoxes(
            t_ns=T0 + 60,
            frame_id="world",
            ids=np.array([4, 17, 2**40]),
            classes=["vehicle", "person", "building"],
            centers=rng.normal(0, 30, (3, 3)),
            sizes=rng.uniform(0.3, 5, (3, 3)),
            yaws=np.array([0.25, -2.5, 3.0]),
            velocities=rng.normal(size=(3, 3)),
            n_returns=np.array([12, 0, 2**20]),  # truth per return, simulated logs carry it
        ),
        ObjectBoxes(
            T0 + 70,
            "world",
            np.zeros(0, np.int64),
            [],
            np.zeros((0, 3)),
            np.zeros((0, 3)),
            np.zeros(0),
            np.zeros((0, 3)),
        ),
    ]
    return frames


def assert_same_frame(a, b) -> None:
    """``b`` (read back) equals ``a`` (written): exact arrays, poses to 1e-12 (quaternions)."""
    assert type(a) is type(b)
    for name in a.__slots__:
        x, y = getattr(a, name), getattr(b, name)
        if name.startswith("T_"):
            np.testing.assert_allclose(y, x, rtol=0, atol=1e-12, err_msg=name)
        elif name == "yaws":
            np.testing.assert_allclose(np.angle(np.exp(1j * (y - x))), 0, atol=1e-12)
        elif isinstance(x, np.ndarray):
            assert y.dtype == x.dtype, name
            np.testing.assert_array_equal(y, x, err_msg=name)
        else:
            assert y == x, name


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> tuple[Path, list]:
    path = tmp_path_factory.mktemp("mcap") / "all.mcap"
    frames = make_frames()
    with McapLogWriter(path) as w:
        for f in frames:
            w.write(f)
        w.attach("scenario.yaml", b"seed: 7\n", "application/yaml", t_ns=T0)
        w.add_metadata("run", {"seed": "7", "world": "test"})
    return path, frames


@pytest.mark.parametrize("compression", list(Compression))
def test_every_frame_kind_round_trips(tmp_path, compression) -> None:
    frames = make_frames(seed=3)
    path = tmp_path / "log.mcap"
    with McapLogWriter(path, McapWriterConfig(compression=compression)) as w:
        for f in frames:
            w.write(f)
    src = open_log(path)
    back = list(src.frames())
    assert len(back) == len(frames)
    for a, b in zip(frames, back, strict=True):
        assert_same_frame(a, b)
    assert src.stats.skipped_records == src.stats.backwards_timestamps == 0


def test_info_attachments_metadata_static(written) -> None:
    path, frames = written
    src = open_log(path)
    info = src.info()
    assert info.topic("/ladar/points").msgtype == "sensor_msgs/msg/PointCloud2"
    assert info.topic("/camera/depth").msgtype == "sensor_msgs/msg/Image"
    assert info.topic("/ground_truth/objects").msgtype == "vision_msgs/msg/Detection3DArray"
    assert info.topic("/imu").count == 2
    assert (info.first_t_ns, info.last_t_ns) == (0, T0 + 70)
    text = format_log_info(info)
    assert "/camera/camera_info" in text and "sensor_msgs/msg/CameraInfo" in text
    src.require_topics(["/camera", "/camera/depth", "/ir", "/ground_truth/objects", "/tf_static"])
    assert "/ground_truth/objects/velocities" not in src.frame_topics()
    assert src.attachments() == {"scenario.yaml": b"seed: 7\n"}
    assert src.metadata() == {"run": {"seed": "7", "world": "test"}}
    np.testing.assert_allclose(
        src.static_transforms[("base_link", "ladar")], frames[0].T_parent_child, atol=1e-12
    )
    assert list(src.static_transforms) == [("base_link", "ladar")]


def test_frames_filter_by_kind_and_topic(written) -> None:
    path, frames = written
    src = open_log(path)
    scans = list(src.frames(kinds=LadarScan))
    assert [s.topic for s in scans] == ["/ladar/points", "/ladar2/points"]
    cams = list(src.frames(topics=["/ir"]))
    assert len(cams) == 1
    assert_same_frame(frames[4], cams[0])
    both = list(
        src.frames(kinds=[ImuFrame, GroundTruthPose], topics=["/imu", "/ground_truth/pose"])
    )
    assert [type(f) for f in both] == [ImuFrame, ImuFrame, GroundTruthPose]


def test_rosbags_reads_our_mcap(written) -> None:
    from rosbags.highlevel import AnyReader

    path, frames = written
    scan = frames[1]
    with AnyReader([path]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types["/ladar/points"] == "sensor_msgs/msg/PointCloud2"
        assert types["/ground_truth/pose"] == "nav_msgs/msg/Odometry"
        assert types["/ground_truth/objects/velocities"] == "std_msgs/msg/Float64MultiArray"
        assert types["/tf_static"] == "tf2_msgs/msg/TFMessage"
        conns = [c for c in reader.connections if c.topic == "/ladar/points"]
        ((conn, t_ns, raw),) = list(reader.messages(connections=conns))
        msg = reader.deserialize(raw, conn.msgtype)
    assert t_ns == scan.t_ns
    assert [f.name for f in msg.fields] == ["x", "y", "z", "intensity", "t", "ring"]
    cloud = np.frombuffer(
        msg.data.tobytes(),
        dtype=np.dtype(
            {
                "names": ["x", "y", "z", "t", "ring"],
                "formats": ["<f4", "<f4", "<f4", "<u4", "<u2"],
                "offsets": [0, 4, 8, 16, 20],
                "itemsize": msg.point_step,
            }
        ),
    )
    np.testing.assert_array_equal(cloud["y"], scan.points_xyz[:, 1])
    np.testing.assert_array_equal(cloud["t"], scan.t_offset_ns)
    np.testing.assert_array_equal(cloud["ring"], scan.ring)
    assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == scan.t_ns


def test_mcap_library_with_ros2_decoder_reads_our_mcap(written) -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path, frames = written
    boxes, cam, gt = frames[10], frames[3], frames[9]
    decoded = {}
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        for schema, channel, _, msg in reader.iter_decoded_messages():
            assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
            decoded.setdefault(channel.topic, (schema.name, msg))
    name, det = decoded["/ground_truth/objects"]
    assert name == "vision_msgs/msg/Detection3DArray"
    assert [d.id for d in det.detections] == [str(i) for i in boxes.ids]
    assert [d.results[0].hypothesis.class_id for d in det.detections] == boxes.classes
    np.testing.assert_array_equal(
        [[d.bbox.size.x, d.bbox.size.y, d.bbox.size.z] for d in det.detections], boxes.sizes
    )
    name, vel = decoded["/ground_truth/objects/velocities"]
    assert name == "std_msgs/msg/Float64MultiArray"
    # the layout says what a row holds: velocities, then the returns on each box
    assert [(d.label, d.size) for d in vel.layout.dim] == [("boxes", 3), ("vxyz_returns", 4)]
    rows = np.reshape(vel.data, (-1, 4))
    np.testing.assert_array_equal(rows[:, :3], boxes.velocities)
    np.testing.assert_array_equal(rows[:, 3], boxes.n_returns)
    name, info = decoded["/camera/camera_info"]
    assert name == "sensor_msgs/msg/CameraInfo" and info.distortion_model == "plumb_bob"
    np.testing.assert_array_equal(np.reshape(info.k, (3, 3)), cam.K)
    name, depth = decoded["/camera/depth"]
    assert (name, depth.encoding, depth.width, depth.height) == (
        "sensor_msgs/msg/Image",
        "32FC1",
        32,
        24,
    )
    name, odom = decoded["/ground_truth/pose"]
    assert name == "nav_msgs/msg/Odometry" and odom.child_frame_id == gt.child_frame_id
    assert odom.pose.pose.position.x == gt.T_parent_child[0, 3]


def test_writer_is_atomic_and_checks_its_input(tmp_path) -> None:
    path = tmp_path / "broken.mcap"
    with pytest.raises(RuntimeError), McapLogWriter(path) as w:
        w.write(make_frames()[1])
        raise RuntimeError("simulated crash while logging")
    assert not path.exists() and not (tmp_path / "broken.mcap.tmp").exists()
    scan = make_frames()[1]
    with McapLogWriter(path) as w:
        with pytest.raises(LogError, match="t_offset_ns"):
            bad = LadarScan(1, "l", scan.points_xyz, scan.intensity, scan.t_offset_ns - 10**9, None)
            w.write(bad)
        with pytest.raises(LogError, match="t_ns=-1"):
            w.write(TransformFrame(-1, "a", "b", np.eye(4)))
        with pytest.raises(LogError, match="neither"):
            w.write(CameraFrame(1, "c", np.zeros((4, 4, 2), np.uint8), np.eye(3)))
        with pytest.raises(LogError, match="non-string"):
            w.add_metadata("m", {"a": 1})
    assert path.exists() and open_log(path).info().message_count == 0


def test_attachments_and_metadata_come_from_the_pass_info_made(written, tmp_path) -> None:
    """info() reads the whole file once; attachments and metadata come from that pass (the
    copy is moved away before they are asked for), and a fresh source reads them alone."""
    path, _ = written
    copy = tmp_path / "copy.mcap"
    copy.write_bytes(path.read_bytes())
    src = open_log(copy)
    src.info()
    copy.rename(tmp_path / "gone.mcap")
    assert src.attachments() == {"scenario.yaml": b"seed: 7\n"}
    assert src.metadata() == {"run": {"seed": "7", "world": "test"}}
    src.metadata()["run"]["seed"] = "changed"  # callers get copies
    assert src.metadata() == {"run": {"seed": "7", "world": "test"}}
    fresh = open_log(tmp_path / "gone.mcap")
    assert fresh.metadata() == {"run": {"seed": "7", "world": "test"}}
    assert fresh.attachments() == {"scenario.yaml": b"seed: 7\n"}

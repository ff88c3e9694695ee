"""Every real recording reads with the expected counts and shapes, and what it yields agrees
with its ground truth or with physics (gravity, integrated wheel speed, static objects)."""

from __future__ import annotations

import itertools
from collections import Counter

import numpy as np
import pytest

from logs import (
    CameraFrame,
    GroundTruthPose,
    ImuFrame,
    LadarScan,
    ObjectBoxes,
    OdometryFrame,
    TransformFrame,
    format_log_info,
    open_log,
)
from logs.av2_log import Av2LogSource
from logs.kitti_log import KittiLogSource
from logs.mcap_log import McapLogSource
from logs.rgbd_log import RgbdLogSource
from logs.rosbag_log import RosbagLogSource

pytestmark = pytest.mark.real_data


def test_av2_sweeps_poses_and_boxes(real_data) -> None:
    src = open_log(real_data / "av2")
    assert isinstance(src, Av2LogSource)
    scans = list(src.frames(kinds=LadarScan))
    assert [s.n_points for s in scans] == [99_229, 99_466]
    first = scans[0]
    assert first.t_ns == 315966265259836000 and first.frame_id == "ladar"
    assert first.points_xyz.dtype == np.float32 and first.ring.dtype == np.uint16
    assert set(np.unique(first.ring)) == set(range(64))  # two stacked 32-beam Velodynes
    assert first.t_offset_ns.min() >= 0
    assert first.t_offset_ns.max() < 110_000_000  # one 10 Hz revolution
    info = src.info()
    assert info.topic("/ground_truth/pose").count == 2706
    assert info.topic("/ground_truth/objects").count == 156
    frames = list(src.frames())
    assert [f.t_ns for f in frames] == sorted(f.t_ns for f in frames)
    assert Counter(type(f) for f in frames) == {
        GroundTruthPose: 2706,
        ObjectBoxes: 156,
        LadarScan: 2,
        TransformFrame: 1,
    }
    assert isinstance(frames[0], TransformFrame)  # the mount comes before any sweep


def test_av2_scans_are_in_the_lidar_frame_and_level_1_orders_their_rings(real_data) -> None:
    """The points come back in base_link through the published mount (the file's own
    numbers, to float16 precision). The rings are AV2's laser numbers, which interleave the
    elevations of its two 32-beam units; level 1's ranking (sp.level1.ring_rows) makes every
    sweep's rows rise in elevation."""
    import pyarrow.feather as feather

    from sp.level1 import ring_rows

    src = open_log(real_data / "av2")
    tf = next(iter(src.frames(kinds=TransformFrame)))
    assert (tf.parent_frame_id, tf.child_frame_id, tf.static) == ("base_link", "ladar", True)
    calib = feather.read_table(real_data / "av2" / "calibration" / "egovehicle_SE3_sensor.feather")
    k = calib["sensor_name"].to_pylist().index("up_lidar")
    assert tf.T_parent_child[:3, 3] == pytest.approx(
        [calib[c][k].as_py() for c in ("tx_m", "ty_m", "tz_m")]
    )
    first_rows = None
    for scan, path in zip(src.frames(kinds=LadarScan), src.sweep_files, strict=True):
        raw = feather.read_table(path, columns=["x", "y", "z", "laser_number"])
        xyz = np.stack([raw[c].to_numpy().astype(np.float64) for c in "xyz"], axis=1)
        T = tf.T_parent_child
        back = scan.points_xyz.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
        np.testing.assert_allclose(back, xyz, atol=1e-5)
        assert np.array_equal(scan.ring, raw["laser_number"].to_numpy())
        p = scan.points_xyz.astype(np.float64)
        elevation = np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
        by_laser = np.array([np.median(elevation[scan.ring == n]) for n in range(64)])
        assert np.any(np.diff(by_laser) < -5.0)  # the laser numbers are out of order
        first_rows = ring_rows(scan.points_xyz, scan.ring) if first_rows is None else first_rows
        row = first_rows[scan.ring]  # level 1 keeps the first sweep's ranking
        median = np.array([np.median(elevation[row == r]) for r in range(64)])
        # pairs of lasers, one of each unit, share an elevation to within a few hundredths
        assert np.all(np.diff(median) > -0.05), np.round(median, 2)
        assert median[0] < -24 and median[-1] > 24  # the lowest and highest beams


def test_av2_without_calibration_stays_in_the_ego_frame_and_says_so(real_data, tmp_path) -> None:
    """A log folder without its calibration file keeps the ego frame: no mount is published,
    and the node takes the LADAR at the body and notes it."""
    import kd_store
    from wm.config import NodeConfig, PoseSource
    from wm.node import WorldModelNode

    for name in ("sensors", "city_SE3_egovehicle.feather", "annotations.feather"):
        (tmp_path / name).symlink_to((real_data / "av2" / name).resolve())
    src = open_log(tmp_path)
    assert src.T_body_ladar is None and not list(src.frames(kinds=TransformFrame))
    assert "/tf_static" not in [t.name for t in src.info().topics]
    scan = next(iter(src.frames(kinds=LadarScan)))
    assert scan.frame_id == "base_link" and set(np.unique(scan.ring)) == set(range(64))
    node = WorldModelNode(kd_store.open(":memory:"), NodeConfig(pose_source=PoseSource.TRUTH))
    for f in src.frames(kinds=(LadarScan,)):
        node.feed(f)
    assert np.array_equal(node.T_body_ladar, np.eye(4))
    assert any("no base_link->ladar transform" in n for n in node.stats.notes)


def test_av2_box_ids_are_stable_and_static_objects_stand_still(real_data) -> None:
    import pyarrow.feather as feather

    table = feather.read_table(real_data / "av2" / "annotations.feather")
    t_ns = table["timestamp_ns"].to_numpy()
    uuids = np.array(table["track_uuid"].to_pylist())
    tx_m = table["tx_m"].to_numpy()
    boxes = list(open_log(real_data / "av2").frames(kinds=ObjectBoxes))
    assert sum(len(b) for b in boxes) == len(uuids) == 11_364
    id_of_uuid: dict[str, int] = {}
    for b in boxes:
        sel = t_ns == b.t_ns
        np.testing.assert_array_equal(b.centers[:, 0], tx_m[sel])
        for uuid, track_id in zip(uuids[sel], b.ids, strict=True):
            assert id_of_uuid.setdefault(uuid, int(track_id)) == track_id
    assert len(id_of_uuid) == len(set(id_of_uuid.values())) == 114
    speeds: dict[str, list[float]] = {}
    for b in boxes:
        for cls, v in zip(b.classes, b.velocities, strict=True):
            if np.isfinite(v).all():
                speeds.setdefault(cls, []).append(float(np.linalg.norm(v)))
    assert np.median(speeds["BOLLARD"]) < 0.3  # fixed to the ground
    assert np.median(speeds["CONSTRUCTION_CONE"]) < 0.3
    assert max(speeds["REGULAR_VEHICLE"]) > 3.0  # traffic moves


def test_kitti_scans_and_labels(real_data) -> None:
    src = open_log(real_data / "kitti" / "sequences" / "00")
    assert isinstance(src, KittiLogSource)
    scans = list(src.frames())
    assert [s.n_points for s in scans] == [124_668, 124_605, 124_478]
    assert [s.t_ns for s in scans] == [0, 100_000_000, 200_000_000]
    assert any("10 Hz" in n for n in src.info().notes)
    raw = np.fromfile(src.scan_files[0], dtype=np.float32).reshape(-1, 4)
    np.testing.assert_array_equal(scans[0].points_xyz, raw[:, :3])
    np.testing.assert_array_equal(scans[0].intensity, raw[:, 3])
    labels = src.labels(0)
    assert labels.shape == (124_668,)
    classes = Counter((labels & 0xFFFF).tolist())
    assert classes[40] > 10_000  # road is the largest surface in front of the car
    road = scans[0].points_xyz[(labels & 0xFFFF) == 40]
    assert abs(np.median(road[:, 2]) + 1.73) < 0.2  # HDL-64 mounted 1.73 m above the road


def test_rgbd_frames_depth_and_poses(real_data) -> None:
    import cv2

    folder = real_data / "7scenes"
    src = open_log(folder)
    assert isinstance(src, RgbdLogSource)
    frames = list(src.frames())
    cams = [f for f in frames if isinstance(f, CameraFrame)]
    poses = [f for f in frames if isinstance(f, GroundTruthPose)]
    assert len(cams) == len(poses) == 200
    assert {c.image.shape for c in cams} == {(480, 640, 3)}
    assert {c.depth.shape for c in cams} == {(480, 640)}
    assert cams[0].K[0, 0] == 585.0 and cams[0].K[1, 2] == 240.0
    mm = cv2.imread(str(folder / "frame-000007.depth.png"), cv2.IMREAD_UNCHANGED)
    unknown = (mm == 0) | (mm == 65535)
    assert unknown.any() and np.isnan(cams[7].depth[unknown]).all()
    np.testing.assert_allclose(cams[7].depth[~unknown], mm[~unknown] / 1000.0, rtol=1e-6)
    np.testing.assert_array_equal(
        poses[7].T_parent_child, np.loadtxt(folder / "frame-000007.pose.txt")
    )
    steps = [
        np.linalg.norm(b.T_parent_child[:3, 3] - a.T_parent_child[:3, 3])
        for a, b in itertools.pairwise(poses)
    ]
    assert max(steps) < 0.05  # a hand-held camera at 30 Hz moves centimetres per frame
    assert src.info().topic("/camera").rate_hz == pytest.approx(30.0)


def test_ros1_bag_topics_gravity_and_wheel_odometry(real_data) -> None:
    src = open_log(real_data / "rosbag" / "robot_localization_test2.bag")
    assert isinstance(src, RosbagLogSource) and src.format_name == "ROS 1 bag"
    info = src.info()
    assert {(t.name, t.msgtype, t.count) for t in info.topics} == {
        ("/imu/data", "sensor_msgs/msg/Imu", 3061),
        ("/jackal_velocity_controller/odom", "nav_msgs/msg/Odometry", 3060),
    }
    assert info.duration_s == pytest.approx(61.2, abs=0.1)
    imu = list(src.frames(kinds=ImuFrame))
    odom = list(src.frames(kinds=OdometryFrame))
    assert len(imu) == 3061 and len(odom) == 3060
    g = np.median([np.linalg.norm(f.linear_acceleration) for f in imu])
    assert g == pytest.approx(9.81, abs=0.1)
    assert all(f.orientation_xyzw is not None for f in imu[:10])
    # the distance along the odometry poses equals the integrated wheel speed
    xyz = np.array([f.T_parent_child[:3, 3] for f in odom])
    t_s = np.array([f.t_ns for f in odom]) * 1e-9
    speed = np.array([np.linalg.norm(f.twist_linear) for f in odom])
    path_m = np.linalg.norm(np.diff(xyz, axis=0), axis=1).sum()
    assert path_m > 50 and (speed[:-1] * np.diff(t_s)).sum() == pytest.approx(path_m, rel=0.01)
    assert src.stats.backwards_timestamps == 0 and src.attachments() == {}


def test_nav2_mcap_odometry_and_tf_agree_with_rosbags(real_data) -> None:
    from rosbags.highlevel import AnyReader

    path = real_data / "rosbag" / "nav2_turtlebot.mcap"
    src = open_log(path)
    assert isinstance(src, McapLogSource)
    text = format_log_info(src.info())
    assert "/amcl_pose" in text and "geometry_msgs/msg/PoseWithCovarianceStamped" in text
    odom = list(src.frames(kinds=OdometryFrame))
    tfs = list(src.frames(kinds=TransformFrame))
    assert len(odom) == 2639 and src.info().topic("/tf").count == 5422
    with AnyReader([path]) as reader:
        conns = [c for c in reader.connections if c.topic in ("/odom", "/tf_static")]
        msgs = {}
        for conn, _, raw in reader.messages(connections=conns):
            msgs.setdefault(conn.topic, reader.deserialize(raw, conn.msgtype))
    first = msgs["/odom"].pose.pose.position
    np.testing.assert_allclose(odom[0].T_parent_child[:3, 3], [first.x, first.y, first.z])
    static = src.static_transforms
    assert len(static) == len(msgs["/tf_static"].transforms) == 29
    for ts in msgs["/tf_static"].transforms:
        tr = ts.transform.translation
        T = static[(ts.header.frame_id, ts.child_frame_id)]
        np.testing.assert_allclose(T[:3, 3], [tr.x, tr.y, tr.z])
    assert sum(1 for f in tfs if not f.static) == len(tfs) - 29

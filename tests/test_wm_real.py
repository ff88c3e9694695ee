"""`wm run` on real recordings (../shared/data/real): an Argoverse 2 log on odometry poses against
its real ground-height raster, a KITTI folder with LADAR odometry, a ROS 1 bag without LADAR."""

from __future__ import annotations

from wm.config import NodeConfig, PoseSource
from wm.run import run_log


def test_av2_map_lies_on_the_real_ground_surface(real_data) -> None:
    """On odometry poses (LADAR alone: the log has no wheel odometry); ``wm run`` scores the map
    with its world aligned to the truth's at the first pose (wm.truth.OdometryScore.T_align)."""
    cfg = NodeConfig(pose_source=PoseSource.ODOMETRY, use_sp=False)
    report = run_log(real_data / "av2", ":memory:", config=cfg, progress=False)
    assert report.sweeps == 2 and report.pose_source == "odometry"
    near = report.metrics["elevation_primitive"]
    # ground cells of the 4 cm level against AV2's ground-height surface (0.3 m cells);
    # measured: 2201 cells, median 0.047 m (truth poses: 2447, 0.041 m)
    assert near["cells"] > 1000 and near["median_abs_m"] < 0.1
    # measured: median 0.039 m (truth poses: 0.048 m)
    assert report.metrics["elevation_subsystem"]["median_abs_m"] < 0.1
    assert not any("camera" in m and "odometry" in m for m in report.missing)


def test_kitti_folder_runs_on_ladar_alone(real_data) -> None:
    report = run_log(real_data / "kitti" / "sequences" / "00" / "velodyne", ":memory:",
                     config=NodeConfig(use_sp=False), progress=False)  # fmt: skip
    assert report.sweeps == 3
    assert any("no wheel odometry" in m for m in report.missing)
    assert report.odometry_status.get("first") == 1


def test_a_bag_without_ladar_says_so(real_data) -> None:
    bag = real_data / "rosbag" / "robot_localization_test2.bag"
    report = run_log(bag, ":memory:", config=NodeConfig(use_sp=False), progress=False)
    assert report.sweeps == 0
    assert any("no LADAR" in m for m in report.missing)

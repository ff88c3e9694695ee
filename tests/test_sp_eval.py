"""Sensory-processing evaluations against ground truth (``make eval``); figures go to results/.

* image flow on the KITTI pair: end-point error beside OpenCV's DIS (ultrafast and medium);
* stereo disparity on the Middlebury cones pair;
* LADAR odometry on the 7-Scenes depth frames (as a range sensor): absolute trajectory error;
* LADAR odometry on the simulated default log: drift per distance travelled, beside the wheel
  odometry alone and the registration alone.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from bench.results import record
from core.geometry import interpolate_pose
from logs.types import (
    CameraFrame,
    GroundTruthPose,
    LadarScan,
    OdometryFrame,
    TransformFrame,
)
from sp.camera import PinholeCamera
from sp.flow import correlation_flow
from sp.odometry import LadarOdometry, OdometryConfig, TrackStatus, WheelOdometry
from sp.stereo import stereo_disparity

pytestmark = pytest.mark.eval
CMD = "make eval"


def test_flow_kitti_end_point_error_beside_dis(real_data):
    d = real_data / "kitti-flow"
    a = cv2.imread(str(d / "frame1.png"), cv2.IMREAD_GRAYSCALE)
    b = cv2.imread(str(d / "frame2.png"), cv2.IMREAD_GRAYSCALE)
    gt = cv2.imread(str(d / "flow_gt.png"), cv2.IMREAD_UNCHANGED)[..., ::-1].astype(np.float64)
    uv, valid = (gt[..., :2] - 2**15) / 64.0, gt[..., 2] > 0

    def epe(flow: np.ndarray) -> float:
        return float(np.linalg.norm(flow - uv, axis=-1)[valid].mean())

    ours = epe(correlation_flow(a, b)[0])
    dis = {
        name: epe(cv2.DISOpticalFlow_create(preset).calc(a, b, None))
        for name, preset in (
            ("ultrafast", cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST),
            ("medium", cv2.DISOPTICAL_FLOW_PRESET_MEDIUM),
        )
    }
    record(
        "sp_eval_flow_kitti_epe_px",
        ours,
        "px",
        baseline="cv2 DIS medium preset",
        baseline_value=dis["medium"],
        target="ratio <= 1.5",
        command=CMD,
    )
    record(
        "sp_eval_flow_kitti_epe_vs_dis_ultrafast_px",
        ours,
        "px",
        baseline="cv2 DIS ultrafast preset",
        baseline_value=dis["ultrafast"],
        target="ratio <= 1",
        command=CMD,
    )
    assert ours <= 1.5 * dis["medium"]


def test_stereo_cones_disparity_error(real_data):
    d = real_data / "middlebury-cones"
    left = cv2.imread(str(d / "left.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(d / "right.png"), cv2.IMREAD_GRAYSCALE)
    gt = cv2.imread(str(d / "disp_left.tif"), cv2.IMREAD_UNCHANGED)
    disp = stereo_disparity(left, right)
    known = gt > 0
    ok = known & np.isfinite(disp)
    err = np.abs(disp - gt)[ok]
    coverage = ok.sum() / known.sum()
    record("sp_eval_stereo_cones_mae_px", float(err.mean()), "px", target="< 1 px", command=CMD)
    record(
        "sp_eval_stereo_cones_bad1_pct",
        100 * float((err > 1).mean()),
        "%",
        target=f"< 10 % (over the {100 * coverage:.0f} % of pixels matched)",
        command=CMD,
    )
    assert err.mean() < 1.0 and coverage > 0.7


def _orthonormal(T: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = T.copy()
    out[:3, :3] = U @ Vt
    return out


def test_odometry_7scenes_absolute_trajectory_error(real_data):
    from logs.source import open_log

    cfg = OdometryConfig(
        max_range_m=6.0,
        min_range_m=0.2,
        voxel_size_m=0.05,
        deskew=False,
        max_step_m=0.5,
        max_step_rad=0.3,
    )
    poses: dict[int, np.ndarray] = {}
    depths: dict[int, CameraFrame] = {}
    for f in open_log(real_data / "7scenes").frames():
        if isinstance(f, GroundTruthPose):
            poses[f.t_ns] = _orthonormal(f.T_parent_child)
        elif isinstance(f, CameraFrame) and f.depth is not None:
            depths[f.t_ns] = f
    od, est, truth = None, [], []
    for t_ns in sorted(set(poses) & set(depths)):
        if od is None:
            od = LadarOdometry(cfg, T_world_body0=poses[t_ns])
        f = depths[t_ns]
        pts, _ = PinholeCamera.from_frame(f).depth_to_points(f.depth)
        pts = pts[::4]
        n = len(pts)
        scan = LadarScan(t_ns, "camera", pts, np.zeros(n, np.float32), np.zeros(n, np.int64))
        est.append(od.update(scan).T_world_body[:3, 3])
        truth.append(poses[t_ns][:3, 3])
    err = np.linalg.norm(np.array(est) - np.array(truth), axis=1)
    path = float(np.sum(np.linalg.norm(np.diff(truth, axis=0), axis=1)))
    ate = float(np.sqrt(np.mean(err**2)))
    record(
        "sp_eval_odometry_7scenes_ate_m",
        ate,
        "m",
        target="< 0.1 m",
        baseline=f"path length of the {len(est)} frames (m)",
        baseline_value=path,
        command=CMD,
    )
    assert len(est) >= 100 and ate < 0.1


def _simulated(seconds: float | None):
    from fixtures.simulate import simulate

    gt_t, gt_T, scans, wheel, T_body_ladar = [], [], [], [], np.eye(4)
    for f in simulate("default", seconds=seconds):
        if isinstance(f, GroundTruthPose):
            gt_t.append(f.t_ns)
            gt_T.append(f.T_parent_child)
        elif isinstance(f, LadarScan):
            scans.append(f)
        elif isinstance(f, OdometryFrame):
            wheel.append(f)
        elif isinstance(f, TransformFrame) and f.child_frame_id == "ladar":
            T_body_ladar = f.T_parent_child
    gt_t = np.array(gt_t)

    def truth(t_ns: int) -> np.ndarray:
        i = int(np.searchsorted(gt_t, t_ns))
        if gt_t[i] == t_ns:
            return gt_T[i]
        a = (t_ns - gt_t[i - 1]) / (gt_t[i] - gt_t[i - 1])
        return interpolate_pose(gt_T[i - 1], gt_T[i], a)

    return scans, wheel, T_body_ladar, truth


def _run(scans, wheel, T_body_ladar, truth, use_wheel: bool):
    """Odometry over the sweeps, fed the wheel odometry up to each sweep's end (when the
    sweep is complete); returns the final drift in % of the distance, the distance, the poses."""
    first = scans[0]
    mid = first.t_ns + int(first.t_offset_ns.max()) // 2
    od = LadarOdometry(OdometryConfig(), T_body_sensor=T_body_ladar, T_world_body0=truth(mid))
    k, est = 0, []
    for s in scans:
        end = s.t_ns + int(s.t_offset_ns.max())
        while use_wheel and k < len(wheel) and wheel[k].t_ns <= end:
            od.add_wheel_odometry(wheel[k])
            k += 1
        est.append(od.update(s))
    P = np.array([e.T_world_body[:3, 3] for e in est])
    G = np.array([truth(e.t_ns)[:3, 3] for e in est])
    dist = float(np.sum(np.linalg.norm(np.diff(G, axis=0), axis=1)))
    return 100 * float(np.linalg.norm(P[-1] - G[-1])) / dist, dist, est


def test_odometry_simulated_default_log_drift():
    scans, wheel, T_body_ladar, truth = _simulated(None)
    fused, dist, est = _run(scans, wheel, T_body_ladar, truth, use_wheel=True)
    icp_only, _, _ = _run(scans, wheel, T_body_ladar, truth, use_wheel=False)
    # The wheel odometry alone, from the same start.
    odo = WheelOdometry(horizon=len(wheel) + 1)
    for w in wheel:
        odo.add(w)
    t0, t1 = est[0].t_ns, est[-1].t_ns
    wheel_end = truth(t0) @ odo.motion(t0, t1)
    wheel_drift = 100 * float(np.linalg.norm(wheel_end[:3, 3] - truth(t1)[:3, 3])) / dist
    record(
        "sp_eval_odometry_sim_drift_pct",
        fused,
        "% of distance",
        baseline=f"wheel odometry alone over the same {dist:.0f} m",
        baseline_value=wheel_drift,
        target="< 0.5 %",
        command=CMD,
    )
    record(
        "sp_eval_odometry_sim_icp_only_drift_pct",
        icp_only,
        "% of distance",
        baseline="wheel odometry alone",
        baseline_value=wheel_drift,
        target="(registration alone, for reference)",
        command=CMD,
    )
    lost = sum(e.status is TrackStatus.LOST for e in est)
    assert lost < 0.05 * len(est)
    assert fused < wheel_drift and fused < icp_only

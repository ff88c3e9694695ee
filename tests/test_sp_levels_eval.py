"""Evaluations of SP levels 2-5 against ground truth (``make eval``).

Simulated logs: the default drive run by the node with the log's true poses (the labelled
baseline of docs/evaluation.md: SP's figures without odometry drift), its KD file scored by
the one protocol (``wm.evaluation``: py-motmetrics CLEAR MOT and identity figures,
classification of the matched pairs).

Real data: KITTI ground precision / recall / F1 under the Patchwork++ protocol against
SemanticKITTI labels; Argoverse 2 cuboid recall and ground accuracy.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

import kd_store
from logs.types import LadarScan, ObjectBoxes
from sp.egosphere import EgosphereConfig
from sp.pipeline import SPConfig
from wm.entities import KDSensoryProcessor

MIN_POINTS = 20
BOX_MARGIN_M = 0.3
OBJECT_CLASSES = ("building", "tree", "bush", "rock", "post", "vehicle", "person")
MOVING_CLASSES = ("vehicle", "person")


def points_in_boxes(points: np.ndarray, boxes: ObjectBoxes, margin: float) -> np.ndarray:
    """(N,) int64 index of the box each world point lies in (first box), -1 none."""
    out = np.full(points.shape[0], -1, dtype=np.int64)
    for k in range(len(boxes)):
        d = points[:, :3].astype(np.float64) - boxes.centers[k]
        c, s = math.cos(boxes.yaws[k]), math.sin(boxes.yaws[k])
        u, v = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
        half = boxes.sizes[k] / 2 + margin
        inside = (np.abs(u) <= half[0]) & (np.abs(v) <= half[1]) & (np.abs(d[:, 2]) <= half[2])
        out[inside & (out < 0)] = k
    return out


def truth_pose_scores(log: Path, kd_path: Path, sp: SPConfig | None = None) -> dict:
    """The node over ``log`` with the log's true poses (the labelled baseline of
    docs/evaluation.md: SP's figures without odometry drift), its KD file scored by the one
    protocol (wm.evaluation: py-motmetrics, TrackEval, evo)."""
    from wm.config import NodeConfig, PoseSource
    from wm.engine_config import EngineConfig
    from wm.evaluation import evaluate_files
    from wm.run import run_log

    config = EngineConfig(node=NodeConfig(pose_source=PoseSource.TRUTH), sp=sp or SPConfig())
    run_log(log, kd_path, config=config, progress=False)
    return evaluate_files(log, kd_path)


@pytest.fixture(scope="module")
def default_log(tmp_path_factory) -> Path:
    """30 s of the default scenario on its own seed (a development seed)."""
    from fixtures.simulate import simulate_to_log

    d = tmp_path_factory.mktemp("default-log")
    return simulate_to_log("default", d / "default.mcap", seconds=30.0, progress=False)


@pytest.mark.eval
def test_eval_simulated_default_tracking(default_log: Path) -> None:
    """With true poses, SP alone meets the issue's targets on the default drive."""
    from bench.results import record

    fig = truth_pose_scores(default_log, default_log.with_suffix(".kd"))
    cmd = "make eval"
    record("sp_levels_truth_poses_mota", fig["mota"], "ratio", target=0.8, command=cmd)
    record(
        "sp_levels_truth_poses_switches_per_100",
        fig["switches_per_100"],
        "per 100",
        target=1.0,
        command=cmd,
    )
    record("sp_levels_truth_poses_precision", fig["precision"], "ratio", target=0.9, command=cmd)
    record("sp_levels_truth_poses_recall", fig["recall"], "ratio", command=cmd)
    record("sp_levels_truth_poses_motp", fig["motp"], "m", command=cmd)
    record(
        "sp_levels_truth_poses_classification_accuracy",
        fig["classification_accuracy"],
        "ratio",
        target=0.85,
        command=cmd,
    )
    print(fig)
    assert fig["num_objects"] >= 300  # enough true object-frames to score (about 500)
    # the targets of docs/evaluation.md, which SP must meet before odometry drifts
    assert fig["mota"] >= 0.8
    assert fig["precision"] >= 0.9
    assert fig["switches_per_100"] <= 1.0
    assert fig["classification_accuracy"] >= 0.85


# ---------------------------------------------------------------- real data

PATCHWORK_GROUND = (40, 44, 48, 49, 60, 72)  # road, parking, sidewalk, other-ground, lane, terrain
PATCHWORK_UNSCORED = (0, 1, 70)  # unlabelled, outlier, vegetation (not scored)


def _ground_scores(pred: np.ndarray, label: np.ndarray) -> tuple[float, float, float]:
    """(precision, recall, F1) of a per-point ground prediction under the Patchwork++ protocol."""
    gt = np.isin(label, PATCHWORK_GROUND)
    scored = ~np.isin(label, PATCHWORK_UNSCORED)
    tp = np.count_nonzero(pred & gt & scored)
    fp = np.count_nonzero(pred & ~gt & scored)
    fn = np.count_nonzero(~pred & gt & scored)
    p, r = tp / max(tp + fp, 1), tp / max(tp + fn, 1)
    return p, r, 2 * p * r / max(p + r, 1e-12)


def patchworkpp_ground_scores(folder: Path) -> list[tuple[float, float, float]]:
    """The same scores for Patchwork++ itself (pypatchworkpp, default parameters, the KITTI
    sensor height 1.723 m) on the same scans."""
    pypatchworkpp = pytest.importorskip("pypatchworkpp", reason="the Patchwork++ baseline")
    params = pypatchworkpp.Parameters()
    params.verbose = False
    params.sensor_height = 1.723
    out = []
    for path in sorted(folder.glob("*.bin")):
        a = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
        label = np.fromfile(path.with_suffix(".label"), dtype=np.uint32) & 0xFFFF
        pw = pypatchworkpp.patchworkpp(params)
        pw.estimateGround(a)
        pred = np.zeros(len(a), dtype=bool)
        pred[pw.getGroundIndices()] = True
        out.append(_ground_scores(pred, label))
    return out


def kitti_ground_scores(folder: Path) -> list[tuple[float, float, float]]:
    """(precision, recall, F1) of our ground per KITTI scan with SemanticKITTI labels."""
    from sp.egosphere import to_egosphere
    from sp.ground import GroundConfig, ground_mask

    cfg = EgosphereConfig(
        n_rows=64,
        n_cols=2048,
        use_ring=False,
        elevation_min_deg=-25.0,
        elevation_max_deg=3.0,
        max_returns=1,
    )
    out = []
    for path in sorted(folder.glob("*.bin")):
        a = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
        label = np.fromfile(path.with_suffix(".label"), dtype=np.uint32) & 0xFFFF
        scan = LadarScan(0, "ladar", a[:, :3].copy(), a[:, 3].copy(), np.zeros(len(a), np.int64))
        img = to_egosphere(scan, cfg)
        ground, _ = ground_mask(img.xyz[..., 0, :], img.valid_first, GroundConfig(1.73))
        out.append(_ground_scores(ground_of_points(scan, cfg, ground), label))
    return out


def ground_of_points(scan: LadarScan, cfg: EgosphereConfig, ground: np.ndarray) -> np.ndarray:
    """Per point of the sweep: the ground label of the pixel it falls in (False when dropped)."""
    from sp.egosphere import spherical

    rng, az, el = spherical(scan.points_xyz.astype(np.float64))
    col = np.clip(((np.pi - az) * cfg.n_cols / (2 * np.pi)).astype(np.int64), 0, cfg.n_cols - 1)
    el_hi, el_lo = np.deg2rad(cfg.elevation_max_deg), np.deg2rad(cfg.elevation_min_deg)
    row = ((el_hi - el) * cfg.n_rows / (el_hi - el_lo)).astype(np.int64)
    ok = (row >= 0) & (row < cfg.n_rows) & (rng >= cfg.min_range_m)
    out = np.zeros(scan.n_points, dtype=bool)
    out[ok] = ground[row[ok], col[ok]]
    return out


@pytest.mark.eval
@pytest.mark.real_data
def test_eval_kitti_ground_patchwork_protocol(real_data: Path) -> None:
    from bench.results import record

    folder = real_data / "kitti" / "sequences" / "00" / "velodyne"
    p, r, f1 = np.array(kitti_ground_scores(folder)).mean(axis=0)
    pw_p, pw_r, pw_f1 = np.array(patchworkpp_ground_scores(folder)).mean(axis=0)
    cmd = "make eval"
    record("sp_levels_kitti_ground_precision", float(p), "ratio", baseline="Patchwork++",
           baseline_value=float(pw_p), command=cmd)  # fmt: skip
    record("sp_levels_kitti_ground_recall", float(r), "ratio", baseline="Patchwork++",
           baseline_value=float(pw_r), command=cmd)  # fmt: skip
    record(
        "sp_levels_kitti_ground_f1",
        float(f1),
        "ratio",
        baseline="Patchwork++ (pypatchworkpp) on the same scans",
        baseline_value=float(pw_f1),
        target="within 2 points of Patchwork++ (paper: 0.965 on SemanticKITTI)",
        command=cmd,
    )
    assert pw_f1 > 0.8  # the baseline ran as meant (paper: 0.965 on all of SemanticKITTI)
    assert f1 >= pw_f1 - 0.02


# ---------------------------------------------------------------- Argoverse 2

AV2_SWEEPS_NS = (315966265259836000, 315966265360032000)  # flow labels belong to the first
AV2_MIN_INTERIOR = 20  # cuboids with at least this many annotated interior points are scored


def _feather(path: Path) -> dict[str, np.ndarray]:
    import pyarrow.feather as feather

    t = feather.read_table(path)
    return {n: t.column(n).to_numpy() for n in t.column_names}


def _av2_pose(c: dict[str, np.ndarray], row: int) -> np.ndarray:
    from core.geometry import quat_to_matrix

    T = np.eye(4)
    q = np.array([c["qx"][row], c["qy"][row], c["qz"][row], c["qw"][row]], dtype=np.float64)
    T[:3, :3] = quat_to_matrix(q)
    T[:3, 3] = [c["tx_m"][row], c["ty_m"][row], c["tz_m"][row]]
    return T


def av2_egosphere() -> EgosphereConfig:
    """Two stacked 32-beam sensors whose beam numbers are not in elevation order: rows by
    elevation bin over their joint field of view."""
    return EgosphereConfig(
        n_rows=96,
        n_cols=1800,
        use_ring=False,
        elevation_min_deg=-26.0,
        elevation_max_deg=16.0,
        max_returns=1,
    )


def run_av2(folder: Path) -> dict[str, float | str]:
    """SP over the two AV2 sweeps (city frame as the world, the true ego poses).

    Ground (first sweep): each point takes its pixel's ground label, scored against
    ``is_ground_0`` of ``flow_labels.feather`` over every point inside the image.
    Cuboids (second sweep, when hypotheses seen twice have frames): those with at least
    ``AV2_MIN_INTERIOR`` annotated interior points; one is recalled when a level-4 object lies
    mostly inside it (the simulated evaluation's optimal assignment on point counts).
    The sweeps' points are given in the ego frame at the sweep's stamp (already compensated),
    so they are passed with zero per-point offsets (no second deskew).
    """
    from sp.egosphere import spherical

    calib = _feather(folder / "calibration" / "egovehicle_SE3_sensor.feather")
    T_ego_ladar = _av2_pose(calib, int(np.flatnonzero(calib["sensor_name"] == "up_lidar")[0]))
    poses = _feather(folder / "city_SE3_egovehicle.feather")
    ann = _feather(folder / "annotations.feather")
    labels = _feather(folder / "flow_labels.feather")
    cfg = av2_egosphere()
    kd = kd_store.open(":memory:")
    sp = KDSensoryProcessor(kd, SPConfig(egosphere=cfg))
    out: dict[str, float | str] = {}
    for k, t_ns in enumerate(AV2_SWEEPS_NS):
        c = _feather(folder / "sensors" / "lidar" / f"{t_ns}.feather")
        xyz_ego = np.stack([c["x"], c["y"], c["z"]], axis=1).astype(np.float64)
        xyz_l = (xyz_ego - T_ego_ladar[:3, 3]) @ T_ego_ladar[:3, :3]
        n = xyz_l.shape[0]
        scan = LadarScan(
            t_ns, "ladar", xyz_l.astype(np.float32), c["intensity"].astype(np.float32),
            np.zeros(n, np.int64),
        )  # fmt: skip
        T_city_ego = _av2_pose(poses, int(np.flatnonzero(poses["timestamp_ns"] == t_ns)[0]))
        result = sp.process(scan, T_city_ego @ T_ego_ladar)
        if k == 0:
            pred = ground_of_points(scan, cfg, result.ground_mask)
            _, _, el = spherical(xyz_l)
            inside = (el >= np.deg2rad(cfg.elevation_min_deg)) & (
                el < np.deg2rad(cfg.elevation_max_deg)
            )
            gt = labels["is_ground_0"].astype(bool)
            tp = np.count_nonzero(pred & gt & inside)
            fp = np.count_nonzero(pred & ~gt & inside)
            fn = np.count_nonzero(~pred & gt & inside)
            out["ground_accuracy"] = float(np.mean(pred[inside] == gt[inside]))
            out["ground_precision"] = tp / max(tp + fp, 1)
            out["ground_recall"] = tp / max(tp + fn, 1)
            continue
        sel = (ann["timestamp_ns"] == t_ns) & (ann["num_interior_pts"] >= AV2_MIN_INTERIOR)
        rows = np.flatnonzero(sel)
        yaws = np.array([_yaw_of(_av2_pose(ann, int(r))) for r in rows])
        boxes = ObjectBoxes(
            t_ns, "base_link", rows.astype(np.int64), [str(ann["category"][r]) for r in rows],
            np.stack([ann["tx_m"][rows], ann["ty_m"][rows], ann["tz_m"][rows]], axis=1),
            np.stack([ann["length_m"][rows], ann["width_m"][rows], ann["height_m"][rows]], 1),
            yaws, np.zeros((rows.size, 3)),
        )  # fmt: skip
        pts_ego = (result.points_world - T_city_ego[:3, 3]) @ T_city_ego[:3, :3]
        in_box = points_in_boxes(pts_ego, boxes, BOX_MARGIN_M)
        objs = [int(i) for i in result.objects]
        overlap = np.zeros((len(objs), len(boxes)))
        n_pts = np.zeros(len(objs))
        for a, oid in enumerate(objs):
            mine = in_box[result.point_entity_ids == oid]
            n_pts[a] = mine.size
            overlap[a] = np.bincount(mine[mine >= 0], minlength=len(boxes))[: len(boxes)]
        ok = overlap >= 0.5 * n_pts[:, None]
        r_idx, c_idx = linear_sum_assignment(np.where(ok, -overlap, 0.0))
        pairs = [(r, c) for r, c in zip(r_idx, c_idx, strict=True) if ok[r, c] and overlap[r, c]]
        out["cuboid_recall"] = len(pairs) / max(len(boxes), 1)
        out["cuboids_scored"] = float(len(boxes))
        # purity: the share of each recalled object's points inside its cuboid (recall is not
        # bought with fragments nor with objects that swallow their surroundings)
        purity = [overlap[r, c] / n_pts[r] for r, c in pairs]
        out["cuboid_purity_mean"] = float(np.mean(purity)) if purity else float("nan")
        out["cuboid_purity_min"] = float(np.min(purity)) if purity else float("nan")
        for cls in sorted(set(boxes.classes)):
            k = [i for i, name in enumerate(boxes.classes) if name == cls]
            got = sum(1 for _, c in pairs if c in k)
            out[f"recall_{cls.lower()}"] = f"{got}/{len(k)}"
    return out


def _yaw_of(T: np.ndarray) -> float:
    return math.atan2(T[1, 0], T[0, 0])


@pytest.mark.eval
@pytest.mark.real_data
def test_eval_av2_cuboid_recall_and_ground(real_data: Path) -> None:
    from bench.results import record

    fig = run_av2(real_data / "av2")
    cmd = "make eval"
    record("sp_levels_av2_cuboid_recall", fig["cuboid_recall"], "ratio", command=cmd)
    record("sp_levels_av2_cuboid_purity", fig["cuboid_purity_mean"], "ratio", command=cmd)
    record("sp_levels_av2_cuboid_purity_min", fig["cuboid_purity_min"], "ratio", command=cmd)
    record("sp_levels_av2_ground_accuracy", fig["ground_accuracy"], "ratio", command=cmd)
    record("sp_levels_av2_ground_precision", fig["ground_precision"], "ratio", command=cmd)
    record("sp_levels_av2_ground_recall", fig["ground_recall"], "ratio", command=cmd)
    print(fig)
    assert fig["cuboids_scored"] >= 20
    assert fig["ground_accuracy"] > 0.9
    assert fig["cuboid_recall"] > 0.6
    # recall is not bought with objects that swallow their surroundings: on average a recalled
    # object's points lie in its cuboid. Not every one: a pedestrian standing against a car
    # is part of the car's object (40 of its 170 points), and faces joined along the line of
    # sight (sp.segments.merge_grazing) can take in a neighbour (purity_min, recorded)
    assert fig["cuboid_purity_mean"] > 0.9

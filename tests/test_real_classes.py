"""Level-4/5 classes on real scans against their per-point labels: SemanticKITTI cars (class 10,
instance ids in the high 16 bits) and Argoverse 2 cuboids.

An object is found when an object entity holds at least half of the labelled object's points
in some sweep, or at least half of the entity's points are the object's. The class library's
prototypes are fitted on simulated training seeds only (wm.fit_classes); these scans are
evaluation data. Run as a script for the numbers:
``.venv/bin/python tests/test_real_classes.py [REAL_DATA_FOLDER]``.
"""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

import kd_store
from kd_store import Level, Status
from logs import open_log
from wm.config import NodeConfig, PoseSource
from wm.node import WorldModelNode
from wm.truth import CLASS_ALIASES

KITTI_CAR = 10
MIN_CAR_POINTS = 50
MIN_CUBOID_POINTS = 20


def _run(folder: Path, config: NodeConfig) -> tuple[kd_store.KnowledgeDatabase, list, object]:
    """Feed the log through a node; returns (its KD, open, the SP results, the log source)."""
    kd, cycles, source, _ = _run_node(folder, config)
    return kd, [c.sp_result for c in cycles if c.sp_result is not None], source


def _run_node(folder: Path, config: NodeConfig):
    """(KD, cycles, log source, node) of the log fed through a node."""
    source = open_log(folder)
    kd = kd_store.open(":memory:")
    node = WorldModelNode(kd, config)
    cycles = []
    for frame in source.frames():
        cycles += node.feed(frame)
    cycles += node.finish()
    return kd, cycles, source, node


def odometry_motion_error(cycles: list, truth) -> tuple[float, float]:
    """(error m, true motion m) of the motion from the first to the last cycle's pose: the
    estimated ``inv(T0) T1`` against the true one at the same times (the relative motion
    needs no alignment: the odometry's world is its own first pose, the truth's a city)."""
    from core.geometry import se3_inverse

    first, last = cycles[0], cycles[-1]
    est = se3_inverse(first.T_world_body) @ last.T_world_body
    true = se3_inverse(truth.at(first.t_pose_ns)) @ truth.at(last.t_pose_ns)
    return float(np.linalg.norm(est[:3, 3] - true[:3, 3])), float(np.linalg.norm(true[:3, 3]))


def _object_of(ids: np.ndarray, member: np.ndarray) -> int | None:
    """The entity id (or None) that holds >= half of ``member`` points, or whose points are
    mostly ``member``; ids (N,) int64 entity per point (-1 none), member (N,) bool."""
    inside = ids[member & (ids >= 0)]
    if inside.size == 0:
        return None
    cand, n_in = np.unique(inside, return_counts=True)
    n_all = np.array([(ids == c).sum() for c in cand])
    ok = (n_in >= 0.5 * member.sum()) | (n_in >= 0.5 * n_all)
    if not ok.any():
        return None
    return int(cand[ok][np.argmax(n_in[ok])])


def _group_counts(kd: kd_store.KnowledgeDatabase) -> Counter:
    """Confirmed entities per most specific class."""
    return Counter(
        f.most_specific_class
        for f in kd.entities()
        if f.status == Status.CONFIRMED and f.level in (Level.OBJECT, Level.GROUP)
    )


def kitti_scores(folder: Path) -> dict:
    """Per car instance with >= MIN_CAR_POINTS in a scan: found by a confirmed object entity?
    classified vehicle? and the confirmed person / crowd / convoy counts. ``recall_alone``
    counts a car only where the entity that found it is at least half this car (an entity
    over three parked cars finds each of them in ``recall``)."""
    kd, results, source = _run(folder, NodeConfig())
    cars: dict[int, dict] = {}
    for i, r in enumerate(results):
        full = source.labels(i)
        lab = full[r.point_index]  # the points the egosphere image kept
        cls, inst = lab & 0xFFFF, lab >> 16
        for k in np.unique(full[(full & 0xFFFF) == KITTI_CAR] >> 16):
            if (full == (k << 16 | KITTI_CAR)).sum() < MIN_CAR_POINTS:  # points in the scan
                continue
            member = (cls == KITTI_CAR) & (inst == k)
            row = cars.setdefault(int(k), {"found": False, "vehicle": False, "classes": set()})
            eid = _object_of(r.point_entity_ids, member)
            if eid is None or eid not in kd:
                continue
            f = kd.get(eid)
            if f.status != Status.CONFIRMED:
                continue
            row["found"] = True
            row["classes"].add(f.most_specific_class)
            row["vehicle"] |= "vehicle" in f.generic_classes
            # how much of the entity is this car: an entity over three parked cars "finds" each
            of_entity = r.point_entity_ids == eid
            purity = float((of_entity & member).sum() / max(of_entity.sum(), 1))
            row["purity"] = max(row.get("purity", 0.0), purity)
    counts = _group_counts(kd)
    n = max(len(cars), 1)
    alone = sum(c["found"] and c.get("purity", 0.0) >= 0.5 for c in cars.values())
    return {
        "cars": len(cars),
        "recall": sum(c["found"] for c in cars.values()) / n,
        "recall_alone": alone / n,
        "vehicle_of_found": sum(c["vehicle"] for c in cars.values())
        / max(sum(c["found"] for c in cars.values()), 1),
        "per_car": {k: (c["found"], sorted(map(str, c["classes"]))) for k, c in cars.items()},
        "person": counts.get("person", 0),
        "crowd": counts.get("crowd", 0),
        "convoy": counts.get("convoy", 0),
        "confirmed": dict(counts),
    }


def _inside(points: np.ndarray, center: np.ndarray, size: np.ndarray, yaw: float) -> np.ndarray:
    """(N,) bool points (N, 3) inside the box (centre, l w h, yaw about z), same frame."""
    d = points - center
    c, s = np.cos(yaw), np.sin(yaw)
    u, v = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
    return (
        (np.abs(u) <= size[0] / 2) & (np.abs(v) <= size[1] / 2) & (np.abs(d[:, 2]) <= size[2] / 2)
    )


def av2_scores(folder: Path) -> dict:
    """Cuboids with >= MIN_CUBOID_POINTS interior points in a sweep: found by an object entity
    (any status: two sweeps are too few to confirm a track) and does its class agree with the
    cuboid's category (CLASS_ALIASES)? On odometry poses (LADAR alone: the log has no wheel
    odometry); points and cuboids are compared per sweep, so no alignment is needed.

    ``recall_framed`` is the recall over the cuboids with that many points in a sweep where
    any object can have an entity: a hypothesis gets its KD frame at its ``birth_hits``-th
    hit (M-of-N birth), so the sweeps before that one hold none (the bound the simulated
    worlds' ``recall_startup`` shows too); ``first_sweeps_only`` counts the cuboids that
    have the points in those sweeps alone."""
    kd, cycles, source, node = _run_node(folder, NodeConfig(pose_source=PoseSource.ODOMETRY))
    results = [c.sp_result for c in cycles if c.sp_result is not None]
    first_framed = node.engine_config.sp.birth_hits - 1  # index of the first sweep with frames
    odometry_error_m, moved_m = odometry_motion_error(cycles, node.truth)
    sweeps = {int(s.t_ns): s for s in source.frames() if type(s).__name__ == "LadarScan"}
    boxes = {b.t_ns: b for b in source.boxes()}
    rows: dict[int, dict] = {}
    for i, r in enumerate(results):
        scan, b = sweeps.get(int(r.t_ns)), boxes.get(int(r.t_ns))
        if scan is None or b is None:
            continue
        # the scan's frame (the LiDAR's) -> base_link, the cuboids' frame
        T = node.T_body_ladar
        pts = scan.points_xyz[r.point_index].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
        for j in range(len(b.ids)):
            member = _inside(pts, b.centers[j], b.sizes[j], float(b.yaws[j]))
            if member.sum() < MIN_CUBOID_POINTS:
                continue
            true_cls = CLASS_ALIASES.get(b.classes[j], b.classes[j].lower())
            row = rows.setdefault(
                int(b.ids[j]), {"found": False, "agree": False, "framed": False, "true": true_cls}
            )
            row["framed"] |= i >= first_framed
            eid = _object_of(r.point_entity_ids, member)
            if eid is None or eid not in kd:
                continue
            f = kd.get(eid)
            row["found"] = True
            row["agree"] |= true_cls in f.generic_classes
            row.setdefault("got", set()).add(f.most_specific_class)
    n = max(len(rows), 1)
    found = [r for r in rows.values() if r["found"]]
    framed = [r for r in rows.values() if r["framed"]]
    known = [r for r in found if r["true"] in ("vehicle", "person", "post")]
    by_class = Counter((r["true"], str(sorted(map(str, r.get("got", ()))))) for r in found)
    return {
        "cuboids": len(rows),
        "recall": len(found) / n,
        "recall_framed": sum(r["found"] for r in framed) / max(len(framed), 1),
        "first_sweeps_only": len(rows) - len(framed),
        "class_agreement": sum(r["agree"] for r in known) / max(len(known), 1),
        "n_known": len(known),
        "by_class": dict(by_class),
        "missed": Counter(r["true"] for r in rows.values() if not r["found"]),
        "confirmed": dict(_group_counts(kd)),
        "odometry_error_m": odometry_error_m,
        "moved_m": moved_m,
        "skipped": dict(node.stats.skipped),
    }


@pytest.mark.real_data
@pytest.mark.eval
def test_kitti_cars_are_found_and_are_vehicles(real_data: Path) -> None:
    from bench.results import record

    s = kitti_scores(real_data / "kitti" / "sequences" / "00")
    cmd = "make eval"
    record("kitti_car_recall", s["recall"], "", target=">= 0.9", command=cmd)
    record("kitti_cars_classified_vehicle", s["vehicle_of_found"], "", target=">= 0.8",
           command=cmd)  # fmt: skip
    record("kitti_car_recall_alone", s["recall_alone"], "", command=cmd)  # entity mostly the car
    record("kitti_false_person_crowd_convoy", s["person"] + s["crowd"] + s["convoy"], "entities",
           target="0 (the labels have no persons)", command=cmd)  # fmt: skip
    assert s["cars"] == 10
    assert s["recall"] >= 0.9, s
    # each car's own entity: 8 of 10 (car 209, in the shadow of 210 and 504, is mostly part of
    # 504's entity; car 219 is never confirmed)
    assert s["recall_alone"] >= 0.8, s
    # target missed, recorded above: 6 of the 9 cars found classified vehicle (0.67; 0.8
    # wanted): cars 208, 210 and 216, seen in part (1.5-2.3 m of them, 1.2-1.5 m high, with
    # 0.06-0.28 m of clearance under them where the whole cars show 0.5-0.9 m), are called
    # rock. 7 of 9 with the classes fitted on simulator 8: the refit on simulator 9's smoother
    # ground (more low rocks and bushes seen, so more of them to learn from) moved car 208's
    # second and last view to vehicle 0.53 against rock 0.43, short of the margin that
    # changes a class once set (rock 0.52 against vehicle 0.42 at its first view). 5 of 9
    # before level 4 measured texture (sp.computation.segment_roughness: the cars' returns
    # are as smooth as the simulator's vehicles', 0.02-0.09 m, where its bushes and crowns
    # scatter 0.25-0.5 m), when 210 was called bush and 211 tree; 6 of 9 before the level-4
    # discriminant.
    # No person, crowd or convoy: the last object called person where the labels have none,
    # 207 "other-object" returns on an upright plane 1.09 m high and 0.9 x 0.6 m across, is
    # street furniture since the simulator has bins and cabinets (version 6) to learn that
    # class from; before, the classes fitted on the simulator's sensors took such real
    # clutter of person size for persons (2 of them before the scene's class mix). Car 213 was
    # called a wall while a sliver of it that had joined its track gave the track its shape
    # (sp.level4_objects.largest_segment_of_track). The vehicle share was 0.78 while three
    # cars parked nose to tail were one entity and that one "vehicle" counted for each (a
    # grouping link across the returns between them, since removed). These bounds guard
    # against worse
    assert s["vehicle_of_found"] >= 0.65, s
    assert s["person"] == 0 and s["crowd"] == 0 and s["convoy"] == 0, s


@pytest.mark.real_data
@pytest.mark.eval
def test_av2_cuboids_are_found(real_data: Path) -> None:
    from bench.results import record

    s = av2_scores(real_data / "av2")
    record("av2_cuboid_recall", s["recall"], "", target=">= 0.9", command="make eval")
    record("av2_cuboid_recall_framed", s["recall_framed"], "", command="make eval")
    record("av2_class_agreement", s["class_agreement"], "", command="make eval")
    record("av2_odometry_error", s["odometry_error_m"], "m", target="< 0.2", command="make eval")
    # the log's two sweeps are 0.1 s apart: the vehicle moves a few centimetres between them,
    # and the odometry (LADAR alone: no wheel odometry in the log) must find that motion
    assert s["moved_m"] < 1.0 and s["odometry_error_m"] < 0.2, s
    # every message of the log is taken, the annotations of tracks seen once (velocity
    # unknown) among them
    assert s["skipped"] == {}, s
    # the target (0.9) is missed: measured on odometry poses 23 of 26 cuboids with >= 20
    # interior points found (recall 0.885; missed: two vehicles and a bicycle). The three
    # have 20-26 points in the first sweep and 18-19 in the second, so they count by the
    # first alone, which by the M-of-N birth holds no object entity; of the cuboids with the
    # points in the second sweep all 23 are found (two of the three missed are held there
    # too, by fewer points than count). Class agreement is 12 of 21 (0.571); how the refits
    # of the class library moved it is in docs/evaluation.md. These bounds guard against
    # losing more
    assert s["recall"] >= 0.85, s
    assert s["recall_framed"] >= 0.95, s
    assert s["class_agreement"] >= 0.4, s


if __name__ == "__main__":
    root = Path(sys.argv[1]) if len(sys.argv) > 1 else Path("/work/shared/data/real")
    print("KITTI", kitti_scores(root / "kitti" / "sequences" / "00"))
    print("AV2", av2_scores(root / "av2"))

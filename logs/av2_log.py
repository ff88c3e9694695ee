"""Argoverse 2 sensor logs (the folder of one log: ``sensors/lidar/<t_ns>.feather`` ...).

* ``sensors/lidar/<t_ns>.feather`` (x, y, z float16 in the ego-vehicle frame, intensity uint8,
  laser_number uint8, offset_ns int32) -> :class:`LadarScan` on ``/ladar/points``, stamped
  with the file's ``t_ns``, ``t_offset_ns`` = offset_ns, intensity 0..255 as float32.
  The points are moved into frame ``ladar``, the upper LiDAR's (``up_lidar`` of
  ``calibration/egovehicle_SE3_sensor.feather``, published as the static transform
  ``base_link -> ladar`` on ``/tf_static``): the ego frame's origin lies on the ground under
  the rear axle, 1.6 m below the sensors, and SP's egosphere and ground segmentation look
  from the sensor. The lower LiDAR's points keep their own positions (its origin is 0.12 m
  below the upper one's). Without the calibration file they stay in ``base_link``.
* ``ring`` = laser_number: each of the two stacked 32-beam units' firing index (0-31 the
  upper unit, 32-63 the lower, mounted upside down), which interleaves elevations; SP's
  level 1 ranks such rings by elevation (:func:`sp.level1.ring_rows`).
* ``city_SE3_egovehicle.feather`` -> :class:`GroundTruthPose` ``world`` (the AV2 city frame)
  -> ``base_link`` on ``/ground_truth/pose``.
* ``annotations.feather`` (cuboids in the ego frame at their timestamp) ->
  :class:`ObjectBoxes` on ``/ground_truth/objects`` in ``base_link``: ids are the track
  UUIDs numbered 0, 1, ... in order of first appearance (stable over the log), classes are
  AV2 category names (``REGULAR_VEHICLE``, ``PEDESTRIAN``, ...), sizes are (length, width,
  height), yaw from the cuboid quaternion. AV2 gives no velocities: they are the central
  differences (one-sided at a track's ends) of each track's city-frame centres over time,
  rotated into the ego frame (m/s over ground; NaN for a track seen once).

Reading needs only pyarrow (no pandas).
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from core.geometry import BODY, LADAR, WORLD, interpolate_pose, quat_to_matrix
from logs.source import LogSource, TopicInfo
from logs.types import (
    GroundTruthPose,
    LadarScan,
    LogError,
    LogMessage,
    ObjectBoxes,
    TransformFrame,
)

LADAR_TOPIC = "/ladar/points"
POSE_TOPIC = "/ground_truth/pose"
BOXES_TOPIC = "/ground_truth/objects"
TF_STATIC_TOPIC = "/tf_static"
# the calibration entry whose pose is the ``ladar`` frame
LADAR_SENSOR = "up_lidar"


def _read_feather(path: Path, columns: list[str]) -> dict[str, np.ndarray]:
    import pyarrow.feather as feather

    try:
        table = feather.read_table(path, columns=columns)
    except Exception as exc:  # pyarrow raises several kinds for a bad file
        raise LogError(f"{path}: cannot read as Feather with columns {columns}: {exc}") from exc
    return {c: table.column(c).to_numpy() for c in columns}


def _quat_wxyz_to_matrices(
    qw: np.ndarray, qx: np.ndarray, qy: np.ndarray, qz: np.ndarray
) -> np.ndarray:
    """(N, 3, 3) rotations from AV2's quaternion columns (w first)."""
    return np.stack([quat_to_matrix(np.array(q)) for q in zip(qx, qy, qz, qw, strict=True)])


class Av2LogSource(LogSource):
    """One Argoverse 2 sensor log folder."""

    format_name = "Argoverse 2 sensor log"

    @classmethod
    def accepts(cls, path: Path) -> bool:
        return path.is_dir() and any((path / "sensors" / "lidar").glob("*.feather"))

    def __init__(self, path: str | Path, *, skip_corrupt: bool = False) -> None:
        super().__init__(path, skip_corrupt=skip_corrupt)
        self.sweep_files = sorted(
            (self.path / "sensors" / "lidar").glob("*.feather"), key=lambda p: int(p.stem)
        )
        try:
            self.sweep_t_ns = np.array([int(p.stem) for p in self.sweep_files], dtype=np.int64)
        except ValueError as exc:
            raise LogError(f"{self.path}: lidar files must be named <t_ns>.feather") from exc
        self._poses: tuple[np.ndarray, np.ndarray] | None = None
        self._boxes: list[ObjectBoxes] | None = None
        self._T_body_ladar: np.ndarray | None = None
        self._calibrated: bool | None = None

    # -------------------------------------------------------------- sensor geometry
    @property
    def T_body_ladar(self) -> np.ndarray | None:
        """(4, 4) pose of the ``ladar`` frame (the upper LiDAR) in ``base_link``, from the
        calibration file; None when the log has none (scans then stay in ``base_link``)."""
        if self._calibrated is None:
            self._calibrated = False
            path = self.path / "calibration" / "egovehicle_SE3_sensor.feather"
            if path.is_file():
                cols = ["sensor_name", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m"]
                c = _read_feather(path, cols)
                names = [str(n) for n in c["sensor_name"]]
                if LADAR_SENSOR not in names:
                    raise LogError(f"{path}: no {LADAR_SENSOR!r} among sensors {names}")
                k = names.index(LADAR_SENSOR)
                T = np.eye(4)
                T[:3, :3] = _quat_wxyz_to_matrices(
                    c["qw"][k : k + 1], c["qx"][k : k + 1], c["qy"][k : k + 1], c["qz"][k : k + 1]
                )[0]
                T[:3, 3] = [c["tx_m"][k], c["ty_m"][k], c["tz_m"][k]]
                self._T_body_ladar = T
                self._calibrated = True
        return self._T_body_ladar

    # -------------------------------------------------------------- ground truth tables
    def poses(self) -> tuple[np.ndarray, np.ndarray]:
        """(t_ns (P,) int64, T_world_body (P, 4, 4)) from city_SE3_egovehicle.feather."""
        if self._poses is None:
            path = self.path / "city_SE3_egovehicle.feather"
            if not path.is_file():
                self._poses = (np.zeros(0, np.int64), np.zeros((0, 4, 4)))
                return self._poses
            cols = ["timestamp_ns", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m"]
            c = _read_feather(path, cols)
            order = np.argsort(c["timestamp_ns"], kind="stable")
            T = np.tile(np.eye(4), (order.size, 1, 1))
            T[:, :3, :3] = _quat_wxyz_to_matrices(c["qw"], c["qx"], c["qy"], c["qz"])[order]
            T[:, :3, 3] = np.stack([c["tx_m"], c["ty_m"], c["tz_m"]], axis=1)[order]
            self._poses = (c["timestamp_ns"][order].astype(np.int64), T)
        return self._poses

    def pose_at(self, t_ns: int) -> np.ndarray:
        """T_world_body at ``t_ns``, interpolated between the nearest poses (clamped at ends)."""
        times, T = self.poses()
        if times.size == 0:
            raise LogError(f"{self.path}: no city_SE3_egovehicle.feather poses")
        j = int(np.searchsorted(times, t_ns))
        if j < times.size and times[j] == t_ns:
            return T[j]
        if j == 0 or j == times.size:
            return T[min(j, times.size - 1)]
        alpha = (t_ns - times[j - 1]) / (times[j] - times[j - 1])
        return interpolate_pose(T[j - 1], T[j], alpha)

    def boxes(self) -> list[ObjectBoxes]:
        """Every annotated instant as ObjectBoxes (ego frame), in time order."""
        if self._boxes is None:
            self._boxes = self._read_boxes()
        return self._boxes

    def _read_boxes(self) -> list[ObjectBoxes]:
        path = self.path / "annotations.feather"
        if not path.is_file():
            return []
        cols = ["timestamp_ns", "track_uuid", "category", "length_m", "width_m", "height_m"]
        cols += ["qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m"]
        c = _read_feather(path, cols)
        t = c["timestamp_ns"].astype(np.int64)
        order = np.argsort(t, kind="stable")
        c = {k: v[order] for k, v in c.items()}
        t = t[order]
        uuids = c["track_uuid"].astype(str)
        first: dict[str, int] = {}
        ids = np.array([first.setdefault(u, len(first)) for u in uuids], dtype=np.int64)
        centers = np.stack([c["tx_m"], c["ty_m"], c["tz_m"]], axis=1).astype(np.float64)
        sizes = np.stack([c["length_m"], c["width_m"], c["height_m"]], axis=1).astype(np.float64)
        qw, qx, qy, qz = (c[k].astype(np.float64) for k in ("qw", "qx", "qy", "qz"))
        yaws = np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
        velocities = self._velocities(t, ids, centers)
        classes = c["category"].astype(str)
        instants = np.flatnonzero(np.r_[True, t[1:] != t[:-1]])
        bounds = np.r_[instants, t.size]
        return [
            ObjectBoxes(
                t_ns=int(t[a]),
                frame_id=BODY,
                ids=ids[a:b],
                classes=classes[a:b].tolist(),
                centers=centers[a:b],
                sizes=sizes[a:b],
                yaws=yaws[a:b],
                velocities=velocities[a:b],
                topic=BOXES_TOPIC,
            )
            for a, b in itertools.pairwise(bounds)
        ]

    def _velocities(self, t: np.ndarray, ids: np.ndarray, centers: np.ndarray) -> np.ndarray:
        """Per-row velocity (m/s, ego frame): central differences of city-frame centres."""
        if self.poses()[0].size == 0:
            return np.full(centers.shape, np.nan)
        T_world_body = {int(s): self.pose_at(int(s)) for s in np.unique(t)}
        R = np.stack([T_world_body[int(s)][:3, :3] for s in t])
        centers_world = np.einsum("nij,nj->ni", R, centers) + np.stack(
            [T_world_body[int(s)][:3, 3] for s in t]
        )
        v_world = np.full(centers.shape, np.nan)
        for track in np.unique(ids):
            rows = np.flatnonzero(ids == track)
            if rows.size >= 2:
                seconds = (t[rows] - t[rows[0]]) * 1e-9
                v_world[rows] = np.gradient(centers_world[rows], seconds, axis=0)
        return np.einsum("nji,nj->ni", R, v_world)  # R^T v: world -> ego axes

    # -------------------------------------------------------------- LogSource
    def _sweep(self, i: int) -> LadarScan:
        path = self.sweep_files[i]
        c = _read_feather(path, ["x", "y", "z", "intensity", "laser_number", "offset_ns"])
        xyz = np.stack([c["x"], c["y"], c["z"]], axis=1).astype(np.float64)
        finite = np.isfinite(xyz).all(axis=1)
        n_bad = int(finite.size - finite.sum())
        if n_bad:
            self.stats.dropped_nonfinite_points += n_bad
        xyz = xyz[finite]
        T = self.T_body_ladar
        if T is not None:  # p_ladar = R^T (p_body - t)
            xyz = (xyz - T[:3, 3]) @ T[:3, :3]
        return LadarScan(
            t_ns=int(self.sweep_t_ns[i]),
            frame_id=BODY if T is None else LADAR,
            points_xyz=xyz.astype(np.float32),
            intensity=c["intensity"][finite].astype(np.float32),
            t_offset_ns=c["offset_ns"][finite].astype(np.int64),
            ring=c["laser_number"][finite].astype(np.uint16),
            topic=LADAR_TOPIC,
        )

    def _first_t_ns(self) -> int | None:
        """The earliest stamp of any message of the log, or None when it has none."""
        times = [int(t[0]) for t in (self.sweep_t_ns, self.poses()[0]) if t.size]
        if self.boxes():
            times.append(self.boxes()[0].t_ns)
        return min(times) if times else None

    def _streams(
        self, kinds: tuple[type, ...] | None, topics: frozenset[str] | None
    ) -> list[Iterator[tuple[int, int, LogMessage]]]:
        def wanted(kind: type, topic: str) -> bool:
            return (kinds is None or kind in kinds) and (topics is None or topic in topics)

        streams = []
        t0 = self._first_t_ns()
        if wanted(TransformFrame, TF_STATIC_TOPIC) and self.T_body_ladar is not None and t0:
            tf = TransformFrame(
                t0, BODY, LADAR, self.T_body_ladar.copy(), static=True, topic=TF_STATIC_TOPIC
            )
            streams.append(iter([(t0, -1, tf)]))
        if wanted(LadarScan, LADAR_TOPIC):
            streams.append((int(t), 0, self._sweep(i)) for i, t in enumerate(self.sweep_t_ns))
        if wanted(GroundTruthPose, POSE_TOPIC):
            times, T = self.poses()
            streams.append(
                (int(s), 1, GroundTruthPose(int(s), WORLD, BODY, T[k], topic=POSE_TOPIC))
                for k, s in enumerate(times)
            )
        if wanted(ObjectBoxes, BOXES_TOPIC):
            streams.append((b.t_ns, 2, b) for b in self.boxes())
        return streams

    def _frames(
        self, kinds: tuple[type, ...] | None, topics: frozenset[str] | None
    ) -> Iterator[LogMessage]:
        for _, _, frame in heapq.merge(*self._streams(kinds, topics), key=lambda x: x[:2]):
            yield frame

    def _topics(self) -> list[TopicInfo]:
        out = []
        t0 = self._first_t_ns()
        if self.T_body_ladar is not None and t0 is not None:
            out.append(TopicInfo(TF_STATIC_TOPIC, "TransformFrame", 1, t0, t0))
        if self.sweep_t_ns.size:
            t = self.sweep_t_ns
            out.append(TopicInfo(LADAR_TOPIC, "LadarScan", t.size, int(t.min()), int(t.max())))
        times = self.poses()[0]
        if times.size:
            out.append(
                TopicInfo(POSE_TOPIC, "GroundTruthPose", times.size, int(times[0]), int(times[-1]))
            )
        boxes = self.boxes()
        if boxes:
            out.append(
                TopicInfo(BOXES_TOPIC, "ObjectBoxes", len(boxes), boxes[0].t_ns, boxes[-1].t_ns)
            )
        return out

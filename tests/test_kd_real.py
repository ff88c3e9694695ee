"""The KD on a real scene: the Argoverse 2 sample's annotated cuboids (114 tracks over 156
lidar sweeps) become entity frames with their states in the city frame; as-of, region, SQL and
restart queries are checked against the annotations themselves."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow.feather as feather
import pytest

import kd_store
from core.geometry import matrix_to_quat, quat_to_matrix
from kd_store import Attribute, Circle, Level, StateBatch

#: AV2 category -> generic class of the default library (bicycles and strollers have none).
CLASS_OF = {
    "REGULAR_VEHICLE": "vehicle",
    "BOX_TRUCK": "vehicle",
    "TRUCK_CAB": "vehicle",
    "VEHICULAR_TRAILER": "vehicle",
    "MOTORCYCLE": "vehicle",
    "PEDESTRIAN": "person",
    "BOLLARD": "post",
    "CONSTRUCTION_CONE": "post",
}


class Scene:
    """Annotations in the city frame: per row track id, t_ns, position, quaternion."""

    def __init__(self, root: Path) -> None:
        a = feather.read_table(root / "av2" / "annotations.feather")
        poses = feather.read_table(root / "av2" / "city_SE3_egovehicle.feather")
        self.t_ns = a["timestamp_ns"].to_numpy()
        pose_t = poses["timestamp_ns"].to_numpy()
        k = np.searchsorted(pose_t, self.t_ns)
        assert np.array_equal(pose_t[k], self.t_ns)  # every sweep has its ego pose

        def quats(t: object) -> np.ndarray:
            return np.stack([t[c].to_numpy() for c in ("qx", "qy", "qz", "qw")], axis=1)

        def xyz(t: object) -> np.ndarray:
            return np.stack([t[c].to_numpy() for c in ("tx_m", "ty_m", "tz_m")], axis=1)

        R_city_ego = np.stack([quat_to_matrix(q) for q in quats(poses)])[k]
        self.ego_city = xyz(poses)[k]
        self.pos = np.einsum("nij,nj->ni", R_city_ego, xyz(a)) + self.ego_city
        R_box = np.stack([quat_to_matrix(q) for q in quats(a)])
        self.quat = np.stack([matrix_to_quat(R) for R in R_city_ego @ R_box])
        uuids = a["track_uuid"].to_pylist()
        self.tracks = sorted(set(uuids))
        self.track = np.array([self.tracks.index(u) for u in uuids])
        self.category = a["category"].to_pylist()
        self.size = np.stack([a[c].to_numpy() for c in ("length_m", "width_m", "height_m")], 1)
        self.times = np.unique(self.t_ns)

    def latest(self, t_ns: int) -> dict[int, np.ndarray]:
        """Ground truth as of ``t_ns``: each track's last annotated position."""
        out = {}
        for i in np.flatnonzero(self.t_ns <= t_ns):  # rows are in time order per track
            out[int(self.track[i])] = self.pos[i]
        return out


@pytest.fixture(scope="module")
def scene(real_data: Path) -> Scene:
    return Scene(real_data)


def _load(kd: kd_store.KnowledgeDatabase, s: Scene) -> None:
    for tid, uuid in enumerate(s.tracks):
        row = int(np.flatnonzero(s.track == tid)[0])
        cls = CLASS_OF.get(s.category[row])
        attrs = {
            n: Attribute(estimated=float(v))
            for n, v in zip(("length_m", "width_m", "height_m"), s.size[row], strict=True)
        }
        kd.add_entity(
            uuid, Level.OBJECT, id=tid, status="confirmed", confidence=1.0,
            generic_classes=() if cls is None else (cls,), attributes=attrs,
        )  # fmt: skip
    for t in s.times:  # one batch a sweep, as SP would emit them
        m = s.t_ns == t
        kd.ingest(StateBatch(s.track[m], s.t_ns[m], "city", s.pos[m], s.quat[m]))


@pytest.mark.real_data
def test_real_scene_as_of_region_sql_and_restart(scene: Scene, tmp_path: Path) -> None:
    path = tmp_path / "av2.kd"
    kd = kd_store.open(path)
    _load(kd, scene)
    assert len(kd.entity_ids()) == len(scene.tracks) == 114
    for t in scene.times[:: len(scene.times) // 12]:
        truth = scene.latest(int(t))
        got = kd.as_of(int(t))
        assert set(got) == set(truth)
        assert all(np.array_equal(got[k].position_xyz, truth[k]) for k in truth)
        sql = kd.sql(f"SELECT entity_id, x, y, z FROM entity_states_as_of({int(t)})")
        xyz = np.stack([sql[c].to_numpy() for c in ("x", "y", "z")], axis=1)
        ids = sql["entity_id"].to_numpy()
        assert all(np.array_equal(xyz[i], truth[int(k)]) for i, k in enumerate(ids))

    final = scene.latest(int(scene.times[-1]))
    vehicles = {int(i) for i in np.unique(scene.track) if CLASS_OF.get(
        scene.category[int(np.flatnonzero(scene.track == i)[0])]) == "vehicle"}  # fmt: skip
    for ego in scene.ego_city[:: len(scene.ego_city) // 5]:
        c = (float(ego[0]), float(ego[1]))
        inside = {k for k, p in final.items() if np.hypot(p[0] - c[0], p[1] - c[1]) <= 30.0}
        assert set(kd.region(Circle("city", c, 30.0)).tolist()) == inside
        got = kd.region(Circle("city", c, 30.0), classes=["vehicle"])
        assert set(got.tolist()) == inside & vehicles
    assert len(inside) > 5  # the check saw a real neighbourhood

    counts = kd.sql(
        "SELECT coalesce(e.class_name, 'none') AS c, count(*) AS n FROM entity_states s "
        "JOIN entities e ON e.id = s.entity_id GROUP BY ALL"
    ).to_pydict()
    want: dict[str, int] = {}
    for cat in scene.category:
        want[CLASS_OF.get(cat, "none")] = want.get(CLASS_OF.get(cat, "none"), 0) + 1
    assert dict(zip(counts["c"], counts["n"], strict=True)) == want
    kd.close()

    with kd_store.open(path) as kd:  # long-term memory after a restart
        for tid in (0, 57, 113):
            rows = np.flatnonzero(scene.track == tid)
            hist = kd.long_term_history(tid)
            assert [s.t_ns for s in hist] == scene.t_ns[rows].tolist()
            assert np.array_equal(np.stack([s.position_xyz for s in hist]), scene.pos[rows])
            assert np.array_equal(np.stack([s.orientation_xyzw for s in hist]), scene.quat[rows])

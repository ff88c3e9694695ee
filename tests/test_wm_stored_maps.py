"""`wm render --kd` and `wm whatif --kd` work from the KD file a `wm run` wrote, without the
log: the maps rebuilt from its tiles are the live node's final windows (every level and layer,
bit for bit), the pictures are the live maps' pictures, What If finds the same collision and
clearance as the log-driven form, and a KD without tiles is one clear error line.

Every run uses odometry poses (the default): the maps lie in the estimated world, which is
aligned to the truth's at the first self pose before it is scored against the true terrain."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from alignment import kd_self_track, true_pose_track

import kd_store
import wm.run
from core.geometry import se3_inverse, transform_points
from fixtures.simulate import simulate_to_log
from kd_store import Level, State, Status
from logs import open_log
from maps.level import LevelConfig, MapLevel
from wm.cli import _parse_waypoints, main, whatif_lines
from wm.config import NodeConfig, PoseSource
from wm.engine_config import EngineConfig
from wm.node import WorldModelNode
from wm.render import render_maps
from wm.tiles import KDTileStore, TileError, stored_maps
from wm.truth import TerrainTruth, elevation_error
from wm.whatif import WaypointPlan, WhatIf

ODOMETRY = ["--poses", "odometry"]  # the default, said explicitly


class Live:
    """What the live node of a `wm run` had at the end."""

    def __init__(self, node: WorldModelNode) -> None:
        self.stack = node.stack
        self.T_world_body = node.stack.T_world_body.copy()
        self.windows = {
            lvl.name: {n: lvl.window(n) for n in lvl.layer_names} for lvl in node.stack.levels
        }


def _run_seen(log: Path, kd: Path, *flags: str) -> Live:
    """`wm run LOG --kd KD` with ``flags``, in this process, so the node is seen."""
    nodes: list[WorldModelNode] = []

    class Recorded(WorldModelNode):
        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            nodes.append(self)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(wm.run, "WorldModelNode", Recorded)
        rc = main(["run", str(log), "--kd", str(kd), *flags, "--no-progress",
                   "--decode-in-process"])  # fmt: skip
    assert rc == 0 and len(nodes) == 1
    return Live(nodes[0])


@pytest.fixture(scope="module")
def ran(tmp_path_factory) -> tuple[Path, Path, Live]:
    """A 1.5 s simulated log through `wm run --kd` (in this process, so the node is seen)."""
    d = tmp_path_factory.mktemp("stored")
    log = simulate_to_log("default", d / "s.mcap", seconds=1.5, seed=3, progress=False)
    kd = d / "kd.duckdb"
    return log, kd, _run_seen(log, kd, *ODOMETRY)


def test_the_stored_maps_are_the_live_windows(ran) -> None:
    log, kd_path, live = ran
    with kd_store.open(kd_path, read_only=True) as kd:
        maps = stored_maps(kd)
        assert maps.levels == ["primitive", "subsystem", "vehicle", "section"]
        assert np.allclose(maps.T_world_body, live.T_world_body, atol=1e-12)
        for lvl in maps.stack.levels:
            assert set(lvl.layer_names) == set(live.windows[lvl.name])
            for name, arr in live.windows[lvl.name].items():
                assert np.array_equal(lvl.window(name), arr, equal_nan=True), (lvl.name, name)
        assert np.isfinite(maps.stack.level("primitive").window("elevation")).sum() > 10_000
        source = open_log(log)  # and the stored map is the simulator's terrain
        terrain = TerrainTruth.from_log(source.attachments(), source.metadata())
        est = kd_self_track(kd)
        # the estimated world into the truth's at the last self pose, where the stored windows
        # lie (as `wm run` scores its local maps: the odometry's drift is scored apart)
        t1 = est.t_ns[-1]
        T_align = true_pose_track(log).at(t1) @ se3_inverse(est.at(t1))
        err = elevation_error(maps.stack.level("subsystem"), terrain, T_align)
        assert err["cells"] > 1000 and err["rmse_m"] < 0.1, err


def test_render_from_the_kd_alone_draws_the_live_maps(ran, tmp_path: Path, capsys) -> None:
    _, kd_path, live = ran
    assert main(["render", "--kd", str(kd_path), str(tmp_path / "kd")]) == 0
    printed = capsys.readouterr().out.split()
    stored = sorted((tmp_path / "kd").glob("*.png"))
    assert len(stored) == 8 and printed.count("picture") == 8  # 4 levels x (elevation, cost)
    with kd_store.open(kd_path, read_only=True) as kd:
        self_id = stored_maps(kd).self_id
        mine = render_maps(kd, live.stack, self_id, tmp_path / "live")
    assert [p.name for p in stored] == sorted(p.name for p in mine)
    for p in stored:
        a, b = cv2.imread(str(p)), cv2.imread(str(tmp_path / "live" / p.name))
        assert a.shape == b.shape and np.array_equal(a, b), p.name


def _plans_at(kd, T_world_body: np.ndarray) -> tuple[int, list[np.ndarray]]:
    """A confirmed object ahead of the vehicle, and two body-frame plans (t, x, y rows) over
    20 s: one through the object where its constant-velocity prediction will be, one passing
    it 8 m to the side."""
    T_body_world = se3_inverse(T_world_body)
    best = None
    for f in kd.entities():
        if f.name == "self" or f.level < Level.OBJECT or f.status != Status.CONFIRMED:
            continue
        b = transform_points(T_body_world, f.state.position_xyz[None])[0]
        bearing = abs(np.arctan2(b[1], b[0]))
        if bearing < np.radians(45) and (best is None or bearing < best[0]):
            best = (bearing, f)
    assert best is not None, "the log's run confirms an object ahead of the vehicle"
    f = best[1]
    t0_ns = kd.get(max(e.id for e in kd.entities() if e.name == "self")).state.t_ns
    arrive_s = 10.0
    xyz = f.state.position_xyz + (arrive_s + (t0_ns - f.state.t_ns) * 1e-9) * f.state.velocity_xyz
    target = transform_points(T_body_world, xyz[None])[0, :2]
    side = np.array([-target[1], target[0]]) / np.linalg.norm(target) * 8.0
    plans = []
    for offset in (np.zeros(2), side):
        p = target + offset
        plans.append(np.array([[0.0, 0.0, 0.0], [arrive_s, *p], [20.0, *(2 * p)]]))
    return f.id, plans


def _cli_whatif(args: list[str], capsys) -> list[str]:
    assert main(["whatif", *args, "--level", "vehicle"]) == 0
    return capsys.readouterr().out.strip().splitlines()[-4:]


def test_whatif_from_the_kd_alone_finds_what_the_log_driven_form_finds(ran, capsys) -> None:
    log, kd_path, _ = ran
    node = wm.run.run_node(log, ":memory:", NodeConfig(pose_source=PoseSource.ODOMETRY))
    with kd_store.open(kd_path, read_only=True) as kd:
        maps = stored_maps(kd)
        target_id, plans = _plans_at(kd, maps.T_world_body)
        results = []
        for kd_, stack, self_id, T in (
            (node.kd, node.stack, node.self_id, node.stack.T_world_body),
            (kd, maps.stack, maps.self_id, maps.T_world_body),
        ):
            world = [
                WaypointPlan(p[:, 0], transform_points(T, np.c_[p[:, 1:], np.zeros(3)])[:, :2])
                for p in plans
            ]
            results.append(WhatIf(kd_, stack, self_id=self_id).simulate(world, level="vehicle"))
    node.kd.close()
    from_log, from_kd = results
    assert from_kd.collision_entity.tolist() == [target_id, -1]  # through it, then beside it
    assert from_log.collision_entity.tolist() == from_kd.collision_entity.tolist()
    assert np.array_equal(from_log.collision_t_s, from_kd.collision_t_s, equal_nan=True)
    assert from_kd.min_clearance_m[0] == 0.0 and from_kd.min_clearance_m[1] > 1.0
    assert np.allclose(from_log.min_clearance_m, from_kd.min_clearance_m, atol=1e-9)
    assert np.allclose(from_log.xy, from_kd.xy, atol=1e-9)
    for name in ("elevation", "slope", "traversability", "cost", "unknown_fraction"):
        a, b = getattr(from_log, name), getattr(from_kd, name)
        assert np.allclose(a, b, atol=1e-9, equal_nan=True), name
    # the command line says the same in both forms
    text = ";".join(",".join(f"{v:.6f}" for v in row) for row in plans[0])
    by_log = _cli_whatif([str(log), *ODOMETRY, "--waypoints", text], capsys)
    by_kd = _cli_whatif(["--kd", str(kd_path), "--waypoints", text], capsys)
    assert by_kd[:3] == by_log[:3]  # distance, first collision, least clearance
    assert f"first collision: entity {target_id} at" in by_kd[1]


def _kd_without_tiles(path: Path) -> None:
    with kd_store.open(path) as kd:
        me = kd.add_entity("self", Level.OBJECT, status=Status.CONFIRMED, confidence=1.0,
                           noteworthy=True)  # fmt: skip
        kd.observe(me.id, State(5, "world", (1.0, 2.0, 0.0)))


@pytest.mark.parametrize("command", ["render", "whatif"])
def test_a_kd_without_tiles_is_one_clear_line(tmp_path: Path, capsys, command: str) -> None:
    path = tmp_path / "bare.duckdb"
    _kd_without_tiles(path)
    args = [str(tmp_path / "out")] if command == "render" else ["--waypoints", "0,0,0;1,1,0"]
    assert main([command, "--kd", str(path), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and "holds no map tiles" in err[0], err
    assert not (tmp_path / "out").exists()


def test_a_kd_missing_the_asked_level_or_the_vehicle_says_so(tmp_path: Path, capsys) -> None:
    path = tmp_path / "part.duckdb"
    _kd_without_tiles(path)
    with kd_store.open(path) as kd:
        kd.put_tile("subsystem", 0, 0, {"elevation": np.zeros((64, 64), np.float32)})
    assert main(["whatif", "--kd", str(path), "--waypoints", "0,0,0;1,1,0",
                 "--level", "primitive"]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert f"KD {path} holds no map tiles of level 'primitive'" in err and "subsystem" in err
    assert main(["render", "--kd", str(path), str(tmp_path / "out")]) == 0  # what it has
    assert sorted(p.name for p in (tmp_path / "out").glob("*.png")) == [
        "level3_subsystem_cost.png", "level3_subsystem_elevation.png"
    ]  # fmt: skip
    notes = [line for line in capsys.readouterr().out.splitlines() if line.startswith("note")]
    assert len(notes) == 3 and "'primitive'; not drawn" in notes[0]
    with kd_store.open(tmp_path / "noself.duckdb") as kd:
        kd.put_tile("subsystem", 0, 0, {"elevation": np.zeros((64, 64), np.float32)})
    with (
        kd_store.open(tmp_path / "noself.duckdb", read_only=True) as kd,
        pytest.raises(TileError, match=r"noself\.duckdb: no self entity"),
    ):
        stored_maps(kd)


def test_run_node_over_a_kd_file_leaves_the_maps_the_kd_forms_read(ran, tmp_path: Path) -> None:
    """`wm whatif LOG --kd FILE` runs the log through `run_node`: the file it leaves holds the
    final map windows of every level, so the `--kd` forms can use it afterwards."""
    log, _, _ = ran
    kd_path = tmp_path / "node.duckdb"
    node = wm.run.run_node(log, kd_path, NodeConfig(pose_source=PoseSource.ODOMETRY))
    windows = {lvl.name: lvl.window("elevation") for lvl in node.stack.levels}
    node.kd.close()
    with kd_store.open(kd_path, read_only=True) as kd:
        maps = stored_maps(kd)
        assert maps.levels == ["primitive", "subsystem", "vehicle", "section"]
        for lvl in maps.stack.levels:
            got = lvl.window("elevation")
            assert np.array_equal(got, windows[lvl.name], equal_nan=True), lvl.name
            assert np.isfinite(got).sum() > 20, lvl.name  # 30 m section cells: about 50 seen


def test_a_kd_written_before_the_layer_rename_still_loads(tmp_path: Path) -> None:
    """A KD file whose tiles hold Welford's M2 as ``z_m2`` (its name before it became
    ``z_sq_dev_sum``): a level over it reads the layer under the new name, and a tile it puts
    back holds only the new name."""
    path = tmp_path / "old.duckdb"
    m2 = np.arange(64, dtype=np.float64).reshape(8, 8)
    with kd_store.open(path) as kd:  # tile (0, 0): global cells ix, iy in [0, 8)
        kd.put_tile("t", 0, 0, {"z_m2": m2, "count": np.ones((8, 8), np.int32)})
    config = LevelConfig("t", 1.0, 32, tile_cells=8)  # window cells [-16, 16) each way
    with kd_store.open(path) as kd:
        level = MapLevel(config, KDTileStore(kd))
        np.testing.assert_array_equal(level.window("z_sq_dev_sum")[16:24, 16:24], m2)
        assert level.window("count")[16:24, 16:24].sum() == 64
        assert level.keep_window() > 0
        stored = kd.get_tile("t", 0, 0)
    assert "z_m2" not in stored
    np.testing.assert_array_equal(stored["z_sq_dev_sum"], m2)


# the run's map stack differs from the default in geometry: a coarser and smaller subsystem
# level (0.5 m, 192 cells, not 0.4 m, 256) and a fifth level the default has not
OTHER_MAPS = """maps:
  levels:
    - {name: primitive, resolution_m: 0.04, keep_tiles: false}
    - {name: subsystem, resolution_m: 0.5, size: 192}
    - {name: vehicle, resolution_m: 4.0}
    - {name: section, resolution_m: 30.0}
    - {name: region, resolution_m: 120.0, size: 16, tile_cells: 16}
"""


def test_the_kd_forms_read_the_maps_with_the_runs_configuration(
    ran, tmp_path: Path, capsys
) -> None:
    """A run with another map configuration: `wm render --kd` and `wm whatif --kd` rebuild its
    maps with the K.config.yaml it recorded (or --config), not the default geometry."""
    log = ran[0]
    cfg = tmp_path / "maps.yaml"
    cfg.write_text(OTHER_MAPS)
    kd_path = tmp_path / "other.duckdb"
    live = _run_seen(log, kd_path, "--config", str(cfg))
    assert [(lvl.name, lvl.resolution_m, lvl.size) for lvl in live.stack.levels][1:] == [
        ("subsystem", 0.5, 192), ("vehicle", 4.0, 256), ("section", 30.0, 256),
        ("region", 120.0, 16),
    ]  # fmt: skip
    recorded = Path(f"{kd_path}.config.yaml")
    assert EngineConfig.from_yaml(recorded) == EngineConfig.from_yaml(cfg)
    capsys.readouterr()

    # pictures: every level of the run, drawn as the live maps are (the default would draw
    # 8, the subsystem level's 256 cells of 0.4 m)
    assert main(["render", "--kd", str(kd_path), str(tmp_path / "kd")]) == 0
    out = capsys.readouterr().out.splitlines()
    stored = sorted((tmp_path / "kd").glob("*.png"))
    assert len(stored) == 10 and "level6_region_elevation.png" in {p.name for p in stored}
    assert f"note: configuration {recorded} (recorded with KD {kd_path})" in out
    with kd_store.open(kd_path, read_only=True) as kd:
        maps = stored_maps(kd, EngineConfig.from_yaml(recorded).maps)
        for lvl in maps.stack.levels:
            for name, arr in live.windows[lvl.name].items():
                assert np.array_equal(lvl.window(name), arr, equal_nan=True), (lvl.name, name)
        assert stored_maps(kd).stack.level("subsystem").size == 256  # what the default reads
        render_maps(kd, live.stack, maps.self_id, tmp_path / "live")
        for p in stored:
            a, b = cv2.imread(str(p)), cv2.imread(str(tmp_path / "live" / p.name))
            assert a.shape == b.shape and np.array_equal(a, b), p.name
        plan = "0,0,0;2,10,0;4,20,0"
        t_s, xy_body = _parse_waypoints(plan)
        want = whatif_lines(
            kd, live.stack, maps.self_id, live.T_world_body, t_s, xy_body, "subsystem"
        )

    # What If over the run's subsystem level says what it says over the live maps
    assert main(["whatif", "--kd", str(kd_path), "--waypoints", plan]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("note: configuration") and out[-4:] == want
    # --config wins over the recorded file: with the default geometry the cells are misread
    default = tmp_path / "default.yaml"
    default.write_text("{}\n")
    argv = ["whatif", "--kd", str(kd_path), "--config", str(default), "--waypoints", plan]
    assert main(argv) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == f"note: configuration {default} (from --config)"
    assert out[-4:] != want  # the risk along the plan


def test_commands_writing_a_kd_record_its_configuration_and_continue_with_it(
    ran, tmp_path: Path, capsys
) -> None:
    """`wm whatif LOG --kd K --config FILE` records K.config.yaml as `wm run` does, and a run
    added to K (`--append`, no --config) takes that configuration: its maps continue K's."""
    log = ran[0]
    cfg = tmp_path / "maps.yaml"
    cfg.write_text(OTHER_MAPS)
    kd_path = tmp_path / "k.duckdb"
    argv = ["whatif", str(log), "--kd", str(kd_path), "--config", str(cfg), "--seconds", "0.5"]
    assert main([*argv, "--waypoints", "0,0,0;2,10,0"]) == 0
    recorded = Path(f"{kd_path}.config.yaml")
    assert EngineConfig.from_yaml(recorded) == EngineConfig.from_yaml(cfg)
    capsys.readouterr()
    argv = ["run", str(log), "--kd", str(kd_path), "--append", "--seconds", "0.3"]
    assert main([*argv, "--no-progress", "--decode-in-process"]) == 0
    with kd_store.open(kd_path, read_only=True) as kd:
        assert kd.run_id == 1
        levels = kd.sql("SELECT DISTINCT level FROM map_tiles WHERE run_id = 1").columns[0]
        assert "region" in levels.to_pylist()  # the appended run's own tiles: its maps had it
    assert EngineConfig.from_yaml(recorded) == EngineConfig.from_yaml(cfg)
    assert f"note: configuration {recorded} (recorded with KD {kd_path})" in capsys.readouterr().out


@pytest.mark.parametrize("command", ["render", "whatif"])
def test_a_configuration_that_does_not_parse_is_one_line_naming_it(
    tmp_path: Path, capsys, command: str
) -> None:
    path = tmp_path / "bare.duckdb"
    _kd_without_tiles(path)
    args = [str(tmp_path / "out")] if command == "render" else ["--waypoints", "0,0,0;1,1,0"]
    recorded = Path(f"{path}.config.yaml")
    recorded.write_text("maps: {levels: [\n")  # cut short: not YAML
    assert main([command, "--kd", str(path), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{recorded}: not a YAML document: expected" in err[0], err
    assert "at line 2, column 1" in err[0]
    assert "give --config FILE" in err[0]
    recorded.write_text("maps: {levls: []}\n")  # a misspelt key
    assert main([command, "--kd", str(path), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{recorded}: maps.levls: unknown key" in err[0], err
    missing = tmp_path / "none.yaml"
    assert main([command, "--kd", str(path), "--config", str(missing), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"wm {command}: error: --config {missing}: the file does not exist"]
    assert not (tmp_path / "out").exists()

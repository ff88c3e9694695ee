"""Map tiles in long-term memory: put/get round trips (every dtype, through flush and reopen,
SQL), refusals, schema version 1 files migrated, a loop route restoring the old map from the
KD in the same run and from a reopened KD file, and a killed writer leaving whole tiles."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import zlib
from pathlib import Path

import duckdb
import numpy as np
import pytest

import kd_store
from kd_store import KDConfig, KDError
from kd_store.persist import SCHEMA_VERSION
from maps.level import LevelConfig
from maps.stack import MapStack, StackConfig
from wm.tiles import KDTileStore, keep_windows, map_stack_over_kd, stored_maps

DTYPES = ("float32", "float64", "int32", "int64", "uint8", "bool")


def _layers(seed: int, shape: tuple[int, ...] = (8, 8)) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    out = {d: (rng.normal(size=shape) * 100).astype(d) for d in DTYPES}
    out["float32"][0, 0] = np.nan
    return out


def _same(a: dict[str, np.ndarray], b: dict[str, np.ndarray] | None) -> bool:
    assert b is not None
    return a.keys() == b.keys() and all(
        a[k].dtype == b[k].dtype and np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind == "f")
        for k in a
    )


def test_tiles_survive_a_flush_and_a_reopen(tmp_path: Path) -> None:
    path = tmp_path / "kd.duckdb"
    with kd_store.open(path) as kd:
        kd.begin_cycle(1_000)
        kd.put_tile("subsystem", 3, -7, _layers(0))
        kd.put_tile("vehicle", -1, 2, _layers(1, (4, 5)), t_ns=2_000)
        mine = _layers(0)
        got = kd.get_tile("subsystem", 3, -7)  # from RAM, a copy
        assert _same(mine, got)
        got["int64"][:] = 0  # changing the copy changes nothing kept
        assert _same(mine, kd.get_tile("subsystem", 3, -7))
        assert kd.get_tile("subsystem", 3, -6) is None
    with kd_store.open(path) as kd:
        assert kd.tile_keys() == [("subsystem", 3, -7), ("vehicle", -1, 2)]
        assert kd.tile_keys("vehicle") == [("vehicle", -1, 2)]
        assert _same(_layers(0), kd.get_tile("subsystem", 3, -7))
        assert _same(_layers(1, (4, 5)), kd.get_tile("vehicle", -1, 2))
        rows = kd.sql(
            "SELECT level, layer, dtype, shape, data, t_ns FROM map_tiles "
            "WHERE level = 'vehicle' AND layer = 'int32'"
        ).to_pylist()
        assert len(rows) == 1 and rows[0]["t_ns"] == 2_000 and rows[0]["shape"] == [4, 5]
        a = np.frombuffer(zlib.decompress(rows[0]["data"]), rows[0]["dtype"]).reshape(4, 5)
        assert np.array_equal(a, _layers(1, (4, 5))["int32"])  # as docs/kd.md says to read it
        t = kd.sql("SELECT DISTINCT t_ns FROM map_tiles WHERE level = 'subsystem'")
        assert t["t_ns"].to_pylist() == [1_000]  # this cycle's time by default
        kd.put_tile("subsystem", 3, -7, {"only": np.ones((2, 2))})  # replaced whole
    with kd_store.open(path, read_only=True) as kd:
        got = kd.get_tile("subsystem", 3, -7)
        assert list(got) == ["only"] and np.array_equal(got["only"], np.ones((2, 2)))
        kd.export_parquet(tmp_path / "pq")
    copy = kd_store.open()  # and through Parquet
    copy.import_parquet(tmp_path / "pq")
    assert copy.tile_keys() == [("subsystem", 3, -7), ("vehicle", -1, 2)]
    assert _same(_layers(1, (4, 5)), copy.get_tile("vehicle", -1, 2))


def test_tiles_are_written_in_batches_before_a_flush(tmp_path: Path) -> None:
    path = tmp_path / "kd.duckdb"
    kd = kd_store.open(path, KDConfig(tile_write_batch=4, tile_cache=2))
    for i in range(10):
        kd.put_tile("l", i, 0, {"a": np.full((3, 3), i)})
    kd.close()  # no flush: only whole batches of 4 reached the file
    with kd_store.open(path) as kd:
        assert kd.tile_keys() == [("l", i, 0) for i in range(8)]
        for i in range(8):  # more than the cache holds: read back from the file
            assert np.array_equal(kd.get_tile("l", i, 0)["a"], np.full((3, 3), i))


@pytest.mark.parametrize(
    ("args", "match"),
    [
        (("", 0, 0, {"a": np.zeros(2)}), "level must be"),
        (("l", 1.5, 0, {"a": np.zeros(2)}), "tx 1.5 is not an int64"),
        (("l", 0, 2**70, {"a": np.zeros(2)}), "ty .* is not an int64"),
        (("l", 0, 0, {}), "non-empty mapping"),
        (("l", 0, 0, {"a": np.array(["x"])}), "layer 'a' has dtype <U1"),
        (("l", 0, 0, {"a": np.float32(1.0)}), "at least one dimension"),
    ],
)
def test_bad_tiles_are_refused(args: tuple, match: str) -> None:
    kd = kd_store.open()
    with pytest.raises(KDError, match=match):
        kd.put_tile(*args)
    assert kd.tile_keys() == []


def test_a_version_1_file_opens_and_is_migrated(tmp_path: Path) -> None:
    path = tmp_path / "old.duckdb"
    with kd_store.open(path) as kd:
        kd.add_entity("tree", 4, id=7, status="confirmed", confidence=1.0)
    con = duckdb.connect(str(path))  # make it what version 1 wrote: no tiles, no runs
    con.execute("DROP VIEW map_tiles")
    con.execute("DROP TABLE map_tile_rows")
    con.execute("DROP VIEW runs")
    con.execute("DROP TABLE run_rows")
    for table in ("entity_frames", "entity_state_rows", "entity_expectation_rows",
                  "event_frames", "relation_rows"):  # fmt: skip
        con.execute(f"ALTER TABLE {table} DROP COLUMN run_id")
    con.execute("UPDATE kd_meta SET value = '1' WHERE key = 'schema_version'")
    con.close()
    with kd_store.open(path, read_only=True) as kd:  # read as it is: no tiles
        assert kd.tile_keys() == [] and kd.get_tile("l", 0, 0) is None
        assert kd.get(7).name == "tree"
        folder = tmp_path / "v1"
        kd.export_parquet(folder)
    assert not (folder / "map_tile_rows.parquet").exists()
    imported = kd_store.open()
    imported.import_parquet(folder)  # a version 1 export imports
    assert imported.get(7).name == "tree"
    with kd_store.open(path) as kd:  # opened for writing: migrated
        kd.put_tile("l", 0, 0, {"a": np.ones(3)})
    con = duckdb.connect(str(path), read_only=True)
    version = con.execute("SELECT value FROM kd_meta WHERE key = 'schema_version'").fetchall()
    assert int(version[0][0]) == SCHEMA_VERSION == 4
    assert con.execute("SELECT count(*) FROM map_tiles").fetchall()[0][0] == 1
    assert con.execute("SELECT run_id FROM entities").fetchall() == [(0,)]
    con.close()


# ---------------------------------------------------------------- loop route through the maps

#: Two small levels (32 x 32 cells, tiles of 8): windows 16 m and 64 m wide.
SMALL = StackConfig(
    levels=(
        LevelConfig("fine", 0.5, size=32, tile_cells=8),
        LevelConfig("coarse", 2.0, size=32, tile_cells=8),
    )
)
HOME = np.array([21.0, 9.0])


def _terrain_z(xy: np.ndarray) -> np.ndarray:
    """The analytic ground: a gentle slope with a bump (metres)."""
    return 0.05 * xy[:, 0] + 0.5 * np.exp(-((xy[:, 0] - 21) ** 2 + (xy[:, 1] - 9) ** 2) / 20)


def _survey(stack: MapStack, centre: np.ndarray, t_ns: int) -> None:
    """Move to ``centre`` and fuse ground points every 0.1 m over 30 m x 30 m around it."""
    stack.move_to(centre)
    g = np.arange(-15.0, 15.0, 0.1) + 0.05
    xy = np.stack(np.meshgrid(g + centre[0], g + centre[1]), -1).reshape(-1, 2)
    pts = np.column_stack([xy, _terrain_z(xy)])
    stack.fuse(pts, t_ns=t_ns, variance_m2=np.full(len(pts), 1e-4))


def _drive(stack: MapStack, a: np.ndarray, b: np.ndarray, step_m: float = 3.0) -> None:
    n = int(np.ceil(np.linalg.norm(b - a) / step_m))
    for s in np.linspace(0.0, 1.0, n + 1)[1:]:
        stack.move_to(a + s * (b - a))


def _windows(stack: MapStack) -> dict[str, dict[str, np.ndarray]]:
    return {lvl.name: {n: lvl.window(n) for n in lvl.layer_names} for lvl in stack.levels}


def _assert_windows_equal(a: dict, b: dict) -> None:
    for lvl, layers in a.items():
        for n, arr in layers.items():
            assert np.array_equal(arr, b[lvl][n], equal_nan=True), (lvl, n)


def _assert_matches_terrain(stack: MapStack) -> None:
    """Ground truth: the fine level's elevation at cell centres near HOME is the terrain."""
    lvl = stack.level("fine")
    g = np.arange(-6.0, 6.0, 0.5) + 0.25
    xy = np.stack(np.meshgrid(g + HOME[0], g + HOME[1]), -1).reshape(-1, 2)
    z = lvl.read("elevation", xy)
    assert np.isfinite(z).all()
    assert np.abs(z - _terrain_z(xy)).max() < 0.05  # within a cell's slope


def test_a_loop_route_gets_the_old_map_back_from_the_kd(tmp_path: Path) -> None:
    far = HOME + np.array([300.0, 40.0])  # beyond every window (the coarse one is 64 m wide)
    kd = kd_store.open(tmp_path / "kd.duckdb", KDConfig(tile_write_batch=8, tile_cache=4))
    stack = map_stack_over_kd(kd, SMALL)
    _survey(stack, HOME, 1)
    before = _windows(stack)
    _assert_matches_terrain(stack)
    _drive(stack, HOME, far)
    assert not np.isfinite(stack.level("coarse").window("elevation")).any()  # all left
    assert len(kd.tile_keys("fine")) >= 16  # the 16 m window, in 4 m tiles, and more
    _drive(stack, far, HOME)
    _assert_windows_equal(before, _windows(stack))  # every layer, bit for bit
    _assert_matches_terrain(stack)
    kd.close()


def test_a_reopened_kd_file_gives_the_old_map_back(tmp_path: Path) -> None:
    path = tmp_path / "kd.duckdb"
    with kd_store.open(path) as kd:  # first run: survey near home, drive off, end away
        stack = map_stack_over_kd(kd, SMALL)
        _survey(stack, HOME, 1)
        before = _windows(stack)
        _drive(stack, HOME, HOME + np.array([0.0, 200.0]))
        _survey(stack, HOME + np.array([0.0, 200.0]), 2)
        end = _windows(stack)
        keep_windows(stack)  # the last windows too
    with kd_store.open(path) as kd:  # a later run starting at the origin
        stack = map_stack_over_kd(kd, SMALL)
        _drive(stack, np.zeros(2), HOME)
        _assert_windows_equal(before, _windows(stack))
        _assert_matches_terrain(stack)
        _drive(stack, HOME, HOME + np.array([0.0, 200.0]))  # where the last run ended
        _assert_windows_equal(end, _windows(stack))


def test_the_kd_store_is_what_the_maps_use() -> None:
    kd = kd_store.open()
    stack = MapStack(SMALL, store=KDTileStore(kd))
    _survey(stack, HOME, 5)
    stack.move_to(HOME + 500.0)  # a jump: every window goes to the KD
    keys = kd.tile_keys()
    assert {k[0] for k in keys} == {"fine", "coarse"}
    tile = kd.get_tile(*keys[0])
    assert set(tile) == set(stack.level("fine").layer_names)
    assert tile["elevation"].shape == (8, 8) and tile["elevation"].dtype == np.float32


# ---------------------------------------------------------------- a killed writer

N_TILES = 40  # per flush; every layer of tile k in flush b holds the value b
WRITER = f"""
import sys
import numpy as np
import kd_store
kd = kd_store.open(sys.argv[1], kd_store.KDConfig(tile_write_batch=10**6))
rng = np.random.default_rng(0)
noise = rng.normal(size=(64, 64))  # incompressible bytes: each flush takes a while
b = 0
while True:
    for k in range({N_TILES}):
        kd.put_tile("fine", k, b % 3, {{
            "value": np.full((64, 64), float(b)),
            "gen": np.full((64, 64), b, np.int64),
            "noise": noise + b,
            "tail": np.full((64, 64), b, np.int32),
        }})
    kd.flush()
    print("flushed", b, flush=True)
    b += 1
"""


def _kill_writer(path: Path, after: int, delay_s: float) -> int:
    env = {**os.environ, "PYTHONPATH": str(Path(kd_store.__file__).parents[1])}
    p = subprocess.Popen(
        [sys.executable, "-c", WRITER, str(path)], stdout=subprocess.PIPE, text=True, env=env
    )
    guard = threading.Timer(60.0, p.kill)
    guard.start()
    last = -1
    try:
        for _ in range(after):
            line = p.stdout.readline()
            assert line.startswith("flushed"), line
            last = int(line.split()[1])
        threading.Event().wait(delay_s)
        p.send_signal(signal.SIGKILL)
    finally:
        guard.cancel()
        p.kill()
        p.wait()
    return last


@pytest.mark.parametrize("delay_s", [0.0, 0.003, 0.02])
def test_a_killed_writer_leaves_whole_tiles_or_none(tmp_path: Path, delay_s: float) -> None:
    path = tmp_path / "kd.duckdb"
    last = _kill_writer(path, after=3, delay_s=delay_s)
    with kd_store.open(path) as kd:
        keys = kd.tile_keys()
        assert len(keys) >= N_TILES * min(3, last + 1)  # every reported flush is there
        for key in keys:
            tile = kd.get_tile(*key)
            b = int(tile["gen"][0, 0])
            assert set(tile) == {"value", "gen", "noise", "tail"}, key
            assert b % 3 == key[2] and last - 2 <= b <= last + 1, (key, b, last)
            assert (tile["gen"] == b).all() and (tile["tail"] == b).all(), key
            assert (tile["value"] == b).all(), key
            noise = np.random.default_rng(0).normal(size=(64, 64))
            assert np.array_equal(tile["noise"], noise + b), key


# ---------------------------------------------------------------- wm run --kd FILE


def test_wm_run_keeps_the_map_in_the_kd_file(tmp_path: Path) -> None:
    """A run over a simulated log leaves its tiles in the KD file, the last windows of every
    level included; a stack rebuilt from the file at the vehicle's last position scores
    against the simulator's terrain as the run's own map did. Odometry poses: the maps lie in
    the estimated world, aligned to the truth's at the first self pose (as ``wm run``'s
    ``elevation_*``, wm.truth.OdometryScore.T_align) before scoring."""
    from alignment import kd_self_track, true_pose_track

    from core.geometry import se3_inverse
    from fixtures.simulate import simulate_to_log
    from logs import open_log
    from wm.config import NodeConfig, PoseSource
    from wm.run import run_log
    from wm.truth import TerrainTruth, elevation_error

    log = simulate_to_log("default", tmp_path / "s.mcap", seconds=1.5, seed=3, progress=False)
    path = tmp_path / "kd.duckdb"
    cfg = NodeConfig(pose_source=PoseSource.ODOMETRY, use_sp=False)
    report = run_log(log, path, config=cfg, progress=False)
    source = open_log(log)
    terrain = TerrainTruth.from_log(source.attachments(), source.metadata())
    with kd_store.open(path, read_only=True) as kd:
        levels = {k[0] for k in kd.tile_keys()}
        assert levels == {"primitive", "subsystem", "vehicle", "section"}
        # the primitive level keeps no tiles while running: only its last window (256 cells
        # in tiles of 64, at most 5 x 5 when not aligned to the tile grid)
        assert 4 <= len(kd.tile_keys("primitive")) <= 25
        self_xy = next(f.state.position_xyz[:2] for f in kd.entities() if f.name == "self")
        est = kd_self_track(kd)
        t0 = est.t_ns[0]
        T_align = true_pose_track(log).at(t0) @ se3_inverse(est.at(t0))  # true <- estimated
        stack = map_stack_over_kd(kd)
        stack.move_to(self_xy)
        restored = elevation_error(stack.level("subsystem"), terrain, T_align)
        primitive = elevation_error(stored_maps(kd).stack.level("primitive"), terrain, T_align)
    for name, got in (("subsystem", restored), ("primitive", primitive)):
        live = report.metrics[f"elevation_{name}"]
        assert got["cells"] == live["cells"] > 1000, name
        # the first pose goes through the KD's quaternion: the same figure up to rounding
        assert got["rmse_m"] == pytest.approx(live["rmse_m"], rel=1e-9, abs=1e-12), name
        assert got["rmse_m"] < 0.5, name  # measured: primitive 0.015 m, subsystem 0.064 m


def test_keep_windows_puts_the_last_window_of_a_level_that_keeps_no_tiles() -> None:
    """A level with ``keep_tiles=False`` sends nothing to the KD while it scrolls, but its last
    window goes in at the end (and the level stays tile-free afterwards)."""
    config = StackConfig(
        levels=(LevelConfig("fine", 0.5, size=32, tile_cells=8, keep_tiles=False), SMALL.levels[1])
    )
    kd = kd_store.open()
    stack = map_stack_over_kd(kd, config)
    _survey(stack, HOME, 1)
    _drive(stack, HOME, HOME + np.array([100.0, 0.0]))
    _survey(stack, HOME + np.array([100.0, 0.0]), 2)
    assert kd.tile_keys("fine") == []  # nothing kept on the way
    end = _windows(stack)
    assert keep_windows(stack) > 0
    ox, oy = stack.level("fine").origin_cell.tolist()  # the 32-cell window in 8-cell tiles
    tiles = {("fine", tx, ty) for tx in range(ox // 8, (ox + 31) // 8 + 1)
             for ty in range(oy // 8, (oy + 31) // 8 + 1)}  # fmt: skip
    assert set(kd.tile_keys("fine")) == tiles
    assert stack.level("fine").store is None
    back = MapStack(SMALL, store=KDTileStore(kd))  # a level that reads tiles, moved there
    back.move_to(HOME + np.array([100.0, 0.0]))
    _assert_windows_equal({"fine": end["fine"]}, {"fine": _windows(back)["fine"]})

"""The one engine configuration (wm.engine_config.EngineConfig): YAML round trip, partial files,
errors naming the file and the dotted key, the node's use of every section, and `wm run`
recording the configuration it ran with next to its KD."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import duckdb
import numpy as np
import pytest

import kd_store
from core.errors import EngineError
from maps.stack import StackConfig
from sp.context import SPConfig
from sp.odometry import LadarOdometry, OdometryConfig
from wm.cli import main
from wm.config import NodeConfig, PoseSource
from wm.engine_config import ConfigError, EngineConfig
from wm.node import WorldModelNode


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_the_default_round_trips_through_yaml(tmp_path: Path) -> None:
    default = EngineConfig()
    text = default.to_yaml(tmp_path / "c.yaml")
    loaded = EngineConfig.from_yaml(tmp_path / "c.yaml")
    assert loaded == default  # NaN layer fills too (one NaN object)
    assert loaded.to_yaml() == text
    assert (tmp_path / "c.yaml").read_text() == text
    # the sections are the subsystems' own classes, with their own defaults
    assert (default.node, default.sp) == (NodeConfig(), SPConfig())
    assert (default.odometry, default.maps) == (OdometryConfig(), StackConfig())


def test_a_partial_file_changes_exactly_the_fields_it_names(tmp_path: Path) -> None:
    path = _write(
        tmp_path / "c.yaml",
        "sp:\n  tracker:\n    min_hits: 5\nodometry:\n  max_range_m: 50\n  convergence: 1e-4\n"
        "node:\n  pose_source: truth\n  prediction: {range_image_hw: [16, 128]}\n",
    )
    d = EngineConfig()
    want = replace(
        d,
        sp=replace(d.sp, tracker=replace(d.sp.tracker, min_hits=5)),
        odometry=replace(d.odometry, max_range_m=50.0, convergence=1e-4),
        node=replace(
            d.node,
            pose_source=PoseSource.TRUTH,
            prediction=replace(d.node.prediction, range_image_hw=(16, 128)),
        ),
    )
    got = EngineConfig.from_yaml(path)
    assert got == want
    assert got.sp.egosphere == d.sp.egosphere  # a section merges into its default, not the class's
    assert EngineConfig.from_yaml(_write(tmp_path / "empty.yaml", "")) == d


@pytest.mark.parametrize(
    ("text", "key", "what"),
    [
        ("sp:\n  tracker:\n    no_such_field: 1\n", "sp.tracker.no_such_field", "unknown key"),
        ("sp:\n  tracker:\n    min_hit: 1\n", "sp.tracker.min_hit", "did you mean min_hits"),
        ("nodes: {}\n", "nodes", "unknown key"),
        ("odometry:\n  max_range_m: far\n", "odometry.max_range_m", "expected float"),
        ("sp:\n  birth_hits: 2.5\n", "sp.birth_hits", "expected int"),
        ("sp:\n  lists: 1\n", "sp.lists", "expected bool"),
        ("node:\n  pose_source: gps\n", "node.pose_source", "expected one of"),
        ("maps:\n  levels:\n  - {name: a, size: big}\n", "maps.levels[0].size", "expected int"),
        (
            "node:\n  prediction: {range_image_hw: [1, 2, 3]}\n",
            "node.prediction.range_image_hw",
            "2 items",
        ),
        ("sp:\n  tracker: 3\n", "sp.tracker", "expected a mapping"),
        ("odometry:\n  min_range_m: 200\n", "odometry", "min_range_m"),  # the class's check
    ],
)
def test_errors_name_the_file_and_the_dotted_key(
    tmp_path: Path, text: str, key: str, what: str
) -> None:
    path = _write(tmp_path / "bad.yaml", text)
    with pytest.raises(ConfigError) as e:
        EngineConfig.from_yaml(path)
    assert isinstance(e.value, EngineError)
    msg = str(e.value)
    assert msg.startswith(f"{path}: ") and f" {key}" in msg and what in msg, msg


def test_wm_config_prints_the_defaults_and_refuses_a_bad_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["config", "--default"]) == 0
    out = capsys.readouterr().out
    assert EngineConfig.from_yaml(_write(tmp_path / "d.yaml", out)) == EngineConfig()
    bad = _write(tmp_path / "bad.yaml", "sp:\n  tracker:\n    no_such_field: 1\n")
    assert main(["config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "sp.tracker.no_such_field" in err


def test_the_node_builds_its_subsystems_from_their_sections() -> None:
    cfg = EngineConfig(
        node=NodeConfig(odometry_process=False),
        sp=replace(SPConfig(), birth_hits=3),
        odometry=OdometryConfig(max_range_m=60.0),
        maps=replace(StackConfig(), apriori_var_m2=0.5),
    )
    with kd_store.open() as kd:
        node = WorldModelNode(kd, cfg)
        assert node.engine_config is cfg and node.config is cfg.node
        assert node.sp is not None and node.sp.ctx.config is cfg.sp
        assert node.stack.config is cfg.maps
        node.T_world_body0 = np.eye(4)
        odo = node._odometry()
        assert isinstance(odo, LadarOdometry) and odo.config is cfg.odometry
        # a bare NodeConfig (existing callers) gets the default subsystems
        bare = WorldModelNode(kd, NodeConfig(use_sp=False))
        assert bare.engine_config == EngineConfig(node=NodeConfig(use_sp=False))


def _level2_names(kd_path: Path) -> list[str]:
    with duckdb.connect(str(kd_path), read_only=True) as c:
        return [
            r[0] for r in c.execute("SELECT name FROM entity_frames WHERE level = 2").fetchall()
        ]


@pytest.fixture(scope="module")
def short_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("log") / "x.mcap"
    argv = ["simulate", "default", "--seconds", "2", "--seed", "3", "--out", str(out)]
    assert main([*argv, "--no-progress"]) == 0
    return out


def test_wm_run_uses_the_config_file_records_it_and_flags_override_it(
    short_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    base = tmp_path / "a.kd"
    assert main(["run", str(short_log), "--kd", str(base), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "poses from odometry (first=1, tracking=19)" in out
    assert f"config {base}.config.yaml" in out
    assert EngineConfig.from_yaml(f"{base}.config.yaml") == EngineConfig()

    # no level-2 lists (SP), no sweep with enough points (the odometry process), and a
    # pose source the --poses flag overrides
    cfg = _write(
        tmp_path / "c.yaml",
        "sp: {lists: false}\nodometry: {min_points: 100000}\nnode: {pose_source: truth}\n",
    )
    kd = tmp_path / "b.kd"
    argv = ["run", str(short_log), "--kd", str(kd), "--config", str(cfg), "--poses", "odometry"]
    assert main([*argv, "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "poses from odometry (lost=20)" in out  # every sweep refused by the odometry
    d = EngineConfig()
    want = replace(
        d, sp=replace(d.sp, lists=False), odometry=replace(d.odometry, min_points=100000)
    )
    assert EngineConfig.from_yaml(f"{kd}.config.yaml") == want  # the effective configuration
    lists = [n for n in _level2_names(base) if n.startswith(("vertex", "range_edge"))]
    assert lists and not [n for n in _level2_names(kd) if n.startswith(("vertex", "range_edge"))]

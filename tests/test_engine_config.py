"""The one engine configuration (wm.engine_config.EngineConfig): YAML round trip, partial files,
errors naming the file and the dotted key, the node's use of every section, `wm run`
recording the configuration it ran with next to its KD, and the sections read outside the
node: the KD's (`wm run` opens the KD with it), What If's (`wm serve` rolls out with it) and
the planner's (`wm bg` plans with it)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import duckdb
import numpy as np
import pytest

import kd_store
from core.errors import EngineError
from kd_store.config import KDConfig
from maps.stack import MapStack, StackConfig
from sp.context import SPConfig
from sp.odometry import LadarOdometry, OdometryConfig
from wm.cli import BG_BUDGET_S, _planner_config, build_parser, main
from wm.config import NodeConfig, PlannerConfig, PoseSource, VehicleConfig, WhatIfConfig
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
    assert (default.kd, default.planner, default.whatif) == (
        KDConfig(),
        PlannerConfig(),
        WhatIfConfig(),
    )
    # YAML has no set: the promotion rule's statuses are written as a list, read back a set
    assert "statuses: [confirmed]" in text and "min_worth: .inf" in text
    assert loaded.kd.promotion.statuses == frozenset({"confirmed"})


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
        ("kd:\n  memory:\n    horizon_s: {}\n", "kd.memory.horizon_s", "did you mean horizons_s"),
        ("kd:\n  promotion: {statuses: confirmed}\n", "kd.promotion.statuses", "expected a list"),
        ("kd:\n  tile_cache: many\n", "kd.tile_cache", "expected int"),
        ("planner:\n  budget: 1\n", "planner.budget", "did you mean budget_s"),
        ("planner:\n  budget_s: 0\n", "planner", "budget_s"),  # the class's check
        ("whatif:\n  vehicle: {lenght_m: 5}\n", "whatif.vehicle.lenght_m", "did you mean length_m"),
        ("whatif:\n  steps_s: {vehicle: fast}\n", "whatif.steps_s.vehicle", "expected float"),
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
    assert "\n" not in msg  # one line


@pytest.mark.parametrize(
    ("command", "text", "key"),
    [
        (["config"], "kd:\n  grid_cell: 4\n", "kd.grid_cell"),
        (["config"], "whatif:\n  horizon_s: {}\n", "whatif.horizon_s"),
        (["bg", "--url", "http://127.0.0.1:9", "--goal", "0,0"], "planner:\n  lvl: x\n",
         "planner.lvl"),
        (["bg", "--url", "http://127.0.0.1:9", "--goal", "0,0"],
         "planner:\n  replan_period_s: -1\n", "planner.replan_period_s"),
    ],
)  # fmt: skip
def test_a_bad_key_of_a_new_section_is_one_line_naming_file_and_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: list[str], text: str, key: str
) -> None:
    """`wm config FILE` and `wm bg --config FILE` (before it reaches for the server) refuse a
    bad key or value of the kd, planner and whatif sections in one line on stderr."""
    bad = _write(tmp_path / "bad.yaml", text)
    argv = [*command, str(bad)] if command == ["config"] else [*command, "--config", str(bad)]
    assert main(argv) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if not ln.startswith("note:")]
    assert len(err) == 1 and str(bad) in err[0] and key in err[0], err


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


def test_wm_run_opens_the_kd_with_the_kd_section(
    short_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A promotion rule of no status (``kd.promotion.statuses: []``) reaches the KD `wm run`
    opens: entities are confirmed in memory, yet long-term memory (the file) receives only
    the noteworthy ones (the vehicle itself)."""
    cfg = _write(tmp_path / "c.yaml", "kd:\n  promotion: {statuses: []}\n")
    kd = tmp_path / "k.kd"
    assert (
        main(["run", str(short_log), "--kd", str(kd), "--config", str(cfg), "--no-progress"]) == 0
    )
    out = capsys.readouterr().out
    assert "confirmed=" in out  # the summary counts the KD in memory
    with duckdb.connect(str(kd), read_only=True) as c:
        rows = dict(
            c.execute("SELECT noteworthy, count(*) FROM entity_frames GROUP BY 1").fetchall()
        )
    assert rows.keys() == {True} and rows[True] >= 1, rows
    assert EngineConfig.from_yaml(f"{kd}.config.yaml").kd.promotion.statuses == frozenset()


def test_bg_takes_the_planner_section_and_its_flags_override_it(tmp_path: Path) -> None:
    """`wm bg`'s planner: the file's planner section over the defaults with wm bg's own
    budget (BG_BUDGET_S when neither the file nor --budget-s gives one), the flags given
    over both."""
    cfg = _write(tmp_path / "p.yaml", "planner:\n  curvatures_1pm: [0.0]\n  level: vehicle\n")
    bg = ["bg", "--url", "http://127.0.0.1:9", "--goal", "0,0"]
    default = _planner_config(build_parser().parse_args(bg))
    assert default == replace(PlannerConfig(), budget_s=BG_BUDGET_S)
    got = _planner_config(
        build_parser().parse_args([*bg, "--config", str(cfg), "--level", "primitive"])
    )
    want = replace(default, curvatures_1pm=(0.0,), level="primitive")
    assert got == want
    cfg.write_text("planner:\n  budget_s: 0.3\n")
    assert _planner_config(build_parser().parse_args([*bg, "--config", str(cfg)])).budget_s == 0.3
    flag = build_parser().parse_args([*bg, "--config", str(cfg), "--budget-s", "2"])
    assert _planner_config(flag).budget_s == 2.0


def test_serve_rolls_out_with_the_whatif_section_and_bg_plans_with_the_planner_section(
    short_log: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    """`wm serve --config` with ``whatif.steps_s: {subsystem: 0.25}``: the server copies only
    that level for What If and rolls out at 0.25 s steps; `wm bg --config` with
    ``planner.curvatures_1pm: [0.0]`` against it hypothesizes one curvature per speed. Both
    are seen over HTTP, in the plan `wm bg --json` prints: its path is timed at 0.25 s steps
    and it weighed 6 candidates (6 speeds x 1 curvature; the default is 6 x 9)."""
    pytest.importorskip("uvicorn")
    from serving import served

    import wm.serve
    from wm.serve import create_app, what_if_over

    served_cfg = _write(tmp_path / "s.yaml", "whatif:\n  steps_s: {subsystem: 0.25}\n")
    bg_cfg = _write(tmp_path / "b.yaml", "planner:\n  curvatures_1pm: [0.0]\n")
    seen: dict = {}

    def serve_then_plan(live, host, port, token, limits) -> None:
        """Instead of serving until Ctrl-C: serve until one `wm bg` plan is made."""
        assert live.wait(300), live.status.error
        wi = what_if_over(live.snapshot)
        seen["config"], seen["levels"] = wi.config, [lv.name for lv in wi.stack.levels]
        with served(create_app(live, token, limits)) as base:
            argv = ["bg", "--url", base, "--goal", "20,0", "--cycles", "1", "--json"]
            seen["bg"] = main([*argv, "--no-tell", "--config", str(bg_cfg)])

    monkeypatch.setattr(wm.serve, "serve", serve_then_plan)
    kd = tmp_path / "live.kd"
    argv = ["serve", "--replay", str(short_log), "--rate", "0", "--kd", str(kd)]
    assert main([*argv, "--config", str(served_cfg)]) == 0
    assert seen["bg"] == 0, capsys.readouterr().err
    assert seen["config"].steps_s == {"subsystem": 0.25}
    assert seen["levels"] == ["subsystem"]  # the copy holds the levels What If serves
    plans = [json.loads(ln) for ln in capsys.readouterr().out.splitlines() if ln.startswith("{")]
    assert len(plans) == 1
    assert plans[0]["candidates"] == 6
    assert np.allclose(np.diff(plans[0]["t_s"]), 0.25)


# --- one place for each setting: the vehicle (node.vehicle), the horizons (kd.memory) ----------


def _rollout(wi, level: str = "subsystem"):
    """One plan asking 10 m/s straight ahead, from rest at the origin."""
    from wm.whatif import ControlPlan, Start

    plan = ControlPlan(np.array([0.0]), np.array([10.0]), np.array([0.0]), "fast")
    return wi.simulate([plan], level=level, start=Start(np.zeros(2), 0.0, 0.0, 0))


def test_the_vehicle_set_in_its_one_place_reaches_the_node_and_what_if(tmp_path: Path) -> None:
    """``node.vehicle`` is the one vehicle: a file setting it there gives it to the node and
    to What If built from the node's configuration (the node's own, the server's per-cycle
    copy, ``wm whatif``'s), whose rollouts keep to its speed limit."""
    from wm.serve import CycleSnapshot, what_if_over
    from wm.serve_ros import node_what_if
    from wm.whatif import WhatIf

    path = _write(tmp_path / "v.yaml", "node:\n  vehicle: {max_speed_mps: 3.0, width_m: 1.5}\n")
    cfg = EngineConfig.from_yaml(path)
    assert cfg.node.vehicle == replace(VehicleConfig(), max_speed_mps=3.0, width_m=1.5)
    assert "vehicle" not in cfg.to_dict()["whatif"]  # written once, in its section
    with kd_store.open() as kd:
        node = WorldModelNode(kd, replace(cfg, node=replace(cfg.node, odometry_process=False)))
        node.stack.move_to(np.zeros(2))
        assert node.config.vehicle.max_speed_mps == 3.0
        snap = CycleSnapshot.of(kd, node.self_id, 0, node.stack, node.engine_config)
        for wi in (node_what_if(node), what_if_over(snap), WhatIf(kd, node.stack, cfg)):
            assert wi.vehicle == cfg.node.vehicle
            assert _rollout(wi).speed.max() == pytest.approx(3.0)
        # the default vehicle (15 m/s at most) goes as fast as the plan asks
        assert _rollout(WhatIf(kd, node.stack)).speed.max() == pytest.approx(10.0)
    with pytest.raises(TypeError, match="not its whatif section"):
        WhatIf(None, node.stack, WhatIfConfig())  # type: ignore[arg-type]


def test_the_horizons_set_in_kd_memory_reach_the_kd_and_what_if(tmp_path: Path) -> None:
    """Each level's planning horizon is ``kd.memory.horizons_s``: the KD's short-term memory
    keeps that long a history and What If rolls out that long."""
    from wm.whatif import WhatIf

    horizons = "{primitive: 0.5, subsystem: 2.0, vehicle: 30, section: 600}"
    text = f"kd:\n  memory:\n    horizons_s: {horizons}\n"
    cfg = EngineConfig.from_yaml(_write(tmp_path / "h.yaml", text))
    assert "horizons_s" not in cfg.to_dict()["whatif"]
    with kd_store.open(":memory:", cfg.kd) as kd:
        assert kd.config.memory.horizon_ns(3) == 2_000_000_000  # SP level 3: subsystem
        wi = WhatIf(kd, MapStack(cfg.maps), cfg)
        wi.stack.move_to(np.zeros(2))
        assert _rollout(wi).t_s[-1] == pytest.approx(2.0)
        assert _rollout(wi, "vehicle").t_s[-1] == pytest.approx(30.0)


def _earlier_format(**whatif: object) -> dict:
    """The defaults as the earlier format wrote them: the vehicle and the horizons in the
    whatif section as well, changed by ``whatif``."""
    doc = EngineConfig().to_dict()
    doc["whatif"]["vehicle"] = dict(doc["node"]["vehicle"])
    doc["whatif"]["horizons_s"] = dict(doc["kd"]["memory"]["horizons_s"])
    doc["whatif"].update(whatif)
    return doc


def test_a_file_of_the_earlier_format_loads_with_a_warning(tmp_path: Path) -> None:
    """A recorded ``K.config.yaml`` of the earlier format gives ``whatif.vehicle`` and
    ``whatif.horizons_s``: read at their new places, each with a warning saying where."""
    import yaml

    path = tmp_path / "old.config.yaml"
    path.write_text(yaml.safe_dump(_earlier_format()))
    with pytest.warns(FutureWarning) as caught:
        assert EngineConfig.from_yaml(path) == EngineConfig()
    said = sorted(str(w.message) for w in caught)
    assert len(said) == 2 and all(s.startswith(f"{path}: ") for s in said)
    assert "whatif.horizons_s is read as kd.memory.horizons_s" in said[0]
    assert "whatif.vehicle is read as node.vehicle" in said[1]
    # the vehicle given in What If's section alone (what What If read then) is node.vehicle
    only = _write(tmp_path / "v.yaml", "whatif:\n  vehicle: {max_speed_mps: 4.0}\n")
    with pytest.warns(FutureWarning, match=r"whatif\.vehicle is read as node\.vehicle"):
        got = EngineConfig.from_yaml(only)
    assert got == replace(
        EngineConfig(), node=replace(NodeConfig(), vehicle=VehicleConfig(max_speed_mps=4.0))
    )


@pytest.mark.parametrize(
    ("text", "old", "new"),
    [
        # two vehicles: which one is meant cannot be told
        ("node:\n  vehicle: {max_speed_mps: 5.0}\nwhatif:\n  vehicle: {max_speed_mps: 4.0}\n",
         "whatif.vehicle", "node.vehicle"),
        # What If's horizons other than the KD's: read there, they would change the KD's memory
        ("whatif:\n  horizons_s: {subsystem: 3.0}\n", "whatif.horizons_s", "kd.memory.horizons_s"),
        ("kd:\n  memory: {horizons_s: {subsystem: 4.0}}\nwhatif:\n  horizons_s: {subsystem: 3.0}\n",
         "whatif.horizons_s", "kd.memory.horizons_s"),
    ],
)  # fmt: skip
def test_a_moved_key_that_would_change_a_run_names_where_it_lives(
    tmp_path: Path, text: str, old: str, new: str
) -> None:
    path = _write(tmp_path / "old.yaml", text)
    with pytest.raises(ConfigError) as e:
        EngineConfig.from_yaml(path)
    msg = str(e.value)
    assert msg.startswith(f"{path}: {old}: ") and f"lives in {new} alone" in msg, msg

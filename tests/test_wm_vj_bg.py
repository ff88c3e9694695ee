"""Value judgment (reference 001, 4.3) and the behavior-generation consumer (4.1): confidence of
KD items, the cost layer, worth from the class library, attention relevance to the current plan
told to the node, the planner's time budget and the continued last plan."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

import kd_store
from kd_store import Attribute, EntityFrame, Level, State, Status, Value
from kd_store.classes import ClassKind, ClassPrototype
from logs.types import GroundTruthPose, LadarScan
from maps.level import LevelConfig, MapLevel
from maps.stack import MapStack
from wm import vj
from wm.bg import Planner
from wm.config import NodeConfig, PlannerConfig, PoseSource, PredictionConfig, VJConfig
from wm.node import NodeError, WorldModelNode
from wm.whatif import ControlPlan, Start, WaypointPlan, WhatIf

CLASSES_YAML = Path(kd_store.__file__).with_name("classes.yaml")
START = Start(np.zeros(2), 0.0, 5.0, 0)
GOAL = np.array([40.0, 0.0])


def _kd_with(cls="rock", center_xy=(20.0, 0.0), size=(1.0, 1.0, 1.0), **fields):
    """A KD holding one confirmed world-frame object of class ``cls``; (kd, id)."""
    kd = kd_store.open()
    kd.begin_cycle(0)
    names = ("length_m", "width_m", "height_m")
    attrs = {n: Attribute(estimated=v) for n, v in zip(names, size, strict=True)}
    fields = {"status": Status.CONFIRMED, "confidence": 0.9, **fields}
    e = kd.add_entity(cls, Level.OBJECT, generic_classes=(cls,), attributes=attrs, **fields)
    kd.observe(e.id, State(0, "world", (*center_xy, 0.5)))
    return kd, e.id


def _whatif(kd) -> WhatIf:
    stack = MapStack()
    stack.move_to(np.zeros(2))
    return WhatIf(kd, stack)


def _yaml_values() -> dict[str, tuple[str | None, Value]]:
    """class name -> (is_a, value) read straight from the class library file."""
    out = {}
    for c in yaml.safe_load(CLASSES_YAML.read_text())["classes"]:
        out[c["name"]] = (c.get("is_a"), Value(**c.get("value", {})))
    return out


# --- item 1: confidence of KD items ------------------------------------------------------------


@pytest.mark.parametrize(
    "status, conf, expected",
    [
        (Status.CONFIRMED, 0.8, 0.8),
        (Status.HYPOTHESIZED, 0.8, 0.4),
        (Status.DENIED, 0.8, 0.0),
        (Status.GONE, 0.8, 0.0),
    ],
)
def test_confidence_of_a_kd_item_follows_its_status(status, conf, expected) -> None:
    f = EntityFrame(id=1, name="x", level=Level.OBJECT, status=status, confidence=conf)
    assert vj.confidence(f) == pytest.approx(expected)


# --- item 3: the cost layer --------------------------------------------------------------------


def _level(size: int = 8) -> MapLevel:
    lvl = MapLevel(LevelConfig(name="subsystem", size=size, keep_tiles=False))
    lvl.set_window("elevation", np.zeros((size, size), np.float32))
    lvl.set_window("traversability", np.ones((size, size), np.float32))
    lvl.set_window("elevation_var", np.zeros((size, size), np.float32))
    return lvl


def _set_cell(lvl: MapLevel, layer: str, row: int, col: int, value) -> None:
    a = lvl.window(layer)
    a[row, col] = value
    lvl.set_window(layer, a)


def test_cost_layer_from_traversability_unknown_and_uncertainty() -> None:
    cfg = VJConfig()
    kd = kd_store.open()
    lvl = _level()
    # scrolled so that storage and window orders differ by an uneven wrap (3 and 1 cells: a
    # roll the wrong way round would not give the window back)
    lvl.move_to(np.array([3.5, 1.5]) * lvl.resolution_m)
    assert lvl.origin_cell.tolist() == [-1, -3]
    for name, v in (("elevation", 0.0), ("traversability", 1.0), ("elevation_var", 0.0)):
        lvl.set_window(name, np.full((8, 8), v, np.float32))
    _set_cell(lvl, "traversability", 0, 1, 0.2)  # hard going
    _set_cell(lvl, "traversability", 0, 2, 0.0)  # impassable
    _set_cell(lvl, "elevation", 0, 3, np.nan)  # never seen
    _set_cell(lvl, "elevation_var", 0, 4, 0.25**2)  # sigma = sigma_ref / 2
    _set_cell(lvl, "elevation_var", 0, 5, 0.5**2)  # sigma = sigma_ref
    _set_cell(lvl, "elevation_var", 0, 6, 2.0**2)  # beyond sigma_ref: capped
    c = vj.cost_window(lvl, kd, cfg)
    assert c.dtype == np.float32 and c.shape == (8, 8)
    assert c[0, 0] == pytest.approx(0.0)  # traversable and certain
    assert c[0, 1] == pytest.approx(cfg.w_traversability * 0.8) and c[0, 1] > c[0, 0]
    assert c[0, 2] == pytest.approx(cfg.w_traversability) and c[0, 2] > c[0, 1]
    assert c[0, 3] == pytest.approx(cfg.w_unknown)
    assert c[0, 4] == pytest.approx(cfg.w_uncertainty * 0.5)
    assert c[0, 5] == pytest.approx(cfg.w_uncertainty)
    assert c[0, 6] == pytest.approx(cfg.w_uncertainty)
    assert c[0, 0] < c[0, 4] < c[0, 5]  # uncertainty raises cost
    vj.write_cost_layer(lvl, kd, cfg)
    np.testing.assert_array_equal(lvl.window("cost"), c)


def test_cost_layer_adds_class_cost_weighed_by_confidence_in_the_entity() -> None:
    kd = kd_store.open()
    kd.begin_cycle(0)
    rock_cost = _yaml_values()["rock"][1].cost
    assert rock_cost > 0

    def rock(status, conf) -> int:
        return kd.add_entity("rock", Level.OBJECT, generic_classes=("rock",), status=status,
                             confidence=conf).id  # fmt: skip

    ids = [rock(Status.CONFIRMED, 1.0), rock(Status.HYPOTHESIZED, 0.8), rock(Status.DENIED, 0.9)]
    lvl = _level()
    for col, eid in enumerate([*ids, 10**6]):  # the last one is not (no longer) in the KD
        _set_cell(lvl, "entity_id", 2, col, eid)
    c = vj.cost_window(lvl, kd, VJConfig())
    expected = [rock_cost * vj.confidence(kd.get(i)) for i in ids] + [0.0]
    np.testing.assert_allclose(c[2, :4], expected, rtol=1e-6)
    assert c[2, 0] == pytest.approx(rock_cost) and c[2, 1] == pytest.approx(0.4 * rock_cost)
    assert c[2, 2] == 0.0  # a denied entity costs nothing
    assert np.all(c[3] == 0.0)


# --- item 3: worth of entities from their classes ----------------------------------------------


def test_entity_worth_cost_and_risk_come_from_the_class_library_file() -> None:
    kd = kd_store.open()
    kd.begin_cycle(0)
    table = _yaml_values()

    def expected(name: str) -> Value:  # the nearest class up the is_a chain with a value
        while name is not None:
            is_a, v = table[name]
            if v != Value():
                return v
            name = is_a
        return Value()

    with_value = [n for n, (_, v) in table.items() if v != Value()]
    assert {"person", "tree", "rock", "vehicle"} <= set(with_value)
    for name in table:
        lvl = Level(kd.classes.get(name).level)
        f = kd.add_entity(f"a {name}", lvl, generic_classes=(name,))
        assert vj.entity_value(kd, f) == expected(name), name
    # a specific class without a value of its own inherits its generic class's
    kd.classes.add(ClassPrototype("oak 7", ClassKind.SPECIFIC, Level.OBJECT, is_a="tree"))
    f = kd.add_entity("oak", Level.OBJECT, generic_classes=("vegetation", "tree"),
                      specific_class="oak 7")  # fmt: skip
    assert vj.entity_value(kd, f) == table["tree"][1]
    assert vj.entity_value(kd, f).risk == pytest.approx(0.8)
    # an entity's own value overrides its class's
    own = Value(cost=0.25, risk=0.05)
    f = kd.add_entity("marked rock", Level.OBJECT, generic_classes=("rock",), value=own)
    assert vj.entity_value(kd, f) == own


def test_plan_risk_scales_with_the_class_risk_of_the_entity_passed() -> None:
    table = _yaml_values()
    straight = ControlPlan(np.array([0.0]), np.array([5.0]), np.array([0.0]), "straight")
    risks = {}
    for cls in ("person", "bush"):
        kd, _ = _kd_with(cls, center_xy=(12.0, 3.5))  # beside the path, not on it
        res = _whatif(kd).simulate([straight], start=START)
        assert res.collision_entity[0] == -1
        risks[cls] = float(vj.evaluate(res, GOAL, VJConfig()).risk[0])
    assert risks["bush"] > 0
    ratio = table["person"][1].risk / table["bush"][1].risk
    assert risks["person"] / risks["bush"] == pytest.approx(ratio, rel=1e-9)


# --- item 2: relevance to the current plan, told to the node -----------------------------------


def _scan(t_ns: int) -> LadarScan:
    pts = np.array([[5.0, 0.0, -1.0], [6.0, 1.0, -1.0]], np.float32)
    return LadarScan(t_ns, "base_link", pts, np.ones(2, np.float32), np.zeros(2, np.int64))


def _node() -> WorldModelNode:
    """A node standing at the origin. Truth poses: these unit tests feed hand-made two-point
    sweeps and need the pose known exactly, which no odometry gives from them."""
    cfg = NodeConfig(pose_source=PoseSource.TRUTH, use_sp=False,
                     prediction=PredictionConfig(range_image_every=0))  # fmt: skip
    node = WorldModelNode(kd_store.open(), cfg)
    for t_ns in (0, 5_000_000_000):  # standing at the origin
        node.feed(GroundTruthPose(t_ns, "world", "base_link", np.eye(4)))
    return node


def test_node_attention_ranks_an_entity_near_the_current_plan_above_an_equal_one() -> None:
    node = _node()
    kd = node.kd
    kd.begin_cycle(0)
    ids = {}
    for name, xy in (("off the plan", (10.0, -10.0)), ("on the plan", (10.0, 10.0))):
        e = kd.add_entity(name, Level.OBJECT, generic_classes=("rock",),
                          status=Status.CONFIRMED, confidence=0.9)  # fmt: skip
        kd.observe(e.id, State(0, "world", (*xy, 0.3)))
        ids[name] = e.id
    off, on = ids["off the plan"], ids["on the plan"]
    node.cycle(_scan(100_000_000))  # no plan: a tie, kept in KD order
    assert kd.attention("subsystem") == [off, on]
    node.set_plan(np.array([[0.0, 0.0], [10.0, 9.0], [20.0, 10.0]]))
    node.cycle(_scan(1_100_000_000))  # the levels' next period
    for level in ("primitive", "subsystem", "vehicle"):
        assert kd.attention(level) == [on, off], level
    node.set_plan(None)
    node.cycle(_scan(2_100_000_000))
    assert kd.attention("subsystem") == [off, on]
    kd.close()


def test_planner_tells_the_node_its_plan_through_the_node_api() -> None:
    node = _node()
    planner = Planner(WhatIf(node.kd, node.stack, self_id=node.self_id), on_select=node.set_plan)
    sel = planner.plan(GOAL, start=START)
    assert node.plan_xy is not None
    np.testing.assert_array_equal(node.plan_xy, sel.xy)
    node.kd.close()


def test_a_bad_plan_is_refused_by_the_node_and_vj() -> None:
    node = _node()
    with pytest.raises(NodeError, match=r"plan point 1 is not finite: \[nan, 1.0\]"):
        node.set_plan(np.array([[0.0, 0.0], [np.nan, 1.0]]))
    with pytest.raises(NodeError, match=r"\(S, 2\).*\(3,\)"):
        node.set_plan(np.zeros(3))
    assert node.plan_xy is None
    with pytest.raises(vj.VJError, match=r"plan_xy .* non-finite"):
        vj.attention(node.kd, np.zeros(2), VJConfig(), plan_xy=np.array([[np.inf, 0.0]]))
    with pytest.raises(vj.VJError, match=r"plan_xy .* shape \(4, 1\)"):
        vj.attention(node.kd, np.zeros(2), VJConfig(), plan_xy=np.zeros((4, 1)))
    node.kd.close()


# --- item 4: the planning period's time budget -------------------------------------------------


def test_planner_with_a_tiny_budget_keeps_the_best_of_the_first_batch() -> None:
    kd, _ = _kd_with("rock", center_xy=(15.0, 0.0), size=(2.0, 2.0, 1.0))
    wi = _whatif(kd)
    cfg = PlannerConfig(budget_s=1e-9)
    planner = Planner(wi, cfg)
    n_all = len(planner.candidates())
    sel = planner.plan(GOAL, start=START)
    assert sel.budget_hit and sel.n_candidates == cfg.batch_size < n_all
    first = planner.candidates()[: cfg.batch_size]
    assert 0 <= sel.index < cfg.batch_size and sel.plan is not None
    assert sel.plan.name == first[sel.index].name
    # the best safe plan of that batch, judged independently
    res = wi.simulate(first, start=START)
    score = vj.evaluate(res, GOAL, VJConfig()).score
    safe = (res.collision_entity < 0) & (res.min_clearance_m >= cfg.min_clearance_m)
    assert safe.any() and sel.index == int(np.flatnonzero(safe)[np.argmax(score[safe])])
    assert sel.collision_entity == -1 and sel.xy.shape == (len(sel.t_s), 2)
    assert np.all(np.isfinite(sel.xy)) and sel.xy[-1, 0] > 1.0  # moving, not stopped
    full = Planner(wi).plan(GOAL, start=START)
    assert not full.budget_hit and full.n_candidates == n_all
    assert full.elapsed_s < PlannerConfig().budget_s


def test_batches_do_not_change_the_choice() -> None:
    kd, _ = _kd_with("rock", center_xy=(15.0, 0.0), size=(2.0, 2.0, 1.0))
    wi = _whatif(kd)
    one = Planner(wi, PlannerConfig(batch_size=1, budget_s=60.0)).plan(GOAL, start=START)
    all_ = Planner(wi, PlannerConfig(batch_size=1000)).plan(GOAL, start=START)
    assert not one.budget_hit and one.n_candidates == all_.n_candidates
    assert one.index == all_.index and one.cost == pytest.approx(all_.cost)
    np.testing.assert_allclose(one.xy, all_.xy)


@pytest.mark.parametrize(
    "field, value", [("budget_s", 0.0), ("budget_s", float("nan")), ("batch_size", 0)]
)
def test_planner_config_refuses_bad_values_by_name(field, value) -> None:
    with pytest.raises(ValueError, match=field):
        PlannerConfig(**{field: value})


# --- item 5: the last plan continued -----------------------------------------------------------


def test_the_last_plan_is_continued_shifted_by_the_time_elapsed() -> None:
    kd, _ = _kd_with("rock", center_xy=(200.0, 200.0))  # far away: a clear field
    wi = _whatif(kd)
    planner = Planner(wi)
    goal = np.array([25.0, 10.0])
    assert not any(isinstance(p, WaypointPlan) for p in planner.candidates(0))  # nothing yet
    sel1 = planner.plan(goal, start=START)
    assert sel1.n_candidates == len(planner.candidates()) == 54
    assert abs(sel1.yaw[-1]) > 0.1  # a turning plan, so the continuation is not a fan member
    cont = planner.candidates(500_000_000)[0]
    assert isinstance(cont, WaypointPlan) and cont.name == "continued"
    k = 6  # t_s[5] = 0.5 s is where the vehicle is now; waypoints from 0.6 s on
    np.testing.assert_allclose(cont.t_s[:-1], sel1.t_s[k:] - 0.5, atol=1e-9)
    np.testing.assert_array_equal(cont.xy[:-1], sel1.xy[k:])
    # one new waypoint at the horizon, 0.5 s on along the last step's velocity
    v_last = (sel1.xy[-1] - sel1.xy[-2]) / (sel1.t_s[-1] - sel1.t_s[-2])
    assert cont.t_s[-1] == pytest.approx(sel1.t_s[-1])
    np.testing.assert_allclose(cont.xy[-1], sel1.xy[-1] + 0.5 * v_last, atol=1e-9)
    assert planner.continued(-1) is None  # a start before the last plan
    assert planner.continued(10_000_000_000) is None  # the last plan is over

    # from where the last plan put the vehicle at 0.5 s, the continuation follows its path
    r1 = wi.simulate([sel1.plan], start=START)
    start2 = Start(sel1.xy[5].copy(), float(sel1.yaw[5]), float(r1.speed[0, 5]), 500_000_000)
    r2 = wi.simulate([cont], start=start2)
    dev = np.linalg.norm(r2.xy[0, : len(sel1.xy) - 5] - sel1.xy[5:], axis=1)
    assert dev.max() < 0.3, dev.max()
    sel2 = planner.plan(goal, start=start2)
    assert sel2.n_candidates == 55  # the continued plan weighed too
    assert planner.last is sel2 and planner.last_t_ns == 500_000_000

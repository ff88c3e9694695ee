"""What If and value judgment against analytic ground truth: a known box on a straight path,
a clear path, a detour, and plans What If must refuse."""

from __future__ import annotations

import numpy as np
import pytest

import kd_store
from kd_store import Attribute, Level, State, Status
from maps.stack import MapStack
from wm import vj
from wm.bg import Planner
from wm.config import VehicleConfig, VJConfig
from wm.whatif import ControlPlan, Start, WaypointPlan, WhatIf, WhatIfError

VEH = VehicleConfig()


def _kd_with_box(center_xy=(20.0, 0.0), size=(1.0, 1.0, 1.0), velocity=(0.0, 0.0, 0.0)):
    kd = kd_store.open()
    kd.begin_cycle(0)
    names = ("length_m", "width_m", "height_m")
    attrs = {n: Attribute(estimated=v) for n, v in zip(names, size, strict=True)}
    e = kd.add_entity("rock", Level.OBJECT, generic_classes=("rock",), status=Status.CONFIRMED,
                      confidence=0.9, attributes=attrs)  # fmt: skip
    kd.observe(e.id, State(0, "world", (*center_xy, 0.5), velocity_xyz=velocity))
    return kd, e.id


def _whatif(kd) -> WhatIf:
    stack = MapStack()
    stack.move_to(np.zeros(2))
    return WhatIf(kd, stack)


START = Start(np.zeros(2), 0.0, 5.0, 0)
STRAIGHT = ControlPlan(np.array([0.0]), np.array([5.0]), np.array([0.0]), "straight")


def test_collision_with_known_box_at_the_right_time_and_id() -> None:
    kd, box_id = _kd_with_box()
    res = _whatif(kd).simulate([STRAIGHT], start=START)
    # front bumper x = 5 t + L/2 meets the box face x = 19.5 at t = 3.45 s; steps of 0.1 s
    t_true = (19.5 - VEH.length_m / 2) / 5.0
    assert res.collision_entity[0] == box_id
    assert t_true <= res.collision_t_s[0] <= t_true + 0.1 + 1e-9
    assert res.min_clearance_m[0] == 0.0


def test_no_collision_on_a_clear_path_and_clearance_is_exact() -> None:
    kd, _ = _kd_with_box(center_xy=(20.0, 5.0))
    res = _whatif(kd).simulate([STRAIGHT], start=START)
    assert res.collision_entity[0] == -1 and np.isnan(res.collision_t_s[0])
    # lateral gap: box side y = 4.5, vehicle side y = 1.0
    assert res.min_clearance_m[0] == pytest.approx(3.5, abs=1e-6)
    assert res.distance_m[0] == pytest.approx(25.0, rel=1e-9)


def test_moving_entity_is_met_at_its_predicted_position() -> None:
    # a box crossing the path: at t = 2 s it is at (10, 0); the vehicle reaches x = 10 then
    kd, box_id = _kd_with_box(center_xy=(10.0, -6.0), velocity=(0.0, 3.0, 0.0))
    res = _whatif(kd).simulate([STRAIGHT], start=START)
    assert res.collision_entity[0] == box_id
    assert 1.0 < res.collision_t_s[0] < 2.5
    kd2, _ = _kd_with_box(center_xy=(10.0, -6.0))  # the same box standing still: no collision
    assert _whatif(kd2).simulate([STRAIGHT], start=START).collision_entity[0] == -1


def test_vj_ranks_a_detour_above_a_path_through_an_obstacle() -> None:
    kd, _ = _kd_with_box()
    t = np.linspace(0.0, 5.0, 21)
    y = np.interp(t, [0.0, 1.5, 3.0, 5.0], [0.0, 4.0, 4.0, 4.0])
    detour = WaypointPlan(t, np.stack([5.0 * t, y], 1), "detour")
    through = WaypointPlan(t, np.stack([5.0 * t, 0.0 * t], 1), "through")
    res = _whatif(kd).simulate([through, detour], start=START)
    ev = vj.evaluate(res, np.array([25.0, 4.0]), VJConfig())
    assert res.collision_entity.tolist()[1] == -1 and res.collision_entity[0] >= 0
    assert ev.best == 1 and ev.score[1] > ev.score[0]


def test_planner_avoids_the_box_and_keeps_moving() -> None:
    kd, _ = _kd_with_box(center_xy=(15.0, 0.0), size=(2.0, 2.0, 1.0))
    sel = Planner(_whatif(kd)).plan(np.array([40.0, 0.0]), start=START)
    assert sel.collision_entity == -1
    d = np.abs(sel.xy - np.array([15.0, 0.0]))
    assert np.all((d[:, 0] > 1.0 + VEH.length_m / 2) | (d[:, 1] > 1.0 + VEH.width_m / 2))
    assert sel.xy[-1, 0] > 15.0  # it went past, not stopped short


def test_many_plans_in_one_call_match_single_calls() -> None:
    kd, _ = _kd_with_box()
    plans = [ControlPlan(np.array([0.0]), np.array([v]), np.array([k]))
             for v in (2.0, 5.0, 8.0) for k in (-0.1, 0.0, 0.1)]  # fmt: skip
    wi = _whatif(kd)
    together = wi.simulate(plans, start=START)
    for i, p in enumerate(plans):
        alone = wi.simulate([p], start=START)
        np.testing.assert_allclose(together.xy[i], alone.xy[0])
        assert together.collision_entity[i] == alone.collision_entity[0]


@pytest.mark.parametrize(
    "plan, level, message",
    [
        (WaypointPlan(np.array([0.0, 1.0, 1.0]), np.zeros((3, 2))), "subsystem", "increase"),
        (WaypointPlan(np.array([0.0, 1.0]), np.array([[0, 0], [np.nan, 1]])), "subsystem", "NaN"),
        (STRAIGHT, "galaxy", "does not exist"),
        (ControlPlan(np.array([-1.0]), np.array([1.0]), np.array([0.0])), "subsystem", ">= 0"),
    ],
)
def test_bad_plans_are_refused_with_a_clear_message(plan, level, message) -> None:
    kd, _ = _kd_with_box()
    with pytest.raises(WhatIfError, match=message):
        _whatif(kd).simulate([plan], start=START, level=level)


def _result_equal(a, b) -> None:
    for name, v in vars(a).items():
        w = getattr(b, name)
        if isinstance(v, np.ndarray):
            assert np.array_equal(v, w, equal_nan=True), name
        else:
            assert v == w, name


def test_what_if_over_a_copy_answers_as_over_the_kd_then() -> None:
    """WhatIf.over a WhatIfCopy answers as WhatIf over the KD and the stack did when the copy
    was taken (start, maps, entities near the start, collisions), and goes on doing so after
    the KD and the maps change: a new box in the path, a wall of blocked cells, a moved self."""
    from wm.whatif import SAMPLED_LAYERS, WhatIfCopy

    kd, box_id = _kd_with_box(center_xy=(20.0, 0.0), velocity=(0.0, 0.1, 0.0))
    me = kd.add_entity("self", Level.OBJECT, generic_classes=("vehicle",),
                       status=Status.CONFIRMED, confidence=1.0)  # fmt: skip
    kd.observe(me.id, State(10**9, "world", (0.0, 0.0, 0.0), velocity_xyz=(4.0, 0.0, 0.0)))
    far = kd.add_entity("rock", Level.OBJECT, generic_classes=("rock",), status=Status.CONFIRMED)
    kd.observe(far.id, State(0, "world", (500.0, 0.0, 0.5)))  # beyond the reach: left out
    stack = MapStack()
    stack.move_to(np.zeros(2))
    lvl = stack.level("subsystem")
    xy = np.stack([np.linspace(0.0, 30.0, 200), np.linspace(-3.0, 3.0, 200)], 1)
    for layer, value in (("elevation", 0.1), ("slope", 0.05), ("traversability", 0.8),
                         ("cost", 0.3)):  # fmt: skip
        lvl.write(layer, xy, value)
    plans = [STRAIGHT, ControlPlan(np.array([0.0]), np.array([3.0]), np.array([0.1]), "left")]
    live = WhatIf(kd, stack, self_id=me.id)
    want = live.simulate(plans, horizon_s=6.0)
    assert want.collision_entity[0] == box_id  # the case holds a collision

    copy = WhatIfCopy.of(kd, stack, me.id, ["subsystem", "vehicle"])
    assert [lv.name for lv in copy.stack.levels] == ["subsystem", "vehicle"]
    assert copy.nbytes == sum(2 * 256 * 256 * 4 for _ in SAMPLED_LAYERS)  # float32 layers
    assert copy.boxes.ids.tolist() == [box_id, far.id]  # not self, id order
    over = WhatIf.over(copy)
    _result_equal(want, over.simulate(plans, horizon_s=6.0))
    near = over.entities_near(np.zeros(2), 100.0, 2 * 10**9)
    assert near.ids.tolist() == [box_id] and near.centers_xyz[0, 1] == pytest.approx(0.2)

    # the node goes on: the copy does not
    lvl.write("traversability", np.array([[10.0, 0.0]]), 0.0)
    lvl.storage("elevation")[...] = 5.0
    stack.move_to(np.array([8.0, 0.0]))
    kd.observe(me.id, State(2 * 10**9, "world", (4.0, 0.0, 0.0)))
    rock = kd.add_entity("rock", Level.OBJECT, generic_classes=("rock",), status=Status.CONFIRMED)
    kd.observe(rock.id, State(10**9, "world", (6.0, 0.0, 0.5)))
    assert not np.array_equal(live.simulate(plans, horizon_s=6.0).xy, want.xy)
    _result_equal(want, over.simulate(plans, horizon_s=6.0))
    with pytest.raises(WhatIfError, match="primitive"):  # a level not copied does not exist
        over.simulate(plans, level="primitive")

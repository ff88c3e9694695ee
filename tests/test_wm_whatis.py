"""What Is on a hand-built KD and a small map stack: analytic states, memory tiers, the time
and frame every answer carries, and bad queries."""

from __future__ import annotations

import numpy as np
import pytest

import kd_store
from core.geometry import NS_PER_S
from kd_store import Level, State, Status
from maps.fusion import FusionConfig
from maps.level import LevelConfig
from maps.stack import MapStack, StackConfig
from wm.whatis import RegionAnswer, WhatIs, WhatIsError


def _kd_with_track():
    """A confirmed surface entity moving at 1 m/s along x, a state every second for 10 s."""
    kd = kd_store.open()
    kd.begin_cycle(0)
    e = kd.add_entity("wall", Level.SURFACE, generic_classes=("wall",), status=Status.CONFIRMED,
                      confidence=0.9)  # fmt: skip
    for k in range(11):
        kd.observe(e.id, State(k * NS_PER_S, "world", (float(k), 0.0, 0.0), velocity_xyz=(1, 0, 0)))
    return kd, e.id


def test_as_of_a_time_in_short_term_memory() -> None:
    kd, i = _kd_with_track()
    wi = WhatIs(kd)
    a = wi.entity(i, int(7.5 * NS_PER_S))
    assert a.source == "short_term" and a.t_ns == 7 * NS_PER_S
    np.testing.assert_allclose(a.position, (7.0, 0.0, 0.0))
    assert wi.entity(i).source == "current" and wi.entity(i).t_ns == 10 * NS_PER_S


def test_older_than_short_term_memory_falls_back_to_long_term() -> None:
    kd, i = _kd_with_track()
    kd.advance(10 * NS_PER_S)  # the subsystem level keeps 5 s; the confirmed wall is promoted
    assert kd.history(i)[0].t_ns >= 5 * NS_PER_S
    a = WhatIs(kd).entity(i, 2 * NS_PER_S)
    assert a.source == "long_term" and a.t_ns == 2 * NS_PER_S
    assert "before short-term memory" in a.note
    np.testing.assert_allclose(a.position, (2.0, 0.0, 0.0))


def test_a_time_no_memory_holds_is_refused_with_the_reason() -> None:
    kd, i = _kd_with_track()
    with pytest.raises(WhatIsError, match="before short-term memory"):
        WhatIs(kd).entity(i, -5 * NS_PER_S)


def test_region_filters_and_events_interval() -> None:
    kd, i = _kd_with_track()
    wi = WhatIs(kd)
    inside = wi.region(kd_store.Circle("world", (10.0, 0.0), 1.0), classes=["surface"])
    assert inside.tolist() == [i]
    assert wi.region(kd_store.Circle("world", (10.0, 0.0), 1.0), min_confidence=0.95).size == 0
    kd.add_event("bump", "contact", 3 * NS_PER_S, t_end_ns=4 * NS_PER_S)
    assert [e.class_name for e in wi.events(0, 5 * NS_PER_S)] == ["contact"]
    assert wi.events(5 * NS_PER_S, 6 * NS_PER_S) == []
    with pytest.raises(WhatIsError, match="ends before it starts"):
        wi.events(6, 5)
    assert wi.sql("SELECT count(*) AS n FROM entities").column("n")[0].as_py() == 1


def test_a_future_time_says_so_and_holds_the_newest_state() -> None:
    kd, i = _kd_with_track()  # cycle at 0 s, newest state at 10 s
    wi = WhatIs(kd, self_id=i)
    now = wi.entity(i, 10 * NS_PER_S)
    assert now.source == "current" and now.note == ""
    a = wi.entity(i, 12 * NS_PER_S)
    assert a.source == "future" and a.t_ns == 10 * NS_PER_S
    assert str(12 * NS_PER_S) in a.note and str(10 * NS_PER_S) in a.note
    np.testing.assert_allclose(a.position, (10.0, 0.0, 0.0))  # held, not extrapolated
    assert wi.self_state(12 * NS_PER_S).source == "future"
    # up to the KD's cycle time the newest state is the state as of then, not a future one
    kd.begin_cycle(12 * NS_PER_S)
    assert wi.entity(i, 12 * NS_PER_S).source == "current"
    assert wi.entity(i, 13 * NS_PER_S).source == "future"
    assert "(12000000000)" in wi.entity(i, 13 * NS_PER_S).note


def test_region_answer_carries_time_frame_and_reads_as_ids() -> None:
    kd, wall = _kd_with_track()  # confirmed, confidence 0.9, at (10, 0) since 10 s
    box = kd.add_entity("box", Level.SURFACE, generic_classes=("wall",),
                        status=Status.HYPOTHESIZED, confidence=0.5)  # fmt: skip
    kd.observe(box.id, State(8 * NS_PER_S, "world", (10.5, 0.0, 0.0)))
    wi = WhatIs(kd)
    near = kd_store.Circle("world", (10.0, 0.0), 1.0)
    a = wi.region(near)
    assert isinstance(a, RegionAnswer)
    assert a.frame == "world" and a.t_ns == 10 * NS_PER_S  # the newest state found
    assert a.ids.dtype == np.int64 and a.ids.tolist() == sorted([wall, box.id])
    assert a.t_state_ns.tolist() == [10 * NS_PER_S if j == wall else 8 * NS_PER_S for j in a.ids]
    # still reads as the bare id array callers used
    assert a.tolist() == list(a) == np.asarray(a).tolist() and len(a) == a.size == 2
    assert wall in a and a[0] == a.ids[0]
    # status and confidence filters
    assert wi.region(near, statuses=[Status.CONFIRMED]).tolist() == [wall]
    assert wi.region(near, statuses=["hypothesized"]).tolist() == [box.id]
    assert wi.region(near, statuses=[Status.DENIED]).size == 0
    assert wi.region(near, min_confidence=0.6).tolist() == [wall]
    assert wi.region(near, min_confidence=0.5).tolist() == sorted([wall, box.id])
    only_box = wi.region(near, statuses=["hypothesized"], min_confidence=0.6)
    assert only_box.size == 0 and only_box.t_state_ns.size == 0
    assert only_box.t_ns == 0  # no state found: the KD's cycle time (begin_cycle(0))
    # the KD's cycle time when it is later; the frame is the region's
    kd.begin_cycle(11 * NS_PER_S)
    assert wi.region(near).t_ns == 11 * NS_PER_S
    odom = wi.region(kd_store.Circle("odom", (10.0, 0.0), 1.0))
    assert odom.frame == "odom" and odom.size == 0 and odom.t_ns == 11 * NS_PER_S


def test_map_window_carries_the_last_fused_sweep_time_and_world_geometry() -> None:
    cfg = StackConfig(
        levels=(LevelConfig("fine", 0.5, size=32), LevelConfig("coarse", 2.0, size=32)),
        fusion=FusionConfig(compiled=False),
    )
    stack = MapStack(cfg)
    stack.move_to(np.array([3.0, -2.0]))
    wi = WhatIs(kd_store.open(), stack)
    assert wi.map_window("fine").t_ns == -1  # nothing fused yet
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-2, 8, 400), rng.uniform(-7, 3, 400), np.zeros(400)])
    stack.fuse(pts, t_ns=3 * NS_PER_S, variance_m2=0.01)
    stack.fuse(pts + np.array([0.0, 0.0, 0.1]), t_ns=3 * NS_PER_S + 100_000_000, variance_m2=0.01)
    for name in ("fine", "coarse"):
        a = wi.map_window(name, ("elevation", "last_seen_ns"), size=16)
        assert a.level == name and a.frame == "world"
        assert isinstance(a.t_ns, int) and a.t_ns == 3 * NS_PER_S + 100_000_000
        assert a.layers["last_seen_ns"].max() == a.t_ns  # the window's newest cell agrees
        lvl = stack.level(name)
        np.testing.assert_allclose(a.xy_min, (np.floor(lvl.center_xy / lvl.resolution_m) - 8)
                                   * lvl.resolution_m)  # fmt: skip
    # the time moves with every fused sweep
    stack.fuse(pts, t_ns=4 * NS_PER_S, variance_m2=0.01)
    assert wi.map_window("coarse").t_ns == 4 * NS_PER_S


def test_an_unknown_frame_is_named_before_any_state_exists() -> None:
    """A frame that does not exist is the question's fault, answered the same before the
    entity has a state (a controller asking at start-up) as after."""
    kd = kd_store.open()
    e = kd.add_entity("self", Level.OBJECT, status=Status.CONFIRMED, confidence=1.0)
    wi = WhatIs(kd, self_id=e.id)
    with pytest.raises(WhatIsError, match="unknown frame 'mars'"):
        wi.entity(e.id, frame="mars")
    with pytest.raises(WhatIsError, match="has no state"):  # a known frame: the state is asked
        wi.entity(e.id, frame="base_link")

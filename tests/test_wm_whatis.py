"""What Is on a hand-built KD: analytic states, memory tiers and bad queries."""

from __future__ import annotations

import numpy as np
import pytest

import kd_store
from kd_store import Level, State, Status
from maps.frames import NS_PER_S
from wm.whatis import WhatIs, WhatIsError


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

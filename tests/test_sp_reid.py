"""Re-identification (sp.reid): a hypothesis takes the frame of an object lost moments ago
when it lies where that object would be, and only then; through SP, a box that is hidden
until its track is gone and then comes back along its path keeps its one KD entity."""

from __future__ import annotations

import numpy as np
import pytest
from test_sp_levels_units import SENSOR_H, _scan_of, flat_scene

import kd_store
from kd_store import Level
from sp.context import SPConfig
from sp.egosphere import EgosphereConfig
from sp.reid import Lost, LostObjects, ReidConfig, ReidError
from wm.entities import KDSensoryProcessor

S = 1_000_000_000  # ns per second


def _walker(oid: int = 7, t_s: float = 10.0) -> Lost:
    """A 1.7 m tall walker lost at (0, 0) walking +x at 1.4 m/s."""
    return Lost(oid, round(t_s * S), np.zeros(2), np.array([1.4, 0.0]), 1.7, moving=True)


def _ids(lost: LostObjects, t_s: list[float], xy: list, height_m: list[float]) -> list[int]:
    """The frame ids ``lost.match`` finds for hypotheses at times ``t_s``, -1 for none."""
    found = lost.match(
        np.array([round(t * S) for t in t_s]), np.array(xy, dtype=float), np.array(height_m)
    )
    return [-1 if o is None else o.id for o in found]


def test_a_walker_found_along_its_path_takes_its_frame_back() -> None:
    lost = LostObjects()
    walker = _walker()
    lost.add(walker)
    # 2 s later, 2.8 m along its path and 1.5 m to the side (it turned): within 1 + 1.5 * 2 m
    found = lost.match(np.array([12 * S]), np.array([[2.8, 1.5]]), np.array([1.6]))
    assert found == [walker] and len(lost) == 0
    # once taken, it is not found a second time
    assert _ids(lost, [12.0], [(2.8, 1.5)], [1.6]) == [-1]


@pytest.mark.parametrize(
    ("t_s", "xy", "height_m", "why"),
    [
        (12.0, (2.8, 4.5), 1.7, "beyond the gate of 4 m at 2 s"),
        (12.0, (2.8, 0.0), 0.9, "0.8 m lower"),
        (14.5, (6.3, 0.0), 1.7, "lost for longer than max_gap_s"),
        (9.0, (0.0, 0.0), 1.7, "seen before it was lost"),
    ],
)
def test_a_hypothesis_elsewhere_is_new(t_s: float, xy: tuple, height_m: float, why: str) -> None:
    lost = LostObjects()
    lost.add(_walker())
    assert _ids(lost, [t_s], [xy], [height_m]) == [-1], why
    assert len(lost) == 1


def test_an_object_at_rest_comes_back_where_it_was() -> None:
    lost = LostObjects()
    lost.add(Lost(3, 10 * S, np.array([5.0, 5.0]), np.zeros(2), 1.0, moving=False))
    # 2 s later, 2 m away: a walker's gate would take it, a bush's does not
    assert _ids(lost, [12.0], [(7.0, 5.0)], [1.0]) == [-1]
    assert _ids(lost, [12.0], [(5.6, 5.4)], [1.0]) == [3]


def test_two_walkers_are_paired_by_the_nearest_predictions() -> None:
    lost = LostObjects()
    lost.add(_walker(1))  # from (0, 0) at +1.4 m/s in x
    lost.add(Lost(2, 10 * S, np.array([0.0, 1.0]), np.array([0.0, 1.4]), 1.7, True))
    # 1 s later: one at (1.4, 0), one at (0, 2.4); given in the other order
    assert _ids(lost, [11.0, 11.0], [(0.1, 2.3), (1.3, 0.1)], [1.7, 1.7]) == [2, 1]


def test_objects_lost_long_ago_are_forgotten_and_a_disabled_memory_keeps_none() -> None:
    lost = LostObjects(ReidConfig(max_gap_s=4.0))
    lost.add(_walker(t_s=10.0))
    lost.forget_before(13 * S)
    assert len(lost) == 1
    lost.forget_before(15 * S)
    assert len(lost) == 0
    off = LostObjects(ReidConfig(enabled=False))
    off.add(_walker())
    assert len(off) == 0


@pytest.mark.parametrize(
    ("kw", "name"),
    [({"radius_m": 0.0}, "radius_m 0.0"), ({"speed_mps": -1.0}, "speed_mps -1.0")],
)
def test_a_setting_that_cannot_be_used_is_refused(kw: dict, name: str) -> None:
    with pytest.raises(ReidError, match=name):
        ReidConfig(**kw)


def _run_hidden_box(reid: ReidConfig, seen_again: int = 10, n_sweeps: int = 40):
    """A 2 m box driving +x at 2.5 m/s from 10 m ahead of the sensor, seen for 1.5 s, hidden for
    1.5 s (longer than its track is kept unseen) and seen again for ``seen_again`` sweeps (then
    hidden), over ``n_sweeps`` sweeps at 10 Hz; the KD SP wrote."""
    kd = kd_store.open(":memory:")
    cfg = SPConfig(egosphere=EgosphereConfig(n_rows=32, n_cols=360, max_returns=1), reid=reid)
    sp = KDSensoryProcessor(kd, cfg)
    T = np.eye(4)
    T[2, 3] = SENSOR_H
    for k in range(n_sweeps):
        hidden = 15 <= k < 30 or k >= 30 + seen_again
        xyz, valid, _ = flat_scene(box_xy=None if hidden else (10.0 + 0.25 * k, 0.0))
        assert sp.process(_scan_of(xyz, valid, k * 100_000_000), T).ok
    return kd


def _objects(kd) -> list:
    """The KD's level-4 entities that were not denied (a one-off hypothesis may be)."""
    return [f for f in kd.entities() if f.level == Level.OBJECT and f.status.value != "denied"]


def test_a_box_hidden_until_its_track_is_gone_keeps_its_entity() -> None:
    kd = _run_hidden_box(ReidConfig())
    objects = _objects(kd)
    assert len(objects) == 1
    box = objects[0]
    assert box.status.value == "confirmed"
    # it appeared and was confirmed twice, and vanished once in between, as one entity
    for event, n in (("appeared", 2), ("confirmed", 2), ("vanished", 1)):
        assert len(kd.events(class_name=event, participant=box.id)) == n, event
    # where the box is now: its near face at x = 18.75 m, its far side at 20.75 m
    assert 18.5 <= box.state.position_xyz[0] <= 20.75
    # without re-identification the same run leaves two entities for the one box
    kd_off = _run_hidden_box(ReidConfig(enabled=False))
    assert len(_objects(kd_off)) == 2


def test_a_lost_object_found_again_by_a_denied_hypothesis_stays_gone() -> None:
    # seen again for two sweeps only: the hypothesis took the box's frame and was denied
    kd = _run_hidden_box(ReidConfig(), seen_again=2)
    objects = _objects(kd)
    assert len(objects) == 1
    box = objects[0]
    # the box's confirmed life stands: gone, not denied, with its states kept, and nothing
    # appeared that was not confirmed
    assert box.status.value == "gone"
    for event, n in (("appeared", 1), ("confirmed", 1), ("vanished", 1), ("denied", 0)):
        assert len(kd.events(class_name=event, participant=box.id)) == n, event


def test_a_lost_object_being_found_again_is_gone_until_confirmed() -> None:
    # the run ends two sweeps after the box is seen again: its hypothesis has the box's frame
    # but is not confirmed yet, and the KD holds the box gone, as it was, not hypothesized
    kd = _run_hidden_box(ReidConfig(), n_sweeps=32)
    assert [f.status.value for f in _objects(kd)] == ["gone"]
    # two sweeps later it is confirmed again
    kd = _run_hidden_box(ReidConfig(), n_sweeps=34)
    assert [f.status.value for f in _objects(kd)] == ["confirmed"]

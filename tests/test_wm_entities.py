"""The world model's entity update (wm.entities, reference 001, 4.2): SP observes, the world
model writes. SP alone leaves the KD as it was; its observations, written in order, give every
entity of its images a frame, the events their frames; the observations that depend on the KD
are judged against it as the earlier writes left it."""

from __future__ import annotations

import numpy as np
import pytest
from test_sp_levels_units import SENSOR_H, H, W, _scan_of, flat_scene

import kd_store
from kd_store import Level, Status
from sp.egosphere import EgosphereConfig
from sp.observations import FrameChange, NewEntity, PartsGone, StateObserved, StateRule
from sp.pipeline import SensoryProcessor, SPConfig
from wm.entities import EntityUpdater, KDSensoryProcessor


def _T_world_ladar() -> np.ndarray:
    T = np.eye(4)
    T[2, 3] = SENSOR_H
    return T


def _config() -> SPConfig:
    return SPConfig(egosphere=EgosphereConfig(n_rows=H, n_cols=W))


def test_sp_writes_nothing_and_the_updater_writes_what_it_observed() -> None:
    xyz, valid, _ = flat_scene()
    kd = kd_store.open(":memory:")
    sp = SensoryProcessor(kd.classes, kd.new_id, _config())
    updater = EntityUpdater(kd)
    for k in range(5):
        r = sp.process(_scan_of(xyz, valid, k * 100_000_000), _T_world_ladar())
        assert r.ok and r.observations
        # SP's sweep wrote no frame: what is in the KD came from the earlier sweeps' updates
        new = [op.entity_id for op in r.observations if isinstance(op, NewEntity)]
        assert not any(i in kd for i in new)
        assert not any(i in kd for i in r.events)
        assert updater.apply(r.observations) == len(r.observations)
        # every entity of the sweep's images and every event now has its frame
        for level, image in r.entity_images.items():
            for i in np.unique(image[image >= 0]):
                assert kd.get(int(i)).level == level
        for e in r.events:
            assert kd.get_event(e).t_start_ns == r.t_ns
    assert any(f.level == Level.OBJECT for f in kd.entities())


def test_kd_sensory_processor_gives_the_same_kd_as_sp_then_the_updater() -> None:
    xyz, valid, _ = flat_scene()
    kd_a, kd_b = kd_store.open(":memory:"), kd_store.open(":memory:")
    sp_a = SensoryProcessor(kd_a.classes, kd_a.new_id, _config())
    sp_b = KDSensoryProcessor(kd_b, _config())
    updater = EntityUpdater(kd_a)
    for k in range(6):
        scan = _scan_of(xyz, valid, k * 100_000_000)
        updater.apply(sp_a.process(scan, _T_world_ladar()).observations)
        sp_b.process(scan, _T_world_ladar())

    def frames(kd: kd_store.KnowledgeDatabase) -> list[tuple]:
        return [(f.id, f.name, f.level, f.status, f.confidence) for f in kd.entities()]

    assert frames(kd_a) == frames(kd_b) and len(frames(kd_a)) > 2


def test_conditional_observations_are_judged_against_the_kd() -> None:
    kd = kd_store.open(":memory:")
    updater = EntityUpdater(kd)
    denied = kd.add_entity("d", Level.LIST, status=Status.DENIED).id
    open_ = kd.add_entity("o", Level.LIST, status=Status.HYPOTHESIZED).id
    confirmed = kd.add_entity("c", Level.LIST, status=Status.CONFIRMED).id
    forgotten = kd.next_id + 10  # an id the KD does not hold
    updater.apply(
        [
            PartsGone((denied, confirmed, forgotten)),  # a denied list stays denied
            FrameChange(open_, status=Status.CONFIRMED, if_status=Status.HYPOTHESIZED),
            FrameChange(confirmed, status=Status.DENIED, if_status=Status.HYPOTHESIZED),
        ]
    )
    assert kd.get(denied).status == Status.DENIED
    assert kd.get(confirmed).status == Status.GONE  # gone, and not denied after that
    assert kd.get(open_).status == Status.CONFIRMED
    assert forgotten not in kd
    s = kd.add_entity("s", Level.SURFACE).id
    p0, v0 = np.array([1.0, 2.0, 0.0]), np.zeros(3)
    updater.apply(
        [
            StateObserved(s, 100, p0, v0, StateRule.IF_NEWER),
            StateObserved(s, 100, p0 + 1.0, v0, StateRule.IF_NEWER),  # no newer: not written
        ]
    )
    assert kd.get(s).state.t_ns == 100 and kd.get(s).state.position_xyz[0] == 1.0
    updater.apply([StateObserved(s, 100, p0 + 1.0, v0, StateRule.AFTER_LAST)])
    assert kd.get(s).state.t_ns == 101 and kd.get(s).state.position_xyz[0] == 2.0


def _sweeps_with_a_refused_write(tell: bool, n_sweeps: int = 6) -> SensoryProcessor:
    """SP on the flat scene, its observations written after each sweep, as the node's entity
    step does; in the first sweep the KD refuses the making of the first level-2 list, so it
    and the rest of that sweep's observations are skipped. With ``tell`` SP is told how many
    were written. A later write the KD refuses raises its KDError."""
    xyz, valid, _ = flat_scene()
    kd = kd_store.open(":memory:")
    sp = SensoryProcessor(kd.classes, kd.new_id, _config())
    updater = EntityUpdater(kd)
    for k in range(n_sweeps):
        r = sp.process(_scan_of(xyz, valid, k * 100_000_000), _T_world_ladar())
        n = None
        if k == 0:
            ops = r.observations
            n = next(
                i
                for i, op in enumerate(ops)
                if isinstance(op, NewEntity) and op.entity_id in sp.level2.ids
            )
            updater.apply(ops[:n])
        else:
            updater.apply(r.observations)
        sp.observations_written(r, n if tell else None)
    return sp


def test_sp_told_what_was_not_written_asks_nothing_of_those_frames() -> None:
    """SP holds no KD: told which observations the world model could not write, it releases
    the lists whose making was skipped (their pixels start new lists) and the following
    sweeps' writes are all accepted; not told, it changes a frame the KD never had."""
    sp = _sweeps_with_a_refused_write(tell=True)
    assert sp.level2.dead.any() and (~sp.level2.dead).any()
    with pytest.raises(kd_store.KDError, match="unknown id"):
        _sweeps_with_a_refused_write(tell=False)


def test_sp_told_what_the_kd_forgot_releases_those_lists() -> None:
    """Lists short-term memory forgot (``kd.advance``) are released when next seen, and new
    lists take their pixels; SP not told keeps them."""
    xyz, valid, _ = flat_scene()
    held = []
    for tell in (True, False):
        kd = kd_store.open(":memory:")
        sp = KDSensoryProcessor(kd, _config())
        for k in range(3):
            sp.process(_scan_of(xyz, valid, k * 100_000_000), _T_world_ladar())
        forgotten = kd.advance(1_500_000_000)  # 1.2 s on: the level-2 hypotheses go
        assert forgotten and all(i in sp.level2.ids for i in forgotten)
        if tell:
            sp.frames_forgotten(forgotten)
        for k in range(3, 5):
            assert sp.process(_scan_of(xyz, valid, k * 100_000_000), _T_world_ladar()).ok
        released = sp.level2.dead[np.isin(sp.level2.ids, forgotten)]
        held.append(set(sp.level2.ids.tolist()) - set(forgotten))
        assert released.any() if tell else not released.any()
    assert held[0] > held[1]  # the released lists' pixels made new lists


def test_groups_keep_the_status_their_frames_hold() -> None:
    """Level 5 keeps each group's status and confidence itself; what the world model could
    not write is undone: a change back to the frame's values, a group never made dropped."""
    kd = kd_store.open(":memory:")
    sp = SensoryProcessor(kd.classes, kd.new_id, SPConfig())
    tc = sp.config.tracker
    members = frozenset({101, 102})
    old = 7  # a group of earlier sweeps, about to be confirmed
    sp.level5.frames[old] = (Status.HYPOTHESIZED, 0.9)
    sp.level5.groups = {old: members}
    sp.level5._group_hits[old] = tc.min_hits
    new = sp.ctx.new_entity("g", Level.GROUP, ("sp5_groups",), confidence=tc.confidence0)
    for gid in (old, new):
        sp.level5.filter(gid, 1000, members, [])
    assert sp.level5.frames[old][0] == Status.CONFIRMED and new in sp.level5.frames
    ops = sp.ctx.take_observations()
    sp.not_written(ops)
    assert sp.level5.frames == {old: (Status.HYPOTHESIZED, 0.9)}

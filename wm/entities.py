"""The world model's entity update: SP's observations of one sweep into the KD.

Reference 001, 4.2 (the world model keeps the KD current, ``KD(t) = KD(t-1) +
Observation(t)``), 4.4.2 (entity frames), 4.4.8 (event frames), 4.4.3 (specific classes
founded from entities). One call of :meth:`EntityUpdater.apply` is the node cycle's entity
step (docs/architecture.md, the node cycle): each observation of :mod:`sp.observations`, in
the order SP made them, becomes an entity frame, a change of one, a state, a relation, an
event frame with its ``involves`` pointers, or a specific class. The few observations that
depend on what the KD holds (a list already denied or forgotten, a state no newer than the
latest) are judged against the KD as the earlier ones of the sweep left it.

SP holds no KD: it is given the class library and the KD's id source, and told what became
of its observations (how many were written, which frames short-term memory forgot).
:class:`KDSensoryProcessor` is SP with this step after every sweep, for callers that run SP
on its own and want its frames in the KD at once (tests, benchmarks).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import Any

import kd_store
from kd_store import State, Status
from sp.observations import (
    AppearanceObserved,
    ClassFounded,
    EventObserved,
    FrameChange,
    NewEntity,
    Observation,
    PartsGone,
    Related,
    StateObserved,
    StateRule,
    StatesObserved,
    Unrelated,
)
from sp.pipeline import SensoryProcessor, SPConfig, SPResult


class EntityUpdater:
    """Writes SP's observations into ``kd``: the only writer of SP's entity and event frames."""

    def __init__(self, kd: kd_store.KnowledgeDatabase) -> None:
        self.kd = kd
        self.n_written = 0  # observations written since the start
        self.n_applied = 0  # observations the last apply wrote (before a refused one)
        self._write: dict[type, Callable[[Any], None]] = {
            NewEntity: self._new_entity,
            FrameChange: self._frame_change,
            PartsGone: self._parts_gone,
            StateObserved: self._state,
            StatesObserved: self._states,
            Related: self._related,
            Unrelated: self._unrelated,
            EventObserved: self._event,
            ClassFounded: self._class_founded,
            AppearanceObserved: self._appearance,
        }

    def apply(self, observations: Iterable[Observation]) -> int:
        """Write ``observations`` in order; returns how many. A write the KD refuses raises
        its ``KDError`` (the observations before it, ``n_applied`` of them, are written)."""
        self.n_applied = 0
        for op in observations:
            self._write[type(op)](op)
            self.n_applied += 1
        self.n_written += self.n_applied
        return self.n_applied

    def _new_entity(self, op: NewEntity) -> None:
        self.kd.add_entity(
            op.name,
            op.level,
            id=op.entity_id,
            images=op.images,
            status=op.status,
            confidence=op.confidence,
            generic_classes=op.generic_classes,
        )

    def _frame_change(self, op: FrameChange) -> None:
        kd = self.kd
        if op.if_status is not None:
            if op.entity_id not in kd or kd.get(op.entity_id).status != op.if_status:
                return
        changes: dict[str, object] = {}
        if op.status is not None:
            changes["status"] = op.status
        if op.confidence is not None:
            changes["confidence"] = op.confidence
        if op.attributes is not None:
            changes["attributes"] = op.attributes
        if op.generic_classes is not None:
            changes["generic_classes"] = op.generic_classes
        if op.sets_specific:
            changes["specific_class"] = op.specific_class
        kd.update_entity(op.entity_id, **changes)

    def _parts_gone(self, op: PartsGone) -> None:
        kd = self.kd
        for lid in op.entity_ids:
            if lid in kd and kd.get(lid).status != Status.DENIED:
                kd.update_entity(lid, status=Status.GONE)

    def _state(self, op: StateObserved) -> None:
        last = self.kd.get(op.entity_id).state
        t_ns = op.t_ns
        if op.rule == StateRule.IF_NEWER:
            if last is not None and last.t_ns >= t_ns:
                return
        elif last is not None:  # AFTER_LAST
            t_ns = max(t_ns, last.t_ns + 1)
        state = State(t_ns, "world", op.position_xyz, velocity_xyz=op.velocity_xyz)
        self.kd.observe(op.entity_id, state)

    def _states(self, op: StatesObserved) -> None:
        self.kd.ingest(op.batch)

    def _related(self, op: Related) -> None:
        self.kd.relate(op.src, op.kind, op.dst, t_ns=op.t_ns)

    def _unrelated(self, op: Unrelated) -> None:
        if not op.if_present or op.src in self.kd:
            self.kd.unrelate(op.src, op.kind, op.dst, t_ns=op.t_ns)

    def _event(self, op: EventObserved) -> None:
        write_event(self.kd, op)

    def _class_founded(self, op: ClassFounded) -> None:
        self.kd.found_specific_class(op.entity_id)

    def _appearance(self, op: AppearanceObserved) -> None:
        attrs = dict(self.kd.get(op.entity_id).attributes)
        attrs["camera_intensity"] = kd_store.Attribute(
            observed=op.camera_intensity, observed_var=0.01
        )
        attrs["camera_coverage"] = kd_store.Attribute(observed=op.camera_coverage)
        if math.isfinite(op.camera_excess_green):
            attrs["camera_excess_green"] = kd_store.Attribute(observed=op.camera_excess_green)
        self.kd.update_entity(op.entity_id, attributes=attrs)


def write_event(kd: kd_store.KnowledgeDatabase, op: EventObserved) -> int:
    """Add the instantaneous event frame of ``op`` (start = end = ``op.t_ns``, its reserved
    id) and its ``involves`` pointers to the entities; returns its id."""
    ids = list(op.entity_ids)
    cls = op.event_class
    name = f"{cls.value}:{','.join(map(str, ids[:4]))}{'...' if len(ids) > 4 else ''}"
    ev = kd.add_event(
        name,
        cls.value,
        op.t_ns,
        id=op.event_id,
        t_end_ns=op.t_ns,
        level=op.level,
        confidence=float(min(max(op.confidence, 0.0), 1.0)),
        attributes={},
    )
    for i in ids:
        kd.relate(ev.id, "involves", i, t_ns=op.t_ns)
    return ev.id


class KDSensoryProcessor(SensoryProcessor):
    """SP followed by the entity update on every sweep: :meth:`process` returns SP's result
    after its observations are in the KD, as the node cycle does in two steps. SP is given
    ``kd``'s class library and id source; ``kd`` itself only the updater holds. A caller that
    lets the KD's memory move on (``kd.advance``) tells SP what it forgot
    (:meth:`frames_forgotten`), as the node does."""

    def __init__(self, kd: kd_store.KnowledgeDatabase, config: SPConfig | None = None) -> None:
        super().__init__(kd.classes, kd.new_id, config)
        self.updater = EntityUpdater(kd)

    def process(self, *args: Any, **kwargs: Any) -> SPResult:
        """:meth:`SensoryProcessor.process` (same arguments, passed on as given, so the two
        signatures cannot drift apart), then its observations into the KD."""
        result = super().process(*args, **kwargs)
        self._apply(result.observations)
        self.observations_written(result)
        return result

    def write_pending(self) -> int:
        """Write what the levels observed outside :meth:`process` (a level's step called on
        its own); returns how many observations."""
        n = self._apply(self.ctx.take_observations())
        self.level4.refresh_classes()
        return n

    def _apply(self, observations: list[Observation]) -> int:
        """The updater's :meth:`EntityUpdater.apply`; when the KD refuses a write, SP is told
        which observations were not written before the error propagates."""
        try:
            return self.updater.apply(observations)
        except kd_store.KDError:
            self.not_written(observations[self.updater.n_applied :])
            raise

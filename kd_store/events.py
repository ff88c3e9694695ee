"""Event frames in RAM: what happened, when, and which of them long-term memory holds.

Reference 001, sections 4.4.8-4.4.9 (event frame, Figure 27) and 4.4.11 (memory tiers). An
event spans ``[t_start_ns, t_end_ns]`` (int64 ns; ``t_end_ns`` None: still going on). Its
pointers (parent and sub-events, before/after, causes, the entities it involves) live in the
relation graph (:mod:`kd_store.relations`); ids come from the KD, which shares one id space
between entities and events.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from kd_store.entities import NO_TIME, TakeId, new_where
from kd_store.errors import KDError
from kd_store.frames import EventFrame, check_event


def overlapping(
    events: Iterable[EventFrame], t_from_ns: int | None, t_to_ns: int | None, class_name: str | None
) -> list[EventFrame]:
    """The ``events`` overlapping [t_from_ns, t_to_ns] (int64 ns; None: unbounded) of
    ``class_name`` (None: any), in start-time order (then id)."""
    lo = NO_TIME if t_from_ns is None else t_from_ns
    hi = np.iinfo(np.int64).max if t_to_ns is None else t_to_ns
    out = [
        e
        for e in events
        if e.overlaps(lo, hi) and (class_name is None or e.class_name == class_name)
    ]
    return sorted(out, key=lambda e: (e.t_start_ns, e.id))


class EventTable:
    """Every event frame in RAM, which of them are in long-term memory and which changed
    since the last flush."""

    def __init__(self) -> None:
        self._events: dict[int, EventFrame] = {}
        self._ltm: set[int] = set()
        self._dirty: set[int] = set()

    def __contains__(self, event_id: object) -> bool:
        return event_id in self._events

    def __len__(self) -> int:
        return len(self._events)

    def load(self, events: Iterable[EventFrame]) -> None:
        """Put events recalled from long-term memory back (clean)."""
        for e in events:
            self._events[e.id] = e
            self._ltm.add(e.id)

    def add(
        self, name: str, class_name: str, t_start_ns: int, fields: dict[str, Any], take_id: TakeId
    ) -> EventFrame:
        """Make an event frame (fields as :class:`EventFrame`; ``id`` optional) and add it;
        the id is taken only once the frame passed its checks."""
        frame_id = fields.pop("id", None)
        probe = EventFrame(id=0, name=name, class_name=class_name, t_start_ns=t_start_ns, **fields)
        check_event(probe, new_where("event", frame_id, name))
        e = dataclasses.replace(probe, id=take_id(frame_id, f"new event {name!r}"))
        self._events[e.id] = e
        self._dirty.add(e.id)
        return e

    def insert(self, event: EventFrame, take_id: TakeId) -> EventFrame:
        """Add a complete event frame with its own id (which must be free)."""
        check_event(event)
        take_id(event.id, f"event {event.id} ({event.name!r})")
        self._events[event.id] = event
        self._dirty.add(event.id)
        return event

    def get(self, event_id: int) -> EventFrame:
        try:
            return self._events[event_id]
        except KeyError:
            raise KDError(f"event {event_id!r}: unknown id") from None

    def update(self, event_id: int, changes: dict[str, Any]) -> EventFrame:
        """Change fields of an event frame (e.g. ``t_end_ns`` when it ends)."""
        old = self.get(event_id)
        if "id" in changes:
            raise KDError(f"event {event_id}: id cannot be changed")
        try:
            new = dataclasses.replace(old, **changes)
        except TypeError as e:
            raise KDError(f"event {event_id} ({old.name!r}): {e}") from None
        check_event(new)
        self._events[event_id] = new
        self._dirty.add(event_id)
        return new

    def query(
        self,
        t_from_ns: int | None,
        t_to_ns: int | None,
        class_name: str | None,
        pool: Iterable[int] | None = None,
    ) -> list[EventFrame]:
        """Events overlapping [t_from_ns, t_to_ns] (None: unbounded) of ``class_name``, among
        the ids ``pool`` (None: all); in start-time order."""
        events = (self._events[i] for i in (self._events if pool is None else pool))
        return overlapping(events, t_from_ns, t_to_ns, class_name)

    def frames(self) -> tuple[EventFrame, ...]:
        """Every event frame in RAM. The frames are frozen (a change replaces one), so the
        tuple stays as it is now while the table goes on: a reader in another thread may keep
        it (wm.serve's per-cycle copy). O(events): references, not copies."""
        return tuple(self._events.values())

    def forget(self, t_now_ns: int, keep: set[int], horizon_ns: Callable[[int], int]) -> list[int]:
        """Forget the short-term events that ended (ongoing ones: end now) longer ago than
        ``horizon_ns(level)`` before ``t_now_ns`` and are not in ``keep`` (attention); returns
        their ids (their pointers are the relation graph's to drop)."""
        gone = []
        for e in list(self._events.values()):
            if e.id in self._ltm or e.id in keep:
                continue
            end = e.t_end_ns if e.t_end_ns is not None else t_now_ns
            if end < t_now_ns - horizon_ns(max(1, min(5, e.level))):
                del self._events[e.id]
                self._dirty.discard(e.id)
                gone.append(e.id)
        return gone

    def in_ltm(self, event_id: int) -> bool:
        return event_id in self._ltm

    def promote(self, min_confidence: float) -> set[int]:
        """Move noteworthy events and those of at least ``min_confidence`` into long-term
        memory (the next flush writes them); returns their ids."""
        new = {
            i
            for i, e in self._events.items()
            if i not in self._ltm and (e.noteworthy or e.confidence >= min_confidence)
        }
        self._ltm |= new
        self._dirty |= new
        return new

    def collect(self) -> list[EventFrame]:
        """The changed long-term events the next flush writes, in id order."""
        return [self._events[i] for i in sorted(self._dirty & self._ltm)]

    def written(self) -> None:
        self._dirty.clear()

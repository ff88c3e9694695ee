"""Events of sensory processing, written to the KD as event frames with the entities involved.

Reference 001, 4.4.8 (events and event frames: class, start and end, entities involved),
4.4.9 (event grouping: an event of level n groups level n-1 happenings). SP emits instants:
an entity appeared, was confirmed, denied, reclassified or vanished; a group formed or split.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from enum import StrEnum

import kd_store


class EventClass(StrEnum):
    APPEARED = "appeared"
    CONFIRMED = "confirmed"
    DENIED = "denied"
    RECLASSIFIED = "reclassified"
    VANISHED = "vanished"
    GROUP_FORMED = "group_formed"
    GROUP_SPLIT = "group_split"


def emit(
    kd: kd_store.KnowledgeDatabase,
    cls: EventClass,
    t_ns: int,
    entity_ids: Iterable[int],
    level: int,
    confidence: float = 1.0,
    attributes: Mapping[str, float] | None = None,
) -> int:
    """Add one instantaneous event frame (start = end = ``t_ns``) involving ``entity_ids``;
    returns its id."""
    ids = [int(i) for i in entity_ids]
    name = f"{cls.value}:{','.join(map(str, ids[:4]))}{'...' if len(ids) > 4 else ''}"
    ev = kd.add_event(
        name,
        cls.value,
        int(t_ns),
        t_end_ns=int(t_ns),
        level=int(level),
        confidence=float(min(max(confidence, 0.0), 1.0)),
        attributes=dict(attributes or {}),
    )
    for i in ids:
        kd.relate(ev.id, "involves", i, t_ns=int(t_ns))
    return ev.id

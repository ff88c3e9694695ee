"""The classes of the events sensory processing observes.

Reference 001, 4.4.8 (events and event frames: class, start and end, entities involved),
4.4.9 (event grouping: an event of level n groups level n-1 happenings). SP observes instants:
an entity appeared, was confirmed, denied, reclassified or vanished; a group formed or split.
Each is an :class:`sp.observations.EventObserved`; the world model writes its event frame
(:func:`wm.entities.write_event`).
"""

from __future__ import annotations

from enum import StrEnum


class EventClass(StrEnum):
    APPEARED = "appeared"
    CONFIRMED = "confirmed"
    DENIED = "denied"
    RECLASSIFIED = "reclassified"
    VANISHED = "vanished"
    GROUP_FORMED = "group_formed"
    GROUP_SPLIT = "group_split"

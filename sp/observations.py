"""What SP observed in one sweep, for the world model to write into the KD.

Reference 001, 4.2 (the world model keeps the KD current: ``KD(t) = KD(t-1) +
Observation(t)``), 4.5 (SP's observations: entities hypothesized, confirmed, denied, their
attributes, states, classes and relations), 4.4.8 (events). SP writes nothing into the KD; each
level records, in the order it observed them, the observations below, and
:class:`wm.entities.EntityUpdater` turns them into entity frames, states, relations and event
frames (docs/architecture.md, the node cycle).

The order matters and is kept: a later observation may refer to a frame an earlier one made,
and a few of them depend on what the KD holds when they are written (``PartsGone``,
``StateObserved.rule``, ``FrameChange.if_status``, ``Unrelated.if_present``): the world model
writes them one after the other, so the KD it consults is the one SP's earlier observations
of the sweep made. Frame ids come from SP's id source (the world model gives the KD's
``new_id``) when SP observes a new entity or an event, so SP's images, tracks and tables and the
KD's frames share the id.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from enum import StrEnum
from typing import TypeAlias

import numpy as np

from kd_store import Attribute, Level, StateBatch, Status
from sp.events import EventClass


@dataclass(frozen=True)
class NewEntity:
    """A new entity frame with id ``entity_id`` (from SP's id source, the KD's): ``name``,
    SP ``level``, the entity ``images`` it appears in, its first ``status`` and
    ``confidence`` (0..1), and generic class pointers (general to specific)."""

    entity_id: int
    name: str
    level: Level
    images: tuple[str, ...]
    status: Status = Status.HYPOTHESIZED
    confidence: float = 0.0
    generic_classes: tuple[str, ...] = ()


@dataclass(frozen=True)
class FrameChange:
    """New values of some fields of entity ``entity_id``'s frame (None: unchanged;
    ``specific_class`` applies only with ``sets_specific``, where None clears it). With
    ``if_status``, written only when the KD holds the frame in that status (a level-2 list
    the KD's short-term memory may have let go of, or another step already settled)."""

    entity_id: int
    status: Status | None = None
    confidence: float | None = None
    attributes: Mapping[str, Attribute] | None = None
    generic_classes: tuple[str, ...] | None = None
    specific_class: str | None = None
    sets_specific: bool = False
    if_status: Status | None = None


@dataclass(frozen=True)
class PartsGone:
    """Lists (or contact boundaries) whose owner went: each is gone, unless the KD no longer
    holds it or holds it denied (a denied list stays denied)."""

    entity_ids: tuple[int, ...]


class StateRule(StrEnum):
    """How a state is written against the entity's latest one in the KD."""

    IF_NEWER = "if_newer"  # only when later than the latest (one state per sweep time)
    AFTER_LAST = "after_last"  # stamped at least 1 ns after the latest


@dataclass(frozen=True)
class StateObserved:
    """One state of entity ``entity_id`` at ``t_ns``, world frame: position (3,) m, velocity
    (3,) m/s; written by ``rule``."""

    entity_id: int
    t_ns: int
    position_xyz: np.ndarray
    velocity_xyz: np.ndarray
    rule: StateRule


@dataclass(frozen=True)
class StatesObserved:
    """States of several entities in one batch (level 4's filtered tracks)."""

    batch: StateBatch


@dataclass(frozen=True)
class Related:
    """``src --kind--> dst`` holds from ``t_ns`` on (the KD adds the paired kind)."""

    src: int
    kind: str
    dst: int
    t_ns: int


@dataclass(frozen=True)
class Unrelated:
    """``src --kind--> dst`` ends at ``t_ns``; with ``if_present``, only when the KD still
    holds ``src``."""

    src: int
    kind: str
    dst: int
    t_ns: int
    if_present: bool = False


@dataclass(frozen=True)
class EventObserved:
    """An instantaneous event (start = end = ``t_ns``) of class ``event_class`` at SP
    ``level``, with id ``event_id`` (from SP's id source, the KD's), involving
    ``entity_ids``; ``confidence`` 0..1 (clipped when written)."""

    event_id: int
    event_class: EventClass
    t_ns: int
    entity_ids: tuple[int, ...]
    level: int
    confidence: float = 1.0


@dataclass(frozen=True)
class ClassFounded:
    """Confirmed entity ``entity_id`` matches no class well: it founds a specific class
    (reference 001, 4.4.3)."""

    entity_id: int


@dataclass(frozen=True)
class AppearanceObserved:
    """Camera grey (0..1, mean of the object's returns in the image), coverage (0..1
    share of its returns inside the image) and excess green (-1..2, NaN in a grey image;
    :mod:`sp.appearance`) of object ``entity_id`` this cycle."""

    entity_id: int
    camera_intensity: float
    camera_coverage: float
    camera_excess_green: float


Observation: TypeAlias = (
    NewEntity
    | FrameChange
    | PartsGone
    | StateObserved
    | StatesObserved
    | Related
    | Unrelated
    | EventObserved
    | ClassFounded
    | AppearanceObserved
)

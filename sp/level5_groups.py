"""SP level 5: groups of objects (convoys, crowds, rows of trees).

Reference 001, 4.5.6 (level 5: groups of objects), 4.5.1 (the five SP functions), 4.5.3
(hypothesize and test), 4.5.4 (recursive estimation). Per sweep:

- windowing: none;
- grouping: :func:`group_labels` over the confirmed objects, :func:`match_groups` across
  sweeps (:meth:`GroupLevel.group`);
- computation: count, length, speed, density (:meth:`GroupLevel.compute`);
- filtering: recursive confidence confirms ("group_formed"); an ended group is gone if
  confirmed, else denied; "group_split" (:meth:`GroupLevel.filter`, :meth:`GroupLevel.step`);
- classification: against the level-5 prototypes (in :meth:`GroupLevel.compute`).

The groups' frames, states, relations and events are observations (:mod:`sp.observations`).
The status and confidence of each current group are kept here as observed, which is what its
KD frame holds once the world model has written them (:meth:`GroupLevel.not_written` undoes
what it could not write).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kd_store import Attribute, Level, Status
from sp.classify import Classifier
from sp.context import IMAGE_NAMES, SPContext, unit
from sp.events import EventClass
from sp.groups import group_labels, match_groups
from sp.level4_objects import ObjectLevel
from sp.observations import (
    FrameChange,
    NewEntity,
    Observation,
    Related,
    StateObserved,
    StateRule,
    Unrelated,
)
from sp.tracking import Tracks, TrackStatus, evident_speed

# classes of objects that move by themselves: only they link as moving members of a group
MOBILE_CLASSES = frozenset({"vehicle", "person"})


@dataclass
class GroupsObserved:
    """Level 5 of one sweep.

    image:   (H, W) int64 group id per pixel (the pixels of its member objects), -1 none.
    events:  ids of the events observed (group_formed, group_split, vanished).
    """

    image: np.ndarray
    events: list[int]


class GroupLevel:
    """Level-5 group entities: ``groups`` maps each current group's id to its member object
    ids, ``frames`` to its status and confidence (0..1) as its frame holds them;
    ``_group_hits`` counts the sweeps each group has been seen."""

    def __init__(self, ctx: SPContext) -> None:
        self.ctx = ctx
        self.groups: dict[int, frozenset[int]] = {}
        self.frames: dict[int, tuple[Status, float]] = {}
        # this sweep's groups whose status or confidence changed: the values before
        self._before: dict[int, tuple[Status, float]] = {}
        self._group_hits: dict[int, int] = {}  # cycles each group has been seen

    def step(self, t_ns: int, image4: np.ndarray, objects: ObjectLevel) -> GroupsObserved:
        """Level 5: groups of the confirmed objects of ``objects`` (:func:`group_labels`);
        ``image4`` (H, W) int64 is the level-4 entity image. Only objects whose motion the
        filter is sure of (:func:`evident_speed`) and whose class moves (vehicle, person)
        link as moving, so static clutter with noisy velocities makes no convoy or crowd. A
        group starts hypothesized and is confirmed by its own recursive confidence as it
        persists (:meth:`filter`), like any other entity."""
        ctx = self.ctx
        self._before = {}
        tr = objects.tracker.tracks
        current = self.group(objects)
        carried, _, ended = match_groups(self.groups, current)
        events: list[int] = []
        groups: dict[int, frozenset[int]] = {}
        for i, members in enumerate(current):
            if i in carried:
                gid = carried[i]
            else:
                gid = ctx.new_entity(
                    f"group@{t_ns}",
                    Level.GROUP,
                    images=(IMAGE_NAMES[5],),
                    status=Status.HYPOTHESIZED,
                    confidence=ctx.config.tracker.confidence0,
                )
            self.filter(gid, t_ns, members, events)
            old = self.groups.get(gid, frozenset())
            for m in members - old:
                ctx.record(Related(m, "belongs_to", gid, t_ns))
            for m in old - members:
                ctx.record(Unrelated(m, "belongs_to", gid, t_ns, if_present=True))
            groups[gid] = members
            self.compute(gid, members, t_ns, tr)
        # a previous group whose members now lie in two or more groups has split
        for gid, old in self.groups.items():
            into = [g for g, m in groups.items() if m & old]
            if len(into) >= 2:
                events.append(ctx.event(EventClass.GROUP_SPLIT, t_ns, [gid, *into], 5))
        for gid in ended:
            for m in self.groups[gid]:
                ctx.record(Unrelated(m, "belongs_to", gid, t_ns, if_present=True))
            was_confirmed = self._frame(gid)[0] == Status.CONFIRMED
            del self.frames[gid]
            status = Status.GONE if was_confirmed else Status.DENIED
            ctx.record(FrameChange(gid, status=status))
            if was_confirmed:
                events.append(ctx.event(EventClass.VANISHED, t_ns, [gid], 5))
        self.groups = groups
        image5 = np.full(image4.shape, -1, dtype=np.int64)
        for gid, members in groups.items():
            image5[np.isin(image4, np.fromiter(members, np.int64))] = gid
        return GroupsObserved(image5, events)

    def group(self, objects: ObjectLevel) -> list[frozenset[int]]:
        """The member ids of each group of confirmed objects this sweep."""
        tr = objects.tracker.tracks
        tc = self.ctx.config.tracker
        conf = np.flatnonzero(tr.status == TrackStatus.CONFIRMED)
        ids = tr.id[conf]
        cls = [objects.track_class.get(int(i), (None, 0))[0] for i in ids]
        is_tree = np.array([c == "tree" for c in cls], dtype=bool)
        mobile = np.array([c in MOBILE_CLASSES for c in cls], dtype=bool)
        sure = tr.moving(tc)[conf] & (evident_speed(tr.x[conf], tr.P[conf], tc.evident_sigmas) > 0)
        v = np.where((mobile & sure)[:, None], tr.x[conf, 3:5], 0.0)
        lab = group_labels(tr.x[conf, :2], v, is_tree, self.ctx.config.groups)
        return [
            frozenset(int(i) for i in ids[lab == g]) for g in range(int(lab.max(initial=-1)) + 1)
        ]

    def filter(self, gid: int, t_ns: int, members: frozenset[int], events: list[int]) -> None:
        """Recursive confidence of group ``gid`` seen again this cycle: it rises by the
        tracker's gain ``alpha`` towards 1 each cycle the group persists; the group is
        confirmed (and "group_formed" appended to ``events``) once it is above the tracker's
        ``confirm`` after ``min_hits`` cycles, as an object track is. A group of earlier
        sweeps has the status and confidence of its frame (``frames``); a new one has those
        it was observed with."""
        ctx = self.ctx
        tc = ctx.config.tracker
        new = ctx.created(gid)
        was = (new.status, new.confidence) if new is not None else self._frame(gid)
        c = was[1] + tc.alpha * (1.0 - was[1]) if gid in self.groups else was[1]
        hits = self._group_hits.get(gid, 0) + 1
        self._group_hits[gid] = hits
        status = None
        if was[0] == Status.HYPOTHESIZED and c >= tc.confirm and hits >= tc.min_hits:
            status = Status.CONFIRMED
            events.append(ctx.event(EventClass.GROUP_FORMED, t_ns, [gid, *members], 5))
        ctx.record(FrameChange(gid, status=status, confidence=unit(c)))
        self._before[gid] = was
        self.frames[gid] = (was[0] if status is None else status, unit(c))

    def _frame(self, gid: int) -> tuple[Status, float]:
        """Status and confidence of the frame of group ``gid`` of an earlier sweep; a
        ValueError (the sweep fails) when its frame was never written."""
        f = self.frames.get(gid)
        if f is None:
            raise ValueError(f"group {gid}: the KD holds no frame of it (never written)")
        return f

    def not_written(self, observations: list[Observation]) -> None:
        """The world model could not write ``observations`` (the tail of a sweep's, after a
        write the KD refused): the groups' status and confidence go back to what their
        frames hold, and a group whose making was not written has no frame."""
        for op in observations:
            # :meth:`filter`'s change (the only one with a confidence) was not written
            if isinstance(op, FrameChange) and op.confidence is not None:
                if op.entity_id in self._before and op.entity_id in self.frames:
                    self.frames[op.entity_id] = self._before[op.entity_id]
        for op in observations:
            if isinstance(op, NewEntity):
                self.frames.pop(op.entity_id, None)

    def compute(self, gid: int, members: frozenset[int], t_ns: int, tracks: Tracks) -> None:
        """Group ``gid``'s attributes from its members' tracks (count, length along its
        longest horizontal extent in m, mean speed m/s, density per m2), its class, and its
        state (world frame: the members' mean position and velocity)."""
        ctx = self.ctx
        k = np.isin(tracks.id, np.fromiter(members, np.int64))
        p, v = tracks.x[k, :3], tracks.x[k, 3:]
        extent = float(np.ptp(p[:, :2], axis=0).max()) if p.shape[0] > 1 else 0.0
        spread = max(extent, 1.0)
        speed = float(np.hypot(*v[:, :2].mean(axis=0)))
        attrs = {
            "count": Attribute(observed=float(k.sum())),
            "length_m": Attribute(observed=extent),
            "speed_mps": Attribute(observed=speed),
            "density_per_m2": Attribute(observed=float(k.sum()) / (spread * spread)),
        }
        m = Classifier(ctx.classes, Level.GROUP).classify({n: a.observed for n, a in attrs.items()})
        ctx.record(FrameChange(gid, attributes=attrs, generic_classes=m.generic))
        ctx.set_class(gid, m.name)
        ctx.record(StateObserved(gid, t_ns, p.mean(axis=0), v.mean(0), StateRule.AFTER_LAST))

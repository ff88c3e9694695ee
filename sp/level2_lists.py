"""SP level 2: lists (range edges, brightness edges, vertices, surface patches).

Reference 001, 4.5.6 (level 2: lists of pixels, edges, vertices, surface patches), 4.5.1 (the
five SP functions), 4.5.3 (hypothesize and test), 4.5.4 (recursive estimation). Per sweep:

- windowing: none;
- grouping: one list per (owner, kind) (:meth:`ListLevel.group`, :func:`list_slots_and_sums`);
- computation: the lists' sums and attributes (:func:`list_attributes`);
- filtering: recursive confidence confirms or denies (:meth:`ListLevel.filter`);
- classification: against the level-2 prototypes (:meth:`ListLevel.classify`).

The lists' frames, relations and statuses are observations (:mod:`sp.observations`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from kd_store import Attribute, Level, Status
from sp.classify import Classifier
from sp.context import IMAGE_NAMES, SPContext, unit
from sp.lists import (
    KIND_CLASS,
    ListAttributes,
    ListKind,
    brightness_edges,
    fill_slots,
    list_attributes,
    list_slots_and_sums,
    list_sums,
    mean_intensity,
)
from sp.observations import FrameChange, PartsGone, Related
from sp.segments import range_edges


@dataclass
class ListsObserved:
    """Level 2 of one sweep, on the egosphere grid (H, W).

    image:   (H, W) int64 list entity id per pixel, -1 none (the contact boundaries and
             creases of level 3 are added by the caller).
    """

    image: np.ndarray


@dataclass
class _Grouped:
    """The pixels of one sweep sorted into lists (:func:`list_slots_and_sums`): ``slots``
    each pixel's slot, ``image`` (H, W) int64 list id per pixel, ``branches`` the vertices'
    branch counts, ``sums`` the lists' sums, ``first_new`` the first slot made this sweep,
    ``mean_intensity`` the sweep's mean intensity the brightness edges were taken against."""

    slots: np.ndarray
    image: np.ndarray
    branches: np.ndarray
    sums: np.ndarray
    first_new: int
    mean_intensity: float


class ListLevel:
    """Level-2 list entities and their tables, one slot per list ever made.

    Per slot: ``ids`` the list's frame id, ``conf`` its recursive confidence, ``hits`` the
    sweeps it was seen, ``open`` whether still hypothesized, ``key`` its owner * 4 + kind,
    ``dead`` denied (its key makes a new list if seen again), ``unheld`` the KD holds no frame
    of it (the world model said so: :meth:`frames_let_go`). ``lut`` maps owner * 4 + kind to
    the slot; ``lists_of`` maps an owner id to its list ids.
    """

    def __init__(self, ctx: SPContext) -> None:
        self.ctx = ctx
        self.lut = np.full(1024, -1, dtype=np.int64)  # owner * 4 + kind -> list slot
        self.ids = np.zeros(0, dtype=np.int64)  # list slot -> list frame id
        self.lists_of: dict[int, list[int]] = {}  # owner id -> its list ids
        # per list slot: recursive confidence, sweeps seen, and whether still hypothesized
        self.conf = np.zeros(0)
        self.hits = np.zeros(0, dtype=np.int64)
        self.open = np.zeros(0, dtype=bool)
        self.key = np.zeros(0, dtype=np.int64)  # slot -> owner * 4 + kind
        self.dead = np.zeros(0, dtype=bool)  # denied: its key makes a new list if seen
        self.unheld = np.zeros(0, dtype=bool)  # the KD holds no frame of it
        self.classifier = Classifier(ctx.classes, Level.LIST, ctx.config.classify)

    def step(
        self,
        t_ns: int,
        owner: np.ndarray,
        range_m: np.ndarray,
        valid: np.ndarray,
        intensity: np.ndarray,
        patch: np.ndarray,
    ) -> ListsObserved:
        """Level 2: list entities on the pixels of ``owner`` ((H, W) int64 id of the confirmed
        object, else the level-3 surface, each pixel is on; -1 none). Range edges, brightness
        edges (:func:`brightness_edges`, off the range edges), vertices (edge ends and
        junctions, :func:`edge_branches`) and the surface patches of the free surfaces
        (``patch``, (H, W) bool, level 3's free-surface pixels). ``range_m`` (H, W) is the
        range in m, inf where empty; ``intensity`` (H, W) the returns' intensity.

        One list entity per (owner, kind), made on first sight and kept while its owner
        lives: "the range edges of object 12" rather than one frame per edge piece per sweep.
        Edge pieces split and join from sweep to sweep as the view changes, so frames of
        single pieces would be born and die every cycle with nothing to track; per (owner,
        kind) the frames are bounded by four per owner, persist as long as their owner, and
        their attributes (integrated over all the pixels of that kind on the owner) are
        stable enough to filter and classify. The individual pieces stay visible in the
        level-2 image."""
        g = self.group(t_ns, owner, range_m, valid, intensity, patch)
        if g is None:
            return ListsObserved(np.full(owner.shape, -1, dtype=np.int64))
        a = list_attributes(g.sums, 2 * math.pi / owner.shape[1], g.mean_intensity)
        self.filter(a.ids)
        self.classify(a, g.first_new)
        return ListsObserved(g.image)

    # ------------------------------------------------------------------ grouping

    def group(
        self,
        t_ns: int,
        owner: np.ndarray,
        range_m: np.ndarray,
        valid: np.ndarray,
        intensity: np.ndarray,
        patch: np.ndarray,
    ) -> _Grouped | None:
        """Each pixel's list, its branches and the lists' sums, in one compiled pass; a new
        (owner, kind) gets a hypothesized list frame (belonging to its owner). None when no
        list exists at all."""
        cfg = self.ctx.config
        r_edge = range_edges(range_m, valid, cfg.segments)
        inten_mean = mean_intensity(intensity, valid)
        b_edge = brightness_edges(intensity, valid, cfg.list_config, inten_mean) & ~r_edge
        patch = patch if patch.shape == owner.shape else np.zeros_like(valid)
        slots, out, branches, missing, sums = list_slots_and_sums(
            owner, r_edge, b_edge, patch, self.lut, self.ids, range_m, intensity
        )
        first_new = self.ids.size
        if missing.size:
            self._new_lists(t_ns, missing)
            fill_slots(slots, out, self.lut, self.ids)
        if self.ids.size == 0:
            return None
        if missing.size:  # new lists: sum again with their pixels
            sums = list_sums(slots, range_m, intensity, r_edge | b_edge, branches, self.ids.size)
        return _Grouped(slots, out, branches, sums, first_new, inten_mean)

    def _new_lists(self, t_ns: int, missing: np.ndarray) -> None:
        """Hypothesized list frames for the keys (owner * 4 + kind) ``missing`` (m,) int64."""
        ctx = self.ctx
        tc = ctx.config.tracker
        if int(missing.max()) >= self.lut.size:
            grown = np.full(max(int(missing.max()) + 1, 2 * self.lut.size), -1, np.int64)
            grown[: self.lut.size] = self.lut
            self.lut = grown
        first_new = self.ids.size
        new = []
        for k in missing:
            oid, kd_kind = divmod(int(k), len(ListKind))
            lid = ctx.new_entity(
                f"{KIND_CLASS[ListKind(kd_kind)]} of {oid}",
                Level.LIST,
                images=(IMAGE_NAMES[2],),
                status=Status.HYPOTHESIZED,
                confidence=tc.confidence0,
            )
            ctx.record(Related(lid, "belongs_to", oid, t_ns))
            self.lut[k] = first_new + len(new)
            self.lists_of.setdefault(oid, []).append(lid)
            new.append(lid)
        self.ids = np.r_[self.ids, np.array(new, dtype=np.int64)]
        self.conf = np.r_[self.conf, np.full(len(new), tc.confidence0)]
        self.hits = np.r_[self.hits, np.zeros(len(new), dtype=np.int64)]
        self.open = np.r_[self.open, np.ones(len(new), dtype=bool)]
        self.key = np.r_[self.key, missing.astype(np.int64)]
        self.dead = np.r_[self.dead, np.zeros(len(new), dtype=bool)]
        self.unheld = np.r_[self.unheld, np.zeros(len(new), dtype=bool)]

    # ------------------------------------------------------------------ filtering

    def filter(self, seen_slots: np.ndarray) -> None:
        """Recursive confidence of every list (4.5.3, as for objects and groups): each sweep
        a list has pixels it rises by the tracker's gain ``alpha`` towards 1, each sweep it
        has none it decays by the same gain. A hypothesized list is confirmed above the
        tracker's ``confirm`` after ``min_hits`` sweeps and denied below its ``deny`` (a
        few pixels of one sweep that never came back); confirmed lists go with their owner.
        ``seen_slots`` (n,) int64: the slots with pixels this sweep."""
        tc = self.ctx.config.tracker
        seen = np.zeros(self.ids.size, dtype=bool)
        seen[seen_slots] = True
        c = self.conf
        c[seen] += tc.alpha * (1.0 - c[seen])
        c[~seen] *= 1.0 - tc.alpha
        self.hits[seen] += 1
        confirm = self.open & (c >= tc.confirm) & (self.hits >= tc.min_hits)
        deny = self.open & (c < tc.deny) & (self.hits > 0) & ~seen
        for k, status in ((confirm, Status.CONFIRMED), (deny, Status.DENIED)):
            for slot in np.flatnonzero(k):
                lid = int(self.ids[slot])
                change = FrameChange(
                    lid, status=status, confidence=unit(c[slot]), if_status=Status.HYPOTHESIZED
                )
                self.ctx.record(change)
        self.open &= ~(confirm | deny)
        self.release(np.flatnonzero(deny))

    def release(self, slots: np.ndarray) -> None:
        """Denied (or forgotten) lists: their (owner, kind) starts a new hypothesis if its
        pixels come back, and they are no longer their owner's."""
        for slot in slots:
            key = int(self.key[slot])
            if 0 <= key < self.lut.size and self.lut[key] == slot:
                self.lut[key] = -1
            owned = self.lists_of.get(key // len(ListKind), [])
            if int(self.ids[slot]) in owned:
                owned.remove(int(self.ids[slot]))
        self.dead[slots] = True
        self.open[slots] = False

    def frames_let_go(self, frame_ids: np.ndarray) -> None:
        """The KD holds no frame of the lists among ``frame_ids`` (int64): its short-term
        memory forgot them, or the world model could not write their making. They are
        released when next seen (:meth:`classify`)."""
        if self.ids.size and len(frame_ids):
            self.unheld |= np.isin(self.ids, frame_ids)

    def owner_gone(self, owner_id: int, also: Iterable[int] = ()) -> None:
        """Owner ``owner_id`` went: its lists (and the lists ``also``, e.g. its contact
        boundary) go too."""
        parts = list(self.lists_of.pop(owner_id, ()))
        parts.extend(also)
        self.parts_gone(parts)

    def parts_gone(self, parts: Iterable[int]) -> None:
        """Lists (or contacts) whose owner went go too; a denied list the KD has already
        dropped stays dropped."""
        parts = tuple(int(i) for i in parts)
        if parts:
            self.ctx.record(PartsGone(parts))

    # ------------------------------------------------------------------ classification

    def classify(self, a: ListAttributes, first_new: int) -> None:
        """Classes and frames of the lists seen (``a``) that are due this sweep or new (slot
        at least ``first_new``). A list the KD no longer holds (its short-term memory let a
        hypothesis go) is treated as denied."""
        ctx = self.ctx
        gone = self.unheld[a.ids]
        if gone.any():
            self.release(a.ids[gone])
        ids = self.ids[a.ids]
        due = (ctx.due(ids) | (a.ids >= first_new)) & ~self.dead[a.ids]
        rows = [r for r, d in zip(a.as_dicts(), due, strict=True) if d]
        matches = self.classifier.classify_many(rows)
        ids, conf = ids[due], self.conf[a.ids[due]]
        ctx.set_classes(ids, [m.name for m in matches])
        for i, c, r, m in zip(ids, conf, rows, matches, strict=True):
            ctx.record(
                FrameChange(
                    int(i),
                    attributes={n: Attribute(observed=v) for n, v in r.items()},
                    generic_classes=m.generic,
                    confidence=unit(c),
                )
            )

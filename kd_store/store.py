"""The knowledge database: frames, pointers, classes and the three memory tiers in one place.

Reference 001 (the 4D/RCS reference model), section 4.4, and docs/architecture.md, section 5:
entity frames 4.4.2, classes 4.4.3, events 4.4.8-4.4.9, memory tiers 4.4.11. In RAM the KD is
immediate experience (this cycle) and short-term memory (recent histories, attention);
long-term memory is a DuckDB file that receives, at each :meth:`KnowledgeDatabase.flush`, the
frames the promotion rule admits, written as Arrow batches in one transaction.

:class:`KnowledgeDatabase` is a facade over one part per noun, each owning its state:
entity frames and their state columns (:mod:`kd_store.entities`), event frames
(:mod:`kd_store.events`), pointers between frames (:mod:`kd_store.relations`), map tiles
(:mod:`kd_store.tiles`), read-only SQL (:mod:`kd_store.query`) and the DuckDB file
(:mod:`kd_store.persist`, the only package that speaks to DuckDB). The facade hands out ids
(entities and events share one id space), dispatches what applies to either kind of frame,
and orders promotion, forgetting and flushes across the parts.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import numpy as np
import pyarrow as pa

from kd_store import persist
from kd_store.classes import ClassLibrary, ClassPrototype
from kd_store.config import KDConfig, PromotionRule
from kd_store.entities import EntityColumns, EntityTable
from kd_store.errors import KDError
from kd_store.events import EventTable
from kd_store.frames import EntityFrame, EventFrame, Level, State, Status
from kd_store.memory import ImmediateExperience, ShortTermMemory
from kd_store.query import SQLReader, kd_settings
from kd_store.relations import FramePointers, Relation, RelationGraph, RelationKind
from kd_store.spatial import Region
from kd_store.states import StateBatch
from kd_store.tiles import MapTile, TileKey, TileMemory, check_tile

__all__ = ["KnowledgeDatabase", "SQLReader", "open"]


class KnowledgeDatabase:
    """Entity and event frames with pointer graphs, a class library and three memory tiers.

    Open with :func:`open` (``":memory:"`` for a throwaway KD). Use as a context manager: a
    clean exit flushes and closes (a throwaway KD's is not flushed: closing discards it).
    Not safe for concurrent writers; readers in other threads use :meth:`reader` (their own
    DuckDB cursor, a consistent snapshot per query).
    """

    def __init__(
        self,
        con: persist.Connection,
        path: str,
        config: KDConfig,
        run_id: int | None = 0,
    ) -> None:
        self.path = path
        #: The run this KD reads and writes (``run_rows``); None: every row, in a read-only
        #: file older than runs (schema version 3), where all rows are run 0.
        self._run = run_id
        self.config = config
        self.promotion_rule: PromotionRule = config.promotion
        self._con = con
        self._lock = threading.RLock()
        self._read_only = False
        self.graph = RelationGraph()
        self.stm = ShortTermMemory({n: round(h * 1e9) for n, h in config.memory.horizons_s.items()})
        self.immediate = ImmediateExperience()
        self._entities = EntityTable(config, ClassLibrary.default(), self.stm, self.immediate)
        self._events = EventTable()
        self._pointers = FramePointers(self.graph, self._kind_of, self._now)
        self._next_id = 0
        # rows collected (stage, flush) that the file does not hold yet, oldest first, and the
        # map tiles among them (marked written once the file holds them)
        self._unflushed: list[persist.Rows] = []
        self._unflushed_tiles: list[MapTile] = []
        #: called with every :class:`~kd_store.persist.Rows` as it is collected (by
        #: :meth:`stage`, :meth:`flush` or a batch of map tiles), in the order the file gets
        #: them: what a replica of the file needs (wm.serve_sql); None: nobody listens
        self.on_rows: Callable[[persist.Rows], None] | None = None
        self._snapshot_targets: dict[str, Path] = {}  # publish_snapshot paths, checked
        self._snapshot_marked: set[Path] = set()  # ... and recorded in kd_meta
        self.tiles = TileMemory(
            lambda: persist.read_tile_keys(self._con, self._run),
            lambda key: persist.read_tile(self._con, key, self._run),
            config.tile_cache,
            self._write_tiles,
            config.tile_write_batch,
        )
        self._load(persist.read(con, run_id))

    @property
    def classes(self) -> ClassLibrary:
        """The class library (4.4.3) entity class pointers are checked against."""
        return self._entities.classes

    @classes.setter
    def classes(self, library: ClassLibrary) -> None:
        self._entities.classes = library

    @property
    def _cols(self) -> EntityColumns:
        """The entities' state columns (for benchmarks that read them in place)."""
        return self._entities.cols

    @property
    def run_id(self) -> int:
        """The run this KD reads and writes: its rows carry this ``run_id`` in every view
        (``runs`` lists them; :func:`open` picks the newest unless told)."""
        return 0 if self._run is None else self._run

    def run_filter(self, alias: str = "") -> str:
        """SQL condition keeping the rows of this KD's run, for queries over the views
        (``alias``: the table's alias in the query); ``TRUE`` in a file older than runs."""
        if self._run is None:
            return "TRUE"
        return f"{alias}.run_id = {self._run}" if alias else f"run_id = {self._run}"

    # ================================================================ files

    def __enter__(self) -> KnowledgeDatabase:
        return self

    def __exit__(
        self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        if et is None and not self._read_only and str(self.path) != ":memory:":
            self.flush()
        self.close()

    def close(self) -> None:
        """Close the file without flushing (what was not flushed is short-term and is lost)."""
        with self._lock:
            self._con.close()

    def checkpoint(self) -> int:
        """Flush, then fold DuckDB's write-ahead log into the file. Returns rows flushed."""
        n = self.flush()
        if self._read_only:
            return n
        with self._lock:
            persist.checkpoint(self._con)
        return n

    def snapshot_target(self, path: str | Path) -> Path:
        """Where :meth:`publish_snapshot` would publish ``path`` (absolute), or a KDError
        when it refuses it (:func:`kd_store.persist.snapshot_target`: the KD itself, or an
        existing file that is no snapshot published there before). Checked once per path."""
        key = str(path)
        if key not in self._snapshot_targets:
            if self._read_only:
                raise KDError(f"snapshot {path}: KD file {self.path} is open read-only")
            self._snapshot_targets[key] = persist.snapshot_target(self.path, path)
        return self._snapshot_targets[key]

    def publish_snapshot(self, path: str | Path, tiles: bool = True) -> Path:
        """Publish a consistent read-only copy of the KD file at ``path``: flush (map tiles
        only if ``tiles``), fold the write-ahead log into the file (CHECKPOINT), copy it
        beside ``path`` and rename it there (:func:`kd_store.persist.copy_snapshot`), so other
        processes can open ``path`` read-only while this one keeps writing the KD. Returns
        the absolute path. KDError when the path is refused (:meth:`snapshot_target`) or the
        copy fails (nothing at ``path`` changed then)."""
        target = self.snapshot_target(path)
        with self._lock:  # no write lands between the checkpoint and the end of the copy
            self.flush(tiles=tiles)
            if target not in self._snapshot_marked:
                persist.mark_snapshot(self._con, target)
                self._snapshot_marked.add(target)
            persist.checkpoint(self._con)
            persist.copy_snapshot(Path(self.path), target)
        return target

    def copy_committed(self, path: str | Path) -> tuple[int, int]:
        """Copy what the KD file holds as of its last flush (the file and its write-ahead log,
        no flush, no CHECKPOINT, no fsync) to ``path`` and ``path.wal``, under the KD's lock
        so that no commit lands mid-copy; returns (file bytes, log bytes). A read-only open of
        the pair (``persist.connect``) sees the KD as of that flush. Cheaper for
        the writer than :meth:`publish_snapshot` (no checkpoint, nothing waits for the disk)
        but no durable snapshot: for readers on this host, each copy to a new ``path``
        (:func:`kd_store.persist.copy_with_wal`). KDError for a throwaway KD or a failed
        copy."""
        if str(self.path) == ":memory:" or self._read_only:
            raise KDError(f"KD copy {path}: only a KD file open for writing is copied this way")
        with self._lock:
            return persist.copy_with_wal(Path(self.path), Path(path))

    def _load(self, s: persist.Stored) -> None:
        """Recall long-term memory: frames, relations and classes (histories stay on disk)."""
        stored = {p.name: p for p in s.classes}
        defaults = {p.name for p in self.classes}
        while stored:  # parents before children
            ready = [p for p in stored.values() if p.is_a is None or p.is_a not in stored]
            if not ready:
                raise KDError(f"KD file {self.path}: stored classes {sorted(stored)} form a cycle")
            for p in ready:
                self.classes.add(p)
                del stored[p.name]
        self.classes.dirty = defaults - {p.name for p in s.classes}
        for f in s.entities:
            self._entities.put(f, ltm=True)
        self._events.load(s.events)
        self.graph.load(s.relations)
        self._next_id = max(s.next_id, self._next_id)

    # ================================================================ ids

    def new_id(self) -> int:
        """A fresh frame id (entities and events share one id space)."""
        i = self._next_id
        self._next_id += 1
        return i

    @property
    def next_id(self) -> int:
        """The id :meth:`new_id` will hand out next (kept across restarts)."""
        return self._next_id

    def __contains__(self, frame_id: object) -> bool:
        return frame_id in self._entities or frame_id in self._events

    def _kind_of(self, frame_id: int, where: str) -> str:
        if frame_id in self._entities:
            return "entity"
        if frame_id in self._events:
            return "event"
        raise KDError(f"{where}: frame {frame_id!r} is not in the KD")

    def _take_id(self, frame_id: int | None, where: str) -> int:
        if frame_id is None:
            return self.new_id()
        frame_id = int(frame_id)
        if frame_id in self:
            raise KDError(f"{where}: id {frame_id} is already taken")
        if frame_id < 0:
            raise KDError(f"{where}: id {frame_id} is negative")
        self._next_id = max(self._next_id, frame_id + 1)
        return frame_id

    def _now(self, t_ns: int | None) -> int:
        """``t_ns``, or when None this cycle's time (0 before the first cycle)."""
        if t_ns is not None:
            return int(t_ns)
        return self.immediate.t_ns if self.immediate.t_ns is not None else 0

    # ================================================================ entities

    def add_entity(self, name: str, level: Level | int, **fields: Any) -> EntityFrame:
        """Make an entity frame (fields as :class:`EntityFrame`; ``id`` optional) and add it.
        A ``state`` becomes the first entry of its short-term memory."""
        return self._entities.add(name, level, fields, self._take_id)

    def insert_entity(self, frame: EntityFrame) -> EntityFrame:
        """Add a complete frame with its own id (which must be free)."""
        return self._entities.insert(frame, self._take_id)

    def get(self, entity_id: int) -> EntityFrame:
        """The entity frame ``entity_id`` (its ``state`` is the latest)."""
        return self._entities.get(entity_id)

    def entities(self) -> Iterator[EntityFrame]:
        """Every entity frame in RAM, in slot order."""
        return self._entities.frames()

    def entity_ids(self) -> np.ndarray:
        """(N,) int64 ids of the entities in RAM, sorted."""
        return self._entities.ids()

    def update_entity(self, entity_id: int, **changes: Any) -> EntityFrame:
        """Change fields of an entity frame (not ``id``; states go through :meth:`observe`).
        A change the promotion rule admits (a confirmation) promotes at once: admission is
        one-way, and a track confirmed and fading before the next flush was still confirmed,
        so long-term memory holds it. A frame long-term memory holds already needs no
        promotion (the others wait for the next flush or :meth:`advance`, as they would)."""
        frame = self._entities.update(entity_id, changes)
        if "status" in changes and self._admits(frame) and not self._entities.in_ltm(entity_id):
            self._promote()
        return frame

    def _admits(self, frame: EntityFrame) -> bool:
        rule = self.promotion_rule
        return frame.status.value in rule.statuses and frame.confidence >= rule.min_confidence

    def observe(self, entity_id: int, state: State) -> EntityFrame:
        """Add one state to an entity's history; it becomes the current state. Expectations
        at or before it are dropped: the present has overtaken them (see :meth:`ingest`)."""
        return self._entities.observe(entity_id, state)

    def expect(self, entity_id: int, states: Iterable[State]) -> EntityFrame:
        """Replace an entity's short-term expectation queue (predicted states, time order)."""
        return self._entities.expect(entity_id, states)

    def mark_noteworthy(self, frame_id: int) -> None:
        """Flag an entity or event for long-term memory (4.4.11)."""
        if self._kind_of(frame_id, "mark_noteworthy") == "entity":
            self.update_entity(frame_id, noteworthy=True)
        else:
            self.update_event(frame_id, noteworthy=True)

    def found_specific_class(self, entity_id: int) -> ClassPrototype:
        """Found a specific class from a confirmed entity and point the entity at it."""
        return self._entities.found_specific_class(entity_id)

    def ingest(self, batch: StateBatch) -> int:
        """Add a batch of state updates (see :class:`StateBatch`); returns rows added.

        Refuses, keeping nothing of the batch: unknown ids, NaN/inf, bad covariances, and times
        that do not strictly increase per entity or are not after its current state.
        Expectations an entity holds at or before its new state are dropped (history now, not
        a contradiction: 4.4.11, short-term expectations are of the future); later ones stay."""
        return self._entities.ingest(batch)

    def _remove_entity(self, entity_id: int) -> None:
        """Forget an entity and every pointer touching it."""
        self._entities.remove(entity_id)
        self.graph.remove_node(entity_id)

    # ================================================================ events

    def add_event(self, name: str, class_name: str, t_start_ns: int, **fields: Any) -> EventFrame:
        """Make an event frame (fields as :class:`EventFrame`; ``id`` optional) and add it."""
        return self._events.add(name, class_name, t_start_ns, fields, self._take_id)

    def insert_event(self, event: EventFrame) -> EventFrame:
        """Add a complete event frame with its own id (which must be free)."""
        return self._events.insert(event, self._take_id)

    def get_event(self, event_id: int) -> EventFrame:
        return self._events.get(event_id)

    def update_event(self, event_id: int, **changes: Any) -> EventFrame:
        """Change fields of an event frame (e.g. ``t_end_ns`` when it ends)."""
        return self._events.update(event_id, changes)

    def events(
        self,
        t_from_ns: int | None = None,
        t_to_ns: int | None = None,
        class_name: str | None = None,
        participant: int | None = None,
    ) -> list[EventFrame]:
        """Events overlapping [t_from_ns, t_to_ns] (open ends: unbounded), of ``class_name``,
        involving entity ``participant``; in start-time order."""
        pool = None if participant is None else self._pointers.involving(participant)
        return self._events.query(t_from_ns, t_to_ns, class_name, pool)

    def event_frames(self) -> tuple[EventFrame, ...]:
        """Every event frame in RAM (short-term memory and what long-term memory recalled), in
        no particular order; frozen frames, so a reader in another thread may keep the tuple
        (:func:`kd_store.events.overlapping` queries it as :meth:`events` does). Call it from
        the writer's thread (between two of its changes)."""
        return self._events.frames()

    def events_at(self, t_ns: int) -> list[EventFrame]:
        """Events going on at ``t_ns``."""
        return self.events(t_ns, t_ns)

    # ================================================================ pointers

    def relate(self, src: int, kind: RelationKind | str, dst: int, t_ns: int | None = None) -> None:
        """Point ``src --kind--> dst`` from ``t_ns`` on (default: this cycle's time, else 0)."""
        self._pointers.relate(src, kind, dst, t_ns)

    def unrelate(
        self, src: int, kind: RelationKind | str, dst: int, t_ns: int | None = None
    ) -> bool:
        """End ``src --kind--> dst`` at ``t_ns`` (kept in history); False if it was not open."""
        return self._pointers.unrelate(src, kind, dst, t_ns)

    def restart_relations(self, t_end_ns: int, t_start_ns: int) -> int:
        """The log's clock went back to ``t_start_ns`` after ``t_end_ns``: every open part-of
        and spatial relation ends at ``t_end_ns`` and holds again from ``t_start_ns`` (the two
        clocks' intervals kept apart, :meth:`kd_store.relations.RelationGraph.restart`);
        returns how many, each direction counted."""
        return self.graph.restart(t_end_ns, t_start_ns)

    def pointers(
        self, frame_id: int, kind: RelationKind | str | None = None, t_ns: int | None = None
    ) -> list[int]:
        """Frames ``frame_id`` points to by ``kind`` at ``t_ns`` (None: now)."""
        return self._pointers.pointers(frame_id, kind, t_ns)

    def pointed_by(
        self, frame_id: int, kind: RelationKind | str | None = None, t_ns: int | None = None
    ) -> list[int]:
        """Frames pointing to ``frame_id`` by ``kind`` at ``t_ns``."""
        return self._pointers.pointed_by(frame_id, kind, t_ns)

    def relations(self, frame_id: int) -> list[Relation]:
        """Every relation from ``frame_id``, open and closed."""
        return self._pointers.relations(frame_id)

    def parent(self, frame_id: int, t_ns: int | None = None) -> int | None:
        return self._pointers.parent(frame_id, t_ns)

    def parts(self, frame_id: int, t_ns: int | None = None) -> list[int]:
        return self._pointers.parts(frame_id, t_ns)

    def ancestors(self, frame_id: int, t_ns: int | None = None) -> list[int]:
        """Parent, grandparent, ... nearest first."""
        return self._pointers.ancestors(frame_id, t_ns)

    def parts_tree(self, frame_id: int, t_ns: int | None = None) -> list[tuple[int, int]]:
        """(id, depth) of the frame and all its parts, depth first."""
        return self._pointers.parts_tree(frame_id, t_ns)

    def neighbourhood(
        self,
        frame_id: int,
        kinds: Iterable[RelationKind | str] | None = None,
        depth: int = 1,
        t_ns: int | None = None,
    ) -> dict[int, int]:
        """Frames within ``depth`` hops over ``kinds`` (either direction): id -> hops."""
        return self._pointers.neighbourhood(frame_id, kinds, depth, t_ns)

    def class_lineage(self, entity_id: int) -> list[str]:
        """The entity's most specific class and its is_a ancestors, most specific first."""
        return self._entities.class_lineage(entity_id)

    # ================================================================ memory tiers

    def begin_cycle(self, t_ns: int) -> None:
        """Start a new cycle of immediate experience at ``t_ns``."""
        self.immediate.begin(t_ns)

    def observed_this_cycle(self) -> np.ndarray:
        """Sorted ids of the frames observed or made since :meth:`begin_cycle`."""
        return self.immediate.ids()

    def set_attention(self, node: str, entity_ids: Iterable[int]) -> None:
        """Set the entities-of-attention list of a node level (``"primitive"``, ...)."""
        self.stm.set_attention(node, entity_ids, self._entities.__contains__)

    def attention(self, node: str) -> list[int]:
        return list(self.stm.attention[node])

    def history(self, entity_id: int) -> list[State]:
        """The entity's short-term memory queue: remembered past states, oldest first."""
        return self._entities.history(entity_id)

    def long_term_history(self, entity_id: int) -> list[State]:
        """The entity's states in long-term memory (after a flush), oldest first."""
        self.flush()
        with self._lock:
            return persist.read_states(self._con, entity_id)

    def as_of(self, t_ns: int, long_term: bool = False) -> dict[int, State]:
        """State of every entity at ``t_ns``: its latest remembered state at or before ``t_ns``.

        Short-term memory only by default (fast, no I/O); ``long_term=True`` also searches the
        long-term histories on disk (after a flush), for times older than the horizons."""
        if not long_term:
            return self._entities.as_of(t_ns)
        self.flush()
        with self._lock:
            stored = persist.read_states_as_of(self._con, t_ns)
        return self._entities.as_of(t_ns, stored)

    def advance(self, t_now_ns: int) -> list[int]:
        """Let short-term memory move on to ``t_now_ns``: trim histories to each level's
        horizon and forget frames older than it that long-term memory did not take and
        attention does not hold (4.4.11). Frames the promotion rule admits are moved to
        long-term memory first, so their histories are kept. Returns the ids forgotten."""
        self._promote()
        self.stm.trim(t_now_ns)
        keep = self.stm.attended()
        gone = [i for i in self._entities.stale(t_now_ns) if i not in keep]
        events = self._events.forget(t_now_ns, keep, self.config.memory.horizon_ns)
        for i in (*gone, *events):
            if i in self._entities:
                self._entities.remove(i)
            self.graph.remove_node(i)
        self.stm.drop(np.array([*gone, *events], dtype=np.int64))
        return sorted([*gone, *events])

    # ================================================================ long-term memory

    def flush(self, tiles: bool = True) -> int:
        """Promote what the rule admits and write every change of long-term frames since the
        last flush, in one transaction, with the pending map tiles unless ``tiles`` is False
        (they then wait for a later flush); the rows :meth:`stage` held go in the same
        transaction. Returns the number of state rows written."""
        if self._read_only:
            return 0
        with self._lock:
            self._take(tiles)
            return self._write_unflushed()

    def stage(self) -> persist.Rows | None:
        """Collect every change of long-term frames since the last :meth:`stage` or
        :meth:`flush` now (promotion first, no map tiles), as the rows a flush now would
        write, and hold them for the next flush of the file, which writes them with its own
        in one transaction (:func:`~kd_store.persist.merge_rows`): the file keeps its cadence
        while :attr:`on_rows` gets each call's changes, for a writer that keeps a replica of
        the file current (a live node serving SQL, once per cycle: wm.serve_sql). Returns
        the rows (None: nothing changed)."""
        if self._read_only:
            return None
        with self._lock:
            return self._take(tiles=False)

    @property
    def unflushed(self) -> list[persist.Rows]:
        """The rows collected (:meth:`stage`) that the file does not hold yet, oldest first:
        a copy of the file (:meth:`copy_committed`) with these written over it in order is the
        KD as of the last :meth:`stage`. Call it under the writer's lock."""
        return list(self._unflushed)

    def _take(self, tiles: bool) -> persist.Rows | None:
        """Promote, collect and convert what changed (map tiles only if ``tiles``) into rows
        held for the file, told to :attr:`on_rows`; the frames' change marks are cleared (the
        rows hold their values now), the tiles' once the file holds them."""
        self._promote()
        w = self._collect(tiles)
        if not w:
            return None
        rows = w.rows()
        self._entities.written()
        self._events.written()
        self.graph.dirty.clear()
        self.classes.dirty.clear()
        self._unflushed.append(rows)
        self._unflushed_tiles += w.tiles
        if self.on_rows is not None:
            self.on_rows(rows)
        return rows

    def _write_unflushed(self) -> int:
        """Write every row held for the file in one transaction, merged; returns the state
        rows written. On failure the rows stay held: the next flush retries them."""
        if not self._unflushed:
            return 0
        rows = persist.merge_rows(self._unflushed)
        persist.write_rows(self._con, rows)
        self._unflushed = []
        tiles, self._unflushed_tiles = self._unflushed_tiles, []
        self.tiles.written(tiles)
        return rows.state_rows

    def _promote(self) -> None:
        """Move the frames the promotion rule admits into long-term memory (in RAM; the next
        flush writes them): their short-term histories join the pending rows, and pointers
        touching them are marked for writing."""
        new_ids = self._entities.promote(self.promotion_rule)
        new_events = self._events.promote(self.promotion_rule.min_event_confidence)
        self._pointers.mark_touching((*new_ids.tolist(), *new_events))

    def _in_ltm(self, frame_id: int) -> bool:
        if frame_id in self._entities:
            return self._entities.in_ltm(frame_id)
        return self._events.in_ltm(frame_id)

    def _collect(self, tiles: bool = True) -> persist.Write:
        """Everything the next flush writes (promotion done); map tiles only if ``tiles``."""
        frames, entity_states, states = self._entities.collect()
        return persist.Write(
            entities=frames,
            entity_states=entity_states,
            states=states,
            events=self._events.collect(),
            relations=self._pointers.collect(self._in_ltm),
            classes=[self.classes.get(c) for c in self.classes.dirty if c in self.classes],
            tiles=list(self.tiles.pending.values()) if tiles else [],
            next_id=self._next_id,
            run_id=self.run_id,
        )

    def _write_tiles(self, tiles: list[MapTile]) -> bool:
        """Write ``tiles`` now, with the rows held for the file before them (one transaction);
        False in a read-only KD."""
        if self._read_only:
            return False
        with self._lock:
            rows = persist.Write(tiles=tiles, next_id=self._next_id, run_id=self.run_id).rows()
            self._unflushed.append(rows)
            if self.on_rows is not None:
                self.on_rows(rows)
            self._write_unflushed()
        return True

    # ================================================================ map tiles

    def put_tile(
        self,
        level: str,
        tx: int,
        ty: int,
        layers: Mapping[str, np.ndarray],
        t_ns: int | None = None,
    ) -> None:
        """Keep a map tile in long-term memory (4.4.11): ``layers`` name -> numeric array (any
        shape; copied), replacing the tile ``(level, tx, ty)`` whole. ``t_ns`` defaults to
        this cycle's time. Written at the next :meth:`flush`, or on its own once
        ``config.tile_write_batch`` tiles wait (one transaction either way)."""
        tile = check_tile(level, tx, ty, layers, self._now(t_ns))
        with self._lock:
            self.tiles.put(tile)

    def get_tile(self, level: str, tx: int, ty: int) -> dict[str, np.ndarray] | None:
        """The tile ``(level, tx, ty)`` as layer name -> array (copies), or None if the KD has
        none (from RAM if put since the last write or recently read, else from the file)."""
        with self._lock:
            return self.tiles.get((level, int(tx), int(ty)))

    def tile_keys(self, level: str | None = None) -> list[TileKey]:
        """Sorted ``(level, tx, ty)`` of every tile the KD holds (of ``level`` if given)."""
        with self._lock:
            return [k for k in self.tiles.keys() if level is None or k[0] == level]

    # ================================================================ queries

    def region(
        self,
        region: Region,
        classes: Iterable[str] | None = None,
        statuses: Iterable[Status | str] | None = None,
        levels: Iterable[int] | None = None,
        min_confidence: float = 0.0,
        poses: dict[str, np.ndarray] | None = None,
    ) -> np.ndarray:
        """Ids (sorted int64) of entities whose current position lies in the region and which
        pass the filters (a class includes its is_a descendants).

        Entities held in ``region.frame`` are always searched. ``poses`` adds entities held in
        other frames: ``{name: T_region_name}`` (4x4 float64, ``p_region = T @ p_name``)."""
        return self._entities.region(region, classes, statuses, levels, min_confidence, poses)

    def sql(self, query: str, flush: bool = True) -> pa.Table:
        """Run one read-only SELECT over the documented views (docs/kd.md); returns Arrow.
        Flushes first by default, so the views show long-term memory up to now. Nothing
        outside the KD can be reached (:func:`open`): reading a file, a URL or an extension
        raises KDError."""
        if flush:
            self.flush()
        with self._lock:
            return persist.read_only_query(persist.cursor(self._con), query)

    def current_columns(self) -> dict[str, np.ndarray]:
        """Copies of every live entity's current state and filter keys (N rows, slot order),
        for a reader in another thread that must not wait for the writer: ``id`` (N,) int64,
        ``t_ns`` (N,) int64 (the current state's time, int64 min without one), ``frame`` (N,)
        object (its frame name, None without a state), ``position`` and ``velocity`` (N, 3)
        m and m/s in that frame, ``status`` (N,) object (names), ``level`` (N,) int8,
        ``confidence`` (N,), ``class_name`` (N,) object (the most specific class, or None).
        Call it from the writer's thread (between two of its changes)."""
        return self._entities.current_columns()

    def reader(self) -> SQLReader:
        """A reader for another thread: its own cursor, a consistent snapshot per query."""
        with self._lock:
            return SQLReader(persist.cursor(self._con))

    def export_parquet(self, folder: str | Path) -> list[Path]:
        """Flush, then write long-term memory as one Parquet file per table in ``folder``."""
        self.flush()
        with self._lock:
            return persist.export_parquet(self._con, folder)

    def import_parquet(self, folder: str | Path) -> None:
        """Load a Parquet KD (from :meth:`export_parquet`) into this KD, which must be empty."""
        if len(self._entities) or len(self._events):
            raise KDError(
                f"import of {folder}: this KD already holds frames; import into a new one"
            )
        with self._lock:
            persist.import_parquet(self._con, folder)
            self._run = persist.latest_run(self._con)
            stored = persist.read(self._con, self._run)
            self.tiles.reset()
        self.classes = ClassLibrary.default()
        self._load(stored)


def open(
    path: str | Path = ":memory:",
    config: KDConfig | None = None,
    read_only: bool = False,
    settings: dict[str, object] | None = None,
    run: int | Literal["latest", "new"] = "latest",
    source: str = "",
) -> KnowledgeDatabase:
    """Open the KD in a DuckDB file (created if missing), or a throwaway one (``":memory:"``).

    ``read_only`` opens an existing file for reading (e.g. a notebook while no writer runs):
    changes stay in RAM and :meth:`KnowledgeDatabase.flush` writes nothing. A file written
    by a newer engine (higher schema version) is refused with a KDError. ``settings``: DuckDB
    configuration fixed at opening, over :func:`kd_store.query.kd_settings` (external access
    off, configuration locked: :meth:`KnowledgeDatabase.sql` cannot read or write outside the
    KD); a KD that serves untrusted SQL is opened with
    :func:`kd_store.query.served_settings`.

    ``run``: which run of the file the KD holds in memory and adds to. A file may hold several
    runs (``wm run --append``), each in its own world frame (odometry starts at identity
    every run), so frames, events, relations and map tiles belong to one run (``run_id`` in
    every view; ids stay unique across runs). ``"latest"`` (default) continues the newest,
    ``"new"`` starts one more (nothing of earlier runs is loaded; a new file's first run is
    0), an int opens that run. ``source`` names a new run's origin (the log) in ``runs``."""
    con = persist.connect(path, read_only=read_only, settings={**kd_settings(), **(settings or {})})
    try:
        run_id = _pick_run(con, run, source, read_only, where=f"KD file {path}")
    except BaseException:
        con.close()
        raise
    kd = KnowledgeDatabase(con, str(path), config or KDConfig(), run_id)
    kd._read_only = read_only
    return kd


def _pick_run(
    con: persist.Connection,
    run: int | Literal["latest", "new"],
    source: str,
    read_only: bool,
    where: str,
) -> int | None:
    """The run :func:`open` holds: None (every row) in a read-only file older than runs."""
    if run not in ("latest", "new") and not (isinstance(run, int) and not isinstance(run, bool)):
        raise KDError(f"{where}: run {run!r}: give 'latest', 'new' or a run id")
    if not persist.has_runs(con):  # read-only and older than schema version 3
        if run not in ("latest", 0):
            raise KDError(f"{where}: run {run!r}: this file (before runs) holds run 0 only")
        return None
    if isinstance(run, int):
        known = persist.run_ids(con)
        if run not in known:
            raise KDError(f"{where}: run {run} is not in the file (its runs: {known})")
        return run
    if read_only:
        if run == "new":
            raise KDError(f"{where}: a new run needs the file open for writing")
        return persist.latest_run(con)
    return persist.begin_run(con, source, new=run == "new")

"""The knowledge database: frames, pointers, classes and the three memory tiers in one place.

Reference 001 (the 4D/RCS reference model), section 4.4, and docs/architecture.md, section 5:
entity frames 4.4.2, classes 4.4.3, events 4.4.8-4.4.9, memory tiers 4.4.11. In RAM the KD is
immediate experience (this cycle) and short-term memory (recent histories, attention);
long-term memory is a DuckDB file that receives, at each :meth:`KnowledgeDatabase.flush`, the
frames the promotion rule admits, written as Arrow batches in one transaction.

Current entity state is also kept in slot-indexed numpy columns, so batch ingest, region
queries and filters never loop in Python over rows; a frame's ``state`` is rebuilt from the
columns the first time it is read after an ingest.
"""

from __future__ import annotations

import contextlib
import dataclasses
import threading
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import duckdb
import numpy as np
import pyarrow as pa

from kd_store import persist
from kd_store.classes import ClassLibrary, ClassPrototype
from kd_store.config import KDConfig, PromotionRule
from kd_store.errors import KDError, ResultTooLarge
from kd_store.frames import (
    STATUS_CODES,
    EntityFrame,
    EventFrame,
    Level,
    State,
    Status,
    check_entity,
    check_event,
    check_expectations,
    check_state,
)
from kd_store.memory import ImmediateExperience, ShortTermMemory
from kd_store.query import kd_settings
from kd_store.relations import Relation, RelationGraph, RelationKind
from kd_store.spatial import Box, GridIndex, Region, check_region
from kd_store.states import StateBatch, StateColumns, check_batch
from kd_store.tiles import TileKey, TileMemory, check_tile

NO_TIME = np.iinfo(np.int64).min
NO_EXPECTATION = np.iinfo(np.int64).max
K = RelationKind
_SPATIAL = {K.ON_TOP_OF, K.BENEATH, K.BESIDE, K.IN_FRONT_OF, K.BEHIND, K.INSIDE_OF, K.NEAR}


class _Columns:
    """Slot-indexed numpy columns of every entity in RAM (current state and filter keys)."""

    def __init__(self, capacity: int = 1024) -> None:
        self.n = 0
        self.id = np.zeros(capacity, np.int64)
        self.alive = np.zeros(capacity, bool)
        self.t_ns = np.full(capacity, NO_TIME, np.int64)
        self.frame = np.full(capacity, -1, np.int32)
        self.pos = np.zeros((capacity, 3))
        self.quat = np.zeros((capacity, 4))
        self.vel = np.zeros((capacity, 3))
        self.cov21 = np.zeros((capacity, 21))
        self.var_rpy = np.zeros((capacity, 3))
        self.status = np.zeros(capacity, np.int8)
        self.level = np.zeros(capacity, np.int8)
        self.confidence = np.zeros(capacity)
        self.max_worth = np.zeros(capacity)
        self.noteworthy = np.zeros(capacity, bool)
        self.klass = np.full(capacity, -1, np.int32)
        self.created_ns = np.zeros(capacity, np.int64)
        self.exp_t0 = np.full(capacity, NO_EXPECTATION, np.int64)  # first expectation's t_ns
        self.ltm = np.zeros(capacity, bool)  # in long-term memory
        self.dirty = np.zeros(capacity, bool)  # changed since the last flush
        self.stale = np.zeros(capacity, bool)  # frame.state older than the columns

    def grow(self) -> None:
        for k, v in vars(self).items():
            if isinstance(v, np.ndarray):
                extra = np.zeros((v.shape[0] // 2, *v.shape[1:]), v.dtype)  # grow by 1.5
                if k == "t_ns":
                    extra[:] = NO_TIME
                elif k == "exp_t0":
                    extra[:] = NO_EXPECTATION
                elif k in ("frame", "klass"):
                    extra[:] = -1
                setattr(self, k, np.concatenate([v, extra]))


class KnowledgeDatabase:
    """Entity and event frames with pointer graphs, a class library and three memory tiers.

    Open with :func:`open` (``":memory:"`` for a throwaway KD). Use as a context manager: a
    clean exit flushes and closes (a throwaway KD's is not flushed: closing discards it).
    Not safe for concurrent writers; readers in other threads use :meth:`reader` (their own
    DuckDB cursor, a consistent snapshot per query).
    """

    def __init__(
        self,
        con: duckdb.DuckDBPyConnection,
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
        self.classes = ClassLibrary.default()
        self.graph = RelationGraph()
        self.stm = ShortTermMemory({n: round(h * 1e9) for n, h in config.memory.horizons_s.items()})
        self.immediate = ImmediateExperience()
        self._cols = _Columns()
        self._frames: list[EntityFrame | None] = []
        self._slot: dict[int, int] = {}
        self._free: list[int] = []
        self._sorted: tuple[np.ndarray, np.ndarray] | None = None
        self._frame_names: list[str] = []
        self._frame_code: dict[str, int] = {}
        self._class_code: dict[str, int] = {}
        self._grid: dict[int, GridIndex] = {}
        self._events: dict[int, EventFrame] = {}
        self._event_ltm: set[int] = set()
        self._event_dirty: set[int] = set()
        self._pending: list[StateColumns] = []
        self._next_id = 0
        self._snapshot_targets: dict[str, Path] = {}  # publish_snapshot paths, checked
        self._snapshot_marked: set[Path] = set()  # ... and recorded in kd_meta
        self.tiles = TileMemory(
            lambda: persist.read_tile_keys(self._con, self._run),
            lambda key: persist.read_tile(self._con, key, self._run),
            config.tile_cache,
        )
        self._load(persist.read(con, run_id))

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
            self._con.execute("CHECKPOINT")
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
            self._con.execute("CHECKPOINT")
            persist.copy_snapshot(Path(self.path), target)
        return target

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
            self._insert_entity(f, ltm=True)
        for e in s.events:
            self._events[e.id] = e
            self._event_ltm.add(e.id)
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
        return frame_id in self._slot or frame_id in self._events

    def _kind_of(self, frame_id: int, where: str) -> str:
        if frame_id in self._slot:
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

    # ================================================================ entities

    def add_entity(self, name: str, level: Level | int, **fields: Any) -> EntityFrame:
        """Make an entity frame (fields as :class:`EntityFrame`; ``id`` optional) and add it.
        A ``state`` becomes the first entry of its short-term memory."""
        frame_id = fields.pop("id", None)
        if "created_ns" not in fields and self.immediate.t_ns is not None:
            fields["created_ns"] = self.immediate.t_ns
        probe = _coerce(EntityFrame(id=0, name=name, level=Level(level), **fields))
        where = _new_where("entity", frame_id, name)
        check_entity(probe, **self._tols(), where=where)
        self._check_classes(probe, where)
        f = dataclasses.replace(probe, id=self._take_id(frame_id, f"new entity {name!r}"))
        self._insert_entity(f, ltm=False)
        return f

    def insert_entity(self, frame: EntityFrame) -> EntityFrame:
        """Add a complete frame with its own id (which must be free)."""
        check_entity(frame, **self._tols())
        frame = _coerce(frame)
        self._check_classes(frame, f"entity {frame.id}")
        self._take_id(frame.id, f"entity {frame.id} ({frame.name!r})")
        self._insert_entity(frame, ltm=False)
        return frame

    def get(self, entity_id: int) -> EntityFrame:
        """The entity frame ``entity_id`` (its ``state`` is the latest)."""
        slot = self._slot.get(entity_id)
        if slot is None:
            raise KDError(f"entity {entity_id!r}: unknown id")
        if self._cols.stale[slot]:
            self._materialize(slot)
        return self._frames[slot]  # type: ignore[return-value]

    def entities(self) -> Iterator[EntityFrame]:
        """Every entity frame in RAM, in slot order."""
        for i in self._slot.values():
            yield self.get(int(self._cols.id[i]))

    def entity_ids(self) -> np.ndarray:
        """(N,) int64 ids of the entities in RAM, sorted."""
        return self._sorted_ids()[0].copy()

    def update_entity(self, entity_id: int, **changes: Any) -> EntityFrame:
        """Change fields of an entity frame (not ``id``; states go through :meth:`observe`)."""
        old = self.get(entity_id)
        where = f"entity {entity_id} ({old.name!r})"
        bad = {"id", "state", "created_ns"} & set(changes)
        if bad:
            raise KDError(f"{where}: {sorted(bad)} cannot be changed with update_entity")
        try:
            new = dataclasses.replace(old, **changes)
        except TypeError as e:
            raise KDError(f"{where}: {e}") from None
        # the state cannot change here and kept expectations were checked when they came in
        same = isinstance(old.expectations, tuple) and new.expectations is old.expectations
        check_entity(new, **self._tols(), where=where, states=not same, old=old)
        new = _coerce(new)
        self._check_classes(new, where)
        slot = self._slot[entity_id]
        self._frames[slot] = new
        self._set_keys(slot, new)
        return new

    def observe(self, entity_id: int, state: State) -> EntityFrame:
        """Add one state to an entity's history; it becomes the current state. Expectations
        at or before it are dropped: the present has overtaken them (see :meth:`ingest`)."""
        f = self.get(entity_id)
        check_state(state, f"entity {entity_id} ({f.name!r})", **self._tols())
        self.ingest(
            StateBatch(
                np.array([entity_id]),
                np.array([state.t_ns]),
                state.frame,
                state.position_xyz[None],
                state.orientation_xyzw[None],
                state.velocity_xyz[None],
                state.covariance[None],
                state.orientation_var_rpy[None],
            )
        )
        return self.get(entity_id)

    def expect(self, entity_id: int, states: Iterable[State]) -> EntityFrame:
        """Replace an entity's short-term expectation queue (predicted states, time order)."""
        old = self.get(entity_id)
        queue = tuple(states)
        check_expectations(queue, old.state, f"entity {entity_id} ({old.name!r})", **self._tols())
        new = dataclasses.replace(old, expectations=queue)
        slot = self._slot[entity_id]
        self._frames[slot] = new
        self._cols.exp_t0[slot] = queue[0].t_ns if queue else NO_EXPECTATION
        self._cols.dirty[slot] = True
        return new

    def mark_noteworthy(self, frame_id: int) -> None:
        """Flag an entity or event for long-term memory (4.4.11)."""
        if self._kind_of(frame_id, "mark_noteworthy") == "entity":
            self.update_entity(frame_id, noteworthy=True)
        else:
            self.update_event(frame_id, noteworthy=True)

    def found_specific_class(self, entity_id: int) -> ClassPrototype:
        """Found a specific class from a confirmed entity and point the entity at it."""
        proto = self.classes.found_specific(self.get(entity_id))
        self.update_entity(entity_id, specific_class=proto.name)
        return proto

    # ---------------------------------------------------------------- batch ingest

    def ingest(self, batch: StateBatch) -> int:
        """Add a batch of state updates (see :class:`StateBatch`); returns rows added.

        Refuses, keeping nothing of the batch: unknown ids, NaN/inf, bad covariances, and times
        that do not strictly increase per entity or are not after its current state.
        Expectations an entity holds at or before its new state are dropped (history now, not
        a contradiction: 4.4.11, short-term expectations are of the future); later ones stay."""
        where = f"state batch in frame {batch.frame!r}"
        c = check_batch(batch, where, **self._tols())
        if not len(c):
            return 0
        slots = self._slots_of(c.entity_id, where)
        order = np.lexsort((c.t_ns, c.entity_id))
        e, t = c.entity_id[order], c.t_ns[order]
        first = np.r_[True, e[1:] != e[:-1]]
        back = ~first & (np.r_[0, np.diff(t)] <= 0)
        if back.any():
            i = int(np.flatnonzero(back)[0])
            raise KDError(
                f"{where}: entity {int(e[i])}: t_ns={int(t[i])} does not come after "
                f"t_ns={int(t[i - 1])} in the same batch"
            )
        head = order[first]
        before = c.t_ns[head] <= self._cols.t_ns[slots[head]]
        if before.any():
            i = int(head[np.flatnonzero(before)[0]])
            raise KDError(
                f"{where}: entity {int(c.entity_id[i])}: t_ns={int(c.t_ns[i])} goes back from "
                f"its current state at t_ns={int(self._cols.t_ns[slots[i]])}"
            )
        # -- checked: from here on nothing raises
        last = order[np.r_[e[1:] != e[:-1], True]]
        self._set_state_columns(slots[last], c.take(last))
        self._drop_overtaken(slots[last], c.t_ns[last])
        self._append_history(c, slots)
        in_ltm = self._cols.ltm[slots]
        if in_ltm.all():
            self._pending.append(c)
        elif in_ltm.any():
            self._pending.append(c.take(in_ltm))
        self.immediate.note(e[first])
        return len(c)

    def _set_state_columns(self, slots: np.ndarray, c: StateColumns) -> None:
        cols = self._cols
        cols.t_ns[slots] = c.t_ns
        cols.frame[slots] = self._frame_code_of(c.frame)
        cols.pos[slots] = c.position_xyz
        cols.quat[slots] = c.orientation_xyzw
        cols.vel[slots] = c.velocity_xyz
        cols.cov21[slots] = c.cov21
        cols.var_rpy[slots] = c.orientation_var_rpy
        cols.stale[slots] = True
        cols.dirty[slots] = True
        self._grid.clear()

    def _drop_overtaken(self, slots: np.ndarray, t_ns: np.ndarray) -> None:
        """Drop the expectations at or before ``t_ns`` (N,) of entities in ``slots`` (N,)."""
        over = np.flatnonzero(self._cols.exp_t0[slots] <= t_ns)
        for slot, t in zip(slots[over].tolist(), t_ns[over].tolist(), strict=True):
            f = self._frames[slot]
            assert f is not None
            keep = tuple(s for s in f.expectations if s.t_ns > t)
            self._frames[slot] = dataclasses.replace(f, expectations=keep)
            self._cols.exp_t0[slot] = keep[0].t_ns if keep else NO_EXPECTATION

    def _append_history(self, c: StateColumns, slots: np.ndarray) -> None:
        nodes = self.config.memory.node_of_sp_level
        levels = self._cols.level[slots]
        present = np.unique(levels)
        names = {nodes[int(lv)] for lv in present}
        if len(names) == 1:
            self.stm.history[names.pop()].append(c)
            return
        for name in names:
            lv = [k for k, v in nodes.items() if v == name]
            self.stm.history[name].append(c.take(np.isin(levels, lv)))

    def _frame_code_of(self, frame: str) -> int:
        code = self._frame_code.get(frame)
        if code is None:
            code = self._frame_code[frame] = len(self._frame_names)
            self._frame_names.append(frame)
        return code

    def _materialize(self, slot: int) -> None:
        cols = self._cols
        v = np.concatenate(
            (
                cols.pos[slot],
                cols.quat[slot],
                cols.vel[slot],
                cols.cov21[slot],
                cols.var_rpy[slot],
            )
        )
        state = State.from_vector(int(cols.t_ns[slot]), self._frame_names[cols.frame[slot]], v)
        object.__setattr__(self._frames[slot], "state", state)  # the KD owns its frames
        cols.stale[slot] = False

    # ---------------------------------------------------------------- slots and keys

    def _insert_entity(self, f: EntityFrame, ltm: bool) -> None:
        cols = self._cols
        if self._free:
            slot = self._free.pop()
        else:
            if cols.n == cols.id.shape[0]:
                cols.grow()
            slot = cols.n
            cols.n += 1
            self._frames.append(None)
        self._frames[slot] = f
        self._slot[f.id] = slot
        cols.id[slot] = f.id
        cols.alive[slot] = True
        cols.created_ns[slot] = f.created_ns
        cols.ltm[slot] = ltm
        cols.dirty[slot] = not ltm
        cols.stale[slot] = False
        cols.t_ns[slot] = NO_TIME
        cols.frame[slot] = -1
        self._set_keys(slot, f)
        self._sorted = None
        if f.state is not None:
            c = StateColumns.from_states([f.id], [f.state])[0]
            self._set_state_columns(np.array([slot]), c)
            cols.stale[slot] = False
            if not ltm:
                self._append_history(c, np.array([slot]))
                self.immediate.note(np.array([f.id]))
        cols.dirty[slot] = not ltm

    def _set_keys(self, slot: int, f: EntityFrame) -> None:
        cols = self._cols
        cols.status[slot] = STATUS_CODES[Status(f.status).value]
        cols.level[slot] = int(f.level)
        cols.confidence[slot] = f.confidence
        cols.max_worth[slot] = f.value.max_worth
        cols.noteworthy[slot] = f.noteworthy
        name = f.most_specific_class
        cols.klass[slot] = (
            -1 if name is None else self._class_code.setdefault(name, len(self._class_code))
        )
        cols.exp_t0[slot] = f.expectations[0].t_ns if f.expectations else NO_EXPECTATION
        cols.dirty[slot] = True

    def _remove_entity(self, entity_id: int) -> None:
        slot = self._slot.pop(entity_id)
        self._frames[slot] = None
        self._cols.alive[slot] = False
        self._cols.t_ns[slot] = NO_TIME
        self._free.append(slot)
        self.graph.remove_node(entity_id)
        self._sorted = None
        self._grid.clear()

    def _sorted_ids(self) -> tuple[np.ndarray, np.ndarray]:
        if self._sorted is None:
            slots = np.fromiter(self._slot.values(), np.int64, len(self._slot))
            ids = self._cols.id[slots]
            order = np.argsort(ids)
            self._sorted = (ids[order], slots[order])
        return self._sorted

    def _slots_of(self, ids: np.ndarray, where: str) -> np.ndarray:
        sorted_ids, sorted_slots = self._sorted_ids()
        if not len(sorted_ids):
            raise KDError(f"{where}: entity {int(ids[0])} is not in the KD")
        k = np.clip(np.searchsorted(sorted_ids, ids), 0, len(sorted_ids) - 1)
        unknown = sorted_ids[k] != ids
        if unknown.any():
            bad = np.unique(ids[unknown])
            raise KDError(f"{where}: entities {bad[:5].tolist()} are not in the KD")
        return sorted_slots[k]

    def _check_classes(self, f: EntityFrame, where: str) -> None:
        for c in (*f.generic_classes, *([f.specific_class] if f.specific_class else [])):
            if c not in self.classes:
                raise KDError(f"{where}: class pointer {c!r} is not in the class library")

    def _tols(self) -> dict[str, float]:
        return {"cov_tol": self.config.covariance_tol, "quat_tol": self.config.quaternion_tol}

    # ================================================================ events

    def add_event(self, name: str, class_name: str, t_start_ns: int, **fields: Any) -> EventFrame:
        """Make an event frame (fields as :class:`EventFrame`; ``id`` optional) and add it."""
        frame_id = fields.pop("id", None)
        probe = EventFrame(id=0, name=name, class_name=class_name, t_start_ns=t_start_ns, **fields)
        check_event(probe, _new_where("event", frame_id, name))
        e = dataclasses.replace(probe, id=self._take_id(frame_id, f"new event {name!r}"))
        self._events[e.id] = e
        self._event_dirty.add(e.id)
        return e

    def insert_event(self, event: EventFrame) -> EventFrame:
        """Add a complete event frame with its own id (which must be free)."""
        check_event(event)
        self._take_id(event.id, f"event {event.id} ({event.name!r})")
        self._events[event.id] = event
        self._event_dirty.add(event.id)
        return event

    def get_event(self, event_id: int) -> EventFrame:
        try:
            return self._events[event_id]
        except KeyError:
            raise KDError(f"event {event_id!r}: unknown id") from None

    def update_event(self, event_id: int, **changes: Any) -> EventFrame:
        """Change fields of an event frame (e.g. ``t_end_ns`` when it ends)."""
        old = self.get_event(event_id)
        if "id" in changes:
            raise KDError(f"event {event_id}: id cannot be changed")
        try:
            new = dataclasses.replace(old, **changes)
        except TypeError as e:
            raise KDError(f"event {event_id} ({old.name!r}): {e}") from None
        check_event(new)
        self._events[event_id] = new
        self._event_dirty.add(event_id)
        return new

    def events(
        self,
        t_from_ns: int | None = None,
        t_to_ns: int | None = None,
        class_name: str | None = None,
        participant: int | None = None,
    ) -> list[EventFrame]:
        """Events overlapping [t_from_ns, t_to_ns] (open ends: unbounded), of ``class_name``,
        involving entity ``participant``; in start-time order."""
        lo = NO_TIME if t_from_ns is None else t_from_ns
        hi = np.iinfo(np.int64).max if t_to_ns is None else t_to_ns
        pool: Iterable[int] = self._events
        if participant is not None:
            self._kind_of(participant, "events by participant")
            pool = self.graph.inn(participant, K.INVOLVES)
        out = [
            e
            for e in (self._events[i] for i in pool)
            if e.overlaps(lo, hi) and (class_name is None or e.class_name == class_name)
        ]
        return sorted(out, key=lambda e: (e.t_start_ns, e.id))

    def events_at(self, t_ns: int) -> list[EventFrame]:
        """Events going on at ``t_ns``."""
        return self.events(t_ns, t_ns)

    # ================================================================ pointers

    def relate(self, src: int, kind: RelationKind | str, dst: int, t_ns: int | None = None) -> None:
        """Point ``src --kind--> dst`` from ``t_ns`` on (default: this cycle's time, else 0)."""
        kind = self._kind(kind, src, dst)
        where = f"relation {src} {kind.value} {dst}"
        ks, kd = self._kind_of(src, where), self._kind_of(dst, where)
        if kind in (K.BELONGS_TO, K.HAS_PART) and ks != kd:
            raise KDError(f"{where}: a {ks} cannot be part of an {kd} (or the other way)")
        if kind in _SPATIAL and "event" in (ks, kd):
            raise KDError(
                f"{where}: spatial relations link entities, {src} is a {ks}, {dst} a {kd}"
            )
        if kind == K.INVOLVES and (ks, kd) != ("event", "entity"):
            raise KDError(f"{where}: involves points from an event to an entity, not {ks}->{kd}")
        self.graph.add(src, kind, dst, self._now(t_ns))

    def unrelate(
        self, src: int, kind: RelationKind | str, dst: int, t_ns: int | None = None
    ) -> bool:
        """End ``src --kind--> dst`` at ``t_ns`` (kept in history); False if it was not open."""
        return self.graph.close(src, self._kind(kind, src, dst), dst, self._now(t_ns))

    def pointers(
        self, frame_id: int, kind: RelationKind | str | None = None, t_ns: int | None = None
    ) -> list[int]:
        """Frames ``frame_id`` points to by ``kind`` at ``t_ns`` (None: now)."""
        self._kind_of(frame_id, "pointers")
        return self.graph.out(frame_id, None if kind is None else RelationKind(kind), t_ns)

    def pointed_by(
        self, frame_id: int, kind: RelationKind | str | None = None, t_ns: int | None = None
    ) -> list[int]:
        """Frames pointing to ``frame_id`` by ``kind`` at ``t_ns``."""
        self._kind_of(frame_id, "pointed_by")
        return self.graph.inn(frame_id, None if kind is None else RelationKind(kind), t_ns)

    def relations(self, frame_id: int) -> list[Relation]:
        """Every relation from ``frame_id``, open and closed."""
        self._kind_of(frame_id, "relations")
        return self.graph.relations_of(frame_id)

    def parent(self, frame_id: int, t_ns: int | None = None) -> int | None:
        self._kind_of(frame_id, "parent")
        return self.graph.parent(frame_id, t_ns)

    def parts(self, frame_id: int, t_ns: int | None = None) -> list[int]:
        return sorted(self.pointers(frame_id, K.HAS_PART, t_ns))

    def ancestors(self, frame_id: int, t_ns: int | None = None) -> list[int]:
        """Parent, grandparent, ... nearest first."""
        self._kind_of(frame_id, "ancestors")
        return self.graph.ancestors(frame_id, t_ns)

    def parts_tree(self, frame_id: int, t_ns: int | None = None) -> list[tuple[int, int]]:
        """(id, depth) of the frame and all its parts, depth first."""
        self._kind_of(frame_id, "parts_tree")
        return self.graph.parts_tree(frame_id, t_ns)

    def neighbourhood(
        self,
        frame_id: int,
        kinds: Iterable[RelationKind | str] | None = None,
        depth: int = 1,
        t_ns: int | None = None,
    ) -> dict[int, int]:
        """Frames within ``depth`` hops over ``kinds`` (either direction): id -> hops."""
        self._kind_of(frame_id, "neighbourhood")
        ks = None if kinds is None else [RelationKind(k) for k in kinds]
        return self.graph.neighbourhood(frame_id, ks, depth, t_ns)

    def class_lineage(self, entity_id: int) -> list[str]:
        """The entity's most specific class and its is_a ancestors, most specific first."""
        name = self.get(entity_id).most_specific_class
        return [] if name is None else self.classes.lineage(name)

    def _kind(self, kind: RelationKind | str, src: int, dst: int) -> RelationKind:
        try:
            return RelationKind(kind)
        except ValueError:
            raise KDError(f"relation {src} {kind!r} {dst}: unknown relation kind") from None

    def _now(self, t_ns: int | None) -> int:
        if t_ns is not None:
            return int(t_ns)
        return self.immediate.t_ns if self.immediate.t_ns is not None else 0

    # ================================================================ memory tiers

    def begin_cycle(self, t_ns: int) -> None:
        """Start a new cycle of immediate experience at ``t_ns``."""
        self.immediate.begin(t_ns)

    def observed_this_cycle(self) -> np.ndarray:
        """Sorted ids of the frames observed or made since :meth:`begin_cycle`."""
        return self.immediate.ids()

    def set_attention(self, node: str, entity_ids: Iterable[int]) -> None:
        """Set the entities-of-attention list of a node level (``"primitive"``, ...)."""
        if node not in self.stm.attention:
            raise KDError(
                f"attention: unknown node level {node!r} (have {sorted(self.stm.attention)})"
            )
        ids = [int(i) for i in entity_ids]
        for i in ids:
            if i not in self._slot:
                raise KDError(f"attention list of {node!r}: entity {i} is not in the KD")
        self.stm.attention[node] = ids

    def attention(self, node: str) -> list[int]:
        return list(self.stm.attention[node])

    def history(self, entity_id: int) -> list[State]:
        """The entity's short-term memory queue: remembered past states, oldest first."""
        f = self.get(entity_id)
        node = self.config.memory.node_of_sp_level[int(f.level)]
        states = self.stm.history[node].states_of(entity_id)
        for name, h in self.stm.history.items():  # after a level change
            if name != node:
                states += h.states_of(entity_id)
        return sorted(states, key=lambda s: s.t_ns)

    def long_term_history(self, entity_id: int) -> list[State]:
        """The entity's states in long-term memory (after a flush), oldest first."""
        self.flush()
        with self._lock:
            return persist.read_states(self._con, entity_id)

    def as_of(self, t_ns: int, long_term: bool = False) -> dict[int, State]:
        """State of every entity at ``t_ns``: its latest remembered state at or before ``t_ns``.

        Short-term memory only by default (fast, no I/O); ``long_term=True`` also searches the
        long-term histories on disk (after a flush), for times older than the horizons."""
        out: dict[int, State] = {}
        sources = [h.as_of(t_ns) for h in self.stm.history.values()]
        if long_term:
            self.flush()
            with self._lock:
                table = self._con.sql(
                    "SELECT * FROM entity_states_as_of($1)", params=[int(t_ns)]
                ).to_arrow_table()
            chunks = StateColumns.from_arrow(table)
            sources.append({int(c.entity_id[i]): c.state(i) for c in chunks for i in range(len(c))})
        for states in sources:
            for k, s in states.items():
                if k in self._slot and (k not in out or s.t_ns > out[k].t_ns):
                    out[k] = s
        return out

    def advance(self, t_now_ns: int) -> list[int]:
        """Let short-term memory move on to ``t_now_ns``: trim histories to each level's
        horizon and forget frames older than it that long-term memory did not take and
        attention does not hold (4.4.11). Frames the promotion rule admits are moved to
        long-term memory first, so their histories are kept. Returns the ids forgotten."""
        self._promote()
        self.stm.trim(t_now_ns)
        keep = self.stm.attended()
        cols, n = self._cols, self._cols.n
        horizon = np.array([0, *(self.config.memory.horizon_ns(lv) for lv in range(1, 6))])
        t_last = np.maximum(cols.t_ns[:n], cols.created_ns[:n])
        stale = cols.alive[:n] & ~cols.ltm[:n] & (t_last < t_now_ns - horizon[cols.level[:n]])
        gone = [i for i in cols.id[np.flatnonzero(stale)].tolist() if i not in keep]
        for e in list(self._events.values()):
            if e.id in self._event_ltm or e.id in keep:
                continue
            end = e.t_end_ns if e.t_end_ns is not None else t_now_ns
            if end < t_now_ns - self.config.memory.horizon_ns(max(1, min(5, e.level))):
                del self._events[e.id]
                self._event_dirty.discard(e.id)
                self.graph.remove_node(e.id)
                gone.append(e.id)
        for entity_id in (g for g in gone if g in self._slot):
            self._remove_entity(entity_id)
        ents = np.array(gone, dtype=np.int64)
        for h in self.stm.history.values():
            h.drop(ents)
        return sorted(gone)

    # ================================================================ long-term memory

    def flush(self, tiles: bool = True) -> int:
        """Promote what the rule admits and write every change of long-term frames since the
        last flush, in one transaction, with the pending map tiles unless ``tiles`` is False
        (they then wait for a later flush). Returns the number of state rows written."""
        if self._read_only:
            return 0
        with self._lock:
            self._promote()
            w = self._collect(tiles)
            if not w:
                return 0
            persist.write(self._con, w)  # on failure nothing is cleared: the next flush retries
            self._cols.dirty[: self._cols.n] = False
            self._event_dirty.clear()
            self.graph.dirty.clear()
            self.classes.dirty.clear()
            self.tiles.written(w.tiles)
            self._pending = []
            return sum(len(c) for c in w.states)

    def _promote(self) -> None:
        """Move the frames the promotion rule admits into long-term memory (in RAM; the next
        flush writes them): their short-term histories join the pending rows, and pointers
        touching them are marked for writing."""
        cols, rule, n = self._cols, self.promotion_rule, self._cols.n
        codes = [STATUS_CODES[Status(s).value] for s in rule.statuses]
        admit = (np.isin(cols.status[:n], codes) & (cols.confidence[:n] >= rule.min_confidence)) | (
            cols.noteworthy[:n] | (cols.max_worth[:n] >= rule.min_worth)
        )
        newly = np.flatnonzero(admit & cols.alive[:n] & ~cols.ltm[:n])
        new_ids = cols.id[newly]
        for h in self.stm.history.values():
            self._pending += h.rows_of(new_ids)
        cols.ltm[newly] = True
        cols.dirty[newly] = True
        new_events = {
            i
            for i, e in self._events.items()
            if i not in self._event_ltm
            and (e.noteworthy or e.confidence >= rule.min_event_confidence)
        }
        self._event_ltm |= new_events
        self._event_dirty |= new_events
        for node in (*new_ids.tolist(), *new_events):  # pointers from and into new frames
            self.graph.dirty.update(r.key for r in self.graph.relations_of(node))
            self.graph.dirty.update(r.key for r in self.graph.relations_into(node))

    def _in_ltm(self, frame_id: int) -> bool:
        slot = self._slot.get(frame_id)
        return bool(self._cols.ltm[slot]) if slot is not None else frame_id in self._event_ltm

    def _collect(self, tiles: bool = True) -> persist.Write:
        """Everything the next flush writes (promotion done); map tiles only if ``tiles``."""
        cols, n = self._cols, self._cols.n
        write_slots = np.flatnonzero(cols.alive[:n] & cols.ltm[:n] & cols.dirty[:n])
        has = cols.t_ns[write_slots] != NO_TIME
        entity_states = persist.current_states_to_arrow(
            cols.t_ns[write_slots],
            [
                self._frame_names[c] if h else None
                for c, h in zip(cols.frame[write_slots], has, strict=True)
            ],
            cols.pos[write_slots],
            cols.quat[write_slots],
            cols.vel[write_slots],
            cols.cov21[write_slots],
            cols.var_rpy[write_slots],
        )
        rels = [r for k in self.graph.dirty if (r := self.graph.find(k)) is not None]
        return persist.Write(
            entities=[self._frames[s] for s in write_slots],  # type: ignore[misc]
            entity_states=entity_states,
            states=[c for c in self._pending if len(c)],
            events=[self._events[i] for i in sorted(self._event_dirty & self._event_ltm)],
            relations=[r for r in rels if self._in_ltm(r.src) and self._in_ltm(r.dst)],
            classes=[self.classes.get(c) for c in self.classes.dirty if c in self.classes],
            tiles=list(self.tiles.pending.values()) if tiles else [],
            next_id=self._next_id,
            run_id=self.run_id,
        )

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
            if len(self.tiles.pending) >= self.config.tile_write_batch and not self._read_only:
                tiles = list(self.tiles.pending.values())
                w = persist.Write(tiles=tiles, next_id=self._next_id, run_id=self.run_id)
                persist.write(self._con, w)
                self.tiles.written(tiles)

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
        check_region(region)
        frames = {region.frame: None, **(poses or {})}
        found = [self._region_in(region, name, T) for name, T in frames.items()]
        cand = np.concatenate(found) if found else np.zeros(0, np.int64)
        cols = self._cols
        keep = np.ones(len(cand), bool)
        if min_confidence > 0:
            keep &= cols.confidence[cand] >= min_confidence
        if statuses is not None:
            codes = [STATUS_CODES[Status(s).value] for s in statuses]
            keep &= np.isin(cols.status[cand], codes)
        if levels is not None:
            keep &= np.isin(cols.level[cand], [int(v) for v in levels])
        if classes is not None:
            names = set().union(*(self.classes.descendants(c) for c in classes))
            codes = [self._class_code[n] for n in names if n in self._class_code]
            keep &= np.isin(cols.klass[cand], codes)
        return np.sort(cols.id[cand[keep]])

    def _region_in(
        self, region: Region, frame: str, T_region_frame: np.ndarray | None
    ) -> np.ndarray:
        """Slots of entities held in ``frame`` whose position lies in ``region``."""
        code = self._frame_code.get(frame)
        if code is None:
            return np.zeros(0, np.int64)
        cols = self._cols
        grid = self._grid.get(code)
        if grid is None:
            slots = np.flatnonzero(cols.alive[: cols.n] & (cols.frame[: cols.n] == code))
            grid = self._grid[code] = GridIndex(slots, cols.pos[slots], self.config.grid_cell_m)
        if T_region_frame is None:
            cand = grid.candidates(region)
            return cand[region.contains(cols.pos[cand])]
        T = np.asarray(T_region_frame, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise KDError(f"region query: pose of frame {frame!r} is not a finite 4x4 matrix")
        R, t = T[:3, :3], T[:3, 3]
        if abs(R[0, 2]) > 1e-9 or abs(R[1, 2]) > 1e-9:
            cand = grid.slots  # a tilted frame: its heights smear into x-y, so test them all
        else:  # the region's x-y bounds seen from ``frame`` (heights do not matter)
            lo_x, lo_y, hi_x, hi_y = region.bounds_xy()
            corners = np.array([[x, y, 0.0] for x in (lo_x, hi_x) for y in (lo_y, hi_y)])
            xy = ((corners - t) @ R)[:, :2]  # R^T (p - t), row-wise
            lo, hi = xy.min(axis=0), xy.max(axis=0)
            cand = grid.candidates(Box(frame, (lo[0], lo[1], 0.0), (hi[0], hi[1], 0.0)))
        p_region = cols.pos[cand] @ R.T + t
        return cand[region.contains(p_region)]

    def sql(self, query: str, flush: bool = True) -> pa.Table:
        """Run one read-only SELECT over the documented views (docs/kd.md); returns Arrow.
        Flushes first by default, so the views show long-term memory up to now. Nothing
        outside the KD can be reached (:func:`open`): reading a file, a URL or an extension
        raises KDError."""
        if flush:
            self.flush()
        with self._lock:
            return _read_only_query(_cursor(self._con), query)

    def current_columns(self) -> dict[str, np.ndarray]:
        """Copies of every live entity's current state and filter keys (N rows, slot order),
        for a reader in another thread that must not wait for the writer: ``id`` (N,) int64,
        ``t_ns`` (N,) int64 (the current state's time, int64 min without one), ``frame`` (N,)
        object (its frame name, None without a state), ``position`` and ``velocity`` (N, 3)
        m and m/s in that frame, ``status`` (N,) object (names), ``level`` (N,) int8,
        ``confidence`` (N,), ``class_name`` (N,) object (the most specific class, or None).
        Call it from the writer's thread (between two of its changes)."""
        c, n = self._cols, self._cols.n
        live = np.flatnonzero(c.alive[:n])
        frames = np.array([None, *self._frame_names], object)
        classes = np.array([None, *sorted(self._class_code, key=self._class_code.get)], object)
        statuses = np.array([s.value for s in Status], object)
        return {
            "id": c.id[live].copy(),
            "t_ns": c.t_ns[live].copy(),
            "frame": frames[c.frame[live] + 1],
            "position": c.pos[live].copy(),
            "velocity": c.vel[live].copy(),
            "status": statuses[c.status[live]],
            "level": c.level[live].copy(),
            "confidence": c.confidence[live].copy(),
            "class_name": classes[c.klass[live] + 1],
        }

    def reader(self) -> SQLReader:
        """A reader for another thread: its own cursor, a consistent snapshot per query."""
        with self._lock:
            return SQLReader(_cursor(self._con))

    def export_parquet(self, folder: str | Path) -> list[Path]:
        """Flush, then write long-term memory as one Parquet file per table in ``folder``."""
        self.flush()
        with self._lock:
            return persist.export_parquet(self._con, folder)

    def import_parquet(self, folder: str | Path) -> None:
        """Load a Parquet KD (from :meth:`export_parquet`) into this KD, which must be empty."""
        if self._slot or self._events:
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


def _new_where(kind: str, frame_id: int | None, name: str) -> str:
    return f"new {kind} {name!r}" if frame_id is None else f"{kind} {frame_id} ({name!r})"


def _cursor(con: duckdb.DuckDBPyConnection) -> duckdb.DuckDBPyConnection:
    cur = con.cursor()
    with contextlib.suppress(duckdb.Error):  # a locked configuration keeps its own setting
        cur.execute("SET enable_progress_bar = false")
    return cur


def _coerce(f: EntityFrame) -> EntityFrame:
    """Enum fields as enums (callers may pass ``"confirmed"`` or ``4``); checked before."""
    if type(f.status) is Status and type(f.level) is Level:
        return f
    return dataclasses.replace(f, status=Status(f.status), level=Level(f.level))


class SQLReader:
    """Read-only SQL on its own DuckDB cursor (use one per thread)."""

    def __init__(self, cursor: duckdb.DuckDBPyConnection) -> None:
        self._cur = cursor
        self._in_tx = False

    def sql(
        self, query: str, max_rows: int | None = None, max_bytes: int | None = None
    ) -> pa.Table:
        """One read-only SELECT; a result of more than ``max_rows`` rows or ``max_bytes``
        bytes (Arrow buffers) is refused with a KDError before it is read whole (None: no
        limit)."""
        return _read_only_query(
            self._cur, query, own_tx=not self._in_tx, max_rows=max_rows, max_bytes=max_bytes
        )

    @contextmanager
    def snapshot(self) -> Iterator[SQLReader]:
        """Run several queries against one snapshot: ``with r.snapshot(): r.sql(...); ...``."""
        self._cur.execute("BEGIN TRANSACTION")
        self._in_tx = True
        try:
            yield self
        finally:
            self._in_tx = False
            self._cur.execute("ROLLBACK")

    def interrupt(self) -> None:
        """Stop the query running on this reader (from another thread)."""
        self._cur.interrupt()

    def close(self) -> None:
        self._cur.close()


def _read_only_query(
    cur: duckdb.DuckDBPyConnection,
    query: str,
    own_tx: bool = True,
    max_rows: int | None = None,
    max_bytes: int | None = None,
) -> pa.Table:
    """One SELECT in a transaction that is rolled back, so even a query with side effects
    leaves nothing behind. With ``max_rows`` or ``max_bytes`` (bytes of Arrow buffers) the
    result is read batch by batch and refused (ResultTooLarge, a KDError naming the limit and
    the query) as
    soon as it passes either, so an untrusted query cannot make the caller hold a result of
    any size; None: no limit (the engine's own queries)."""
    try:
        statements = duckdb.extract_statements(query)
    except duckdb.Error as e:
        raise KDError(f"SQL {query!r}: {e}") from None
    if len(statements) != 1 or statements[0].type != duckdb.StatementType.SELECT:
        kinds = [s.type.name for s in statements]
        raise KDError(f"SQL {query!r}: only one read-only SELECT is allowed, got {kinds}")
    if own_tx:
        cur.execute("BEGIN TRANSACTION")
    try:
        rel = cur.sql(query)
        if max_rows is None and max_bytes is None:
            return rel.to_arrow_table()
        return _bounded_arrow(rel, query, max_rows, max_bytes)
    except duckdb.PermissionException as e:
        raise KDError(
            f"SQL {query!r}: refused, a KD's SQL reads the KD's own views only (docs/kd.md), "
            f"no file, URL or extension outside it ({e})"
        ) from None
    except (duckdb.Error, pa.ArrowException, OSError) as e:
        # a failure while a streamed result is read (an error() call, an interrupt at the
        # time limit) reaches Python through Arrow's stream as OSError or an Arrow error
        raise KDError(f"SQL {query!r}: {e}") from None
    finally:
        if own_tx:
            cur.execute("ROLLBACK")


# rows per Arrow batch of a bounded result: the limits are checked batch by batch, so at most
# this many rows beyond a limit are ever read
_BATCH_ROWS = 65_536


def _bounded_arrow(
    rel: duckdb.DuckDBPyRelation, query: str, max_rows: int | None, max_bytes: int | None
) -> pa.Table:
    """``rel``'s result as Arrow, read through a record-batch reader and refused with
    ResultTooLarge as soon as it holds more than ``max_rows`` rows or ``max_bytes`` bytes
    (None: that limit is off). DuckDB streams the result, so a refused query stops there."""
    rows_cap = max_rows if max_rows is not None else _BATCH_ROWS
    # older DuckDB (1.0) names the reader fetch_arrow_reader
    to_reader = getattr(rel, "to_arrow_reader", None) or rel.fetch_arrow_reader
    reader = to_reader(max(1, min(rows_cap + 1, _BATCH_ROWS)))
    schema = reader.schema
    batches: list[pa.RecordBatch] = []
    rows = size = 0
    try:
        for batch in reader:
            rows, size = rows + batch.num_rows, size + batch.nbytes
            if max_rows is not None and rows > max_rows:
                raise ResultTooLarge(
                    f"SQL {query!r}: the result has more than the limit of {max_rows:,} rows "
                    f"(max_rows); narrow it (WHERE, LIMIT, an aggregate) or raise the limit"
                )
            if max_bytes is not None and size > max_bytes:
                raise ResultTooLarge(
                    f"SQL {query!r}: the result passed the limit of {_mb(max_bytes)} "
                    f"(max_bytes) at {_mb(size)} after {rows:,} rows; narrow it (fewer "
                    f"columns or rows, shorter values) or raise the limit"
                )
            batches.append(batch)
    finally:
        reader.close()
    return pa.Table.from_batches(batches, schema=schema)


def _mb(n_bytes: int) -> str:
    """``n_bytes`` as MB (2**20 bytes) for a message."""
    return f"{n_bytes / 2**20:,.1f} MB"


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
    con: duckdb.DuckDBPyConnection,
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

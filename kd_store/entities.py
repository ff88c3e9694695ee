"""Entity frames in RAM: current state columns, histories, status, confidence, region queries.

Reference 001, section 4.4.2 (entity frame, Figure 18) and 4.4.11 (memory tiers): an entity
frame's current state is its immediate experience, its remembered states are its short-term
memory queue (:mod:`kd_store.memory`), and the promotion rule admits it to long-term memory.

Current entity state is kept in slot-indexed numpy columns, so batch ingest, region queries and
filters never loop in Python over rows; a frame's ``state`` is rebuilt from the columns the
first time it is read after an ingest. This part owns the frames, their columns and the state
rows waiting for the next flush; ids are handed out by the KD (entities and events share one
id space) and pointers live in the relation graph (:mod:`kd_store.relations`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import numpy as np
import pyarrow as pa

from kd_store import persist
from kd_store.classes import ClassLibrary, ClassPrototype
from kd_store.config import KDConfig, PromotionRule
from kd_store.errors import KDError
from kd_store.frames import (
    STATUS_CODES,
    EntityFrame,
    Level,
    State,
    Status,
    check_entity,
    check_expectations,
    check_state,
)
from kd_store.memory import ImmediateExperience, ShortTermMemory
from kd_store.spatial import Box, GridIndex, Region, check_region
from kd_store.states import StateBatch, StateColumns, check_batch

NO_TIME = np.iinfo(np.int64).min
NO_EXPECTATION = np.iinfo(np.int64).max

#: ``take_id(frame_id, where)``: the KD's id allocator (None: a fresh id; else that id, which
#: must be free), shared with events.
TakeId = Callable[[int | None, str], int]


class EntityColumns:
    """Slot-indexed numpy columns of every entity in RAM (current state and filter keys).

    Positions (m), velocities (m/s) and orientations are in the frame named by ``frame``
    (a code into :attr:`EntityTable.frame_names`); ``cov21`` is the packed 6x6 covariance."""

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


class EntityTable:
    """Every entity frame in RAM, its current state columns and its pending long-term rows.

    ``classes`` is the KD's class library (class pointers are checked against it), ``stm`` and
    ``immediate`` the KD's short-term memory and this cycle, which ingest feeds."""

    def __init__(
        self,
        config: KDConfig,
        classes: ClassLibrary,
        stm: ShortTermMemory,
        immediate: ImmediateExperience,
    ) -> None:
        self.config = config
        self.classes = classes
        self.stm = stm
        self.immediate = immediate
        self.cols = EntityColumns()
        self._frames: list[EntityFrame | None] = []
        self._slot: dict[int, int] = {}
        self._free: list[int] = []
        self._sorted: tuple[np.ndarray, np.ndarray] | None = None
        self._frame_names: list[str] = []
        self._frame_code: dict[str, int] = {}
        self._class_code: dict[str, int] = {}
        self._grid: dict[int, GridIndex] = {}
        self._pending: list[StateColumns] = []  # state rows of long-term entities to write

    def __contains__(self, entity_id: object) -> bool:
        return entity_id in self._slot

    def __len__(self) -> int:
        return len(self._slot)

    def tols(self) -> dict[str, float]:
        return {"cov_tol": self.config.covariance_tol, "quat_tol": self.config.quaternion_tol}

    # ---------------------------------------------------------------- frames

    def add(
        self, name: str, level: Level | int, fields: dict[str, Any], take_id: TakeId
    ) -> EntityFrame:
        """Make an entity frame (fields as :class:`EntityFrame`; ``id`` optional) and add it;
        the id is taken only once the frame passed its checks."""
        frame_id = fields.pop("id", None)
        if "created_ns" not in fields and self.immediate.t_ns is not None:
            fields["created_ns"] = self.immediate.t_ns
        probe = coerce(EntityFrame(id=0, name=name, level=Level(level), **fields))
        where = new_where("entity", frame_id, name)
        check_entity(probe, **self.tols(), where=where)
        self._check_classes(probe, where)
        f = dataclasses.replace(probe, id=take_id(frame_id, f"new entity {name!r}"))
        self.put(f, ltm=False)
        return f

    def insert(self, frame: EntityFrame, take_id: TakeId) -> EntityFrame:
        """Add a complete frame with its own id (which must be free)."""
        check_entity(frame, **self.tols())
        frame = coerce(frame)
        self._check_classes(frame, f"entity {frame.id}")
        take_id(frame.id, f"entity {frame.id} ({frame.name!r})")
        self.put(frame, ltm=False)
        return frame

    def get(self, entity_id: int) -> EntityFrame:
        """The entity frame ``entity_id`` (its ``state`` is the latest)."""
        slot = self._slot.get(entity_id)
        if slot is None:
            raise KDError(f"entity {entity_id!r}: unknown id")
        if self.cols.stale[slot]:
            self._materialize(slot)
        return self._frames[slot]  # type: ignore[return-value]

    def frames(self) -> Iterator[EntityFrame]:
        """Every entity frame in RAM, in slot order."""
        for i in self._slot.values():
            yield self.get(int(self.cols.id[i]))

    def ids(self) -> np.ndarray:
        """(N,) int64 ids of the entities in RAM, sorted."""
        return self._sorted_ids()[0].copy()

    def update(self, entity_id: int, changes: dict[str, Any]) -> EntityFrame:
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
        check_entity(new, **self.tols(), where=where, states=not same, old=old)
        new = coerce(new)
        self._check_classes(new, where)
        slot = self._slot[entity_id]
        self._frames[slot] = new
        self._set_keys(slot, new)
        return new

    def observe(self, entity_id: int, state: State) -> EntityFrame:
        """Add one state to an entity's history (see :meth:`ingest`)."""
        f = self.get(entity_id)
        check_state(state, f"entity {entity_id} ({f.name!r})", **self.tols())
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
        check_expectations(queue, old.state, f"entity {entity_id} ({old.name!r})", **self.tols())
        new = dataclasses.replace(old, expectations=queue)
        slot = self._slot[entity_id]
        self._frames[slot] = new
        self.cols.exp_t0[slot] = queue[0].t_ns if queue else NO_EXPECTATION
        self.cols.dirty[slot] = True
        return new

    def found_specific_class(self, entity_id: int) -> ClassPrototype:
        """Found a specific class from a confirmed entity and point the entity at it."""
        proto = self.classes.found_specific(self.get(entity_id))
        self.update(entity_id, {"specific_class": proto.name})
        return proto

    def class_lineage(self, entity_id: int) -> list[str]:
        """The entity's most specific class and its is_a ancestors, most specific first."""
        name = self.get(entity_id).most_specific_class
        return [] if name is None else self.classes.lineage(name)

    # ---------------------------------------------------------------- batch ingest

    def ingest(self, batch: StateBatch) -> int:
        """Add a batch of state updates (see :meth:`KnowledgeDatabase.ingest`); rows added."""
        where = f"state batch in frame {batch.frame!r}"
        c = check_batch(batch, where, **self.tols())
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
        before = c.t_ns[head] <= self.cols.t_ns[slots[head]]
        if before.any():
            i = int(head[np.flatnonzero(before)[0]])
            raise KDError(
                f"{where}: entity {int(c.entity_id[i])}: t_ns={int(c.t_ns[i])} goes back from "
                f"its current state at t_ns={int(self.cols.t_ns[slots[i]])}"
            )
        # -- checked: from here on nothing raises
        last = order[np.r_[e[1:] != e[:-1], True]]
        self._set_state_columns(slots[last], c.take(last))
        self._drop_overtaken(slots[last], c.t_ns[last])
        self._append_history(c, slots)
        in_ltm = self.cols.ltm[slots]
        if in_ltm.all():
            self._pending.append(c)
        elif in_ltm.any():
            self._pending.append(c.take(in_ltm))
        self.immediate.note(e[first])
        return len(c)

    def _set_state_columns(self, slots: np.ndarray, c: StateColumns) -> None:
        cols = self.cols
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
        over = np.flatnonzero(self.cols.exp_t0[slots] <= t_ns)
        for slot, t in zip(slots[over].tolist(), t_ns[over].tolist(), strict=True):
            f = self._frames[slot]
            assert f is not None
            keep = tuple(s for s in f.expectations if s.t_ns > t)
            self._frames[slot] = dataclasses.replace(f, expectations=keep)
            self.cols.exp_t0[slot] = keep[0].t_ns if keep else NO_EXPECTATION

    def _append_history(self, c: StateColumns, slots: np.ndarray) -> None:
        nodes = self.config.memory.node_of_sp_level
        levels = self.cols.level[slots]
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
        cols = self.cols
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

    def put(self, f: EntityFrame, ltm: bool) -> None:
        """Place a checked frame in a slot (``ltm``: recalled from long-term memory)."""
        cols = self.cols
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
        cols = self.cols
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

    def remove(self, entity_id: int) -> None:
        """Forget the entity (its pointers are the relation graph's to drop)."""
        slot = self._slot.pop(entity_id)
        self._frames[slot] = None
        self.cols.alive[slot] = False
        self.cols.t_ns[slot] = NO_TIME
        self._free.append(slot)
        self._sorted = None
        self._grid.clear()

    def _sorted_ids(self) -> tuple[np.ndarray, np.ndarray]:
        if self._sorted is None:
            slots = np.fromiter(self._slot.values(), np.int64, len(self._slot))
            ids = self.cols.id[slots]
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

    # ---------------------------------------------------------------- memory tiers

    def history(self, entity_id: int) -> list[State]:
        """The entity's short-term memory queue: remembered past states, oldest first."""
        f = self.get(entity_id)
        node = self.config.memory.node_of_sp_level[int(f.level)]
        states = self.stm.history[node].states_of(entity_id)
        for name, h in self.stm.history.items():  # after a level change
            if name != node:
                states += h.states_of(entity_id)
        return sorted(states, key=lambda s: s.t_ns)

    def as_of(self, t_ns: int, stored: list[StateColumns] | None = None) -> dict[int, State]:
        """State of every entity in RAM at ``t_ns`` from short-term memory and, if given, the
        long-term rows ``stored`` (each entity's latest state at or before ``t_ns``)."""
        out: dict[int, State] = {}
        sources = [h.as_of(t_ns) for h in self.stm.history.values()]
        if stored is not None:
            sources.append({int(c.entity_id[i]): c.state(i) for c in stored for i in range(len(c))})
        for states in sources:
            for k, s in states.items():
                if k in self._slot and (k not in out or s.t_ns > out[k].t_ns):
                    out[k] = s
        return out

    def stale(self, t_now_ns: int) -> list[int]:
        """Ids of the short-term entities whose last news (state or making) is older than
        their level's horizon at ``t_now_ns`` (4.4.11: forgettable unless attended)."""
        cols, n = self.cols, self.cols.n
        horizon = np.array([0, *(self.config.memory.horizon_ns(lv) for lv in range(1, 6))])
        t_last = np.maximum(cols.t_ns[:n], cols.created_ns[:n])
        stale = cols.alive[:n] & ~cols.ltm[:n] & (t_last < t_now_ns - horizon[cols.level[:n]])
        return cols.id[np.flatnonzero(stale)].tolist()

    # ---------------------------------------------------------------- long-term memory

    def in_ltm(self, entity_id: int) -> bool:
        return bool(self.cols.ltm[self._slot[entity_id]])

    def promote(self, rule: PromotionRule) -> np.ndarray:
        """Move the entities ``rule`` admits into long-term memory (in RAM; the next flush
        writes them, with their short-term histories). Returns their ids."""
        cols, n = self.cols, self.cols.n
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
        return new_ids

    def collect(self) -> tuple[list[EntityFrame], dict[str, pa.Array], list[StateColumns]]:
        """What the next flush writes of entities: changed long-term frames, their current
        states (Arrow columns) and the pending state rows."""
        cols, n = self.cols, self.cols.n
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
        frames = [self._frames[s] for s in write_slots]
        return frames, entity_states, [c for c in self._pending if len(c)]  # type: ignore[return-value]

    def written(self) -> None:
        """The collected rows are on disk."""
        self.cols.dirty[: self.cols.n] = False
        self._pending = []

    # ---------------------------------------------------------------- queries

    def region(
        self,
        region: Region,
        classes: Iterable[str] | None = None,
        statuses: Iterable[Status | str] | None = None,
        levels: Iterable[int] | None = None,
        min_confidence: float = 0.0,
        poses: dict[str, np.ndarray] | None = None,
    ) -> np.ndarray:
        """Ids (sorted int64) of entities in ``region`` passing the filters (see
        :meth:`KnowledgeDatabase.region`)."""
        check_region(region)
        frames = {region.frame: None, **(poses or {})}
        found = [self._region_in(region, name, T) for name, T in frames.items()]
        cand = np.concatenate(found) if found else np.zeros(0, np.int64)
        cols = self.cols
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
        cols = self.cols
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

    def current_columns(self) -> dict[str, np.ndarray]:
        """Copies of every live entity's current state and filter keys (see
        :meth:`KnowledgeDatabase.current_columns`)."""
        c, n = self.cols, self.cols.n
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


def new_where(kind: str, frame_id: int | None, name: str) -> str:
    """How a message names a frame being made (``kind``: entity or event)."""
    return f"new {kind} {name!r}" if frame_id is None else f"{kind} {frame_id} ({name!r})"


def coerce(f: EntityFrame) -> EntityFrame:
    """Enum fields as enums (callers may pass ``"confirmed"`` or ``4``); checked before."""
    if type(f.status) is Status and type(f.level) is Level:
        return f
    return dataclasses.replace(f, status=Status(f.status), level=Level(f.level))

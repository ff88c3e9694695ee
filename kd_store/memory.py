"""Short-term memory and immediate experience (reference 001, section 4.4.11).

Immediate experience is this cycle: the frames observed since ``begin_cycle``. Short-term
memory keeps, per node level, the recent state history of its entities (the short-term
memory queue of every entity frame of Figure 18) as far back as the level plans ahead
(4.4.10), plus the entities-of-attention list. Histories are column chunks, so a batch of a
million updates is appended without per-row Python.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np

from kd_store.errors import KDError
from kd_store.frames import State
from kd_store.states import StateColumns, concat


class StateHistory:
    """State rows of one node level, oldest chunks first; each chunk is time-checked already."""

    def __init__(self, horizon_ns: int) -> None:
        self.horizon_ns = int(horizon_ns)
        self.chunks: list[StateColumns] = []

    def __len__(self) -> int:
        return sum(len(c) for c in self.chunks)

    def append(self, chunk: StateColumns) -> None:
        if len(chunk):
            self.chunks.append(chunk)

    def trim(self, t_now_ns: int) -> None:
        """Forget rows older than ``t_now_ns - horizon_ns``."""
        cutoff = t_now_ns - self.horizon_ns
        kept = []
        for c in self.chunks:
            if c.t_ns.min() >= cutoff:
                kept.append(c)
            elif c.t_ns.max() >= cutoff:
                kept.append(c.take(c.t_ns >= cutoff))
        self.chunks = kept
        if len(self.chunks) > 64:  # keep chunk lists short for as-of queries
            self.chunks = concat(self.chunks)

    def drop(self, entity_ids: np.ndarray) -> None:
        """Forget every row of ``entity_ids``."""
        if len(entity_ids) == 0:
            return
        kept = []
        for c in self.chunks:
            gone = np.isin(c.entity_id, entity_ids)
            if gone.any():  # a chunk without them stays as it is (no copy)
                c = c.take(~gone)
            if len(c):
                kept.append(c)
        self.chunks = kept

    def rows_of(self, entity_ids: np.ndarray) -> list[StateColumns]:
        """The rows of ``entity_ids`` (any order), one list entry per non-empty chunk."""
        if len(entity_ids) == 0 or not self.chunks:
            return []
        # one membership test over every chunk's ids: a history holds dozens of small chunks
        # (one a sweep), and a test per chunk costs more in calls than in comparisons
        sizes = np.array([len(c.entity_id) for c in self.chunks])
        all_ids = np.concatenate([c.entity_id for c in self.chunks])
        hit = np.flatnonzero(np.isin(all_ids, entity_ids))
        if not hit.size:
            return []
        starts = np.concatenate([[0], np.cumsum(sizes)])
        which = np.searchsorted(starts, hit, side="right") - 1
        out = []
        for k in np.unique(which).tolist():
            out.append(self.chunks[k].take(hit[which == k] - starts[k]))
        return out

    def states_of(self, entity_id: int) -> list[State]:
        """One entity's remembered states, oldest first."""
        rows = [
            (int(c.t_ns[i]), c, int(i))
            for c in self.chunks
            for i in np.flatnonzero(c.entity_id == entity_id)
        ]
        rows.sort(key=lambda r: r[0])
        return [c.state(i) for _, c, i in rows]

    def as_of(self, t_ns: int) -> dict[int, State]:
        """For each entity with a row at or before ``t_ns``, its latest such state."""
        ids, ts, chunk_i, row_i = [], [], [], []
        for k, c in enumerate(self.chunks):
            rows = np.flatnonzero(c.t_ns <= t_ns)
            ids.append(c.entity_id[rows])
            ts.append(c.t_ns[rows])
            chunk_i.append(np.full(rows.shape, k))
            row_i.append(rows)
        if not ids:
            return {}
        eid, t = np.concatenate(ids), np.concatenate(ts)
        ci, ri = np.concatenate(chunk_i), np.concatenate(row_i)
        order = np.lexsort((t, eid))
        last = order[np.r_[eid[order][1:] != eid[order][:-1], True]] if len(order) else order
        return {int(eid[j]): self.chunks[int(ci[j])].state(int(ri[j])) for j in last}


class ShortTermMemory:
    """Per node level: a :class:`StateHistory` and an entities-of-attention list."""

    def __init__(self, horizons_ns: dict[str, int]) -> None:
        self.history = {name: StateHistory(h) for name, h in horizons_ns.items()}
        self.attention: dict[str, list[int]] = {name: [] for name in horizons_ns}

    def trim(self, t_now_ns: int) -> None:
        for h in self.history.values():
            h.trim(t_now_ns)

    def drop(self, entity_ids: np.ndarray) -> None:
        """Forget every row of ``entity_ids`` at every level."""
        for h in self.history.values():
            h.drop(entity_ids)

    def set_attention(
        self, node: str, entity_ids: Iterable[int], known: Callable[[int], bool]
    ) -> None:
        """Set the entities-of-attention list of a node level (``known(id)``: the entity is
        in the KD)."""
        if node not in self.attention:
            raise KDError(f"attention: unknown node level {node!r} (have {sorted(self.attention)})")
        ids = [int(i) for i in entity_ids]
        for i in ids:
            if not known(i):
                raise KDError(f"attention list of {node!r}: entity {i} is not in the KD")
        self.attention[node] = ids

    def attended(self) -> set[int]:
        return {i for ids in self.attention.values() for i in ids}


class ImmediateExperience:
    """This cycle: its time and the frames observed or made in it."""

    def __init__(self) -> None:
        self.t_ns: int | None = None
        self._ids: list[np.ndarray] = []

    def begin(self, t_ns: int) -> None:
        self.t_ns = int(t_ns)
        self._ids = []

    def note(self, ids: np.ndarray) -> None:
        self._ids.append(np.asarray(ids, dtype=np.int64))

    def ids(self) -> np.ndarray:
        """Sorted unique ids observed this cycle."""
        if not self._ids:
            return np.zeros(0, dtype=np.int64)
        return np.unique(np.concatenate(self._ids))

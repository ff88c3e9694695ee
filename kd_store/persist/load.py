"""Reading a KD file back: what :func:`kd_store.open` loads (:class:`Stored`: a run's frames,
events, relations, and the classes), and the long-term state histories, which stay on disk
until asked for (times int64 ns of log time, states in the frame each row names).
"""

from __future__ import annotations

from dataclasses import dataclass

import duckdb
import pyarrow as pa

from kd_store.classes import ClassPrototype
from kd_store.frames import EntityFrame, EventFrame, State
from kd_store.persist.arrow import (
    classes_from_arrow,
    entities_from_arrow,
    events_from_arrow,
    expectations_from_arrow,
    relations_from_arrow,
)
from kd_store.relations import Relation
from kd_store.states import StateColumns


@dataclass(slots=True)
class Stored:
    """What a KD file holds, as frames (state histories stay on disk)."""

    entities: list[EntityFrame]
    events: list[EventFrame]
    relations: list[Relation]
    classes: list[ClassPrototype]
    next_id: int


def read(con: duckdb.DuckDBPyConnection, run_id: int | None = None) -> Stored:
    """Run ``run_id``'s frames, events and relations (every run's when None), and the classes
    (shared by all runs)."""

    def table(name: str, order: str = "") -> pa.Table:
        where = "" if run_id is None else f" WHERE run_id = {int(run_id)}"
        return con.sql(f"SELECT * FROM {name}{where}{order}").to_arrow_table()

    exp = expectations_from_arrow(table("entity_expectation_rows"))
    rows = con.execute("SELECT value FROM kd_meta WHERE key = 'next_id'").fetchall()
    return Stored(
        entities=entities_from_arrow(table("entity_frames", " ORDER BY id"), exp),
        events=events_from_arrow(table("event_frames", " ORDER BY id")),
        relations=relations_from_arrow(table("relation_rows")),
        classes=classes_from_arrow(con.sql("SELECT * FROM class_prototypes").to_arrow_table()),
        next_id=int(rows[0][0]) if rows else 0,
    )


def read_states(con: duckdb.DuckDBPyConnection, entity_id: int) -> list[State]:
    """One entity's long-term state history, oldest first."""
    t = con.sql(
        "SELECT * FROM entity_state_rows WHERE entity_id = $1 ORDER BY t_ns", params=[entity_id]
    ).to_arrow_table()
    states = [c.state(i) for c in StateColumns.from_arrow(t) for i in range(len(c))]
    return sorted(states, key=lambda s: s.t_ns)


def read_states_as_of(con: duckdb.DuckDBPyConnection, t_ns: int) -> list[StateColumns]:
    """Each entity's latest long-term state at or before ``t_ns`` (the
    ``entity_states_as_of`` macro of every run in the file)."""
    table = con.sql("SELECT * FROM entity_states_as_of($1)", params=[int(t_ns)]).to_arrow_table()
    return StateColumns.from_arrow(table)

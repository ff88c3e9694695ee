"""KD frames as Arrow tables and back: the rows of ``entity_frames``,
``entity_expectation_rows``, ``event_frames``, ``relation_rows`` and ``class_prototypes``.
No DuckDB here: :mod:`kd_store.persist.flush` writes these tables, :mod:`kd_store.persist.load`
reads them.

A state's columns are those of :class:`kd_store.frames.State`, in the frame its ``frame``
column names (``world`` for the node's entities): ``t_ns`` int64 ns of log time, position
``x, y, z`` m, orientation quaternion ``qx, qy, qz, qw``, velocity ``vx, vy, vz`` m/s,
``cov_pv`` the 6x6 position-velocity covariance packed as its 21 upper-triangle values (m^2,
m^2/s, m^2/s^2), ``var_rpy`` the orientation variances (rad^2). A frame without a state has
them all null.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from kd_store.classes import ClassKind, ClassPrototype
from kd_store.covariance import unpack_covariance
from kd_store.frames import (
    ATTRIBUTE_FIELDS,
    VALUE_FIELDS,
    Attribute,
    EntityFrame,
    EventFrame,
    Level,
    State,
    Status,
    Value,
)
from kd_store.relations import Relation, RelationKind
from kd_store.states import StateColumns

_ATTR = pa.struct([(k, pa.float64()) for k in ATTRIBUTE_FIELDS])
_CELL = pa.struct([("map_level", pa.int32()), ("col", pa.int64()), ("row", pa.int64())])
_STATE_COLS = ("x", "y", "z", "qx", "qy", "qz", "qw", "vx", "vy", "vz")


def _state_lists(states: list[State | None]) -> dict[str, pa.Array]:
    """Nullable state columns of the ``entity_frames`` table."""
    cols: dict[str, list] = {k: [] for k in ("t_ns", "frame", *_STATE_COLS, "cov_pv", "var_rpy")}
    for s in states:
        if s is None:
            for v in cols.values():
                v.append(None)
            continue
        cols["t_ns"].append(s.t_ns)
        cols["frame"].append(s.frame)
        vals = (*s.position_xyz, *s.orientation_xyzw, *s.velocity_xyz)
        for k, v in zip(_STATE_COLS, vals, strict=True):
            cols[k].append(float(v))
        cols["cov_pv"].append(s.covariance_packed.tolist())
        cols["var_rpy"].append(s.orientation_var_rpy.tolist())
    out = {k: pa.array(v, type=pa.float64()) for k, v in cols.items() if k in _STATE_COLS}
    out["t_ns"] = pa.array(cols["t_ns"], type=pa.int64())
    out["frame"] = pa.array(cols["frame"], type=pa.string())
    out["cov_pv"] = pa.array(cols["cov_pv"], type=pa.list_(pa.float64(), 21))
    out["var_rpy"] = pa.array(cols["var_rpy"], type=pa.list_(pa.float64(), 3))
    return out


def current_states_to_arrow(
    t_ns: np.ndarray,
    frame: list[str | None],
    pos: np.ndarray,
    quat: np.ndarray,
    vel: np.ndarray,
    cov21: np.ndarray,
    var_rpy: np.ndarray,
) -> dict[str, pa.Array]:
    """Nullable state columns of ``entity_frames`` straight from arrays (N rows; a row whose
    ``frame`` is None has no state)."""
    none = np.array([f is None for f in frame], dtype=bool)
    n = len(frame)

    def col(a: np.ndarray) -> pa.Array:
        return pa.array(np.ascontiguousarray(a), mask=none)

    def fixed(a: np.ndarray, k: int) -> pa.Array:
        values = pa.array(np.ascontiguousarray(a).reshape(-1))
        return pa.FixedSizeListArray.from_arrays(values, k, mask=pa.array(none))

    vals = np.concatenate([pos, quat, vel], axis=1).reshape(n, 10)
    out = {k: col(vals[:, i]) for i, k in enumerate(_STATE_COLS)}
    out["t_ns"] = col(t_ns.astype(np.int64))
    out["frame"] = pa.array(frame, type=pa.string())
    out["cov_pv"] = fixed(cov21, 21)
    out["var_rpy"] = fixed(var_rpy, 3)
    return out


def entities_to_arrow(
    frames: list[EntityFrame], states: dict[str, pa.Array] | None = None
) -> pa.Table:
    """``entity_frames`` rows; ``states`` (from :func:`current_states_to_arrow`) replaces the
    frames' own ``state`` fields when given."""
    cols: dict[str, pa.Array | list] = {
        "id": pa.array([f.id for f in frames], type=pa.int64()),
        "name": [f.name for f in frames],
        "name_uncertainty": pa.array([f.name_uncertainty for f in frames], type=pa.float64()),
        "level": pa.array([int(f.level) for f in frames], type=pa.int8()),
        "status": [f.status.value for f in frames],
        "confidence": pa.array([f.confidence for f in frames], type=pa.float64()),
        "generic_classes": pa.array(
            [list(f.generic_classes) for f in frames], pa.list_(pa.string())
        ),
        "specific_class": pa.array([f.specific_class for f in frames], type=pa.string()),
    }
    for k in VALUE_FIELDS:
        cols[k] = pa.array([float(getattr(f.value, k)) for f in frames], type=pa.float64())
    cols["images"] = pa.array([list(f.images) for f in frames], type=pa.list_(pa.string()))
    cols["map_cells"] = _cells_array(frames)
    cols["attributes"] = _attributes_array(frames)
    cols["created_ns"] = pa.array([f.created_ns for f in frames], type=pa.int64())
    cols["noteworthy"] = pa.array([f.noteworthy for f in frames], type=pa.bool_())
    cols.update(states if states is not None else _state_lists([f.state for f in frames]))
    return pa.table(cols)


def _offsets(counts: list[int]) -> pa.Array:
    """int32 list offsets of lists of ``counts`` items."""
    out = np.zeros(len(counts) + 1, dtype=np.int32)
    np.cumsum(counts, out=out[1:])
    return pa.array(out)


def _cells_array(frames: list[EntityFrame]) -> pa.Array:
    """``map_cells`` of ``frames`` as one list-of-struct array, built from flat columns: a
    frame is written at every flush (and every cycle while a live node serves SQL), and Arrow
    converts nested Python dicts one by one."""
    cells = [c for f in frames for c in f.map_cells]
    flat = np.array(cells, dtype=np.int64).reshape(-1, 3)
    values = pa.StructArray.from_arrays(
        [pa.array(flat[:, 0].astype(np.int32)), pa.array(flat[:, 1]), pa.array(flat[:, 2])],
        fields=list(_CELL),
    )
    return pa.ListArray.from_arrays(_offsets([len(f.map_cells) for f in frames]), values)


def _attributes_array(frames: list[EntityFrame]) -> pa.Array:
    """``attributes`` of ``frames`` as one map array (name -> the six values of
    :data:`~kd_store.frames.ATTRIBUTE_FIELDS`), built from flat columns as
    :func:`_cells_array`."""
    items = [(k, a) for f in frames for k, a in f.attributes.items()]
    values = pa.StructArray.from_arrays(
        [
            pa.array([float(getattr(a, n)) for _, a in items], pa.float64())
            for n in ATTRIBUTE_FIELDS
        ],
        fields=list(_ATTR),
    )
    keys = pa.array([k for k, _ in items], pa.string())
    return pa.MapArray.from_arrays(_offsets([len(f.attributes) for f in frames]), keys, values)


def _state_from_row(r: dict) -> State | None:
    if r["t_ns"] is None:
        return None
    cov = unpack_covariance(np.array([r["cov_pv"]], dtype=np.float64))[0]
    return State(
        int(r["t_ns"]),
        r["frame"],
        np.array([r["x"], r["y"], r["z"]], dtype=np.float64),
        np.array([r["qx"], r["qy"], r["qz"], r["qw"]], dtype=np.float64),
        np.array([r["vx"], r["vy"], r["vz"]], dtype=np.float64),
        cov,
        np.array(r["var_rpy"], dtype=np.float64),
    )


def entities_from_arrow(
    table: pa.Table, expectations: dict[int, tuple[State, ...]] | None = None
) -> list[EntityFrame]:
    expectations = expectations or {}
    out = []
    for r in table.to_pylist():
        out.append(
            EntityFrame(
                id=int(r["id"]),
                name=r["name"],
                level=Level(r["level"]),
                status=Status(r["status"]),
                confidence=r["confidence"],
                name_uncertainty=r["name_uncertainty"],
                attributes={k: Attribute(**v) for k, v in r["attributes"]},
                state=_state_from_row(r),
                expectations=expectations.get(int(r["id"]), ()),
                generic_classes=tuple(r["generic_classes"]),
                specific_class=r["specific_class"],
                value=Value(**{k: r[k] for k in VALUE_FIELDS}),
                images=tuple(r["images"]),
                map_cells=tuple((c["map_level"], c["col"], c["row"]) for c in r["map_cells"]),
                created_ns=int(r["created_ns"]),
                noteworthy=bool(r["noteworthy"]),
            )
        )
    return out


def expectations_to_arrow(frames: list[EntityFrame]) -> pa.Table:
    ids = [f.id for f in frames for _ in f.expectations]
    states = [s for f in frames for s in f.expectations]
    chunks = StateColumns.from_states(ids, states)
    if not chunks:
        return StateColumns(
            np.zeros(0, np.int64), np.zeros(0, np.int64), "", np.zeros((0, 3)), np.zeros((0, 4)),
            np.zeros((0, 3)), np.zeros((0, 21)), np.zeros((0, 3)),
        ).to_arrow()  # fmt: skip
    return pa.concat_tables([c.to_arrow() for c in chunks])


def expectations_from_arrow(table: pa.Table) -> dict[int, tuple[State, ...]]:
    out: dict[int, list[State]] = {}
    for c in StateColumns.from_arrow(table):
        for i in range(len(c)):
            out.setdefault(int(c.entity_id[i]), []).append(c.state(i))
    return {k: tuple(sorted(v, key=lambda s: s.t_ns)) for k, v in out.items()}


def events_to_arrow(events: list[EventFrame]) -> pa.Table:
    cols: dict[str, pa.Array] = {
        "id": pa.array([e.id for e in events], type=pa.int64()),
        "name": pa.array([e.name for e in events], type=pa.string()),
        "class_name": pa.array([e.class_name for e in events], type=pa.string()),
        "t_start_ns": pa.array([e.t_start_ns for e in events], type=pa.int64()),
        "t_end_ns": pa.array([e.t_end_ns for e in events], type=pa.int64()),
        "attributes": pa.array(
            [[(k, float(v)) for k, v in e.attributes.items()] for e in events],
            type=pa.map_(pa.string(), pa.float64()),
        ),
        "level": pa.array([e.level for e in events], type=pa.int8()),
        "confidence": pa.array([e.confidence for e in events], type=pa.float64()),
        "name_uncertainty": pa.array([e.name_uncertainty for e in events], type=pa.float64()),
    }
    for k in VALUE_FIELDS:
        cols[k] = pa.array([float(getattr(e.value, k)) for e in events], type=pa.float64())
    cols["noteworthy"] = pa.array([e.noteworthy for e in events], type=pa.bool_())
    return pa.table(cols)


def events_from_arrow(table: pa.Table) -> list[EventFrame]:
    return [
        EventFrame(
            id=int(r["id"]),
            name=r["name"],
            class_name=r["class_name"],
            t_start_ns=int(r["t_start_ns"]),
            t_end_ns=None if r["t_end_ns"] is None else int(r["t_end_ns"]),
            attributes=dict(r["attributes"]),
            level=int(r["level"]),
            confidence=r["confidence"],
            name_uncertainty=r["name_uncertainty"],
            value=Value(**{k: r[k] for k in VALUE_FIELDS}),
            noteworthy=bool(r["noteworthy"]),
        )
        for r in table.to_pylist()
    ]


def relations_to_arrow(rels: list[Relation]) -> pa.Table:
    return pa.table(
        {
            "src_id": pa.array([r.src for r in rels], type=pa.int64()),
            "kind": pa.array([r.kind.value for r in rels], type=pa.string()),
            "dst_id": pa.array([r.dst for r in rels], type=pa.int64()),
            "t_from_ns": pa.array([r.t_from_ns for r in rels], type=pa.int64()),
            "t_to_ns": pa.array([r.t_to_ns for r in rels], type=pa.int64()),
        }
    )


def relations_from_arrow(table: pa.Table) -> list[Relation]:
    return [
        Relation(r["src_id"], RelationKind(r["kind"]), r["dst_id"], r["t_from_ns"], r["t_to_ns"])
        for r in table.to_pylist()
    ]


def classes_to_arrow(protos: list[ClassPrototype]) -> pa.Table:
    m = pa.map_(pa.string(), pa.float64())
    cols: dict[str, pa.Array] = {
        "name": pa.array([p.name for p in protos], type=pa.string()),
        "kind": pa.array([p.kind.value for p in protos], type=pa.string()),
        "level": pa.array([int(p.level) for p in protos], type=pa.int8()),
        "is_a": pa.array([p.is_a for p in protos], type=pa.string()),
        "attributes": pa.array([list(p.attributes.items()) for p in protos], type=m),
        "weights": pa.array([list(p.weights.items()) for p in protos], type=m),
    }
    for k in VALUE_FIELDS:
        cols[k] = pa.array([float(getattr(p.value, k)) for p in protos], type=pa.float64())
    cols["fitted"] = pa.array([p.fitted for p in protos], type=pa.bool_())
    return pa.table(cols)


def classes_from_arrow(table: pa.Table) -> list[ClassPrototype]:
    return [
        ClassPrototype(
            name=r["name"],
            kind=ClassKind(r["kind"]),
            level=Level(r["level"]),
            is_a=r["is_a"],
            attributes=dict(r["attributes"]),
            weights=dict(r["weights"]),
            value=Value(**{k: r[k] for k in VALUE_FIELDS}),
            fitted=bool(r.get("fitted") or False),  # files before schema version 4: none
        )
        for r in table.to_pylist()
    ]

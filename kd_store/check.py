"""Integrity check of a KD file: do its rows hang together?

:func:`check_file` opens a KD file read-only (the KD's locked-down DuckDB settings, so the
check can neither change nor lock it for writing) and looks for what the engine never writes
but a killed process, a hand edit or a bug could leave behind:

- ``missing_table``: a table the file's schema version should have is absent;
- ``duplicate_entity_id`` / ``duplicate_event_id``: two frames share one address;
- ``orphan_state`` / ``orphan_expectation``: a state (expectation) row whose ``entity_id`` has
  no entity frame;
- ``dangling_relation``: a relation whose ``src_id`` or ``dst_id`` is neither an entity nor an
  event frame (entities and events share one id space);
- ``event_missing_entity``: an event's ``involves`` pointer to an entity frame that is absent;
- ``nonfinite_position``: a state, expectation or entity frame whose x, y or z (metres) is NaN
  or infinite (an entity frame with no state at all has NULL there, which is allowed);
- ``unknown_run`` (schema version 3 on): rows of a ``run_id`` that ``run_rows`` does not
  record (the ids named are run ids);
- ``run_mismatch``: a state or expectation row in another run than its entity frame, or a
  relation in another run than its source frame (runs have separate world frames).

The result is a typed :class:`KDCheck`; printing it is the command line's job (``wm check``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from kd_store import persist
from kd_store.errors import KDError
from kd_store.query import kd_settings

#: ids named per defect at most (the count is always exact)
MAX_IDS = 20

#: (defect kind, table, SQL selecting the offending ids, what is wrong). Each query returns one
#: column ``id``; the entity/event id space is the union of both frame tables.
_FRAME_IDS = "(SELECT id FROM entity_frames UNION ALL SELECT id FROM event_frames)"
_FINITE = "isfinite(x) AND isfinite(y) AND isfinite(z)"
_CHECKS: tuple[tuple[str, str, str, str], ...] = (
    (
        "duplicate_entity_id", "entity_frames",
        "SELECT id FROM entity_frames GROUP BY id HAVING count(*) > 1",
        "ids shared by two or more entity frames",
    ),
    (
        "duplicate_event_id", "event_frames",
        "SELECT id FROM event_frames GROUP BY id HAVING count(*) > 1",
        "ids shared by two or more event frames",
    ),
    (
        "orphan_state", "entity_state_rows",
        "SELECT DISTINCT entity_id AS id FROM entity_state_rows "
        "WHERE entity_id NOT IN (SELECT id FROM entity_frames)",
        "entity ids with states but no entity frame",
    ),
    (
        "orphan_expectation", "entity_expectation_rows",
        "SELECT DISTINCT entity_id AS id FROM entity_expectation_rows "
        "WHERE entity_id NOT IN (SELECT id FROM entity_frames)",
        "entity ids with expected states but no entity frame",
    ),
    (
        "dangling_relation", "relation_rows",
        f"SELECT DISTINCT src_id AS id FROM relation_rows WHERE src_id NOT IN {_FRAME_IDS} "
        f"UNION SELECT DISTINCT dst_id FROM relation_rows WHERE dst_id NOT IN {_FRAME_IDS}",
        "ids at a relation end (src_id, dst_id) that are no entity or event frame",
    ),
    (
        "event_missing_entity", "relation_rows",
        "SELECT DISTINCT src_id AS id FROM relation_rows WHERE kind = 'involves' "
        "AND src_id IN (SELECT id FROM event_frames) "
        "AND dst_id NOT IN (SELECT id FROM entity_frames)",
        "events 'involving' an entity id with no entity frame",
    ),
    (
        "nonfinite_position", "entity_state_rows",
        f"SELECT DISTINCT entity_id AS id FROM entity_state_rows WHERE NOT ({_FINITE})",
        "entities with a state whose position (x, y, z m) is NaN or infinite",
    ),
    (
        "nonfinite_position", "entity_expectation_rows",
        f"SELECT DISTINCT entity_id AS id FROM entity_expectation_rows WHERE NOT ({_FINITE})",
        "entities with an expected state whose position (x, y, z m) is NaN or infinite",
    ),
    (
        "nonfinite_position", "entity_frames",
        f"SELECT DISTINCT id FROM entity_frames WHERE x IS NOT NULL AND NOT ({_FINITE})",
        "entity frames whose current position (x, y, z m) is NaN or infinite",
    ),
)  # fmt: skip


def _run_checks() -> tuple[tuple[str, str, str, str], ...]:
    """The checks of run ids (schema version 3 on), as :data:`_CHECKS`."""
    unknown = tuple(
        (
            "unknown_run", t,
            f"SELECT DISTINCT run_id AS id FROM {t} "
            "WHERE run_id NOT IN (SELECT run_id FROM run_rows)",
            "run ids with rows here that run_rows does not record",
        )
        for t in persist.RUN_TABLES
    )  # fmt: skip
    mismatch = tuple(
        (
            "run_mismatch", t,
            f"SELECT DISTINCT r.{key} AS id FROM {t} r JOIN {frames} f ON f.id = r.{key} "
            "WHERE r.run_id <> f.run_id",
            f"{what} in another run than their frame",
        )
        for t, key, frames, what in (
            ("entity_state_rows", "entity_id", "entity_frames", "entities with states"),
            ("entity_expectation_rows", "entity_id", "entity_frames", "entities with expectations"),
            ("relation_rows", "src_id", "entity_frames", "entities with relations"),
            ("relation_rows", "src_id", "event_frames", "events with relations"),
        )
    )  # fmt: skip
    return unknown + mismatch


#: the tables the checks read
_NEEDED = frozenset(
    {"entity_frames", "event_frames", "entity_state_rows", "entity_expectation_rows",
     "relation_rows"}
)  # fmt: skip


@dataclass(frozen=True)
class Defect:
    """One kind of defect in one table: how many ids show it, the first :data:`MAX_IDS` of
    them (ascending), and what is wrong in words."""

    kind: str
    table: str
    count: int
    ids: tuple[int, ...]
    what: str

    def text(self) -> str:
        """One line: kind, table, count, ids (``...`` when more than listed)."""
        more = ", ..." if self.count > len(self.ids) else ""
        ids = ", ".join(str(i) for i in self.ids)
        return f"{self.kind} in {self.table}: {self.count} {self.what} (ids {ids}{more})"


@dataclass(frozen=True)
class KDCheck:
    """What :func:`check_file` found: rows per table (tables present only), the file's
    schema version and every defect (empty when the file is sound)."""

    path: str
    schema_version: int
    counts: dict[str, int]
    defects: list[Defect] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.defects


def check_file(path: str | Path) -> KDCheck:
    """Check the KD file ``path`` (module docstring), opened read-only. Raises
    FileNotFoundError when it does not exist and KDError (one line) when it is not a KD file
    or DuckDB cannot open it (another process writing it, say)."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"KD file {p} does not exist")
    try:
        con = persist.connect(p, read_only=True, settings=kd_settings())
    except KDError as e:  # DuckDB's messages can span lines; the CLI prints one
        raise KDError(" ".join(str(e).split())) from None
    try:
        return _check(con, str(p))
    finally:
        con.close()


def _check(con: persist.Connection, where: str) -> KDCheck:
    rows = con.execute("SELECT value FROM kd_meta WHERE key = 'schema_version'").fetchall()
    version = int(rows[0][0]) if rows else 0
    present = {
        r[0] for r in con.execute("SELECT table_name FROM information_schema.tables").fetchall()
    }
    counts = {
        t: int(con.execute(f"SELECT count(*) FROM {t}").fetchall()[0][0])
        for t in persist.TABLES
        if t in present
    }
    defects = [
        Defect("missing_table", t, 1, (), f"table of schema version {version} absent")
        for t in persist.TABLES
        if t not in present and persist.TABLES_SINCE.get(t, 1) <= version
    ]
    if _NEEDED <= present:  # else the missing table is the defect, reported above
        runs = _run_checks() if version >= 3 and "run_rows" in present else ()
        for kind, table, sql, what in (*_CHECKS, *runs):
            defect = _defect(con, kind, table, sql, what)
            if defect is not None:
                defects.append(defect)
    return KDCheck(where, version, counts, defects)


def _defect(con: persist.Connection, kind: str, table: str, sql: str, what: str) -> Defect | None:
    """The defect ``sql`` finds (its ``id`` column), or None when it finds no row."""
    count = int(con.execute(f"SELECT count(*) FROM ({sql})").fetchall()[0][0])
    if not count:
        return None
    ids = con.execute(f"SELECT id FROM ({sql}) ORDER BY id LIMIT {MAX_IDS}").fetchall()
    return Defect(kind, table, count, tuple(int(r[0]) for r in ids), what)

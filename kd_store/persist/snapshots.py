"""Read-only snapshots of a KD file: a byte copy published atomically beside it after a
checkpoint, for other processes to open while the node writes the KD, and the rule for
where one may be published (never over the KD, the log or any file that is no snapshot);
and the cheaper copy of a KD file with its write-ahead log (:func:`copy_with_wal`) that a
live node's server reads SQL from.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import duckdb

from kd_store.errors import KDError
from kd_store.persist.schema import _has_table

#: kd_meta key naming where a KD publishes its snapshots (absolute path). A snapshot is a
#: byte copy of its KD, so it carries the key too: a file whose key names its own path is a
#: snapshot published there, which the next publication may replace.
SNAPSHOT_KEY = "snapshot_path"
_DUCKDB_MAGIC = b"DUCK"  # at byte 8 of every DuckDB file


def snapshot_target(kd_path: str | Path, snapshot_path: str | Path) -> Path:
    """The absolute path a snapshot of the KD file ``kd_path`` may be published at, or a
    KDError saying why not. The rule: ``snapshot_path`` is not the KD (nor its ``.wal``), its
    folder exists, and it either does not exist or is a snapshot published there before (a
    KD file whose ``snapshot_path`` meta key names it); anything else there (another KD, the
    log, any other file) is never replaced."""
    where = f"snapshot {snapshot_path}"
    if str(kd_path) == ":memory:":
        raise KDError(f"{where}: a throwaway KD (':memory:') has no file to publish")
    target, kd = Path(snapshot_path).resolve(), Path(kd_path).resolve()
    if target in (kd, Path(f"{kd}.wal")):
        raise KDError(f"{where}: is the KD file itself; give another path")
    if not target.parent.is_dir():
        raise KDError(f"{where}: folder {target.parent} does not exist")
    if target.is_dir():
        raise KDError(f"{where}: is a folder; give a file name")
    if target.exists() and not _is_snapshot_at(target):
        raise KDError(
            f"{where}: the file exists and is no snapshot published there before; "
            "remove it or give another path"
        )
    return target


def _is_snapshot_at(path: Path) -> bool:
    """``path`` is a DuckDB KD file whose ``snapshot_path`` meta key names ``path``."""
    with path.open("rb") as f:
        if f.read(12)[8:12] != _DUCKDB_MAGIC:
            return False
    try:  # plain DuckDB: the KD's connect would refuse or migrate a file of another version
        con = duckdb.connect(str(path), read_only=True)
    except duckdb.Error:
        return False  # not readable (or another process writes it): not ours to replace
    try:
        if not _has_table(con, "kd_meta"):
            return False
        rows = con.execute("SELECT value FROM kd_meta WHERE key = ?", [SNAPSHOT_KEY]).fetchall()
    except duckdb.Error:
        return False
    finally:
        con.close()
    return bool(rows) and rows[0][0] == str(path)


def mark_snapshot(con: duckdb.DuckDBPyConnection, target: Path) -> None:
    """Record in the KD's meta table that its snapshots go to ``target`` (absolute), in one
    transaction; the snapshots copy it, which is how a later publication recognises them."""
    con.execute("BEGIN TRANSACTION")
    try:
        con.execute("DELETE FROM kd_meta WHERE key = ?", [SNAPSHOT_KEY])
        con.execute("INSERT INTO kd_meta VALUES (?, ?)", [SNAPSHOT_KEY, str(target)])
        con.execute("COMMIT")
    except BaseException:
        con.execute("ROLLBACK")
        raise


def copy_snapshot(kd_path: Path, target: Path) -> None:
    """Copy the checkpointed KD file ``kd_path`` (no write-ahead log left: everything is in
    the file) onto ``target`` atomically: into ``.<name>.partial`` beside it, fsync, then
    ``os.replace``. A reader never sees a half-written file, and one that has the old
    snapshot open keeps its inode. A ``.wal`` beside the target is removed first: read-only
    opens never write one, and a stale one would be replayed into the new snapshot."""
    wal = Path(f"{kd_path}.wal")
    if wal.exists() and wal.stat().st_size:
        raise KDError(f"KD file {kd_path}: write-ahead log not empty after CHECKPOINT")
    partial = target.with_name(f".{target.name}.partial")
    try:
        shutil.copyfile(kd_path, partial)  # overwrites a partial a killed run left
        fd = os.open(partial, os.O_RDONLY)
        try:
            os.fsync(fd)  # the bytes are on disk before the name points at them
        finally:
            os.close(fd)
        Path(f"{target}.wal").unlink(missing_ok=True)
        os.replace(partial, target)
        _fsync_dir(target.parent)
    except OSError as e:
        partial.unlink(missing_ok=True)
        raise KDError(f"snapshot {target}: cannot publish ({e})") from None


def copy_with_wal(kd_path: Path, target: Path) -> tuple[int, int]:
    """Copy the KD file ``kd_path`` and its write-ahead log, as they lie between two commits
    (the caller holds the KD's lock), to ``target`` and ``target.wal``; returns (file bytes,
    log bytes). No CHECKPOINT and no fsync: a read-only open of the pair replays the log into
    its own memory, so the copy costs the writer only the bytes copied, and it is a working
    copy for readers on this host that the next one replaces, not a durable one. ``target``
    must be a new name (a reader may hold the one before open); a ``target.wal`` there is
    removed when the KD has no log, so that it is not replayed into the copy."""
    wal, target_wal = Path(f"{kd_path}.wal"), Path(f"{target}.wal")
    try:
        shutil.copyfile(kd_path, target)
        if wal.exists():
            shutil.copyfile(wal, target_wal)
        else:
            target_wal.unlink(missing_ok=True)
        return target.stat().st_size, target_wal.stat().st_size if wal.exists() else 0
    except OSError as e:
        target.unlink(missing_ok=True)
        target_wal.unlink(missing_ok=True)
        raise KDError(f"KD copy {target}: cannot write it ({e})") from None


def _fsync_dir(folder: Path) -> None:
    """Make a rename in ``folder`` durable (POSIX; a no-op where folders cannot be opened)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)

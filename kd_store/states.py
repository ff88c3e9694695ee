"""Entity states in columns: the batch callers ingest and the chunks short-term memory keeps.

A :class:`StateBatch` is N state updates of many entities in one coordinate frame; the KD
checks it as a whole with numpy (no per-row Python) and keeps it as :class:`StateColumns`
with the covariance packed to its 21 upper-triangle entries (row-major over x, y, z, vx,
vy, vz), the layout of the ``cov_pv`` column on disk.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from kd_store.covariance import FLAT_LO, pack_checked, psd_mask
from kd_store.errors import KDError
from kd_store.frames import State


@dataclass(slots=True)
class StateBatch:
    """N state updates in one coordinate frame ``frame`` (what SP's filters emit per cycle).

    entity_id:            (N,) int64.
    t_ns:                 (N,) int64; per entity strictly increasing and after its last state.
    position_xyz:         (N, 3) float64 m.
    orientation_xyzw:     (N, 4) float64 unit quaternions, or None for identity.
    velocity_xyz:         (N, 3) float64 m/s, or None for zero.
    covariance:           (N, 6, 6) float64 over (x, y, z, vx, vy, vz), or None for zero.
    orientation_var_rpy:  (N, 3) float64 rad^2, or None for zero.
    """

    entity_id: np.ndarray
    t_ns: np.ndarray
    frame: str
    position_xyz: np.ndarray
    orientation_xyzw: np.ndarray | None = None
    velocity_xyz: np.ndarray | None = None
    covariance: np.ndarray | None = None
    orientation_var_rpy: np.ndarray | None = None


@dataclass(slots=True)
class StateColumns:
    """Checked states in columns; one coordinate frame per chunk. Shapes as
    :class:`StateBatch` but every array present and the covariance packed, ``cov21`` (N, 21)."""

    entity_id: np.ndarray
    t_ns: np.ndarray
    frame: str
    position_xyz: np.ndarray
    orientation_xyzw: np.ndarray
    velocity_xyz: np.ndarray
    cov21: np.ndarray
    orientation_var_rpy: np.ndarray

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def take(self, rows: np.ndarray) -> StateColumns:
        """Rows by index or boolean mask."""
        return StateColumns(
            self.entity_id[rows],
            self.t_ns[rows],
            self.frame,
            self.position_xyz[rows],
            self.orientation_xyzw[rows],
            self.velocity_xyz[rows],
            self.cov21[rows],
            self.orientation_var_rpy[rows],
        )

    def state(self, i: int) -> State:
        """Row ``i`` as a :class:`State` (copies, so the chunk can be freed)."""
        v = np.concatenate(
            (
                self.position_xyz[i],
                self.orientation_xyzw[i],
                self.velocity_xyz[i],
                self.cov21[i],
                self.orientation_var_rpy[i],
            )
        )
        return State.from_vector(int(self.t_ns[i]), self.frame, v)

    @staticmethod
    def from_states(entity_ids: list[int], states: list[State]) -> list[StateColumns]:
        """One chunk per coordinate frame from single states."""
        out = []
        for frame in dict.fromkeys(s.frame for s in states):
            idx = [i for i, s in enumerate(states) if s.frame == frame]
            sel = [states[i] for i in idx]
            out.append(
                StateColumns(
                    np.array([entity_ids[i] for i in idx], dtype=np.int64),
                    np.array([s.t_ns for s in sel], dtype=np.int64),
                    frame,
                    np.array([s.position_xyz for s in sel]).reshape(-1, 3),
                    np.array([s.orientation_xyzw for s in sel]).reshape(-1, 4),
                    np.array([s.velocity_xyz for s in sel]).reshape(-1, 3),
                    np.array([s.covariance_packed for s in sel]).reshape(-1, 21),
                    np.array([s.orientation_var_rpy for s in sel]).reshape(-1, 3),
                )
            )
        return out

    def to_arrow(self) -> pa.Table:
        """Rows in the layout of the ``entity_state_rows`` table (see ``schema.sql``)."""
        return rows_to_arrow([self])

    @staticmethod
    def from_arrow(table: pa.Table) -> list[StateColumns]:
        """Inverse of :meth:`to_arrow`; one chunk per frame."""
        out = []
        frames = table.column("frame")  # compared in Arrow: strings to numpy would load pandas
        for frame in frames.unique().to_pylist():  # in order of first appearance
            t = table.filter(pc.equal(frames, frame))

            def col(name: str, t: pa.Table = t) -> np.ndarray:
                return t.column(name).to_numpy()

            def fixed(name: str, k: int, t: pa.Table = t) -> np.ndarray:
                flat = t.column(name).combine_chunks().flatten().to_numpy()
                return flat.reshape(-1, k).astype(np.float64)

            out.append(
                StateColumns(
                    col("entity_id").astype(np.int64),
                    col("t_ns").astype(np.int64),
                    str(frame),
                    np.stack([col("x"), col("y"), col("z")], axis=1),
                    np.stack([col("qx"), col("qy"), col("qz"), col("qw")], axis=1),
                    np.stack([col("vx"), col("vy"), col("vz")], axis=1),
                    fixed("cov_pv", 21),
                    fixed("var_rpy", 3),
                )
            )
        return out


_SCALAR_COLUMNS = (
    ("x", "position_xyz", 0),
    ("y", "position_xyz", 1),
    ("z", "position_xyz", 2),
    ("qx", "orientation_xyzw", 0),
    ("qy", "orientation_xyzw", 1),
    ("qz", "orientation_xyzw", 2),
    ("qw", "orientation_xyzw", 3),
    ("vx", "velocity_xyz", 0),
    ("vy", "velocity_xyz", 1),
    ("vz", "velocity_xyz", 2),
)


def rows_to_arrow(chunks: list[StateColumns]) -> pa.Table:
    """Chunks as one table in the layout of ``entity_state_rows`` (see ``schema.sql``), every
    column a single contiguous Arrow array (DuckDB appends one large chunk fastest).

    Each column is gathered once with numpy from the chunks' columns (contiguous when the
    chunk came from :func:`check_batch`) and handed to Arrow without a further copy; no
    per-chunk tables to concatenate and combine."""

    def cat(arrays: list[np.ndarray]) -> np.ndarray:
        return np.ascontiguousarray(arrays[0]) if len(arrays) == 1 else np.concatenate(arrays)

    def fixed(name: str, k: int) -> pa.Array:
        flat = cat([getattr(c, name) for c in chunks]).reshape(-1)
        return pa.FixedSizeListArray.from_arrays(pa.array(flat), k)

    frames = [_repeated_string(c.frame, len(c)) for c in chunks]
    cols: dict[str, object] = {
        "entity_id": cat([c.entity_id for c in chunks]),
        "t_ns": cat([c.t_ns for c in chunks]),
        "frame": frames[0] if len(frames) == 1 else pa.concat_arrays(frames),
    }
    for col, name, k in _SCALAR_COLUMNS:
        cols[col] = cat([getattr(c, name)[:, k] for c in chunks])
    cols["cov_pv"] = fixed("cov21", 21)
    cols["var_rpy"] = fixed("orientation_var_rpy", 3)
    return pa.table(cols)


def _repeated_string(s: str, n: int) -> pa.Array:
    """Arrow string array of ``n`` copies of ``s``, built from its two buffers (far cheaper
    than casting a dictionary array to string)."""
    data = s.encode()
    offsets = np.arange(n + 1, dtype=np.int32) * len(data)
    return pa.StringArray.from_buffers(n, pa.py_buffer(offsets), pa.py_buffer(data * n))


def _array(a: object, shape_tail: tuple[int, ...], n: int, name: str, where: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.shape != (n, *shape_tail):
        raise KDError(f"{where}: {name} has shape {arr.shape}, expected {(n, *shape_tail)}")
    return arr


def _all_finite(a: np.ndarray) -> bool:
    """Whether every entry is finite. Any NaN or inf makes the sum NaN or inf, so a finite sum
    settles it in one reduction without a boolean temporary; only a sum that is not finite
    (a bad entry, or finite values overflowing) takes the entry-wise test."""
    with np.errstate(over="ignore", invalid="ignore"):
        total = a.sum()
    return bool(np.isfinite(total)) or bool(np.isfinite(a).all())


def _column_copy(a: object | None, k: int, n: int, name: str, where: str) -> np.ndarray:
    """(n, k) float64 copy of ``a`` in column-major order (zeros for None); never a view."""
    out = np.zeros((n, k), order="F")
    if a is not None:
        out[:] = _array(a, (k,), n, name, where)
    return out


def check_batch(
    b: StateBatch, where: str, cov_tol: float = 1e-9, quat_tol: float = 1e-6
) -> StateColumns:
    """Check a batch as a whole and return it as columns (copies, never views of the caller's
    arrays). Refuses NaN/inf, non-unit quaternions, negative variances and covariances that are
    not symmetric positive semidefinite, naming the first bad row's entity and time."""
    eid = np.asarray(b.entity_id)
    t = np.asarray(b.t_ns)
    if eid.ndim != 1 or t.shape != eid.shape:
        raise KDError(f"{where}: entity_id {eid.shape} and t_ns {t.shape} must be equal (N,)")
    if not np.issubdtype(eid.dtype, np.integer) or not np.issubdtype(t.dtype, np.integer):
        raise KDError(f"{where}: entity_id and t_ns must be integer arrays, got {eid.dtype}")
    n = eid.shape[0]
    # the one copy of each caller array, column-major: every column of the chunk is then a
    # contiguous run that to_arrow hands to Arrow without another copy
    pos = _column_copy(b.position_xyz, 3, n, "position_xyz", where)
    quat = _column_copy(b.orientation_xyzw, 4, n, "orientation_xyzw", where)
    if b.orientation_xyzw is None:
        quat[:, 3] = 1.0
    vel = _column_copy(b.velocity_xyz, 3, n, "velocity_xyz", where)
    var = _column_copy(b.orientation_var_rpy, 3, n, "orientation_var_rpy", where)
    if b.covariance is None:
        flat = np.zeros((n, 36))
    else:
        flat = _array(b.covariance, (6, 6), n, "covariance", where).reshape(n, 36)
    cov21, scale, symmetric = pack_checked(flat, cov_tol)  # the covariance's one copy

    def refuse(ok: bool, bad_rows: Callable[[], np.ndarray], what: str, values: np.ndarray) -> None:
        # cheap whole-array test first; per-row work only to name the first bad row
        if ok:
            return
        bad = bad_rows()
        i = int(np.flatnonzero(bad)[0])
        raise KDError(
            f"{where}: entity {int(eid[i])} at t_ns={int(t[i])}: {what}: "
            f"{np.array2string(values[i], precision=6)} (row {i}; "
            f"{int(bad.sum())} bad rows in all)"
        )

    for name, a in (
        ("position_xyz", pos),
        ("orientation_xyzw", quat),
        ("velocity_xyz", vel),
        ("orientation_var_rpy", var),
    ):
        refuse(
            _all_finite(a),
            lambda a=a: ~np.isfinite(a).all(axis=1),
            f"{name} is not finite",
            a,
        )
    refuse(not (var < 0).any(), lambda: (var < 0).any(axis=1), "negative orientation_var_rpy", var)
    # symmetric (NaN-safe) with finite packed entries means all 36 are finite
    cov_finite = _all_finite(cov21) and (symmetric or bool(np.isfinite(flat).all()))
    refuse(
        cov_finite,
        lambda: ~np.isfinite(flat).all(axis=1),
        "covariance is not finite",
        flat.reshape(n, 6, 6),
    )
    bad_norm = np.abs(np.einsum("ij,ij->i", quat, quat) - 1.0) > 2 * quat_tol
    refuse(not bad_norm.any(), lambda: bad_norm, "not a unit quaternion", quat)

    def asym() -> np.ndarray:
        lo = np.take(flat, FLAT_LO, axis=1)
        return (np.abs(cov21 - lo) > (cov_tol * scale)[:, None]).any(axis=1)

    cov = flat.reshape(n, 6, 6)
    refuse(symmetric, asym, "covariance is not symmetric", cov)
    psd = psd_mask(cov21, cov_tol, scale)
    refuse(bool(psd.all()), lambda: ~psd, "covariance is not positive semidefinite", cov)
    return StateColumns(
        eid.astype(np.int64, copy=True),
        t.astype(np.int64, copy=True),
        str(b.frame),
        pos,
        quat,
        vel,
        cov21,
        var,
    )


def concat(chunks: list[StateColumns]) -> list[StateColumns]:
    """Merge chunks of the same frame (keeps one chunk per frame, in first-seen order)."""
    by_frame: dict[str, list[StateColumns]] = {}
    for c in chunks:
        by_frame.setdefault(c.frame, []).append(c)
    out = []
    for frame, cs in by_frame.items():
        if len(cs) == 1:
            out.append(cs[0])
            continue
        out.append(
            StateColumns(
                *(np.concatenate([getattr(c, k) for c in cs]) for k in ("entity_id", "t_ns")),
                frame,
                *(
                    np.concatenate([getattr(c, k) for c in cs])
                    for k in (
                        "position_xyz",
                        "orientation_xyzw",
                        "velocity_xyz",
                        "cov21",
                        "orientation_var_rpy",
                    )
                ),
            )
        )
    return out

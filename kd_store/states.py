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
        n = len(self)

        def fixed(a: np.ndarray, k: int) -> pa.Array:
            return pa.FixedSizeListArray.from_arrays(pa.array(a.reshape(-1)), k)

        p, q, v = self.position_xyz, self.orientation_xyzw, self.velocity_xyz
        return pa.table(
            {
                "entity_id": self.entity_id,
                "t_ns": self.t_ns,
                "frame": pa.DictionaryArray.from_arrays(
                    pa.array(np.zeros(n, dtype=np.int32)), pa.array([self.frame])
                ).cast(pa.string()),
                "x": p[:, 0],
                "y": p[:, 1],
                "z": p[:, 2],
                "qx": q[:, 0],
                "qy": q[:, 1],
                "qz": q[:, 2],
                "qw": q[:, 3],
                "vx": v[:, 0],
                "vy": v[:, 1],
                "vz": v[:, 2],
                "cov_pv": fixed(np.ascontiguousarray(self.cov21), 21),
                "var_rpy": fixed(np.ascontiguousarray(self.orientation_var_rpy), 3),
            }
        )

    @staticmethod
    def from_arrow(table: pa.Table) -> list[StateColumns]:
        """Inverse of :meth:`to_arrow`; one chunk per frame."""
        out = []
        frames = table.column("frame").to_numpy(zero_copy_only=False)
        for frame in dict.fromkeys(frames.tolist()):
            t = table.filter(pa.array(frames == frame))

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


def _array(a: object, shape_tail: tuple[int, ...], n: int, name: str, where: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.shape != (n, *shape_tail):
        raise KDError(f"{where}: {name} has shape {arr.shape}, expected {(n, *shape_tail)}")
    return arr


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
    pos = _array(b.position_xyz, (3,), n, "position_xyz", where)
    quat = (
        np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
        if b.orientation_xyzw is None
        else _array(b.orientation_xyzw, (4,), n, "orientation_xyzw", where)
    )
    vel = np.zeros((n, 3)) if b.velocity_xyz is None else _array(b.velocity_xyz, (3,), n, "", where)
    var = (
        np.zeros((n, 3))
        if b.orientation_var_rpy is None
        else _array(b.orientation_var_rpy, (3,), n, "orientation_var_rpy", where)
    )
    if b.covariance is None:
        cov = np.zeros((n, 6, 6))
    else:
        cov = _array(b.covariance, (6, 6), n, "covariance", where)

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
            bool(np.isfinite(a).all()),
            lambda a=a: ~np.isfinite(a).all(axis=1),
            f"{name} is not finite",
            a,
        )
    refuse(not (var < 0).any(), lambda: (var < 0).any(axis=1), "negative orientation_var_rpy", var)
    flat = cov.reshape(n, 36)
    refuse(
        bool(np.isfinite(flat).all()),
        lambda: ~np.isfinite(flat).all(axis=1),
        "covariance is not finite",
        cov,
    )
    bad_norm = np.abs(np.einsum("ij,ij->i", quat, quat) - 1.0) > 2 * quat_tol
    refuse(not bad_norm.any(), lambda: bad_norm, "not a unit quaternion", quat)
    cov21, scale, symmetric = pack_checked(flat, cov_tol)

    def asym() -> np.ndarray:
        lo = np.take(flat, FLAT_LO, axis=1)
        return (np.abs(cov21 - lo) > (cov_tol * scale)[:, None]).any(axis=1)

    refuse(symmetric, asym, "covariance is not symmetric", cov)
    psd = psd_mask(cov21, cov_tol, scale)
    refuse(bool(psd.all()), lambda: ~psd, "covariance is not positive semidefinite", cov)
    return StateColumns(
        eid.astype(np.int64, copy=True),
        t.astype(np.int64, copy=True),
        str(b.frame),
        pos.copy(),
        quat.copy(),
        vel.copy(),
        cov21,
        var.copy(),
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

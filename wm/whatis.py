"""What Is (reference 001, 4.2 item 3): the state of the world now or at time t, in the frame
the caller asks for.

"The WM answers What Is? queries from BG and other modules": the self state; an entity by id,
as of a time, in a requested frame; entities in a region with class, status and confidence
filters; a map window per level and layers; events in an interval; read-only SQL (4.4.12).
Every answer carries its time (``t_ns``) and frame.

Frames: ``"world"``; ``"base_link"`` (the body at the answer's time, from the self entity's
history); ``"ladar"`` (body times the mount ``T_body_ladar``); ``"egosphere"`` (the LADAR's
spherical coordinates: azimuth rad, elevation rad, range m, as ``position``); ``"map:<level>"``
(window column, row of the level's current window, float cells, and world z). Velocities are
rotated into the frame (frames are treated as momentarily still).
A time older than short-term memory is answered from long-term memory where it can
(``source`` says which) and refused with :class:`WhatIsError` where it cannot. A time after
the newest the WM knows (the KD's cycle time and the entity's newest state) is answered with
the newest state, flagged ``source="future"`` with a ``note``: What Is does not predict.
Region answers are as of the KD's present (its cycle time, or the newest state found if
later) in the region's frame; map answers are as of the stack's last fused sweep.
"""

from __future__ import annotations

import bisect
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

import kd_store
from core.errors import EngineError
from core.geometry import quat_to_matrix, se3, se3_inverse
from kd_store import Box, Circle, State, Status
from maps.stack import MapStack
from wm.poses import PoseError, PoseTrack


class WhatIsError(EngineError, ValueError):
    """A What Is query that cannot be answered (names the value and why)."""


@dataclass(frozen=True)
class EntityAnswer:
    """An entity's state at ``t_ns`` (the state's own time, int64 ns) in ``frame``: position
    (3,), velocity (3,), and ``source``: "current" (its newest state), "short_term",
    "long_term" (older than short-term memory), or "future" (the asked time is after the
    newest the WM knows; this is the newest state, held, not a prediction). ``note`` says why
    for "long_term" and "future" ("" otherwise)."""

    entity_id: int
    t_ns: int
    frame: str
    position: np.ndarray
    velocity: np.ndarray
    status: str
    confidence: float
    class_name: str | None
    source: str
    note: str = ""


@dataclass(frozen=True, eq=False)
class RegionAnswer:
    """Entities in a region as of ``t_ns`` (int64 ns; -1 if the KD knows no time), the
    region given in ``frame``: ``ids`` (K,) sorted int64 and ``t_state_ns`` (K,) int64, the
    time of each one's current state. Reads as ``ids`` (``len``, iteration, indexing, ``in``,
    ``np.asarray``, ``tolist``, ``size``), as the bare id array it replaces did."""

    ids: np.ndarray
    t_ns: int
    frame: str
    t_state_ns: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)

    def __iter__(self) -> Iterator[np.int64]:
        return iter(self.ids)

    def __getitem__(self, k: int | slice | np.ndarray) -> np.int64 | np.ndarray:
        return self.ids[k]

    def __contains__(self, entity_id: object) -> bool:
        return entity_id in self.ids

    def __array__(self, dtype: np.dtype | None = None, copy: bool | None = None) -> np.ndarray:
        a = np.asarray(self.ids, dtype=dtype)
        return a.copy() if copy else a

    @property
    def size(self) -> int:
        return int(self.ids.size)

    def tolist(self) -> list[int]:
        return self.ids.tolist()


@dataclass(frozen=True)
class MapAnswer:
    """A window of layers of one level: arrays (rows, cols) in window order (row 0 south),
    ``xy_min`` world corner of cell [0, 0] (m, so ``frame`` is "world"), ``resolution_m``;
    ``t_ns`` the time (int64 ns) of the stack's last fused sweep, -1 if none was fused yet."""

    level: str
    t_ns: int
    frame: str
    xy_min: np.ndarray
    resolution_m: float
    layers: dict[str, np.ndarray]


class WhatIs:
    """The What Is interface over a KD and (optionally) the map stack."""

    def __init__(
        self,
        kd: kd_store.KnowledgeDatabase,
        stack: MapStack | None = None,
        self_id: int | None = None,
        T_body_ladar: np.ndarray | None = None,
    ) -> None:
        self.kd, self.stack, self.self_id = kd, stack, self_id
        self.T_body_ladar = np.eye(4) if T_body_ladar is None else np.asarray(T_body_ladar)

    # --- states ----------------------------------------------------------------------------

    def state_at(self, entity_id: int, t_ns: int | None = None) -> tuple[State, str]:
        """The entity's state at ``t_ns`` (None: latest) and where it came from (the
        ``source`` of :class:`EntityAnswer`)."""
        f = self.kd.get(entity_id)
        if f.state is None:
            raise WhatIsError(f"entity {entity_id} ({f.name!r}) has no state yet")
        if t_ns is None or t_ns >= f.state.t_ns:
            future = t_ns is not None and t_ns > self.newest_known_ns(f.state.t_ns)
            return f.state, "future" if future else "current"
        hist = self.kd.history(entity_id)
        if hist and hist[0].t_ns <= t_ns:
            return _latest_before(hist, t_ns), "short_term"
        lt = self.kd.long_term_history(entity_id)
        if lt and lt[0].t_ns <= t_ns:
            return _latest_before(lt, t_ns), "long_term"
        oldest = hist[0].t_ns if hist else f.state.t_ns
        raise WhatIsError(
            f"entity {entity_id}: t_ns={t_ns} is before short-term memory (oldest {oldest}) "
            f"and long-term memory holds no state that old"
        )

    def newest_known_ns(self, t_state_ns: int = -1) -> int:
        """The newest time (int64 ns) the WM knows: the KD's cycle time (``begin_cycle``) or
        ``t_state_ns`` (a state's time) if later; -1 if neither is known."""
        t_cycle = self.kd.immediate.t_ns
        return max(-1 if t_cycle is None else int(t_cycle), int(t_state_ns))

    def self_state(self, t_ns: int | None = None) -> EntityAnswer:
        """The vehicle's own state (world frame)."""
        if self.self_id is None:
            raise WhatIsError("this What Is has no self entity")
        return self.entity(self.self_id, t_ns)

    def T_world_body(self, t_ns: int | None = None) -> np.ndarray:
        """The body pose (4x4) at ``t_ns`` from the self entity's history, by the rules of
        :class:`~wm.poses.PoseTrack` over the states around it: interpolated between the one
        before and the one after (the KD holds one a sweep, so the one before alone is up to
        a sweep stale, 1 m at 10 m/s), continued from the last two a little past the newest,
        and held at the nearest beyond that."""
        if self.self_id is None:
            raise WhatIsError("body-relative frames need the self entity")
        s, source = self.state_at(self.self_id, t_ns)
        newest = self.kd.get(self.self_id).state
        if t_ns is None or newest is None:
            return _pose_of(s)
        hist = (
            self.kd.long_term_history(self.self_id)
            if source == "long_term"
            else self.kd.history(self.self_id)
        )
        states = [h for h in hist if h.t_ns < newest.t_ns] + [newest]  # time order
        i = bisect.bisect_right([h.t_ns for h in states], t_ns)
        track = PoseTrack()
        for h in states[max(i - 2, 0) : i + 1]:
            track.add(h.t_ns, _pose_of(h))
        try:
            return track.at(t_ns)
        except PoseError:  # too far past the newest (or before the oldest) to continue
            return _pose_of(states[min(max(i - 1, 0), len(states) - 1)])

    def entity(self, entity_id: int, t_ns: int | None = None, frame: str = "world") -> EntityAnswer:
        """Entity ``entity_id`` as of ``t_ns`` in ``frame`` (module docstring)."""
        self.check_frame(frame)  # a wrong frame is wrong whatever the KD holds yet
        s, source = self.state_at(entity_id, t_ns)
        if s.frame != "world":
            raise WhatIsError(f"entity {entity_id}: state held in {s.frame!r}, not 'world'")
        f = self.kd.get(entity_id)
        p, v = self._to_frame(s.position_xyz, s.velocity_xyz, frame, s.t_ns)
        note = ""
        if source == "future":
            note = (
                f"t_ns={t_ns} is after the newest time known ({self.newest_known_ns(s.t_ns)}):"
                f" this is the newest state (t_ns={s.t_ns}), held, not a prediction"
            )
        elif source == "long_term":
            note = f"t_ns={t_ns} is before short-term memory: answered from long-term memory"
        return EntityAnswer(entity_id, s.t_ns, frame, p, v, f.status.value, f.confidence,
                            f.most_specific_class, source, note)  # fmt: skip

    def check_frame(self, frame: str) -> None:
        """WhatIsError naming ``frame`` unless answers can be given in it."""
        if frame.startswith("map:"):
            self._level(frame[4:])
        elif frame not in ("world", "base_link", "ladar", "egosphere"):
            raise WhatIsError(
                f"unknown frame {frame!r}; frames: world, base_link, ladar, egosphere, map:<level>"
            )

    def _to_frame(self, p_w: np.ndarray, v_w: np.ndarray, frame: str, t_ns: int):
        if frame == "world":
            return p_w.copy(), v_w.copy()
        if frame.startswith("map:"):
            lvl = self._level(frame[4:])
            lo, _ = lvl.bounds_xy
            cr = (p_w[:2] - lo) / lvl.resolution_m
            return np.array([cr[0], cr[1], p_w[2]]), v_w / np.array([lvl.resolution_m] * 2 + [1])
        T_world = self.T_world_body(t_ns)
        if frame in ("ladar", "egosphere"):
            T_world = T_world @ self.T_body_ladar
        else:
            self.check_frame(frame)
        T = se3_inverse(T_world)
        p = T[:3, :3] @ p_w + T[:3, 3]
        v = T[:3, :3] @ v_w
        if frame == "egosphere":
            r = float(np.linalg.norm(p))
            az, el = np.arctan2(p[1], p[0]), np.arcsin(p[2] / r) if r > 0 else 0.0
            return np.array([az, el, r]), v
        return p, v

    # --- regions, maps, events, SQL ----------------------------------------------------------

    def region(
        self,
        region: Box | Circle,
        classes: list[str] | None = None,
        statuses: list[Status | str] | None = None,
        min_confidence: float = 0.0,
        levels: list[int] | None = None,
    ) -> RegionAnswer:
        """Entities whose current position lies in ``region`` (held in ``region.frame``) and
        which pass the filters (``KD.region``), as of the KD's present (:meth:`newest_known_ns`
        over the cycle time and the states found)."""
        ids = self.kd.region(region, classes, statuses, levels, min_confidence)
        t_state = np.array([self.kd.get(int(i)).state.t_ns for i in ids], dtype=np.int64)
        t_ns = self.newest_known_ns(int(t_state.max()) if len(t_state) else -1)
        return RegionAnswer(ids, t_ns, region.frame, t_state)

    def map_window(
        self,
        level: str,
        layers: tuple[str, ...] = ("elevation",),
        center_xy: np.ndarray | None = None,
        size: int = 64,
    ) -> MapAnswer:
        """``size`` x ``size`` cells of ``layers`` at ``level`` around ``center_xy`` (world m;
        default: the window centre); cells outside the window hold the layer's fill."""
        lvl = self._level(level)
        c = lvl.center_xy if center_xy is None else np.asarray(center_xy, np.float64)[:2]
        cell0 = np.floor(c / lvl.resolution_m).astype(np.int64) - size // 2
        r0 = int(cell0[1] - lvl.origin_cell[1])
        c0 = int(cell0[0] - lvl.origin_cell[0])
        out = {}
        for name in layers:
            lvl.require(name)
            spec = lvl.specs[name]
            a = np.full((size, size), spec.fill, dtype=lvl.storage(name).dtype)
            rs, re = max(r0, 0), min(r0 + size, lvl.size)
            cs, ce = max(c0, 0), min(c0 + size, lvl.size)
            if rs < re and cs < ce:
                rows, cols = np.arange(rs, re), np.arange(cs, ce)
                sr, sc = lvl.window_to_storage(rows, cols)
                a[rs - r0 : re - r0, cs - c0 : ce - c0] = lvl.storage(name)[np.ix_(sr, sc)]
            out[name] = a
        xy_min = cell0.astype(np.float64) * lvl.resolution_m
        return MapAnswer(level, self.stack.t_last_fused_ns, "world", xy_min, lvl.resolution_m, out)

    def events(self, t_from_ns: int, t_to_ns: int, class_name: str | None = None) -> list:
        """Event frames overlapping ``[t_from_ns, t_to_ns]`` (start-time order)."""
        check_interval(t_from_ns, t_to_ns)
        return self.kd.events(t_from_ns, t_to_ns, class_name=class_name)

    def sql(self, query: str) -> pa.Table:
        """One read-only SELECT over the KD's views (docs/kd.md)."""
        return self.kd.sql(query)

    def _level(self, name: str):
        if self.stack is None:
            raise WhatIsError("map queries need the map stack")
        names = [lv.name for lv in self.stack.levels]
        if name not in names:
            raise WhatIsError(f"map level {name!r} does not exist; levels: {names}")
        return self.stack.level(name)


def check_interval(t_from_ns: int, t_to_ns: int) -> None:
    """WhatIsError naming an events interval (int64 ns) that ends before it starts."""
    if t_to_ns < t_from_ns:
        raise WhatIsError(f"events: interval [{t_from_ns}, {t_to_ns}] ns ends before it starts")


def _pose_of(s: State) -> np.ndarray:
    return se3(quat_to_matrix(s.orientation_xyzw), s.position_xyz)


def _latest_before(states: list[State], t_ns: int) -> State:
    ts = np.array([s.t_ns for s in states])
    return states[int(np.searchsorted(ts, t_ns, side="right")) - 1]

"""Re-identification: a new object hypothesis takes the frame of an object lost moments ago.

Reference 001, 4.4.11 (short-term memory "persists for some interval after the sensory input
disappears" and keeps "the path of an entity through space"), 4.5.3 (hypothesize and test).

A confirmed track that goes unseen for its ``max_misses`` cycles is gone (:mod:`sp.tracking`).
A walker hidden for two seconds in a crowd or behind a parked van, or a car behind a truck,
then comes back as a new hypothesis, and without more the knowledge database would hold two
entities for one object: a user asking how many persons the vehicle passed would count it
twice. So each object that goes is remembered for ``max_gap_s`` (:class:`LostObjects`), and a
hypothesis that earns its frame (level 4's M-of-N birth) takes instead the frame of a lost
object it may be: one whose position, carried on at its last velocity, lies within
``radius_m`` of it, plus ``speed_mps`` for each second lost if the object was moving (a
walker turns, a car brakes), and whose height is within ``height_m`` of it. Several candidates are
paired by the optimal assignment of distances relative to each gate
(``scipy.optimize.linear_sum_assignment``). An object at rest comes back where it was: only
one the tracker had moving gets the speed allowance (a car parked in a row, lost behind a
passing van, must not go to the car parked 3 m beside it).

All positions are world xy in metres, times int64 ns.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from core.errors import EngineError


class ReidError(EngineError, ValueError):
    """A re-identification setting or input that cannot be used; names the value."""


@dataclass(frozen=True)
class ReidConfig:
    """When a new hypothesis is a lost object (module docstring); ``enabled`` False: never.

    max_gap_s:  how long a lost object is remembered (s): a walker at 1.4 m/s is hidden for
                about 3 s behind a 4 m van seen side-on.
    radius_m:   the gate around the lost object's predicted position (m): a body's footprint
                and the wander of its visible centre.
    speed_mps:  the gate's growth per second lost for an object that was moving (m/s): how far
                a walker strays from a straight path.
    height_m:   the largest difference of height (m) between the two (a person is not a car).
    """

    enabled: bool = True
    max_gap_s: float = 4.0
    radius_m: float = 1.0
    speed_mps: float = 1.5
    height_m: float = 0.5

    def __post_init__(self) -> None:
        if not (self.max_gap_s >= 0 and self.radius_m > 0):
            raise ReidError(
                f"re-identification max_gap_s {self.max_gap_s}, radius_m {self.radius_m}: "
                "need >= 0, > 0"
            )
        if not (self.speed_mps >= 0 and self.height_m >= 0):
            raise ReidError(
                f"re-identification speed_mps {self.speed_mps}, height_m {self.height_m}: "
                "need >= 0, >= 0"
            )


@dataclass
class Lost:
    """One object that went: its frame ``id``, last measured time ``t_ns``, world position
    ``xy`` (2,) m and velocity ``v_xy`` (2,) m/s as reported (zero at rest), ``height_m``,
    whether it was moving, and ``kept``: whatever its level keeps of it, to hand back."""

    id: int
    t_ns: int
    xy: np.ndarray
    v_xy: np.ndarray
    height_m: float
    moving: bool
    kept: dict[str, Any] = field(default_factory=dict)


class LostObjects:
    """The objects lost within the last ``max_gap_s``, by frame id."""

    def __init__(self, config: ReidConfig | None = None) -> None:
        self.config = config or ReidConfig()
        self.lost: dict[int, Lost] = {}

    def __len__(self) -> int:
        return len(self.lost)

    def add(self, lost: Lost) -> None:
        """Remember ``lost`` (an object of the same id lost before is replaced)."""
        if self.config.enabled:
            self.lost[int(lost.id)] = lost

    def forget_before(self, t_ns: int) -> None:
        """Forget the objects last seen more than ``max_gap_s`` before ``t_ns``."""
        horizon = int(t_ns) - round(self.config.max_gap_s * 1e9)
        for i in [i for i, o in self.lost.items() if o.t_ns < horizon]:
            del self.lost[i]

    def match(self, t_ns: np.ndarray, xy: np.ndarray, height_m: np.ndarray) -> list[Lost | None]:
        """The lost object each new hypothesis is (None: none), for hypotheses seen at
        ``t_ns`` (N,) int64 ns at world ``xy`` (N, 2) m, ``height_m`` (N,) m. Each lost object
        goes to at most one, and a matched one is no longer remembered."""
        t_ns = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        n = t_ns.size
        out: list[Lost | None] = [None] * n
        if not n or not self.lost:
            return out
        xy = np.asarray(xy, dtype=np.float64).reshape(n, 2)
        h = np.asarray(height_m, dtype=np.float64).reshape(n)
        cfg = self.config
        ids = np.array(list(self.lost), dtype=np.int64)
        objs = [self.lost[int(i)] for i in ids]
        t0 = np.array([o.t_ns for o in objs], dtype=np.int64)
        p0 = np.array([o.xy for o in objs], dtype=np.float64).reshape(-1, 2)
        v0 = np.array([o.v_xy for o in objs], dtype=np.float64).reshape(-1, 2)
        h0 = np.array([o.height_m for o in objs], dtype=np.float64)
        moving = np.array([o.moving for o in objs], dtype=bool)
        dt = (t_ns[:, None] - t0[None, :]) * 1e-9  # (N, L) s since each was last seen
        pred = p0[None, :, :] + v0[None, :, :] * np.maximum(dt, 0.0)[..., None]
        d = np.hypot(*np.moveaxis(xy[:, None, :] - pred, -1, 0))
        gate = cfg.radius_m + np.where(moving[None, :], cfg.speed_mps * np.maximum(dt, 0.0), 0.0)
        ok = (dt >= 0) & (dt <= cfg.max_gap_s) & (d <= gate)
        ok &= np.abs(h[:, None] - h0[None, :]) <= cfg.height_m
        if not ok.any():
            return out
        cost = np.where(ok, d / gate, 1e6)
        rows, cols = linear_sum_assignment(cost)
        for r, c in zip(rows.tolist(), cols.tolist(), strict=True):
            if ok[r, c]:
                out[r] = self.lost.pop(int(ids[c]))
        return out

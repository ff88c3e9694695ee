"""Entity and event frames: what the KD knows about one thing or one happening.

Follows reference 001 (the 4D/RCS reference model), section 4.4.2 (entity frame, Figure 18)
and section 4.4.8 (event frame, Figure 27); see docs/architecture.md, section 5. Frames are
frozen: change them through the :class:`~kd_store.store.KnowledgeDatabase`, which validates
every change and keeps its indexes in step. Pointers between frames (parent, parts,
situational, temporal, causal, involves) live in the KD's relation graph, not in the frames,
so the two directions of a pointer can never disagree (see :mod:`kd_store.relations`).

Units: metres, radians, seconds as int64 nanoseconds (``t_ns``); quaternions (x, y, z, w).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import IntEnum, StrEnum

import numpy as np

from kd_store.covariance import DIAG, FLAT_UP, UNPACK_FLAT, psd_mask
from kd_store.errors import KDError

#: Order of the 6x6 state covariance: position then velocity.
COVARIANCE_ORDER = ("x", "y", "z", "vx", "vy", "vz")


class Level(IntEnum):
    """Sensory-processing level of an entity (4.4.3, geometrical entity classes)."""

    POINT = 1
    LIST = 2
    SURFACE = 3
    OBJECT = 4
    GROUP = 5


class Status(StrEnum):
    """Where a grouping hypothesis stands (4.5, hypothesize and test)."""

    HYPOTHESIZED = "hypothesized"
    CONFIRMED = "confirmed"
    DENIED = "denied"
    GONE = "gone"


STATUS_CODES: dict[str, int] = {s.value: i for i, s in enumerate(Status)}


_P, _Q, _V, _C, _R = slice(0, 3), slice(3, 7), slice(7, 10), slice(10, 31), slice(31, 34)
_IDENTITY_Q = (0.0, 0.0, 0.0, 1.0)


class State:
    """Dynamic state of an entity at one time, in the coordinate frame ``frame``. Immutable.

    position_xyz:        (3,) float64, metres.
    orientation_xyzw:    (4,) float64 unit quaternion, rotation of the entity in ``frame``.
    velocity_xyz:        (3,) float64, m/s, expressed in ``frame``.
    covariance:          (6, 6) float64 over (x, y, z, vx, vy, vz): m^2, m^2/s, m^2/s^2;
                         symmetric positive semidefinite.
    orientation_var_rpy: (3,) float64 rad^2, variances of roll, pitch, yaw.

    The arrays are read-only, taken from one (34,) vector holding the covariance packed to
    its upper triangle (so a state costs about 450 bytes); ``asymmetry`` keeps how far the
    covariance given was from symmetric, for the KD's check.
    """

    __slots__ = ("_asym", "_v", "frame", "t_ns")

    def __init__(
        self,
        t_ns: int,
        frame: str,
        position_xyz: object,
        orientation_xyzw: object = _IDENTITY_Q,
        velocity_xyz: object = (0.0, 0.0, 0.0),
        covariance: object | None = None,
        orientation_var_rpy: object = (0.0, 0.0, 0.0),
    ) -> None:
        v = np.zeros(34)
        asym = 0.0
        try:
            v[_P] = np.asarray(position_xyz, dtype=np.float64).reshape(3)
            v[_Q] = np.asarray(orientation_xyzw, dtype=np.float64).reshape(4)
            v[_V] = np.asarray(velocity_xyz, dtype=np.float64).reshape(3)
            if covariance is not None:
                C = np.asarray(covariance, dtype=np.float64).reshape(6, 6)
                v[_C] = C.reshape(36)[FLAT_UP]
                with np.errstate(invalid="ignore"):
                    asym = float(np.max(np.abs(C - C.T)))
            v[_R] = np.asarray(orientation_var_rpy, dtype=np.float64).reshape(3)
        except (ValueError, TypeError) as e:
            raise KDError(f"state at t_ns={t_ns} in {frame!r}: wrong shape or type ({e})") from None
        self._init(int(t_ns), str(frame), v, asym)

    def _init(self, t_ns: int, frame: str, v: np.ndarray, asym: float) -> None:
        v.flags.writeable = False
        self.t_ns, self.frame, self._asym, self._v = t_ns, frame, asym, v

    @classmethod
    def from_vector(cls, t_ns: int, frame: str, v: np.ndarray) -> State:
        """From the (34,) layout: position (3), quaternion (4), velocity (3), covariance packed
        to its upper triangle (21), var_rpy (3)."""
        s = cls.__new__(cls)
        s._init(t_ns, frame, v, 0.0)
        return s

    def __setattr__(self, name: str, value: object) -> None:
        if hasattr(self, "_v"):
            raise AttributeError(f"State is immutable (tried to set {name})")
        object.__setattr__(self, name, value)

    def __reduce__(self) -> tuple:
        # pickled as its vector (a live node sends states to its server's process): the
        # default would set the slots one by one, which __setattr__ refuses once _v is set
        return (_state_of, (self.t_ns, self.frame, self._v, self._asym))

    @property
    def position_xyz(self) -> np.ndarray:
        return self._v[_P]

    @property
    def orientation_xyzw(self) -> np.ndarray:
        return self._v[_Q]

    @property
    def velocity_xyz(self) -> np.ndarray:
        return self._v[_V]

    @property
    def covariance(self) -> np.ndarray:
        c = self._v[_C][UNPACK_FLAT].reshape(6, 6)
        c.flags.writeable = False
        return c

    @property
    def covariance_packed(self) -> np.ndarray:
        """(21,) upper triangle of the covariance, row-major (the ``cov_pv`` layout)."""
        return self._v[_C]

    @property
    def asymmetry(self) -> float:
        """max |C - C^T| of the covariance this state was made with (0 if made packed)."""
        return self._asym

    @property
    def orientation_var_rpy(self) -> np.ndarray:
        return self._v[_R]

    @property
    def vector(self) -> np.ndarray:
        """The read-only (34,) vector behind the fields."""
        return self._v

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, State):
            return NotImplemented
        return (
            self.t_ns == other.t_ns
            and self.frame == other.frame
            and bool(np.array_equal(self._v, other._v))
        )

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return (
            f"State(t_ns={self.t_ns}, frame={self.frame!r}, "
            f"position_xyz={self.position_xyz.tolist()}, "
            f"orientation_xyzw={self.orientation_xyzw.tolist()}, "
            f"velocity_xyz={self.velocity_xyz.tolist()}, "
            f"cov_diag={np.diag(self.covariance).tolist()}, "
            f"orientation_var_rpy={self.orientation_var_rpy.tolist()})"
        )


make_state = State  # the constructor takes array-likes


def _state_of(t_ns: int, frame: str, v: np.ndarray, asym: float) -> State:
    """A :class:`State` as pickled (:meth:`State.__reduce__`)."""
    s = State.__new__(State)
    s._init(t_ns, frame, np.array(v, dtype=np.float64), asym)
    return s


@dataclass(frozen=True, slots=True)
class Attribute:
    """One named attribute held three ways (4.4.2): observed from sensors, estimated by the
    filter, predicted by the world model, each with its variance. NaN means not available."""

    observed: float = math.nan
    observed_var: float = math.nan
    estimated: float = math.nan
    estimated_var: float = math.nan
    predicted: float = math.nan
    predicted_var: float = math.nan

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Attribute):
            return NotImplemented
        a = np.array(_attribute_tuple(self))
        b = np.array(_attribute_tuple(other))
        return bool(np.array_equal(a, b, equal_nan=True))

    __hash__ = None  # type: ignore[assignment]


ATTRIBUTE_FIELDS = (
    "observed",
    "observed_var",
    "estimated",
    "estimated_var",
    "predicted",
    "predicted_var",
)


def _attribute_tuple(a: Attribute) -> tuple[float, ...]:
    return tuple(getattr(a, k) for k in ATTRIBUTE_FIELDS)


@dataclass(frozen=True, slots=True)
class Value:
    """Worth of an entity or event to value judgment (4.4.2, 4.3): dimensionless utilities."""

    worth_preserve: float = 0.0
    worth_acquire: float = 0.0
    worth_defend: float = 0.0
    worth_defeat: float = 0.0
    cost: float = 0.0
    risk: float = 0.0

    @property
    def max_worth(self) -> float:
        return max(self.worth_preserve, self.worth_acquire, self.worth_defend, self.worth_defeat)


VALUE_FIELDS = ("worth_preserve", "worth_acquire", "worth_defend", "worth_defeat", "cost", "risk")


@dataclass(frozen=True, slots=True)
class EntityFrame:
    """What the KD knows about one entity (reference 4.4.2, Figure 18).

    id:               frame address in the KD (int64, shared id space with events).
    name:             entity name; ``name_uncertainty`` in [0, 1] says how unsure it is.
    level:            SP level 1 point ... 5 group.
    status:           hypothesized / confirmed / denied / gone, with ``confidence`` in [0, 1].
    attributes:       name -> :class:`Attribute` (observed, estimated, predicted + variances).
    state:            latest estimated :class:`State`, or None before the first observation.
                      Past states are the short-term memory queue (``KnowledgeDatabase.history``).
    expectations:     short-term expectation queue: predicted future states, in time order.
    generic_classes:  class pointers, general to specific (e.g. ``("vegetation", "tree")``).
    specific_class:   pointer to the specific class of this one entity, or None.
    value:            worth to preserve/acquire/defend/defeat, cost and risk.
    images:           names of the entity images it appears in; their pixels hold ``id``.
    map_cells:        (map level, column, row) of map cells it occupies.
    created_ns:       time the frame was made.
    noteworthy:       flagged by SP/WM/VJ for long-term memory (4.4.11).
    """

    id: int
    name: str
    level: Level
    status: Status = Status.HYPOTHESIZED
    confidence: float = 0.0
    name_uncertainty: float = 1.0
    attributes: Mapping[str, Attribute] = field(default_factory=dict)
    state: State | None = None
    expectations: tuple[State, ...] = ()
    generic_classes: tuple[str, ...] = ()
    specific_class: str | None = None
    value: Value = field(default_factory=Value)
    images: tuple[str, ...] = ()
    map_cells: tuple[tuple[int, int, int], ...] = ()
    created_ns: int = 0
    noteworthy: bool = False

    @property
    def most_specific_class(self) -> str | None:
        """The specific class, else the last generic class, else None."""
        if self.specific_class is not None:
            return self.specific_class
        return self.generic_classes[-1] if self.generic_classes else None


@dataclass(frozen=True, slots=True)
class EventFrame:
    """What the KD knows about one event (reference 4.4.8, Figure 27).

    id:              frame address (int64, shared id space with entities).
    class_name:      generic event class (e.g. ``"obstacle_avoided"``).
    t_start_ns:      start time; ``t_end_ns`` is the end, or None while the event goes on.
    attributes:      name -> float (amplitude, duration, ...), units in the name.
    level:           grouping level 1..5 (4.4.9): level-n events group level n-1 sub-events.
    confidence:      in [0, 1]; ``name_uncertainty`` likewise.
    value:           cost / benefit of the event to value judgment.
    Parent, sub-events, entities involved, temporal and causal relations are pointers in the
    relation graph (belongs_to/has_part, involves, before/after/during/simultaneous_with, causes).
    """

    id: int
    name: str
    class_name: str
    t_start_ns: int
    t_end_ns: int | None = None
    attributes: Mapping[str, float] = field(default_factory=dict)
    level: int = 1
    confidence: float = 0.0
    name_uncertainty: float = 1.0
    value: Value = field(default_factory=Value)
    noteworthy: bool = False

    def overlaps(self, t_from_ns: int, t_to_ns: int) -> bool:
        """True when the event's interval meets the closed interval [t_from_ns, t_to_ns]."""
        end = self.t_end_ns if self.t_end_ns is not None else np.iinfo(np.int64).max
        return self.t_start_ns <= t_to_ns and end >= t_from_ns


# ---------------------------------------------------------------- validation of one frame


def _check_unit(x: float, what: str, where: str) -> None:
    if not (0.0 <= x <= 1.0):
        raise KDError(f"{where}: {what} {x!r} is not in [0, 1]")


def check_state(s: State, where: str, cov_tol: float = 1e-9, quat_tol: float = 1e-6) -> None:
    """Refuse a state with wrong shapes, NaN/inf, a non-unit quaternion or a covariance that is
    not symmetric positive semidefinite. ``where`` names the frame for the message."""
    shapes = {
        "position_xyz": (3,),
        "orientation_xyzw": (4,),
        "velocity_xyz": (3,),
        "covariance": (6, 6),
        "orientation_var_rpy": (3,),
    }
    for name, shape in shapes.items():
        a = getattr(s, name)
        if not isinstance(a, np.ndarray) or a.shape != shape:
            raise KDError(f"{where}: state {name} must be a {shape} array, got {a!r}")
        if not np.all(np.isfinite(a)):
            raise KDError(f"{where}: state {name} at t_ns={s.t_ns} is not finite: {a.tolist()}")
    if abs(float(np.linalg.norm(s.orientation_xyzw)) - 1.0) > quat_tol:
        raise KDError(
            f"{where}: orientation_xyzw {s.orientation_xyzw.tolist()} at t_ns={s.t_ns} "
            "is not a unit quaternion"
        )
    if np.any(s.orientation_var_rpy < 0):
        raise KDError(f"{where}: orientation_var_rpy {s.orientation_var_rpy.tolist()} < 0")

    C = s.covariance
    scale = max(1.0, float(np.max(np.diag(C))))  # as for batches (see covariance.psd_mask)
    if not s.asymmetry <= cov_tol * scale or not psd_mask(s.covariance_packed[None], cov_tol)[0]:
        raise KDError(
            f"{where}: covariance at t_ns={s.t_ns} is not symmetric positive semidefinite: "
            f"{np.array2string(C, precision=4)}"
        )


def check_expectations(
    states: Sequence[State],
    current: State | None,
    where: str,
    cov_tol: float = 1e-9,
    quat_tol: float = 1e-6,
) -> None:
    """Refuse an expectation queue that :func:`check_state` would refuse state by state, or
    whose times do not strictly increase after ``current`` (the entity's state, if any).

    One batched test over all states (finite values, unit quaternions, variances >= 0,
    symmetry, and the positive-semidefinite test of :func:`~kd_store.covariance.psd_mask`
    on the stacked covariances); only a refused queue is checked state by state, so the
    message names the first bad state exactly as :func:`check_state` does."""
    if not states:
        return
    for s in states:
        if not isinstance(s, State):
            raise KDError(f"{where}: expectation {s!r} is not a State")
        if s.vector.shape != (34,):  # made from a malformed vector: name the bad field
            check_state(s, f"{where} expectation", cov_tol, quat_tol)
    V = np.stack([s.vector for s in states])
    t = np.fromiter((s.t_ns for s in states), np.int64, len(states))
    asym = np.fromiter((s.asymmetry for s in states), np.float64, len(states))
    cov21 = V[:, _C]
    scale = np.maximum(1.0, cov21[:, DIAG].max(axis=1))
    ok = np.isfinite(V).all(axis=1)
    ok &= np.abs(np.linalg.norm(V[:, _Q], axis=1) - 1.0) <= quat_tol
    ok &= (V[:, _R] >= 0).all(axis=1)
    ok &= asym <= cov_tol * scale
    ok &= psd_mask(cov21, cov_tol, scale)
    if not ok.all():
        bad = states[int(np.flatnonzero(~ok)[0])]
        check_state(bad, f"{where} expectation", cov_tol, quat_tol)
        raise KDError(f"{where}: expectation {bad!r} is not a valid state")  # not reached
    prev = np.r_[np.iinfo(np.int64).min if current is None else current.t_ns, t[:-1]]
    back = np.flatnonzero(t <= prev)
    if len(back):
        i = int(back[0])
        raise KDError(
            f"{where}: expectation at t_ns={int(t[i])} is not after the state before it "
            f"(t_ns={int(prev[i])})"
        )


def check_attribute(a: Attribute, name: str, where: str) -> None:
    """Values may be NaN (not available) but not inf; variances NaN or >= 0."""
    v = (a.observed, a.observed_var, a.estimated, a.estimated_var, a.predicted, a.predicted_var)
    # the common case in one expression (floats, none inf, no variance below 0); NaN passes
    # every comparison below as False, as it must
    if (
        all(type(x) is float for x in v)
        and not any(x in _INF for x in v)
        and not (v[1] < 0 or v[3] < 0 or v[5] < 0)
    ):
        return
    for k in ATTRIBUTE_FIELDS:
        v = getattr(a, k)
        if not isinstance(v, float | int) or math.isinf(v):
            raise KDError(f"{where}: attribute {name!r}.{k} = {v!r} is not a finite float or NaN")
        if k.endswith("_var") and v < 0:
            raise KDError(f"{where}: attribute {name!r}.{k} = {v!r} is a negative variance")


_INF = (math.inf, -math.inf)


def check_value(v: Value, where: str) -> None:
    for k in VALUE_FIELDS:
        x = getattr(v, k)
        if not math.isfinite(x):
            raise KDError(f"{where}: value {k} = {x!r} is not finite")


def check_entity(
    f: EntityFrame,
    cov_tol: float = 1e-9,
    quat_tol: float = 1e-6,
    where: str | None = None,
    states: bool = True,
    old: EntityFrame | None = None,
) -> None:
    """Refuse an entity frame with a field out of its domain; the message names the frame.
    ``states=False`` skips the state and expectations (for a change that keeps both, whose
    states were checked when they came in: states are immutable). With ``old``, the frame it
    replaces, attributes it kept (the same immutable objects) are not checked again."""
    where = where or f"entity {f.id} ({f.name!r})"
    if not isinstance(f.id, int | np.integer) or not (0 <= int(f.id) < 2**63):
        raise KDError(f"{where}: id {f.id!r} is not a non-negative int64")
    try:
        Level(f.level)
        Status(f.status)
    except ValueError as e:
        raise KDError(f"{where}: {e}") from None
    _check_unit(f.confidence, "confidence", where)
    _check_unit(f.name_uncertainty, "name_uncertainty", where)
    kept = old.attributes if old is not None else {}
    for name, a in f.attributes.items():
        if kept.get(name) is a:
            continue
        if not isinstance(a, Attribute):
            raise KDError(f"{where}: attribute {name!r} is {a!r}, not an Attribute")
        check_attribute(a, name, where)
    if states and f.state is not None:
        check_state(f.state, where, cov_tol, quat_tol)
    if states:
        check_expectations(f.expectations, f.state, where, cov_tol, quat_tol)
    check_value(f.value, where)
    for cell in f.map_cells:
        if len(cell) != 3:
            raise KDError(f"{where}: map cell {cell!r} is not (level, column, row)")


def check_event(e: EventFrame, where: str | None = None) -> None:
    """Refuse an event frame with a field out of its domain; the message names the event."""
    where = where or f"event {e.id} ({e.name!r})"
    if not isinstance(e.id, int | np.integer) or not (0 <= int(e.id) < 2**63):
        raise KDError(f"{where}: id {e.id!r} is not a non-negative int64")
    if e.t_end_ns is not None and e.t_end_ns < e.t_start_ns:
        raise KDError(f"{where}: t_end_ns {e.t_end_ns} is before t_start_ns {e.t_start_ns}")
    _check_unit(e.confidence, "confidence", where)
    _check_unit(e.name_uncertainty, "name_uncertainty", where)
    for k, v in e.attributes.items():
        if not isinstance(v, float | int) or not math.isfinite(v):
            raise KDError(f"{where}: attribute {k!r} = {v!r} is not a finite number")
    check_value(e.value, where)

"""Typed configuration of the knowledge database, with every default in one place."""

from __future__ import annotations

from dataclasses import dataclass, field

#: Planning horizon (seconds) of each node level; short-term memory at a level keeps a
#: history about as long as that level plans ahead (reference 001, section 4.4.10 and 4.4.11).
DEFAULT_HORIZONS_S: dict[str, float] = {
    "primitive": 0.5,
    "subsystem": 5.0,
    "vehicle": 60.0,
    "section": 600.0,
}

#: The node level whose short-term memory holds entities of each SP level (1 point ... 5 group).
DEFAULT_NODE_OF_SP_LEVEL: dict[int, str] = {
    1: "primitive",
    2: "primitive",
    3: "subsystem",
    4: "vehicle",
    5: "section",
}


@dataclass(slots=True)
class MemoryConfig:
    """Short-term memory: history length per node level and which level each SP level uses."""

    horizons_s: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_HORIZONS_S))
    node_of_sp_level: dict[int, str] = field(default_factory=lambda: dict(DEFAULT_NODE_OF_SP_LEVEL))

    def horizon_ns(self, sp_level: int) -> int:
        """History length in int64 ns kept for entities of ``sp_level``."""
        return round(self.horizons_s[self.node_of_sp_level[int(sp_level)]] * 1e9)


@dataclass(slots=True)
class PromotionRule:
    """Which short-term frames long-term memory receives (4.4.11), judged at each
    ``flush`` and ``advance``.

    Value judgment sets it (``KnowledgeDatabase.promotion_rule``). An entity is promoted when
    it is flagged noteworthy, or its status is in ``statuses`` with confidence at least
    ``min_confidence``, or its largest worth (preserve/acquire/defend/defeat) is at least
    ``min_worth``. An event is promoted when noteworthy or its confidence is at least
    ``min_event_confidence``. Promotion is one-way: long-term memory does not forget.
    """

    statuses: frozenset[str] = frozenset({"confirmed"})
    min_confidence: float = 0.5
    min_worth: float = float("inf")
    min_event_confidence: float = 0.5


@dataclass(slots=True)
class KDConfig:
    """All knobs of a knowledge database.

    grid_cell_m:      cell size (metres) of the spatial index over entity positions.
    covariance_tol:   relative tolerance of the symmetry and positive-semidefinite checks.
    quaternion_tol:   allowed deviation of a quaternion's norm from 1.
    tile_write_batch: map tiles waiting in RAM before they are written on their own (one
                      transaction); ``flush`` writes them too. Bounds RAM on long runs.
    tile_cache:       clean map tiles kept decoded in RAM for reads.
    """

    memory: MemoryConfig = field(default_factory=MemoryConfig)
    promotion: PromotionRule = field(default_factory=PromotionRule)
    grid_cell_m: float = 8.0
    covariance_tol: float = 1e-9
    quaternion_tol: float = 1e-6
    tile_write_batch: int = 64
    tile_cache: int = 64

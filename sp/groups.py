"""Level-5 grouping: objects close together that move alike (convoys, crowds) and static
vegetation in a row (tree lines).

Reference 001, 4.5.6 (level 5 of sensory processing: "groups of objects ... a convoy, a
crowd, a tree line"), 4.5.2 (gestalt grouping by proximity and similarity of motion).
Two confirmed objects link when both move, are within ``link_moving_m`` and their velocities
differ by less than ``max_dv_mps``; or when both are trees within ``link_tree_m``. Groups are
the connected components with at least ``min_members`` objects; they keep their identity from
cycle to cycle by the largest overlap of members.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components


@dataclass(frozen=True)
class GroupConfig:
    link_moving_m: float = 16.0
    max_dv_mps: float = 1.0
    min_speed_mps: float = 0.5
    link_tree_m: float = 12.0
    min_members: int = 2


def group_labels(
    position_xy: np.ndarray,
    velocity_xy: np.ndarray,
    is_tree: np.ndarray,
    config: GroupConfig | None = None,
) -> np.ndarray:
    """(T,) int64 group label per object (0..G-1), -1 for objects in no group.

    position_xy, velocity_xy: (T, 2) world m and m/s; is_tree: (T,) bool.
    """
    cfg = config or GroupConfig()
    T = position_xy.shape[0]
    out = np.full(T, -1, dtype=np.int64)
    if T < cfg.min_members:
        return out
    d = np.linalg.norm(position_xy[:, None] - position_xy[None], axis=2)
    dv = np.linalg.norm(velocity_xy[:, None] - velocity_xy[None], axis=2)
    moving = np.linalg.norm(velocity_xy, axis=1) >= cfg.min_speed_mps
    link = moving[:, None] & moving[None] & (d <= cfg.link_moving_m) & (dv <= cfg.max_dv_mps)
    link |= is_tree[:, None] & is_tree[None] & (d <= cfg.link_tree_m)
    np.fill_diagonal(link, False)
    a, b = np.nonzero(link)
    g = coo_matrix((np.ones(a.size, np.int8), (a, b)), shape=(T, T))
    _, comp = connected_components(g, directed=False)
    counts = np.bincount(comp)
    keep = counts >= cfg.min_members
    new = np.full(counts.size, -1, dtype=np.int64)
    new[keep] = np.arange(int(keep.sum()))
    return new[comp]


def match_groups(
    previous: dict[int, frozenset[int]], current: list[frozenset[int]]
) -> tuple[dict[int, int], list[int], list[int]]:
    """Carry group identities over: returns (current index -> previous group id, the indices of
    current groups that are new, the previous ids no current group continues). Each previous
    group continues into the current group sharing most members with it (ties: first)."""
    carried: dict[int, int] = {}
    used: set[int] = set()
    pairs = sorted(
        (
            (-len(members & prev), i, gid)
            for i, members in enumerate(current)
            for gid, prev in previous.items()
            if members & prev
        ),
    )
    for _, i, gid in pairs:
        if i in carried or gid in used:
            continue
        carried[i] = gid
        used.add(gid)
    new = [i for i in range(len(current)) if i not in carried]
    ended = [gid for gid in previous if gid not in used]
    return carried, new, ended

"""A world-modeling node run over a list of log frames, for tests that compare runs, and what
a KD file holds after a run."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import kd_store
from wm.config import NodeConfig
from wm.node import WorldModelNode


def self_poses(frames, config: NodeConfig | None = None) -> tuple[list[np.ndarray], WorldModelNode]:
    """Feed ``frames`` to a node over a throwaway KD (SP off unless ``config`` says otherwise):
    the self pose ``T_world_body`` of every cycle, and the node (its stats) after the run."""
    kd = kd_store.open(":memory:")
    node = WorldModelNode(kd, config or NodeConfig(use_sp=False))
    poses = []
    for f in frames:
        poses += [c.T_world_body for c in node.feed(f)]
    poses += [c.T_world_body for c in node.finish()]
    kd.close()
    return poses, node


def in_file(path: Path) -> dict:
    """What the KD file holds: confirmed objects, and the self entity's states (count and
    newest time, ns)."""
    with kd_store.open(path, read_only=True) as kd:
        objects = kd.sql(
            "SELECT count(*) AS n FROM entities WHERE status = 'confirmed' AND level = 4 "
            "AND name <> 'self'"
        )["n"][0].as_py()
        me = kd.sql(
            "SELECT count(*) AS n, max(s.t_ns) AS t FROM entity_states s "
            "JOIN entities e ON e.id = s.entity_id WHERE e.name = 'self'"
        ).to_pylist()[0]
    return {"objects": objects, "self_states": me["n"], "self_t_ns": me["t"]}

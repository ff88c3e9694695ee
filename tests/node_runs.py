"""A world-modeling node run over a list of log frames, for tests that compare runs."""

from __future__ import annotations

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

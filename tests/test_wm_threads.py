"""The node's process runs its BLAS libraries on one thread during a run (their idle threads
would spin on the core the odometry process needs), and gives them back their limits after."""

from __future__ import annotations

import numpy as np
from threadpoolctl import threadpool_info

from wm.config import NodeConfig
from wm.run import compute_threads


def _blas_threads() -> list[int]:
    return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]


def test_compute_threads_limits_blas_inside_and_restores_after() -> None:
    np.ones((64, 64)) @ np.ones((64, 64))  # numpy's BLAS is loaded
    before = _blas_threads()
    assert before
    with compute_threads(NodeConfig().compute_threads):
        assert set(_blas_threads()) == {1}
    assert _blas_threads() == before
    with compute_threads(None):
        assert _blas_threads() == before

"""Evaluation: is the simulated LADAR good enough for real scan matching?

KISS-ICP (with its deskewing, fed our per-point times) runs on 20 s of the ``default`` and
``village`` drives; its trajectory is compared with the simulator's true sensor poses. The
figure is the final position error as a percentage of the distance driven.
"""

from __future__ import annotations

import numpy as np
import pytest

from bench.results import record
from core.geometry import se3_inverse
from fixtures.simulate import Simulator


def kiss_icp_drift_percent(name: str, seconds: float) -> tuple[float, float]:
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    sim = Simulator(name)
    ladar = sim.ladar
    config = KISSConfig()
    config.data.max_range = 100.0
    config.data.min_range = 2.0
    config.data.deskew = True
    config.mapping.voxel_size = 1.0
    kiss = KissICP(config)
    estimated, truth = [], []
    for k in range(round(seconds * ladar.config.rate_hz)):
        t_ns = k * ladar.period_ns
        scan = ladar.sweep(t_ns)
        kiss.register_frame(scan.points_xyz.astype(np.float64), scan.t_offset_ns / ladar.period_ns)
        estimated.append(kiss.last_pose.copy())
        # KISS-ICP deskews to the end of the sweep: compare with the sensor pose there
        truth.append(sim.world.T_world_body(t_ns + ladar.period_ns) @ ladar.T_body_ladar)
    E = se3_inverse(estimated[0]) @ np.array(estimated)
    G = se3_inverse(truth[0]) @ np.array(truth)
    distance = float(np.sum(np.linalg.norm(np.diff(G[:, :3, 3], axis=0), axis=1)))
    error = float(np.linalg.norm(E[-1, :3, 3] - G[-1, :3, 3]))
    return 100.0 * error / distance, distance


@pytest.mark.eval
@pytest.mark.parametrize("name", ["default", "village"])
def test_kiss_icp_tracks_the_simulated_ladar(name: str) -> None:
    seconds = 20.0
    drift, distance = kiss_icp_drift_percent(name, seconds)
    record(
        f"sim_kiss_icp_drift_{name}",
        drift,
        "% of distance",
        target="< 3 % final position error after 20 s (KITTI-like scan matching)",
        command="make eval",
    )
    assert distance > 80.0
    assert drift < 3.0

"""Level 1 puts a sensor's rings in elevation order, whatever order its driver numbers them in
(sp.level1.ring_rows): a simulated sweep's egosphere image is the same with its rings
shuffled (a raw firing order) or reversed (numbered from the top)."""

from __future__ import annotations

import numpy as np
import pytest

from core.geometry import LADAR
from fixtures.simulate import Simulator
from logs.types import LadarScan
from sp.context import SPConfig
from sp.level1 import PixelLevel, ring_rows


@pytest.fixture(scope="module")
def sweep() -> LadarScan:
    frames = Simulator("default", seed=5).frames(0.25)
    return next(f for f in frames if isinstance(f, LadarScan) and f.frame_id == LADAR)


def _image(scan: LadarScan) -> tuple[np.ndarray, np.ndarray]:
    px = PixelLevel(SPConfig()).step(scan, np.eye(4), int(scan.t_ns))
    return px.valid, px.xyz_s


def _renumbered(scan: LadarScan, new_of_old: np.ndarray) -> LadarScan:
    ring = new_of_old[scan.ring.astype(np.int64)].astype(np.uint16)
    return LadarScan(
        scan.t_ns, scan.frame_id, scan.points_xyz, scan.intensity, scan.t_offset_ns, ring,
        topic=scan.topic,
    )  # fmt: skip


def test_a_sensor_in_elevation_order_is_left_alone(sweep: LadarScan) -> None:
    assert sweep.ring is not None and np.unique(sweep.ring).size >= 20
    assert ring_rows(sweep.points_xyz, sweep.ring) is None
    # numbered from the top, as an egosphere told so expects
    top = int(sweep.ring.max()) - sweep.ring.astype(np.int64)
    assert ring_rows(sweep.points_xyz, top, zero_at_bottom=False) is None


@pytest.mark.parametrize("order", ["shuffled", "from the top"])
def test_rings_out_of_elevation_order_give_the_same_image(sweep: LadarScan, order: str) -> None:
    n = int(sweep.ring.max()) + 1
    if order == "shuffled":
        new_of_old = np.random.default_rng(0).permutation(n)
    else:
        new_of_old = n - 1 - np.arange(n)
    valid, xyz = _image(sweep)
    valid_r, xyz_r = _image(_renumbered(sweep, new_of_old))
    assert valid_r.sum() == valid.sum() > 1000
    np.testing.assert_array_equal(valid_r, valid)
    np.testing.assert_array_equal(xyz_r, xyz)
    # and without the renumbering the rows would be wrong: the check is what fixed it
    raw = PixelLevel(SPConfig())
    raw._rings_checked = True
    assert not np.array_equal(raw.step(_renumbered(sweep, new_of_old), np.eye(4), 0).xyz_s, xyz)


def test_ring_rows_ranks_the_rings_present_and_keeps_the_others() -> None:
    # rings 1, 4 and 6 at elevations +10, -10 and 0 degrees; 0, 2, 3 and 5 absent
    el = np.deg2rad([10.0, -10.0, 0.0])
    ring = np.repeat([1, 4, 6], 5)
    xyz = np.stack([np.cos(el), np.zeros(3), np.sin(el)], axis=1).repeat(5, axis=0) * 20.0
    rows = ring_rows(xyz, ring)
    assert rows.tolist() == [0, 6, 2, 3, 1, 5, 4]  # lowest (4) -> 1, middle (6) -> 4, top -> 6
    assert ring_rows(xyz, ring, zero_at_bottom=False).tolist() == [0, 1, 2, 3, 6, 5, 4]
    assert ring_rows(np.zeros((0, 3)), np.zeros(0, np.int64)) is None

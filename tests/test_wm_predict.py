"""The prediction chain of the node (reference 001, 4.2 item 2): a predicted range image compared
with the observed sweep gives surprise points where the world changed; surprises that stay
open a ``world_change`` event; surprise points are next cycle's attention, and inside an
attention window a small group becomes an entity hypothesis it would not be outside one.
Also: each map level's slow work runs at the level's own period."""

from __future__ import annotations

import numpy as np
import pytest
from test_sp_levels_units import SENSOR_H, H, W, _scan_of, flat_scene

import kd_store
from kd_store import Level
from sp.egosphere import EgosphereConfig
from sp.pipeline import SPConfig
from wm import predict
from wm.config import NodeConfig, PoseSource, PredictionConfig
from wm.entities import KDSensoryProcessor

BOX = dict(box_xy=(12.0, 0.5), half=1.0, top=1.5)


def _world(xyz_sensor: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Sensor points of a flat scene (sensor at the origin) in a world where it is at z = H."""
    return xyz_sensor[valid] + np.array([0.0, 0.0, SENSOR_H])


def _T_world_ladar() -> np.ndarray:
    T = np.eye(4)
    T[2, 3] = SENSOR_H
    return T


def _prediction_of(points_world: np.ndarray, cfg: PredictionConfig) -> predict.RangePrediction:
    """A predicted range image of the empty scene, as the ray cast would give it."""
    T = _T_world_ladar()
    p = points_world - T[:3, 3]
    el = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))
    span = (float(el.min()) - 1e-3, float(el.max()) + 1e-3)
    rng, _ = predict.range_image(p, cfg.range_image_hw, span)
    return predict.RangePrediction(0, T, rng, span)


def test_a_new_object_is_a_surprise_where_it_stands_and_the_unchanged_world_is_not() -> None:
    cfg = PredictionConfig()
    empty = _world(*flat_scene(box_xy=None)[:2])
    xyz, valid, on_box = flat_scene(**BOX)
    pred = _prediction_of(empty, cfg)

    same = predict.compare(pred, empty, _T_world_ladar(), cfg)
    assert same is not None and same.n_compared > 100
    assert same.surprise_fraction == 0.0 and len(same.surprise_world_xyz) == 0
    assert same.median_abs_error_m < 0.05

    changed = predict.compare(pred, _world(xyz, valid), _T_world_ladar(), cfg)
    assert changed is not None and changed.surprise_fraction > 0.0
    s = changed.surprise_world_xyz
    assert len(s) > 0
    # the surprises lie on the box that appeared (its footprint, up to its top); a far ground
    # pixel of the coarse image may differ by more than mismatch_m at grazing incidence
    (bx, by), half = BOX["box_xy"], BOX["half"]
    on = (np.abs(s[:, 0] - bx) <= half + 0.05) & (np.abs(s[:, 1] - by) <= half)
    assert on.mean() >= 0.95 and np.all(s[on, 2] <= BOX["top"] + 0.05)
    # and it covers most of the box's returns (one pixel of the coarse image may hold ground)
    assert on.sum() >= 0.5 * min(int(on_box.sum()), cfg.max_attention_points)


def _comparison(fraction: float) -> predict.Comparison:
    return predict.Comparison(0.1, fraction, 1000, np.zeros((0, 3)))


def test_a_surprise_that_stays_opens_a_world_change_event_and_closes_it_when_gone() -> None:
    kd = kd_store.open(":memory:")
    ev = predict.SurpriseEvents(threshold=0.02)
    t = [1_000_000_000 * k for k in range(1, 6)]
    kd.begin_cycle(t[0])
    ev.update(kd, _comparison(0.10), t[0])  # once: not yet an event
    assert kd.sql("SELECT count(*) AS n FROM events").column("n")[0].as_py() == 0
    ev.update(kd, _comparison(0.01), t[1])  # gone again: the run restarts
    ev.update(kd, _comparison(0.10), t[2])
    ev.update(kd, _comparison(0.08), t[3])  # stayed over two comparisons: an event
    rows = kd.sql("SELECT class_name, t_start_ns, t_end_ns FROM events").to_pylist()
    assert len(rows) == 1 and rows[0]["class_name"] == "world_change"
    assert rows[0]["t_start_ns"] == t[2]  # it began at the first of the two
    ev.update(kd, _comparison(0.0), t[4])
    rows = kd.sql("SELECT t_start_ns, t_end_ns FROM events").to_pylist()
    assert rows == [{"t_start_ns": t[2], "t_end_ns": t[4]}]


@pytest.mark.parametrize("attended", [False, True])
def test_attention_lets_a_small_group_become_a_hypothesis(attended: bool) -> None:
    """A post 25 m away covers 3 pixels, fewer than an object hypothesis needs: only inside an
    attention window (where the world model saw a surprise) does it become an entity."""
    box = dict(box_xy=(25.0, 0.3), half=0.2, top=1.0)
    xyz, valid, on_box = flat_scene(**box)
    assert 2 <= on_box.sum() < 4  # below SegmentConfig.min_pixels, at least min_pixels_attended
    kd = kd_store.open(":memory:")
    sp = KDSensoryProcessor(kd, SPConfig(egosphere=EgosphereConfig(n_rows=H, n_cols=W)))
    att = np.array([[25.0, 0.3, 0.5]]) if attended else None
    result = None
    for k in range(5):  # a hypothesis is born after M of N sweeps
        scan = _scan_of(xyz, valid, k * 100_000_000)
        result = sp.process(scan, _T_world_ladar(), attention_world_xyz=att)
    assert result is not None
    img4 = result.entity_images[4]
    objects = [f for f in kd.entities() if f.level == Level.OBJECT]
    if attended:
        assert len(objects) == 1 and np.all(img4[on_box & (img4 >= 0)] == objects[0].id)
        assert np.count_nonzero(img4[on_box] >= 0) >= 2
        np.testing.assert_allclose(objects[0].state.position_xyz[:2], [25.0, 0.3], atol=0.5)
    else:
        assert objects == [] and not np.any(img4[on_box] >= 0)


def test_each_level_updates_its_terrain_at_its_own_period(monkeypatch, tmp_path) -> None:
    from fixtures.simulate import simulate_to_log
    from wm import node as node_module
    from wm.run import run_node

    calls: dict[str, int] = {}
    real = node_module.update_terrain

    def counting(level, config):
        calls[level.name] = calls.get(level.name, 0) + 1
        return real(level, config)

    monkeypatch.setattr(node_module, "update_terrain", counting)
    log = simulate_to_log("default", tmp_path / "d.mcap", seconds=3.0, seed=3, progress=False)
    periods = {"primitive": 0.2, "subsystem": 0.5, "vehicle": 1.0, "section": 5.0}
    cfg = NodeConfig(pose_source=PoseSource.ODOMETRY, use_sp=False, level_periods_s=periods)
    node = run_node(log, ":memory:", cfg)
    span_s = (node.stats.sweeps - 1) * 0.1  # sweeps at 10 Hz
    node.kd.close()
    for name, period in periods.items():  # due at the first sweep, then once a period
        expect = 1 + int(span_s / period + 1e-9)
        assert abs(calls[name] - expect) <= 1, (name, calls[name], expect)
    assert calls["primitive"] > 2 * calls["vehicle"] > calls["section"] == 1

"""An object's texture through SP (sp.computation.segment_roughness, level 4): a box with a
smooth face and a "bush" of the same size whose returns come from inside it, as leaves scatter
a LADAR's returns, are told apart by the roughness_m their KD frames carry and the classifier
is given."""

from __future__ import annotations

import numpy as np
from test_sp_levels_units import SENSOR_H, _scan_of, flat_scene

import kd_store
from kd_store import Level
from sp.context import SPConfig
from sp.egosphere import EgosphereConfig
from wm.entities import KDSensoryProcessor


def _run(foliage_depth_m: float, n_sweeps: int = 8):
    """SP over a 2 m box 10 m ahead, its returns pushed ``foliage_depth_m`` into it on average
    along their rays (exponentially distributed) and 1 cm range noise everywhere; the KD and
    the sensory processor."""
    rng = np.random.default_rng(3)
    kd = kd_store.open(":memory:")
    cfg = SPConfig(egosphere=EgosphereConfig(n_rows=32, n_cols=360, max_returns=1))
    sp = KDSensoryProcessor(kd, cfg)
    T = np.eye(4)
    T[2, 3] = SENSOR_H
    for k in range(n_sweeps):
        xyz, valid, box = flat_scene(box_xy=(10.0, 0.0))
        r = np.linalg.norm(xyz, axis=2)
        extra = rng.normal(0.0, 0.01, r.shape)
        if foliage_depth_m > 0:
            extra += np.where(box, rng.exponential(foliage_depth_m, r.shape), 0.0)
        xyz = xyz * ((r + extra) / r)[..., None]
        assert sp.process(_scan_of(xyz, valid, k * 100_000_000), T).ok
    return kd, sp


def _texture(foliage_depth_m: float) -> tuple[float, float]:
    """(the KD frame's last roughness_m, the one level 4 classifies by) of the one object."""
    kd, sp = _run(foliage_depth_m)
    objects = [f for f in kd.entities() if f.level == Level.OBJECT]
    assert len(objects) == 1
    f = objects[0]
    rows = dict(zip(*sp.level4.class_rows(), strict=True))
    (row,) = rows.values()
    return f.attributes["roughness_m"].observed, row["roughness_m"]


def test_a_smooth_face_and_foliage_differ_in_texture() -> None:
    smooth_kd, smooth_row = _texture(0.0)
    leafy_kd, leafy_row = _texture(0.2)
    # 1 cm noise: a second difference of it has a mean |.| of about 0.02 m
    assert smooth_kd < 0.05 and smooth_row < 0.05
    assert leafy_kd > 0.15 and leafy_row > 0.15

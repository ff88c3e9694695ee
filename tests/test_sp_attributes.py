"""Level 1 attribute images (sp.attributes) against analytic surfaces and ramps."""

from __future__ import annotations

import numpy as np
import pytest

from logs.types import LadarScan
from sp.attributes import (
    AttributeImageError,
    egosphere_attributes,
    image_attributes,
    intensity,
    range_rate,
    spatial_gradients,
    surface_normals,
    temporal_gradient,
)
from sp.egosphere import EgosphereConfig, to_egosphere


def ground_scan(height_m: float, noise_m: float = 0.0, t_ns: int = 0, seed: int = 0) -> LadarScan:
    """A 32-beam LADAR over a flat ground plane ``height_m`` below it."""
    el = np.deg2rad(np.linspace(-25, -5, 32))
    az = np.pi - (np.arange(512) + 0.5) * 2 * np.pi / 512
    E, A = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    r = height_m / -d[:, 2]
    r = r + np.random.default_rng(seed).normal(0, noise_m, r.shape) if noise_m else r
    ring = np.repeat(np.arange(32), 512).astype(np.uint16)  # beam 0 is the lowest
    n = len(r)
    return LadarScan(
        t_ns,
        "ladar",
        (d * r[:, None]).astype(np.float32),
        np.full(n, 0.5, np.float32),
        np.zeros(n, np.int64),
        ring,
    )


CFG = EgosphereConfig(n_rows=32, n_cols=512, max_returns=1)


def test_gradients_of_a_ramp():
    rows, cols = np.mgrid[0:40, 0:50]
    gx, gy = spatial_gradients(2.0 * cols + 3.0 * rows)
    assert np.allclose(gx, 2.0) and np.allclose(gy, 3.0)


def test_temporal_gradient_and_range_rate():
    a = np.full((4, 5), 10.0, np.float32)
    assert np.allclose(temporal_gradient(a + 2.0, a, 0.5), 4.0)
    assert np.allclose(range_rate(a - 1.0, a, 0.1), -10.0)
    with pytest.raises(AttributeImageError, match=r"\(4, 5\) now vs \(4, 4\)"):
        temporal_gradient(a, a[:, :4], 0.1)
    with pytest.raises(AttributeImageError, match="dt_s=0"):
        range_rate(a, a, 0)


def test_intensity_refuses_what_is_not_an_image():
    assert intensity(np.array([[[255, 0, 0]]], np.uint8))[0, 0] == pytest.approx(0.299 * 255)
    with pytest.raises(AttributeImageError, match="bool"):
        intensity(np.zeros((3, 3), bool))
    with pytest.raises(AttributeImageError, match=r"\(3, 3, 2\)"):
        intensity(np.zeros((3, 3, 2)))


def test_ground_plane_normals_point_up_and_it_is_smooth():
    img = to_egosphere(ground_scan(1.8), CFG)
    att = egosphere_attributes(img)
    n = att.normals[2:-2]  # interior rows
    ok = np.all(np.isfinite(n), axis=-1)
    assert ok.mean() > 0.95
    assert np.allclose(n[ok], [0.0, 0.0, 1.0], atol=1e-3)
    assert np.nanmax(att.roughness_m[2:-2]) < 0.01


def test_tilted_plane_normal():
    # Plane through (10, 0, 0) with normal (-1, 0, 1)/sqrt(2): z = x - 10 ahead of the sensor.
    rows, cols = np.mgrid[0:20, 0:30].astype(np.float64)
    x = 5.0 + 0.1 * cols
    y = -1.0 + 0.1 * rows
    xyz = np.stack([x, y, x - 10.0], -1)
    n = surface_normals(xyz)[1:-1, 1:-1]
    want = np.array([-1.0, 0.0, 1.0]) / np.sqrt(2)  # faces the sensor at the origin
    assert np.allclose(n, want, atol=1e-6)


def test_roughness_measures_bumps_not_slopes():
    smooth = egosphere_attributes(to_egosphere(ground_scan(1.8), CFG))
    rough = egosphere_attributes(to_egosphere(ground_scan(1.8, noise_m=0.05), CFG))
    assert np.nanmax(smooth.roughness_m[2:-2]) < 1e-3
    assert np.nanmedian(rough.roughness_m[2:-2]) > 0.01


def test_range_rate_of_a_sensor_rising_over_the_ground():
    before = egosphere_attributes(to_egosphere(ground_scan(1.8, t_ns=0), CFG))
    now = egosphere_attributes(to_egosphere(ground_scan(2.0, t_ns=100_000_000), CFG), before)
    # r = h / sin(-el): dr/dt = (dh/dt) / sin(-el) with dh/dt = 2 m/s.
    el = np.deg2rad(np.linspace(-25, -5, 32))[::-1]
    want = 2.0 / np.sin(-el)
    assert np.allclose(now.dr_dt, want[:, None], rtol=1e-4)
    assert now.dI_dt is not None and np.allclose(now.dI_dt, 0.0)


def test_image_attributes_chain():
    _, cols = np.mgrid[0:32, 0:32]
    first = image_attributes(0, (4 * cols).astype(np.uint8))
    second = image_attributes(50_000_000, (4 * cols + 1).astype(np.uint8), first)
    assert np.allclose(second.dI_dx, 4.0) and np.allclose(second.dI_dt, 20.0)
    assert set(second.names()) == {"intensity", "dI_dx", "dI_dy", "dI_dt"}


def test_attribute_pyramids_average_known_pixels():
    from sp.attributes import Level1Attributes, attribute_pyramids

    rng = np.random.default_rng(0)
    r = rng.uniform(5, 50, (256, 256)).astype(np.float32)
    r[:8, :8] = np.nan  # an unknown 8x8 corner: one level-3 pixel has nothing under it
    r[8, 8] = np.nan
    n = np.zeros((256, 256, 3), np.float32)
    n[..., 2] = 1.0
    pyr = attribute_pyramids(Level1Attributes(0, range_m=r, normals=n), levels=4)
    assert [p.shape for p in pyr["range_m"]] == [(256, 256), (128, 128), (64, 64), (32, 32)]
    assert np.isnan(pyr["range_m"][3][0, 0])
    block = r[8:16, 8:16]
    assert pyr["range_m"][3][1, 1] == pytest.approx(np.nanmean(block), rel=1e-5)
    assert np.allclose(pyr["normals"][2], [0.0, 0.0, 1.0])

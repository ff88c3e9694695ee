"""A priori rasters (the real Argoverse 2 ground-height map) and map registration."""

from __future__ import annotations

import numpy as np
import pytest

from maps.apriori import AprioriError, ElevationRaster, load_av2_ground_height, write_raster
from maps.fusion import fuse_points
from maps.level import LevelConfig, MapLevel
from maps.registration import RegistrationError, register_levels, register_to_raster
from maps.stack import MapStack, StackConfig


@pytest.fixture(scope="module")
def av2_raster(real_data) -> ElevationRaster:
    return load_av2_ground_height(real_data / "av2" / "map")


def _noisy_shifted(raster: ElevationRaster, offset_xy: np.ndarray, seed: int) -> ElevationRaster:
    rng = np.random.default_rng(seed)
    noisy = raster.heights_m + rng.normal(0.0, 0.05, raster.heights_m.shape)
    return ElevationRaster(noisy, raster.A_pixel_world, "noisy copy").shifted(offset_xy)


def test_av2_raster_geometry(av2_raster: ElevationRaster) -> None:
    assert av2_raster.heights_m.shape == (785, 880)
    assert av2_raster.pixel_size_m == pytest.approx(0.3)
    # pixel centres map back onto themselves
    cr = np.array([[0.5, 0.5], [879.5, 784.5], [440.5, 300.5]])
    xy = av2_raster.pixel_to_world(cr)
    np.testing.assert_allclose(av2_raster.world_to_pixel(xy), cr, atol=1e-9)
    h = av2_raster.sample(xy)
    expect = av2_raster.heights_m[cr[:, 1].astype(int), cr[:, 0].astype(int)]
    np.testing.assert_array_equal(h, expect)
    # the AV2 ego pose of this log is around city (5200, 2400): inside the raster, at 40-80 m
    assert 40.0 < np.nanmedian(av2_raster.sample(np.array([[5204.4, 2401.5]]))) < 80.0


@pytest.mark.parametrize(("res", "offset"), [(0.3, (2.7, -1.9)), (0.6, (-3.1, 4.4))])
def test_av2_raster_registers_against_shifted_noisy_copy(
    av2_raster: ElevationRaster, res: float, offset: tuple[float, float]
) -> None:
    centre = av2_raster.pixel_to_world(np.array([[440.0, 392.0]]))[0]
    ref = MapLevel(LevelConfig("ref", res, 256, keep_tiles=False))
    mov = MapLevel(LevelConfig("mov", res, 256, keep_tiles=False))
    ref.move_to(centre)
    mov.move_to(centre)
    write_raster(ref, av2_raster, 0.01, only_empty=False)
    write_raster(mov, _noisy_shifted(av2_raster, np.array(offset), seed=1), 0.01, only_empty=False)
    got = register_levels(ref, mov)
    assert np.all(np.abs(got.offset_xy_m - offset) < 0.5 * res), got
    assert got.confidence > 0.5 and got.peak > 0.9


def test_fused_local_map_registers_against_the_raster(av2_raster: ElevationRaster) -> None:
    """A local map built from points with a drifting pose: the offset is the drift."""
    rng = np.random.default_rng(5)
    centre = av2_raster.pixel_to_world(np.array([[440.0, 392.0]]))[0]
    local = MapLevel(LevelConfig("local", 0.6, 160, keep_tiles=False))
    local.move_to(centre)
    xy = centre + rng.uniform(-45, 45, size=(150000, 2))
    z = av2_raster.sample(xy) + rng.normal(0, 0.03, len(xy))
    drift = np.array([-1.3, 2.0])
    fuse_points(local, np.column_stack([xy + drift, z]), 0.03**2, t_ns=0)
    got = register_to_raster(local, av2_raster)
    assert np.all(np.abs(got.offset_xy_m - drift) < 0.3), got  # half a 0.6 m cell
    assert got.peak > 0.9  # (the pyramid's confidence can be 0 here: see its aperture test)
    # without leaving steep steps out of both maps, the holes fusion leaves on them (points
    # gated as obstacles) pull the peak off by most of a cell
    off = register_to_raster(local, av2_raster, max_step_m=None)
    assert np.max(np.abs(off.offset_xy_m - drift)) > np.max(np.abs(got.offset_xy_m - drift))


def test_stack_takes_apriori_terrain_at_the_coarse_end(av2_raster: ElevationRaster) -> None:
    levels = (LevelConfig("subsystem", 0.4, 64), LevelConfig("vehicle", 4.0, 32))
    stack = MapStack(StackConfig(levels=levels))
    centre = av2_raster.pixel_to_world(np.array([[440.0, 392.0]]))[0]
    stack.move_to(centre)
    written = stack.set_apriori(av2_raster)
    assert set(written) == {"vehicle"} and written["vehicle"] > 500
    vehicle = stack.level("vehicle")
    cells = vehicle.cell_to_world(vehicle.world_to_cell(centre[None]))
    prior = vehicle.read("elevation", cells)[0]
    assert abs(prior - np.nanmean(av2_raster.sample(cells + np.array([[0.5, 0.5]])))) < 1.0
    # moving 40 m east brings 10 new columns in: they are filled from the raster as they enter
    stack.move_to(centre + np.array([40.0, 0.0]))
    fresh = MapLevel(vehicle.config)
    fresh.origin_cell = vehicle.origin_cell.copy()
    write_raster(fresh, av2_raster, 0.25)
    east = vehicle.window("elevation")[:, -10:]
    assert np.isfinite(east).sum() > 100  # the raster is 264 m wide: these cells are on it
    np.testing.assert_array_equal(east, fresh.window("elevation")[:, -10:])
    # observed points refine the prior: the Kalman gain favours the precise measurement
    p = np.array([[*cells[0], prior + 0.5]])
    stack.move_to(centre)
    stack.fuse(p, variance_m2=1e-4, t_ns=1)
    assert vehicle.read("elevation", cells)[0] == pytest.approx(prior + 0.5, abs=0.01)


def test_bad_rasters_and_registrations_are_refused(tmp_path) -> None:
    with pytest.raises(AprioriError, match="Sim2_city"):
        load_av2_ground_height(tmp_path)
    with pytest.raises(AprioriError, match=r"\(H, W\)"):
        ElevationRaster(np.zeros(5), np.eye(2, 3))
    with pytest.raises(RegistrationError, match="resolution"):
        register_levels(MapLevel(LevelConfig("a", 0.4, 8)), MapLevel(LevelConfig("b", 0.5, 8)))

"""Simulated sensors against analytic truth in tiny worlds (flat ground, boxes at known places)."""

from __future__ import annotations

import numpy as np
import pytest

from core.geometry import NS_PER_S, se3_inverse, transform_points
from fixtures.scenario import (
    AgentSpec,
    ObjectClass,
    ObjectSpec,
    RouteSpec,
    Scenario,
    TerrainSpec,
    load_scenario,
)
from fixtures.sensors import Camera, CameraConfig, Ladar, LadarConfig, Odometry, OdometryConfig
from fixtures.world import World

MOUNT = (0.0, 0.0, 2.0)  # LADAR mount in the body frame for these tests
BOX_MIN, BOX_MAX = np.array([13.0, 2.0, -0.5]), np.array([17.0, 8.0, 3.0])  # building, z0 = 0


def flat_world(speed_mps: float = 0.0, objects=None, agents=None, route_y: float = 0.0) -> World:
    """Flat ground z = 0 (100 m square) and a static ego on a straight +x route."""
    if objects is None:  # a 4 x 6 x 3 m building at (15, 5): occupies BOX_MIN..BOX_MAX
        objects = [ObjectSpec(ObjectClass.BUILDING, (15.0, 5.0), (4.0, 6.0, 3.0), 0.0)]
    scenario = Scenario(
        name="flat",
        terrain=TerrainSpec(
            size_m=100.0, resolution_m=2.0, hills_amplitude_m=0.0, roughness_rms_m=0.0
        ),
        route=RouteSpec(waypoints=[(0.0, route_y), (45.0, route_y)], speed_mps=speed_mps),
        objects=objects,
        agents=agents or [],
    )
    return World(scenario)


def small_ladar(**kw) -> LadarConfig:
    """A small LADAR without noise or dropouts (each test turns on what it measures)."""
    base = dict(
        n_beams=16,
        n_azimuth=360,
        range_noise_sigma_m=0.0,
        range_noise_per_m=0.0,
        dropout_prob=0.0,
        weak_dropout_max=0.0,
        intensity_noise_rel=0.0,
        intensity_noise_abs=0.0,
        mount_xyz=MOUNT,
        max_range_m=60.0,
    )
    base.update(kw)
    return LadarConfig(**base)


def analytic_range(dirs: np.ndarray, origin=MOUNT, box=(BOX_MIN, BOX_MAX)) -> np.ndarray:
    """Range along unit rays from ``origin`` to the plane z = 0 or the axis-aligned box."""
    o = np.asarray(origin, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_plane = np.where(dirs[:, 2] < 0, -o[2] / dirs[:, 2], np.inf)
        t1 = (box[0] - o) / dirs
        t2 = (box[1] - o) / dirs
    t_near = np.max(np.minimum(t1, t2), axis=1)
    t_far = np.min(np.maximum(t1, t2), axis=1)
    t_box = np.where((t_near <= t_far) & (t_near > 0), t_near, np.inf)
    return np.minimum(t_plane, t_box)


def all_ray_dirs(ladar: Ladar) -> np.ndarray:
    return ladar.dirs_sensor.reshape(-1, 3)


def test_zero_noise_ranges_match_the_analytic_plane_and_box() -> None:
    world = flat_world()
    cfg = small_ladar()
    ladar = Ladar(cfg, world, np.random.default_rng(0))
    scan = ladar.sweep(0)
    p = scan.points_xyz.astype(np.float64)
    r = np.linalg.norm(p, axis=1)
    expected = analytic_range(p / r[:, None])
    assert np.max(np.abs(r - expected)) < 2e-3
    # every ray with an analytic hit inside the range window returns, and only those
    r_all = analytic_range(all_ray_dirs(ladar))
    n_expected = int(np.sum((r_all >= cfg.min_range_m) & (r_all <= cfg.max_range_m)))
    assert scan.n_points == n_expected
    on_box = np.all((transform_points(np.eye(4), p) + MOUNT >= BOX_MIN - 1e-3), axis=1)
    assert on_box.sum() > 20  # the box is really seen
    assert scan.points_xyz.dtype == np.float32 and scan.ring.dtype == np.uint16


def test_range_noise_has_the_configured_sigma() -> None:
    world = flat_world()
    scan = Ladar(small_ladar(range_noise_sigma_m=0.05), world, np.random.default_rng(1)).sweep(0)
    p = scan.points_xyz.astype(np.float64)
    r = np.linalg.norm(p, axis=1)
    residual = r - analytic_range(p / r[:, None])
    assert scan.n_points > 2000
    assert abs(residual.mean()) < 0.005
    assert residual.std() == pytest.approx(0.05, rel=0.06)


def test_dropout_fraction_matches() -> None:
    world = flat_world()
    full = Ladar(small_ladar(), world, np.random.default_rng(2)).sweep(0)
    dropped = Ladar(small_ladar(dropout_prob=0.3), world, np.random.default_rng(2)).sweep(0)
    assert dropped.n_points / full.n_points == pytest.approx(0.7, abs=0.03)


def test_point_times_increase_across_the_sweep() -> None:
    ladar = Ladar(small_ladar(), flat_world(), np.random.default_rng(0))
    scan = ladar.sweep(5 * NS_PER_S)
    t = scan.t_offset_ns
    assert t.dtype == np.int64 and scan.t_ns == 5 * NS_PER_S
    assert np.all(np.diff(t) >= 0) and t[0] >= 0 and t[-1] < ladar.period_ns
    assert t[-1] > 0.9 * ladar.period_ns  # the sweep spans the period
    # azimuth advances with time: column j fires at j * period / n_azimuth
    az = np.arctan2(scan.points_xyz[:, 1], scan.points_xyz[:, 0])
    expected_az = np.deg2rad(-180.0) + 2 * np.pi * t / ladar.period_ns
    assert np.allclose(np.angle(np.exp(1j * (az - expected_az))), 0.0, atol=0.01)


def test_motion_during_a_sweep_shifts_wall_points_by_v_dt() -> None:
    wall = [ObjectSpec(ObjectClass.WALL, (21.0, 0.0), (2.0, 60.0, 6.0), 0.0)]  # face at x = 20
    v = 10.0
    static = Ladar(small_ladar(), flat_world(0.0, wall), np.random.default_rng(0)).sweep(0)
    moving = Ladar(small_ladar(), flat_world(v, wall), np.random.default_rng(0)).sweep(0)

    def wall_points(scan):
        # the wall is the only thing that far ahead above the ground (z = -2 m in this frame)
        on_wall = (scan.points_xyz[:, 0] > 10.0) & (scan.points_xyz[:, 2] > -1.9)
        keys = scan.t_offset_ns[on_wall] * 100 + scan.ring[on_wall]
        return dict(zip(keys.tolist(), scan.points_xyz[on_wall].astype(np.float64), strict=True))

    a, b = wall_points(static), wall_points(moving)
    common = sorted(set(a) & set(b))
    assert len(common) > 50
    dt_s = np.array([k // 100 for k in common]) / NS_PER_S
    dx = np.array([a[k][0] - b[k][0] for k in common])
    assert np.ptp(dt_s) > 0.03  # the wall spans a good part of the sweep
    assert np.allclose(dx, v * dt_s, atol=2e-3)
    # deskewed with the true motion, the moving sensor's points lie on the wall face x = 20
    x_world = np.array([b[k][0] for k in common]) + MOUNT[0] + v * dt_s
    assert np.allclose(x_world, 20.0, atol=2e-3)


def test_moving_agent_is_placed_at_each_rays_time() -> None:
    # a 4 x 2 x 2 m vehicle driving across in front of a static sensor at 8 m/s
    agent = AgentSpec(
        cls=ObjectClass.VEHICLE,
        path=[(10.0, -30.0), (10.0, 30.0)],
        speed_mps=8.0,
        start_m=28.0,
        size=(4.0, 2.0, 2.0),
    )
    world = flat_world(objects=[], agents=[agent])
    scan = Ladar(small_ladar(), world, np.random.default_rng(0)).sweep(0)
    p = scan.points_xyz.astype(np.float64)
    r = np.linalg.norm(p, axis=1)
    d = p / r[:, None]
    t_s = scan.t_offset_ns / NS_PER_S
    y_c = -30.0 + 28.0 + 8.0 * t_s  # the agent's centre at each ray's own time (heading +y)
    centers = np.column_stack([np.full_like(y_c, 10.0), y_c, np.full_like(y_c, 1.0)])
    o = np.asarray(MOUNT, dtype=np.float64)
    # the agent's mesh placed there, independently of the sensor's culling and grouping
    t_near, _ = world.cast_agent(
        0, np.broadcast_to(o, d.shape), d, centers, np.full(len(d), np.pi / 2)
    )
    on_agent = np.isfinite(t_near)
    assert on_agent.sum() > 10
    assert np.allclose(r[on_agent], t_near[on_agent], atol=1e-4)
    # the rest is ground
    assert np.allclose(r[~on_agent], -o[2] / d[~on_agent, 2], atol=2e-3)


def test_same_seed_same_scan_other_seed_other_noise() -> None:
    world = flat_world()
    cfg = small_ladar(range_noise_sigma_m=0.02, dropout_prob=0.05)
    a = Ladar(cfg, world, np.random.default_rng(5)).sweep(0)
    b = Ladar(cfg, world, np.random.default_rng(5)).sweep(0)
    c = Ladar(cfg, world, np.random.default_rng(6)).sweep(0)
    for field in ("points_xyz", "intensity", "t_offset_ns", "ring"):
        assert np.array_equal(getattr(a, field), getattr(b, field))
    assert a.n_points != c.n_points or not np.array_equal(a.points_xyz, c.points_xyz)


def test_camera_depth_agrees_with_ladar_range_on_common_surfaces() -> None:
    world = flat_world()
    ladar = Ladar(small_ladar(n_beams=32, n_azimuth=720), world, np.random.default_rng(0))
    cam_cfg = CameraConfig(width=128, height=96, hfov_deg=100.0, noise_sigma_gray=0.0)
    camera = Camera(cam_cfg.without_depth_errors(), world, np.random.default_rng(0))
    scan, frame = ladar.sweep(0), camera.render(0)
    assert frame.image.shape == (96, 128, 3) and frame.depth.dtype == np.float32
    T_cam_ladar = se3_inverse(camera.T_body_camera) @ ladar.T_body_ladar
    pc = transform_points(T_cam_ladar, scan.points_xyz.astype(np.float64))
    pc = pc[pc[:, 2] > 0.5]
    uv = pc[:, :2] / pc[:, 2:] * [frame.K[0, 0], frame.K[1, 1]] + frame.K[:2, 2]
    u0, v0 = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    inside = (u0 >= 0) & (v0 >= 0) & (u0 < 127) & (v0 < 95)
    pc, uv, u0, v0 = pc[inside], uv[inside], u0[inside], v0[inside]
    corners = np.stack(
        [
            frame.depth[v0, u0],
            frame.depth[v0, u0 + 1],
            frame.depth[v0 + 1, u0],
            frame.depth[v0 + 1, u0 + 1],
        ],
        axis=1,
    ).astype(np.float64)
    # on a plane 1/depth is affine in pixel coordinates, so bilinear interpolation of it is exact;
    # keep pixels whose 2x2 neighbourhood lies on one surface (no edge inside)
    inv = 1.0 / corners
    smooth = np.all(np.isfinite(inv), axis=1) & (np.ptp(inv, axis=1) < 0.2 * np.min(inv, axis=1))
    fu, fv = uv[:, 0] - u0, uv[:, 1] - v0
    inv_interp = (
        inv[:, 0] * (1 - fu) * (1 - fv)
        + inv[:, 1] * fu * (1 - fv)
        + inv[:, 2] * (1 - fu) * fv
        + inv[:, 3] * fu * fv
    )
    rel = np.abs(1.0 / inv_interp[smooth] - pc[smooth, 2]) / pc[smooth, 2]
    assert smooth.sum() > 200
    assert np.median(rel) < 1e-3 and np.percentile(rel, 95) < 1e-2


def test_camera_sees_sky_above_and_ground_below() -> None:
    cfg = CameraConfig(noise_sigma_gray=0.0, shot_noise_gain=0.0).without_depth_errors()
    frame = Camera(cfg, flat_world(), np.random.default_rng(0)).render(0)
    assert np.all(np.isnan(frame.depth[0])) and np.all(np.isfinite(frame.depth[-1]))
    assert frame.image[0].mean() > frame.image[-1].mean()  # bright sky, darker ground
    assert frame.K[0, 0] == pytest.approx(128.0)  # 90 deg over 256 px


def drive(world: World, cfg: OdometryConfig, seed: int, seconds: float):
    odom = Odometry(cfg, world, np.random.default_rng(seed))
    errors, dists = [], []
    step_ns = round(NS_PER_S / cfg.rate_hz)
    for t in range(0, round(seconds * NS_PER_S) + 1, step_ns):
        frame, _ = odom.step(t)
        truth = world.T_world_body(t)
        errors.append(np.linalg.norm(frame.T_parent_child[:3, 3] - truth[:3, 3]))
        dists.append(odom.distance_m)
    return np.array(errors), np.array(dists), odom


@pytest.fixture(scope="module")
def default_world() -> World:
    return World(load_scenario("default"))


def test_noise_free_odometry_is_exact(default_world: World) -> None:
    quiet = OdometryConfig(0.0 + 50.0, 0.0, 0.0, 0.0, 0.0)
    errors, dists, _ = drive(default_world, quiet, seed=0, seconds=20.0)
    assert dists[-1] > 100.0 and errors.max() < 1e-6


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_odometry_drift_grows_with_distance(default_world: World, seed: int) -> None:
    errors, dists, _ = drive(default_world, OdometryConfig(), seed=seed, seconds=60.0)
    assert dists[-1] > 400.0
    # grows: the error over the last tenth of the drive exceeds the one over the first tenth
    n = len(errors) // 10
    assert errors[-n:].mean() > errors[:n].mean()
    # plausible wheel/gyro drift: between 0.05 % and 5 % of the distance driven
    assert 5e-4 < errors[-1] / dists[-1] < 0.05


def test_imu_measures_gravity_at_rest() -> None:
    world = flat_world()
    odom = Odometry(OdometryConfig(imu=True), world, np.random.default_rng(0))
    for t in range(0, NS_PER_S // 5, NS_PER_S // 50):
        frame, imu = odom.step(t)
    assert imu is not None
    assert np.allclose(imu.linear_acceleration, [0.0, 0.0, 9.80665], atol=0.3)
    assert np.allclose(frame.twist_linear, 0.0, atol=0.3)

"""The simulator is not generous: appearance overlaps between classes, sizes stray beyond the
prototypes, LADAR ranges are noisy with dropouts, camera depth is imperfect, and the parking
lot packs many vehicles and pedestrians close together. Each property is measured from
simulated data against the world's ground truth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from core.geometry import NS_PER_S
from fixtures.scenario import (
    ObjectClass,
    ObjectSpec,
    PopulationSpec,
    RouteSpec,
    Scenario,
    TerrainSpec,
    load_scenario,
)
from fixtures.sensors import Camera, CameraConfig, Ladar, LadarConfig
from fixtures.simulate import Simulator
from fixtures.world import CLASS_INDEX, LEAF_DEPTH_RANGE, World
from logs.types import ObjectBoxes

BUILDING = ObjectClass.BUILDING


def ray_box_entry(origins, dirs, center, yaw: float, half) -> np.ndarray:
    """(N,) range (m) at which each ray (origins, dirs (N, 3), world) enters the upright box
    (``center`` (3,), ``yaw`` rad about z, half-extents ``half`` (3,)): the slab test; inf
    for a miss or a ray starting inside."""
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # world -> box axes
    o, d = (origins - center) @ R.T, dirs @ R.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - o) / d, (half - o) / d
    t_near = np.max(np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2)), axis=1)
    t_far = np.min(np.where(np.isnan(t1), np.inf, np.maximum(t1, t2)), axis=1)
    return np.where((t_near <= t_far) & (t_near > 0), t_near, np.inf)


def flat_scenario(objects: list[ObjectSpec], populations=None, seed: int = 0) -> Scenario:
    """Flat ground (no hills, no roughness) and a static ego at the origin facing +x."""
    return Scenario(
        name="flat",
        seed=seed,
        terrain=TerrainSpec(
            size_m=200.0, resolution_m=2.0, hills_amplitude_m=0.0, roughness_rms_m=0.0
        ),
        route=RouteSpec(waypoints=[(0.0, 0.0), (45.0, 0.0)], speed_mps=0.0),
        objects=objects,
        populations=populations or [],
    )


@pytest.fixture(scope="module")
def parking_sweeps() -> list[tuple]:
    """(scan, truth) of six sweeps spread over the parking drive."""
    sim = Simulator("parking")
    return [sim.ladar.sweep_with_truth(k * 5 * NS_PER_S) for k in range(6)]


def per_object_median_intensity(sweeps, cls: ObjectClass, min_points: int = 20) -> np.ndarray:
    """Median LADAR intensity of each object of class ``cls`` with enough returns."""
    ids, values = [], []
    for scan, truth in sweeps:
        sel = truth.cls == CLASS_INDEX[cls]
        ids.append(truth.object_id[sel])
        values.append(scan.intensity[sel])
    ids, values = np.concatenate(ids), np.concatenate(values)
    out = [np.median(values[ids == i]) for i in np.unique(ids) if np.sum(ids == i) >= min_points]
    return np.asarray(out)


def test_intensity_varies_within_a_class_and_overlaps_other_classes(parking_sweeps) -> None:
    vehicles = per_object_median_intensity(parking_sweeps, ObjectClass.VEHICLE)
    persons = per_object_median_intensity(parking_sweeps, ObjectClass.PERSON, min_points=5)
    posts = per_object_median_intensity(parking_sweeps, ObjectClass.POST, min_points=5)
    terrain = per_object_median_intensity(parking_sweeps, ObjectClass.TERRAIN)
    assert vehicles.size >= 20 and persons.size >= 3 and posts.size >= 3
    # within a class: dark and bright paint, far more than incidence shading alone gives
    lo, hi = np.percentile(vehicles, [10, 90])
    assert hi / lo > 2.0, (lo, hi)
    # between classes: people, posts and the ground each look like some vehicle
    for other in (persons, posts, terrain):
        inside = (other >= vehicles.min()) & (other <= vehicles.max())
        assert inside.mean() >= 0.5, (other, vehicles.min(), vehicles.max())
    # and no class owns an intensity band: the class medians are not separable by thresholds
    assert vehicles.min() < np.median(persons) < vehicles.max()


FOLIAGE = (CLASS_INDEX[ObjectClass.BUSH], CLASS_INDEX[ObjectClass.TREE])


def test_range_noise_matches_its_model_against_the_cast_truth(parking_sweeps) -> None:
    cfg = LadarConfig()
    residuals, ranges = [], []
    for scan, truth in parking_sweeps:
        hard = ~np.isin(truth.cls, FOLIAGE)  # leaves have a model of their own (below)
        r_meas = np.linalg.norm(scan.points_xyz.astype(np.float64), axis=1)
        residuals.append((r_meas - truth.range_m)[hard])
        ranges.append(truth.range_m[hard])
    res, r = np.concatenate(residuals), np.concatenate(ranges)
    assert abs(res.mean()) < 0.002
    # points are float32: ~1e-6 relative, far below the noise
    for lo, hi in ((2.0, 10.0), (40.0, 120.0)):
        sel = (r >= lo) & (r < hi)
        assert sel.sum() > 300, (lo, hi, sel.sum())
        expected = np.sqrt(
            np.mean(np.hypot(cfg.range_noise_sigma_m, cfg.range_noise_per_m * r[sel]) ** 2)
        )
        assert res[sel].std() == pytest.approx(expected, rel=0.1), (lo, hi)
    near, far = (r < 10.0), (r >= 40.0)
    assert res[far].std() > 1.1 * res[near].std()  # the range-proportional part shows


def test_foliage_returns_come_from_inside_the_leaves() -> None:
    """A bush's and a tree crown's returns lie behind the cast surface, on average by the
    configured depth times the plant's own leaf depth and scattered as much (exponential),
    where a trunk's, a wall's and the ground's only carry the range noise: vegetation is rough
    to a LADAR, a hard shell is not. Plants differ: dense foliage stops a beam within
    centimetres, an open crown lets it in for decimetres."""
    cfg = LadarConfig()
    sim = Simulator("default", seed=8)
    world = sim.world
    depth: dict[str, list[np.ndarray]] = {"leaf": [], "hard": []}
    for k in range(8):
        t_ns = world.t0_ns + int((10.0 + k) * NS_PER_S)
        scan, truth = sim.ladar.sweep_with_truth(t_ns)
        r_meas = np.linalg.norm(scan.points_xyz.astype(np.float64), axis=1)
        _, origins, dirs = sim.ladar.rays_world(t_ns)
        z = origins[truth.ray // cfg.n_beams, 2] + dirs.reshape(-1, 3)[truth.ray, 2] * truth.range_m
        leaf = world.is_foliage(truth.object_id, z)
        scale = cfg.foliage_depth_m * world.leaf_depth_of(truth.object_id[leaf])
        depth["leaf"].append((r_meas - truth.range_m)[leaf] / scale)
        depth["hard"].append((r_meas - truth.range_m)[~leaf])
    leaf, hard = np.concatenate(depth["leaf"]), np.concatenate(depth["hard"])
    assert leaf.size > 300, leaf.size
    # in units of each plant's own mean depth: a standard exponential
    assert np.mean(leaf) == pytest.approx(1.0, rel=0.15)
    assert np.std(leaf) == pytest.approx(1.0, rel=0.2)
    assert np.mean(leaf < 0.0) < 0.15  # mostly behind the surface, not noise about it
    assert abs(np.mean(hard)) < 0.003 and np.std(hard) < 0.05
    plants = [o.object_id for o in world.statics if o.cls in (ObjectClass.BUSH, ObjectClass.TREE)]
    others = [
        o.object_id for o in world.statics if o.cls not in (ObjectClass.BUSH, ObjectClass.TREE)
    ]
    own = world.leaf_depth_of(np.array(plants))
    lo, hi = LEAF_DEPTH_RANGE
    assert len(plants) >= 10 and np.all((own >= lo) & (own <= hi))
    assert own.max() > 3 * own.min()  # dense and open foliage in one world
    assert np.all(world.leaf_depth_of(np.array(others)) == 1.0)
    # tree trunks are hard: only a tree's crown is leaves
    tree = next(o for o in world.statics if o.cls is ObjectClass.TREE)
    base = tree.center[2] - tree.size[2] / 2
    ids = np.array([tree.object_id, tree.object_id])
    assert world.is_foliage(ids, np.array([base + 0.1, base + 0.9 * tree.size[2]])).tolist() == [
        False,
        True,
    ]


def test_dropouts_are_a_few_percent_and_more_on_dark_and_grazing_surfaces() -> None:
    # two identical walls side by side facing the sensor, one dark, one bright
    walls = [
        ObjectSpec(ObjectClass.WALL, (20.0, -6.0), (0.5, 8.0, 4.0), 0.0),
        ObjectSpec(ObjectClass.WALL, (20.0, 6.0), (0.5, 8.0, 4.0), 0.0),
    ]
    world = World(flat_scenario(walls))
    world.object_albedo[1], world.object_albedo[2] = 0.05, 0.8
    ladar = Ladar(LadarConfig(n_beams=32, n_azimuth=1024), world, np.random.default_rng(4))
    kept = {1: 0, 2: 0, "near": 0, "far": 0}
    total = dict.fromkeys(kept, 0)
    n_points = n_rays = 0
    for k in range(5):
        t_ns = k * ladar.period_ns
        times, origins, dirs = ladar.rays_world(t_ns)
        hits = world.cast_rays(origins, dirs, times, 120.0)
        scan, truth = ladar.sweep_with_truth(t_ns)
        n_points, n_rays = n_points + scan.n_points, n_rays + truth.n_rays_hit
        r_all, id_all = hits.range_m.ravel(), hits.object_id.ravel()
        ground = {"near": (id_all == 0) & (r_all < 8.0), "far": (id_all == 0) & (r_all > 40.0)}
        for key in (1, 2):
            total[key] += int(np.sum(id_all == key))
            kept[key] += int(np.sum(truth.object_id == key))
        for key, sel in ground.items():
            total[key] += int(sel.sum())
            kept[key] += int(np.isin(truth.ray, np.flatnonzero(sel)).sum())
    lost = {k: 1.0 - kept[k] / total[k] for k in kept}
    assert 0.02 <= 1.0 - n_points / n_rays <= 0.12, n_points / n_rays
    assert lost[2] == pytest.approx(0.02, abs=0.015)  # bright, head on: the random dropouts
    assert lost[1] > lost[2] + 0.03  # dark
    assert lost["far"] > lost["near"] + 0.05  # grazing and far
    assert min(total.values()) > 300


def test_intensity_is_noisy_about_albedo_times_shading() -> None:
    world = World(flat_scenario([]))
    ladar = Ladar(LadarConfig(), world, np.random.default_rng(1))
    scan, truth = ladar.sweep_with_truth(0)
    ground = truth.object_id == 0
    d = scan.points_xyz[ground].astype(np.float64)
    cos = np.abs(d[:, 2]) / np.linalg.norm(d, axis=1)  # flat ground: the normal is z
    ratio = scan.intensity[ground] / (truth.albedo[ground] * (0.2 + 0.8 * cos))
    assert ground.sum() > 5000
    assert np.median(ratio) == pytest.approx(1.0, abs=0.02)
    assert 0.06 < np.std(ratio) < 0.25


def test_camera_depth_error_grows_with_range_and_has_holes() -> None:
    # a low wall 10 m ahead: ground near the camera, the wall, and far ground above its top
    wall = [ObjectSpec(BUILDING, (11.0, 0.0), (2.0, 8.0, 1.0), 0.0)]
    world = World(flat_scenario(wall))
    cfg = CameraConfig(width=192, height=144, pitch_down_deg=15.0)
    frames = [Camera(cfg, world, np.random.default_rng(s)).render(0) for s in range(3)]
    exact = Camera(cfg.without_depth_errors(), world, np.random.default_rng(0)).render(0).depth
    surface = np.isfinite(exact)
    err = np.concatenate([(f.depth - exact)[surface] for f in frames])
    z = np.tile(exact[surface], len(frames))
    valid = np.isfinite(err)
    assert 0.02 < 1.0 - valid.mean() < 0.5, 1.0 - valid.mean()  # holes, not too many
    stds = []
    for lo, hi in ((3.0, 6.0), (15.0, 30.0)):
        sel = valid & (z >= lo) & (z < hi)
        assert sel.sum() > 200, (lo, hi)
        sigma = cfg.depth_noise_sigma_m + cfg.depth_noise_quadratic_per_m * z[sel] ** 2
        stds.append(err[sel].std())
        assert stds[-1] == pytest.approx(np.sqrt(np.mean(sigma**2)), rel=0.2), (lo, hi)
    assert stds[1] > 5.0 * stds[0]
    # the far ground just above the wall's top (the far side of a depth edge) has no depth
    col = exact[:, 96]
    edge = np.flatnonzero(col[:-1] > 1.5 * col[1:])  # row i much farther than row i + 1
    assert edge.size == 1 and all(np.isnan(f.depth[edge[0], 96]) for f in frames)


def test_camera_is_rgb_with_per_object_colours() -> None:
    houses = [
        ObjectSpec(BUILDING, (20.0, 5.0), (2.0, 6.0, 6.0), 0.0),  # left in the image
        ObjectSpec(BUILDING, (20.0, -5.0), (2.0, 6.0, 6.0), 0.0),
    ]
    world = World(flat_scenario(houses, seed=3))
    cfg = CameraConfig()
    frame = Camera(cfg, world, np.random.default_rng(0)).render(0)
    assert frame.image.shape == (256, 256, 3) and frame.image.dtype == np.uint8
    grey = Camera(CameraConfig(color=False), world, np.random.default_rng(0)).render(0)
    assert grey.image.shape == (256, 256)
    # both faces look at the camera away from the sun: colour times the ambient light
    patches = frame.image[90:110, 80:108], frame.image[90:110, 147:175]
    for oid, patch in zip((1, 2), patches, strict=True):
        measured = patch.reshape(-1, 3).mean(axis=0)
        expected = world.object_rgb[oid] * cfg.ambient * 255.0
        assert np.allclose(measured, expected, atol=1.5), (oid, measured, expected)
    assert np.max(np.abs(world.object_rgb[1] - world.object_rgb[2])) * cfg.ambient * 255 > 5


def test_parking_lot_has_parked_vehicles_pedestrians_and_moving_vehicles() -> None:
    sim = Simulator("parking")
    boxes = next(f for f in sim.frames(0.1) if isinstance(f, ObjectBoxes))
    classes = np.asarray(boxes.classes)
    speed = np.linalg.norm(boxes.velocities, axis=1)
    vehicle = classes == "vehicle"
    parked = vehicle & (speed == 0.0)
    assert parked.sum() >= 20
    assert (vehicle & (speed > 1.0)).sum() >= 2  # some drive
    assert (classes == "person").sum() >= 6 and max(
        len(g) for g in sim.world.groups().values()
    ) >= 3
    # parked close together: most have a neighbour within 1.5 m (side to side)
    c = boxes.centers[parked, :2]
    half_w = boxes.sizes[parked, 1] / 2
    d = np.linalg.norm(c[:, None] - c[None], axis=2) + np.diag(np.full(len(c), np.inf))
    j = np.argmin(d, axis=1)
    gap = d[np.arange(len(c)), j] - half_w - half_w[j]
    assert np.mean(gap < 1.5) > 0.5
    # the ego drives slowly along the aisles
    xy = sim.world.T_world_body(np.arange(0, 60 * NS_PER_S, NS_PER_S // 10))[:, :2, 3]
    v = np.linalg.norm(np.diff(xy, axis=0), axis=1) / 0.1
    assert 2.95 < v.min() and v.max() < 5.05
    # parked cars hide each other in part: vehicles both hit directly and behind another
    # vehicle's hit on rays that enter their own box
    ladar = sim.ladar
    times, origins, dirs = ladar.rays_world(NS_PER_S)
    hits = sim.world.cast_rays(origins, dirs, times, 120.0)
    o = np.repeat(origins, dirs.shape[1], axis=0)
    d, hit_id, hit_r = dirs.reshape(-1, 3), hits.object_id.ravel(), hits.range_m.ravel()
    hit_vehicle = hits.cls.ravel() == CLASS_INDEX[ObjectClass.VEHICLE]
    ego = sim.world.T_world_body(NS_PER_S)[:2, 3]
    partly = 0
    for k in np.flatnonzero(parked & (np.linalg.norm(boxes.centers[:, :2] - ego, axis=1) < 30)):
        t_box = ray_box_entry(o, d, boxes.centers[k], boxes.yaws[k], boxes.sizes[k] / 2)
        behind = np.isfinite(t_box) & hit_vehicle & (hit_id != boxes.ids[k]) & (hit_r < t_box)
        partly += bool(np.any(hit_id == boxes.ids[k]) and behind.sum() >= 5)
    assert partly >= 3, partly


def test_sizes_stray_beyond_the_class_prototypes() -> None:
    # kd_store/classes.yaml prototypes: vehicle length 4.5 m, person height 1.75 m
    lengths, heights = [], []
    for name in ("parking", "default", "village"):
        boxes = World(load_scenario(name)).object_boxes(0)
        classes = np.asarray(boxes.classes)
        lengths.append(boxes.sizes[classes == "vehicle", 0])
        heights.append(boxes.sizes[classes == "person", 2])
    lengths, heights = np.concatenate(lengths), np.concatenate(heights)
    assert lengths.min() < 3.8 and lengths.max() > 6.5
    # children well under it, adults over it by more than a standard deviation (0.09 m)
    assert heights.min() < 1.3 and heights.max() > 1.85
    # the jitter leaves a population's range: 20 objects all drawn at exactly 10 x 8 x 6 m
    pop = PopulationSpec(BUILDING, 20, (10.0, 8.0, 6.0), (10.0, 8.0, 6.0), 2.0, 2.0, None)
    world = World(flat_scenario([], [dataclasses.replace(pop, size_jitter=0.1)]))
    sizes = np.array([o.size for o in world.statics])
    assert np.any(sizes[:, 0] < 9.0) and np.any(sizes[:, 0] > 11.0)


def test_appearance_and_size_streams_leave_terrain_and_placement_alone() -> None:
    base = load_scenario("default")
    agents = [dataclasses.replace(a, size_jitter=0.2) for a in base.agents]
    a, b = World(base), World(dataclasses.replace(base, agents=agents))
    assert np.array_equal(a.terrain_raster().heights, b.terrain_raster().heights)
    assert np.array_equal([o.center for o in a.statics], [o.center for o in b.statics])
    assert np.array_equal(a.object_albedo, b.object_albedo)
    assert not np.array_equal(a.object_boxes(0).sizes, b.object_boxes(0).sizes)

"""The simulated world against its own analytic truth: terrain, route, agents, boxes."""

from __future__ import annotations

import numpy as np
import pytest

from core.geometry import NS_PER_S, check_pose, yaw_of
from fixtures.scenario import ObjectClass, load_scenario
from fixtures.world import CLASS_INDEX, World


@pytest.fixture(scope="module")
def world() -> World:
    return World(load_scenario("default"))


def test_same_seed_same_world_other_seed_other_world(world: World) -> None:
    again = World(load_scenario("default"))
    other = World(load_scenario("default").with_seed(8))
    centers = np.array([o.center for o in world.statics])
    assert np.array_equal(centers, np.array([o.center for o in again.statics]))
    assert np.array_equal(world.terrain_raster().heights, again.terrain_raster().heights)
    assert not np.allclose(centers[:, :2], np.array([o.center for o in other.statics])[:, :2])
    assert not np.allclose(world.terrain_raster().heights, other.terrain_raster().heights)


def test_terrain_raster_is_the_height_function(world: World) -> None:
    r = world.terrain_raster()
    assert r.heights.dtype == np.float32 and r.shape == (401, 401)
    rows, cols = np.array([0, 7, 200, 400]), np.array([3, 100, 250, 400])
    x, y = r.origin_x + cols * r.resolution_m, r.origin_y + rows * r.resolution_m
    assert np.allclose(r.heights[rows, cols], world.height(x, y), atol=1e-6)
    assert np.allclose(r.heights[rows, cols], world.terrain.analytic_height(x, y), atol=1e-4)
    assert np.ptp(r.heights) > 2.0  # rolling, not flat


def test_every_world_is_as_rough_as_its_ground_is(world: World) -> None:
    """The bumps the vehicle rides over (the height less its smooth part) are as rough as
    the spec says: a ploughed field's 0.05 m RMS in the countryside, the open country and the
    village, 0.02 m on the car park's asphalt; none is the 0.2 m of simulators 1-8, bumps no
    field or street has."""
    rng = np.random.default_rng(3)
    for name, rms in (("default", 0.05), ("open", 0.05), ("village", 0.05), ("parking", 0.02)):
        w = world if name == "default" else World(load_scenario(name))
        x, y = rng.uniform(-80.0, 80.0, (2, 20000))
        bumps = w.terrain.analytic_height(x, y) - w.terrain.smooth_height(x, y)
        assert np.sqrt(np.mean(bumps**2)) == pytest.approx(rms, rel=0.15), name


def test_vertical_rays_hit_the_terrain_at_its_height(world: World) -> None:
    rng = np.random.default_rng(0)
    xy = rng.uniform(-150, 150, (500, 2))
    # keep off objects: compare only rays that hit the terrain (object id 0)
    origins = np.column_stack([xy, np.full(len(xy), 50.0)])
    dirs = np.broadcast_to([0.0, 0.0, -1.0], (len(xy), 1, 3))
    hits = world.cast_rays(origins, dirs, np.zeros(len(xy), dtype=np.int64))
    terrain = hits.object_id[:, 0] == 0
    assert terrain.mean() > 0.8
    z_hit = 50.0 - hits.range_m[terrain, 0]
    # height() is the rendered mesh itself (float32 vertices)
    assert np.max(np.abs(z_hit - world.height(xy[terrain, 0], xy[terrain, 1]))) < 1e-4
    # and the mesh samples the analytic function: equal at vertices, rough in between
    analytic = world.terrain.analytic_height(xy[:, 0], xy[:, 1])
    assert 0.01 < np.max(np.abs(analytic - world.height(xy[:, 0], xy[:, 1]))) < 0.5


def test_route_stays_on_the_terrain_with_the_slope_attitude(world: World) -> None:
    t_ns = np.arange(0, 60 * NS_PER_S, NS_PER_S // 4)
    T = world.T_world_body(t_ns)
    for k in (0, 17, 239):
        check_pose(T[k], "T_world_body")
    x, y = T[:, 0, 3], T[:, 1, 3]
    # the body rides the smooth ground: the rough mesh is within a few decimetres of it
    assert np.allclose(T[:, 2, 3], world.terrain.smooth_height(x, y), atol=1e-9)
    assert np.max(np.abs(T[:, 2, 3] - world.height(x, y))) < 1.0
    # body z is the smooth terrain normal (the suspension filters roughness); pitch/roll real
    assert np.allclose(T[:, :3, 2], world.terrain.normal(x, y, smooth=True), atol=1e-9)
    assert np.max(np.degrees(np.arccos(T[:, 2, 2]))) > 2.0


def test_route_speed_and_turns(world: World) -> None:
    t_ns = np.arange(0, 60 * NS_PER_S, NS_PER_S // 10)
    xy = world.T_world_body(t_ns)[:, :2, 3]
    speed = np.linalg.norm(np.diff(xy, axis=0), axis=1) / 0.1  # along the ground track
    assert 4.95 < speed.min() and speed.max() < 10.05  # 5-10 m/s
    yaw = np.unwrap([yaw_of(T) for T in world.T_world_body(t_ns)])
    assert np.ptp(yaw) > np.radians(90)  # it turns
    assert np.max(np.abs(np.diff(yaw))) < np.radians(5)  # smoothly (at 0.1 s steps)


def test_agents_move_at_their_stated_speeds(world: World) -> None:
    t_ns = np.linspace(0, 59 * NS_PER_S, 120).astype(np.int64)
    dt_ns = NS_PER_S // 20
    a = world.agent_states(t_ns)
    b = world.agent_states(t_ns + dt_ns)
    moved = np.linalg.norm((b.centers - a.centers)[:, :, :2], axis=2) / (dt_ns / NS_PER_S)
    for k, track in enumerate(world.agents):
        # median: a step that rounds a path corner is a little shorter than the path
        assert np.median(moved[:, k]) == pytest.approx(track.speed_mps, rel=1e-3)
        assert np.allclose(np.linalg.norm(a.velocities[:, k], axis=1), track.speed_mps)
        ground = world.terrain.smooth_height(a.centers[:, k, 0], a.centers[:, k, 1])
        on_ground = ground + track.size[2] / 2
        assert np.allclose(a.centers[:, k, 2], on_ground)


def test_object_boxes_have_stable_ids_and_truthful_motion(world: World) -> None:
    b0 = world.object_boxes(0)
    b1 = world.object_boxes(2 * NS_PER_S)
    assert len(b0) == len(world.statics) + len(world.agents) == len(set(b0.ids.tolist()))
    assert np.array_equal(b0.ids, b1.ids) and b0.classes == b1.classes
    assert {"building", "tree", "bush", "rock", "post", "wall", "vehicle", "person"} <= set(
        b0.classes
    )
    static = np.array([c not in ("vehicle", "person") for c in b0.classes])
    assert np.array_equal(b0.centers[static], b1.centers[static])
    assert np.all(b0.velocities[static] == 0)
    # agents: displacement over 2 s equals velocity * 2 s on straight stretches (most of them)
    disp = b1.centers[~static, :2] - b0.centers[~static, :2]
    straight = np.linalg.norm(disp - 2.0 * b0.velocities[~static, :2], axis=1) < 1e-6
    assert straight.sum() >= len(straight) - 2
    assert np.all(b0.sizes > 0)


def test_convoy_members_keep_their_spacing(world: World) -> None:
    spec = next(s for s in world.scenario.agents if s.members == 2)
    members = [a for a in world.agents if a.group == world.scenario.agents.index(spec)]
    states = world.agent_states(np.array([5 * NS_PER_S]))
    ids = [a.object_id for a in world.agents]
    c0, c1 = (states.centers[0, ids.index(m.object_id), :2] for m in members)
    assert np.linalg.norm(c0 - c1) == pytest.approx(spec.spacing_m, abs=0.05)


@pytest.mark.parametrize("name", ["default", "village", "parking"])
def test_the_members_of_a_crowd_keep_apart(name: str) -> None:
    """Simulator 10: no two walkers of a crowd share space. Over 30 seeds, every pair of
    members' footprints, placed by their offsets from the leader's path point (as they stand
    on a straight stretch of the path), keeps ``CROWD_CLEARANCE_M`` apart along or across it.
    Simulator 9's scatter put 2.5 % (village) to 11 % (car park) of these pairs inside each
    other, a third on some seeds."""
    from fixtures.world import CROWD_CLEARANCE_M, _make_tracks

    base = load_scenario(name)
    crowds = [s for s in base.agents if s.formation.value == "crowd" and s.members > 1]
    assert crowds, name
    pairs = 0
    for seed in range(30):
        rng, rng_size = np.random.default_rng(seed), np.random.default_rng(seed + 1000)
        tracks = _make_tracks(crowds, 0, rng, rng_size)
        for g in range(len(crowds)):
            group = [t for t in tracks if t.group == g]
            for i, a in enumerate(group):
                for b in group[:i]:
                    gap_along = abs(a.along_m - b.along_m) - (a.size[0] + b.size[0]) / 2
                    gap_across = abs(a.lateral_m - b.lateral_m) - (a.size[1] + b.size[1]) / 2
                    assert max(gap_along, gap_across) >= CROWD_CLEARANCE_M - 1e-9, (seed, g)
                    pairs += 1
    assert pairs >= 30


def test_a_crowd_with_no_room_is_refused() -> None:
    import dataclasses

    from fixtures.scenario import ScenarioError
    from fixtures.world import _make_tracks

    spec = next(s for s in load_scenario("village").agents if s.formation.value == "crowd")
    dense = dataclasses.replace(spec, members=40, spacing_m=0.5)
    with pytest.raises(ScenarioError, match="no room for member"):
        _make_tracks([dense], 0, np.random.default_rng(0), np.random.default_rng(1))


def test_agent_culling_never_loses_a_hit(world: World) -> None:
    """Rays cast through the culled path equal a brute-force cast against every agent's mesh."""
    rng = np.random.default_rng(3)
    T, B = 40, 300
    t_ns = np.sort(rng.integers(0, 60 * NS_PER_S, T))
    states = world.agent_states(t_ns)
    # origins a few metres from a random agent at each group's time, rays in all directions
    pick = rng.integers(0, len(world.agents), T)
    origins = states.centers[np.arange(T), pick] + rng.normal(0.0, 6.0, (T, 3))
    origins[:, 2] = world.height(origins[:, 0], origins[:, 1]) + 1.5
    dirs = rng.normal(size=(T, B, 3))
    dirs /= np.linalg.norm(dirs, axis=2, keepdims=True)
    hits = world.cast_rays(origins, dirs, t_ns)
    brute = np.full((T, B), np.inf)
    for k in range(len(world.agents)):
        for g in range(T):
            r, _ = world.cast_agent(
                k,
                np.repeat(origins[g : g + 1], B, axis=0),
                dirs[g],
                np.repeat(states.centers[g : g + 1, k], B, axis=0),
                np.full(B, states.yaws[g, k]),
            )
            brute[g] = np.minimum(brute[g], r)
    on_agent = brute < hits.range_m + 1e-9
    assert on_agent.sum() > 100
    assert np.allclose(hits.range_m[on_agent], brute[on_agent])
    assert np.all(hits.cls[on_agent] >= 0)


def test_ladar_hits_lie_inside_their_objects_ground_truth_boxes(world: World) -> None:
    """Every ray that hits an object ends inside that object's box (agents: at the ray's time)."""
    from fixtures.sensors import Ladar, LadarConfig

    ladar = Ladar(LadarConfig(n_beams=32, n_azimuth=512), world, np.random.default_rng(0))
    seen: set[str] = set()
    for t_ns in (8 * NS_PER_S, 30 * NS_PER_S, 41 * NS_PER_S):
        times, origins, dirs = ladar.rays_world(t_ns)
        hits = world.cast_rays(origins, dirs, times, 120.0)
        ti, bi = np.nonzero(hits.object_id > 0)
        p = origins[ti] + dirs[ti, bi] * hits.range_m[ti, bi][:, None]
        for oid in np.unique(hits.object_id[ti, bi]):
            sel = hits.object_id[ti, bi] == oid
            boxes = world.object_boxes(int(times[ti[sel][0]]))  # statics: any time will do
            k = int(np.flatnonzero(boxes.ids == oid)[0])
            seen.add(boxes.classes[k])
            if boxes.classes[k] in ("vehicle", "person"):  # place the box at each ray's time
                agent = [a.object_id for a in world.agents].index(oid)
                states = world.agent_states(times[ti[sel]])
                centers, yaws = states.centers[:, agent], states.yaws[:, agent]
            else:
                centers, yaws = boxes.centers[k][None], np.full(sel.sum(), boxes.yaws[k])
            c, s = np.cos(yaws), np.sin(yaws)
            d = p[sel] - centers
            local = np.column_stack([c * d[:, 0] + s * d[:, 1], c * d[:, 1] - s * d[:, 0], d[:, 2]])
            half = boxes.sizes[k] / 2 + 1e-3
            # below the box is the part sunk into the ground: only x, y and the top are bounded
            inside = np.all(np.abs(local[:, :2]) <= half[:2], axis=1) & (local[:, 2] <= half[2])
            assert inside.all(), (boxes.classes[k], oid, np.abs(local).max(axis=0), half)
    assert {"building", "tree", "vehicle"} <= seen


def test_a_parked_vehicle_stands_on_wheels_clear_of_the_ground() -> None:
    """LADAR beams pass under a parked vehicle's body between its wheels and meet its side
    above, and its ground-truth box bounds its mesh (a few cm of wheel sink below)."""
    world = World(load_scenario("parking"))
    cars = [o for o in world.statics if o.cls.value == "vehicle"]
    assert len(cars) > 10
    rng = np.random.default_rng(2)
    under = side = 0
    for car in [cars[i] for i in rng.choice(len(cars), 8, replace=False)]:
        c, s = np.cos(car.yaw), np.sin(car.yaw)
        d = car.mesh.vertices - car.center
        local = np.column_stack([c * d[:, 0] + s * d[:, 1], c * d[:, 1] - s * d[:, 0], d[:, 2]])
        half = car.size / 2 + 1e-6
        assert np.all(np.abs(local[:, :2]) <= half[:2]) and local[:, 2].max() <= half[2]
        assert local[:, 2].min() >= -half[2] - 0.05
        # level rays from 0.3 m off the car's side (its neighbours in a row stand close), at
        # the middle of its length: 7 cm over the ground and at 45 % of its height
        left = np.array([-s, c, 0.0])
        ground = world.height(np.array([car.center[0]]), np.array([car.center[1]]))[0]
        base = max(ground, car.center[2] - half[2])
        origin = car.center - (half[1] + 0.3) * left
        origins = np.array([[*origin[:2], base + 0.07], [*origin[:2], base + 0.45 * car.size[2]]])
        hits = world.cast_rays(origins, np.broadcast_to(left, (2, 1, 3)), np.zeros(2, np.int64))
        low, mid = hits.object_id[:, 0] == car.object_id
        under += int(not low)
        side += int(mid)
    assert side == 8  # every body is met at 45 % of its height
    assert under >= 6  # and 7 cm over the ground the beams go under it (a slope may stop one)


def test_moving_agents_are_bodies_not_boxes(world: World) -> None:
    """A moving vehicle's beams pass under its body and meet its side; a person's head is
    narrower than the shoulders, so a level ray just inside the top corner of its box misses
    it where a box would be hit; both meet the body near the middle of the box."""
    t_ns = world.t0_ns + 7 * NS_PER_S
    states = world.agent_states(np.array([t_ns]))
    origins, dirs, expect = [], [], []
    for k, agent in enumerate(world.agents):
        c, yaw, (l, w, h) = states.centers[0, k], states.yaws[0, k], agent.size
        left = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
        start = c - (w / 2 + 0.3) * left
        base = c[2] - h / 2
        if agent.cls.value == "vehicle":
            rows = [(base + 0.07, False), (base + 0.45 * h, True)]
        else:
            forward = np.array([np.cos(yaw), np.sin(yaw), 0.0])
            start_top = start + 0.4 * l * forward
            origins.append([*start_top[:2], base + 0.97 * h])
            dirs.append(left)
            expect.append((agent.object_id, False))
            rows = [(base + 0.6 * h, True)]
        for z, hit in rows:
            origins.append([*start[:2], z])
            dirs.append(left)
            expect.append((agent.object_id, hit))
    hits = world.cast_rays(
        np.array(origins), np.array(dirs)[:, None, :], np.full(len(origins), t_ns, np.int64)
    )
    got = hits.object_id[:, 0] == np.array([oid for oid, _ in expect])
    want = np.array([hit for _, hit in expect])
    kinds = {a.cls.value for a in world.agents}
    assert kinds == {"vehicle", "person"}
    assert np.array_equal(got, want), [(e, g) for e, g in zip(expect, got, strict=True)]


def test_village_cars_are_parked_side_on_at_the_kerb() -> None:
    """The village's parked cars line its streets a few metres from the lane, lengthwise."""
    world = World(load_scenario("village"))
    cars = [o for o in world.statics if o.cls.value == "vehicle"]
    assert len(cars) >= 20
    xy = world.route.xy
    for car in cars:
        d = np.hypot(*(xy - car.center[:2]).T)
        i = int(np.argmin(d))
        assert 2.2 + car.size[1] / 2 - 0.2 < d[i] < 2.2 + car.size[1] / 2 + 1.0
        along = abs(np.cos(car.yaw - world.route.heading[i]))
        assert along > 0.95


def test_people_stand_by_the_road_with_a_persons_body_and_no_speed() -> None:
    """Some persons stand still: static, at the village's pavements, 1.8-3.6 m off the lane;
    a level ray meets a standing person's body at chest height, and one just inside the top
    corner of its box misses the narrower head."""
    world = World(load_scenario("village"))
    standing = [o for o in world.statics if o.cls.value == "person"]
    assert len(standing) >= 5
    boxes = world.object_boxes(world.t0_ns)
    ids = np.asarray(boxes.ids)
    for p in standing:
        d = np.hypot(*(world.route.xy - p.center[:2]).T).min()
        assert 1.8 + p.size[1] / 2 - 0.2 < d < 1.8 + p.size[1] / 2 + 1.7
        k = int(np.flatnonzero(ids == p.object_id)[0])
        assert boxes.classes[k] == "person" and np.all(boxes.velocities[k] == 0.0)
    origins, dirs, expect = [], [], []
    for p in standing:
        (l, w, h), yaw = p.size, p.yaw
        left = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
        forward = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        start = p.center - (w / 2 + 0.3) * left
        base = p.center[2] - h / 2
        for z, shift, hit in ((base + 0.6 * h, 0.0, True), (base + 0.97 * h, 0.4 * l, False)):
            origins.append([*(start + shift * forward)[:2], z])
            dirs.append(left)
            expect.append((p.object_id, hit))
    hits = world.cast_rays(
        np.array(origins), np.array(dirs)[:, None, :], np.zeros(len(origins), np.int64)
    )
    got = hits.object_id[:, 0] == np.array([oid for oid, _ in expect])
    assert np.array_equal(got, [hit for _, hit in expect])


def test_persons_have_the_statures_of_people() -> None:
    """Heights drawn for a range of 1.0-2.0 m are a street's: adults around 1.70 m and a
    few children, not a uniform spread (under which 45 % would be below 1.45 m)."""
    from fixtures.world import _member_size

    spec = load_scenario("village").agents[0]  # the crowd: 1.0-2.0 m
    assert spec.cls.value == "person" and spec.size[2] == 1.0 and spec.size_max[2] == 2.0
    rng = np.random.default_rng(5)
    h = np.array([_member_size(spec, rng)[2] for _ in range(4000)])
    assert 0.11 < np.mean(h < 1.45) < 0.19
    adults = h[h >= 1.45]
    assert abs(np.median(adults) - 1.70) < 0.02 and 0.07 < adults.std() < 0.11
    assert h.min() >= 1.0 and h.max() <= 2.0


def test_a_persons_breadth_and_depth_scale_with_the_stature() -> None:
    """Simulator 8: a child is slim (a body's breadth is about a quarter of its stature at
    every age), not an adult's footprint under a child's height, which is a bin's."""
    from fixtures.world import _member_size, _person_size, _stature

    spec = load_scenario("village").agents[0]  # the crowd: 1.0-2.0 m
    rng = np.random.default_rng(11)
    s = np.array([_member_size(spec, rng) for _ in range(4000)])
    child, adult = s[s[:, 2] < 1.45], s[s[:, 2] >= 1.45]
    assert len(child) > 300
    # breadth over stature has one spread for children and adults (only the jitter and the
    # uniform footprint draw vary it), so the children are narrower in proportion
    ratio_c, ratio_a = child[:, 1] / child[:, 2], adult[:, 1] / adult[:, 2]
    assert abs(np.median(ratio_c) - np.median(ratio_a)) < 0.02
    assert np.median(child[:, 1]) < 0.8 * np.median(adult[:, 1])
    assert np.median(child[:, :2].max(axis=1)) < 0.45  # a wheelie bin is 0.48-0.75 m wide
    # the scaling takes no draw of its own: the stature is the one _stature draws and the
    # generator ends where it would, so every later draw of a seed (the other objects) is
    # as it was in simulator 7
    a, b = np.random.default_rng(3), np.random.default_rng(3)
    for _ in range(200):
        p = _person_size(np.array([0.4, 0.6, 0.0]), a, 1.0, 2.0)
        assert p[2] == _stature(b, 1.0, 2.0)
    assert a.random() == b.random()


def test_street_furniture_stands_by_the_roads_with_upright_faces() -> None:
    """Bins, cabinets and machines (simulator 6) stand by the village's street and in the car
    park, of published sizes, never moving; a level ray at half height meets one's face, a
    ray over its top misses, and its returns are labelled with its class."""
    for name, at_least in (("village", 12), ("parking", 8), ("default", 6)):
        world = World(load_scenario(name))
        pieces = [o for o in world.statics if o.cls.value == "street furniture"]
        assert len(pieces) >= at_least, name
        boxes = world.object_boxes(world.t0_ns)
        ids = np.asarray(boxes.ids)
        sizes = np.array([o.size for o in pieces])
        assert np.all(sizes[:, 2] > 0.8) and np.all(sizes[:, 2] < 1.9)  # knee to head high
        assert np.all(np.max(sizes[:, :2], axis=1) < 1.65)  # a 1100 l container at most
        for o in pieces:
            k = int(np.flatnonzero(ids == o.object_id)[0])
            assert boxes.classes[k] == "street furniture" and np.all(boxes.velocities[k] == 0)
        origins, dirs, expect = [], [], []
        for o in pieces:
            h = o.size[2]
            base = o.center[2] - h / 2
            toward = np.array([1.0, 0.0, 0.0])
            for z, hit in ((base + 0.5 * h, True), (base + h + 0.05, False)):
                origins.append([o.center[0] - np.hypot(*o.size[:2]) / 2 - 0.2, o.center[1], z])
                dirs.append(toward)
                expect.append((o.object_id, hit))
        hits = world.cast_rays(
            np.array(origins), np.array(dirs)[:, None, :], np.zeros(len(origins), np.int64)
        )
        got = hits.object_id[:, 0] == np.array([oid for oid, _ in expect])
        assert np.array_equal(got, [hit for _, hit in expect]), name
        hit_cls = hits.cls[:, 0][np.array([hit for _, hit in expect])]
        assert np.all(hit_cls == CLASS_INDEX[ObjectClass.FURNITURE])

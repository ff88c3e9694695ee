"""The world model's ground as SP's prior for far returns (sp.ground_prior): the expected
ground on a map grid, far returns over a car judged against it, and the node's prior against
the simulator's terrain."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
from kernel_reference.ground_prior_reference import expected_ground_reference as expected

from sp.ground import GroundConfig, ground_mask
from sp.ground_prior import (
    ABOVE,
    GROUND,
    OBJECT,
    GroundPrior,
    GroundPriorConfig,
    GroundPriorError,
    above_prior,
    on_known_ground,
)

RES = 0.4
SLOPE = math.tan(math.radians(15.0))


def _prior(heights: dict[tuple[int, int], float], n: int = 64, origin=(-20, 35)) -> GroundPrior:
    """A toroidal grid holding ``heights`` at global cells (ix, iy), NaN elsewhere."""
    z = np.full((n, n), np.nan, dtype=np.float32)
    for (ix, iy), h in heights.items():
        z[iy % n, ix % n] = h
    return GroundPrior(z, origin, RES)


def _block(x0: int, x1: int, y0: int, y1: int, h: float) -> dict[tuple[int, int], float]:
    return {(ix, iy): h for ix in range(x0, x1) for iy in range(y0, y1)}


def test_expected_ground_is_the_lowest_known_nearby_raised_by_the_slope() -> None:
    # ground at 0 m around a 2 m x 2 m roof the map took for ground (1.4 m), window at
    # cells -20..43 x 35..98
    cells = _block(-10, 10, 40, 60, 0.0) | _block(-2, 3, 48, 53, 1.4)
    prior = _prior(cells)
    centre = (np.array([[0, 50]]) + 0.5) * RES  # the roof's middle cell
    # the nearest ground cell is 3 cells (1.2 m) away
    assert expected(prior, centre, 2.0, SLOPE)[0] == pytest.approx(3 * RES * SLOPE, abs=1e-6)
    # a smaller radius sees only the roof
    assert expected(prior, centre, 0.8, SLOPE)[0] == pytest.approx(1.4, abs=1e-6)
    # no slope allowance: the ground itself
    assert expected(prior, centre, 2.0, 0.0)[0] == pytest.approx(0.0, abs=1e-6)
    # unknown within the radius, and outside the window (whose storage cell holds ground)
    far_xy = (np.array([[-15, 80], [-10 + 64, 45]]) + 0.5) * RES
    assert np.isnan(expected(prior, far_xy, 2.0, SLOPE)).all()


def test_a_prior_grid_that_is_not_square_is_refused() -> None:
    with pytest.raises(GroundPriorError, match=r"\(4, 5\)"):
        GroundPrior(np.zeros((4, 5)), (0, 0), RES)
    with pytest.raises(GroundPriorError, match="resolution_m -1"):
        GroundPrior(np.zeros((4, 4)), (0, 0), -1.0)
    with pytest.raises(GroundPriorError, match="slope_deg 85"):
        GroundPriorConfig(slope_deg=85.0)


SENSOR_H = 1.8


def _column(profile: list[tuple[float, float]], n_cols: int = 90) -> tuple[np.ndarray, ...]:
    """An image whose every column holds ``profile`` ((range m, height m) below the sensor,
    bottom row first) at azimuths around the sensor at the world origin; (xyz, valid,
    horizontal range)."""
    az = np.linspace(-np.pi, np.pi, n_cols, endpoint=False)
    r = np.array([p[0] for p in profile])[::-1, None]
    z = np.array([p[1] for p in profile])[::-1, None]
    xyz = np.stack(np.broadcast_arrays(r * np.cos(az), r * np.sin(az), z), axis=-1)
    valid = np.ones((len(profile), n_cols), dtype=bool)
    return np.ascontiguousarray(xyz, dtype=np.float64), valid, np.hypot(xyz[..., 0], xyz[..., 1])


def not_ground(xyz, rng, ground, prior, config) -> np.ndarray:
    """(H, W) bool: the ground pixels the prior takes out of the ground."""
    return above_prior(xyz, rng, ground, prior, config) != GROUND


def _flat_prior(z_m: float, n: int = 256) -> GroundPrior:
    return GroundPrior(np.full((n, n), z_m, dtype=np.float32), (-n // 2, -n // 2), RES)


# the ground every 2.5 m out to 25 m, as the low beams see it far out
FAR_GROUND = [(2.0 + 2.5 * k, -SENSOR_H) for k in range(10)]


def test_a_far_return_over_flat_ground_is_not_ground_with_the_prior() -> None:
    # one return 0.9 m up at 30 m (a car's roof over nearer cars, a low rock's top): from the
    # last ground return 7.5 m before it, a gentle rise the column walk takes for ground
    xyz, valid, rng = _column([*FAR_GROUND, (30.0, -SENSOR_H + 0.9)])
    ground, _ = ground_mask(xyz, valid, GroundConfig())
    assert ground[0].all()  # without the prior
    off = not_ground(xyz, rng, ground, _flat_prior(-SENSOR_H), GroundPriorConfig())
    assert off[0].all() and not off[1:].any()
    # ... unless the map knows nothing there
    unknown = _flat_prior(np.nan)
    assert not not_ground(xyz, rng, ground, unknown, GroundPriorConfig()).any()


def test_the_one_row_on_a_low_rock_far_out_is_not_ground_with_the_prior() -> None:
    # a 32-beam sensor's rows lie 0.7 m apart at 30 m: the one row on a 0.8 m rock there
    # may hit it 0.6 m up
    xyz, valid, rng = _column([*FAR_GROUND, (30.0, -SENSOR_H + 0.6)])
    ground, _ = ground_mask(xyz, valid, GroundConfig())
    assert ground[0].all()
    off = not_ground(xyz, rng, ground, _flat_prior(-SENSOR_H), GroundPriorConfig())
    assert off[0].all() and not off[1:].any()
    # (the former 0.8 m limit left it ground) ...
    old = GroundPriorConfig(above_m=0.8)
    assert not not_ground(xyz, rng, ground, _flat_prior(-SENSOR_H), old).any()
    # ... and a 0.3 m hump is ground
    xyz, valid, rng = _column([*FAR_GROUND, (30.0, -SENSOR_H + 0.3)])
    assert not not_ground(xyz, rng, ground, _flat_prior(-SENSOR_H), GroundPriorConfig()).any()


def _span_prior(low_m: float, high_m: float, n: int = 256) -> GroundPrior:
    """Flat ground at the sensor's foot, every cell's returns seen so far spanning
    ``low_m``..``high_m`` (world z) in the map's lowest and highest layers."""
    flat = _flat_prior(-SENSOR_H, n)
    lo = np.full((n, n), low_m, dtype=np.float32)
    hi = np.full((n, n), high_m, dtype=np.float32)
    return GroundPrior(flat.z_m, flat.origin_cell, RES, lo, hi)


def test_the_one_row_on_a_rock_face_is_not_ground_once_the_map_saw_the_face() -> None:
    # the one row on a low rock at 30 m hits it 0.35 m up: below above_m, so one sweep alone
    # leaves it ground ...
    ground_z = -SENSOR_H
    xyz, valid, rng = _column([*FAR_GROUND, (30.0, ground_z + 0.35)])
    ground, _ = ground_mask(xyz, valid, GroundConfig())
    assert ground[0].all()
    cfg = GroundPriorConfig()
    assert not not_ground(xyz, rng, ground, _flat_prior(ground_z), cfg).any()
    # ... but earlier sweeps' rows climbed its face: its cells hold returns from the foot to
    # 0.7 m up, and the return stands 0.35 m over the lowest of them
    code = above_prior(xyz, rng, ground, _span_prior(ground_z, ground_z + 0.7), cfg)
    assert (code[0] == OBJECT).all() and (code[1:] == GROUND).all()
    # terrain: its cells' returns lie at one height give or take a slope's 0.15 m ...
    gentle = _span_prior(ground_z + 0.2, ground_z + 0.35)
    assert (above_prior(xyz, rng, ground, gentle, cfg) == GROUND).all()
    # ... and the foot of something tall (a person walked there) is still ground
    xyz, valid, rng = _column([*FAR_GROUND, (30.0, ground_z + 0.1)])
    tall = _span_prior(ground_z, ground_z + 1.8)
    assert (above_prior(xyz, rng, ground, tall, cfg) == GROUND).all()


def _row_on_rock(up_m: float) -> Callable[..., np.ndarray]:
    """One row's hit ``up_m`` over the foot of a 0.38 m rock 30 m out, which the column walk
    calls ground: a function ``code(cfg, low_m, high_m)`` giving :func:`above_prior`'s codes
    of the column against a prior whose cells span ``low_m``..``high_m`` over the foot
    (default 0..0.35 m: the rock's face seen from its foot up)."""
    ground_z = -SENSOR_H
    xyz, valid, rng = _column([*FAR_GROUND, (30.0, ground_z + up_m)])
    ground, _ = ground_mask(xyz, valid, GroundConfig())
    assert ground[0].all()

    def code(cfg: GroundPriorConfig, low_m: float = 0.0, high_m: float = 0.35) -> np.ndarray:
        return above_prior(xyz, rng, ground, _span_prior(ground_z + low_m, ground_z + high_m), cfg)

    return code


def test_the_one_row_on_a_rock_under_half_a_metre_is_not_ground_once_its_face_was_seen() -> None:
    # this sweep's row hits the rock 0.3 m over its foot
    code = _row_on_rock(0.3)
    c = code(GroundPriorConfig())
    assert (c[0] == OBJECT).all() and (c[1:] == GROUND).all()
    # (a cell must span half a metre by the former rule: the rock's face never did) ...
    assert (code(GroundPriorConfig(span_m=0.5)) == GROUND).all()
    # ... while terrain's cells, 0.25 m from their lowest to their highest return (a fold, a
    # steep slope, range noise far out), stay ground
    assert (code(GroundPriorConfig(), 0.05, 0.3) == GROUND).all()


def test_the_hits_sinking_down_a_low_rocks_face_stay_on_it() -> None:
    # later sweeps' hits on the same rock, the range grown, lie 0.15 m over its foot: in a
    # cell spanning the rock's face (under low_body_m) they are on the face ...
    code = _row_on_rock(0.15)
    c = code(GroundPriorConfig())
    assert (c[0] == OBJECT).all() and (c[1:] == GROUND).all()
    assert (code(GroundPriorConfig(low_body_m=0.0)) == GROUND).all()
    # ... while in a cell of a car (1.5 m) they are the ground beside it, and a fold of the
    # terrain (0.25 m) holds no face at all
    for high_m in (1.5, 0.25):
        assert (code(GroundPriorConfig(), 0.0, high_m) == GROUND).all(), high_m


def test_a_prior_with_only_one_of_the_span_layers_is_refused() -> None:
    z = np.zeros((4, 4), dtype=np.float32)
    with pytest.raises(GroundPriorError, match="both z_min_m and z_max_m"):
        GroundPrior(z, (0, 0), RES, z_min_m=z)
    with pytest.raises(GroundPriorError, match=r"z_max_m has shape \(3, 3\)"):
        GroundPrior(z, (0, 0), RES, z, np.zeros((3, 3), dtype=np.float32))


def test_a_far_slope_the_prior_knows_stays_ground() -> None:
    # the ground rises at 10 degrees from 20 m; the map holds the slope (its cells' heights)
    rise = math.tan(math.radians(10.0))
    profile = FAR_GROUND[:8] + [(r, -SENSOR_H + (r - 20.0) * rise) for r in (22.0, 26.0, 30.0)]
    xyz, valid, rng = _column(profile)
    ground, _ = ground_mask(xyz, valid, GroundConfig())
    assert ground.all()
    n = 256
    ix = (np.arange(n) + n // 2) % n - n // 2  # the global cell each storage column holds
    x_centre = (ix + 0.5) * RES
    z = np.broadcast_to(-SENSOR_H + np.clip(np.hypot(x_centre, 0.0) - 20.0, 0, None) * rise, (n, n))
    # a radial slope along x only at the azimuth 0 columns; judge those columns
    prior = GroundPrior(np.ascontiguousarray(z, dtype=np.float32), (-n // 2, -n // 2), RES)
    col0 = np.argmin(np.abs(np.arctan2(xyz[0, :, 1], xyz[0, :, 0])))
    off = not_ground(xyz, rng, ground, prior, GroundPriorConfig())
    assert not off[:, col0].any()
    # the same returns over a flat map 1 m lower are judged objects
    off_low = not_ground(xyz, rng, ground, _flat_prior(-SENSOR_H - 1.0), GroundPriorConfig())
    assert off_low[:3, col0].all()


def test_near_returns_are_left_to_the_column_walk() -> None:
    xyz, valid, rng = _column(FAR_GROUND)
    ground = np.ones(valid.shape, dtype=bool)
    below = _flat_prior(-SENSOR_H - 1.0)  # a prior a metre too low
    off = not_ground(xyz, rng, ground, below, GroundPriorConfig(min_range_m=15.0))
    assert off[rng >= 15.0].all() and not off[rng < 15.0].any()


@pytest.fixture(scope="module")
def node_and_world(tmp_path_factory):
    """A node run with the true poses over a 3 s default-scenario log, and the log's world."""
    from fixtures.simulate import Simulator, simulate_to_log
    from wm.config import NodeConfig, PoseSource
    from wm.run import run_node

    path = tmp_path_factory.mktemp("prior") / "default.mcap"
    simulate_to_log("default", path, seconds=3.0, seed=7, progress=False)
    node = run_node(path, ":memory:", NodeConfig(pose_source=PoseSource.TRUTH))
    yield node, Simulator("default", seed=7).world
    node.kd.close()


def test_the_node_gives_sp_the_terrain(node_and_world) -> None:
    node, world = node_and_world
    prior = node._ground_prior()
    lvl = node.stack.level(node.config.ground_prior_level)
    rows, cols = np.mgrid[0 : lvl.size, 0 : lvl.size]
    xy = lvl.window_to_world(rows.ravel(), cols.ravel())
    body = node.track.at(node.last_sweep_t_ns)[:2, 3]
    xy = xy[np.hypot(*(xy - body).T) <= 35.0]
    own = expected(prior, xy, 0.0, 0.0)  # the map's own cells
    known = np.isfinite(own)
    assert known.mean() > 0.4  # the map knows much of the ground within 35 m
    cfg = GroundPriorConfig()
    e = expected(prior, xy[known], cfg.radius_m, math.tan(math.radians(cfg.slope_deg)))
    err = e - np.asarray(world.height(xy[known, 0], xy[known, 1]))
    # the expected ground is the simulator's terrain: to a few cm in the median, and never
    # far above it (a building's roof, wider than the radius, is the exception)
    assert np.median(np.abs(err)) < 0.05
    lo, hi = np.quantile(err, [0.01, 0.99])
    assert lo > -0.35 and hi < 0.15


def test_a_node_refuses_a_ground_prior_level_it_has_not() -> None:
    import kd_store
    from maps.stack import StackError
    from wm.config import NodeConfig
    from wm.node import WorldModelNode

    with kd_store.open(":memory:") as kd, pytest.raises(StackError, match=r"'nowhere'.*subsystem"):
        WorldModelNode(kd, NodeConfig(ground_prior_level="nowhere"))


def test_returns_are_coded_by_how_far_they_stand_above_the_expected_ground() -> None:
    flat = _flat_prior(-SENSOR_H)
    for up, code in ((0.3, GROUND), (0.6, ABOVE), (0.9, OBJECT)):
        xyz, valid, rng = _column([*FAR_GROUND, (30.0, -SENSOR_H + up)])
        ground, _ = ground_mask(xyz, valid, GroundConfig())
        got = above_prior(xyz, rng, ground, flat, GroundPriorConfig())
        assert (got[0] == code).all() and (got[1:] == GROUND).all(), up
    # a pixel the column walk already took out of the ground is not judged
    xyz, valid, rng = _column([*FAR_GROUND, (30.0, -SENSOR_H + 0.9)])
    none = np.zeros(valid.shape, dtype=bool)
    assert (above_prior(xyz, rng, none, flat, GroundPriorConfig()) == GROUND).all()
    with pytest.raises(GroundPriorError, match=r"object_margin_m -0.1 is not >= 0"):
        GroundPriorConfig(object_margin_m=-0.1)


N_ROWS, N_COLS = 16, 720
FAR_COLS = slice(356, 368)  # 6 degrees: 3.9 m at 37.5 m


def _scan_rows(
    ground: list[tuple[float, float]],
    far: list[tuple[float, float]],
    beside: list[tuple[float, float]] | None = None,
):
    """A LadarScan at t = 0 whose every column holds the ``ground`` rows ((range m, height m)
    below the sensor, bottom row first) and, over ``FAR_COLS`` only, the ``far`` rows above
    them (holding ``beside``, one per far row, in the other columns, when given); returns
    (scan, (H, W) bool valid pixels, (H, W) bool the top far row's pixels over ``FAR_COLS``)."""
    from logs.types import LadarScan

    az = np.pi - (np.arange(N_COLS) + 0.5) * 2 * np.pi / N_COLS
    xyz = np.full((N_ROWS, N_COLS, 3), np.nan)
    for k, (r, z) in enumerate([*ground, *far]):
        cols = FAR_COLS if k >= len(ground) else slice(None)
        xyz[N_ROWS - 1 - k, cols] = np.stack(
            [r * np.cos(az[cols]), r * np.sin(az[cols]), np.full_like(az[cols], z)], -1
        )
    out = np.ones(N_COLS, dtype=bool)
    out[FAR_COLS] = False
    for k, (r, z) in enumerate(beside or []):
        xyz[N_ROWS - 1 - len(ground) - k, out] = np.stack(
            [r * np.cos(az[out]), r * np.sin(az[out]), np.full_like(az[out], z)], -1
        )
    valid = np.isfinite(xyz[..., 0])
    pts = xyz[valid].astype(np.float32)
    ring = (N_ROWS - 1 - np.nonzero(valid)[0]).astype(np.uint16)
    n = len(pts)
    scan = LadarScan(0, "ladar", pts, np.full(n, 0.5, np.float32), np.zeros(n, np.int64), ring)
    top = np.zeros(valid.shape, dtype=bool)
    top[N_ROWS - len(ground) - len(far), FAR_COLS] = True
    return scan, valid, top


def _ground_after_sp(
    scan, prior: GroundPrior, config: GroundPriorConfig, ground: GroundConfig | None = None
) -> np.ndarray:
    """(H, W) bool ground mask of one SP cycle on ``scan`` with the ground ``prior``, the
    sensor 1.8 m over the world's ground at z = 0."""
    import kd_store
    from sp.egosphere import EgosphereConfig
    from sp.pipeline import SPConfig
    from wm.entities import KDSensoryProcessor

    cfg = SPConfig(
        egosphere=EgosphereConfig(n_rows=N_ROWS, n_cols=N_COLS, max_returns=1),
        ground_prior=config,
        ground=ground or GroundConfig(),
    )
    sp = KDSensoryProcessor(kd_store.open(":memory:"), cfg)
    T = np.eye(4)
    T[2, 3] = SENSOR_H
    return sp.process(scan, T, ground_prior=prior).ground_mask


@pytest.mark.parametrize("margin_m", [0.2, 10.0])
def test_a_far_bush_standing_above_the_expected_ground_is_an_object(margin_m: float) -> None:
    # one row on a bush 0.75 m over the flat ground at 37.5 m, 2.2 degrees over a 0.2 m bump
    # at 24 m, so the column walk takes it for ground
    bump = [(3.0 + 1.5 * k, -SENSOR_H) for k in range(12)] + [(24.0, -SENSOR_H + 0.2)]
    scan, valid, bush = _scan_rows(bump, [(37.5, -SENSOR_H + 0.75)])
    ground = _ground_after_sp(scan, _flat_prior(0.0), GroundPriorConfig(object_margin_m=margin_m))
    # the bush row stands 0.75 m over the ground the map knows, 0.2 m under its column's
    # ground continued from the bump: without the rule its segment is too low for an object
    assert (ground[bush] == (margin_m > 1.0)).all()
    assert ground[valid & ~bush].all()


def test_far_returns_on_the_ground_the_map_knows_are_marked() -> None:
    # ground at 0 m everywhere, but a 2 m x 2 m block at 1.4 m (a car's body the map fused as
    # ground where it saw nothing lower) around cell (50, 0) and no knowledge near x = -20 m
    n = 256
    z = np.zeros((n, n), dtype=np.float32)
    for ix in range(48, 53):
        for iy in range(-2, 3):
            z[iy % n, ix % n] = 1.4
    z[:, (np.arange(-55, -45)) % n] = np.nan
    prior = GroundPrior(z, (-n // 2, -n // 2), RES)
    cfg = GroundPriorConfig()
    pts = np.array(
        [
            [30.0, 5.0, 0.15],  # far, on the ground
            [30.0, 5.0, 0.35],  # far, 0.35 m above it
            [10.0, 5.0, 0.05],  # near, on the ground
            [20.2, 0.2, 1.45],  # on the block's cell, which stands over the ground beside it
            [-20.0, 0.0, 0.0],  # far, nothing known there
        ]
    )
    xyz = pts.reshape(1, -1, 3)
    rng = np.hypot(xyz[..., 0], xyz[..., 1])
    valid = np.ones(rng.shape, dtype=bool)
    got = on_known_ground(xyz, rng, valid, prior, cfg)
    assert got[0].tolist() == [True, False, True, False, False]
    far_only = GroundPriorConfig(on_ground_min_range_m=15.0)
    assert on_known_ground(xyz, rng, valid, prior, far_only)[0].tolist() == [True] + [False] * 4
    # the block's cell is taken at its word when nothing lower is known near it
    alone = np.full((n, n), np.nan, dtype=np.float32)
    alone[0, 50] = 1.4
    lone = GroundPrior(alone, (-n // 2, -n // 2), RES)
    assert on_known_ground(xyz[:, 3:4], rng[:, 3:4], valid[:, 3:4], lone, cfg).all()
    assert not on_known_ground(xyz, rng, ~valid, prior, cfg).any()  # invalid pixels never


@pytest.mark.parametrize("map_knows_bank", [True, False])
def test_a_far_step_on_the_ground_the_map_knows_is_terrain(map_knows_bank: bool) -> None:
    # flat ground out to 25 m and, over FAR_COLS, a row at 31 m on the foot of a step and
    # one 0.3 m beyond on its top, 0.6 m up
    flat = [(3.0 + 2.0 * k, -SENSOR_H) for k in range(12)]
    scan, _, top = _scan_rows(flat, [(31.0, -SENSOR_H), (31.3, -SENSOR_H + 0.6)])
    # the map: flat at 0, and (when it knows the bank) 0.6 m from x = 31.2 m on
    n = 256
    ix = (np.arange(n) + n // 2) % n - n // 2  # the global cell each storage column holds
    z = np.zeros((n, n), dtype=np.float32)
    if map_knows_bank:
        z[:, (ix + 0.5) * RES > 31.2] = 0.6
    prior = GroundPrior(z, (-n // 2, -n // 2), RES)
    ground = _ground_after_sp(scan, prior, GroundPriorConfig())
    # the step's top row stands 0.6 m over the column's ground: an object to the column walk;
    # on a bank the map knows it is terrain, on ground the map knows flat it stays an object
    assert (ground[top] == map_knows_bank).all()


def test_a_far_rock_its_row_shows_standing_stays_an_object_where_the_map_fused_it() -> None:
    # flat ground out to 25 m; the top row meets a rock 0.6 m up at 37.5 m over FAR_COLS and
    # the ground 60 m out beside it. The map holds 0.6 m past x = 31.2 m: it fused the rock's
    # own returns as ground (the column walk took them for ground in earlier sweeps)
    flat = [(3.0 + 2.0 * k, -SENSOR_H) for k in range(12)]
    scan, _, rock = _scan_rows(flat, [(37.5, -SENSOR_H + 0.6)], beside=[(60.0, -SENSOR_H)])
    n = 256
    ix = (np.arange(n) + n // 2) % n - n // 2
    z = np.zeros((n, n), dtype=np.float32)
    z[:, (ix + 0.5) * RES > 31.2] = 0.6
    prior = GroundPrior(z, (-n // 2, -n // 2), RES)
    # the rock's returns lie on the ground the map knows, but its row shows it standing
    ground = _ground_after_sp(scan, prior, GroundPriorConfig())
    assert not ground[rock].any()
    # without the row's evidence (no piece stands raised_m over the ground line) it is terrain
    blind = GroundConfig(raised_m=5.0)
    assert _ground_after_sp(scan, prior, GroundPriorConfig(), blind)[rock].all()


def test_a_far_low_body_its_rows_show_standing_is_no_terrain_patch() -> None:
    # two rows on the top of a low, broad body 36-37.5 m out (0.28 m and 0.9 m up, a plane
    # tilted 22 degrees, starting within terrain_clearance_m of the ground), both passed by
    # their rows beside it: a terrain patch by its shape, standing by its rows
    flat = [(3.0 + 2.0 * k, -SENSOR_H) for k in range(12)]
    body = [(36.0, -SENSOR_H + 0.28), (37.5, -SENSOR_H + 0.9)]
    scan, valid, top = _scan_rows(flat, body, beside=[(45.0, -SENSOR_H), (60.0, -SENSOR_H)])
    on_body = np.zeros_like(valid)
    on_body[N_ROWS - len(flat) - 2 : N_ROWS - len(flat), FAR_COLS] = True
    assert valid[on_body].all() and top[on_body].sum() == 12
    ground = _ground_after_sp(scan, None, GroundPriorConfig())
    assert not ground[on_body].any()
    # without its rows' evidence it is mostly ground (the walk's and the patch rule's)
    blind = GroundConfig(raised_m=5.0)
    assert _ground_after_sp(scan, None, GroundPriorConfig(), blind)[on_body].sum() >= 20

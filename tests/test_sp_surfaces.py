"""Level-3 free-standing surfaces (sp.surfaces) and the pipeline's level 2 and 3 on a
ray-cast wall standing on a plane (analytic truth) and on a simulated sweep (simulator truth):
the surfaces cover the true walls, keep their ids, classify as walls, carry their ground
contact; class and value images agree with the KD."""

from __future__ import annotations

import math

import numpy as np
import pytest
from kernel_reference.surfaces_reference import (
    crease_pixels_reference,
    find_creases_reference,
    near_blocks_reference,
)

import kd_store
from kd_store import Level, Status
from logs.types import LadarScan
from sp.context import IMAGE_NAMES
from sp.egosphere import EgosphereConfig
from sp.lists import ListConfig, patch_grid
from sp.pipeline import SPConfig
from sp.surfaces import (
    N_PLANE,
    N_STATE,
    SurfaceConfig,
    SurfaceObservations,
    SurfaceTracker,
    components,
    components_scipy,
    crease_pixels,
    find_creases,
    group_patches,
    measure,
    near_blocks,
    plane_fit,
    predict,
    process_noise,
    update,
)
from sp.tracking import TrackStatus
from wm.entities import KDSensoryProcessor

H, W = 32, 360
EL = np.deg2rad(np.linspace(2.0, -25.0, H))  # row 0 highest
AZ = np.pi - (np.arange(W) + 0.5) * 2 * np.pi / W
SENSOR_H = 1.8
WALL = ((8.0, -6.0), (9.0, 6.0), 3.0)  # footprint corners (x, y) and height: a 12 m wall


def wall_scene(dx: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray-cast the ground plane z = -SENSOR_H and the wall (moved by -dx along x, as if the
    sensor had driven dx forward). Returns (xyz (H, W, 3), valid, wall (H, W) bool)."""
    E, A = np.meshgrid(EL, AZ, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1)
    with np.errstate(divide="ignore"):
        t = np.where(d[..., 2] < -1e-6, -SENSOR_H / d[..., 2], np.inf)
    t = np.where(t < 60.0, t, np.inf)
    (x0, y0), (x1, y1), top = WALL
    lo = np.array([x0 - dx, y0, -SENSOR_H])
    hi = np.array([x1 - dx, y1, -SENSOR_H + top])
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = lo / d, hi / d
    tmin = np.nanmax(np.minimum(t0, t1), axis=-1)
    tmax = np.nanmin(np.maximum(t0, t1), axis=-1)
    hit = (tmax >= tmin) & (tmin > 0) & (tmin < t)
    t = np.where(hit, tmin, t)
    valid = np.isfinite(t)
    xyz = np.where(valid[..., None], d * np.where(valid, t, 0)[..., None], np.nan)
    return xyz, valid, hit


def _scan(xyz: np.ndarray, valid: np.ndarray, t_ns: int) -> LadarScan:
    pts = xyz[valid].astype(np.float32)
    ring = (H - 1 - np.nonzero(valid)[0]).astype(np.uint16)
    n = pts.shape[0]
    return LadarScan(t_ns, "ladar", pts, np.full(n, 0.5, np.float32), np.zeros(n, np.int64), ring)


def _sp(kd: kd_store.KnowledgeDatabase) -> KDSensoryProcessor:
    cfg = SPConfig(
        egosphere=EgosphereConfig(n_rows=H, n_cols=W, max_returns=1),
        surfaces=SurfaceConfig(confirm_hits=2),
    )
    return KDSensoryProcessor(kd, cfg)


def _pose(dx: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[0, 3], T[2, 3] = dx, SENSOR_H
    return T


# ---------------------------------------------------------------- grouping and tracking


@pytest.mark.parametrize("seed", range(5))
def test_components_match_scipy(seed: int) -> None:
    g = np.random.default_rng(seed)
    n = int(g.integers(1, 60))
    m = int(g.integers(0, 2 * n))
    a, b = g.integers(0, n, m), g.integers(0, n, m)
    np.testing.assert_array_equal(components(n, a, b), components_scipy(n, a, b))


def test_patches_of_the_wall_group_into_one_vertical_surface() -> None:
    xyz, _, wall = wall_scene()
    g = patch_grid(xyz, wall, ListConfig())
    obs = group_patches(g, 2 * math.pi / W, math.radians(27 / 31))
    assert len(obs) == 1
    assert obs.slope_rad[0] == pytest.approx(math.pi / 2, abs=0.02)
    np.testing.assert_allclose(obs.normal[0], [-1.0, 0.0, 0.0], atol=0.02)  # faces the sensor
    assert obs.centroid[0, 0] == pytest.approx(8.0, abs=0.05)
    assert obs.roughness_m[0] < 0.01
    top = 8.0 * math.tan(EL[0])  # the top beam sees the wall this high above the sensor
    assert obs.height_m[0] == pytest.approx(SENSOR_H + top, abs=0.3)
    # the visible face, 12 m x 3 m, less the rows above the top beam
    assert 20.0 < obs.area_m2[0] < 40.0
    blocks = obs.label[g.block_of_pixel(H, W)]
    assert np.mean(blocks[wall] >= 0) > 0.9  # the surface covers the wall


def _obs(
    normal: np.ndarray,
    centroid: np.ndarray,
    area: float | np.ndarray = 30.0,
    n_pixels: int | np.ndarray = 500,
    roughness: float | np.ndarray = 0.02,
    height: float | np.ndarray = 3.0,
) -> SurfaceObservations:
    """S observed surfaces (centroids in the world frame: the sensor at the origin)."""
    normal = np.atleast_2d(np.asarray(normal, dtype=np.float64))
    S = normal.shape[0]

    def col(v: float | np.ndarray, dtype: type = np.float64) -> np.ndarray:
        return np.broadcast_to(np.asarray(v, dtype=dtype), (S,)).copy()

    return SurfaceObservations(
        label=np.zeros(0, np.int64),
        n_pixels=col(n_pixels, np.int64),
        area_m2=col(area),
        centroid=np.atleast_2d(np.asarray(centroid, dtype=np.float64)),
        normal=normal,
        roughness_m=col(roughness),
        height_m=col(height),
        extent_m=np.sqrt(col(area)),
    )


def _step(tr: SurfaceTracker, obs: SurfaceObservations, t_ns: int, next_id: list[int]):
    idx = tr.match(obs.normal, obs.centroid, obs.area_m2)
    n_new = int(np.count_nonzero(idx < 0))
    new = np.arange(next_id[0], next_id[0] + n_new, dtype=np.int64)
    next_id[0] += n_new
    return tr.update(idx, new, obs, obs.centroid, t_ns)


def test_tracker_keeps_ids_matches_by_plane_and_forgets() -> None:
    tr = SurfaceTracker(SurfaceConfig(forget_s=1.0))
    n = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    c = np.array([[8.0, 0.0, 0.0], [20.0, 0.0, -1.8]])
    obs = _obs(n, c, area=np.array([30.0, 50.0]))
    ids = tr.update(tr.match(n, c, obs.area_m2), np.array([7, 9]), obs, c, 0)
    assert ids.tolist() == [7, 9]
    # next sweep: the wall seen 1 m further along itself, a new parallel wall 3 m behind it
    n2 = np.array([[-1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    c2 = np.array([[8.05, 1.0, 0.1], [11.0, 0.0, 0.0]])
    idx = tr.match(n2, c2, np.array([30.0, 30.0]))
    assert idx.tolist() == [0, -1]
    ids2 = tr.update(idx, np.array([12]), _obs(n2, c2), c2, 500_000_000)
    assert ids2.tolist() == [7, 12]
    assert tr.forget(1_200_000_000).tolist() == [9]  # unseen since t = 0
    assert tr.ids.tolist() == [7, 12]
    np.testing.assert_array_equal(tr.rows(np.array([12, 7])), [1, 0])


# ---------------------------------------------------------------- recursive estimation

N_TRUE = np.array([-math.cos(0.3), -math.sin(0.3), 0.0])  # a wall facing the sensor
OFFSET_TRUE = -9.0  # N_TRUE . p = OFFSET_TRUE on the wall


def _sighting(g: np.random.Generator, sigma_n: float = 0.004, sigma_d: float = 0.01):
    """One noisy sighting of the true wall: a random visible part (centroid along the wall),
    the normal tilted by sigma_n rad, the centroid off the wall by sigma_d m."""
    u = np.cross(N_TRUE, [0.0, 0.0, 1.0])
    along = g.uniform(-3.0, 3.0) * u + g.uniform(-0.5, 0.5) * np.array([0.0, 0.0, 1.0])
    c = OFFSET_TRUE * N_TRUE + along + g.normal(0.0, sigma_d) * N_TRUE
    n = N_TRUE + g.normal(0.0, sigma_n, 3)
    return _obs(n / np.linalg.norm(n), c, area=g.uniform(20.0, 40.0))


def test_consistent_surface_is_confirmed_and_converges_to_the_true_plane() -> None:
    g = np.random.default_rng(3)
    tr = SurfaceTracker(SurfaceConfig())
    next_id = [1]
    conf, var_n = [], []
    for k in range(30):
        ids = _step(tr, _sighting(g), k * 100_000_000, next_id)
        assert ids.tolist() == [1]  # always the same surface
        conf.append(float(tr.confidence[0]))
        var_n.append(float(np.trace(tr.P[0, :3, :3])))
        if k + 1 < tr.config.confirm_hits:
            assert tr.status[0] == TrackStatus.HYPOTHESIZED
    assert tr.status[0] == TrackStatus.CONFIRMED
    assert conf[1] > conf[0] and conf[2] > conf[1]  # grows with consistent sightings
    assert min(conf[3:]) > tr.config.confirm
    assert var_n[-1] < 0.2 * var_n[0]  # the normal's uncertainty shrinks
    normal, offset = tr.plane()
    assert math.degrees(math.acos(min(1.0, float(normal[0] @ N_TRUE)))) < 0.3
    assert offset[0] == pytest.approx(OFFSET_TRUE, abs=0.02)
    assert tr.x[0, 5] == pytest.approx(3.0, abs=0.05)  # height
    assert 20.0 < tr.x[0, 4] < 40.0  # area


@pytest.mark.parametrize("jump", ["offset", "tilt"])
def test_surface_that_jumps_loses_confidence_and_is_denied(jump: str) -> None:
    g = np.random.default_rng(4)
    tr = SurfaceTracker(SurfaceConfig(confirm_hits=5))
    next_id = [1]
    for k in range(3):  # consistent first
        _step(tr, _sighting(g), k * 100_000_000, next_id)
    before = float(tr.confidence[0])
    status = []
    for k in range(3, 6):  # then the plane jumps and stays (still matched)
        o = _sighting(g)
        if jump == "offset":
            o.centroid[0] += 0.5 * N_TRUE  # 0.5 m off the wall, inside the match gate
        else:
            c, s = math.cos(0.2), math.sin(0.2)  # turned 11.5 degrees about the vertical
            o.normal[0] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ o.normal[0]
        ids = _step(tr, o, k * 100_000_000, next_id)
        assert ids.tolist() == [1]
        status.append(int(tr.status[0]))
        if k == 3:
            assert tr.nis[0] > tr.config.gate_chi2
            assert tr.confidence[0] < before
        if tr.status[0] == TrackStatus.DENIED:
            break
    assert status[-1] == TrackStatus.DENIED
    assert TrackStatus.CONFIRMED not in status
    assert tr.drop_denied().tolist() == [1]
    assert len(tr.ids) == 0


def test_unseen_hypothesis_decays_and_is_denied() -> None:
    tr = SurfaceTracker(SurfaceConfig())
    next_id = [1]
    g = np.random.default_rng(5)
    _step(tr, _sighting(g), 0, next_id)
    other = _obs([0.0, 0.0, 1.0], [30.0, 0.0, -1.8])  # only another surface is seen
    conf = [float(tr.confidence[0])]
    for k in range(1, 10):
        _step(tr, other, k * 100_000_000, next_id)
        conf.append(float(tr.confidence[0]))
        if tr.status[0] == TrackStatus.DENIED:
            break
    assert np.all(np.diff(conf) < 0)
    assert tr.status[0] == TrackStatus.DENIED


def test_filter_equals_filterpy() -> None:
    from filterpy.kalman import KalmanFilter

    g = np.random.default_rng(6)
    cfg = SurfaceConfig()
    T = 3
    anchor = g.normal(0.0, 5.0, (T, 3))
    refs = []
    x = P = None
    for _ in range(8):
        n = g.normal(0.0, 1.0, (T, 3))
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        c = anchor + g.normal(0.0, 2.0, (T, 3))
        o = _obs(n, c, area=g.uniform(0, 50, T), n_pixels=g.integers(1, 900, T),
                 roughness=g.uniform(0, 0.1, T))  # fmt: skip
        ref = n if x is None else x[:, :3]
        z, R = measure(o, c, anchor, ref, cfg)
        if x is None:
            x, P = z.copy(), R.copy()
            for t in range(T):
                kf = KalmanFilter(dim_x=N_STATE, dim_z=N_STATE)
                kf.x, kf.P, kf.F, kf.H = z[t].copy(), R[t].copy(), np.eye(7), np.eye(7)
                refs.append(kf)
            continue
        dt = g.uniform(0.05, 0.3, T)
        Q = process_noise(dt, cfg)
        x, P = predict(x, P, Q)
        x, P, nis = update(x, P, z, R)
        for t, kf in enumerate(refs):
            kf.predict(Q=Q[t])
            kf.update(z[t], R=R[t])
            np.testing.assert_allclose(x[t], kf.x, rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(P[t], kf.P, rtol=1e-8, atol=1e-12)
            yp, Sp = kf.y[:N_PLANE], kf.S[:N_PLANE, :N_PLANE]
            assert nis[t] == pytest.approx(float(yp @ np.linalg.solve(Sp, yp)), rel=1e-9)


def _spd(P: np.ndarray) -> bool:
    return bool(np.allclose(P, P.transpose(0, 2, 1), atol=0.0) and np.linalg.eigvalsh(P).min() > 0)


def test_covariances_stay_spd_with_degenerate_fits() -> None:
    # 3 collinear points: the fitted "normal" is any axis across the line, zero residual
    line = np.array([[8.0, 0.0, 0.0], [8.0, 0.5, 0.0], [8.0, 1.0, 0.0]])
    c3, n3, k3 = plane_fit(np.zeros(3, np.int64), line, 1)
    assert k3.tolist() == [3] and abs(float(n3[0] @ [0.0, 1.0, 0.0])) < 1e-9
    cases = [
        _obs(n3, c3, area=0.0, n_pixels=3, roughness=0.0, height=0.0),  # collinear
        _obs([-1.0, 0.0, 0.0], [8.0, 0.2, 0.0], area=0.0, n_pixels=1, roughness=0.0),  # 1 px
        _obs([0.0, 0.0, 0.0], [8.0, 0.1, 0.0], area=0.0, n_pixels=0, roughness=0.0),  # none
    ]
    tr = SurfaceTracker(SurfaceConfig())
    none = np.zeros(0, np.int64)
    tr.update(np.array([-1]), np.array([1]), cases[0], cases[0].centroid, 0)
    assert _spd(tr.P)
    for k, o in enumerate(cases * 3):  # each continues the one surface
        tr.update(np.array([0]), none, o, o.centroid, (k + 1) * 100_000_000)
        assert np.all(np.isfinite(tr.x)) and _spd(tr.P)
        z, R = measure(o, o.centroid, tr.anchor[:1], tr.normal[:1], tr.config)
        assert np.all(np.isfinite(z)) and _spd(R)
    assert tr.ids.tolist() == [1]


def test_plane_fit_recovers_random_planes() -> None:
    g = np.random.default_rng(7)
    L = 4
    n_true = g.normal(0.0, 1.0, (L, 3))
    n_true /= np.linalg.norm(n_true, axis=1, keepdims=True)
    lab = g.integers(0, L, 400)
    p = g.normal(0.0, 3.0, (400, 3))
    p -= np.einsum("ij,ij->i", p, n_true[lab])[:, None] * n_true[lab]  # onto planes through 0
    p += n_true[lab] * np.arange(L)[lab, None]  # plane l at offset l
    c, n, k = plane_fit(lab, p, L)
    assert k.sum() == 400
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", n, n_true)), 1.0, atol=1e-9)
    np.testing.assert_allclose(np.einsum("ij,ij->i", c, n_true), np.arange(L), atol=1e-9)


# ---------------------------------------------------------------- the pipeline


def test_pipeline_free_surface_on_the_wall_persists_and_touches_the_ground() -> None:
    kd = kd_store.open(":memory:")
    sp = _sp(kd)
    first = None
    for k in range(2):  # in the third sweep the wall is a confirmed object (and its face)
        dx = 0.3 * k
        xyz, valid, wall = wall_scene(dx)
        r = sp.process(_scan(xyz, valid, k * 100_000_000), _pose(dx))
        img3 = r.entity_images[3]
        # the wall is not yet a confirmed object: its pixels are a free surface
        on = np.unique(img3[wall & ~r.ground_mask])
        on = on[on >= 0]
        assert on.size == 1 and on[0] in r.surfaces
        assert np.mean(img3[wall & ~r.ground_mask] == on[0]) > 0.85
        first = int(on[0]) if first is None else first
        assert on[0] == first  # the same surface from sweep to sweep
    g = kd.get(sp.level3.ground_id)  # the ground plane: flat, under the sensor at world z = 0
    assert g.attributes["slope_rad"].observed < 0.01
    assert g.attributes["roughness_m"].observed < 0.01
    assert g.state.position_xyz[2] == pytest.approx(0.0, abs=0.02)
    s = kd.get(first)
    assert s.level == Level.SURFACE and IMAGE_NAMES[3] in s.images
    assert s.status == Status.CONFIRMED  # seen in confirm_hits sweeps
    assert "wall" in s.generic_classes
    assert s.attributes["slope_rad"].observed == pytest.approx(math.pi / 2, abs=0.05)
    assert s.state.position_xyz[0] == pytest.approx(8.0, abs=0.2)  # world x of the wall face
    # its ground contact: a level-2 list of the surface, on the ground, on the bottom row
    contact = [i for i in kd.parts(first) if kd.get(i).name.startswith("contact")]
    assert len(contact) == 1
    assert sp.level3.ground_id in kd.pointers(contact[0], "on_top_of")
    rows, cols = np.nonzero(r.entity_images[2] == contact[0])
    assert rows.size >= 20 and np.all(r.ground_mask[rows + 1, cols])
    # its surface patches: a level-2 list of kind surface_patch, classified so
    img2 = r.entity_images[2]
    patches = [i for i in kd.parts(first) if kd.get(i).name.startswith("surface_patch")]
    assert len(patches) == 1
    assert kd.get(patches[0]).generic_classes[-1] == "surface_patch"
    assert np.all(img3[img2 == patches[0]] == first)
    assert not any(kd.get(int(i)).name.startswith("crease") for i in np.unique(img2[img2 >= 0]))
    assert s.confidence > sp.config.surfaces.confirm  # consistent sightings


def test_class_images_agree_with_the_kd_and_value_images_with_the_library() -> None:
    kd = kd_store.open(":memory:")
    sp = _sp(kd)
    r = None
    for k in range(4):
        xyz, valid, _ = wall_scene()
        r = sp.process(_scan(xyz, valid, k * 100_000_000), _pose())
    assert r is not None
    names = r.class_names
    seen = 0
    for level in (2, 3, 4, 5):
        ent, cls = r.entity_images[level], r.class_images[level]
        assert cls.shape == ent.shape and cls.dtype == np.int32
        assert np.all(cls[ent < 0] == -1)
        for i in np.unique(ent[ent >= 0]):
            f = kd.get(int(i))
            assert f.level == level
            got = set(cls[ent == i].tolist())
            assert len(got) == 1  # one class per entity
            c = got.pop()
            if level == 4:
                want = sp.level4.track_class.get(int(i), (None, 0))[0]
                assert (names[c] if c >= 0 else None) == want
            else:
                assert c >= 0 and names[c] == f.generic_classes[-1]
                seen += 1
    assert seen >= 3  # the ground, a surface and lists at least
    comp = np.where(r.class_images[4] >= 0, r.class_images[4], r.class_images[3])
    for n in ("cost", "risk", "worth_preserve"):
        v = r.value_images[n]
        assert v.dtype == np.float32 and v.shape == (H, W)
        assert np.isnan(v[comp < 0]).all()
        for c in np.unique(comp[comp >= 0]):
            want = getattr(kd.classes.get(names[c]).value, n)
            assert np.all(v[comp == c] == np.float32(want))
    flat = r.point_pixel
    np.testing.assert_array_equal(r.point_class_ids, comp.reshape(-1)[flat])


def box_scene(boxes: list[tuple[tuple[float, ...], tuple[float, ...]]]):
    """Ray-cast the ground plane z = -SENSOR_H and axis-aligned boxes (lo, hi corners, sensor
    frame). Returns (xyz (H, W, 3), valid (H, W), box (H, W) int64 index hit, -1 none)."""
    E, A = np.meshgrid(EL, AZ, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1)
    with np.errstate(divide="ignore"):
        t = np.where(d[..., 2] < -1e-6, -SENSOR_H / d[..., 2], np.inf)
    t = np.where(t < 60.0, t, np.inf)
    box = np.full(t.shape, -1, dtype=np.int64)
    for i, (lo, hi) in enumerate(boxes):
        with np.errstate(divide="ignore", invalid="ignore"):
            t0, t1 = np.array(lo) / d, np.array(hi) / d
        tmin = np.nanmax(np.minimum(t0, t1), axis=-1)
        tmax = np.nanmin(np.maximum(t0, t1), axis=-1)
        hit = (tmax >= tmin) & (tmin > 0) & (tmin < t)
        t, box = np.where(hit, tmin, t), np.where(hit, i, box)
    valid = np.isfinite(t)
    xyz = np.where(valid[..., None], d * np.where(valid, t, 0)[..., None], np.nan)
    return xyz, valid, box


def test_two_walls_at_a_right_angle_have_one_crease_along_the_corner() -> None:
    z0, z1 = -SENSOR_H, 1.2
    # a wall across the view at x = 8 and one along it at y = 4: a corner at (8, 4)
    xyz, valid, box = box_scene(
        [((8.0, -6.0, z0), (8.3, 4.3, z1)), ((2.0, 4.0, z0), (8.3, 4.3, z1))]
    )
    kd = kd_store.open(":memory:")
    sp = _sp(kd)
    r = sp.process(_scan(xyz, valid, 0), _pose())
    img3 = r.entity_images[3]
    walls = []
    for i in range(2):  # each wall is a free surface
        ids, n = np.unique(img3[box == i], return_counts=True)
        walls.append(int(ids[np.argmax(n)]))
        assert walls[-1] in r.surfaces
    creases = [
        i
        for i in np.unique(r.entity_images[2])
        if i >= 0 and kd.get(int(i)).name.startswith("crease")
    ]
    assert len(creases) == 1
    c = kd.get(int(creases[0]))
    assert c.level == Level.LIST and c.generic_classes[-1] == "slope_edge"
    parent = kd.pointers(c.id, "belongs_to")
    beside = kd.pointers(c.id, "beside")
    assert sorted(parent + beside) == sorted(walls)
    assert c.id in kd.parts(parent[0])
    # its pixels lie along the corner: near the vertical line (8, 4), over most of its rows
    on = r.entity_images[2] == c.id
    p = xyz[on]
    assert np.all(np.hypot(p[:, 0] - 8.0, p[:, 1] - 4.0) < 0.4)
    rows_corner = np.unique(
        np.nonzero((box >= 0) & (np.hypot(xyz[..., 0] - 8, xyz[..., 1] - 4) < 0.3))[0]
    )
    assert np.unique(np.nonzero(on)[0]).size >= 0.7 * rows_corner.size
    assert np.all(np.isin(img3[on], [walls[0], walls[1], -1]))
    # the next sweep finds the same crease
    r2 = sp.process(_scan(xyz, valid, 100_000_000), _pose())
    assert np.count_nonzero(r2.entity_images[2] == c.id) >= 0.8 * np.count_nonzero(on)


def test_find_creases_ignores_coplanar_and_distant_surfaces() -> None:
    bh, bw = 4, 16
    blocks = np.full((2, 10), -1, np.int64)
    # 0 next to 1 (17 degrees apart: no crease) and, round the wrap, 2 blocks from 2 (at 90
    # degrees: a crease); 3 at 90 degrees too but 4 blocks from anything
    blocks[:, 0], blocks[:, 1], blocks[:, 8], blocks[:, 5] = 0, 1, 2, 3
    label = np.repeat(np.repeat(blocks, bh, axis=0), bw, axis=1)
    n = np.array([[1.0, 0, 0], [math.cos(0.3), math.sin(0.3), 0], [0, 1.0, 0], [0, 0, 1.0]])
    g = np.random.default_rng(8)
    xyz = g.normal(0.0, 1.0, (*label.shape, 3))
    xyz[..., :2] *= 0.05  # near the z axis: the line where planes 0 and 2 (through 0) meet
    free = np.ones(label.shape, bool)
    args = (label, free, xyz, np.arange(4), n, np.zeros((4, 3)))
    cr = find_creases(blocks, (bh, bw), *args, SurfaceConfig())
    assert (cr.a.tolist(), cr.b.tolist()) == ([0], [2])
    # its pixels: those of 0, 2 or none, near both, within the tolerance of the line
    assert cr.pixel.size > 0 and np.all(cr.crease == 0)
    assert np.all(np.isin(label.reshape(-1)[cr.pixel], [0, 2, -1]))
    assert np.all(np.hypot(*xyz.reshape(-1, 3)[cr.pixel, :2].T) <= 0.25)
    ref = find_creases_reference(blocks, (bh, bw), *args, SurfaceConfig())
    np.testing.assert_array_equal(ref.pixel, cr.pixel)
    narrow = SurfaceConfig(crease_gap_blocks=1)
    assert len(find_creases(blocks, (bh, bw), *args, narrow)) == 0


def _random_blocks(g: np.random.Generator, shape: tuple[int, int], S: int) -> np.ndarray:
    lab = g.integers(-1, S, shape)
    return np.where(g.random(shape) < 0.4, -1, lab)


@pytest.mark.parametrize("seed", range(6))
def test_crease_kernels_match_their_numpy_references(seed: int) -> None:
    g = np.random.default_rng(seed)
    nbr, nbc = int(g.integers(1, 6)), int(g.integers(1, 12))
    S = int(g.integers(1, 6))
    blocks = _random_blocks(g, (nbr, nbc), S)
    if seed == 0:
        blocks[:] = -1  # degenerate: no surface at all
    for gap in (0, 1, 2, 3):
        got = near_blocks(blocks, gap)
        want = near_blocks_reference(blocks, gap)
        assert sorted(zip(*got, strict=True)) == sorted(zip(*want, strict=True))
    bh, bw = int(g.integers(1, 5)), int(g.integers(1, 6))
    H, W = nbr * bh - int(g.integers(0, bh)), nbc * bw  # a last block row cut short
    label = g.integers(-1, S + 2, (H, W))
    free = g.random((H, W)) < 0.5
    xyz = g.normal(0.0, 1.0, (H, W, 3))
    xyz[g.random((H, W)) < 0.1] = np.nan  # no return
    C = 3
    pair = g.integers(0, C, 20)
    blk = g.integers(0, nbr * nbc, 20)
    u = g.normal(0.0, 1.0, (C, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    args = (pair, blk, nbc, (bh, bw), label, free, xyz, g.integers(0, S, C),
            g.integers(0, S, C), g.normal(0.0, 1.0, (C, 3)), u, 0.5, 0.4)  # fmt: skip
    got, want = crease_pixels(*args), crease_pixels_reference(*args)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    n = g.normal(0.0, 1.0, (S, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    fa = (blocks, (bh, bw), label, free, xyz, np.arange(S), n, g.normal(0.0, 1.0, (S, 3)))
    a = find_creases(*fa, az_step_rad=0.1)
    b = find_creases_reference(*fa, az_step_rad=0.1)
    for name in ("a", "b", "pixel", "crease"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def _in_boxes(p: np.ndarray, boxes, margin: float) -> np.ndarray:
    out = np.full(len(p), -1)
    for k in range(len(boxes.ids)):
        d = p - boxes.centers[k]
        ca, sa = math.cos(boxes.yaws[k]), math.sin(boxes.yaws[k])
        lx, ly = d[:, 0] * ca + d[:, 1] * sa, -d[:, 0] * sa + d[:, 1] * ca
        s = boxes.sizes[k] / 2 + margin
        out[(abs(lx) <= s[0]) & (abs(ly) <= s[1]) & (abs(d[:, 2]) <= s[2])] = k
    return out


def test_simulated_sweep_surfaces_cover_the_true_walls() -> None:
    from fixtures.simulate import simulate
    from logs.types import GroundTruthPose, ObjectBoxes, TransformFrame

    kd = kd_store.open(":memory:")
    sp = KDSensoryProcessor(kd)
    T_body_ladar = T_world_body = boxes = None
    for f in simulate("default", seconds=0.2):
        if isinstance(f, TransformFrame) and f.child_frame_id == "ladar":
            T_body_ladar = f.T_parent_child
        elif isinstance(f, GroundTruthPose):
            T_world_body = f.T_parent_child
        elif isinstance(f, ObjectBoxes):
            boxes = f
        elif isinstance(f, LadarScan) and T_body_ladar is not None and boxes is not None:
            r = sp.process(f, T_world_body @ T_body_ladar)
            break
    # the first sweep: no object confirmed yet, every wall is a free surface
    surf = np.isin(r.entity_images[3].reshape(-1)[r.point_pixel], r.surfaces)
    k = _in_boxes(r.points_world.astype(np.float64), boxes, 0.5)
    wallish = np.array([c in ("building", "wall") for c in boxes.classes])
    on_wall = (k >= 0) & wallish[np.maximum(k, 0)]
    assert on_wall.sum() > 300
    assert (surf & on_wall).sum() >= 0.9 * surf.sum()  # surfaces lie on true walls
    assert (surf & on_wall).sum() >= 0.5 * on_wall.sum()  # and cover most of them
    for s in r.surfaces:
        assert "wall" in kd.get(s).generic_classes


def test_real_av2_sweeps_surface_innovations_fit_their_gate(real_data) -> None:
    """Two real Argoverse 2 sweeps (true ego poses): the surfaces of the second that continue
    ones of the first have innovations the filter's R explains (the plane NIS of a 4-dof
    chi-square has mean 4: R not overconfident; nearly all within the 99.9 % gate)."""
    from test_sp_levels_eval import AV2_SWEEPS_NS, _av2_pose, _feather, av2_egosphere

    folder = real_data / "av2"
    calib = _feather(folder / "calibration" / "egovehicle_SE3_sensor.feather")
    T_ego_ladar = _av2_pose(calib, int(np.flatnonzero(calib["sensor_name"] == "up_lidar")[0]))
    poses = _feather(folder / "city_SE3_egovehicle.feather")
    kd = kd_store.open(":memory:")
    sp = KDSensoryProcessor(kd, SPConfig(egosphere=av2_egosphere()))
    tr = sp.level3.surface_tracker
    seen: list[set[int]] = []
    for t_ns in AV2_SWEEPS_NS:
        c = _feather(folder / "sensors" / "lidar" / f"{t_ns}.feather")
        xyz = np.stack([c["x"], c["y"], c["z"]], axis=1).astype(np.float64)
        xyz_l = ((xyz - T_ego_ladar[:3, 3]) @ T_ego_ladar[:3, :3]).astype(np.float32)
        n = xyz_l.shape[0]
        scan = LadarScan(t_ns, "ladar", xyz_l, c["intensity"].astype(np.float32),
                         np.zeros(n, np.int64))  # fmt: skip
        T = _av2_pose(poses, int(np.flatnonzero(poses["timestamp_ns"] == t_ns)[0]))
        r = sp.process(scan, T @ T_ego_ladar)
        seen.append(set(r.surfaces))
    both = np.array(sorted(seen[0] & seen[1]), dtype=np.int64)
    denied = [i for i in seen[0] - seen[1] if kd.get(i).status == Status.DENIED]
    assert both.size >= 20  # most surfaces continue
    nis = tr.nis[tr.rows(both)]
    assert np.median(nis) < 4.0
    # the denied ones (removed from the table) count as outside the gate
    assert np.count_nonzero(nis <= tr.config.gate_chi2) >= 0.85 * (both.size + len(denied))

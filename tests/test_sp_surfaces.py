"""Level-3 free-standing surfaces (sp.surfaces) and the pipeline's level 2 and 3 on a
ray-cast wall standing on a plane (analytic truth) and on a simulated sweep (simulator truth):
the surfaces cover the true walls, keep their ids, classify as walls, carry their ground
contact; class and value images agree with the KD."""

from __future__ import annotations

import math

import numpy as np
import pytest

import kd_store
from kd_store import Level, Status
from sp.egosphere import EgosphereConfig
from sp.lists import ListConfig, patch_grid
from sp.logs.types import LadarScan
from sp.pipeline import IMAGE_NAMES, SensoryProcessor, SPConfig
from sp.surfaces import SurfaceConfig, SurfaceTracker, components, components_scipy, group_patches

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


def _sp(kd: kd_store.KnowledgeDatabase) -> SensoryProcessor:
    cfg = SPConfig(
        egosphere=EgosphereConfig(n_rows=H, n_cols=W, max_returns=1),
        surfaces=SurfaceConfig(confirm_hits=2),
    )
    return SensoryProcessor(kd, cfg)


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


def test_tracker_keeps_ids_matches_by_plane_and_forgets() -> None:
    tr = SurfaceTracker(SurfaceConfig(forget_s=1.0))
    n = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    c = np.array([[8.0, 0.0, 0.0], [20.0, 0.0, -1.8]])
    ids = tr.update(tr.match(n, c, np.array([30.0, 50.0])), np.array([7, 9]), n, c,
                    np.array([6.0, 5.0]), 0)  # fmt: skip
    assert ids.tolist() == [7, 9]
    # next sweep: the wall seen 1 m further along itself, a new parallel wall 3 m behind it
    n2 = np.array([[-1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    c2 = np.array([[8.05, 1.0, 0.1], [11.0, 0.0, 0.0]])
    idx = tr.match(n2, c2, np.array([30.0, 30.0]))
    assert idx.tolist() == [0, -1]
    ids2 = tr.update(idx, np.array([12]), n2, c2, np.array([6.0, 4.0]), 500_000_000)
    assert ids2.tolist() == [7, 12]
    assert tr.forget(1_200_000_000).tolist() == [9]  # unseen since t = 0
    assert tr.ids.tolist() == [7, 12]


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
    g = kd.get(sp.ground_id)  # the ground plane: flat, under the sensor at world z = 0
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
    assert sp.ground_id in kd.pointers(contact[0], "on_top_of")
    rows, cols = np.nonzero(r.entity_images[2] == contact[0])
    assert rows.size >= 20 and np.all(r.ground_mask[rows + 1, cols])
    # its surface patches: a level-2 list of kind surface_patch, classified so
    img2 = r.entity_images[2]
    patches = [i for i in kd.parts(first) if kd.get(i).name.startswith("surface_patch")]
    assert len(patches) == 1
    assert kd.get(patches[0]).generic_classes[-1] == "surface_patch"
    assert np.all(img3[img2 == patches[0]] == first)


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
                want = sp.track_class.get(int(i), (None, 0))[0]
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
    from sp.logs.types import GroundTruthPose, ObjectBoxes, TransformFrame

    kd = kd_store.open(":memory:")
    sp = SensoryProcessor(kd)
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

"""Predictions for the next cycle (reference 001, 4.2 item 2; docs/architecture.md, the node
cycle, step 6).

* Expected entity states: each entity observed this cycle gets a short-term expectation queue
  (4.4.2) by a constant-velocity model, ``x*(t+dt) = F x(t)``, ``P* = F P F^T + Q dt``
  (the ``x*(t|t-1)`` of the estimator ``x(t|t) = x*(t|t-1) + K (y - y*)``, reference 001,
  4.5.4).
* A predicted range image for the next sweep pose, ray-cast (open3d) against the current
  elevation map (a height-field mesh) and entity boxes at their predicted positions.
  Compared with the observed sweep, the pixels that differ by more than ``mismatch_m`` are
  surprises: their world points become next cycle's attention (4.5.1, windowing), and a
  surprise that stays over consecutive comparisons opens a ``world_change`` event (4.4.8).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d  # ray casting; imported with the module, not inside the first cycle

import kd_store
from core.geometry import se3_inverse, transform_points
from kd_store import Level, State, Status
from logs.types import LadarScan
from maps.level import MapLevel
from wm.config import PredictionConfig
from wm.shapes import boxes_of

Q_POS_M2_PER_S = 0.05  # process noise of the constant-velocity model, per second
Q_VEL_M2S2_PER_S = 0.5
SURPRISE_EVENT_FRACTION = 0.02  # fraction of compared pixels that counts as a change


def expect_entities(
    kd: kd_store.KnowledgeDatabase,
    steps_s: tuple[float, ...],
    min_confidence: float = 0.5,
    min_speed_mps: float = 0.2,
    skip: int = -1,
) -> list[int]:
    """Write expectation queues (``steps_s`` seconds after each state) for the object and
    group entities confirmed, observed this cycle with at least ``min_confidence`` and moving
    (a static entity's expectation is its state, so one that stops loses its queue);
    returns their ids. The KD drops expectations a later observation overtakes."""
    out = []
    for eid in kd.observed_this_cycle().tolist():
        if eid == skip:
            continue
        try:
            f = kd.get(int(eid))
        except kd_store.KDError:
            continue  # an event id, or forgotten
        s = f.state
        if (
            s is None
            or f.level < Level.OBJECT
            or f.status != Status.CONFIRMED
            or f.confidence < min_confidence
        ):
            continue
        if float(np.linalg.norm(s.velocity_xyz)) < min_speed_mps:
            if f.expectations:  # it stopped: last cycle's queue came from an old velocity
                kd.expect(f.id, [])
            continue
        kd.expect(f.id, propagate_many(s, steps_s))
        out.append(f.id)
    return out


_Q_DIAG = np.array([Q_POS_M2_PER_S] * 3 + [Q_VEL_M2S2_PER_S] * 3)


def propagate(s: State, dt_s: float) -> State:
    """The state ``dt_s`` seconds on at constant velocity, covariance grown (module docstring)."""
    return propagate_many(s, (dt_s,))[0]


def propagate_many(s: State, steps_s: tuple[float, ...] | list[float]) -> list[State]:
    """:func:`propagate` to each of ``steps_s`` (s) at once: ``x* = F x``, ``P* = F P F^T +
    Q |dt|`` for every step in one batch of (K, 6, 6) products."""
    dt = np.asarray(steps_s, dtype=np.float64).reshape(-1)
    F = np.broadcast_to(np.eye(6), (dt.size, 6, 6)).copy()
    F[:, 0, 3] = F[:, 1, 4] = F[:, 2, 5] = dt
    P = F @ s.covariance @ F.transpose(0, 2, 1)
    P[:, np.arange(6), np.arange(6)] += _Q_DIAG * np.abs(dt)[:, None]
    P = 0.5 * (P + P.transpose(0, 2, 1))
    pos = s.position_xyz + dt[:, None] * s.velocity_xyz
    return [
        State(
            s.t_ns + round(float(d) * 1e9),
            s.frame,
            pos[k],
            s.orientation_xyzw,
            s.velocity_xyz,
            P[k],
            s.orientation_var_rpy,
        )
        for k, d in enumerate(dt)
    ]


# --- predicted range image ---------------------------------------------------------------------


@dataclass
class RangePrediction:
    """A predicted range image: ``range_m`` (H, W) float32 (inf: no return expected) seen from
    ``T_world_ladar`` at ``t_ns``; rows span ``elevation_rad`` (lo, hi), columns azimuth
    -pi..pi."""

    t_ns: int
    T_world_ladar: np.ndarray
    range_m: np.ndarray
    elevation_rad: tuple[float, float]


@dataclass
class Comparison:
    """Observed vs predicted: median |error| (m) where both have a return, the fraction of
    those pixels that are surprises, and surprise points (K, 3) in the world."""

    median_abs_error_m: float
    surprise_fraction: float
    n_compared: int
    surprise_world_xyz: np.ndarray


def heightfield_mesh(level: MapLevel, stride: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of the level's elevation window, every ``stride`` cells: vertices (V, 3)
    float32 world metres, triangles (T, 3) int32; quads with an unknown corner are left out."""
    e = level.window("elevation")[::stride, ::stride]
    rows, cols = np.mgrid[0 : level.size : stride, 0 : level.size : stride]
    xy = level.window_to_world(rows.ravel(), cols.ravel())
    verts = np.column_stack([xy, e.ravel()]).astype(np.float32)
    h, w = e.shape
    idx = np.arange(h * w).reshape(h, w)
    ok = np.isfinite(e)
    quad = ok[:-1, :-1] & ok[1:, :-1] & ok[:-1, 1:] & ok[1:, 1:]
    a, b = idx[:-1, :-1][quad], idx[:-1, 1:][quad]
    c, d = idx[1:, :-1][quad], idx[1:, 1:][quad]
    tris = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)]).astype(np.int32)
    verts[~np.isfinite(verts)] = 0.0
    return verts, tris


def box_meshes(centers, sizes, yaws) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of M oriented boxes (bottom at centre z - h/2): (8M, 3), (12M, 3)."""
    unit = np.array(
        [[x, y, z] for z in (-0.5, 0.5) for y in (-0.5, 0.5) for x in (-0.5, 0.5)], np.float64
    )
    faces = np.array(
        [[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
         [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]], np.int32
    )  # fmt: skip
    m = len(centers)
    if m == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32)
    c, s = np.cos(yaws), np.sin(yaws)
    local = unit[None] * sizes[:, None, :]
    x = c[:, None] * local[..., 0] - s[:, None] * local[..., 1]
    y = s[:, None] * local[..., 0] + c[:, None] * local[..., 1]
    verts = np.stack([x, y, local[..., 2]], -1) + centers[:, None, :]
    tris = faces[None] + 8 * np.arange(m)[:, None, None]
    return verts.reshape(-1, 3).astype(np.float32), tris.reshape(-1, 3).astype(np.int32)


def egosphere_rays(hw: tuple[int, int], elevation_rad: tuple[float, float]) -> np.ndarray:
    """Unit ray directions (H, W, 3) in the sensor frame: rows from low to high elevation,
    columns azimuth from -pi to pi (pixel centres)."""
    h, w = hw
    el = elevation_rad[0] + (np.arange(h) + 0.5) * (elevation_rad[1] - elevation_rad[0]) / h
    az = -np.pi + (np.arange(w) + 0.5) * 2 * np.pi / w
    E, A = np.meshgrid(el, az, indexing="ij")
    return np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1)


def predict_range_image(
    level: MapLevel,
    kd: kd_store.KnowledgeDatabase,
    T_world_ladar: np.ndarray,
    t_ns: int,
    config: PredictionConfig,
    scan: LadarScan,
    skip: int = -1,
) -> RangePrediction | None:
    """Ray-cast the expected range image of a sweep from ``T_world_ladar`` at ``t_ns``; the
    elevation span is the current sweep's. None when the map holds no terrain yet."""
    p = np.asarray(scan.points_xyz, dtype=np.float64)
    if len(p) < 10:
        return None
    el = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))
    span = (float(np.percentile(el, 0.5)), float(np.percentile(el, 99.5)))
    verts, tris = heightfield_mesh(level)
    if len(tris) == 0:
        return None
    frames = [
        f
        for f in kd.entities()
        if f.id != skip and f.level == Level.OBJECT and f.state is not None
        and f.state.frame == "world"
    ]  # fmt: skip
    ents = boxes_of(frames)
    if len(ents):
        dt = (t_ns - np.array([f.state.t_ns for f in frames])) * 1e-9  # type: ignore[union-attr]
        centers = ents.centers_xyz + dt[:, None] * ents.velocities_xyz
        bv, bt = box_meshes(centers, ents.sizes_lwh, ents.yaws)
        tris = np.concatenate([tris, bt + len(verts)])
        verts = np.concatenate([verts, bv])
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(verts), o3d.core.Tensor(tris.astype(np.uint32)))
    dirs = egosphere_rays(config.range_image_hw, span) @ T_world_ladar[:3, :3].T
    origin = np.broadcast_to(T_world_ladar[:3, 3], dirs.shape)
    rays = np.concatenate([origin, dirs], -1).reshape(-1, 6).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return RangePrediction(t_ns, T_world_ladar, hit.reshape(config.range_image_hw), span)


def range_image(
    points_sensor: np.ndarray, hw: tuple[int, int], elevation_rad: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest range per pixel (H, W) float32 (inf: none) of sensor points (N, 3), and each
    point's flat pixel index (N,) (-1 outside the elevation span)."""
    h, w = hw
    r = np.linalg.norm(points_sensor, axis=1)
    el = np.arctan2(points_sensor[:, 2], np.hypot(points_sensor[:, 0], points_sensor[:, 1]))
    az = np.arctan2(points_sensor[:, 1], points_sensor[:, 0])
    row = np.floor((el - elevation_rad[0]) / (elevation_rad[1] - elevation_rad[0]) * h)
    col = np.clip(np.floor((az + np.pi) / (2 * np.pi) * w), 0, w - 1)
    ok = (row >= 0) & (row < h)
    pix = np.where(ok, row * w + col, -1).astype(np.int64)
    img = np.full(h * w, np.inf, dtype=np.float32)
    np.minimum.at(img, pix[ok], r[ok].astype(np.float32))
    return img.reshape(h, w), pix


def compare(
    pred: RangePrediction,
    points_world: np.ndarray,
    T_world_ladar: np.ndarray,
    config: PredictionConfig,
) -> Comparison | None:
    """The observed sweep (world points, deskewed) against the prediction, in the predicted
    sensor frame. None when no pixel has both a prediction and an observation."""
    p = transform_points(se3_inverse(pred.T_world_ladar), points_world)
    obs, pix = range_image(p, config.range_image_hw, pred.elevation_rad)
    both = np.isfinite(obs) & np.isfinite(pred.range_m)
    n = int(both.sum())
    if n == 0:
        return None
    with np.errstate(invalid="ignore"):  # inf - inf where neither has a return
        err = np.where(both, np.abs(obs - pred.range_m), 0.0)
    bad = both & (err > config.mismatch_m)
    flat_bad = bad.ravel()
    sel = (pix >= 0) & flat_bad[np.maximum(pix, 0)]
    surprise = points_world[sel]
    if len(surprise) > config.max_attention_points:
        step = len(surprise) // config.max_attention_points + 1
        surprise = surprise[::step]
    return Comparison(
        float(np.median(err[both])), float(bad.sum()) / n, n, np.asarray(surprise, np.float64)
    )


class SurpriseEvents:
    """Opens a ``world_change`` event when surprises stay over two comparisons, closes it
    when they go (reference 001, 4.4.8: an event is a state change that persists)."""

    def __init__(self, threshold: float = SURPRISE_EVENT_FRACTION) -> None:
        self.threshold = threshold
        self.run = 0
        self.first_t_ns = 0
        self.open_id: int | None = None

    def update(self, kd: kd_store.KnowledgeDatabase, cmp: Comparison, t_ns: int) -> None:
        if cmp.surprise_fraction >= self.threshold:
            self.run += 1
            if self.run == 1:
                self.first_t_ns = t_ns
            if self.run >= 2 and self.open_id is None:
                self.open_id = kd.add_event(
                    f"world_change@{self.first_t_ns}",
                    "world_change",
                    self.first_t_ns,
                    attributes={"surprise_fraction": cmp.surprise_fraction},
                    confidence=min(1.0, 0.5 + cmp.surprise_fraction),
                ).id
        else:
            self.run = 0
            if self.open_id is not None:
                kd.update_event(self.open_id, t_end_ns=t_ns)
                self.open_id = None

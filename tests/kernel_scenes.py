"""Inputs that the kernel harness (test_kernel_equivalence.py) and the modules' own tests share:
synthetic scenes and sweeps built to exercise every code path of a compiled kernel. Moved
verbatim from the per-kernel test files when their equivalence cases joined the harness."""

from __future__ import annotations

import dataclasses
import itertools

import cv2
import numpy as np

from logs.types import LadarScan

# --- sp.computation: label images with their points, intensities, ranges and ground ---------


def attribute_scene(
    seed: int, H: int, W: int, n_blobs: int, far: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Arguments of segment_attributes: labels (H, W) int64, points (H, W, 3) float64 m,
    intensity (H, W) float32, range (H, W) float32 m, time offsets (H, W) int64 ns, ground
    height (H, W) float64 m.

    ``n_blobs`` rectangles of pixels on a rough surface; with ``n_blobs > 1`` also a planar
    and a collinear segment, pixels of existing segments scattered over the image (segments
    interleaved in flat order), labels below -1 (no segment), one-pixel segments and no
    pixel of segment 2 (a segment without pixels inside 0..K-1). ``far``: the points about
    1000 m from the origin (sums of large numbers: rounding).
    """
    g = np.random.default_rng(seed)
    labels = np.full((H, W), -1, np.int64)
    for k in range(n_blobs):
        h, w = g.integers(1, max(2, H // 3)), g.integers(1, max(2, W // 12))
        i, j = g.integers(0, H - h + 1), g.integers(0, W - w + 1)
        labels[i : i + h, j : j + w] = k
    rows, cols = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    xyz = np.stack(
        [0.2 * cols, 0.1 * rows, np.sin(0.05 * cols) + 0.3 * rows / H], axis=-1
    ) + g.normal(0.0, 0.05, (H, W, 3))
    k = n_blobs
    if n_blobs > 1:
        # a planar segment (z constant: zero smallest eigenvalue) and a collinear one
        labels[H - 2 :, : W // 8] = k
        xyz[H - 2 :, : W // 8, 2] = 0.5
        labels[0, W // 2 : W // 2 + W // 8] = k + 1
        xyz[0, W // 2 : W // 2 + W // 8, 1:] = 2.0
        k += 2
        # scattered pixels of existing segments, and "no segment" written as -7
        scatter = g.random((H, W)) < 0.05
        labels[scatter] = g.integers(0, k, int(scatter.sum()))
        labels[g.random((H, W)) < 0.02] = -7
        for _ in range(5):  # one-pixel segments
            labels[g.integers(0, H), g.integers(0, W)] = k
            k += 1
        labels[labels == 2] = -1  # a gap in the labels: segment 2 without pixels
        labels[H - 1, 0] = n_blobs  # (the planar segment's pixel with a NaN range below)
    if far:
        xyz += np.array([1000.0, -1500.0, 40.0])
    intensity = g.uniform(0.0, 100.0, (H, W)).astype(np.float32)
    intensity[g.random((H, W)) < 0.1] = np.nan
    intensity.flat[g.integers(0, H * W, 3)] = np.inf
    intensity.flat[g.integers(0, H * W, 3)] = -np.inf
    rng = np.linalg.norm(xyz, axis=-1).astype(np.float32)
    if n_blobs > 1:
        # one NaN range in the planar segment: the reference's minimum is NaN
        rng[H - 1, 0] = np.nan
    t_off = g.integers(0, 100_000_000, (H, W))
    ground = xyz[..., 2] - g.uniform(0.0, 2.0, (H, W))
    ground[g.random((H, W)) < 0.3] = np.nan
    ground.flat[g.integers(0, H * W, 3)] = np.inf
    ground[labels == 0] = np.nan  # a segment without ground below it
    return labels, xyz, intensity, rng, t_off, ground


# --- sp.egosphere: LADAR scans ----------------------------------------------------------------


def scan_of(points: np.ndarray, ring: np.ndarray | None = None) -> LadarScan:
    n = len(points)
    return LadarScan(
        t_ns=1_000_000_000,
        frame_id="ladar",
        points_xyz=np.asarray(points, np.float32),
        intensity=np.linspace(0, 1, n, dtype=np.float32),
        t_offset_ns=np.arange(n, dtype=np.int64) * 1000,
        ring=ring,
    )


def random_scan(seed: int, n: int, with_ring: bool, sweep_order: bool = False) -> LadarScan:
    """n points (a little more: duplicates are appended) over and beyond the default
    elevation span, some NaN, some nearer than 0.5 m, some on bin edges, many tied in range."""
    rng = np.random.default_rng(seed)
    az = rng.uniform(-np.pi, np.pi, n)
    el = np.radians(rng.uniform(-30.0, 8.0, n))  # default span -25..3 deg: some dropped
    # some points on column and row edges of the 64 x 1024 and 48 x 100 grids
    edge = rng.random(n) < 0.1
    cols = rng.choice([1024, 100], n)
    az[edge] = np.pi - rng.integers(0, cols[edge] + 1) * (2 * np.pi / cols[edge])
    edge_el = rng.random(n) < 0.05
    el[edge_el] = np.radians(3.0 - rng.integers(0, 65, int(edge_el.sum())) * 28.0 / 64)
    r = rng.uniform(0.0, 80.0, n)
    r[rng.random(n) < 0.1] = rng.choice([10.0, 20.0])  # the same range from many directions
    xyz = np.column_stack(
        [r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)]
    ).astype(np.float32)
    xyz[rng.random(n) < 0.03, rng.integers(0, 3)] = np.nan
    # straight behind, on either side of the azimuth seam (atan2 of -0 and +0: -pi and pi)
    xyz[:4] = [[-5.0, 0.0, -1.0], [-5.0, -0.0, -1.0], [-7.0, 0.0, -1.0], [-7.0, -0.0, -1.0]]
    ring = rng.integers(0, 70, n).astype(np.uint16) if with_ring else None  # >= 64: dropped
    # exact duplicates and z-mirrored copies (the same range, the same pixel when the row is
    # the beam): ties in range, broken by the point index
    dup = rng.choice(n, n // 10)
    mirrored = xyz[dup] * np.float32([1.0, 1.0, -1.0])
    xyz = np.concatenate([xyz, xyz[dup], mirrored])
    if ring is not None:
        ring = np.concatenate([ring, ring[dup], ring[dup]])
    if sweep_order:  # column by column, as a spinning LADAR fires
        order = np.argsort(-np.arctan2(xyz[:, 1], xyz[:, 0]), kind="stable")
        xyz = xyz[order]
        ring = None if ring is None else ring[order]
    return scan_of(xyz, ring)


# --- sp.segments: ray-cast LADAR images -------------------------------------------------------

SENSOR_H = 1.8


def segment_scene(
    seed: int, H: int, W: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """A ray-cast LADAR image: ground plane, walls, cars, poles, far thin objects (boxes),
    dropped returns and rows that do not fire (a sparse beam pattern binned by elevation).

    Returns xyz (H, W, 3) float64 (0 where empty), range (H, W) float64 (NaN, inf, 0 or -1
    where empty: every form of "no return"), valid (H, W) bool, row_step, col_step (rad).
    """
    g = np.random.default_rng(seed)
    el = np.linspace(np.radians(3.0), np.radians(-25.0), H)
    el = el + g.normal(0.0, 0.1, H) * (el[0] - el[1])  # rows not evenly spaced
    col_step = 2 * np.pi / W
    az = np.pi - (np.arange(W) + 0.5) * col_step + g.normal(0.0, 0.05 * col_step, W)
    E, A = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1)
    boxes = []
    # a street: building fronts on four sides, with gaps, seen at grazing angles along it
    for axis, side in itertools.product((0, 1), (-1, 1)):
        at = side * g.uniform(6.0, 40.0)
        for lo, hi in zip(*(np.sort(g.uniform(-70, 70, (2, 3)), axis=0)), strict=True):
            c, half = np.zeros(2), np.zeros(2)
            c[axis], half[axis] = at, g.uniform(0.2, 1.0)
            c[1 - axis], half[1 - axis] = 0.5 * (lo + hi), 0.5 * (hi - lo)
            boxes.append((c - half, c + half, g.uniform(3.0, 15.0)))
            for _ in range(g.integers(0, 4)):  # people a step before the front (range steps)
                p = c.copy()
                p[axis] -= side * g.uniform(1.0, 3.0)
                p[1 - axis] = g.uniform(lo, hi)
                boxes.append((p - 0.25, p + 0.25, g.uniform(1.0, 2.0)))
    for _ in range(g.integers(8, 20)):  # cars and people, near and far
        c = g.uniform(-25, 25, 2)
        half = g.uniform(0.2, 2.5, 2)
        boxes.append((c - half, c + half, g.uniform(0.8, 2.0)))
    for _ in range(g.integers(10, 25)):  # poles and thin far objects: small far pieces
        ang, r = g.uniform(-np.pi, np.pi), g.uniform(15.0, 60.0)
        c = r * np.array([np.cos(ang), np.sin(ang)])
        half = g.uniform(0.03, 0.3, 2)
        boxes.append((c - half, c + half, g.uniform(1.0, 4.0)))
    for _ in range(g.integers(2, 6)):  # fences / bicycles: slats a little apart, far off
        ang, r = g.uniform(-np.pi, np.pi), g.uniform(16.0, 30.0)
        c, along = r * np.array([np.cos(ang), np.sin(ang)]), np.array([-np.sin(ang), np.cos(ang)])
        gap, top = g.uniform(0.3, 0.38), g.uniform(0.6, 1.2)
        for k in range(g.integers(3, 7)):
            p = c + k * gap * along
            boxes.append((p - 0.04, p + 0.04, top))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d[..., 2] < -1e-6, -SENSOR_H / d[..., 2], np.inf)  # the ground
        for lo, hi, top in boxes:
            lo3 = np.array([lo[0], lo[1], -SENSOR_H])
            hi3 = np.array([hi[0], hi[1], top - SENSOR_H])
            t0, t1 = lo3 / d, hi3 / d
            tmin = np.nanmax(np.minimum(t0, t1), axis=-1)
            tmax = np.nanmin(np.maximum(t0, t1), axis=-1)
            t = np.where((tmax >= tmin) & (tmin > 0) & (tmin < t), tmin, t)
    t = np.where(t < 80.0, t + g.normal(0.0, 0.02, t.shape), np.inf)  # range noise
    t[g.random(H) < 0.3] = np.inf  # rows that do not fire
    t[g.random((H, W)) < 0.05] = np.inf  # dropped returns
    valid = np.isfinite(t) & (t >= 1.0)
    xyz = np.where(valid[..., None], d * np.where(valid, t, 0.0)[..., None], 0.0)
    empty_as = g.choice(np.array([np.nan, np.inf, 0.0, -1.0]), size=(H, W))
    rng = np.where(valid, t, empty_as)
    return xyz, rng, valid, float(el[0] - el[1]), col_step


def non_ground(xyz: np.ndarray, valid: np.ndarray, seed: int) -> np.ndarray:
    """The pipeline's grouping mask, roughly: valid returns above the ground, a few left out
    (a pixel that is valid but not grouped breaks image contiguity: the near join's case)."""
    keep = np.random.default_rng(seed + 1000).random(valid.shape) > 0.05
    return valid & (xyz[..., 2] > -SENSOR_H + 0.15) & keep


# --- sp.ground: ray-cast sweeps in the gravity-aligned sensor frame -------------------------


def ground_rays(h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """(h, w, 3) unit rays: rows from +0.3 rad (row 0) down to -0.4 rad with a little jitter
    per row, columns in :mod:`sp.egosphere`'s azimuth order (pi down to -pi)."""
    el = np.linspace(0.3, -0.4, h) + rng.normal(0.0, 1e-3, h)
    az = np.pi - (np.arange(w) + 0.5) * 2 * np.pi / w
    E, A = np.meshgrid(el, az, indexing="ij")
    return np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1)


def plane_t(d: np.ndarray, height: float, a: float, b: float, dz: float = 0.0) -> np.ndarray:
    """Ray parameter (m) where rays ``d`` meet z = -height + dz + a x + b y (inf if never)."""
    den = d[..., 2] - a * d[..., 0] - b * d[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (-height + dz) / den
    return np.where((den < -1e-6) & (t > 0), t, np.inf)


def box_t(d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Ray parameter (m) of the first hit of rays ``d`` from the origin on the box [lo, hi]
    (its far side when the origin is inside it)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = lo / d, hi / d
    t_near = np.nanmax(np.minimum(t1, t2), axis=-1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=-1)
    t = np.where(t_near > 0, t_near, t_far)
    return np.where((t_near <= t_far) & (t > 0), t, np.inf)


def ground_sweep(
    seed: int,
    h: int = 64,
    w: int = 1024,
    fill: str = "nan",
    height: float | None = None,
    quantum_m: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """A ray-cast sweep in the gravity-aligned sensor frame: a sloped ground with a curb
    (a 0.1 m step beyond a line), boxes (cars, a wall) standing on it, range noise, raised
    returns (vegetation), random and column-block drop-outs, no return beyond 120 m.

    Returns xyz (h, w, 3) float64 m, with ``fill`` ("nan", "zero" or "junk") where invalid, and
    valid (h, w) bool. ``quantum_m`` > 0 rounds the coordinates to it, as a sensor's fixed
    resolution does: then the returns of a vertical face share exact ranges (ties).
    """
    rng = np.random.default_rng(seed)
    sensor_h = rng.uniform(1.5, 2.2) if height is None else height
    a, b = rng.uniform(-0.15, 0.15, 2)  # up to ~9 degrees of slope
    d = ground_rays(h, w, rng)
    t = plane_t(d, sensor_h, a, b)
    # the curb: beyond y = y0 the ground is 0.1 m higher
    y0 = rng.uniform(3.0, 8.0)
    t_curb = plane_t(d, sensor_h, a, b, dz=0.1)
    t = np.where(t_curb * d[..., 1] > y0, t_curb, t)
    for _ in range(rng.integers(3, 9)):
        cx, cy = rng.uniform(-40, 40, 2)
        if np.hypot(cx, cy) < 4.0:
            continue
        half = rng.uniform([0.5, 0.5], [3.0, 1.2])
        z0 = -sensor_h + a * cx + b * cy
        lo = np.array([cx - half[0], cy - half[1], z0 - 0.5])
        hi = np.array([cx + half[0], cy + half[1], z0 + rng.uniform(0.4, 3.0)])
        t = np.minimum(t, box_t(d, lo, hi))
    t = t * (1 + 0.002 * rng.standard_normal(t.shape))
    valid = np.isfinite(t) & (t < 120.0) & (t > 0.5)
    valid &= rng.random(valid.shape) >= 0.05
    for _ in range(3):  # a few blocks of columns with no return (a puddle, an occlusion)
        j = rng.integers(0, w)
        valid[:, j : j + rng.integers(1, 12)] = False
    xyz = np.where(valid[..., None], t[..., None] * d, 0.0)
    xyz[..., 2] += 0.02 * rng.standard_normal(valid.shape)
    xyz[..., 2] += np.where(rng.random(valid.shape) < 0.02, rng.uniform(0.1, 1.5, valid.shape), 0)
    if quantum_m > 0:
        xyz = np.round(xyz / quantum_m) * quantum_m
    xyz[~valid] = {"nan": np.nan, "zero": 0.0, "junk": 1e6}[fill]
    return xyz, valid


# --- sp.lists: level-2 sweeps -------------------------------------------------------------------

GROUND_OWNER = 500  # owner id of the ground in the synthetic owner images


@dataclasses.dataclass
class ListSweep:
    """A synthetic LADAR sweep as SP level 2 gets it.

    range_m:   (H, W) float32 metres, inf where empty (and NaN, 0 or -1 at some empty pixels:
               every form of "no return"), 1 to 80 m where valid;
    valid:     (H, W) bool;
    intensity: (H, W) float32 reflectance-like units, NaN where empty;
    owner:     (H, W) int64 object (0..), ground (GROUND_OWNER) or -1 (none, or an unowned
               return).
    """

    range_m: np.ndarray
    valid: np.ndarray
    intensity: np.ndarray
    owner: np.ndarray


def list_sweep(seed: int, H: int = 64, W: int = 1024) -> ListSweep:
    """A sweep of ground, boxes (walls, cars, people, poles) and foliage seen from 1.8 m."""
    g = np.random.default_rng(seed)
    el = np.linspace(np.radians(3.0), np.radians(-25.0), H)[:, None] * np.ones((1, W))
    az = (np.arange(W)[None, :] + 0.5) * (2 * np.pi / W) * np.ones((H, 1))
    with np.errstate(divide="ignore"):
        rng = np.where(el < -1e-3, SENSOR_H / np.sin(-el), np.inf)  # the flat ground
    rng = rng * (1.0 + g.normal(0.0, 0.003, (H, W)))  # range noise
    owner = np.where(np.isfinite(rng), GROUND_OWNER, -1)
    refl = np.where(np.isfinite(rng), 0.2, np.nan)
    # painted stripes on the ground (lane markings: a step in brightness, not in range)
    for _ in range(g.integers(2, 5)):
        a0 = g.uniform(0, 2 * np.pi)
        stripe = (np.abs(((az - a0) + np.pi) % (2 * np.pi) - np.pi) < g.uniform(0.01, 0.05)) & (
            owner == GROUND_OWNER
        )
        refl[stripe] = g.uniform(0.5, 0.9)
    # boxes: an azimuth span, a top elevation, a range at one end and a slope along azimuth
    # (a wall at a grazing angle); poles thin and far; people and cars near
    boxes = []
    for kind, n in (("wall", g.integers(3, 7)), ("car", g.integers(3, 9)), ("pole", 8)):
        for _ in range(n):
            a0 = g.uniform(0, 2 * np.pi)
            if kind == "wall":
                span, r0, slope, top = g.uniform(0.2, 1.2), g.uniform(8, 60), g.uniform(-8, 8), 12
            elif kind == "car":
                span, r0, slope, top = g.uniform(0.05, 0.4), g.uniform(3, 25), 0.0, 1.6
            else:
                span, r0, slope, top = g.uniform(0.003, 0.02), g.uniform(10, 75), 0.0, 4
            boxes.append((a0, span, r0, slope, top))
    for k, (a0, span, r0, slope, top) in enumerate(boxes):
        da = (az - a0) % (2 * np.pi)
        r = np.clip(r0 + slope * da, 1.0, 80.0)
        top_el = np.arctan2(top - SENSOR_H, r)
        hit = (da < span) & (el <= top_el) & (r < rng)
        rng = np.where(hit, r * (1.0 + g.normal(0.0, 0.002, (H, W))), rng)
        owner = np.where(hit, k, owner)
        refl = np.where(hit, g.uniform(0.05, 0.8), refl)
    # foliage: ranges scattered by metres (a range edge at most pixels), its own owner
    for _ in range(g.integers(1, 3)):
        a0, span = g.uniform(0, 2 * np.pi), g.uniform(0.1, 0.4)
        hit = ((az - a0) % (2 * np.pi) < span) & (el > np.radians(-12))
        r = g.uniform(4.0, 12.0, (H, W))
        rng = np.where(hit, r, rng)
        owner = np.where(hit, len(boxes), owner)
        refl = np.where(hit, g.uniform(0.1, 0.4, (H, W)), refl)
    rng = np.where(rng > 80.0, np.inf, rng)
    valid = np.isfinite(rng)
    valid &= g.random((H, W)) > 0.03  # dropped returns
    valid[g.random(H) < 0.05] = False  # rows that did not fire
    owner = np.where(valid, owner, -1)
    owner[valid & (g.random((H, W)) < 0.02)] = -1  # returns in no object
    rng = np.where(valid, rng, np.inf).astype(np.float32)
    # the other forms of "no return" on a few empty pixels
    empty = np.flatnonzero(~valid.ravel())
    for v in (np.nan, 0.0, -1.0):
        rng.ravel()[g.choice(empty, size=min(empty.size, 20), replace=False)] = v
    inten = (refl * 1000.0 / np.maximum(np.where(valid, rng, 1.0), 1.0) ** 0.5).astype(np.float32)
    inten = inten * (1.0 + g.normal(0.0, 0.05, (H, W))).astype(np.float32)
    inten[~valid] = np.nan
    return ListSweep(rng, valid, inten, owner.astype(np.int64))


def small_list_sweep(seed: int, H: int, W: int) -> ListSweep:
    """A small image with steps, NaN and empty pixels everywhere (every border case)."""
    g = np.random.default_rng(seed)
    rng = g.choice([2.0, 2.2, 5.0, 30.0, 31.0, 79.0], (H, W)) * g.uniform(0.99, 1.01, (H, W))
    valid = g.random((H, W)) < 0.8
    rng = np.where(valid, rng, g.choice([np.inf, np.nan, 0.0], (H, W)))
    inten = np.where(valid, g.uniform(0.0, 100.0, (H, W)), np.nan)
    owner = np.where(valid, g.integers(-1, 4, (H, W)), -1)
    return ListSweep(
        rng.astype(np.float32), valid, inten.astype(np.float32), owner.astype(np.int64)
    )


# --- maps.pyramid: textures -------------------------------------------------------------------


def texture(shape: tuple[int, int], seed: int, blur: float = 2.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), blur)
    return img * 100.0 + 20.0


def crops(base: np.ndarray, shift: tuple[int, int], size: tuple[int, int], pad: int = 24):
    """``ref`` and ``mov = ref`` translated by ``shift`` (rows, cols), both cut from ``base``."""
    (dr, dc), (h, w) = shift, size
    ref = base[pad : pad + h, pad : pad + w]
    mov = base[pad - dr : pad - dr + h, pad - dc : pad - dc + w]
    return ref, mov

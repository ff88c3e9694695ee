"""Inputs that the kernel harness (test_kernel_equivalence.py) and the modules' own tests share:
synthetic scenes and sweeps built to exercise every code path of a compiled kernel. Moved
verbatim from the per-kernel test files when their equivalence cases joined the harness."""

from __future__ import annotations

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
